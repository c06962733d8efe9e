"""Lanes near junctions and on short or divided roads: line joins, carried lines, dividers."""

from __future__ import annotations

import numpy as np
from synth_markings import SynthRoad, make_road, model_lines, polyline_distance, straight

from lidar2xodr.config import LanesConfig, MarkingsConfig
from lidar2xodr.data import LaneModel, Trajectory
from lidar2xodr.lanes import build_lane_model
from lidar2xodr.lanes.structure import _extend, _hold_to
from lidar2xodr.lanes.tracks import _continuations, _observed
from lidar2xodr.markings import find_candidates

LCFG = LanesConfig()
MCFG = MarkingsConfig()


def _build(road: SynthRoad) -> LaneModel:
    return build_lane_model(road.cloud, find_candidates(road.cloud.xyz, MCFG), LCFG)


def _rows(m: int = 200) -> np.ndarray:
    return np.full((5, m), np.nan)


def test_a_line_that_goes_on_after_a_gap_at_its_offset_is_one_line() -> None:
    t = _rows()
    k = np.arange(200)
    t[0, :90] = 1.0 + 0.002 * k[:90]  # ends at 89 ...
    t[1, 110:] = 1.0 + 0.002 * k[110:]  # ... and goes on at 110 where it would be
    t[2, :] = -3.0  # a neighbour across the gap
    t[3, 105:] = 2.6  # starts in the gap, but 1.4 m off: another line
    t[4, 100:] = 1.2 + 0.3 * (k[100:] - 100)  # runs across the road: no continuation
    root = _continuations(t, gap_max=40, tol=0.5, probe=10)
    assert root[1] == 0 and root[0] == 0
    assert root[3] == 3 and root[4] == 4 and root[2] == 2
    t[1, 110:] += 0.8  # the same gap, 0.8 m off
    assert _continuations(t, gap_max=40, tol=0.5, probe=10)[1] == 1
    t[1, 110:] -= 0.8
    assert _continuations(t, gap_max=15, tol=0.5, probe=10)[1] == 1, "gap longer than allowed"


def _carry(points_k: np.ndarray, points_t: np.ndarray) -> np.ndarray:
    """An outer solid line at -5.25 measured from station 100 on, carried back towards station 0."""
    t = np.full((3, 200), np.nan)
    t[0], t[1] = 1.75, -1.75
    t[2, 100:] = -5.25
    on = np.isfinite(t)
    seen = _observed(points_k, points_t, np.ones(len(points_k), dtype=bool), 200)
    _hold_to(t, on, 2, 100, 0, seen)
    return on[2]


def test_an_outer_line_is_carried_back_only_where_it_may_have_been_missed() -> None:
    k = np.repeat(np.arange(200), 20)
    lines = np.tile(np.r_[np.full(10, 1.75), np.full(10, -1.75)], 200)
    assert _carry(k, lines)[:100].all(), "nothing seen beyond it: not yet observed, carried"
    posts = np.arange(0, 200, 4).repeat(5)
    k2, t2 = np.r_[k, posts], np.r_[lines, np.full(len(posts), -14.0)]
    assert not _carry(k2, t2)[:100].any(), "paint seen 9 m beyond, none where it would run: absent"
    own = np.arange(0, 100).repeat(3)
    k3, t3 = np.r_[k2, own], np.r_[t2, np.full(len(own), -5.3)]
    assert _carry(k3, t3)[:100].all(), "its own paint is there, only not fitted: carried"


def _there_and_back(road: SynthRoad, shift: float) -> None:
    """The ego drives the road, turns and drives back `shift` metres left of its first pass."""
    tr = road.cloud.trajectory
    back = tr.poses[::-1].copy()
    back[:, :2, 3] += shift * back[:, :2, 1]
    times = np.r_[tr.times, tr.times[-1] + 1.0 + (tr.times - tr.times[0])]
    road.cloud.trajectory = Trajectory(times, np.concatenate([tr.poses, back]))


def test_short_two_way_road_gets_its_divider_from_a_drive_both_ways() -> None:
    """230 m of a paint-only two-way road, shorter than divider_min_length_m (300 m)."""
    road = make_road([straight(230.0)], two_way=(3.5, 3.5), ego_lane=0, gnss_noise=0.05, seed=41)
    assert all(sec.divider_id is None for sec in _build(road).sections), "one way only: no evidence"
    _there_and_back(road, 3.75)
    model = _build(road)
    assert model.s[-1] < LCFG.divider_min_length_m
    dividers = {sec.divider_id for sec in model.sections}
    assert len(dividers) == 1 and None not in dividers
    pts = road.line_xy(road.lines[0], np.arange(20.0, 210.0, 1.0))
    d = np.min([polyline_distance(pts, p) for p in model_lines(model)[dividers.pop()]], axis=0)
    assert np.sqrt(np.mean(d**2)) < 0.05, "the divider is the solid line between the directions"


def test_a_carriageway_beside_another_beyond_a_median_is_one_way_whatever_the_ego_did() -> None:
    """The ego turns and drives back in the left lane of its own carriageway (a simulator's wrong way):
    beside the broken line it drove both ways, but the other carriageway lies left beyond a median."""
    road = make_road([straight(600.0)], opposite=4.0, ego_lane=1, gnss_noise=0.05, seed=42)
    _there_and_back(road, 3.75)
    model = _build(road)
    assert all(sec.divider_id is None for sec in model.sections)
    assert {len(sec.boundary_ids) - 1 for sec in model.sections} == {3}


def test_a_line_followed_back_as_an_opening_taper_stops_inside_another_line() -> None:
    """An edge that starts after a gore (row 3, from station 200, widening from 2.5 m to 3.5 m off the
    divider) is followed back as an opening taper only where no line lies beyond it: the old edge
    (row 2, -3.5 m up to station 150) ends that. Its lane, not row 3, is the outermost there."""
    m = 300
    t = np.full((4, m), np.nan)
    t[0], t[1] = 3.5, 0.0
    t[2, :150] = -3.5
    k = np.arange(m)
    t[3, 200:] = -np.minimum(2.5 + 0.025 * (k[200:] - 200), 3.5)
    on = np.isfinite(t)
    assert _extend(t, on, 3, 200, 1, 40, 300, 3.5)
    followed = np.flatnonzero(on[3, :200])
    assert len(followed) and followed.min() == 150, "followed back until the old edge lies beyond it"


def test_a_line_carried_back_stays_beside_the_neighbour_that_keeps_its_place() -> None:
    """two_plus_one s3: a 2+1 road's centre line moves across a lane (3.5 m over 40 m) where the
    passing lane begins; that lane's line, seen from there on, was carried back at its offset to the
    moving centre line (its nearest neighbour) and ran out to the edge. It stays beside the edge."""
    m = 300
    k = np.arange(m, dtype=float)
    centre = 3.5 - np.clip((k - 100) / 40.0, 0.0, 1.0) * 3.3
    t = np.vstack([np.full(m, 7.0), np.where(k >= 140, 3.5, np.nan), centre, np.full(m, -3.5)])
    on = np.isfinite(t)
    _hold_to(t, on, 1, 140, 0)
    assert on[1, :140].all() and np.allclose(t[1, :140], 3.5), "at its offset to the edge, not the centre line"
    t, on = t[:3], on[:3].copy()  # no far edge: nothing tells which neighbour moved, the nearest is taken
    on[1, :140] = False
    _hold_to(t, on, 1, 140, 0)
    assert np.allclose(t[1, :100], 3.5 + 3.3)
