"""OpenSCENARIO of the recorded traffic on the generated map, with cut-ins, cut-outs and lane changes.

`export_scenario(ego, tracks, map_path, out_path, cfg)` writes one .xosc (scenariogeneration, OpenSCENARIO
1.2 by default) that replays the recording on the map:

- RoadNetwork/LogicFile is the map's path relative to the .xosc's folder.
- One entity per track (Vehicle of its category, or Pedestrian) with its median box. The reference point
  of every participant is the centre of its box on the ground (BoundingBox centre = (0, 0, h/2)), so the
  written positions are the recorded box centres; the ego's reference point is its pose origin and its
  box sits `ego_center_x_m` ahead of it.
- Every entity follows its recorded path: FollowTrajectoryAction, Polyline of WorldPositions with
  vertex times in simulation time (TimeReference/Timing domainAbsoluteRelative=absolute, scale 1,
  offset 0; simulation time 0 = first ego pose), following mode `position`. Vertices are the smoothed
  samples, thinned while linear interpolation in time reproduces every dropped sample within
  `vertex_tolerance_m` and `vertex_yaw_tolerance_rad`. Heading is unwrapped (no 2 pi jumps).
- z is the road surface of the map under the position (nearest map sample, lateral interpolation
  between lane borders plus the longitudinal slope); positions off the map keep the recorded ground
  height (box bottom), or the ego's when none was recorded.
- Entities seen at the start (first sample within `spawn_tolerance_s`) are teleported to their first
  sample in Init with their initial speed. An entity that appears later is not in Init: an event at
  SimulationTime >= its first sample adds it there (AddEntityAction), and a second event started by
  the end of the first makes it follow its path. An entity whose track ends before the recording is
  removed at its last sample (DeleteEntityAction): it left the sensor's view, and a frozen ghost would
  block traffic. The StopTrigger ends the scenario when the recording ends.
- Manoeuvres relative to the map's lanes (lane id of the road the vehicle is on, with a hysteresis:
  `lane_change_margin_m` deep into the new lane, held for `lane_change_dwell_s`; the time reported is
  the border crossing; changes across roads or off the map are not reported): `ego_lane_change`;
  `cut_in` = another vehicle enters the ego's lane while its centre is 0..`cut_in_range_m` ahead of the
  ego's (along the ego's heading); `cut_out` = it leaves the ego's lane from there; `lane_change` =
  any other lane change. They are returned in the summary and written as XML comments in the
  participant's ManeuverGroup and in a summary comment at the top of the Storyboard.
- The output is byte-reproducible: fixed FileHeader date (SOURCE_DATE_EPOCH when set, else
  1970-01-01), rounded coordinates (1 mm, 0.1 mrad, 0.1 ms).
"""

from __future__ import annotations

import datetime as dt
import math
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from lxml import etree
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from scenariogeneration import xosc
from scipy.spatial import cKDTree

from lidar2xodr.config import Config, ScenarioConfig
from lidar2xodr.data import Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import staged, write_bytes
from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.tracks import Track, TrackSet

EGO = "Ego"
_HEAVY = {"truck", "semitrailer", "trailer", "bus", "tram", "train"}
_MASS = {"car": 1500.0, "van": 2500.0, "truck": 12000.0, "semitrailer": 30000.0, "trailer": 8000.0,
         "bus": 14000.0, "motorbike": 250.0, "bicycle": 90.0, "tram": 40000.0, "train": 100000.0}


@dataclass
class Manoeuvre:
    """A lane change seen on the map; `distance_m` = centre distance ahead of the ego (cut-in/out)."""

    kind: str  # cut_in | cut_out | ego_lane_change | lane_change
    actor: str
    time_s: float  # simulation time
    road_id: str
    from_lane: int
    to_lane: int
    direction: str  # left | right (as seen by the actor)
    distance_m: float | None = None


@dataclass
class ScenarioSummary:
    """What `export_scenario` wrote: entities, timing, manoeuvres, and everything odd about the input."""

    path: Path
    map_path: Path
    duration_s: float
    time_offset_s: float  # recording time of simulation time 0
    entities: dict[str, str]  # entity name -> track id ("ego" for the ego)
    late_entities: list[str]
    removed_entities: list[str]
    vertices: int
    manoeuvres: list[Manoeuvre] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["path"], d["map_path"] = str(self.path), str(self.map_path)
        return d


# --------------------------------------------------------------------------------------------
# the map: surface height and lane of a position


@dataclass
class Located:
    """Where positions lie on the map; `on_map` False = none of the fields is meaningful."""

    on_map: np.ndarray
    road_id: np.ndarray  # object
    lane_id: np.ndarray  # int
    z: np.ndarray
    hdg: np.ndarray
    depth: np.ndarray  # distance of the position from the nearer border of its lane


class MapIndex:
    """Nearest-sample lookup on a sampled OpenDRIVE map (cKDTree over the reference-line samples).

    Lateral positions are horizontal offsets from the reference line, compared with the horizontal
    offsets of the lane borders (superelevation shortens t by cos(roll)); z is interpolated linearly
    between the two borders of the lane and carried along the road with the reference line's slope.
    """

    def __init__(self, odr: OpenDriveMap, step: float, margin: float) -> None:
        self.step, self.margin = step, margin
        secs = [s for s in odr.sample(step) if len(s.s) > 0]
        if not secs:
            raise InputError(odr.path, "the map has no roads to place the traffic on")
        self.sections = []
        xy, hdg, sec, row, tmin, tmax = [], [], [], [], [], []
        for k, sc in enumerate(secs):
            ids = sorted(sc.lane_ids)
            normal = np.stack([-np.sin(sc.hdg), np.cos(sc.hdg)], axis=1)
            bt = np.stack([np.sum((sc.border_xyz[i][:, :2] - sc.xyz[:, :2]) * normal, axis=1) for i in ids], axis=1)
            order = np.argsort(bt, axis=1, kind="stable")
            bt = np.take_along_axis(bt, order, axis=1)
            bz = np.take_along_axis(np.stack([sc.border_xyz[i][:, 2] for i in ids], axis=1), order, axis=1)
            sorted_ids = np.asarray(ids)[order]
            lanes = np.where(sorted_ids[:, :-1] < 0, sorted_ids[:, :-1], sorted_ids[:, 1:])
            dzds = np.gradient(sc.xyz[:, 2], sc.s) if len(sc.s) > 1 else np.zeros(1)
            self.sections.append((sc.road_id, bt, bz, lanes, dzds))
            m = len(sc.s)
            xy.append(sc.xyz[:, :2])
            hdg.append(sc.hdg)
            sec.append(np.full(m, k))
            row.append(np.arange(m))
            tmin.append(bt[:, 0])
            tmax.append(bt[:, -1])
        self.xy, self.hdg = np.vstack(xy), np.concatenate(hdg)
        self.sec, self.row = np.concatenate(sec), np.concatenate(row)
        self.tmin, self.tmax = np.concatenate(tmin), np.concatenate(tmax)
        self.tree = cKDTree(self.xy)

    def locate(self, xy: np.ndarray) -> Located:
        n = len(xy)
        out = Located(np.zeros(n, bool), np.full(n, "", dtype=object), np.zeros(n, np.int64),
                      np.full(n, np.nan), np.full(n, np.nan), np.zeros(n))
        if n == 0:
            return out
        k = min(8, len(self.xy))
        _, cand = self.tree.query(xy, k=k)
        cand = cand.reshape(n, k)
        d = xy[:, None, :] - self.xy[cand]
        c, s = np.cos(self.hdg[cand]), np.sin(self.hdg[cand])
        ds = d[..., 0] * c + d[..., 1] * s
        t = -d[..., 0] * s + d[..., 1] * c
        ok = (np.abs(ds) <= self.step) & (t >= self.tmin[cand] - self.margin) & (t <= self.tmax[cand] + self.margin)
        first = np.argmax(ok, axis=1)
        has = ok[np.arange(n), first]
        pick = cand[np.arange(n), first]
        t_pick, ds_pick = t[np.arange(n), first], ds[np.arange(n), first]
        out.on_map = has
        for k_sec in np.unique(self.sec[pick[has]]):
            m = has & (self.sec[pick] == k_sec)
            road_id, bt, bz, lanes, dzds = self.sections[k_sec]
            rows = self.row[pick[m]]
            tt = t_pick[m]
            b, z = bt[rows], bz[rows]
            j = np.clip(np.sum(b <= tt[:, None], axis=1) - 1, 0, b.shape[1] - 2)
            ar = np.arange(len(rows))
            b0, b1, z0, z1 = b[ar, j], b[ar, j + 1], z[ar, j], z[ar, j + 1]
            w = np.clip(np.where(b1 > b0, (tt - b0) / np.where(b1 > b0, b1 - b0, 1.0), 0.0), 0.0, 1.0)
            out.road_id[m] = road_id
            out.lane_id[m] = lanes[rows, j]
            out.z[m] = z0 + w * (z1 - z0) + ds_pick[m] * dzds[rows]
            out.hdg[m] = self.hdg[pick[m]]
            out.depth[m] = np.maximum(np.minimum(tt - b0, b1 - tt), 0.0)
        return out


# --------------------------------------------------------------------------------------------
# geometry helpers


def thin_vertices(t: np.ndarray, xyz: np.ndarray, yaw: np.ndarray, tol: float, yaw_tol: float) -> np.ndarray:
    """Indices of the samples to keep so that linear interpolation in time stays within tol (Douglas-Peucker
    in time: the error of a dropped sample is measured at its own time stamp)."""
    n = len(t)
    keep = np.zeros(n, dtype=bool)
    keep[[0, n - 1]] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        w = (t[i + 1:j] - t[i]) / (t[j] - t[i])
        err = np.linalg.norm(xyz[i] + w[:, None] * (xyz[j] - xyz[i]) - xyz[i + 1:j], axis=1) / tol
        yerr = np.abs(yaw[i] + w * (yaw[j] - yaw[i]) - yaw[i + 1:j]) / yaw_tol
        score = np.maximum(err, yerr)
        m = int(np.argmax(score))
        if score[m] > 1.0:
            mid = i + 1 + m
            keep[mid] = True
            stack += [(i, mid), (mid, j)]
    return np.flatnonzero(keep)


def _ego_samples(ego: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    times, idx = np.unique(ego.times, return_index=True)
    if len(times) < 2:
        raise InputError("ego trajectory", "needs at least two poses with distinct times")
    poses = ego.poses[idx]
    if not np.all(np.isfinite(poses)):
        raise InputError("ego trajectory", "holds non-finite poses")
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    return times, poses[:, :3, 3].copy(), yaw


@dataclass
class _Entity:
    name: str
    track_id: str
    category: str
    dims: np.ndarray
    times: np.ndarray  # recording time
    xyz: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    where: Located
    center_x: float = 0.0


def _safe_name(category: str, tid: str, used: set[str]) -> str:
    base = re.sub(r"[^A-Za-z0-9_.-]", "_", f"{category}_{tid}")
    name, k = base, 2
    while name in used or name == EGO:
        name, k = f"{base}_{k}", k + 1
    used.add(name)
    return name


# --------------------------------------------------------------------------------------------
# manoeuvres


def _runs(times: np.ndarray, codes: np.ndarray, dwell: float) -> list[tuple[int, int, int]]:
    """Runs (first, last sample, lane code) of constant lane; the shortest run under `dwell` joins the run
    before it (the first run joins the next), repeated until every run lasts `dwell` or only one is left."""
    codes = codes.copy()
    while True:
        cut = np.flatnonzero(np.diff(codes) != 0) + 1
        first, last = np.r_[0, cut], np.r_[cut - 1, len(codes) - 1]
        dur = times[last] - times[first]
        if len(first) < 2 or dur.min() >= dwell:
            return [(int(a), int(b), int(codes[a])) for a, b in zip(first, last, strict=True)]
        r = int(np.argmin(dur))
        codes[first[r]:last[r] + 1] = codes[first[r - 1]] if r > 0 else codes[first[r + 1]]


def _lane_changes(e: _Entity, dwell: float, margin: float) -> list[tuple[float, int, str, int, int, str]]:
    """(time, sample index, road, from lane, to lane, direction) of each lane change of one entity.

    Hysteresis in space and time: a sample counts for a new lane of the same road only once its centre
    is `margin` deep inside it, and a lane must then be held for `dwell`; both lanes must have been
    entered that deep (a track that starts on a lane line has no known lane to leave). The reported time
    is the last crossing of the border before that (midway between the two samples around it).
    """
    w = e.where
    raw = [(str(w.road_id[i]), int(w.lane_id[i])) if w.on_map[i] else None for i in range(len(e.times))]
    keys = list(raw)
    for i in range(1, len(keys)):
        prev = keys[i - 1]
        if keys[i] is not None and prev is not None and keys[i] != prev and keys[i][0] == prev[0] \
                and w.depth[i] < margin:
            keys[i] = prev
    table = {k: q for q, k in enumerate(dict.fromkeys(keys))}
    lookup = list(table)
    runs = _runs(e.times, np.array([table[k] for k in keys]), dwell)
    codes = np.array([table.get(k, -1) for k in raw])

    def established(r: tuple[int, int, int]) -> bool:
        m = codes[r[0]:r[1] + 1] == r[2]
        return bool(m.any() and w.depth[r[0]:r[1] + 1][m].max() >= margin)

    out = []
    for a, b in zip(runs[:-1], runs[1:], strict=True):
        ka, kb = lookup[a[2]], lookup[b[2]]
        if ka is None or kb is None or ka[0] != kb[0] or ka[1] == kb[1] or not (established(a) and established(b)):
            continue
        i = b[0]
        c = i
        while c > a[0] and raw[c - 1] == kb:
            c -= 1
        tc = 0.5 * (e.times[max(c - 1, 0)] + e.times[c])
        left = kb[1] > ka[1]
        if math.cos(e.yaw[i] - w.hdg[i]) < 0:
            left = not left
        out.append((tc, i, ka[0], ka[1], kb[1], "left" if left else "right"))
    return out


def detect_manoeuvres(ego: _Entity, others: list[_Entity], cfg: ScenarioConfig, t0: float) -> list[Manoeuvre]:
    """Ego lane changes, cut-ins, cut-outs and other lane changes (see the module doc)."""
    found: list[Manoeuvre] = []
    for tc, _, road, a, b, d in _lane_changes(ego, cfg.lane_change_dwell_s, cfg.lane_change_margin_m):
        found.append(Manoeuvre("ego_lane_change", EGO, round(float(tc - t0), 3), road, a, b, d))
    ew = ego.where
    for e in others:
        if e.category == "pedestrian":
            continue
        for tc, _, road, a, b, d in _lane_changes(e, cfg.lane_change_dwell_s, cfg.lane_change_margin_m):
            j = int(np.clip(np.searchsorted(ego.times, tc), 0, len(ego.times) - 1))
            ego_lane = (str(ew.road_id[j]), int(ew.lane_id[j])) if ew.on_map[j] else None
            p_obj = np.array([np.interp(tc, e.times, e.xyz[:, k]) for k in range(2)])
            p_ego = np.array([np.interp(tc, ego.times, ego.xyz[:, k]) for k in range(2)])
            yaw_e = float(np.interp(tc, ego.times, ego.yaw))
            ahead = float(np.dot(p_obj - p_ego, [math.cos(yaw_e), math.sin(yaw_e)]))
            near = 0.0 < ahead <= cfg.cut_in_range_m
            kind = "lane_change"
            if near and ego_lane == (road, b):
                kind = "cut_in"
            elif near and ego_lane == (road, a):
                kind = "cut_out"
            dist = round(ahead, 2) if kind != "lane_change" else None
            found.append(Manoeuvre(kind, e.name, round(float(tc - t0), 3), road, a, b, d, dist))
    return sorted(found, key=lambda m: (m.time_s, m.actor))


# --------------------------------------------------------------------------------------------
# writing


def _r(v: float, nd: int) -> float:
    return float(round(float(v), nd)) + 0.0


def _position(p: np.ndarray, yaw: float) -> xosc.WorldPosition:
    return xosc.WorldPosition(_r(p[0], 3), _r(p[1], 3), _r(p[2], 3), _r(yaw, 4))


def _object(e: _Entity, max_speed: float) -> xosc.Vehicle | xosc.Pedestrian:
    length, width, height = (float(v) for v in e.dims)
    bb = xosc.BoundingBox(_r(width, 3), _r(length, 3), _r(height, 3), _r(e.center_x, 3), 0, _r(height / 2, 3))
    if e.category == "pedestrian":
        return xosc.Pedestrian(e.name, 80, xosc.PedestrianCategory.pedestrian, bb, model="pedestrian")
    wheel = 1.0 if e.category in _HEAVY else 0.65
    track_w = _r(0.85 * width, 3)
    ax = _r(0.3 * length, 3)
    front = xosc.Axle(0.5, wheel, track_w, _r(e.center_x + ax, 3), wheel / 2)
    rear = xosc.Axle(0.0, wheel, track_w, _r(e.center_x - ax, 3), wheel / 2)
    return xosc.Vehicle(e.name, getattr(xosc.VehicleCategory, e.category), bb, front, rear,
                        max_speed, 10, 10, _MASS.get(e.category, 1500.0))


def _time_trigger(name: str, t: float) -> xosc.ValueTrigger:
    return xosc.ValueTrigger(name, 0, xosc.ConditionEdge.none,
                             xosc.SimulationTimeCondition(_r(t, 4), xosc.Rule.greaterOrEqual))


def _follow(e: _Entity, t0: float, cfg: ScenarioConfig) -> tuple[xosc.FollowTrajectoryAction, int]:
    keep = thin_vertices(e.times, e.xyz, e.yaw, cfg.vertex_tolerance_m, cfg.vertex_yaw_tolerance_rad)
    times = [_r(e.times[i] - t0, 4) for i in keep]
    uniq = [k for q, k in enumerate(keep) if q == 0 or times[q] > times[q - 1]]
    times = [_r(e.times[i] - t0, 4) for i in uniq]
    poly = xosc.Polyline(times, [_position(e.xyz[i], e.yaw[i]) for i in uniq])
    traj = xosc.Trajectory(f"{e.name}_recorded", False)
    traj.add_shape(poly)
    return xosc.FollowTrajectoryAction(traj, xosc.FollowingMode.position, xosc.ReferenceContext.absolute, 1, 0), \
        len(uniq)


def _creation_date() -> dt.datetime:
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "0")
    try:
        return dt.datetime.fromtimestamp(int(epoch), tz=dt.timezone.utc).replace(tzinfo=None)
    except (ValueError, OverflowError, OSError):
        return dt.datetime(1970, 1, 1)


def _comment(text: str) -> etree._Comment:
    return etree.Comment(" " + text.replace("--", "- -") + " ")


def export_scenario(
    ego: Trajectory, tracks: TrackSet, map_path: Path, out_path: Path, cfg: Config | ScenarioConfig | None = None
) -> ScenarioSummary:
    """Write the OpenSCENARIO of the recording (see the module doc) atomically and summarise it."""
    scfg = cfg.scenario if isinstance(cfg, Config) else (cfg or ScenarioConfig())
    map_path, out_path = Path(map_path), Path(out_path)
    odr = OpenDriveMap.load(staged(map_path))  # a map written in the same build is still staged
    index = MapIndex(odr, scfg.map_sample_step_m, scfg.off_map_margin_m)
    warnings = list(tracks.warnings)
    counts: dict[str, int] = {}
    if tracks.origin is not None and tracks.origin.proj and odr.geo_reference and \
            tracks.origin.proj.split() != odr.geo_reference.split():
        warnings.append("the tracks were projected with a different geoReference than the map's")

    et, exyz, eyaw = _ego_samples(ego)
    t0, t_end = float(et[0]), float(et[-1])
    ew = index.locate(exyz[:, :2])
    exyz[ew.on_map, 2] = ew.z[ew.on_map]
    speed_e = np.hypot(*np.gradient(exyz[:, :2], et, axis=0).T)
    ego_e = _Entity(EGO, "ego", "car", np.array(scfg.ego_dims_m, dtype=float), et, exyz, eyaw, speed_e, ew,
                    scfg.ego_center_x_m)
    counts["ego_off_map_samples"] = int((~ew.on_map).sum())
    if counts["ego_off_map_samples"]:
        warnings.append(f"{counts['ego_off_map_samples']} of {len(et)} ego poses lie outside the map")

    entities: list[_Entity] = []
    used: set[str] = set()
    outside = off_samples = off_tracks = 0
    for tr in tracks.tracks:
        e = _clip_and_place(tr, t0, t_end, index, ego_e)
        if e is None:
            outside += 1
            continue
        n_off = int((~e.where.on_map).sum())
        off_samples += n_off
        if n_off == len(e.times):
            off_tracks += 1
            if scfg.drop_off_map:
                continue
        e.name = _safe_name(e.category, tr.id, used)
        entities.append(e)
    counts.update(outside_recording_tracks=outside, off_map_samples=off_samples, off_map_tracks=off_tracks)
    if outside:
        warnings.append(f"{outside} tracks lie outside the recording's time span (ego poses) and were left out")
    if off_samples:
        n_all = sum(len(e.times) for e in entities)
        action = "dropped" if scfg.drop_off_map else "kept"
        warnings.append(f"{off_samples} of {n_all} participant samples lie outside the map "
                        f"({off_tracks} tracks entirely, {action})")

    manoeuvres = detect_manoeuvres(ego_e, entities, scfg, t0)
    xml, n_vert, late, removed = _build_xosc(ego_e, entities, manoeuvres, map_path, out_path, t0, t_end, scfg,
                                             tracks.source, warnings)
    write_bytes(out_path, xml)
    counts["vertices"] = n_vert
    all_counts = {**{f"tracks.{k}": v for k, v in tracks.counts.items()}, **counts}
    return ScenarioSummary(
        path=out_path, map_path=map_path, duration_s=round(t_end - t0, 4), time_offset_s=t0,
        entities={EGO: "ego", **{e.name: e.track_id for e in entities}}, late_entities=late,
        removed_entities=removed, vertices=n_vert, manoeuvres=manoeuvres, counts=all_counts, warnings=warnings,
    )


def _clip_and_place(tr: Track, t0: float, t_end: float, index: MapIndex, ego: _Entity) -> _Entity | None:
    m = (tr.times >= t0 - 1e-9) & (tr.times <= t_end + 1e-9)
    if m.sum() < 2:
        return None
    xyz = tr.xyz[m].copy()
    where = index.locate(xyz[:, :2])
    no_z = ~np.isfinite(xyz[:, 2])
    xyz[no_z, 2] = np.interp(tr.times[m][no_z], ego.times, ego.xyz[:, 2]) if no_z.any() else xyz[no_z, 2]
    xyz[where.on_map, 2] = where.z[where.on_map]
    return _Entity("", tr.id, tr.category, tr.dims, tr.times[m], xyz, tr.yaw[m], tr.speed[m], where)


def _build_xosc(ego: _Entity, entities: list[_Entity], manoeuvres: list[Manoeuvre], map_path: Path,
                out_path: Path, t0: float, t_end: float, cfg: ScenarioConfig, source: str,
                warnings: list[str]) -> tuple[bytes, int, list[str], list[str]]:
    max_speed = _r(max(70.0, 1.2 * max([float(np.max(e.speed)) for e in [ego, *entities]])), 1)
    ents = xosc.Entities()
    init = xosc.Init()
    story = xosc.Story("recorded_traffic")
    act = xosc.Act("replay", _time_trigger("replay_start", 0.0))
    n_vert = 0
    late: list[str] = []
    removed: list[str] = []
    for e in [ego, *entities]:
        ents.add_scenario_object(e.name, _object(e, max_speed))
        follow, nv = _follow(e, t0, cfg)
        n_vert += nv
        man = xosc.Maneuver(f"{e.name}_replay")
        group = xosc.ManeuverGroup(f"{e.name}_group")
        group.add_actor(e.name)
        first = _position(e.xyz[0], e.yaw[0])
        if e is ego or e.times[0] - t0 <= cfg.spawn_tolerance_s:
            init.add_init_action(e.name, xosc.TeleportAction(first))
            init.add_init_action(e.name, xosc.AbsoluteSpeedAction(
                _r(e.speed[0], 3), xosc.TransitionDynamics(xosc.DynamicsShapes.step, xosc.DynamicsDimension.time, 0)))
            ev = xosc.Event(f"{e.name}_follow", xosc.Priority.parallel)
            ev.add_trigger(_time_trigger(f"{e.name}_follow_start", 0.0))
            ev.add_action(f"{e.name}_trajectory", follow)
            man.add_event(ev)
        else:
            late.append(e.name)
            appear = xosc.Event(f"{e.name}_appear", xosc.Priority.parallel)
            appear.add_trigger(_time_trigger(f"{e.name}_appear_time", e.times[0] - t0))
            appear.add_action(f"{e.name}_add", xosc.AddEntityAction(e.name, first))
            man.add_event(appear)
            ev = xosc.Event(f"{e.name}_follow", xosc.Priority.parallel)
            ev.add_trigger(xosc.ValueTrigger(
                f"{e.name}_after_appear", 0, xosc.ConditionEdge.none,
                xosc.StoryboardElementStateCondition(xosc.StoryboardElementType.event, f"{e.name}_appear",
                                                     xosc.StoryboardElementState.completeState)))
            ev.add_action(f"{e.name}_trajectory", follow)
            man.add_event(ev)
        if e is not ego and t_end - e.times[-1] > cfg.spawn_tolerance_s:
            removed.append(e.name)
            gone = xosc.Event(f"{e.name}_leave", xosc.Priority.parallel)
            gone.add_trigger(_time_trigger(f"{e.name}_leave_time", e.times[-1] - t0))
            gone.add_action(f"{e.name}_delete", xosc.DeleteEntityAction(e.name))
            man.add_event(gone)
        group.add_maneuver(man)
        act.add_maneuver_group(group)
    story.add_act(act)
    stop = xosc.ValueTrigger("recording_end", 0, xosc.ConditionEdge.rising,
                             xosc.SimulationTimeCondition(_r(t_end - t0, 4), xosc.Rule.greaterThan), "stop")
    board = xosc.StoryBoard(init, stop)
    board.add_story(story)
    rel = Path(os.path.relpath(map_path.resolve(), out_path.resolve().parent)).as_posix()
    scenario = xosc.Scenario(
        f"Recorded traffic of {Path(source).name}", "lidar2xodr", xosc.ParameterDeclarations(), ents, board,
        xosc.RoadNetwork(roadfile=rel), xosc.Catalog(), osc_minor_version=cfg.osc_minor_version,
        creation_date=_creation_date(),
    )
    root = etree.fromstring(ET.tostring(scenario.get_element(), encoding="utf-8"))
    _annotate(root, manoeuvres, warnings, t0)
    etree.indent(root, space="  ")
    xml = etree.tostring(root, xml_declaration=True, encoding="utf-8", pretty_print=True)
    return xml, n_vert, late, removed


def _annotate(root: etree._Element, manoeuvres: list[Manoeuvre], warnings: list[str], t0: float) -> None:
    """Manoeuvres and input warnings as XML comments (no effect on the simulation)."""
    board = root.find("Storyboard")
    lines = [f"simulation time 0 = recording time {t0:.4f} s"]
    lines += [f"{m.kind} at {m.time_s:.2f} s: {m.actor} road {m.road_id} lane {m.from_lane} -> {m.to_lane} "
              f"({m.direction})" + (f", {m.distance_m:.1f} m ahead of the ego" if m.distance_m is not None else "")
              for m in manoeuvres]
    lines += [f"warning: {w}" for w in warnings]
    if board is not None:
        board.addprevious(_comment("lidar2xodr recorded traffic\n    " + "\n    ".join(lines) + "\n"))
    groups = {g.get("name"): g for g in root.iter("ManeuverGroup")}
    for m in manoeuvres:
        g = groups.get(f"{m.actor}_group")
        if g is not None and len(g):
            text = (f"{m.kind} at {m.time_s:.2f} s: lane {m.from_lane} -> {m.to_lane} ({m.direction}) "
                    f"on road {m.road_id}")
            if m.distance_m is not None:
                text += f", {m.distance_m:.1f} m ahead of the ego"
            g[0].addprevious(_comment(text))


def print_summary(summary: ScenarioSummary, out: Console, err: Console) -> None:
    """Entities, timing and manoeuvres on `out`; every warning about the input on `err`."""
    table = Table(title=f"scenario {summary.path}", show_header=True)
    table.add_column("item")
    table.add_column("value", justify="right")
    table.add_row("map", escape(str(summary.map_path)))
    table.add_row("duration", f"{summary.duration_s:.2f} s")
    table.add_row("entities (incl. ego)", str(len(summary.entities)))
    table.add_row("appear later / leave early", f"{len(summary.late_entities)} / {len(summary.removed_entities)}")
    table.add_row("polyline vertices", str(summary.vertices))
    for key in ("tracks.dropped_short", "tracks.dropped_jumpy", "tracks.smoothed", "off_map_tracks"):
        table.add_row(key.replace("tracks.", "tracks ").replace("_", " "), str(summary.counts.get(key, 0)))
    out.print(table)
    for m in summary.manoeuvres:
        where = f", {m.distance_m:.1f} m ahead" if m.distance_m is not None else ""
        text = f"{m.time_s:8.2f} s  {m.kind:<16} {m.actor}: lane {m.from_lane} -> {m.to_lane} ({m.direction})"
        out.print(text + where, highlight=False)
    for w in summary.warnings:
        err.print(f"[yellow]warning:[/] {w}", highlight=False, soft_wrap=True)
