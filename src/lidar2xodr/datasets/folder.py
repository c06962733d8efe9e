"""A plain folder of scan files (PCD / LAS / LAZ / PLY / KITTI .bin / .npy), optionally with poses.

Decisions:
- Scans are sorted by natural name order; the most common supported type in the folder is read.
- Points are in the SENSOR frame and the mount is unknown: it is estimated from the first
  scan's ground plane (sensor height above the road, roll and pitch; yaw and lever arm zero).
- Scan times: per-point times when the files have them; else `times.txt` / `timestamps.txt` (one
  per scan, seconds or KITTI date-time lines) in the folder or its parent; else the scan index.
  When such a file exists and the per-point times look like offsets (|median| < 1 s) they are
  added to it.
- Poses (the first found): `poses.csv` / `*.csv` (time + x y z or lat lon alt + roll pitch yaw,
  see `poses.py`), or KITTI `poses.txt` (one 3x4 per scan, times from the scans). They are poses
  of the SENSOR in the world frame (what a LiDAR SLAM or a KITTI file gives); the reader turns
  them into vehicle poses with the (estimated) mount. When a KITTI `calib.txt` with `Tr:` sits
  next to poses.txt, the camera-frame poses are converted to the LiDAR frame.
- Intensity scale: detected from the first scan's data type and range (`base.detect_intensity_scale`)
  unless given.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar2xodr.data import GeoOrigin, SensorInfo, Trajectory
from lidar2xodr.datasets.base import RawScan, ScanFileDataset
from lidar2xodr.datasets.pointfiles import read_scan_file, scan_files
from lidar2xodr.datasets.poses import read_kitti_poses, read_kitti_timestamps, read_pose_csv
from lidar2xodr.errors import InputError

_TIME_FILES = ("times.txt", "timestamps.txt")


def _kitti_tr(calib: Path) -> np.ndarray | None:
    if not calib.is_file():
        return None
    try:
        for line in calib.read_text(encoding="utf-8").splitlines():
            if line.startswith("Tr:"):
                T = np.eye(4)
                T[:3, :] = np.array(line.split()[1:13], dtype=np.float64).reshape(3, 4)
                return T
    except (OSError, ValueError) as exc:
        raise InputError(calib, f"cannot read Tr: {exc}") from None
    return None


class FolderDataset(ScanFileDataset):
    """Reader of a folder of scan files with optional poses and time files."""

    estimate_mount = True

    def __init__(self, path: Path, intensity_scale: float | None = None, max_range_m: float = 200.0) -> None:
        super().__init__()
        self.path = path
        self.items = scan_files(path)
        if not self.items:
            raise InputError(path, "no scan files found (looked for .pcd .las .laz .ply .bin .npy)")
        self.names = [str(p) for p in self.items]
        self.sensor = SensorInfo(name="unknown", max_range_m=max_range_m)
        self.origin = GeoOrigin()
        if intensity_scale is not None:
            self.intensity_scale = self.sensor.intensity_scale = float(intensity_scale)
        self.stamps = self._stamps()
        self._sensor_poses: Trajectory | None = None
        self._kitti_poses: np.ndarray | None = None
        self._find_poses()

    def _stamps(self) -> np.ndarray | None:
        for folder in (self.path, self.path.parent):
            for name in _TIME_FILES:
                f = folder / name
                if f.is_file():
                    stamps = read_kitti_timestamps(f)
                    if len(stamps) != len(self.items):
                        raise InputError(f, f"{len(stamps)} times for {len(self.items)} scans")
                    return stamps
        return None

    def _find_poses(self) -> None:
        kitti = self.path / "poses.txt"
        csvs = sorted(self.path.glob("*.csv"))
        if (self.path / "poses.csv").is_file():
            csvs = [self.path / "poses.csv"]
        if csvs:
            if len(csvs) > 1:
                raise InputError(self.path, f"several CSV files, which are the poses? {[c.name for c in csvs]} "
                                 "(name it poses.csv)")
            self._sensor_poses, self.origin = read_pose_csv(csvs[0])
        elif kitti.is_file():
            T = read_kitti_poses(kitti, len(self.items))
            tr = _kitti_tr(self.path / "calib.txt")
            if tr is not None:
                T = np.linalg.inv(tr) @ T @ tr
            self._kitti_poses = T

    def poses(self) -> Trajectory | None:
        """Vehicle poses; available once the mount is known (after the first scan was read)."""
        if self._sensor_poses is None and self._kitti_poses is None:
            return None
        if self.estimate_mount:
            self._estimate_from_first()
        inv_mount = np.linalg.inv(self.sensor.mount)
        if self._sensor_poses is not None:
            return Trajectory(times=self._sensor_poses.times, poses=self._sensor_poses.poses @ inv_mount)
        assert self._kitti_poses is not None
        times = self.stamps if self.stamps is not None else self._first_pass_stamps()
        return Trajectory(times=times, poses=self._kitti_poses @ inv_mount)

    def _estimate_from_first(self) -> None:
        for k in range(len(self.items)):
            raw = self._read_checked(k)
            if raw is not None and raw.xyz.size:
                xyz = raw.xyz[np.isfinite(raw.xyz).all(axis=1)]
                if len(xyz):
                    self._estimate_mount(xyz)
                    return
        raise InputError(self.path, "no readable scan to estimate the sensor mount from")

    def _first_pass_stamps(self) -> np.ndarray:
        """Per-scan stamps for index-aligned KITTI poses when there is no time file."""
        stamps = np.arange(len(self.items), dtype=np.float64)
        if self.items[0].suffix.lower() == ".bin":
            return stamps
        for k, item in enumerate(self.items):
            raw = read_scan_file(item)
            stamps[k] = float(np.nanmax(raw.times)) if raw.times is not None else float(k)
        return stamps

    def _read(self, k: int) -> RawScan:
        raw = read_scan_file(self.items[k])
        if self.stamps is not None:
            raw.stamp = float(self.stamps[k])
            if raw.times is not None and abs(float(np.nanmedian(raw.times))) < 1.0:
                raw.times = raw.times + raw.stamp
        elif raw.times is None:
            raw.stamp = float(k)
        return raw
