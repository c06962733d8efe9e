"""Junction events, slicing and the network file of `branches` on hand-made lane models."""

from __future__ import annotations

import numpy as np
import pytest

from lidar2xodr.branches import (
    _chained,
    _meeting_station,
    _separator_solid_from,
    build_network,
    find_events,
    flip_model,
    load_network,
    reframe_start,
    save_network,
    slice_model,
)
from lidar2xodr.config import Config
from lidar2xodr.data import (
    Boundary,
    GroundPlanes,
    LaneModel,
    LaneSection,
    MarkingCloud,
    RoadLink,
    RoadNetwork,
    Trajectory,
)
from lidar2xodr.errors import InputError


def _road(widen_from: float | None = None, length: float = 300.0) -> LaneModel:
    """Straight 3-boundary road along x; the right lane widens (diverges) from `widen_from`."""
    s = np.arange(0.0, length + 1e-9, 1.0)
    ref = np.stack([s, np.zeros_like(s), np.zeros_like(s)], axis=1)
    right = np.full_like(s, -3.5)
    sections = [LaneSection(0.0, length, [0, 1, 2])]
    if widen_from is not None:
        grow = s > widen_from
        right[grow] -= 0.004 * (s[grow] - widen_from) ** 2
        end = float(s[np.flatnonzero(right < -12.0)[0]])
        right[s > end] = np.nan
        sections = [LaneSection(0.0, end, [0, 1, 2]), LaneSection(end, length, [0, 1])]
    bounds = [Boundary(0, np.full_like(s, 3.5)), Boundary(1, np.zeros_like(s), "broken"), Boundary(2, right)]
    return LaneModel(s=s, reference=ref, boundaries=bounds, sections=sections)


def test_a_diverging_lane_is_an_event_at_its_gore_and_a_steady_road_is_none() -> None:
    cfg = Config().lanes
    assert find_events(_road(), cfg) == []
    events = find_events(_road(widen_from=150.0), cfg)
    assert len(events) == 1
    ev = events[0]
    assert (ev.kind, ev.side, ev.lane) == ("diverge", "right", 1)
    assert 145 <= ev.k <= 160  # where the width was last normal (3.5 + 0.3 m)


def test_an_entry_lane_appearing_at_full_width_beside_a_new_outer_line_is_a_merge() -> None:
    """An on-ramp's lane joins at the gore at full width and then tapers out as an acceleration lane:
    typed entry by the lanes stage, and still the merge the junction builder models."""
    s = np.arange(0.0, 301.0, 1.0)
    ramp_lane = np.where(s < 250, 3.5, np.maximum(3.5 - 0.07 * (s - 250), 0.0))
    bounds = [Boundary(0, np.full_like(s, 3.5)), Boundary(1, np.zeros_like(s), "broken"),
              Boundary(2, np.full_like(s, -3.5), "broken"),
              Boundary(3, np.where(s >= 100, -3.5 - ramp_lane, np.nan))]
    sections = [LaneSection(0.0, 100.0, [0, 1, 2]), LaneSection(100.0, 300.0, [0, 1, 2, 3], lane_types=None)]
    road = LaneModel(s=s, reference=np.stack([s, 0 * s, 0 * s], axis=1), boundaries=bounds, sections=sections)
    untyped = find_events(road, Config().lanes)
    road.sections[1].lane_types = ["driving", "driving", "entry"]
    typed = find_events(road, Config().lanes)
    assert [(e.kind, e.lane) for e in typed] == [("merge", 2)] == [(e.kind, e.lane) for e in untyped]


def test_slice_and_flip_keep_the_geometry() -> None:
    road = _road()
    part = slice_model(road, 100, 200, drop={2})
    assert part.s[0] == 0.0 and part.s[-1] == 100.0
    assert [sec.boundary_ids for sec in part.sections] == [[0, 1]]
    assert np.allclose(part.reference[:, 0], np.arange(100.0, 201.0))
    flipped = flip_model(road)
    assert flipped.sections[0].boundary_ids == [2, 1, 0]
    by_id = {b.id: b for b in flipped.boundaries}
    assert np.allclose(by_id[2].t, 3.5) and np.allclose(by_id[0].t, -3.5)
    assert np.allclose(flipped.reference[0, :2], road.reference[-1, :2])


def test_reframe_moves_the_start_and_keeps_the_boundaries_in_the_world() -> None:
    road = _road()
    moved = reframe_start(road, np.array([0.0, 1.0]), 0.0, blend_m=40.0)
    assert np.allclose(moved.reference[0, :2], [0.0, 1.0], atol=1e-9)
    assert np.allclose(moved.reference[60:, :2], road.reference[60:, :2])
    by_id = {b.id: b for b in moved.boundaries}
    assert abs(by_id[0].t[0] - 2.5) < 1e-3  # the line at y = 3.5 is 2.5 m left of y = 1 (same-station offset)
    assert np.allclose(by_id[0].t[60:], 3.5)


def test_network_file_round_trip_and_single_road_files(tmp_path) -> None:
    a, b = slice_model(_road(), 0, 150), slice_model(_road(), 150, 300, drop={2})
    net = RoadNetwork([a, b], [RoadLink(0, 1, [(0, 0)], True, open_in=[1]), RoadLink(0, 1, [], True, open_out=[0])],
                      ["w"])
    path = tmp_path / "lanes.json"
    save_network(net, path)
    back = load_network(path)
    assert len(back.roads) == 2 and back.links == net.links and back.warnings == ["w"]
    assert np.allclose(back.roads[1].reference, b.reference)
    save_network(RoadNetwork([a]), path)
    assert len(load_network(path).roads) == 1
    path.write_text(path.read_text().replace('"format"', '"fmt"'))
    with pytest.raises(InputError):
        load_network(path)


def test_no_event_leaves_the_road_whole() -> None:
    cfg = Config()
    road = _road()
    net = build_network(None, road, cfg.lanes, cfg.markings)  # type: ignore[arg-type]
    assert net.roads == [road] and net.links == []


def test_a_lane_into_a_branch_that_was_not_built_is_open_at_the_junction() -> None:
    """Where the diverging lane's branch cannot be built (no markings beside the road here), the lane
    still goes on into it: the continuation link names it in `open_in`, so the exporter ends it at
    its measured width instead of closing it to 0 before the junction."""
    cfg = Config()
    road = _road(widen_from=150.0)
    net = build_network(_cloud(np.zeros((0, 2))), road, cfg.lanes, cfg.markings)
    assert len(net.roads) == 2 and len(net.links) == 1
    assert net.links[0].continuation and net.links[0].open_in == [1]
    assert any("measured width" in w for w in net.warnings)


def test_a_junction_whose_roads_share_no_lane_leaves_the_road_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """The continuation of a junction links the lanes that go on; where none do (the road after it
    measured again elsewhere, seen on Town04 with a changed frame), the exporter would refuse the
    whole map ("links no lanes"). The drive's road is kept whole, with a warning, instead."""
    import lidar2xodr.branches as branches

    cfg = Config()
    road = _road(widen_from=150.0)
    monkeypatch.setattr(branches, "_lane_links", lambda a, b: [])
    net = build_network(_cloud(np.zeros((0, 2))), road, cfg.lanes, cfg.markings)
    assert net.roads == [road] and net.links == []
    assert any("share no lane" in w for w in net.warnings)


def test_a_lane_from_a_ramp_that_was_not_built_is_open_at_the_junction() -> None:
    """An on-ramp with one painted line cannot be built as a road of its own; the lane it brings
    still starts at the junction at full width: the continuation link names it in `open_out`."""
    cfg = Config()
    s = np.arange(0.0, 301.0, 1.0)
    bounds = [Boundary(0, np.full_like(s, 3.5)), Boundary(1, np.zeros_like(s), "broken"),
              Boundary(2, np.full_like(s, -3.5), "broken"), Boundary(3, np.where(s >= 100, -7.0, np.nan))]
    sections = [LaneSection(0.0, 100.0, [0, 1, 2]), LaneSection(100.0, 300.0, [0, 1, 2, 3])]
    road = LaneModel(s=s, reference=np.stack([s, 0 * s, 0 * s], axis=1), boundaries=bounds, sections=sections)
    net = build_network(_cloud(np.zeros((0, 2))), road, cfg.lanes, cfg.markings)
    assert len(net.roads) == 2 and len(net.links) == 1
    link = net.links[0]
    assert link.continuation and link.open_out == [2] and link.open_in == []
    assert net.roads[1].sections[0].boundary_ids == [0, 1, 2, 3]
    assert any("starts at the junction at its measured width" in w for w in net.warnings)


def test_a_ramp_that_was_not_built_joins_where_its_inner_line_reaches_the_road() -> None:
    """The joining lane's outer line was held back to s = 100 m beyond its paint, while the ramp's inner
    line still converges onto the road's edge up to s = 125 m (esmini highway_merge): the lane joins,
    at full width, where that line reaches the road. A ramp with an unpainted inner edge (no points
    inside the lane), or paint hugging the road's edge, joins where the lane's section begins."""
    cfg = Config()
    s = np.arange(0.0, 301.0, 1.0)
    bounds = [Boundary(0, np.full_like(s, 3.5)), Boundary(1, np.zeros_like(s), "broken"),
              Boundary(2, np.full_like(s, -3.5)), Boundary(3, np.where(s >= 100, -7.0, np.nan))]
    sections = [LaneSection(0.0, 100.0, [0, 1, 2]), LaneSection(100.0, 300.0, [0, 1, 2, 3])]
    road = LaneModel(s=s, reference=np.stack([s, 0 * s, 0 * s], axis=1), boundaries=bounds, sections=sections)
    x = np.repeat(np.arange(100.0, 125.5, 0.5), 8)
    inner = np.column_stack([x, -6.5 + 3.0 * (x - 100.0) / 25.0])  # from 3 m inside the lane to its inner line
    net = build_network(_cloud(inner), road, cfg.lanes, cfg.markings)
    assert net.links[0].open_out == [2]
    assert 120.0 <= net.roads[0].s[-1] <= 125.0
    assert [len(sec.boundary_ids) - 1 for sec in net.roads[0].sections] == [2]
    plain = build_network(_cloud(np.zeros((0, 2))), road, cfg.lanes, cfg.markings)
    assert plain.roads[0].s[-1] == 100.0
    x = np.repeat(np.arange(100.0, 110.5, 0.5), 8)
    hugging = np.column_stack([x, np.full(len(x), -4.2)])  # 0.7 m beside the road's edge: not a ramp's line
    assert build_network(_cloud(hugging), road, cfg.lanes, cfg.markings).roads[0].s[-1] == 100.0


def _cloud(xy: np.ndarray) -> MarkingCloud:
    n = len(xy)
    planes = GroundPlanes(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    return MarkingCloud(np.column_stack([xy, np.zeros(n)]), np.ones(n, dtype=np.float32), np.zeros(n, dtype=np.int32),
                        np.zeros(n), planes, Trajectory(np.zeros(0), np.zeros((0, 4, 4))))


def test_branch_points_keep_marking_lines_and_drop_short_clutter() -> None:
    """Only paint of marking lines spanning branch_min_line_m or more measures a branch: a 40 m
    solid line stays, a 2 m blob (clutter where the ego turned) goes."""
    rng = np.random.default_rng(3)
    line = np.column_stack([rng.uniform(0.0, 40.0, 3000), rng.normal(0.0, 0.05, 3000)])
    blob = rng.normal([20.0, 15.0], 0.5, (200, 2))
    cfg = Config()
    kept = _chained(_cloud(np.vstack([line, blob])), cfg.lanes, cfg.markings)
    assert len(kept.xyz) >= 0.95 * len(line)
    assert np.all(np.abs(kept.xyz[:, 1]) < 1.0), "the blob is gone"


def test_a_merging_ramp_meets_its_lane_where_its_axis_reaches_the_lane_middle() -> None:
    """The joining lane (right, between -1.75 and -5.25) was carried back to s 150; the ramp's axis,
    coming in at an angle, reaches the lane's middle (-3.5) only at s 180."""
    road = _road()
    s = road.s
    right = np.where(s >= 150.0, -5.25, np.nan)
    road.boundaries = [Boundary(0, np.full_like(s, 1.75)), Boundary(1, np.full_like(s, -1.75), "broken"),
                       Boundary(2, right)]
    road.sections = [LaneSection(0.0, 150.0, [0, 1]), LaneSection(150.0, 300.0, [0, 1, 2])]
    x = np.arange(100.0, 181.0)
    ramp = LaneModel(s=x - 100.0, reference=np.column_stack([x, -3.5 - 0.3 * (180.0 - x), 0 * x]),
                     boundaries=[], sections=[])
    ev = find_events(road, Config().lanes)[0]
    assert (ev.kind, ev.k) == ("merge", 150)
    assert abs(_meeting_station(ramp, road, ev) - 180) <= 1
    far = LaneModel(s=ramp.s, reference=ramp.reference + [0.0, -8.0, 0.0], boundaries=[], sections=[])
    assert _meeting_station(far, road, ev) is None, "an axis that never comes within half a lane"


def _separator(pieces: list[tuple[float, float]]) -> MarkingCloud:
    """Paint of the separator (t = 0) of `_road`, as dense points on the stretches given."""
    rng = np.random.default_rng(5)
    xs = np.concatenate([np.arange(a, b, 0.1) for a, b in pieces])
    return _cloud(np.column_stack([xs, rng.normal(0.0, 0.03, len(xs))]))


@pytest.mark.parametrize(("pieces", "expected"), [
    # dashes 6 m long every 18 m, solid from s 130 on (out of step with the dashes): the junction starts there
    ([(a, a + 6.0) for a in range(70, 115, 18)] + [(130.0, 200.0)], 130),
    # the solid stretch begins in step with the dashes (a dash at 124 runs into it): solid from that dash's end
    ([(a, a + 6.0) for a in range(70, 110, 18)] + [(124.0, 200.0)], 130),
    # broken up to the gore and beyond: where the lines separate
    ([(a, a + 6.0) for a in range(70, 200, 18)], None),
    # solid all along: where the lines separate
    ([(60.0, 200.0)], None),
    # turning solid 60 m before the gore: too far to be this junction's
    ([(a, a + 6.0) for a in range(20, 85, 18)] + [(90.0, 200.0)], None),
])
def test_a_diverge_starts_where_its_separator_turns_solid(pieces: list[tuple[float, float]],
                                                          expected: int | None) -> None:
    """esmini's split and exit maps start their junctions where the line between the leaving lane and the
    road turns solid, 10-20 m before the lines separate (highway_split s1: centre 0.284 -> 0.054 m)."""
    cfg = Config().lanes
    road = _road(widen_from=150.0)
    ev = find_events(road, cfg)[0]
    k = _separator_solid_from(_separator(pieces), road, ev, cfg)
    assert k == (ev.k if expected is None else expected)
    assert expected is None or ev.k - k >= 15


def test_a_diverge_whose_branch_is_not_built_keeps_its_junction_where_the_lines_separate() -> None:
    """Without a branch road the leaving lane ends at the junction: cut where its separator turns solid it
    would lose 20 m of lane the markings show (highway_split s2/s3: lane graph 0.975 -> 0.95)."""
    cfg = Config()
    road = _road(widen_from=150.0)
    ev = find_events(road, cfg.lanes)[0]
    cloud = _separator([(a, a + 6.0) for a in range(70, 115, 18)] + [(130.0, 200.0)])
    assert _separator_solid_from(cloud, road, ev, cfg.lanes) == 130 < ev.k
    net = build_network(cloud, road, cfg.lanes, cfg.markings)
    assert len(net.roads) == 2, "no branch is built from the separator's paint alone"
    assert net.roads[0].s[-1] - net.roads[0].s[0] == pytest.approx(road.s[ev.k] - road.s[0])
