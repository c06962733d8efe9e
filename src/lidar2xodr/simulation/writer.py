"""The drive directory: scans as binary PCD, poses and objects as CSV, meta.yaml, truth/, optional MCAP.

Layout (format lidar2xodr-drive, version 1), all inside one directory renamed into place:
    meta.yaml, scans/000000.pcd ..., poses.csv, objects.csv, preview.png,
    truth/map.xodr, truth/poses.csv, truth/route.json, truth/objects.csv, [drive.mcap], [preview/*.png]

Conventions (decisions): poses at 100 Hz; angles in radians with R = Rz(yaw) Ry(pitch) Rx(roll)
(ISO 8855: positive pitch = nose down); positions in the map's own x/y/z frame (offset 0);
lat/lon (deg, WGS84) and alt (m, the map's z taken as height) only when the map has a
geoReference. Objects are reported at each scan's mid time; objects.csv lists what a perception
system would: vehicles with at least 3 LiDAR returns in that scan, with noise (position 0.08 m,
height 0.05 m, yaw 0.02 rad, size 0.05 m, velocity 0.2 m/s). Fixed decimals, no wall-clock time.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pypcd4 import Encoding, PointCloud
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError, ProjError

from lidar2xodr.simulation.lidar import ScanOut

POSE_HEADER = "time,x,y,z,roll,pitch,yaw,lat,lon,alt"
OBJECT_HEADER = "time,id,class,x,y,z,yaw,length,width,height,vx,vy"
PCD_FIELDS = ("x", "y", "z", "intensity", "t")
PCD_TYPES = (np.float32, np.float32, np.float32, np.float32, np.float64)


def write_pcd(path: Path, scan: ScanOut) -> None:
    cols = [scan.xyz[:, 0], scan.xyz[:, 1], scan.xyz[:, 2], scan.intensity, scan.t]
    PointCloud.from_points(cols, PCD_FIELDS, PCD_TYPES).save(path, encoding=Encoding.BINARY)


class Geo:
    """Map x/y to lat/lon through the map's geoReference (None when absent or not understood)."""

    def __init__(self, geo_reference: str | None) -> None:
        self.proj = geo_reference
        self.note: str | None = None
        self._t: Transformer | None = None
        if not geo_reference:
            self.note = "the map has no geoReference: lat/lon unknown, poses are in the map frame"
            return
        candidates = [(geo_reference, None)]
        no_grids = re.sub(r"\+(geoidgrids|nadgrids)=\S+", "", geo_reference).strip()
        if no_grids != geo_reference:
            candidates.append((no_grids, "its datum grid files are not installed: read without them"))
        if "+proj=" not in geo_reference and "+lat_0" in geo_reference:
            # CARLA writes "+lat_0=.. +lon_0=.." without a projection: it means a transverse Mercator there
            candidates.append((f"+proj=tmerc +ellps=WGS84 +k=1 +x_0=0 +y_0=0 {geo_reference} +no_defs",
                               "geoReference has no +proj: read as +proj=tmerc (CARLA convention)"))
        problem = ""
        for text, note in candidates:
            try:
                self._t = Transformer.from_crs(CRS.from_user_input(text), CRS.from_epsg(4326), always_xy=True)
                self._t.transform(0.0, 0.0, errcheck=True)
                self.note = note
                return
            except (CRSError, ProjError) as exc:
                self._t = None
                problem = problem or str(exc)
        self.note = f"geoReference not understood by PROJ ({problem}); lat/lon left empty"

    @property
    def ok(self) -> bool:
        return self._t is not None

    def latlon(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        assert self._t is not None
        lon, lat = self._t.transform(xyz[:, 0], xyz[:, 1])
        return np.asarray(lat), np.asarray(lon), xyz[:, 2]

    def origin(self) -> dict[str, Any]:
        if not self.ok:
            return {"lat": None, "lon": None, "alt": 0.0, "proj": self.proj, "note": self.note}
        lat, lon, _ = self.latlon(np.zeros((1, 3)))
        out = {"lat": round(float(lat[0]), 9), "lon": round(float(lon[0]), 9), "alt": 0.0, "proj": self.proj}
        if self.note:
            out["note"] = self.note
        return out


def rpy(rot: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations to (N, 3) roll, pitch, yaw with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = np.arctan2(rot[:, 2, 1], rot[:, 2, 2])
    pitch = -np.arcsin(np.clip(rot[:, 2, 0], -1.0, 1.0))
    yaw = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
    return np.column_stack([roll, pitch, yaw])


def poses_csv(times: np.ndarray, xyz: np.ndarray, angles: np.ndarray, geo: Geo) -> str:
    angles = angles.copy()
    angles[:, 2] = (angles[:, 2] + math.pi) % (2 * math.pi) - math.pi
    cols = [f"{t:.6f}" for t in times], *[_fmt(xyz[:, i], 4) for i in range(3)], \
        *[_fmt(angles[:, i], 7) for i in range(3)]
    if geo.ok:
        lat, lon, alt = geo.latlon(xyz)
        geo_cols = [_fmt(lat, 9), _fmt(lon, 9), _fmt(alt, 4)]
    else:
        geo_cols = [[""] * len(times)] * 3
    rows = [",".join(r) for r in zip(*cols, *geo_cols, strict=True)]
    return POSE_HEADER + "\n" + "".join(r + "\n" for r in rows)


def object_lines(rows: list[tuple]) -> str:
    """objects.csv lines (no header) of (time, id, class, x, y, z, yaw, length, width, height, vx, vy)."""
    out = []
    for t, oid, cls, x, y, z, yaw, ln, wd, ht, vx, vy in rows:
        out.append(f"{t:.6f},{oid},{cls},{x:.3f},{y:.3f},{z:.3f},{yaw:.4f},{ln:.3f},{wd:.3f},{ht:.3f},"
                   f"{vx:.3f},{vy:.3f}\n")
    return "".join(out)


def _fmt(a: np.ndarray, d: int) -> list[str]:
    a = np.where(np.abs(a) < 0.5 * 10.0**-d, 0.0, a)  # no "-0.0000"
    return [f"{v:.{d}f}" for v in a]


def write_yaml(path: Path, data: dict[str, Any]) -> None:
    path.write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None), encoding="utf-8")


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")


def copy_map(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)


class BagWriter:
    """ROS 2 MCAP with sensor_msgs/PointCloud2 on /lidar/points (frame `lidar`), sensor_msgs/NavSatFix
    on /gnss/fix (maps with a geoReference), geometry_msgs/PoseStamped on /gnss/pose (the vehicle
    frame `base_link` in the map frame) and the sensor mount `base_link` -> `lidar` on /tf_static,
    as a ROS driver stack records it (without it a reader can only guess the mount); the raw
    intensity of 100 % goes into the bag's custom data `lidar2xodr.intensity_scale`."""

    def __init__(self, out_dir: Path, with_fix: bool,
                 mount: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
                 intensity_scale: float | None = None) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.tmp = out_dir / ".bag"
        self.target = out_dir / "drive.mcap"
        self.w = Writer(self.tmp, version=8, storage_plugin=StoragePlugin.MCAP)
        self.w.open()
        if intensity_scale is not None:  # the raw value of 100 % (Livox: 150), read back by our reader
            self.w.set_custom_data("lidar2xodr.intensity_scale", repr(float(intensity_scale)))
        self.c_pts = self.w.add_connection("/lidar/points", "sensor_msgs/msg/PointCloud2", typestore=self.ts)
        self.c_pose = self.w.add_connection("/gnss/pose", "geometry_msgs/msg/PoseStamped", typestore=self.ts)
        self.c_fix = self.w.add_connection("/gnss/fix", "sensor_msgs/msg/NavSatFix", typestore=self.ts) \
            if with_fix else None
        self.mount = mount
        self.c_tf = self.w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=self.ts) \
            if mount is not None else None

    def _tf_static(self, t: float) -> None:
        """The mount (position, roll pitch yaw in rad, R = Rz Ry Rx) as one static transform."""
        from scipy.spatial.transform import Rotation

        assert self.mount is not None and self.c_tf is not None
        T, g = self.ts.types, "geometry_msgs/msg/"
        (x, y, z), (roll, pitch, yaw) = self.mount
        q = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
        tf = T[g + "Transform"](T[g + "Vector3"](float(x), float(y), float(z)), T[g + "Quaternion"](*map(float, q)))
        msg = T["tf2_msgs/msg/TFMessage"]([T[g + "TransformStamped"](self._header(t, "base_link"), "lidar", tf)])
        self.w.write(self.c_tf, _ns(t), self.ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
        self.mount = None

    def _header(self, t: float, frame: str):
        T = self.ts.types
        sec = int(math.floor(t))
        return T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](sec, int(round((t - sec) * 1e9)) % 10**9),
                                        frame)

    def scan(self, t: float, scan: ScanOut) -> None:
        if self.mount is not None:
            self._tf_static(t)
        T = self.ts.types
        pf = T["sensor_msgs/msg/PointField"]
        n = len(scan.t)
        rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<f8")])
        rec["x"], rec["y"], rec["z"] = scan.xyz[:, 0], scan.xyz[:, 1], scan.xyz[:, 2]
        rec["intensity"], rec["t"] = scan.intensity, scan.t
        fields = [pf("x", 0, 7, 1), pf("y", 4, 7, 1), pf("z", 8, 7, 1), pf("intensity", 12, 7, 1), pf("t", 16, 8, 1)]
        msg = T["sensor_msgs/msg/PointCloud2"](self._header(t, "lidar"), 1, n, fields, False, 24, 24 * n,
                                              rec.view(np.uint8).reshape(-1), True)
        self.w.write(self.c_pts, _ns(t), self.ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))

    def pose(self, t: float, xyz: np.ndarray, quat: np.ndarray, latlonalt: tuple[float, float, float] | None,
             sigma: float) -> None:
        T = self.ts.types
        g = "geometry_msgs/msg/"
        pose = T[g + "Pose"](T[g + "Point"](*map(float, xyz)), T[g + "Quaternion"](*map(float, quat)))
        msg = T[g + "PoseStamped"](self._header(t, "map"), pose)
        self.w.write(self.c_pose, _ns(t), self.ts.serialize_cdr(msg, g + "PoseStamped"))
        if self.c_fix is not None and latlonalt is not None:
            st = T["sensor_msgs/msg/NavSatStatus"](0, 1)
            cov = np.diag([sigma**2, sigma**2, (1.5 * sigma) ** 2]).reshape(-1).astype(np.float64)
            fix = T["sensor_msgs/msg/NavSatFix"](self._header(t, "gnss"), st, *latlonalt, cov, 2)
            self.w.write(self.c_fix, _ns(t), self.ts.serialize_cdr(fix, "sensor_msgs/msg/NavSatFix"))

    def close(self) -> None:
        self.w.close()
        mcap = next(self.tmp.glob("*.mcap"))
        mcap.replace(self.target)
        shutil.rmtree(self.tmp, ignore_errors=True)


def _ns(t: float) -> int:
    return int(round(t * 1e9))


def quaternions(rot: np.ndarray) -> np.ndarray:
    """(N, 3, 3) to (N, 4) x, y, z, w."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rot).as_quat()
