"""Travel direction of each lane from the recorded traffic: a two-way road driven one way.

Why: the lanes stage decides that a road carries both directions from the paint and the ego
(a long solid line the ego never crosses, or a line the ego drove both ways beside). A two-way road
with a broken centre line driven ONE way (the usual test drive: out and not back) has neither, so
its oncoming lane was exported as a second lane of the ego's direction: a wrong lane count and
wrong lane directions (sweep of the shared maps, 1 km drives: curves_elevation and crest-curve gave
lane count 0, boundaries RMSE 1.75-1.85 m, against 0.056 m when the 2 km drive came back). The
recording's object list settles it: oncoming cars drive in the oncoming lanes.

What: every track sample (world frame, moving faster than `traffic_min_speed_mps`, heading within
45 deg of the road's axis either way) is placed on the lane model by its nearest reference station
and its lateral offset, and counted, in metres driven, as travelling along or against s in the lane
it lies in. The ego's own trajectory counts as travel along s. In a lane section without a divider,
lanes whose traffic is against s over at least `traffic_min_m` and at least `traffic_share` of the
lane's traffic, forming a block at the section's left edge beside a block of lanes with traffic along
s, make the boundary between the blocks the divider (lane 0 of the exported road); sections without
enough traffic of their own take the divider of a neighbouring decided section when they hold that
boundary and no traffic contradicts it. A divider the lanes stage set is never moved; traffic that
contradicts it is reported as a warning. Without an object list nothing changes.

The simulator's objects.csv is the true traffic, an ideal object list; real object lists (aiMotive
boxes, A9 tracks) are noisier, which the thresholds in metres and shares absorb.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import LaneModel, Trajectory

_MAX_ANGLE_COS = np.cos(np.radians(45.0))


@dataclass
class LaneTraffic:
    """Metres driven along and against s per lane (left to right) of each lane section."""

    along: list[np.ndarray]
    against: list[np.ndarray]


def _frame(model: LaneModel) -> tuple[cKDTree, np.ndarray, np.ndarray]:
    xy = model.reference[:, :2]
    tan = np.gradient(xy, model.s, axis=0)
    tan /= np.maximum(np.linalg.norm(tan, axis=1), 1e-12)[:, None]
    return cKDTree(xy), tan, np.stack([-tan[:, 1], tan[:, 0]], axis=1)


def _place(model: LaneModel, xy: np.ndarray, heading: np.ndarray, step_m: np.ndarray, counts: LaneTraffic) -> None:
    """Add samples (xy, travel heading, metres each) to the lanes they lie in."""
    if len(xy) == 0:
        return
    tree, tan, left = _frame(model)
    _, k = tree.query(xy)
    d = xy - model.reference[k, :2]
    along_s = np.sum(d * tan[k], axis=1)
    t = np.sum(d * left[k], axis=1)
    cos = np.cos(heading) * tan[k, 0] + np.sin(heading) * tan[k, 1]
    beside = (np.abs(along_s) < 1.5) & (np.abs(cos) >= _MAX_ANGLE_COS)
    for i, sec in enumerate(model.sections):
        in_sec = beside & (model.s[k] >= sec.s_start) & (model.s[k] <= sec.s_end)
        if not in_sec.any():
            continue
        bt = np.stack([model.boundaries[b].t[k[in_sec]] for b in sec.boundary_ids], axis=1)  # left to right
        ts = t[in_sec]
        lane = np.sum(bt > ts[:, None], axis=1) - 1  # boundaries left of the sample, minus one
        inside = (lane >= 0) & (lane < len(sec.boundary_ids) - 1) & np.isfinite(bt).all(axis=1)
        w = step_m[in_sec][inside]
        forward = cos[in_sec][inside] > 0
        np.add.at(counts.along[i], lane[inside][forward], w[forward])
        np.add.at(counts.against[i], lane[inside][~forward], w[~forward])


def lane_traffic(model: LaneModel, tracks: list, ego: Trajectory | None, min_speed: float) -> LaneTraffic:
    """Metres of traffic along and against s in every lane of every section (tracks: lidar2xodr.tracks.Track).

    All samples (tracks and ego) are placed in one pass, so the road's frame is built once.
    """
    counts = LaneTraffic([np.zeros(len(s.boundary_ids) - 1) for s in model.sections],
                         [np.zeros(len(s.boundary_ids) - 1) for s in model.sections])
    xy, hdg, step = [np.zeros((0, 2))], [np.zeros(0)], [np.zeros(0)]
    for tr in tracks:
        if len(tr.times) < 2:
            continue
        ok = tr.speed >= min_speed
        xy.append(tr.xyz[ok, :2])
        hdg.append(tr.yaw[ok])
        step.append((np.abs(np.gradient(tr.times)) * tr.speed)[ok])
    if ego is not None and len(ego.times) > 1:
        seg = np.gradient(ego.positions[:, :2], axis=0)
        xy.append(ego.positions[:, :2])
        hdg.append(np.arctan2(seg[:, 1], seg[:, 0]))
        step.append(np.hypot(seg[:, 0], seg[:, 1]))
    _place(model, np.concatenate(xy), np.concatenate(hdg), np.concatenate(step), counts)
    return counts


def _split(along: np.ndarray, against: np.ndarray, cfg: LanesConfig) -> int | None:
    """Index j: lanes [0, j) carry traffic against s, lanes [j, n) along s; None when undecided."""
    total = along + against
    opposite = (against >= cfg.traffic_min_m) & (against >= cfg.traffic_share * total)
    same = (along >= cfg.traffic_min_m) & (along >= cfg.traffic_share * total)
    if not opposite.any() or not same.any():
        return None
    j = int(np.flatnonzero(opposite)[-1]) + 1
    if not opposite[:j][total[:j] >= cfg.traffic_min_m].all() or same[:j].any() or opposite[j:].any():
        return None
    return j


def apply_traffic_directions(model: LaneModel, tracks: list, ego: Trajectory | None, cfg: LanesConfig) -> list[str]:
    """Set the divider of lane sections from the traffic's directions (module doc); returns the warnings."""
    if not cfg.traffic_directions or not model.sections:
        return []
    counts = lane_traffic(model, tracks, ego, cfg.traffic_min_speed_mps)
    warnings = []
    decided: dict[int, int] = {}
    for i, sec in enumerate(model.sections):
        j = _split(counts.along[i], counts.against[i], cfg)
        if j is None:
            continue
        bid = sec.boundary_ids[j]
        if sec.divider_id is None:
            decided[i] = bid
        elif sec.divider_id != bid:
            warnings.append(f"traffic on s {sec.s_start:.0f}-{sec.s_end:.0f} m runs against the road's direction "
                            f"left of another line than the divider; the divider was kept")
    if not decided:
        return warnings
    for i, sec in enumerate(model.sections):
        if i in decided or sec.divider_id is not None:
            continue
        near = sorted(decided, key=lambda d: abs(d - i))
        bid = decided[near[0]]
        if bid not in sec.boundary_ids[1:-1]:
            continue
        pos = sec.boundary_ids.index(bid)
        if counts.along[i][:pos].max(initial=0.0) >= cfg.traffic_min_m or \
                counts.against[i][pos:].max(initial=0.0) >= cfg.traffic_min_m:
            continue
        decided[i] = bid
    for i, bid in sorted(decided.items()):
        model.sections[i].divider_id = bid
    first, last = model.sections[min(decided)], model.sections[max(decided)]
    warnings.append(f"a two-way road from the traffic's directions on s {first.s_start:.0f}-{last.s_end:.0f} m: "
                    f"oncoming vehicles left of the line between the directions (no paint or ego evidence)")
    return warnings
