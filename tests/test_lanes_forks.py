"""Exits where the edge line leaves with the exit lane and the through lane's edge turns into a
broken line: gap bridging, fork labelling and the exit lane kept at full width (issue #13)."""

from __future__ import annotations

import numpy as np

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import Boundary, LaneModel, LaneSection
from lidar2xodr.lanes.frame import Frame
from lidar2xodr.lanes.labels import _fork_curves
from lidar2xodr.lanes.structure import _bend, _open_beside_edge
from lidar2xodr.lanes.tapers import _type_by_width
from lidar2xodr.lanes.tracks import _bridge_gaps, _Lines

M = 300


def test_a_gap_is_bridged_along_the_neighbour_that_stays_parallel() -> None:
    """Line 0 is unobserved on stations 100-199; line 1 (0.3 of it observed) stays 3.5 m away, line 2
    (fully observed) diverges from line 0 there. The bridge keeps line 0 3.5 m from line 1."""
    k = np.arange(M, dtype=float)
    parallel = 0.01 * k
    edge = parallel - 3.5
    leaving = np.where(k < 100, edge, edge - 0.05 * (k - 100)).clip(min=edge - 3.5)
    t = np.vstack([np.where((k < 100) | (k >= 200), edge, edge - 1.0), parallel, leaving])
    observed = np.ones_like(t, dtype=bool)
    observed[0, 100:200] = False
    observed[1] = (k % 18) < 6
    lines = _Lines.from_dense(t, observed)
    _bridge_gaps(lines, 20, 0.5)
    assert np.allclose(lines.dense(np.array([0]))[0, 100:200], edge[100:200], atol=1e-9)


def test_fork_labelling_keeps_the_edge_on_its_course_and_carries_the_leaving_line_back() -> None:
    """An edge r bent towards a line q that is kept from station 150 and leaves it at 0.05 m/m: r's
    labelling curve follows its inner neighbour p at the offset it had well before the fork; q is
    carried back straight to where it meets that course."""
    k = np.arange(M, dtype=float)
    p = np.zeros(M)
    course = np.full(M, -3.5)
    q = np.where(k >= 150, -3.5 - 0.05 * (k - 130), np.nan)
    bent = np.where(k >= 135, -3.5 - 0.02 * (k - 135), -3.5)
    curves = np.vstack([bent, p, q])
    on = np.isfinite(curves)
    out = _fork_curves(curves, on, 2.5)
    zone = (k >= 150) & (-3.5 - 0.05 * (k - 130) > -3.5 - 2.5)
    assert np.allclose(out[0, zone], course[zone]), "the edge keeps its course through the fork"
    assert np.allclose(out[0, :130], bent[:130]) and np.allclose(out[1], p)
    back = (k >= 133) & (k < 150)
    assert np.allclose(out[2, back], -3.5 - 0.05 * (k[back] - 130)), "q goes on straight back to the edge"
    assert np.isnan(out[2, 125])


def _model(widths_exit: np.ndarray) -> LaneModel:
    """Two through lanes (ids 0-2); an exit lane beyond id 2 (outer line id 3) on stations 100-199."""
    s = np.arange(M, dtype=float)
    b = [Boundary(0, np.full(M, 3.5), "solid"), Boundary(1, np.zeros(M), "broken"),
         Boundary(2, np.full(M, -3.5), "broken"),
         Boundary(3, np.where((s >= 100) & (s < 200), -3.5 - widths_exit, np.nan), "solid")]
    secs = [LaneSection(0.0, 100.0, [0, 1, 2]), LaneSection(100.0, 200.0, [0, 1, 2, 3]),
            LaneSection(200.0, 299.0, [0, 1, 2])]
    return LaneModel(s=s, reference=np.column_stack([s, np.zeros(M), np.zeros(M)]), boundaries=b, sections=secs)


def test_a_lane_opening_from_zero_and_leaving_at_full_width_is_an_exit_lane() -> None:
    s = np.arange(M, dtype=float)
    model = _model(np.clip((s - 100) / 60.0, 0.0, 1.0) * 3.5)
    _type_by_width(model, 1, LanesConfig())
    assert [sec.lane_types for sec in model.sections] == [None, ["driving", "driving", "exit"], None]
    mirrored = _model(np.clip((s - 100) / 60.0, 0.0, 1.0) * 3.5)
    _type_by_width(mirrored, -1, LanesConfig())
    assert mirrored.sections[1].lane_types == ["driving", "driving", "entry"], "driven against s"


def test_a_full_lane_or_one_that_closes_again_is_left_alone() -> None:
    s = np.arange(M, dtype=float)
    full = _model(np.full(M, 3.5))
    _type_by_width(full, 1, LanesConfig())
    assert full.sections[1].lane_types is None, "appears at full width: a merge for the junction builder"
    both = _model(np.minimum(np.clip((s - 100) / 40.0, 0, 1), np.clip((199 - s) / 40.0, 0, 1)) * 3.5)
    _type_by_width(both, 1, LanesConfig())
    assert both.sections[1].lane_types is None, "opens and closes inside the road: an added lane"
    widening = _model(np.clip((s - 100) / 60.0, 0.0, 1.0) * 3.5 + np.clip((s - 180) / 10.0, 0.0, 2.0))
    _type_by_width(widening, 1, LanesConfig())
    assert widening.sections[1].lane_types is None, "still widening at its end: a diverge"


def test_a_lane_whose_inner_line_begins_at_its_taper_and_leaves_at_full_width_is_an_exit_lane() -> None:
    """corridor 13: the edge (id 2) moves out with the exit lane and leaves with it; the lane's inner line
    (id 3) begins at the taper's narrow end and goes on as the edge. The previous section holds no lane
    between 3 and 2, and the outer line 2 ends with the section."""
    s = np.arange(M, dtype=float)
    widths = np.clip((s - 100) / 60.0, 0.0, 1.0) * 3.5
    b = [Boundary(0, np.full(M, 3.5), "solid"), Boundary(1, np.zeros(M), "broken"),
         Boundary(2, np.where(s < 100, -3.5, np.where(s < 200, -3.5 - widths, np.nan)), "solid"),
         Boundary(3, np.where(s >= 100, -3.5, np.nan), "broken")]
    secs = [LaneSection(0.0, 100.0, [0, 1, 2]), LaneSection(100.0, 200.0, [0, 1, 3, 2]),
            LaneSection(200.0, 299.0, [0, 1, 3])]
    model = LaneModel(s=s, reference=np.column_stack([s, np.zeros(M), np.zeros(M)]), boundaries=b, sections=secs)
    _type_by_width(model, 1, LanesConfig())
    assert model.sections[1].lane_types == ["driving", "driving", "exit"]


def _edge_taper(jump: float = 0.0, left_edge: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Line 0 at 0 (inner), edge 1 at -3.5 moving out to -7 over stations 100-160, line 2 painted at
    -3.5 from station 160 (the exit lane's line, painted where the lane is full), the left edge at 3.5."""
    k = np.arange(M, dtype=float)
    edge = -3.5 - np.clip((k - 100) / 60.0, 0.0, 1.0) * 3.5
    edge[150:160] -= jump
    t = np.vstack([np.zeros(M), edge, np.where(k >= 160, -3.5, np.nan)] + ([np.full(M, 3.5)] if left_edge else []))
    return t, np.isfinite(t)


def test_a_line_painted_only_at_full_width_is_carried_back_to_where_the_edge_meets_it() -> None:
    t, on = _edge_taper()
    assert _open_beside_edge(t, on, 2, 160, 1, 120, 2.5)
    assert on[2, 101:160].all() and np.allclose(t[2, 101:160], -3.5), "at its offset to the inner line"
    assert not on[2, :100].any(), "no further than where the edge meets it"
    jumped, jumped_on = _edge_taper(jump=1.0)
    assert not _open_beside_edge(jumped, jumped_on, 2, 160, 1, 120, 2.5), "an edge that jumps is no taper"
    t, on = _edge_taper()
    assert not _open_beside_edge(t, on, 2, 160, 1, 30, 2.5), "no taper end within reach"
    assert not on[2, :160].any()
    alone, alone_on = _edge_taper(left_edge=False)
    assert not _open_beside_edge(alone, alone_on, 2, 160, 1, 120, 2.5), "either neighbour may have moved"
    moving_inner, moving_on = _edge_taper()
    k = np.arange(M, dtype=float)
    moving_inner[0] = -3.5 + np.clip((k - 100) / 60.0, 0.0, 1.0) * 3.5  # a 2+1 road's centre line moving across
    moving_inner[1] = -7.0  # the edge stays
    assert not _open_beside_edge(moving_inner, moving_on, 2, 160, 1, 120, 2.5), "the edge stayed: nothing opened"


def _recentred(inner: np.ndarray, edge: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray, Frame]:
    """Three lines given by their world y at x = 0..M-1 (NaN: absent), measured from the frame the
    lanes stage recentres on the middle of the outermost lines (inner and edge)."""
    x = np.arange(M, dtype=float)
    frame = Frame(np.column_stack([x, 0.5 * (inner + edge)]), 1.0)
    rows = []
    for y in (inner, edge, line):
        there = np.isfinite(y)
        fine = np.arange(x[there][0], x[there][-1], 0.1)
        s, t, _ = frame.project(np.column_stack([fine, np.interp(fine, x[there], y[there])]))
        rows.append(np.where((frame.s >= s[0]) & (frame.s <= s[-1]), np.interp(frame.s, s, t), np.nan))
    t = np.vstack(rows)
    return t, np.isfinite(t), frame


def test_with_no_third_line_the_world_tells_which_line_moved() -> None:
    """corridor_017 s1: a two-lane carriageway whose far edge is not seen, so only the lane line p, the
    edge e and the new lane's line b are there. The frame keeps the middle of p and e, so both swing by
    half the taper and their spacings cannot tell which one moved: p's straight world course does."""
    k = np.arange(M, dtype=float)
    edge = -3.5 - np.clip((k - 100) / 60.0, 0.0, 1.0) * 3.5
    t, on, frame = _recentred(np.zeros(M), edge, np.where(k >= 160, -3.5, np.nan))
    start = int(np.flatnonzero(on[2])[0])
    assert abs(t[0, 50] - t[0, 200]) > 1.0, "the inner line swings in the frame"
    blind_t, blind_on = t.copy(), on.copy()
    assert not _open_beside_edge(blind_t, blind_on, 2, start, 1, 120, 2.5), "without the frame: either may have moved"
    assert _open_beside_edge(t, on, 2, start, 1, 120, 2.5, frame)
    world = frame.point(np.where(on[2], t[2], 0.0))[:, 1]
    assert on[2, 110:start].all() and np.allclose(world[110:start], -3.5, atol=0.05), "at its offset to the inner line"
    assert not on[2, :95].any(), "no further than where the edge meets it"
    wiggle = 1.0 * np.sin(np.clip((k - 100) / 60.0, 0.0, 1.0) * np.pi)  # p bends too: the world cannot tell
    t, on, frame = _recentred(wiggle, edge + wiggle, np.where(k >= 160, -3.5, np.nan))
    assert not _open_beside_edge(t, on, 2, start, 1, 120, 2.5, frame)


def test_the_walk_follows_lines_the_carriageway_choice_dropped_before_the_new_line() -> None:
    """corridor_007 s2: before the exit lane's line starts, the edge and the inner line are two lanes
    apart, too wide for one, and the carriageway choice kept one of them per station; their fitted
    courses are still there, and the walk follows them."""
    t, on = _edge_taper()
    on[1, 150:160] = False
    on[0, 140:150] = False
    assert _open_beside_edge(t, on, 2, 160, 1, 120, 2.5)
    assert on[2, 101:160].all() and np.allclose(t[2, 101:160], -3.5)


def test_a_line_along_a_curve_does_not_bend_a_taper_line_does() -> None:
    """`_bend`: a line 3.5 m beside an axis on a 700 m radius stays within 5 cm of a quadratic
    over 300 m; an edge that comes in by a lane between two parallel stretches deviates by decimetres."""
    a = np.linspace(0.0, 300.0 / 700.0, M)
    frame = Frame(700.0 * np.column_stack([np.sin(a), 1.0 - np.cos(a)]), 1.0)
    n = len(frame.s)
    k = np.arange(n, dtype=float)
    t = np.vstack([np.full(n, -3.5), -3.5 - np.clip((k - 100) / 60.0, 0.0, 1.0) * 3.5])
    on = np.isfinite(t)
    assert _bend(frame, t, on, 0, np.arange(n)) < 0.05
    assert _bend(frame, t, on, 1, np.arange(n)) > 0.5


def test_a_line_found_only_once_its_lane_is_nearly_full_is_carried_along_the_inner_line() -> None:
    """highway_exit s2: the exit lane's line was first kept where its lane was 2.4 m wide, under
    `min_lane_width_m`; it was then carried back at its offset to the diverging edge, a 0.6 m lane
    beside the through lane over 100 m. A lane as wide as the narrowest lane cars use is enough."""
    from lidar2xodr.lanes.structure import _follow_tapers

    t, _ = _edge_taper()
    t[2, 142:160] = -3.5  # found from station 142, where the lane beyond is 2.45 m wide
    on = np.isfinite(t)
    # lanes 3 m wide elsewhere: over 0.8 of a lane where it starts, so `_extend` sees no taper on its own paint
    t, on = _follow_tapers(t, on, 1.0, 3.0, LanesConfig(), None, np.array([False, True, False, True]))
    assert on[2, 101:142].all() and np.allclose(t[2, 101:142], -3.5), "along the inner line, to where the edge meets it"
    assert not on[2, :100].any()


def test_a_gap_is_bridged_along_the_neighbour_that_does_not_stray_inside_it() -> None:
    """two_plus_one: the passing lane's line (row 1, at 1.7) is unobserved where the centre line (row 0)
    moves across a lane and back (stations 100-199); both the centre and the edge (row 2, at 5.2) have
    the same spacing to row 1 at the gap's two ends, and the centre is nearer. Bridged along the centre,
    the line ran out to the edge; it is bridged along the edge, which keeps its spacing to the far edge
    (row 3) inside the gap."""
    k = np.arange(M, dtype=float)
    across = np.clip(np.minimum(k - 100, 199 - k) / 30.0, 0.0, 1.0) * 3.4
    t = np.vstack([-1.7 + across, np.full(M, 1.7), np.full(M, 5.2), np.full(M, -5.2)])
    t[1, 100:200] = 0.0  # unobserved: the fit's values there are replaced by the bridge
    observed = np.ones_like(t, dtype=bool)
    observed[1, 100:200] = False
    lines = _Lines.from_dense(t, observed)
    _bridge_gaps(lines, 20, 0.5)
    assert np.allclose(lines.dense(np.array([1]))[0, 100:200], 1.7, atol=1e-9)
