"""The drive's road when the markings' own road axis misses it: the road built along stretches of the drive.

`build_lane_model` finds its road axis from the markings alone (the middles of their cross-sections,
ordered along one path). A drive through a network of streets (a town: blocks, crossings, turns at
right angles) has no one path through its markings: the axis threads through several streets and
the road built on it may lie under none of the drive (Town04's default route: 48 m of road, none of
it driven). Where the road built holds less than `_MIN_HELD_SHARE` of the drive, the road is built
again from the markings along stretches of the drive (`_WINDOW_M` of the trajectory at a time, every
half window; the markings within `_REACH_M` of it), and the road holding most of the drive is kept,
with a warning naming the stretch. A drive shorter than one stretch is left as built. The trajectory
only chooses which markings are looked at; lanes still come from the markings alone. Drives whose
road holds most of the drive are not changed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from lidar2xodr.data import LaneModel, MarkingCloud, Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.lanes.frame import Frame

_MIN_HELD_SHARE = 0.2  # a road under less than a fifth of the drive is not the drive's road
_WINDOW_M = 300.0  # a stretch of the drive: a street between two turns, a few hundred metres
_REACH_M = 25.0  # markings this far from the stretch's path: a motorway's width on either side
_SAMPLE_M = 1.0


def _path_samples(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points every `_SAMPLE_M` along the drive's path and the arc length of every trajectory pose."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    if arc[-1] <= 0:
        return xy[:1], arc
    s = np.arange(0.0, arc[-1] + 1e-9, _SAMPLE_M)
    return np.stack([np.interp(s, arc, xy[:, 0]), np.interp(s, arc, xy[:, 1])], axis=1), arc


def held_length(model: LaneModel, path: np.ndarray) -> float:
    """Metres of the sampled path that lie on the model's carriageway (between its outermost boundaries
    at their station, inside the road's length)."""
    if len(model.s) < 2 or not model.boundaries:
        return 0.0
    frame = Frame(model.reference[:, :2], float(model.s[1] - model.s[0]))
    s, t, inside = frame.project(path)
    k = np.clip(np.rint(s / (frame.s[1] - frame.s[0])).astype(np.int64), 0, len(model.s) - 1)
    rows = np.array([b.t for b in model.boundaries], dtype=np.float64)[:, k]
    fin = np.isfinite(rows)
    top = np.max(np.where(fin, rows, -np.inf), axis=0)
    bottom = np.min(np.where(fin, rows, np.inf), axis=0)
    on = inside & (fin.sum(axis=0) >= 2) & (t <= top) & (t >= bottom)
    return float(on.sum()) * _SAMPLE_M


def build_along_drive(cloud: MarkingCloud, model: LaneModel,
                      build: Callable[[MarkingCloud], LaneModel]) -> LaneModel:
    """`model`, or the road built along a stretch of the drive when that holds more of it (see the module).

    `build(sub_cloud)` builds a road from a part of the cloud (candidates found there)."""
    traj = cloud.trajectory
    if len(traj) < 2:
        return model
    xy = traj.positions[:, :2]
    path, arc = _path_samples(xy)
    total = float(len(path)) * _SAMPLE_M
    held = held_length(model, path)
    if total < _WINDOW_M or held >= _MIN_HELD_SHARE * total:
        return model
    tree = cKDTree(np.asarray(cloud.xyz)[:, :2])
    best, best_held, best_at = model, held, (0.0, 0.0)
    for a in np.arange(0.0, max(arc[-1] - 0.5 * _WINDOW_M, 0.0) + 1e-9, 0.5 * _WINDOW_M):
        poses = (arc >= a) & (arc <= a + _WINDOW_M)
        if poses.sum() < 2:
            continue
        near = np.unique(np.concatenate(tree.query_ball_point(_path_samples(xy[poses])[0], _REACH_M)))
        if len(near) < 50:
            continue
        sub = cloud.subset(near.astype(np.int64), Trajectory(traj.times[poses], traj.poses[poses]))
        try:
            road = build(sub)
        except InputError:
            continue
        got = held_length(road, path)
        if got > best_held:
            best, best_held, best_at = road, got, (float(a), float(min(a + _WINDOW_M, arc[-1])))
    if best is model:
        return model
    best.warnings.insert(0, f"the road found from all markings lies under {held:.0f} m of the {total:.0f} m drive "
                            "(a network of streets has no one road axis); built from the markings along the "
                            f"drive's stretch {best_at[0]:.0f}-{best_at[1]:.0f} m instead: {best_held:.0f} m of the "
                            "drive lie on it, the rest of the drive is not mapped")
    return best
