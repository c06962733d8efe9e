"""Lane directions from the recorded traffic: oncoming tracks make a two-way road, nothing else does."""

from __future__ import annotations

import numpy as np

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import Boundary, LaneModel, LaneSection, Trajectory
from lidar2xodr.lane_directions import apply_traffic_directions, lane_traffic
from lidar2xodr.tracks import Track

CFG = LanesConfig()


def _model(lanes: int = 2, divider: int | None = None) -> LaneModel:
    """A gently curved road along x, lanes of 3.5 m, boundaries 0..lanes from left to right."""
    s = np.arange(0.0, 601.0, 1.0)
    ref = np.stack([s, 0.0002 * (s - 300.0) ** 2, np.zeros_like(s)], axis=1)
    ts = [lanes * 1.75 - 3.5 * i for i in range(lanes + 1)]
    bounds = [Boundary(i, np.full(len(s), t), "broken" if 0 < i < lanes else "solid") for i, t in enumerate(ts)]
    return LaneModel(s=s, reference=ref, boundaries=bounds,
                     sections=[LaneSection(0.0, 600.0, list(range(lanes + 1)), divider)])


def _track(model: LaneModel, tid: str, t_off: float, forward: bool, speed: float = 20.0) -> Track:
    """A car at lateral offset t_off driving the whole road along (forward) or against s."""
    xy = model.reference[:, :2]
    tan = np.gradient(xy, model.s, axis=0)
    tan /= np.linalg.norm(tan, axis=1)[:, None]
    left = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    pts = xy + t_off * left
    hdg = np.arctan2(tan[:, 1], tan[:, 0])
    if not forward:
        pts, hdg = pts[::-1], hdg[::-1] + np.pi
    times = np.arange(len(pts)) / speed
    return Track(tid, "car", np.array([4.5, 1.8, 1.5]), times, np.column_stack([pts, np.zeros(len(pts))]), hdg,
                 np.full(len(pts), speed))


def _ego(model: LaneModel, t_off: float) -> Trajectory:
    tr = _track(model, "ego", t_off, True)
    poses = np.tile(np.eye(4), (len(tr.times), 1, 1))
    poses[:, :3, 3] = tr.xyz
    return Trajectory(tr.times, poses)


def test_oncoming_traffic_in_the_left_lane_makes_the_centre_line_the_divider() -> None:
    model = _model()
    counts = lane_traffic(model, [_track(model, "a", 1.75, False)], None, CFG.traffic_min_speed_mps)
    assert counts.against[0][0] > 500 and counts.along[0].sum() == 0 and counts.against[0][1] == 0
    warnings = apply_traffic_directions(model, [_track(model, "a", 1.75, False)], _ego(model, -1.75), CFG)
    assert model.sections[0].divider_id == 1 and any("two-way" in w for w in warnings)


def test_same_direction_traffic_or_no_traffic_changes_nothing() -> None:
    model = _model(lanes=3)
    tracks = [_track(model, "a", 3.5, True), _track(model, "b", 0.0, True)]
    assert apply_traffic_directions(model, tracks, _ego(model, -3.5), CFG) == []
    assert model.sections[0].divider_id is None
    assert apply_traffic_directions(model, [], None, CFG) == [] and model.sections[0].divider_id is None


def test_oncoming_traffic_right_of_same_direction_traffic_is_no_divider() -> None:
    """A wrong-way driver on the right (or tracks in the wrong frame) cannot make lane 0."""
    model = _model()
    apply_traffic_directions(model, [_track(model, "a", -1.75, False)], _ego(model, 1.75), CFG)
    assert model.sections[0].divider_id is None


def test_a_short_oncoming_glimpse_decides_nothing() -> None:
    model = _model()
    short = _track(model, "a", 1.75, False)
    keep = slice(0, int(CFG.traffic_min_m * 0.5))
    short = Track("a", "car", short.dims, short.times[keep], short.xyz[keep], short.yaw[keep], short.speed[keep])
    apply_traffic_directions(model, [short], _ego(model, -1.75), CFG)
    assert model.sections[0].divider_id is None


def test_a_divider_from_paint_is_kept_and_contradicting_traffic_reported() -> None:
    model = _model(lanes=3, divider=2)
    tracks = [_track(model, "a", 3.5, False), _track(model, "b", 0.0, True)]
    warnings = apply_traffic_directions(model, tracks, _ego(model, -3.5), CFG)
    assert model.sections[0].divider_id == 2 and any("divider was kept" in w for w in warnings)
