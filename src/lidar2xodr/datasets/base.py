"""The one interface every recording reader implements, plus the shared reading machinery.

A reader streams `Scan`s in the VEHICLE frame (ISO 8855, origin on the road below the reference
point) with intensity normalised to 0..1 and absolute per-point times in seconds where the format
has them. Decisions shared by every reader:

- Non-finite points (NaN/inf in x, y, z, intensity or time) are dropped and counted in
  `stats.dropped_points`; a scan left with no point is skipped and counted in `stats.empty_scans`.
  An empty scan is not a broken file: organised clouds store "no return" as NaN, and a sensor
  facing open sky over a crest or off the end of the paved world returns nothing. A scan whose
  points all carry the same time in a format with per-point times (one return) counts as empty
  too: without a stamp it cannot be placed.
- A file that cannot be read (truncated, corrupt) is skipped and listed in `stats.bad_scans`;
  the extraction stage aborts when more than `max_bad_scan_share` are bad. Skips are not
  reported one by one: a read that ends logs one warning line with the counts
  (`ReadStats.summary`), a read that the extraction aborts leaves the one error line.
- A scan without an intensity field, or scans whose stamps go backwards, are an InputError
  naming the file: both make the marking filter or the accumulation silently wrong.
- A scan's stamp is the time of its last point when per-point times exist (the end of the
  sweep, as ROS drivers stamp it), else the format's own scan time.
- Intensities above the sensor's scale are clipped to 1 (saturated returns).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from lidar2xodr.data import GeoOrigin, Scan, SensorInfo, Trajectory
from lidar2xodr.errors import InputError

log = logging.getLogger("lidar2xodr.datasets")
T = TypeVar("T")


@dataclass
class ReadStats:
    """What the reader had to drop: bad scans (name, reason) and non-finite points."""

    bad_scans: list[tuple[str, str]] = field(default_factory=list)
    empty_scans: int = 0
    dropped_points: int = 0
    scans_read: int = 0
    points_read: int = 0

    def summary(self, total: int, where: str | Path) -> str | None:
        """One line with what was skipped of `total` scans in `where`; None when nothing was."""
        skipped = len(self.bad_scans) + self.empty_scans
        if not skipped:
            return None
        parts = []
        if self.bad_scans:
            name, why = self.bad_scans[0]
            first = name[len(str(where)):].lstrip("/") if name.startswith(f"{where}/") else name
            parts.append(f"{len(self.bad_scans)} unreadable (first: {first}: {why})")
        if self.empty_scans:
            parts.append(f"{self.empty_scans} empty")
        return f"skipped {skipped} of {total} scans in {where}: {', '.join(parts)}"


@runtime_checkable
class Dataset(Protocol):
    """A recorded drive: scans in the vehicle frame, optional poses, sensor and geo metadata."""

    path: Path
    sensor: SensorInfo
    origin: GeoOrigin
    stats: ReadStats

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[Scan]: ...

    def poses(self) -> Trajectory | None: ...


@dataclass
class RawScan:
    """One scan as a format delivers it: sensor-frame points, raw intensity, times in seconds."""

    xyz: np.ndarray
    intensity: np.ndarray | None
    times: np.ndarray | None = None
    stamp: float | None = None
    untimed: bool = False  # the format has per-point times, but this scan's all share one value


class CorruptScan(Exception):
    """Raised by a format's reader for a file that cannot be decoded; the scan is skipped."""


def detect_intensity_scale(values: np.ndarray) -> float:
    """The raw value that means 100 %: from the data type, else from the largest value.

    Integer types use their full range (uint8 -> 255, uint16 -> 65535). Floats are matched to
    the usual conventions by their maximum: <= 1 (normalised), <= 100 (percent, Livox/Hesai
    calibrated reflectivity), <= 255 (8-bit drivers that publish floats), else 65535.
    """
    if values.dtype == np.uint8 or values.dtype == np.int8:
        return 255.0
    if values.dtype in (np.uint16, np.int16, np.uint32, np.int32):
        top = float(values.max()) if values.size else 0.0
        return 255.0 if top <= 255 else 65535.0
    finite = values[np.isfinite(values)]
    top = float(finite.max()) if finite.size else 1.0
    for scale in (1.0, 100.0, 255.0):
        if top <= scale:
            return scale
    return 65535.0


def time_unit(span: float) -> float:
    """Factor that turns a per-point time span into seconds, guessed from the sweep duration.

    A sweep lasts 10 ms to 1 s; spans of 1e1..1e3, 1e4..1e6 or beyond are taken as ms, us, ns.
    """
    for factor in (1.0, 1e-3, 1e-6, 1e-9):
        if span * factor <= 2.0:
            return factor
    return 1e-9


def transform(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return xyz @ T[:3, :3].T + T[:3, 3]


def mount_from_xyzrpy(x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> np.ndarray:
    """T_vehicle_sensor from a position and intrinsic z-y'-x'' (yaw, pitch, roll) angles in radians."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


class ScanFileDataset:
    """Base of the readers: iterates over `items`, reads each with `_read`, cleans and normalises.

    Subclasses set `path`, `sensor`, `origin`, `items` (one per scan), `names` (for messages) and
    implement `_read(k) -> RawScan`. `points_in_vehicle_frame` skips the mount transform for
    formats that store points already in the vehicle frame. When `estimate_mount` is set the
    mount is unknown: it is estimated from the first readable scan's ground plane.
    """

    path: Path
    sensor: SensorInfo
    origin: GeoOrigin
    items: Sequence[Any]
    names: Sequence[str]
    points_in_vehicle_frame: bool = False
    estimate_mount: bool = False
    intensity_scale: float | None = None

    def __init__(self) -> None:
        self.stats = ReadStats()
        self._trajectory: Trajectory | None = None

    def __len__(self) -> int:
        return len(self.items)

    def poses(self) -> Trajectory | None:
        return self._trajectory

    def _read(self, k: int) -> RawScan:  # pragma: no cover - abstract
        """Read scan `k` (an index into `items`)."""
        raise NotImplementedError

    def _name(self, k: int) -> str:
        return self.names[k]

    def _read_checked(self, k: int) -> RawScan | None:
        try:
            raw = self._read(k)
        except CorruptScan as exc:
            self._bad(self._name(k), str(exc))
            return None
        if raw.intensity is None:
            raise InputError(
                self._name(k), "scan has no intensity field; lane markings are found by their reflectivity"
            )
        return raw

    def _raw_scans(self) -> Iterator[tuple[int, RawScan | None]]:
        """(index, raw scan or None when unreadable) in recording order."""
        for k in range(len(self.items)):
            yield k, self._read_checked(k)

    def _bad(self, name: str, reason: str) -> None:
        self.stats.bad_scans.append((name, reason))
        log.debug("skipping scan %s: %s", name, reason)

    def _report_skips(self) -> None:
        line = self.stats.summary(len(self), self.path)
        if line is not None:
            log.warning("%s", line)

    def __iter__(self) -> Iterator[Scan]:
        self.stats = ReadStats()
        last_stamp = -np.inf
        for k, raw in self._raw_scans():
            if raw is None:
                continue
            scan = self._clean(k, raw)
            if scan is None:
                continue
            last_stamp = self._accept(k, scan.stamp, last_stamp)
            yield scan
        self._report_skips()

    def _accept(self, k: int, stamp: float, last_stamp: float) -> float:
        if stamp < last_stamp:
            raise InputError(
                self._name(k),
                f"scan time {stamp:.6f} s is before the previous scan's {last_stamp:.6f} s "
                "(timestamps must increase)",
            )
        self.stats.scans_read += 1
        return stamp

    @property
    def random_access(self) -> bool:
        """Whether `read_scan(k)` may read scan k alone (formats not read as one stream)."""
        return type(self)._raw_scans is ScanFileDataset._raw_scans

    def read_scan(self, k: int) -> tuple[Scan | None, ReadStats]:
        """Scan k read and cleaned alone, its counts in a ReadStats of its own; None when unreadable.

        For readers in worker processes: after the first scan (which fixes the intensity scale and
        an estimated mount) reading is pure, and `iter_scans` merges the counts in recording order.
        """
        saved, self.stats = self.stats, ReadStats()
        try:
            raw = self._read_checked(k)
            return (None if raw is None else self._clean(k, raw)), self.stats
        finally:
            self.stats = saved

    def iter_scans(self, results: Iterable[tuple[int, float | None, ReadStats, T]]) -> Iterator[T]:
        """The payloads of per-scan results (index, stamp or None when unreadable, counts, payload).

        Results come in recording order, e.g. from `read_scan` in worker processes; counted and
        checked (timestamps increase) as `__iter__` does, and `stats` reset first like there.
        """
        self.stats = ReadStats()
        last_stamp = -np.inf
        for k, stamp, part, payload in results:
            self.stats.bad_scans += part.bad_scans
            self.stats.empty_scans += part.empty_scans
            self.stats.dropped_points += part.dropped_points
            self.stats.points_read += part.points_read
            if stamp is None:
                continue
            last_stamp = self._accept(k, stamp, last_stamp)
            yield payload
        self._report_skips()

    def _clean(self, k: int, raw: RawScan) -> Scan | None:
        name = self._name(k)
        xyz = np.asarray(raw.xyz, dtype=np.float64).reshape(-1, 3)
        inten = np.asarray(raw.intensity)
        if self.intensity_scale is None:
            self.intensity_scale = detect_intensity_scale(inten) if inten.size else 1.0
            self.sensor.intensity_scale = self.intensity_scale
        inten = inten.astype(np.float64).reshape(-1)
        times = None if raw.times is None else np.asarray(raw.times, dtype=np.float64).reshape(-1)
        if len(inten) != len(xyz) or (times is not None and len(times) != len(xyz)):
            self._bad(name, "point fields have different lengths")
            return None
        ok = np.isfinite(xyz).all(axis=1) & np.isfinite(inten)
        if times is not None:
            ok &= np.isfinite(times)
        self.stats.points_read += len(xyz)
        self.stats.dropped_points += int(len(ok) - ok.sum())
        if not ok.all():
            xyz, inten = xyz[ok], inten[ok]
            times = None if times is None else times[ok]
        if len(xyz) == 0 or (raw.untimed and raw.stamp is None):
            self.stats.empty_scans += 1
            log.debug("skipping scan %s: %s", name, "no finite point" if len(xyz) == 0 else
                     "its points share one time (a scan of one return cannot be placed in time)")
            return None
        if self.estimate_mount:
            self._estimate_mount(xyz)
        if not self.points_in_vehicle_frame:
            xyz = transform(self.sensor.mount, xyz)
        intensity = np.clip(inten / self.intensity_scale, 0.0, 1.0).astype(np.float32)
        if times is not None:
            stamp = float(times.max())
        elif raw.stamp is not None:
            stamp = float(raw.stamp)
        else:
            stamp = float(k)
        return Scan(index=k, stamp=stamp, xyz=xyz, intensity=intensity, times=times)

    def _estimate_mount(self, xyz: np.ndarray) -> None:
        from lidar2xodr.extraction import estimate_mount

        self.sensor.mount = estimate_mount(xyz, self.sensor.max_range_m)
        self.estimate_mount = False
        log.info("mount estimated from the ground: sensor %.2f m above the road", self.sensor.mount[2, 3])


def check_trajectory(times: np.ndarray, where: str | Path) -> None:
    """Poses must be finite and strictly increasing in time."""
    if len(times) < 2:
        raise InputError(where, f"needs at least 2 poses, found {len(times)}")
    if not np.isfinite(times).all():
        raise InputError(where, "pose times are not all finite")
    bad = np.nonzero(np.diff(times) <= 0)[0]
    if bad.size:
        raise InputError(where, f"pose times are not increasing (row {bad[0] + 2}: {times[bad[0] + 1]!r})")
