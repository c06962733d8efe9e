"""Readers of recorded drives, one module per format, one interface (`base.Dataset`).

`open_dataset(path)` recognises the format from what the path holds, in this order:
`drive` (meta.yaml with format lidar2xodr-drive), `aimotive` (dynamic/raw-revolutions/),
`kitti_raw` (velodyne_points/data/), `rosbag` (.bag file or folder of them, rosbag2 folder with
metadata.yaml), `folder` (scan files directly inside). `format=` overrides the guess.
"""

from __future__ import annotations

import math
from pathlib import Path

from lidar2xodr.datasets.base import Dataset, ReadStats
from lidar2xodr.errors import InputError

FORMATS = ("drive", "aimotive", "kitti_raw", "rosbag", "folder")

__all__ = ["FORMATS", "Dataset", "ReadStats", "detect_format", "drives_in", "open_dataset"]


def detect_format(path: Path) -> str:
    """Name of the format `path` holds; InputError when none fits."""
    from lidar2xodr.datasets.aimotive import is_aimotive
    from lidar2xodr.datasets.drive import is_drive
    from lidar2xodr.datasets.kitti_raw import is_kitti_raw
    from lidar2xodr.datasets.pointfiles import scan_files
    from lidar2xodr.datasets.rosbag import is_rosbag

    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.is_file():
        if is_rosbag(path):
            return "rosbag"
        raise InputError(path, "a single file is not a drive (give a folder, a .bag file or a rosbag2 folder)")
    if is_drive(path):
        return "drive"
    if is_aimotive(path):
        return "aimotive"
    if is_kitti_raw(path):
        return "kitti_raw"
    if is_rosbag(path):
        return "rosbag"
    if scan_files(path):
        return "folder"
    raise InputError(path, "no scans found: expected meta.yaml, dynamic/raw-revolutions/, velodyne_points/data/, "
                     "a ROS bag, or scan files (.pcd .las .laz .ply .bin .npy)")


def drives_in(paths: list[Path]) -> list[Path]:
    """The drives the paths name: each path itself, or, for a folder that is no drive, its sub-folders
    that are (sorted by name: `build fleet/` fuses every drive recorded into fleet/).

    A path named twice is an error: the same markings fused twice would only weigh that drive double.
    """
    out: list[Path] = []
    for path in map(Path, paths):
        try:
            detect_format(path)
            found = [path]
        except InputError as exc:
            try:
                subs = sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith("."))
            except OSError:
                subs = []
            found = []
            for sub in subs:
                try:
                    detect_format(sub)
                except InputError:
                    continue
                found.append(sub)
            if not found:
                if subs:
                    raise InputError(path, f"{exc.problem}; nor is any of its folders a drive") from None
                raise
        for drive in found:
            if drive.resolve() in {d.resolve() for d in out}:
                raise InputError(drive, "this drive is given twice")
            out.append(drive)
    return out


def open_dataset(
    path: str | Path,
    format: str | None = None,
    *,
    topic: str | None = None,
    pose_topic: str | None = None,
    intensity_scale: float | None = None,
) -> Dataset:
    """Open a recorded drive. `topic`/`pose_topic` choose bag topics; `intensity_scale` overrides
    the detected raw value of 100 % reflectivity (folder and bag formats)."""
    path = Path(path)
    fmt = format or detect_format(path)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    _check_options(path, fmt, topic=topic, pose_topic=pose_topic, intensity_scale=intensity_scale)
    if fmt == "drive":
        from lidar2xodr.datasets.drive import DriveDataset

        return DriveDataset(path)
    if fmt == "aimotive":
        from lidar2xodr.datasets.aimotive import AimotiveDataset

        return AimotiveDataset(path)
    if fmt == "kitti_raw":
        from lidar2xodr.datasets.kitti_raw import KittiRawDataset

        return KittiRawDataset(path)
    if fmt == "rosbag":
        from lidar2xodr.datasets.rosbag import RosbagDataset

        return RosbagDataset(path, topic=topic, pose_topic=pose_topic, intensity_scale=intensity_scale)
    if fmt == "folder":
        from lidar2xodr.datasets.folder import FolderDataset

        if not path.is_dir():
            raise InputError(path, "the folder format needs a folder of scan files")
        return FolderDataset(path, intensity_scale=intensity_scale)
    raise InputError(path, f"unknown format {fmt!r} (known: {', '.join(FORMATS)})")


def _check_options(path: Path, fmt: str, *, topic: str | None, pose_topic: str | None,
                   intensity_scale: float | None) -> None:
    """Refuse reader options the drive's format would silently ignore, and scales that mean nothing.

    A `--topic` given for a folder of PCDs, or an `--intensity-scale` for a drive whose format
    states its own scale (meta.yaml, the aiMotive and KITTI layouts), is a user's mistake that
    would otherwise change nothing and go unnoticed.
    """
    if intensity_scale is not None and not (math.isfinite(intensity_scale) and intensity_scale > 0):
        raise InputError(path, f"--intensity-scale must be a positive number, not {intensity_scale:g}")
    unused = [name for name, value, used_by in (("--topic", topic, {"rosbag"}),
                                                ("--pose-topic", pose_topic, {"rosbag"}),
                                                ("--intensity-scale", intensity_scale, {"rosbag", "folder"}))
              if value is not None and fmt not in used_by]
    if unused:
        verb = "does" if len(unused) == 1 else "do"
        raise InputError(path, f"{' and '.join(unused)} {verb} not apply to a drive of format {fmt!r} "
                         "(topics are for bags; the intensity scale for folders and bags)")
