"""Pose files: CSV (local or geodetic), KITTI poses.txt, KITTI OXTS; geodetic to a local frame.

Conventions (documented for users):
- Angles are radians; rotation R = Rz(yaw) Ry(pitch) Rx(roll) (intrinsic z-y'-x''), yaw counted
  counter-clockwise from the x axis of the local frame (east for geodetic poses, as in KITTI OXTS).
- Geodetic poses are projected with pyproj into a transverse Mercator frame centred on the first
  pose (WGS84, k=1); heights are relative to the first pose's altitude. The frame is written as
  the PROJ string of the drive's GeoOrigin. Grid convergence inside a drive (< 0.1 deg for 10 km)
  is ignored, as the OpenDRIVE geoReference does.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lidar2xodr.data import GeoOrigin, Trajectory
from lidar2xodr.datasets.base import check_trajectory
from lidar2xodr.errors import InputError

_ALIASES = {
    "time": ("time", "t", "timestamp", "stamp", "time_s", "sec"),
    "x": ("x", "tx", "pos_x"),
    "y": ("y", "ty", "pos_y"),
    "z": ("z", "tz", "pos_z"),
    "lat": ("lat", "latitude"),
    "lon": ("lon", "lng", "long", "longitude"),
    "alt": ("alt", "altitude", "height", "h"),
    "roll": ("roll",),
    "pitch": ("pitch",),
    "yaw": ("yaw", "heading"),
}


def poses_from_xyzrpy(xyz: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    """(M, 4, 4) poses from positions and (roll, pitch, yaw) rows."""
    T = np.tile(np.eye(4), (len(xyz), 1, 1))
    T[:, :3, :3] = Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix()
    T[:, :3, 3] = xyz
    return T


def local_tmerc(lat0: float, lon0: float) -> str:
    return f"+proj=tmerc +lat_0={lat0:.9f} +lon_0={lon0:.9f} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"


def check_geodetic(lat: np.ndarray, lon: np.ndarray, alt: np.ndarray, where: str | Path) -> None:
    """Latitudes within +-90 deg, longitudes within +-180 deg, all finite (InputError naming `where`)."""
    for name, v, top in (("latitude", lat, 90.0), ("longitude", lon, 180.0), ("altitude", alt, np.inf)):
        v = np.asarray(v, dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(v) | (np.abs(v) > top))
        if bad.size:
            limit = "finite" if top == np.inf else f"within +-{top:g} deg"
            raise InputError(where, f"{name} {float(v[bad[0]])!r} (value {bad[0] + 1}) is not {limit}")


def geodetic_to_local(lat: np.ndarray, lon: np.ndarray, alt: np.ndarray,
                      where: str | Path = "poses") -> tuple[np.ndarray, GeoOrigin]:
    """Project WGS84 positions into a tmerc frame centred on the first one (checked, see `check_geodetic`)."""
    from pyproj import Transformer

    check_geodetic(lat, lon, alt, where)

    proj = local_tmerc(float(lat[0]), float(lon[0]))
    tf = Transformer.from_crs("EPSG:4326", proj, always_xy=True)
    e, n = tf.transform(lon, lat)
    xyz = np.column_stack([e, n, alt - alt[0]])
    return xyz, GeoOrigin(lat=float(lat[0]), lon=float(lon[0]), alt=float(alt[0]), proj=proj)


def _column(header: list[str], key: str) -> int | None:
    low = [h.strip().lower() for h in header]
    for name in _ALIASES[key]:
        if name in low:
            return low.index(name)
    return None


POSE_CSV_REQUIRED = "time, yaw and x y z (local) or lat lon alt (geodetic)"
POSE_CSV_OPTIONAL = {"roll": 0.0, "pitch": 0.0}


def read_pose_csv(path: Path) -> tuple[Trajectory, GeoOrigin]:
    """CSV with a header: time + x y z (local) or time + lat lon alt, + yaw [+ roll pitch].

    Local x y z win when both are present (the drive format writes both); an empty lat/lon column
    is allowed then and gives the origin. Required: time, yaw and a full position (a missing
    heading or height would silently bend or flatten the drive); roll and pitch are optional and
    taken as zero (a level vehicle) when their columns are absent.
    """
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read poses: {exc}") from None
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if len(rows) < 3:
        raise InputError(path, "pose CSV needs a header and at least 2 rows")
    header, body = rows[0], rows[1:]
    cols = {k: _column(header, k) for k in _ALIASES}
    local = all(cols[k] is not None for k in ("x", "y", "z"))
    geo = cols["lat"] is not None and cols["lon"] is not None
    position = ("x", "y", "z") if local or not geo else ("lat", "lon", "alt")
    missing = [k for k in ("time", *position, "yaw") if cols[k] is None]
    if missing:
        raise InputError(path, f"missing column(s) {', '.join(missing)} (required: {POSE_CSV_REQUIRED}; "
                         f"found: {', '.join(h.strip() for h in header)})")

    def values(key: str, required: bool = True) -> np.ndarray:
        idx = cols[key]
        if idx is None:
            return np.full(len(body), POSE_CSV_OPTIONAL[key])
        out = np.empty(len(body))
        for i, row in enumerate(body):
            cell = row[idx].strip() if idx < len(row) else ""
            if cell == "" and not required:
                out[i] = np.nan
                continue
            try:
                out[i] = float(cell)
            except ValueError:
                raise InputError(path, f"row {i + 2}, column {header[idx]!r}: not a number: {cell!r}") from None
        return out

    times = values("time")
    check_trajectory(times, path)
    rpy = np.column_stack([values("roll"), values("pitch"), values("yaw")])
    origin = GeoOrigin()
    if local:
        xyz = np.column_stack([values("x"), values("y"), values("z")])
        if geo:
            lat, lon = values("lat", False), values("lon", False)
            alt = values("alt", False) if cols["alt"] is not None else np.zeros(len(body))
            if np.isfinite(lat[0]) and np.isfinite(lon[0]):
                origin = GeoOrigin(lat=float(lat[0]), lon=float(lon[0]), alt=float(np.nan_to_num(alt[0])))
                check_geodetic(lat[:1], lon[:1], np.nan_to_num(alt[:1]), path)
    else:
        xyz, origin = geodetic_to_local(values("lat"), values("lon"), values("alt"), path)
    if not (np.isfinite(xyz).all() and np.isfinite(rpy).all()):
        raise InputError(path, "poses contain non-finite values")
    return Trajectory(times=times, poses=poses_from_xyzrpy(xyz, rpy)), origin


def read_kitti_poses(path: Path, n_expected: int | None = None) -> np.ndarray:
    """KITTI poses.txt: one 3x4 row-major matrix (12 numbers) per line -> (M, 4, 4)."""
    try:
        data = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read KITTI poses: {exc}") from None
    if data.shape[1] != 12:
        raise InputError(path, f"KITTI poses need 12 numbers per line, found {data.shape[1]}")
    if not np.isfinite(data).all():
        raise InputError(path, "poses contain non-finite values")
    if n_expected is not None and len(data) != n_expected:
        raise InputError(path, f"{len(data)} poses for {n_expected} scans (KITTI poses are one per scan)")
    T = np.tile(np.eye(4), (len(data), 1, 1))
    T[:, :3, :] = data.reshape(-1, 3, 4)
    return T


def read_kitti_timestamps(path: Path) -> np.ndarray:
    """KITTI raw timestamps.txt ('2011-09-26 13:02:25.964389445') or times.txt (seconds) -> seconds."""
    try:
        lines = [ln.strip() for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    except OSError as exc:
        raise InputError(path, f"cannot read timestamps: {exc}") from None
    try:
        if lines and " " in lines[0]:
            stamps = np.array([np.datetime64(ln.replace(" ", "T"), "ns") for ln in lines])
            return (stamps - stamps[0]).astype(np.int64) * 1e-9 + _day_seconds(stamps[0])
        return np.array([float(ln) for ln in lines])
    except ValueError as exc:
        raise InputError(path, f"bad timestamp: {exc}") from None


def _day_seconds(stamp: np.datetime64) -> float:
    """Seconds since midnight: keeps the numbers small while staying comparable across files."""
    day = stamp.astype("datetime64[D]")
    return float((stamp - day).astype(np.int64) * 1e-9)


def read_oxts(files: list[Path]) -> tuple[np.ndarray, GeoOrigin]:
    """KITTI OXTS packets (lat lon alt roll pitch yaw ... per file) -> IMU poses in a local frame."""
    rows = []
    for f in files:
        try:
            vals = np.array(f.read_text(encoding="utf-8").split()[:6], dtype=np.float64)
        except (OSError, ValueError) as exc:
            raise InputError(f, f"cannot read OXTS packet: {exc}") from None
        if vals.size < 6 or not np.isfinite(vals).all():
            raise InputError(f, "OXTS packet needs finite lat lon alt roll pitch yaw")
        rows.append(vals)
    data = np.array(rows)
    xyz, origin = geodetic_to_local(data[:, 0], data[:, 1], data[:, 2], files[0].parent)
    return poses_from_xyzrpy(xyz, data[:, 3:6]), origin
