"""Splits, exits and merges: the carriageway as several roads joined by direct junctions.

The lanes stage (`lanes.build_lane_model`) models the ego's carriageway as one road. Where a lane
leaves it (a split or an exit: the lane's width grows beyond every lane width because its lines
diverge) or joins it (a merge: a lane converges from far away, or appears at full width rather than
growing from zero like an added lane), that one road is cut at the junction station and the lane
that leaves or joins becomes its own road, built from the markings the carriageway does not explain.
Nothing here uses the ego trajectory to connect markings (the lanes stage uses it only to pick the
carriageway; the branch's lanes stage likewise).

Rules (parameters in `LanesConfig`):
- Event: the outermost lane of a lane section (the rightmost; the leftmost too on a one-way road)
  whose width at the section's end (diverge) or start (merge) exceeds its median width by
  `branch_widening_m`, or (merge) a new outermost lane at a section start that starts at 70 % of its
  width or more, not at the start of the drive (an added lane grows from zero: the lanes stage
  follows its taper). A diverge is sought in the drive's last section too (unlike a merge in its
  first: a carriageway split seen only to the drive's end, highway_example_with_merge_and_split at
  seed 2, is built right as a junction, 0.107 m boundaries, and 2.136 m without it). An entry or
  exit lane (typed by the lanes stage) is no event, except an entry lane that appears at full width
  beside the road with a new outer line: an on-ramp's lane joining at the gore, which then runs on
  as the acceleration lane and tapers out. The junction station is where the lane's width was last
  normal (median + 0.3 m): the gore nose, where the two lines begin to separate.
- Roads: the measured road before the junction (A) and after it (B: the same reference line, so B
  continues A exactly, without the lane that leaves or joins) plus the branch (C). C is built by the
  lanes stage from the marking points beside the lost lane's side beyond the junction (before it, for
  a merge, up to 30 m past it, where the ramp's lines may still converge) that lie farther than
  `assign_distance_m` from every line kept in B (A, for a merge), plus, so C starts at
  the gore, for a diverge every point from 0.5 m inside the lost lane's inner line outwards within
  30 m of the junction, for a merge only the lost lane's own two lines over 15 m after the junction
  (a ramp that converges at an angle must not share its axis with the road's edge before it); of
  these only points of marking lines (candidates) spanning `branch_min_line_m` or more are used
  (clutter at a U-turn would bend C's axis). C is kept when it has lanes over
  `branch_min_length_m`, its junction end lies within two lane widths of the lost lane's middle and its
  heading there is within 30 deg of the road's; it is oriented to travel like the road (a diverging
  branch starts at the junction, a merging one ends there) and cut to start (end) on the junction's
  cross-section. Otherwise the lane ends at the junction (a warning says why).
- Links: A -> B as a continuation (every lane that goes on, by lateral overlap); A -> C (diverge) or
  C -> B (merge): the lost lane to C's lane on that side. The exporter writes them as one direct
  junction and snaps C's lane borders onto the road's at the junction.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lidar2xodr.config import LanesConfig, MarkingsConfig
from lidar2xodr.data import TAPER_LANE_TYPES, LaneModel, LaneSection, MarkingCloud, RoadLink, RoadNetwork
from lidar2xodr.errors import InputError

_NORMAL_MARGIN_M = 0.3
_NEW_LANE_SHARE = 0.7
_GORE_M = 15.0
_DASH_GAP_M = 1.0  # no marking point over this length of a line: a gap between dashes
_MAX_HEADING_DEG = 30.0
_NOSE_MARGIN_M = 0.5  # a point this far inside a lane from both its lines is on neither
_NOSE_MIN_POINTS = 20  # fewer points inside the lane are clutter, not a ramp's line
_NOSE_MIN_PER_STATION = 5  # the line's last station holds this many (a stray return lies beyond it)


@dataclass
class Event:
    """A lane that leaves (diverge) or joins (merge) the road at station index `k`."""

    kind: str  # diverge | merge
    k: int
    section: int  # index of the section holding the lane
    lane: int  # lane index in that section (between boundary_ids[lane] and [lane + 1])
    side: str  # right | left


def _stations_of(model: LaneModel, sec: LaneSection) -> np.ndarray:
    return np.flatnonzero((model.s >= sec.s_start - 1e-9) & (model.s <= sec.s_end + 1e-9))


def _lane_width(model: LaneModel, sec: LaneSection, lane: int, ks: np.ndarray) -> np.ndarray:
    by_id = {b.id: b for b in model.boundaries}
    return by_id[sec.boundary_ids[lane]].t[ks] - by_id[sec.boundary_ids[lane + 1]].t[ks]


def _outer_lanes(sec: LaneSection) -> list[tuple[int, str]]:
    lanes = [(len(sec.boundary_ids) - 2, "right")]
    if sec.divider_id is None and len(sec.boundary_ids) > 2:
        lanes.append((0, "left"))
    return lanes


def find_events(model: LaneModel, cfg: LanesConfig) -> list[Event]:
    """Diverging and merging lanes of the road (see the module docstring), ordered along s."""
    events: list[Event] = []
    n_sec = len(model.sections)
    for j, sec in enumerate(model.sections):
        ks = _stations_of(model, sec)
        if len(ks) < 6:
            continue
        for lane, side in _outer_lanes(sec):
            tapered = sec.lane_types is not None and sec.lane_types[lane] in TAPER_LANE_TYPES
            w = _lane_width(model, sec, lane, ks)
            ok = np.isfinite(w)
            normal = w[ok & (w <= cfg.max_lane_width_m)]
            if len(normal) < 5:
                continue
            med = float(np.median(normal))
            outer = sec.boundary_ids[lane + 1] if side == "right" else sec.boundary_ids[lane]
            goes_on = j + 1 < n_sec and outer in model.sections[j + 1].boundary_ids
            came = j > 0 and outer in model.sections[j - 1].boundary_ids
            if not tapered and not goes_on and np.nanmax(w[-3:]) > med + cfg.branch_widening_m:
                i = len(w) - 1
                while i > 0 and not (w[i] <= med + _NORMAL_MARGIN_M):
                    i -= 1
                events.append(Event("diverge", int(ks[i]), j, lane, side))
            elif not came and j > 0:
                if not tapered and np.nanmax(w[:3]) > med + cfg.branch_widening_m:
                    i = 0
                    while i < len(w) - 1 and not (w[i] <= med + _NORMAL_MARGIN_M):
                        i += 1
                    events.append(Event("merge", int(ks[i]), j, lane, side))
                elif float(np.nanmedian(w[:3])) >= _NEW_LANE_SHARE * med and _is_new(model, j, lane):
                    events.append(Event("merge", int(ks[0]), j, lane, side))
    return sorted(events, key=lambda e: e.k)


def _is_new(model: LaneModel, j: int, lane: int) -> bool:
    """No lane of the previous section overlaps this one by half its width at the section change."""
    by_id = {b.id: b for b in model.boundaries}
    sec, prev = model.sections[j], model.sections[j - 1]
    k0 = int(_stations_of(model, sec)[0])
    left, right = by_id[sec.boundary_ids[lane]].t[k0 + 1], by_id[sec.boundary_ids[lane + 1]].t[k0 + 1]
    for i in range(len(prev.boundary_ids) - 1):
        tl, tr = by_id[prev.boundary_ids[i]].t[: k0 + 1], by_id[prev.boundary_ids[i + 1]].t[: k0 + 1]
        both = np.flatnonzero(np.isfinite(tl) & np.isfinite(tr))
        if not len(both):
            continue
        pl, pr = tl[both[-1]], tr[both[-1]]
        if min(left, pl) - max(right, pr) > 0.5 * (left - right):
            return False
    return True


# --------------------------------------------------------------------------------------------
# slicing and orienting lane models


def slice_model(model: LaneModel, k0: int, k1: int, drop: set[int] | None = None) -> LaneModel:
    """Stations k0..k1 (inclusive) as a road of its own, s from 0, without the boundaries in `drop`."""
    drop = drop or set()
    s0, s1 = float(model.s[k0]), float(model.s[k1])
    sections: list[LaneSection] = []
    for sec in model.sections:
        a, b = max(sec.s_start, s0), min(sec.s_end, s1)
        if b - a <= 1e-9:
            continue
        ids = [i for i in sec.boundary_ids if i not in drop]
        divider = sec.divider_id if sec.divider_id in ids[1:-1] else None
        if len(ids) < 2:
            continue
        types = _kept_types(sec, ids)
        marks = {i: m for i, m in (sec.marks or {}).items() if i in ids} or None
        if sections and sections[-1].boundary_ids == ids and sections[-1].divider_id == divider \
                and sections[-1].lane_types == types and sections[-1].marks == marks:
            sections[-1].s_end = b - s0
        else:
            sections.append(LaneSection(a - s0, b - s0, ids, divider, types, marks))
    if sections:
        sections[0].s_start = 0.0
        sections[-1].s_end = s1 - s0
        for prev, nxt in zip(sections, sections[1:], strict=False):
            nxt.s_start = prev.s_end
    keep = {i for sec in sections for i in sec.boundary_ids}
    boundaries = [replace(b, t=np.asarray(b.t[k0 : k1 + 1], dtype=np.float64).copy())
                  for b in model.boundaries if b.id in keep]
    return LaneModel(s=np.asarray(model.s[k0 : k1 + 1]) - s0, reference=np.asarray(model.reference[k0 : k1 + 1]).copy(),
                     boundaries=boundaries, sections=sections, origin=model.origin, warnings=[])


def _kept_types(sec: LaneSection, ids: list[int]) -> list[str] | None:
    """Lane types of the lanes between consecutive kept boundaries `ids` (a lane that spans a dropped
    boundary takes the type of its inner part, the lane nearer the road's middle)."""
    if sec.lane_types is None:
        return None
    pos = [sec.boundary_ids.index(i) for i in ids]
    types = [sec.lane_types[a] if a == 0 else sec.lane_types[b - 1] for a, b in zip(pos[:-1], pos[1:], strict=True)]
    return None if all(t == "driving" for t in types) else types


def flip_model(model: LaneModel) -> LaneModel:
    """The same road described in the opposite direction (left and right swap)."""
    length = float(model.s[-1])
    boundaries = [replace(b, t=-np.asarray(b.t)[::-1].copy()) for b in model.boundaries]
    sections = [LaneSection(length - sec.s_end, length - sec.s_start, list(reversed(sec.boundary_ids)), sec.divider_id,
                            None if sec.lane_types is None else list(reversed(sec.lane_types)),
                            None if sec.marks is None else dict(sec.marks))
                for sec in reversed(model.sections)]
    return LaneModel(s=(length - model.s[::-1]).copy(), reference=model.reference[::-1].copy(), boundaries=boundaries,
                     sections=sections, candidates=model.candidates, origin=model.origin, warnings=list(model.warnings))


# --------------------------------------------------------------------------------------------
# geometry helpers


def _frame(model: LaneModel) -> tuple[np.ndarray, np.ndarray]:
    """Reference x, y and unit left normals at the stations."""
    ref = np.asarray(model.reference, dtype=np.float64)[:, :2]
    tan = np.gradient(ref, axis=0)
    tan /= np.maximum(np.linalg.norm(tan, axis=1), 1e-12)[:, None]
    return ref, np.stack([-tan[:, 1], tan[:, 0]], axis=1)


def _project(model: LaneModel, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest station index and left offset of points."""
    ref, normal = _frame(model)
    _, k = cKDTree(ref).query(xy)
    return k, np.sum((xy - ref[k]) * normal[k], axis=1)


def _lines(model: LaneModel, keep: dict[int, np.ndarray] | None = None) -> list[np.ndarray]:
    """World x, y of every boundary at its finite stations (or where `keep[id]` is set)."""
    ref, normal = _frame(model)
    out = []
    for b in model.boundaries:
        ks = np.flatnonzero(np.isfinite(b.t) if keep is None else keep[b.id])
        out.append(ref[ks] + normal[ks] * b.t[ks, None])
    return out


def _heading(model: LaneModel, k: int) -> float:
    ref = np.asarray(model.reference)[:, :2]
    a, b = max(k - 3, 0), min(k + 3, len(ref) - 1)
    d = ref[b] - ref[a]
    return float(np.arctan2(d[1], d[0]))


# --------------------------------------------------------------------------------------------
# the branch road


def _branch_cloud(cloud: MarkingCloud, main: LaneModel, ev: Event, kept_lines: list[np.ndarray],
                  cfg: LanesConfig, markings_cfg: MarkingsConfig) -> MarkingCloud:
    """Marking points of the branch (see the module docstring), without paint no marking line chains."""
    sec = main.sections[ev.section]
    xy = np.asarray(cloud.xyz)[:, :2]
    k, t = _project(main, xy)
    by_id = {b.id: b for b in main.boundaries}
    inner, outer = sec.boundary_ids[ev.lane], sec.boundary_ids[ev.lane + 1]
    if ev.side == "left":
        inner, outer = outer, inner
    sign = 1.0 if ev.side == "left" else -1.0
    gore = int(round(_GORE_M / max(float(main.s[1] - main.s[0]), 1e-6)))
    diverge = ev.kind == "diverge"
    t_in = by_id[inner].t[ev.k]
    ref, normal = _frame(main)
    fork = ref[ev.k] + normal[ev.k] * t_in
    # beyond the junction's cross-section (before it, for a merge): a ramp far from the road has no
    # meaningful nearest station
    h = _heading(main, ev.k)
    along = (xy - fork) @ np.array([np.cos(h), np.sin(h)])
    # a merging ramp's lines go on converging past the junction, where its lane is the road's already
    ahead = along >= 0.0 if diverge else along <= 2.0 * _GORE_M
    beside = sign * (t - t_in) > cfg.assign_distance_m
    far = _far_from(xy, kept_lines, cfg.assign_distance_m * 2)
    if diverge:
        # at the gore the branch's inner line is still the road's line: taken from 0.5 m inside it outwards
        near_gore = (k >= ev.k - 2 * gore) & (k <= ev.k + 2 * gore)
        gore_pts = near_gore & (sign * (t - t_in) > -cfg.assign_distance_m)
    else:
        # after the junction the lane is the road's: only its own two lines over the gore length (the
        # road's edge before the junction is no part of a ramp that converges at an angle)
        with np.errstate(invalid="ignore"):
            on_lane = (np.abs(t - by_id[inner].t[k]) <= cfg.assign_distance_m) | (
                np.abs(t - by_id[outer].t[k]) <= cfg.assign_distance_m)
        gore_pts = (k >= ev.k) & (k <= ev.k + gore) & on_lane
    take = (ahead & beside & far) | gore_pts
    take &= np.linalg.norm(xy - fork, axis=1) <= cfg.branch_window_m
    return _chained(cloud.subset(np.flatnonzero(take)), cfg, markings_cfg)


def _chained(cloud: MarkingCloud, cfg: LanesConfig, markings_cfg: MarkingsConfig) -> MarkingCloud:
    """The points of marking lines (candidates) whose points span `branch_min_line_m` or more."""
    from lidar2xodr.lanes.labels import _label_by_candidates
    from lidar2xodr.markings import find_candidates

    if len(cloud.xyz) == 0:
        return cloud
    cands = find_candidates(cloud.xyz, markings_cfg)
    if not cands:
        return cloud.subset(np.zeros(0, dtype=np.int64))
    xy = np.asarray(cloud.xyz)[:, :2]
    label = _label_by_candidates(xy, cands, np.arange(len(cands)), cfg)
    keep = np.zeros(len(xy), dtype=bool)
    for i, c in enumerate(cands):
        mine = label == i
        if not mine.any():
            continue
        d = np.asarray(c.directions, dtype=np.float64).mean(axis=0)
        along = xy[mine] @ (d / max(float(np.linalg.norm(d)), 1e-9))
        if float(along.max() - along.min()) >= cfg.branch_min_line_m:
            keep |= mine
    return cloud.subset(np.flatnonzero(keep))


def _orient_and_cut(branch: LaneModel, main: LaneModel, ev: Event, cfg: LanesConfig) -> tuple[LaneModel | None, str]:
    """Branch oriented like the road, cut at the junction's cross-section; None (and why) if it does not fit."""
    sec = main.sections[ev.section]
    by_id = {b.id: b for b in main.boundaries}
    t_mid = 0.5 * (by_id[sec.boundary_ids[ev.lane]].t[ev.k] + by_id[sec.boundary_ids[ev.lane + 1]].t[ev.k])
    ref, normal = _frame(main)
    fork = ref[ev.k] + normal[ev.k] * t_mid
    width = abs(float(by_id[sec.boundary_ids[ev.lane]].t[ev.k] - by_id[sec.boundary_ids[ev.lane + 1]].t[ev.k]))
    bref = np.asarray(branch.reference)[:, :2]
    d = np.linalg.norm(bref - fork, axis=1)
    k_near = int(np.argmin(d))
    if d[k_near] > 2.0 * max(width, 3.0):
        return None, f"its lines come no closer than {d[k_near]:.1f} m to the junction"
    h_main = _heading(main, ev.k)
    h_branch = _heading(branch, k_near)
    turn = np.degrees(abs((h_branch - h_main + np.pi) % (2 * np.pi) - np.pi))
    if turn > 90.0:
        branch = flip_model(branch)
        k_near = len(branch.s) - 1 - k_near
        turn = 180.0 - turn
    if turn > _MAX_HEADING_DEG:
        return None, f"it meets the road at {turn:.0f} deg"
    # the part beyond the cross-section on the road's side of the junction is cut away
    along = np.array([np.cos(h_main), np.sin(h_main)])
    ahead = (np.asarray(branch.reference)[:, :2] - ref[ev.k]) @ along
    if ev.kind == "diverge":
        idx = np.flatnonzero(ahead >= 0.0)
        k0, k1 = (int(idx[0]), len(branch.s) - 1) if len(idx) else (0, -1)
    else:
        idx = np.flatnonzero(ahead <= 0.0)
        k0, k1 = (0, int(idx[-1])) if len(idx) else (0, -1)
    if k1 - k0 < 4 or branch.s[k1] - branch.s[k0] < cfg.branch_min_length_m:
        return None, f"it is shorter than {cfg.branch_min_length_m:g} m beyond the junction"
    out = slice_model(branch, k0, k1)
    if not out.sections:
        return None, "it has no lanes beyond the junction"
    return out, ""


def _last_finite(t: np.ndarray) -> float:
    ok = np.flatnonzero(np.isfinite(t))
    return float(t[ok[-1]]) if len(ok) else float("nan")


def _lane_links(prev: LaneModel, nxt: LaneModel) -> list[tuple[int, int]]:
    """Lanes of prev's last section that go on in nxt's first section (the exporter's overlap rule; one frame)."""
    from lidar2xodr.export_opendrive import link_lanes

    def intervals(model: LaneModel, sec: LaneSection, pick: Callable[[np.ndarray], float]) -> np.ndarray:
        t = [pick(next(b.t for b in model.boundaries if b.id == i)) for i in sec.boundary_ids]
        return np.stack([t[1:], t[:-1]], axis=1)

    links = link_lanes(intervals(prev, prev.sections[-1], _last_finite),
                       intervals(nxt, nxt.sections[0], lambda t: _last_finite(t[::-1])))
    return sorted((i, j) for j, i in links.items())


def _normal_lines(model: LaneModel, cfg: LanesConfig) -> list[np.ndarray]:
    """World x, y of every boundary where both its lanes (if any) have a normal width."""
    ok = {b.id: np.isfinite(b.t) for b in model.boundaries}
    for sec in model.sections:
        ks = _stations_of(model, sec)
        for lane in range(len(sec.boundary_ids) - 1):
            w = _lane_width(model, sec, lane, ks)
            normal = w[np.isfinite(w) & (w <= cfg.max_lane_width_m)]
            if not len(normal):
                continue
            bad = ks[~(w <= float(np.median(normal)) + cfg.branch_widening_m)]
            for bid in sec.boundary_ids[lane : lane + 2]:
                ok[bid][bad] = False
    return _lines(model, ok)


def _far_from(xy: np.ndarray, lines: list[np.ndarray], dist: float) -> np.ndarray:
    pts = [p for p in lines if len(p)]
    if not pts:
        return np.ones(len(xy), dtype=bool)
    d, _ = cKDTree(np.vstack(pts)).query(xy, distance_upper_bound=dist)
    return ~np.isfinite(d)


def reframe_start(model: LaneModel, point: np.ndarray, heading: float, blend_m: float = 40.0,
                  at_end: bool = False) -> LaneModel:
    """Move the reference line's start (end) onto `point` with `heading`, blended out over `blend_m`.

    The boundaries stay where they are in the world: their offsets are taken against the moved line.
    """
    ref = np.asarray(model.reference, dtype=np.float64).copy()
    s = np.asarray(model.s, dtype=np.float64)
    old, normal_old = _frame(model)
    dist = (s - s[0]) if not at_end else (s[-1] - s)
    u = np.clip(dist / max(min(blend_m, float(s[-1] - s[0])), 1e-6), 0.0, 1.0)
    fade = 1.0 - u * u * (3.0 - 2.0 * u)
    k_end = 0 if not at_end else len(s) - 1
    shift = np.asarray(point, dtype=np.float64)[:2] - old[k_end]
    direction = np.array([np.cos(heading), np.sin(heading)])
    sign = 1.0 if not at_end else -1.0
    # a linear term turns the start tangent onto `heading` (within the blend, tangent errors of a few degrees)
    tangent = np.gradient(old, s, axis=0)[k_end]
    turn = direction * np.linalg.norm(tangent) - tangent
    ramp = dist * fade * fade
    ref[:, :2] = old + fade[:, None] * shift + sign * ramp[:, None] * turn[None, :]
    out = replace(model, reference=ref, boundaries=[])
    new, normal_new = _frame(out)
    boundaries = []
    for b in model.boundaries:
        world = old + normal_old * np.asarray(b.t)[:, None]
        boundaries.append(replace(b, t=np.sum((world - new) * normal_new, axis=1)))
    out.boundaries = boundaries
    out.sections = [replace(sec) for sec in model.sections]
    return out


def _road_end(model: LaneModel, at_end: bool) -> tuple[np.ndarray, float]:
    k = len(model.s) - 1 if at_end else 0
    return np.asarray(model.reference)[k, :2], _heading(model, k)


def build_network(cloud: MarkingCloud, main: LaneModel, lanes_cfg: LanesConfig, markings_cfg: MarkingsConfig,
                  where: str = "marking cloud") -> RoadNetwork:
    """The road `main` cut at its first junction, with the branch built from the remaining markings."""
    from lidar2xodr.lanes import build_lane_model
    from lidar2xodr.markings import find_candidates

    # a ramp is short and seen from afar: its lanes need only half the usual stable stretch
    short = lanes_cfg.model_copy(update={"min_section_length_m": 0.5 * lanes_cfg.min_section_length_m})

    def lanes_of(sub: MarkingCloud, what: str) -> LaneModel:
        return build_lane_model(sub, find_candidates(sub.xyz, markings_cfg), short, where=f"{where} ({what})")

    events = find_events(main, lanes_cfg)
    if not events:
        return RoadNetwork([main], [], list(main.warnings))
    ev = events[0]
    # the branch is measured from the markings beyond where the lines separate, and cut at the junction
    seen_from = ev
    if ev.kind == "diverge":
        ev = replace(ev, k=_separator_solid_from(cloud, main, ev, lanes_cfg))
    warnings = list(main.warnings)
    sec = main.sections[ev.section]
    lost = sec.boundary_ids[ev.lane + 1] if ev.side == "right" else sec.boundary_ids[ev.lane]
    last = len(main.s) - 1
    diverge = ev.kind == "diverge"
    xy = np.asarray(cloud.xyz)[:, :2]

    def attempt(ev: Event) -> tuple[LaneModel, LaneModel, LaneModel | None, LaneModel | None, str]:
        if diverge:
            road_a, road_b = slice_model(main, 0, ev.k), slice_model(main, ev.k, last, drop={lost})
        else:
            road_a, road_b = slice_model(main, 0, ev.k, drop={lost}), slice_model(main, ev.k, last)
        sub = _branch_cloud(cloud, main, seen_from if diverge else ev,
                            _normal_lines(road_b if diverge else road_a, lanes_cfg), lanes_cfg, markings_cfg)
        if len(sub.xyz) < 50:
            return road_a, road_b, None, None, "too few markings beside the road there"
        try:
            raw = lanes_of(sub, "branch")
        except InputError as exc:
            return road_a, road_b, None, None, exc.problem
        branch, why = _orient_and_cut(raw, main, ev, lanes_cfg)
        return road_a, road_b, raw, branch, why

    road_a, road_b, raw, branch, why = attempt(ev)
    if branch is None and diverge and ev.k != seen_from.k:
        # no branch road: the lane ends at the junction, so it is kept up to where the lines separate
        ev = seen_from
        road_a, road_b, raw, branch, why = attempt(ev)
    if branch is None and raw is not None and not diverge:
        # the joining lane's outer line was carried back along the converging ramp: the junction is
        # where the ramp's lane meets the road's
        k_meet = _meeting_station(raw, main, ev)
        if k_meet is not None and k_meet > ev.k:
            road_a2, road_b2, raw2, branch2, why2 = attempt(replace(ev, k=k_meet))
            if branch2 is not None:
                ev, road_a, road_b, branch, why = replace(ev, k=k_meet), road_a2, road_b2, branch2, why2
    if branch is None and not diverge:
        # no ramp road: the lane joins where the ramp's inner line reaches the road, not before
        k_nose = _ramp_nose(xy, main, ev)
        if k_nose is not None and k_nose > ev.k:
            ev = replace(ev, k=k_nose)
            road_a, road_b = slice_model(main, 0, ev.k, drop={lost}), slice_model(main, ev.k, last)
    if len(road_a.s) < 5 or len(road_b.s) < 5 or not road_a.sections or not road_b.sections:
        return RoadNetwork([main], [], warnings)
    label = f"the lane {'leaving' if diverge else 'joining'} on the {ev.side} at s {main.s[ev.k]:.0f} m"
    rest = road_b if diverge else road_a
    messy = [e for e in find_events(rest, lanes_cfg) if (e.k < 50 if diverge else e.k > len(rest.s) - 50)]
    if branch is not None and messy:
        # both sides leave the measured axis (a split): the continuing carriageway is measured again
        # from its own markings, without the branch's
        k_main, _ = _project(main, xy)
        side = (k_main >= ev.k - int(_GORE_M)) if diverge else (k_main <= ev.k + int(_GORE_M))
        far = _far_from(xy, _lines(branch),
                        lanes_cfg.assign_distance_m)
        try:
            again, why_again = _orient_and_cut(lanes_of(cloud.subset(np.flatnonzero(side & far)), "continuing road"),
                                               main, replace(ev, lane=_middle_lane(main, ev)), lanes_cfg)
        except InputError as exc:
            again, why_again = None, exc.problem
        if again is not None:
            point, heading = _road_end(road_a, at_end=True) if diverge else _road_end(road_b, at_end=False)
            if diverge:
                road_b = reframe_start(again, point, heading)
            else:
                road_a = reframe_start(again, point, heading, at_end=True)
        else:
            warnings.append(f"the carriageway beyond s {main.s[ev.k]:.0f} m could not be measured again "
                            f"({why_again}); it keeps the first measurement")
    roads = [road_a, road_b]
    through = _lane_links(road_a, road_b)
    if not through:
        # the road before and the road after share no lane (both measured again, or a lane count that
        # jumps): a junction of nothing is no map, the road is written whole
        return RoadNetwork([main], [], warnings + [f"{label} is not modelled as a junction: the road before "
                                                   "and after it share no lane"])
    links = [RoadLink(0, 1, through, continuation=True)]
    if branch is None:
        # the lane goes on into (comes from) the road that was not built: it ends (starts) at the
        # junction at its measured width, not in a taper
        ids = (road_a.sections[-1] if diverge else road_b.sections[0]).boundary_ids
        if lost in ids:
            lane = [ids.index(lost) - 1 if ev.side == "right" else ids.index(lost)]
            if diverge:
                links[0].open_in = lane
            else:
                links[0].open_out = lane
        warnings.append(f"{label} was not built as a road of its own ({why}): it "
                        f"{'ends' if diverge else 'starts'} at the junction at its measured width")
        return RoadNetwork(roads, links, warnings + _further(road_b if diverge else road_a, lanes_cfg))
    roads.append(branch)
    at = 0 if diverge else -1
    branch_lane = 0 if ev.side == "right" else len(branch.sections[at].boundary_ids) - 2
    if diverge:
        links.append(RoadLink(0, 2, [(ev.lane, branch_lane)], continuation=False))
    else:
        links.append(RoadLink(2, 1, [(branch_lane, ev.lane)], continuation=False))
    n_lanes = max(len(sc.boundary_ids) - 1 for sc in branch.sections)
    warnings.append(f"{label}: a {'branch' if diverge else 'ramp'} of {n_lanes} lane(s), {branch.s[-1]:.0f} m, "
                    "joined by a junction")
    return RoadNetwork(roads, links, warnings + _further(road_b if diverge else road_a, lanes_cfg))


def _separator_solid_from(cloud: MarkingCloud, main: LaneModel, ev: Event, cfg: LanesConfig) -> int:
    """The diverge's junction station moved back to where the line between the leaving lane and the road
    turns from broken to solid, if it does so within two gore lengths before the lines separate.

    A split or an exit is announced by its separator turning solid: from there on no car may change
    between the two, so the lanes belong to different roads (the esmini maps start their junctions
    there, 10-20 m before the lines separate). A line solid all along, or broken up to the gore, leaves
    the station where it was. A dash gap is any stretch over `_DASH_GAP_M` without marking points. A
    solid stretch that begins in step with the dashes before it (one dash period after the last one)
    begins with a dash: the line is known to be solid only from that dash's end on.
    """
    sec = main.sections[ev.section]
    sep = sec.boundary_ids[ev.lane] if ev.side == "right" else sec.boundary_ids[ev.lane + 1]
    t_sep = {b.id: b for b in main.boundaries}[sep].t
    if not np.isfinite(t_sep[ev.k]):
        return ev.k
    xy = np.asarray(cloud.xyz)[:, :2]
    ref, normal = _frame(main)
    k, t = _project(main, xy)
    tangent = np.stack([normal[:, 1], -normal[:, 0]], axis=1)
    s_pts = main.s[k] + np.sum((xy - ref[k]) * tangent[k], axis=1)
    s_ev = float(main.s[ev.k])
    with np.errstate(invalid="ignore"):
        on = np.abs(t - t_sep[k]) <= cfg.assign_distance_m
    on &= (s_pts >= s_ev - 6 * _GORE_M) & (s_pts <= s_ev + _DASH_GAP_M)  # two dash periods before the solid
    along = np.sort(s_pts[on])
    if len(along) < 2:
        return ev.k
    cuts = np.flatnonzero(np.diff(along) > _DASH_GAP_M)
    starts, ends = along[np.r_[0, cuts + 1]], along[np.r_[cuts, len(along) - 1]]
    inside = np.flatnonzero(starts <= s_ev)
    if len(inside) < 2 or ends[inside[-1]] < s_ev:
        return ev.k
    i = int(inside[-1])
    start = float(starts[i])
    if i >= 2:  # two dashes before it: their period (from their ends: the window cuts the first's start)
        period = float(np.median(np.diff(ends[:i])))
        if abs(start - starts[i - 1] - period) <= _DASH_GAP_M:
            start += float(np.median(ends[1:i] - starts[1:i]))
    if not (s_ev - 2 * _GORE_M <= start < s_ev - _DASH_GAP_M):
        return ev.k
    return int(np.searchsorted(main.s, start))


def _after_junction(main: LaneModel, ev: Event) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stations from the junction on, up to 3 gore lengths and within the lane's section, and the
    offsets t of the event lane's left and right lines (at every station)."""
    sec = main.sections[ev.section]
    by_id = {b.id: b for b in main.boundaries}
    ks = _stations_of(main, sec)
    gore = int(round(_GORE_M / max(float(main.s[1] - main.s[0]), 1e-6)))
    ks = ks[(ks >= ev.k) & (ks <= ev.k + 3 * gore)]
    return ks, by_id[sec.boundary_ids[ev.lane]].t, by_id[sec.boundary_ids[ev.lane + 1]].t


def _meeting_station(branch: LaneModel, main: LaneModel, ev: Event) -> int | None:
    """The station from the junction on (up to 3 gore lengths, within the lane's section) where the
    branch's reference line comes nearest the lost lane's middle, if within half a lane width."""
    ks, left_of, right_of = _after_junction(main, ev)
    if not len(ks):
        return None
    left, right = left_of[ks], right_of[ks]
    ref, normal = _frame(main)
    middle = ref[ks] + normal[ks] * (0.5 * (left + right))[:, None]
    ok = np.isfinite(middle).all(axis=1)
    if not ok.any():
        return None
    d, _ = cKDTree(np.asarray(branch.reference)[:, :2]).query(np.where(ok[:, None], middle, 0.0))
    d = np.where(ok, d, np.inf)
    best = int(np.argmin(d))
    return int(ks[best]) if d[best] <= 0.5 * abs(float(left[best] - right[best])) else None


def _ramp_nose(xy: np.ndarray, main: LaneModel, ev: Event) -> int | None:
    """The last station (within 3 gore lengths after the junction, in the lane's section) with
    `_NOSE_MIN_PER_STATION` marking points inside the joining lane, `_NOSE_MARGIN_M` from both its
    lines: the ramp's inner line, still converging onto the road's edge. None when fewer than
    `_NOSE_MIN_POINTS` lie there (a ramp whose inner edge is unpainted, or one that meets the road
    before the junction), or when none lies half a lane from the road's edge (paint hugging the edge
    is not a ramp's line crossing the lane: roadgen corridor_012 s1 has such points 0.6-0.8 m beside it).

    Where the lane's outer line was held back beyond its paint, the joining lane began at full width
    up to 25 m before the gore nose (esmini highway_merge), where the ramp still runs apart."""
    ks, left_of, right_of = _after_junction(main, ev)
    if not len(ks):
        return None
    k, t = _project(main, xy)
    on = np.isin(k, ks)
    k, t = k[on], t[on]
    left, right = left_of[k], right_of[k]
    with np.errstate(invalid="ignore"):
        inside = (t < left - _NOSE_MARGIN_M) & (t > right + _NOSE_MARGIN_M)
    if inside.sum() < _NOSE_MIN_POINTS:
        return None
    # the ramp's line crosses the lane towards the road: some of it lies half a lane from the road's edge
    edge = left if ev.side == "right" else right
    if not np.any(inside & (np.abs(t - edge) >= 0.5 * np.abs(left - right))):
        return None
    counts = np.bincount(k[inside] - ks[0], minlength=len(ks))
    held = np.flatnonzero(counts >= _NOSE_MIN_PER_STATION)
    return int(ks[0] + held[-1]) if len(held) else None


def _further(rest: LaneModel, cfg: LanesConfig) -> list[str]:
    more = find_events(rest, cfg)
    if not more:
        return []
    return [f"{len(more)} further lane(s) leaving or joining the road are not modelled as junctions (only the first "
            "one is): " + ", ".join(f"{e.kind} on the {e.side}" for e in more)]


def _middle_lane(main: LaneModel, ev: Event) -> int:
    """The lane next to the lost one on the road's side (the continuing carriageway's junction lane)."""
    n = len(main.sections[ev.section].boundary_ids) - 1
    return max(0, min(n - 1, ev.lane - 1 if ev.side == "right" else ev.lane + 1))


# --------------------------------------------------------------------------------------------
# lanes.json with a network


def save_network(network: RoadNetwork, path: str | Path) -> None:
    """lanes.json: the first road as the single-road format (so any reader of one road works), plus a
    `network` entry with every road and the junction links when there is more than one road."""
    from lidar2xodr.lanes import model_dict, save_lanes

    extra = None
    if len(network.roads) > 1 or network.links:
        extra = {
            "roads": [model_dict(r) for r in network.roads],
            "links": [{"incoming": lk.incoming, "outgoing": lk.outgoing, "lanes": [list(p) for p in lk.lanes],
                       "continuation": lk.continuation, "open_in": list(lk.open_in),
                       "open_out": list(lk.open_out)} for lk in network.links],
            "warnings": list(network.warnings),
        }
    save_lanes(network.roads[0], path, network=extra)


def load_network(path: str | Path) -> RoadNetwork:
    """Read lanes.json (with or without a network); InputError naming the file and element when malformed."""
    from lidar2xodr.lanes import model_from, read_lanes_json

    data = read_lanes_json(path)
    main = model_from(data, path)
    net = data.get("network")
    if net is None:
        return RoadNetwork([main], [], list(main.warnings))
    try:
        roads = [model_from(r, f"{path} network road {i}") for i, r in enumerate(net["roads"])]
        links = []
        for j, lk in enumerate(net["links"]):
            link = RoadLink(int(lk["incoming"]), int(lk["outgoing"]), [(int(a), int(b)) for a, b in lk["lanes"]],
                            bool(lk["continuation"]), [int(i) for i in lk.get("open_in", [])],
                            [int(i) for i in lk.get("open_out", [])])
            if not (0 <= link.incoming < len(roads) and 0 <= link.outgoing < len(roads)):
                raise InputError(f"{path} network link {j}", f"names a road outside 0..{len(roads) - 1}")
            links.append(link)
        warnings = [str(w) for w in net["warnings"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"malformed network: missing or wrong field {exc}") from None
    if not roads:
        raise InputError(path, "the network has no roads")
    return RoadNetwork(roads, links, warnings)
