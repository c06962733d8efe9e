"""Object tracks of the recorded traffic: readers, association, cleaning and smoothing.

`load_tracks(path, ego)` reads what a perception system reports and returns clean, smoothed tracks
in the world (map) frame. It recognises, in this order:

1. a drive directory with `objects.csv` (header `time,id,class,x,y,z,yaw,length,width,height,vx,vy`,
   world frame, box centre, yaw in rad) and `poses.csv` (`time,x,y,z,roll,pitch,yaw,...`, the ego
   pose, angles in rad), used as the ego trajectory when none is given;
2. `detections.csv` / `detections.json` in a directory, or any other .csv / .json file: the generic
   format below;
3. the aiMotive layout `dynamic/box/3d_body/frame_*.json` (or that folder itself): per-frame boxes in
   the ego body frame (x forward, y left, origin on the ground), stamped by their `Timestamp` in ns
   (the same clock as the LAZ files' GPS time);
4. an OSC-Generator style `trajectories_file.csv` (the A9 drive): ego GNSS `lat,long` (deg),
   `heading` (deg, clockwise from north), `speed` (km/h) and objects `pos_x_i, pos_y_i` in the ego
   frame (x forward, y left), `class_i`.

Generic format: a CSV with a header, or JSON (a list of rows, `{"frame": f, "detections": [rows]}` or
`{"frame": f, "frames": [{"time": t, "objects": [rows]}]}`). Columns/keys (case-insensitive, aliases
in `_ALIASES`): `time` (s), `x`, `y` required; `id`, `class`, `z`, `yaw` (rad), `length`, `width`,
`height`, `vx`, `vy`, `frame` (`world` default, or `vehicle`) optional. Rows without an id are
associated into tracks frame by frame (Hungarian assignment, scipy `linear_sum_assignment`, on
constant-velocity predictions with a gate). Vehicle-frame rows need the ego trajectory.

Decisions (see ScenarioConfig for the numbers):
- Cleaning per track: samples are sorted by time (out-of-order samples counted), duplicates dropped;
  spikes (farther than `spike_m` from the robust prediction of their 4 neighbours) removed; the track is split
  where no sample arrives for `max_gap_s` or the implied speed exceeds `max_speed_mps`; pieces with
  fewer than `min_track_samples` samples or shorter than `min_track_duration_s` are dropped, and a
  track with more than `max_spike_share` spikes is dropped as jumpy.
- Smoothing: a cubic smoothing spline per axis with the penalty chosen by generalised
  cross-validation (scipy `make_smoothing_spline`); velocity is its derivative. A track counts as
  `smoothed` when the spline moved a sample by more than 5 cm.
- Heading: the motion direction where the object moves faster than `heading_min_speed_mps` (robust
  to the 180 deg flips of box detectors), the box yaw otherwise, held from the nearest known value.
- Category: majority vote of the per-sample class through `ScenarioConfig.class_map` and `_CLASSES`;
  an unknown class becomes `truck` for boxes longer than 7 m and `car` otherwise, with a warning.
  Size: per-axis median of the positive box sizes; zero or missing sizes get the category default.
- A9: the `heading` column disagrees with the GNSS course by several degrees on the sample drive, so
  the ego path is the speed/heading dead reckoning rotated and shifted onto the GNSS fixes (2D
  Procrustes), plus the low-passed GNSS residual (`gnss_smoothing_s`); the ego yaw is the heading
  column plus that rotation. Numeric classes (7, 9) have no published meaning: they are unknown.
"""

from __future__ import annotations

import csv
import json
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation, Slerp

from lidar2xodr.config import Config, ScenarioConfig
from lidar2xodr.data import GeoOrigin, Trajectory
from lidar2xodr.errors import InputError

CATEGORY_DIMS: dict[str, tuple[float, float, float]] = {
    "car": (4.6, 1.9, 1.5),
    "van": (5.3, 2.0, 2.3),
    "truck": (12.0, 2.55, 3.8),
    "semitrailer": (16.5, 2.55, 4.0),
    "trailer": (8.0, 2.55, 3.5),
    "bus": (12.0, 2.55, 3.2),
    "motorbike": (2.2, 0.8, 1.5),
    "bicycle": (1.8, 0.6, 1.7),
    "tram": (30.0, 2.65, 3.4),
    "train": (60.0, 3.0, 4.2),
    "pedestrian": (0.5, 0.6, 1.8),
}
"""Default box (length, width, height) per OpenSCENARIO category, used for zero or missing sizes."""

_CLASSES: dict[str, str] = {
    **{k: "car" for k in ("car", "passenger_car", "sedan", "suv", "pickup", "vehicle", "medium_car",
                          "small_car", "compact_car", "luxury_car")},
    **{k: "van" for k in ("van", "delivery_van", "minivan")},
    **{k: "truck" for k in ("truck", "lorry", "hgv", "heavy_truck", "construction_vehicle")},
    **{k: "semitrailer" for k in ("semitrailer", "semi_trailer", "articulated_truck", "tractor_trailer")},
    "trailer": "trailer",
    **{k: "bus" for k in ("bus", "coach")},
    **{k: "motorbike" for k in ("motorbike", "motorcycle", "moto", "scooter", "motorcyclist")},
    **{k: "bicycle" for k in ("bicycle", "bike", "cyclist")},
    "tram": "tram",
    "train": "train",
    **{k: "pedestrian" for k in ("pedestrian", "person", "walker", "ped")},
}

_ALIASES: dict[str, tuple[str, ...]] = {
    "time": ("time", "t", "timestamp", "time_s", "stamp"),
    "id": ("id", "track_id", "object_id", "obj_id", "objectid"),
    "class": ("class", "type", "category", "label", "object_type", "objecttype"),
    "x": ("x",),
    "y": ("y",),
    "z": ("z",),
    "yaw": ("yaw", "heading", "theta", "rz"),
    "length": ("length", "l"),
    "width": ("width", "w"),
    "height": ("height", "h"),
    "vx": ("vx",),
    "vy": ("vy",),
    "frame": ("frame",),
}
_VEHICLE_FRAMES = {"vehicle", "ego", "body", "vehicle_frame", "sensor"}
_WORLD_FRAMES = {"world", "map", "global", ""}
_SMOOTHED_M = 0.05


@dataclass
class Track:
    """One participant: samples in the world frame, smoothed; `dims` = (length, width, height)."""

    id: str
    category: str
    dims: np.ndarray
    times: np.ndarray
    xyz: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    raw_class: str = ""

    def __len__(self) -> int:
        return len(self.times)


@dataclass
class TrackSet:
    """The clean tracks of one recording, with what was dropped or changed on the way.

    `ego` is set when the input carries its own ego trajectory (poses.csv, A9 GNSS); `origin` when
    the reader chose the world frame itself (A9: transverse Mercator at the first fix, or the map's
    geoReference when one was passed).
    """

    tracks: list[Track]
    source: str
    dropped: int = 0
    smoothed: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    ego: Trajectory | None = None
    origin: GeoOrigin | None = None


@dataclass
class _Detections:
    """Raw per-sample rows of one reader."""

    source: str
    time: np.ndarray
    ids: np.ndarray  # object array of str, "" = no id
    cls: np.ndarray  # object array of str
    xyz: np.ndarray
    yaw: np.ndarray
    dims: np.ndarray
    vel: np.ndarray
    vehicle: np.ndarray  # bool: row is in the vehicle frame


# --------------------------------------------------------------------------------------------
# entry point


def load_tracks(
    path_or_drive: Path,
    ego: Trajectory | None,
    *,
    cfg: Config | ScenarioConfig | None = None,
    geo_reference: str | None = None,
    workers: int | None = None,
) -> TrackSet:
    """Read, associate, clean and smooth the object tracks of a recording (see the module doc).

    `ego` (T_world_vehicle) places vehicle-frame detections; `geo_reference` (a PROJ string, e.g. the
    map's) is the frame GNSS-only inputs are projected into. The tracks are smoothed on `workers`
    processes (default: the extraction's `workers` with a full `Config`, else one); the result is the
    same on any number.
    """
    scfg = cfg.scenario if isinstance(cfg, Config) else (cfg or ScenarioConfig())
    path = Path(path_or_drive)
    if not path.exists():
        raise InputError(path, "not found")
    kind, file = _detect(path)
    warnings: list[str] = []
    origin: GeoOrigin | None = None
    own_ego: Trajectory | None = None
    if kind == "a9":
        det, own_ego, origin = _read_a9(file, scfg, geo_reference, warnings)
    elif kind == "aimotive":
        det = _read_aimotive(file)
    elif file.suffix.lower() == ".json":
        det = _read_generic_json(file)
    else:
        det = _read_generic_csv(file)
    if kind == "objects" and (file.parent / "poses.csv").is_file():
        own_ego = read_poses_csv(file.parent / "poses.csv")
    ego = ego if ego is not None else own_ego
    counts: Counter[str] = Counter(detections=len(det.time))
    det = _to_world(det, ego, counts)
    if workers is None:
        workers = 1
        if isinstance(cfg, Config):
            from lidar2xodr.extraction import worker_count

            workers = worker_count(cfg.extraction)
    tracks = _build_tracks(det, ego, scfg, counts, warnings, workers)
    dropped = counts["dropped_short"] + counts["dropped_jumpy"]
    _warn_counts(det.source, counts, warnings)
    return TrackSet(tracks=tracks, source=det.source, dropped=dropped, smoothed=counts["smoothed"],
                    counts=dict(sorted(counts.items())), warnings=warnings, ego=own_ego, origin=origin)


def _detect(path: Path) -> tuple[str, Path]:
    if path.is_file():
        if path.suffix.lower() == ".csv" and _is_a9(path):
            return "a9", path
        if path.name == "objects.csv":
            return "objects", path
        if path.suffix.lower() not in (".csv", ".json"):
            raise InputError(path, "unknown track format: expected .csv or .json")
        return "generic", path
    for name, kind in (("objects.csv", "objects"), ("detections.csv", "generic"), ("detections.json", "generic")):
        if (path / name).is_file():
            return kind, path / name
    for folder in (path / "dynamic" / "box" / "3d_body", path / "box" / "3d_body", path):
        if folder.is_dir() and any(folder.glob("frame_*.json")):
            return "aimotive", folder
    if (path / "trajectories_file.csv").is_file():
        return "a9", path / "trajectories_file.csv"
    raise InputError(path, "no object tracks found: expected objects.csv, detections.csv/.json, "
                     "dynamic/box/3d_body/frame_*.json or trajectories_file.csv")


def _is_a9(path: Path) -> bool:
    try:
        with path.open(encoding="utf-8", newline="") as fh:
            header = {h.strip().lower() for h in next(csv.reader(fh), [])}
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read: {exc}") from None
    return {"lat", "long", "heading", "speed", "pos_x_1"} <= header


# --------------------------------------------------------------------------------------------
# readers


def _float(values: list[Any], path: Path | str, column: str, required: bool, first_row: int = 2) -> np.ndarray:
    """Strings/numbers to float64; empty = NaN unless required. InputError names the row."""
    out = np.full(len(values), np.nan)
    for i, v in enumerate(values):
        if v is None or (isinstance(v, str) and not v.strip()):
            if required:
                raise InputError(path, f"row {i + first_row}: column {column} is empty")
            continue
        try:
            out[i] = float(v)
        except (TypeError, ValueError):
            raise InputError(path, f"row {i + first_row}: column {column}: {v!r} is not a number") from None
        if required and not math.isfinite(out[i]):
            raise InputError(path, f"row {i + first_row}: column {column} is not finite")
    return out


def _class_str(v: Any) -> str:
    """Class labels as lower-case text; numeric labels without a trailing '.0'."""
    if v is None:
        return ""
    s = str(v).strip().lower()
    try:
        f = float(s)
        if math.isfinite(f) and f == int(f):
            return str(int(f))
    except ValueError:
        pass
    return s


def _rows_to_detections(rows: list[dict[str, Any]], path: Path, default_frame: str, first_row: int) -> _Detections:
    if not rows:
        raise InputError(path, "no detections")
    keys = {k.strip().lower(): k for k in rows[0] if k is not None}  # None: values beyond the header
    col: dict[str, str] = {}
    for canon, aliases in _ALIASES.items():
        for a in aliases:
            if a in keys:
                col[canon] = keys[a]
                break
    missing = [c for c in ("time", "x", "y") if c not in col]
    if missing:
        raise InputError(path, f"missing column(s) {', '.join(missing)}; found {', '.join(keys) or 'none'}")

    def get(canon: str) -> list[Any]:
        k = col.get(canon)
        return [r.get(k) if k else None for r in rows]

    def num(canon: str, required: bool = False) -> np.ndarray:
        return _float(get(canon), path, canon, required, first_row)

    frames = [(_class_str(f) if f is not None else default_frame) for f in get("frame")]
    bad = sorted({f for f in frames if f not in _VEHICLE_FRAMES | _WORLD_FRAMES})
    if bad:
        raise InputError(path, f"unknown frame {bad[0]!r}: expected world or vehicle")
    n = len(rows)
    z = num("z")
    return _Detections(
        source=str(path),
        time=num("time", True),
        ids=np.array([("" if v is None else str(v).strip()) for v in get("id")], dtype=object),
        cls=np.array([_class_str(v) for v in get("class")], dtype=object),
        xyz=np.stack([num("x", True), num("y", True), np.where(np.isfinite(z), z, np.nan)], axis=1),
        yaw=num("yaw"),
        dims=np.stack([num("length"), num("width"), num("height")], axis=1),
        vel=np.stack([num("vx"), num("vy")], axis=1) if n else np.empty((0, 2)),
        vehicle=np.array([f in _VEHICLE_FRAMES for f in frames], dtype=bool),
    )


def _read_generic_csv(path: Path, default_frame: str = "world") -> _Detections:
    try:
        with path.open(encoding="utf-8", newline="") as fh:
            reader = csv.DictReader(line for line in fh if not line.lstrip().startswith("#"))
            rows = [dict(r) for r in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"cannot read CSV: {exc}") from None
    return _rows_to_detections(rows, path, default_frame, first_row=2)


def _read_generic_json(path: Path) -> _Detections:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read JSON: {exc}") from None
    frame = "world"
    if isinstance(data, dict):
        frame = _class_str(data.get("frame", "world"))
        if isinstance(data.get("detections"), list):
            rows = data["detections"]
        elif isinstance(data.get("frames"), list):
            rows = []
            for i, fr in enumerate(data["frames"]):
                if not isinstance(fr, dict) or "time" not in fr or not isinstance(fr.get("objects", []), list):
                    raise InputError(path, f"frames[{i}]: expected {{'time': t, 'objects': [...]}}")
                rows += [{**o, "time": fr["time"]} for o in fr.get("objects", []) if isinstance(o, dict)]
        else:
            raise InputError(path, "expected a list of detections or a 'detections' or 'frames' list")
    elif isinstance(data, list):
        rows = data
    else:
        raise InputError(path, "expected a JSON list or object")
    if not all(isinstance(r, dict) for r in rows):
        raise InputError(path, "every detection must be a JSON object")
    return _rows_to_detections(rows, path, frame, first_row=0)


def _read_aimotive(folder: Path) -> _Detections:
    files = sorted(folder.glob("frame_*.json"))
    rows: list[dict[str, Any]] = []
    for f in files:
        try:
            d = json.loads(f.read_text(encoding="utf-8"))
            stamp = float(d["Timestamp"]) * 1e-9
            for i, o in enumerate(d["CapturedObjects"]):
                try:
                    qw, qx, qy, qz = (float(o[f"BoundingBox3D Orientation Quat {k}"]) for k in "WXYZ")
                    rows.append({
                        "time": stamp, "id": str(o["ObjectId"]), "class": o.get("ObjectType", ""),
                        "x": o["BoundingBox3D Origin X"], "y": o["BoundingBox3D Origin Y"],
                        "z": o["BoundingBox3D Origin Z"],
                        "yaw": math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)),
                        "length": o["BoundingBox3D Extent X"], "width": o["BoundingBox3D Extent Y"],
                        "height": o["BoundingBox3D Extent Z"],
                    })
                except KeyError as exc:
                    raise InputError(f, f"CapturedObjects[{i}]: missing field {exc}") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f, f"cannot read box file: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f, f"not an aiMotive box file (Timestamp/CapturedObjects): {exc}") from None
    if not rows:
        raise InputError(folder, "the box files hold no objects")
    det = _rows_to_detections(rows, folder, "vehicle", first_row=0)
    det.vehicle[:] = True
    return det


def read_poses_csv(path: Path) -> Trajectory:
    """Ego poses T_world_vehicle from CSV: the drive's `poses.csv` (time,x,y,z,roll,pitch,yaw,...; rad,
    ISO 8855 Z-Y-X order) or the extraction's `*.trajectory.csv` (time,x,y,z,qx,qy,qz,qw)."""
    try:
        with path.open(encoding="utf-8", newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"cannot read poses: {exc}") from None
    if not rows:
        raise InputError(path, "no poses")
    quat = all(c in rows[0] for c in ("qx", "qy", "qz", "qw"))
    need = ("time", "x", "y", "z", *(("qx", "qy", "qz", "qw") if quat else ("roll", "pitch", "yaw")))
    missing = [c for c in need if c not in rows[0]]
    if missing:
        raise InputError(path, f"missing column(s) {', '.join(missing)}")
    v = {c: _float([r[c] for r in rows], path, c, True) for c in need}
    order = np.argsort(v["time"], kind="stable")
    keep = order[np.r_[True, np.diff(v["time"][order]) > 0]]
    if quat:
        q = np.stack([v["qx"], v["qy"], v["qz"], v["qw"]], 1)[keep]
        if np.any(np.linalg.norm(q, axis=1) < 1e-9):
            raise InputError(path, "a quaternion has zero length")
        rot = Rotation.from_quat(q)
    else:
        rot = Rotation.from_euler("ZYX", np.stack([v["yaw"], v["pitch"], v["roll"]], 1)[keep])
    poses = np.tile(np.eye(4), (len(keep), 1, 1))
    poses[:, :3, :3] = rot.as_matrix()
    poses[:, :3, 3] = np.stack([v["x"], v["y"], v["z"]], 1)[keep]
    return Trajectory(times=v["time"][keep], poses=poses)


def _read_a9(
    path: Path, cfg: ScenarioConfig, geo_reference: str | None, warnings: list[str]
) -> tuple[_Detections, Trajectory, GeoOrigin]:
    from pyproj import Transformer
    from pyproj.exceptions import CRSError, ProjError

    try:
        with path.open(encoding="utf-8", newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"cannot read CSV: {exc}") from None
    if len(rows) < 2:
        raise InputError(path, "fewer than two rows")

    def col(name: str, required: bool = True) -> np.ndarray:
        return _float([r.get(name) for r in rows], path, name, required)

    t, lat, lon = col("timestamp"), col("lat"), col("long")
    heading, speed = col("heading"), col("speed") / 3.6
    if np.any(np.diff(t) <= 0):
        raise InputError(path, "timestamps are not strictly increasing")
    proj = geo_reference or (f"+proj=tmerc +lat_0={lat[0]:.9f} +lon_0={lon[0]:.9f} +k=1 +x_0=0 +y_0=0 "
                             "+ellps=WGS84 +units=m +no_defs")
    try:
        gx, gy = Transformer.from_crs("EPSG:4326", proj, always_xy=True).transform(lon, lat)
    except (CRSError, ProjError) as exc:
        raise InputError("geoReference", f"cannot project into {proj!r}: {exc}") from None
    gnss = np.stack([gx, gy], axis=1)
    yaw_col = np.unwrap(np.pi / 2 - np.radians(heading))
    step = speed[:, None] * np.stack([np.cos(yaw_col), np.sin(yaw_col)], axis=1)
    dr = np.vstack([[0.0, 0.0], np.cumsum(0.5 * (step[1:] + step[:-1]) * np.diff(t)[:, None], axis=0)])
    a, b = dr - dr.mean(0), gnss - gnss.mean(0)
    cross, dot = np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)
    theta = math.atan2(cross, dot) if np.sum(a * a) > 1.0 else 0.0
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    fitted = dr @ rot.T
    fitted += gnss.mean(0) - fitted.mean(0)
    sigma = cfg.gnss_smoothing_s / float(np.median(np.diff(t)))
    resid = gnss - fitted
    xy = fitted + gaussian_filter1d(resid, sigma, axis=0, mode="nearest")
    yaw = yaw_col + theta
    rms = float(np.sqrt(np.mean(np.sum((gnss - xy) ** 2, axis=1))))
    if abs(theta) > math.radians(1.0):
        warnings.append(f"{path.name}: the heading column differs from the GNSS course by "
                        f"{math.degrees(theta):.1f} deg; the ego yaw follows the course")
    warnings.append(f"{path.name}: ego path = dead reckoning fitted to GNSS, RMS {rms:.2f} m")
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    poses[:, :2, 3] = xy
    ego = Trajectory(times=t, poses=poses)

    out: list[dict[str, Any]] = []
    i = 1
    while f"pos_x_{i}" in rows[0]:
        px, py = col(f"pos_x_{i}", False), col(f"pos_y_{i}", False)
        cls = [r.get(f"class_{i}", "") for r in rows]
        ok = np.isfinite(px) & np.isfinite(py)
        c, s_ = np.cos(yaw[ok]), np.sin(yaw[ok])
        wx = xy[ok, 0] + c * px[ok] - s_ * py[ok]
        wy = xy[ok, 1] + s_ * px[ok] + c * py[ok]
        for k, j in enumerate(np.flatnonzero(ok)):
            out.append({"time": t[j], "id": str(i), "class": cls[j], "x": wx[k], "y": wy[k]})
        i += 1
    if not out:
        raise InputError(path, "no objects (pos_x_i/pos_y_i) in any row")
    origin = GeoOrigin(lat=float(lat[0]), lon=float(lon[0]), proj=proj)
    det = _rows_to_detections(out, path, "world", first_row=0)
    det.source = str(path)
    return det, ego, origin


# --------------------------------------------------------------------------------------------
# frames and association


def interpolate_poses(traj: Trajectory, t: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """Positions and rotations of T_world_vehicle at times t (inside the trajectory's time span)."""
    times, idx = np.unique(traj.times, return_index=True)
    pos = traj.poses[idx, :3, 3]
    if len(times) == 1:
        return np.repeat(pos, len(t), axis=0), Rotation.from_matrix(np.repeat(traj.poses[idx, :3, :3], len(t), 0))
    p = np.stack([np.interp(t, times, pos[:, k]) for k in range(3)], axis=1)
    rot = Slerp(times, Rotation.from_matrix(traj.poses[idx, :3, :3]))(np.clip(t, times[0], times[-1]))
    return p, rot


def _ego_velocity(traj: Trajectory | None, t: np.ndarray) -> np.ndarray:
    if traj is None or len(traj) < 2:
        return np.zeros((len(t), 2))
    times, idx = np.unique(traj.times, return_index=True)
    if len(times) < 2:
        return np.zeros((len(t), 2))
    v = np.gradient(traj.poses[idx, :2, 3], times, axis=0)
    return np.stack([np.interp(t, times, v[:, k]) for k in range(2)], axis=1)


def _to_world(det: _Detections, ego: Trajectory | None, counts: Counter[str]) -> _Detections:
    """Vehicle-frame rows into the world frame with the ego pose at their time."""
    if not det.vehicle.any():
        return det
    if ego is None or len(ego) == 0:
        raise InputError(det.source, "detections are in the vehicle frame but no ego trajectory is known "
                         "(give poses.csv in the drive or --ego)")
    inside = ~det.vehicle | ((det.time >= ego.times.min() - 1e-6) & (det.time <= ego.times.max() + 1e-6))
    counts["outside_ego_time"] += int((~inside).sum())
    if not (inside & det.vehicle).any():
        raise InputError(det.source, f"no vehicle-frame detection lies in the ego trajectory's time span "
                         f"[{ego.times.min():.3f}, {ego.times.max():.3f}] s (detections: "
                         f"[{det.time.min():.3f}, {det.time.max():.3f}] s): do they share a clock?")
    keep = np.flatnonzero(inside)
    det = _Detections(det.source, det.time[keep], det.ids[keep], det.cls[keep], det.xyz[keep].copy(),
                      det.yaw[keep].copy(), det.dims[keep], det.vel[keep].copy(), det.vehicle[keep])
    m = det.vehicle
    if m.any():
        p, rot = interpolate_poses(ego, det.time[m])
        half_h = np.where(np.isfinite(det.dims[m, 2]), det.dims[m, 2] / 2, 0.0)
        local = det.xyz[m].copy()
        local[:, 2] = np.where(np.isfinite(local[:, 2]), local[:, 2], half_h)
        det.xyz[m] = p + rot.apply(local)
        mat = rot.as_matrix()
        ego_yaw = np.arctan2(mat[:, 1, 0], mat[:, 0, 0])
        det.yaw[m] = ego_yaw + det.yaw[m]
        det.vel[m] = np.nan
    return det


def associate(
    times: np.ndarray, xy: np.ndarray, gate_m: float, max_gap_s: float, init_vel: np.ndarray | None = None
) -> np.ndarray:
    """Track labels for detections without ids (Hungarian assignment on constant-velocity predictions).

    A detection joins the track whose prediction is nearest within `gate_m` (2 x gate for tracks seen
    once, whose velocity is only the initial guess `init_vel`: the detection's own or the ego's);
    tracks unseen for more than `max_gap_s` end; unassigned detections start new tracks.
    """
    n = len(times)
    labels = np.full(n, -1, dtype=np.int64)
    order = np.argsort(times, kind="stable")
    frame_t, starts = np.unique(times[order], return_index=True)
    bounds = np.r_[starts, n]
    init = np.zeros((n, 2)) if init_vel is None else np.where(np.isfinite(init_vel), init_vel, 0.0)
    last_t: list[float] = []
    pos: list[np.ndarray] = []
    vel: list[np.ndarray] = []
    seen: list[int] = []
    for f, t in enumerate(frame_t):
        rows = order[bounds[f]:bounds[f + 1]]
        active = [k for k in range(len(last_t)) if t - last_t[k] <= max_gap_s]
        assigned = np.zeros(len(rows), dtype=bool)
        if active:
            a = np.array(active)
            pred = np.array([pos[k] + vel[k] * (t - last_t[k]) for k in active])
            cost = cdist(pred, xy[rows])
            gate = np.where(np.array([seen[k] for k in active]) == 1, 2 * gate_m, gate_m)
            out = cost > gate[:, None]
            r, c = linear_sum_assignment(np.where(out, 1e9, cost))
            for ri, ci in zip(r, c, strict=True):
                if out[ri, ci]:
                    continue
                k = int(a[ri])
                dt = t - last_t[k]
                if dt > 0:
                    vel[k] = (xy[rows[ci]] - pos[k]) / dt
                pos[k], last_t[k] = xy[rows[ci]], float(t)
                seen[k] += 1
                labels[rows[ci]] = k
                assigned[ci] = True
        for ci in np.flatnonzero(~assigned):
            labels[rows[ci]] = len(last_t)
            last_t.append(float(t))
            pos.append(xy[rows[ci]])
            vel.append(init[rows[ci]])
            seen.append(1)
    return labels


# --------------------------------------------------------------------------------------------
# cleaning, smoothing, category


def _group_rows(det: _Detections, ego: Trajectory | None, cfg: ScenarioConfig, counts: Counter[str]) -> list[
        tuple[str, np.ndarray]]:
    """(track id, row indices in file order) per object; rows without id are associated first."""
    has_id = det.ids != ""
    groups: list[tuple[str, np.ndarray]] = []
    if has_id.any():
        ids = det.ids[has_id].astype(str)
        rows = np.flatnonzero(has_id)
        for uid in sorted(set(ids.tolist()), key=_natural_key):
            groups.append((uid, rows[ids == uid]))
    if (~has_id).any():
        rows = np.flatnonzero(~has_id)
        init = np.where(np.isfinite(det.vel[rows]), det.vel[rows], _ego_velocity(ego, det.time[rows]))
        labels = associate(det.time[rows], det.xyz[rows, :2], cfg.gate_m, cfg.max_gap_s, init)
        counts["associated_detections"] += len(rows)
        for lab in range(labels.max() + 1):
            groups.append((f"a{lab}", rows[labels == lab]))
    return groups


def _natural_key(s: str) -> tuple[int, float, str]:
    try:
        return 0, float(s), s
    except ValueError:
        return 1, 0.0, s


def spike_residual(t: np.ndarray, xy: np.ndarray, half: int = 2) -> np.ndarray:
    """Distance of each sample from the robust constant-velocity prediction of its neighbours.

    For sample i: v = median of the 2*half finite-difference velocities around i; the prediction is
    the median over the neighbours j (|i - j| <= half, j != i) of p_j + v (t_i - t_j). A lone spike
    moves neither median, so only the spike itself gets a large residual (a plain running median of
    positions would also flag its neighbours once the spike is as large as the motion per sample).
    """
    n = len(t)
    idx = np.arange(n)
    v = np.diff(xy, axis=0) / np.diff(t)[:, None]
    k = np.clip(idx[:, None] + np.arange(-half, half)[None, :], 0, n - 2)
    v_med = np.median(v[k], axis=1)
    offs = np.r_[np.arange(-half, 0), np.arange(1, half + 1)]
    j = np.clip(idx[:, None] + offs[None, :], 0, n - 1)
    pred = xy[j] + v_med[:, None, :] * (t[:, None] - t[j])[..., None]
    return np.linalg.norm(xy - np.median(pred, axis=1), axis=1)


def _split_clean(t: np.ndarray, xyz: np.ndarray, cfg: ScenarioConfig, counts: Counter[str]) -> list[np.ndarray]:
    """Index arrays of the usable pieces of one time-sorted, duplicate-free track."""
    n = len(t)
    keep = np.ones(n, dtype=bool) if n < 5 else spike_residual(t, xyz[:, :2]) <= cfg.spike_m
    spikes = int((~keep).sum())
    counts["spikes_removed"] += spikes
    if n and spikes > cfg.max_spike_share * n:
        counts["dropped_jumpy"] += 1
        return []
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return []
    dt = np.diff(t[idx])
    jump = np.linalg.norm(np.diff(xyz[idx, :2], axis=0), axis=1)
    cut = (dt > cfg.max_gap_s) | (jump > cfg.max_speed_mps * np.maximum(dt, 1e-9))
    counts["splits"] += int(cut.sum())
    pieces = np.split(idx, np.flatnonzero(cut) + 1)
    good = [p for p in pieces
            if len(p) >= cfg.min_track_samples and t[p[-1]] - t[p[0]] >= cfg.min_track_duration_s]
    counts["dropped_short"] += len(pieces) - len(good)
    return good


def smooth_track(t: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GCV smoothing spline per axis: smoothed positions and their velocity (NaN z stays NaN)."""
    from scipy.interpolate import make_smoothing_spline

    tt = t - t[0]
    out, vel = xyz.copy(), np.zeros_like(xyz)
    for k in range(3):
        v = xyz[:, k]
        if not np.all(np.isfinite(v)):
            continue
        try:
            spl = make_smoothing_spline(tt, v)
            s, d = spl(tt), spl.derivative()(tt)
        except (ValueError, np.linalg.LinAlgError):
            s, d = v, np.gradient(v, tt)
        if np.all(np.isfinite(s)) and np.all(np.isfinite(d)):
            out[:, k], vel[:, k] = s, d
        else:
            vel[:, k] = np.gradient(v, tt)
    return out, vel


def _heading(vel: np.ndarray, yaw_meas: np.ndarray, min_speed: float) -> np.ndarray:
    speed = np.hypot(vel[:, 0], vel[:, 1])
    yaw = np.where(speed >= min_speed, np.arctan2(vel[:, 1], vel[:, 0]), yaw_meas)
    ok = np.isfinite(yaw)
    if not ok.any():
        return np.zeros(len(yaw))
    u = np.unwrap(yaw[ok])
    idx = np.arange(len(yaw))
    nearest = np.flatnonzero(ok)[np.clip(np.searchsorted(np.flatnonzero(ok), idx), 0, ok.sum() - 1)]
    full = np.empty(len(yaw))
    full[ok] = u
    full[~ok] = full[nearest[~ok]]
    return np.unwrap(full)


def categorise(raw: list[str], length: float, class_map: dict[str, str]) -> tuple[str, bool]:
    """(OpenSCENARIO category, known?) from the per-sample raw classes by majority vote."""
    user = {_class_str(k): v.strip().lower() for k, v in class_map.items()}
    cats = [user.get(c) or _CLASSES.get(c) for c in raw]
    votes = Counter(c for c in cats if c in CATEGORY_DIMS)
    if votes:
        return sorted(votes.items(), key=lambda kv: (-kv[1], kv[0]))[0][0], True
    return ("truck" if math.isfinite(length) and length > 7.0 else "car"), False


def _smooth_task(_job: Any, t: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return smooth_track(t, xyz)


_PARALLEL_TRACKS = 4  # fewer tracks are smoothed here: a pool would cost more than it saves


def _smooth_all(items: list[tuple[np.ndarray, np.ndarray]], workers: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """`smooth_track` of every (times, xyz), in order; on `workers` processes when there are enough
    tracks (the GCV search of scipy's smoothing spline is most of a build's lanes stage on a busy
    motorway: 4.7 of 14.5 s for 32 tracks on a 3 km drive). Each track is smoothed alone, so the
    result is the same bytes on any number of workers."""
    if workers <= 1 or len(items) < _PARALLEL_TRACKS:
        return [smooth_track(t, xyz) for t, xyz in items]
    from lidar2xodr.scheduler import task_runner

    with task_runner(None, min(workers, len(items)), None) as submit:
        futures = [submit(_smooth_task, t, xyz) for t, xyz in items]
        return [f.result() for f in futures]


def _build_tracks(det: _Detections, ego: Trajectory | None, cfg: ScenarioConfig, counts: Counter[str],
                  warnings: list[str], workers: int = 1) -> list[Track]:
    pending: list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray, list[str]]] = []
    unknown: Counter[str] = Counter()
    for gid, rows in _group_rows(det, ego, cfg, counts):
        t_file = det.time[rows]
        counts["out_of_order"] += int(np.sum(np.diff(t_file) < 0))
        rows = rows[np.argsort(t_file, kind="stable")]
        t = det.time[rows]
        first = np.r_[True, np.diff(t) > 0]
        counts["duplicates"] += int((~first).sum())
        rows, t = rows[first], t[first]
        pieces = _split_clean(t, det.xyz[rows], cfg, counts)
        for k, piece in enumerate(pieces):
            r = rows[piece]
            tid = gid if len(pieces) == 1 else f"{gid}.{k + 1}"
            dims = det.dims[r]
            valid = np.all(np.isfinite(dims) & (dims > 0), axis=1)
            length = float(np.median(dims[valid, 0])) if valid.any() else math.nan
            raw = det.cls[r].tolist()
            category, known = categorise(raw, length, cfg.class_map)
            if not known:
                for c in set(raw):
                    unknown[c or "(none)"] += raw.count(c)
            if valid.any():
                box = np.median(dims[valid], axis=0)
            else:
                box = np.array(CATEGORY_DIMS[category])
                counts["zero_size_tracks"] += 1
            xyz = det.xyz[r]
            if np.isfinite(xyz[:, 2]).any():
                xyz[:, 2] = np.where(np.isfinite(xyz[:, 2]), xyz[:, 2], np.nanmedian(xyz[:, 2])) - box[2] / 2
            pending.append((tid, category, box, r, xyz, raw))
    smoothed = _smooth_all([(det.time[r], xyz) for _, _, _, r, xyz, _ in pending], workers)
    tracks: list[Track] = []
    for (tid, category, box, r, xyz, raw), (smooth, vel) in zip(pending, smoothed, strict=True):
        moved = np.linalg.norm(np.nan_to_num(smooth - xyz), axis=1)
        if moved.max() > _SMOOTHED_M:
            counts["smoothed"] += 1
        tracks.append(Track(
            id=tid, category=category, dims=box, times=det.time[r].copy(), xyz=smooth,
            yaw=_heading(vel, det.yaw[r], cfg.heading_min_speed_mps),
            speed=np.hypot(vel[:, 0], vel[:, 1]), raw_class=Counter(raw).most_common(1)[0][0],
        ))
    counts["tracks"] = len(tracks)
    for c, n in sorted(unknown.items()):
        counts["unknown_class_samples"] += n
        warnings.append(f"unknown class {c!r} ({n} samples): category chosen from the box length")
    return tracks


def _warn_counts(source: str, counts: Counter[str], warnings: list[str]) -> None:
    name = Path(source).name
    msgs = {
        "out_of_order": "samples were out of time order (sorted)",
        "duplicates": "samples repeated a time stamp (dropped)",
        "spikes_removed": "spike samples removed",
        "splits": "tracks split at gaps or jumps",
        "dropped_short": "tracks dropped as too short",
        "dropped_jumpy": "tracks dropped as too jumpy",
        "zero_size_tracks": "tracks had zero or missing size (category default used)",
        "outside_ego_time": "vehicle-frame detections lay outside the ego trajectory's time span (dropped)",
    }
    for key, text in msgs.items():
        if counts[key]:
            warnings.append(f"{name}: {counts[key]} {text}")
