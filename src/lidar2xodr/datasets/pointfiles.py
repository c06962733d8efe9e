"""Readers of single scan files: PCD, LAS/LAZ, PLY, KITTI .bin, .npy.

Field names are matched case-insensitively: intensity from `intensity`, `i`, `reflectivity`,
`reflectance`, `remission`; per-point time from `t`, `time`, `timestamp`, `offset_time`,
`gps_time`. Per-point time units are guessed from the sweep duration (`base.time_unit`).
A file that cannot be decoded raises `CorruptScan` (the scan is skipped and counted).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar2xodr.datasets.base import CorruptScan, RawScan, time_unit
from lidar2xodr.errors import InputError

SCAN_SUFFIXES = (".pcd", ".las", ".laz", ".ply", ".bin", ".npy")
INTENSITY_NAMES = ("intensity", "i", "reflectivity", "reflectance", "remission")
TIME_NAMES = ("t", "time", "timestamp", "timestamps", "offset_time", "gps_time")


def _find(names: tuple[str, ...] | list[str], wanted: tuple[str, ...]) -> str | None:
    low = {n.lower(): n for n in names}
    for w in wanted:
        if w in low:
            return low[w]
    return None


def seconds(raw: np.ndarray | None) -> np.ndarray | None:
    """Per-point times in seconds; None when absent or constant (no usable per-point timing)."""
    if raw is None or raw.size == 0:
        return None
    t = raw.astype(np.float64)
    finite = t[np.isfinite(t)]
    if finite.size == 0:
        return t
    span = float(finite.max() - finite.min())
    if span <= 0.0:
        return None
    return t * time_unit(span)


def from_structured(arr: np.ndarray, name: str | Path) -> RawScan:
    """A RawScan from a structured array with x, y, z and optional intensity/time fields."""
    names = list(arr.dtype.names or ())
    arr = arr.reshape(-1)  # pypcd4 gives an empty cloud the shape (0, n_fields)
    xs = [_find(names, (c,)) for c in ("x", "y", "z")]
    if any(c is None for c in xs):
        raise InputError(name, f"scan has no x, y, z fields (fields: {names})")
    xyz = np.column_stack([np.asarray(arr[c], dtype=np.float64) for c in xs])  # type: ignore[index]
    inten_name = _find(names, INTENSITY_NAMES)
    time_name = _find(names, TIME_NAMES)
    times = seconds(None if time_name is None else np.asarray(arr[time_name]))
    return RawScan(
        xyz=xyz,
        intensity=None if inten_name is None else np.asarray(arr[inten_name]),
        times=times,
        untimed=time_name is not None and times is None and len(xyz) > 0,
    )


def read_pcd(path: Path) -> RawScan:
    from pypcd4 import PointCloud

    try:
        pc = PointCloud.from_path(path)
        arr = pc.pc_data
    except Exception as exc:  # pypcd4 raises many kinds on a broken file
        raise CorruptScan(f"cannot decode PCD: {exc}") from None
    return from_structured(arr, path)


def read_las(path: Path, time_scale: float | None = None) -> RawScan:
    """LAS/LAZ via laspy; `gps_time` is the per-point time (unit guessed unless `time_scale`).

    LAZ is decompressed by single-threaded lazrs: its parallel backend starts a thread pool that a
    forked extraction worker inherits dead (it hangs), and the workers are the parallelism.
    """
    import laspy

    try:
        las = laspy.read(path, laz_backend=laspy.LazBackend.Lazrs)
        xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
        names = list(las.point_format.dimension_names)
        inten = np.asarray(las.intensity) if "intensity" in names else None
        raw_t = np.asarray(las.gps_time) if "gps_time" in names else None
    except Exception as exc:  # laspy/lazrs raise several kinds on a broken file
        raise CorruptScan(f"cannot decode LAS/LAZ: {exc}") from None
    if raw_t is not None and time_scale is not None:
        times = raw_t.astype(np.float64) * time_scale
    else:
        times = seconds(raw_t)
    return RawScan(xyz=xyz, intensity=inten, times=times)


def read_ply_scan(path: Path) -> RawScan:
    from lidar2xodr.markings_io import read_ply

    try:
        arr = read_ply(path)
    except InputError as exc:
        raise CorruptScan(exc.problem) from None
    return from_structured(arr, path)


def read_kitti_bin(path: Path) -> RawScan:
    """KITTI Velodyne .bin: float32 x y z reflectance (0..1), no per-point time."""
    try:
        raw = np.fromfile(path, dtype="<f4")
    except OSError as exc:
        raise CorruptScan(f"cannot read: {exc}") from None
    if raw.size % 4:
        raise CorruptScan(f"size {raw.size * 4} bytes is not a multiple of 16 (x y z r float32)")
    pts = raw.reshape(-1, 4)
    return RawScan(xyz=pts[:, :3].astype(np.float64), intensity=pts[:, 3])


def read_npy(path: Path) -> RawScan:
    """.npy: a structured array with named fields, or (N, >=4) columns x y z intensity [time]."""
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise CorruptScan(f"cannot decode .npy: {exc}") from None
    if arr.dtype.names:
        return from_structured(arr, path)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InputError(path, f".npy scan must be (N, 4+) x y z intensity [time], found shape {arr.shape}")
    if arr.shape[1] < 4:
        return RawScan(xyz=arr[:, :3], intensity=None)
    return RawScan(xyz=arr[:, :3], intensity=arr[:, 3], times=seconds(arr[:, 4]) if arr.shape[1] > 4 else None)


def read_scan_file(path: Path) -> RawScan:
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        return read_pcd(path)
    if suffix in (".las", ".laz"):
        return read_las(path)
    if suffix == ".ply":
        return read_ply_scan(path)
    if suffix == ".bin":
        return read_kitti_bin(path)
    if suffix == ".npy":
        return read_npy(path)
    raise InputError(path, f"unknown scan file type {suffix!r} (known: {', '.join(SCAN_SUFFIXES)})")


def scan_files(folder: Path) -> list[Path]:
    """Scan files of the most common supported type in `folder`, in natural (numeric) name order."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES]
    if not files:
        return []
    suffixes = [p.suffix.lower().replace(".laz", ".las") for p in files]
    main = max(sorted(set(suffixes)), key=suffixes.count)
    return sorted((p for p, s in zip(files, suffixes, strict=True) if s == main), key=_natural_key)


def _natural_key(p: Path) -> tuple:
    import re

    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name))
