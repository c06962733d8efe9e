"""Save and load the marking cloud, so the markings stage can run alone.

Files (all written atomically, as one set):
- `<stem>.ply`: binary little-endian PLY, one `vertex` element with properties
  `double x, double y, double z, float intensity, int scan, double time` (world frame, metres,
  intensity 0..1, scan index, absolute point time in seconds).
- `<stem>.planes.csv`: `time,px,py,pz,nx,ny,nz` one row per scan: the ground plane's point below
  the vehicle and its upward unit normal, world frame.
- `<stem>.trajectory.csv`: `time,x,y,z,qx,qy,qz,qw`: T_world_vehicle (scipy quaternion order).
- `<stem>.origin.json`: `{"lat", "lon", "alt", "proj"}` of the world frame (nulls without GNSS).
Numbers in the CSVs are written with Python's shortest round-trip repr, so load(save(c)) == c.
"""

from __future__ import annotations

import contextlib
import json
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lidar2xodr.data import GeoOrigin, GroundPlanes, MarkingCloud, Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import atomic_path

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_NP_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}
MARKING_FIELDS = (("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4"), ("scan", "i4"), ("time", "f8"))


def sidecars(path: str | Path) -> dict[str, Path]:
    path = Path(path)
    stem = path.with_suffix("")
    return {
        "planes": stem.with_name(stem.name + ".planes.csv"),
        "trajectory": stem.with_name(stem.name + ".trajectory.csv"),
        "origin": stem.with_name(stem.name + ".origin.json"),
    }


def ply_bytes(vertices: np.ndarray, comment: str = "") -> bytes:
    """Binary little-endian PLY of one structured array as the `vertex` element."""
    props = "".join(
        f"property {_NP_TO_PLY[vertices.dtype[n].str[1:]]} {n}\n" for n in vertices.dtype.names or ()
    )
    head = "ply\nformat binary_little_endian 1.0\n"
    if comment:
        head += f"comment {comment}\n"
    head += f"element vertex {len(vertices)}\n{props}end_header\n"
    le = vertices.astype(vertices.dtype.newbyteorder("<"), copy=False)
    return head.encode("ascii") + le.tobytes()


def read_ply(path: str | Path) -> np.ndarray:
    """The `vertex` element of a PLY file (ascii or binary) as a structured array.

    Elements before `vertex` must have fixed-size properties (no lists); what follows is ignored.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0 or data.find(b"\n", end) < 0:
        raise InputError(path, "not a PLY file (no 'ply' magic or no 'end_header' line)")
    body_start = data.index(b"\n", end) + 1
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) == 3:
            if not tok[2].isdigit():
                raise InputError(path, f"PLY element {tok[1]!r}: count {tok[2]!r} is not a non-negative integer")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property" and elements:
            if len(tok) >= 2 and tok[1] == "list":
                elements[-1][2].append((tok[-1], "list"))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                if any(tok[2] == name for name, _ in elements[-1][2]):
                    raise InputError(path, f"PLY element {elements[-1][0]!r} has property {tok[2]!r} twice")
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise InputError(path, f"unsupported PLY property line: {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(path, f"unsupported PLY format {fmt!r}")
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = body_start
    skip_rows = 0
    for name, count, props in elements:
        if any(t == "list" for _, t in props):
            raise InputError(path, f"PLY element {name!r} has list properties")
        dtype = np.dtype([(p, order + t) for p, t in props])
        if name == "vertex":
            if fmt == "ascii":
                text = data[body_start:].decode("ascii", errors="replace").splitlines()[skip_rows:skip_rows + count]
                try:
                    table = np.array([[float(v) for v in ln.split()] for ln in text], dtype=np.float64)
                except ValueError as exc:
                    raise InputError(path, f"bad ASCII PLY vertex: {exc}") from None
                if table.shape != (count, len(props)):
                    raise InputError(path, f"ASCII PLY: expected {count} vertices of {len(props)} values")
                out = np.empty(count, dtype=[(p, t) for p, t in props])
                for i, (p, _) in enumerate(props):
                    out[p] = table[:, i]
                return out
            need = count * dtype.itemsize
            if len(data) - offset < need:
                left = max(len(data) - offset, 0)
                raise InputError(path, f"truncated PLY: {count} vertices need {need} bytes after "
                                 f"{offset - body_start} bytes of earlier elements, {left} present")
            return np.frombuffer(data, dtype=dtype, count=count, offset=offset).astype(dtype.newbyteorder("="))
        offset += count * dtype.itemsize
        skip_rows += count
    raise InputError(path, "PLY file has no vertex element")


def _fmt(row: np.ndarray) -> str:
    return ",".join(repr(float(v)) for v in row)


def _csv_text(header: str, table: np.ndarray) -> str:
    return header + "\n" + "".join(_fmt(r) + "\n" for r in table)


def save_markings(cloud: MarkingCloud, path: str | Path) -> None:
    """Write the PLY and its three sidecars; either all four appear or none changes."""
    path = Path(path)
    verts = np.empty(len(cloud.xyz), dtype=list(MARKING_FIELDS))
    verts["x"], verts["y"], verts["z"] = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    verts["intensity"] = cloud.intensity
    verts["scan"] = cloud.scan_index
    verts["time"] = cloud.time
    planes = cloud.planes
    plane_table = np.column_stack([planes.times, planes.points_world, planes.normals_world]).reshape(-1, 7)
    traj = cloud.trajectory
    quat = Rotation.from_matrix(traj.poses[:, :3, :3]).as_quat() if len(traj) else np.zeros((0, 4))
    traj_table = np.column_stack([traj.times, traj.positions, quat]).reshape(-1, 8)
    o = cloud.origin
    origin = {"lat": o.lat, "lon": o.lon, "alt": o.alt, "proj": o.proj}
    side = sidecars(path)
    with contextlib.ExitStack() as stack:
        tmp_ply = stack.enter_context(atomic_path(path))
        tmp_planes = stack.enter_context(atomic_path(side["planes"]))
        tmp_traj = stack.enter_context(atomic_path(side["trajectory"]))
        tmp_origin = stack.enter_context(atomic_path(side["origin"]))
        tmp_ply.write_bytes(ply_bytes(verts, "lidar2xodr lane-marking points, world frame"))
        tmp_planes.write_text(_csv_text("time,px,py,pz,nx,ny,nz", plane_table), encoding="utf-8")
        tmp_traj.write_text(_csv_text("time,x,y,z,qx,qy,qz,qw", traj_table), encoding="utf-8")
        tmp_origin.write_text(json.dumps(origin, indent=2, sort_keys=True) + "\n", encoding="utf-8")


def _read_csv(path: Path, header: str) -> np.ndarray:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise InputError(path, "sidecar file missing (written by `lidar2xodr extract`)") from None
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None
    if not lines or lines[0].strip() != header:
        raise InputError(path, f"expected header {header!r}")
    ncol = header.count(",") + 1
    cells = [ln.split(",") for ln in lines[1:] if ln.strip()]
    for i, row in enumerate(cells):
        if len(row) != ncol:
            raise InputError(path, f"row {i + 2} has {len(row)} values, expected {ncol}")
    try:
        table = np.array([[float(v) for v in row] for row in cells], dtype=np.float64).reshape(-1, ncol)
    except ValueError as exc:
        raise InputError(path, f"not a number: {exc}") from None
    if not np.isfinite(table).all():
        raise InputError(path, "non-finite values")
    return table


def load_markings(path: str | Path) -> MarkingCloud:
    """Read what `save_markings` wrote; InputError naming the file for anything missing or wrong."""
    path = Path(path)
    verts = read_ply(path)
    names = verts.dtype.names or ()
    missing = [n for n, _ in MARKING_FIELDS if n not in names]
    if missing:
        raise InputError(path, f"PLY vertex lacks properties {missing}")
    xyz = np.column_stack([verts["x"], verts["y"], verts["z"]]).astype(np.float64)
    if not np.isfinite(xyz).all():
        raise InputError(path, "non-finite marking coordinates")
    side = sidecars(path)
    planes = _read_csv(side["planes"], "time,px,py,pz,nx,ny,nz")
    traj = _read_csv(side["trajectory"], "time,x,y,z,qx,qy,qz,qw")
    poses = np.tile(np.eye(4), (len(traj), 1, 1))
    if len(traj):
        norms = np.linalg.norm(traj[:, 4:8], axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-3):
            raise InputError(side["trajectory"], "quaternions are not unit length")
        poses[:, :3, :3] = Rotation.from_quat(traj[:, 4:8]).as_matrix()
        poses[:, :3, 3] = traj[:, 1:4]
    try:
        raw = json.loads(side["origin"].read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(side["origin"], "sidecar file missing (written by `lidar2xodr extract`)") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(side["origin"], f"cannot read: {exc}") from None
    if not isinstance(raw, dict):
        raise InputError(side["origin"], "expected a JSON object with lat, lon, alt, proj")
    alt = raw.get("alt")
    origin = GeoOrigin(
        lat=raw.get("lat"), lon=raw.get("lon"),
        alt=float(alt) if alt is not None and math.isfinite(float(alt)) else 0.0, proj=raw.get("proj"),
    )
    return MarkingCloud(
        xyz=xyz,
        intensity=np.asarray(verts["intensity"], dtype=np.float32),
        scan_index=np.asarray(verts["scan"], dtype=np.int32),
        time=np.asarray(verts["time"], dtype=np.float64),
        planes=GroundPlanes(times=planes[:, 0], points_world=planes[:, 1:4], normals_world=planes[:, 4:7]),
        trajectory=Trajectory(times=traj[:, 0], poses=poses),
        origin=origin,
    )
