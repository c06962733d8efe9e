"""The aiMotive multimodal dataset layout (one sequence folder).

`dynamic/raw-revolutions/frame_NNNNNNN.laz`: one Hesai Pandar64 revolution per camera frame, points
already in the body frame (x forward, y left, z up, origin on the ground: our vehicle frame),
intensity 0..254 (uint8 scale, 255 taken as 100 %), per-point `gps_time` in nanoseconds.
Revolutions last ~100 ms but frames come every ~66.7 ms, so consecutive scans share a third of
their points (the extraction stage accumulates each return once). No poses.
`sensor/calibration/calibration.json`: the LiDAR entry (`sensor_type: lidar`) gives
`RT_body_from_sensor`, our mount (the sensor sits ~1.68 m above the road).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lidar2xodr.data import GeoOrigin, SensorInfo
from lidar2xodr.datasets.base import RawScan, ScanFileDataset
from lidar2xodr.datasets.pointfiles import _natural_key, read_las
from lidar2xodr.errors import InputError

PANDAR64_RANGE_M = 200.0


def is_aimotive(path: Path) -> bool:
    return (path / "dynamic" / "raw-revolutions").is_dir()


def _lidar_mount(calib: Path) -> tuple[np.ndarray, str]:
    try:
        entries = json.loads(calib.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(calib, "missing: the LiDAR mount is read from it") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(calib, f"cannot read: {exc}") from None
    lidars = [(k, v) for k, v in entries.items() if isinstance(v, dict) and v.get("sensor_type") == "lidar"]
    if len(lidars) != 1:
        raise InputError(calib, f"expected one entry with sensor_type 'lidar', found {len(lidars)}")
    key, entry = lidars[0]
    try:
        T = np.array(entry["RT_body_from_sensor"], dtype=np.float64)
    except (KeyError, ValueError, TypeError):
        raise InputError(calib, f"{key}: no 4x4 RT_body_from_sensor") from None
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(calib, f"{key}: RT_body_from_sensor is not a finite 4x4 matrix")
    name = str(entry.get("custom_vars", {}).get("product_name") or key)
    return T, name


class AimotiveDataset(ScanFileDataset):
    """Reader of an aiMotive sequence: LAZ revolutions in the body frame, mount from calibration."""

    points_in_vehicle_frame = True

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.path = path
        folder = path / "dynamic" / "raw-revolutions"
        self.items = sorted(folder.glob("frame_*.la[sz]"), key=_natural_key)
        if not self.items:
            raise InputError(folder, "no frame_*.laz revolutions found")
        self.names = [str(p) for p in self.items]
        mount, name = _lidar_mount(path / "sensor" / "calibration" / "calibration.json")
        self.sensor = SensorInfo(name=name, mount=mount, max_range_m=PANDAR64_RANGE_M, intensity_scale=255.0)
        self.intensity_scale = 255.0
        self.origin = GeoOrigin()

    def _read(self, k: int) -> RawScan:
        return read_las(self.items[k], time_scale=1e-9)
