"""KITTI raw drives: `velodyne_points/data/*.bin` + `oxts/data/*.txt` (+ their timestamps.txt).

Decisions:
- The vehicle frame is the OXTS/IMU frame lowered onto the road. KITTI's Velodyne sits 1.73 m
  above the road (KITTI sensor setup); `calib_imu_to_velo.txt` (in the drive folder or its
  parent, the date folder) gives the IMU-to-Velodyne transform and hence the IMU height. Without
  the file the Velodyne is assumed level, 1.73 m above the road, and the IMU 0.93 m.
- OXTS lat/lon/alt/roll/pitch/yaw become IMU poses in a transverse Mercator frame centred on the
  first packet (pyproj, see `poses.py`); yaw 0 = east, counter-clockwise, as in the devkit.
- Scan stamps come from `velodyne_points/timestamps.txt`, pose times from `oxts/timestamps.txt`
  (seconds since midnight of the recording day); without them both fall back to 10 Hz indices.
- Velodyne reflectance is already 0..1.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar2xodr.data import GeoOrigin, SensorInfo, Trajectory
from lidar2xodr.datasets.base import RawScan, ScanFileDataset, check_trajectory
from lidar2xodr.datasets.pointfiles import _natural_key, read_kitti_bin
from lidar2xodr.datasets.poses import read_kitti_timestamps, read_oxts
from lidar2xodr.errors import InputError

VELODYNE_HEIGHT_M = 1.73
IMU_HEIGHT_M = 0.93
RATE_HZ = 10.0


def is_kitti_raw(path: Path) -> bool:
    return (path / "velodyne_points" / "data").is_dir()


def _read_calib(path: Path) -> np.ndarray:
    """T_velo_imu from calib_imu_to_velo.txt ('R: 9 numbers', 'T: 3 numbers')."""
    vals: dict[str, np.ndarray] = {}
    try:
        for line in path.read_text(encoding="utf-8").splitlines():
            key, _, rest = line.partition(":")
            if key in ("R", "T"):
                vals[key] = np.array(rest.split(), dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read calibration: {exc}") from None
    if vals.get("R", np.zeros(0)).size != 9 or vals.get("T", np.zeros(0)).size != 3:
        raise InputError(path, "needs 'R:' with 9 numbers and 'T:' with 3 numbers")
    T = np.eye(4)
    T[:3, :3] = vals["R"].reshape(3, 3)
    T[:3, 3] = vals["T"]
    return T


class KittiRawDataset(ScanFileDataset):
    """Reader of one KITTI raw drive folder (synced or extract)."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.path = path
        velo = path / "velodyne_points"
        self.items = sorted((velo / "data").glob("*.bin"), key=_natural_key)
        if not self.items:
            raise InputError(velo / "data", "no .bin scans found")
        self.names = [str(p) for p in self.items]
        calib = next((c for c in (path / "calib_imu_to_velo.txt", path.parent / "calib_imu_to_velo.txt")
                      if c.is_file()), None)
        if calib is not None:
            T_imu_velo = np.linalg.inv(_read_calib(calib))
            imu_height = VELODYNE_HEIGHT_M - T_imu_velo[2, 3]
        else:
            T_imu_velo = np.eye(4)
            T_imu_velo[2, 3] = VELODYNE_HEIGHT_M - IMU_HEIGHT_M
            imu_height = IMU_HEIGHT_M
        self.T_vehicle_imu = np.eye(4)
        self.T_vehicle_imu[2, 3] = imu_height
        self.sensor = SensorInfo(
            name="Velodyne HDL-64E", mount=self.T_vehicle_imu @ T_imu_velo, max_range_m=120.0, intensity_scale=1.0
        )
        self.intensity_scale = 1.0
        self.origin = GeoOrigin()
        stamps_file = velo / "timestamps.txt"
        self.stamps = read_kitti_timestamps(stamps_file) if stamps_file.is_file() else None
        if self.stamps is not None and len(self.stamps) != len(self.items):
            raise InputError(stamps_file, f"{len(self.stamps)} times for {len(self.items)} scans")
        self._load_oxts(path / "oxts")

    def _load_oxts(self, oxts: Path) -> None:
        files = sorted((oxts / "data").glob("*.txt"), key=_natural_key)
        if not files:
            return
        imu_poses, self.origin = read_oxts(files)
        stamps_file = oxts / "timestamps.txt"
        if stamps_file.is_file():
            times = read_kitti_timestamps(stamps_file)
            if len(times) != len(files):
                raise InputError(stamps_file, f"{len(times)} times for {len(files)} OXTS packets")
        else:
            times = np.arange(len(files)) / RATE_HZ
        check_trajectory(times, stamps_file)
        self._trajectory = Trajectory(times=times, poses=imu_poses @ np.linalg.inv(self.T_vehicle_imu))

    def _read(self, k: int) -> RawScan:
        raw = read_kitti_bin(self.items[k])
        raw.stamp = float(self.stamps[k]) if self.stamps is not None else k / RATE_HZ
        return raw
