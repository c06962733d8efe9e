"""Entry and exit lanes that end or begin in a taper, lane types in lanes.json and in the .xodr."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from lidar2xodr.branches import find_events
from lidar2xodr.config import Config, LanesConfig, MarkingsConfig
from lidar2xodr.data import GeoOrigin, GroundPlanes, LaneModel, MarkingCloud, Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.export_opendrive import export_opendrive
from lidar2xodr.lanes import build_lane_model, load_lanes, save_lanes
from lidar2xodr.markings import find_candidates

LCFG = LanesConfig()
LENGTH = 500.0
W = 3.75  # through lanes; left edge at +W, centre line at 0, right edge at -W


def _paint(rng: np.random.Generator, t_of: Callable[[np.ndarray], np.ndarray], s0: float, s1: float,
           width: float, dash: float | None = None, gap: float = 0.0) -> np.ndarray:
    """(s, t) points of a painted line between s0 and s1 (dashes `dash` long with `gap` between)."""
    if dash is None:
        spans = [(s0, s1)]
    else:
        starts = np.arange(s0, s1, dash + gap)
        spans = [(a, min(a + dash, s1)) for a in starts]
    out = []
    for a, b in spans:
        s = rng.uniform(a, b, rng.poisson(150.0 * width * (b - a)))
        out.append(np.stack([s, t_of(s) + rng.uniform(-width / 2, width / 2, len(s))], axis=1))
    return np.concatenate(out)


def _cloud(extra: list[np.ndarray], rng: np.random.Generator, right_dash: float | None = None) -> MarkingCloud:
    """A straight two-lane carriageway along x (solid left edge, broken centre line, right edge solid or
    broken with `right_dash` dashes), the `extra` (s, t) points, strays, and an ego in the left lane."""
    parts = [
        _paint(rng, lambda s: np.full_like(s, W), 0.0, LENGTH, 0.30),
        _paint(rng, np.zeros_like, 3.0, LENGTH, 0.15, 6.0, 12.0),
        _paint(rng, lambda s: np.full_like(s, -W), 0.0, LENGTH, 0.30, right_dash, right_dash or 0.0),
        np.stack([rng.uniform(0.0, LENGTH, 150), rng.uniform(-12.0, 8.0, 150)], axis=1),
        *extra,
    ]
    st = np.concatenate(parts)
    xyz = np.column_stack([st[:, 0], st[:, 1], 0.01 * st[:, 0]]) + rng.normal(0.0, 0.03, (len(st), 3))
    n_scans = int(LENGTH / 2.5) + 1
    x_ego = np.arange(n_scans) * 2.5
    poses = np.tile(np.eye(4), (n_scans, 1, 1))
    poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = x_ego, 0.5 * W, 0.01 * x_ego
    scan = np.clip(((st[:, 0] - rng.uniform(5.0, 60.0, len(st))) / 2.5).astype(int), 0, n_scans - 1)
    order = np.lexsort((xyz[:, 0], scan))
    times = x_ego / 30.0
    return MarkingCloud(xyz[order], np.full(len(xyz), 0.8, dtype=np.float32), scan[order].astype(np.int32),
                        times[scan[order]], GroundPlanes(times, np.tile([0.0, 0.0, 1.0], (n_scans, 1)),
                                                         poses[:, :3, 3].copy()),
                        Trajectory(times, poses), GeoOrigin())


def _taper_line(s_wide: float, s_meet: float, width: float) -> Callable[[np.ndarray], np.ndarray]:
    """Offset of a straight line `width` beyond the right edge at s_wide that meets it at s_meet."""
    return lambda s: -W - width * (s - s_meet) / (s_wide - s_meet)


def _build(cloud: MarkingCloud) -> LaneModel:
    return build_lane_model(cloud, find_candidates(cloud.xyz, MarkingsConfig()), LCFG)


def _station(model: LaneModel, x: float) -> float:
    """Model station of the point of the straight road at x."""
    return float(model.s[int(np.argmin(np.abs(np.asarray(model.reference)[:, 0] - x)))])


def _width(model: LaneModel, sec_index: int, lane: int, s: float) -> float:
    sec = model.sections[sec_index]
    k = int(np.argmin(np.abs(model.s - s)))
    t = {b.id: b.t for b in model.boundaries}
    return float(t[sec.boundary_ids[lane]][k] - t[sec.boundary_ids[lane + 1]][k])


@pytest.fixture(scope="module")
def entry() -> tuple[LaneModel, float, float]:
    """An acceleration lane first seen 3.5 m wide at x = 200 whose solid edge closes onto the right
    edge (broken 6 m / 6 m beside it) at x = 260 (3.3 deg); the edge goes on as the road's edge.
    The right edge is broken along the whole road, so before x = 200 the lane is there too, its
    outer border unseen (a broken line has a lane on both sides); after the taper it is not."""
    rng = np.random.default_rng(5)
    line = _paint(rng, _taper_line(200.0, 260.0, 3.5), 200.0, 258.0, 0.30)
    cloud = _cloud([line], rng, right_dash=6.0)
    model = _build(cloud)
    return model, _station(model, 200.0), _station(model, 260.0)


def test_entry_taper_is_an_entry_lane_that_closes_to_zero(entry: tuple[LaneModel, float, float]) -> None:
    model, s_wide, s_meet = entry
    counts = [len(sec.boundary_ids) - 1 for sec in model.sections]
    assert counts == [3, 3, 2]
    first, taper, last = model.sections
    assert taper.lane_types == ["driving", "driving", "entry"]
    assert first.lane_types == ["driving", "driving", "entry"], "the entry lane before its outer line is seen"
    kinds = {b.id: b.mark_type for b in model.boundaries}
    assert kinds[first.boundary_ids[-1]] == "none" and kinds[taper.boundary_ids[-1]] == "solid"
    assert last.lane_types is None, "no lane beyond the broken edge where the taper closed"
    assert abs(taper.s_start - s_wide) < 3.0, "the lane starts where its outer line is first seen"
    assert abs(taper.s_end - s_meet) < 3.0, "and ends where it meets the edge"
    assert _width(model, 1, 2, taper.s_start) == pytest.approx(3.5, abs=0.2)
    assert _width(model, 1, 2, taper.s_end - 1.0) < 0.15
    assert _width(model, 1, 2, 0.5 * (taper.s_start + taper.s_end)) == pytest.approx(1.75, abs=0.2)
    for j, sec in enumerate(model.sections):
        for lane in (0, 1):
            assert _width(model, j, lane, 0.5 * (sec.s_start + sec.s_end)) == pytest.approx(W, abs=0.1)
    assert any(w.startswith("entry lane on the right") and "3.3 deg" in w for w in model.warnings)
    assert find_events(model, LCFG) == [], "a taper lane of the road is no ramp junction"


def test_exit_taper_is_an_exit_lane_that_opens_from_zero() -> None:
    """The mirror image: a solid line leaves the right edge at x = 240 and is last seen 3.5 m out at
    x = 300; beyond x = 300 the exit lane goes on beside the broken edge, its outer border unseen."""
    rng = np.random.default_rng(6)
    line = _paint(rng, _taper_line(300.0, 240.0, 3.5), 242.0, 300.0, 0.30)
    model = _build(_cloud([line], rng, right_dash=6.0))
    assert [len(sec.boundary_ids) - 1 for sec in model.sections] == [2, 3, 3]
    first, taper, last = model.sections
    assert taper.lane_types == ["driving", "driving", "exit"]
    assert first.lane_types is None, "no lane beyond the broken edge before the exit lane opens"
    assert last.lane_types == ["driving", "driving", "exit"]
    assert {b.id: b.mark_type for b in model.boundaries}[last.boundary_ids[-1]] == "none"
    assert abs(taper.s_start - _station(model, 240.0)) < 3.0
    assert abs(taper.s_end - _station(model, 300.0)) < 3.0
    assert _width(model, 1, 2, taper.s_start) < 0.15
    assert _width(model, 1, 2, taper.s_end - 1.0) == pytest.approx(3.5, abs=0.2)
    assert any(w.startswith("exit lane on the right") for w in model.warnings)


def test_guard_rail_beside_the_edge_and_clutter_make_no_lane() -> None:
    """A guard-rail-like line 2 m outside the solid edge that never meets it, a slanted line that stays
    4-5 m out (the far side of a ramp), and a crooked line that comes close: none is a lane."""
    rng = np.random.default_rng(7)
    rail = _paint(rng, lambda s: np.full_like(s, -W - 2.0), 0.0, LENGTH, 0.20)
    far = _paint(rng, lambda s: -W - 5.0 + 0.02 * (s - 100.0), 100.0, 150.0, 0.30)
    crooked = _paint(rng, lambda s: -W - 1.5 - 1.2 * np.sin((s - 300.0) / 6.0), 300.0, 360.0, 0.30)
    model = _build(_cloud([rail, far, crooked], rng))
    assert [len(sec.boundary_ids) - 1 for sec in model.sections] == [2]
    assert all(sec.lane_types is None for sec in model.sections)
    assert not any("entry" in w or "exit" in w for w in model.warnings)


def test_a_taper_too_short_for_a_section_is_not_a_lane_but_noted() -> None:
    """A converging line seen over 25 m (22 m of it over 0.5 m from the edge) that meets the solid
    edge 27 m after it is first seen."""
    rng = np.random.default_rng(8)
    line = _paint(rng, _taper_line(200.0, 227.0, 2.7), 200.0, 225.0, 0.30)
    model = _build(_cloud([line], rng))
    assert [len(sec.boundary_ids) - 1 for sec in model.sections] == [2]
    assert any("makes no lane: shorter than 30 m" in w for w in model.warnings)


def test_lane_types_round_trip_and_reach_the_xodr(entry: tuple[LaneModel, float, float], tmp_path: Path) -> None:
    model, _, _ = entry
    save_lanes(model, tmp_path / "lanes.json")
    again = load_lanes(tmp_path / "lanes.json")
    assert [sec.lane_types for sec in again.sections] == [sec.lane_types for sec in model.sections]
    export_opendrive(again, None, Config().export, tmp_path / "map.xodr")
    from lxml import etree

    root = etree.parse(str(tmp_path / "map.xodr")).getroot()
    kinds = [[lane.get("type") for lane in sec.iter("lane") if lane.get("id") != "0"]
             for sec in root.iter("laneSection")]
    assert kinds == [["driving", "driving", "entry"], ["driving", "driving", "entry"], ["driving"] * 2]
    sections = list(root.iter("laneSection"))
    before, taper = ([lane for lane in sec.iter("lane") if lane.get("type") == "entry"][0] for sec in sections[:2])
    assert before.find("roadMark").get("type") == "none", "its outer border was not seen before the taper"
    assert float(before.find("width").get("a")) == pytest.approx(W, abs=0.1), "as wide as its neighbour"
    assert taper.find("link/predecessor") is not None, "one lane through both sections"


def test_old_lanes_json_loads_driving_and_bad_types_are_rejected(
    entry: tuple[LaneModel, float, float], tmp_path: Path
) -> None:
    model, _, _ = entry
    save_lanes(model, tmp_path / "lanes.json")
    data = json.loads((tmp_path / "lanes.json").read_text())
    for sec in data["sections"]:
        del sec["lane_types"]
    (tmp_path / "old.json").write_text(json.dumps(data))
    assert all(sec.lane_types is None for sec in load_lanes(tmp_path / "old.json").sections)
    data["sections"][1]["lane_types"] = ["driving", "ramp"]
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match="section 1"):
        load_lanes(tmp_path / "bad.json")


@pytest.mark.slow
def test_aimotive_sample_has_two_through_lanes_and_the_entry_lane(shared_data: Path) -> None:
    """Real drive (extraction ~20 s). The camera frames show the ego in the left of two lanes; right of
    the short-dash line an acceleration lane (already there in the first frame, 43) whose solid edge
    converges onto that line (frame 65, ego at x ~ 44 m) and is gone by frame 92 (x ~ 98 m). LiDAR
    sees that edge from x ~ 44 m; it meets the short-dash line near x ~ 79 m. Before, the lane is
    built beside the short-dash line with its outer border unseen."""
    from test_extraction import aimotive_cloud

    cloud, _ = aimotive_cloud(shared_data / "lidar" / "aimotive_highway_sample")
    model = build_lane_model(cloud, find_candidates(cloud.xyz, MarkingsConfig()), LCFG)
    counts = [len(sec.boundary_ids) - 1 for sec in model.sections]
    assert counts == [3, 3, 2]
    before, taper, _ = model.sections
    assert before.lane_types == taper.lane_types == ["driving", "driving", "entry"]
    assert {b.id: b.mark_type for b in model.boundaries}[before.boundary_ids[-1]] == "none"
    x = np.asarray(model.reference)[:, 0]  # the drive's frame: x = 0 at the first scan, along the drive
    assert 35.0 <= np.interp(taper.s_start, model.s, x) <= 55.0 and 70.0 <= np.interp(taper.s_end, model.s, x) <= 90.0
    t = {b.id: b.t for b in model.boundaries}
    for sec in model.sections:
        k = (model.s >= sec.s_start) & (model.s < sec.s_end)
        for lane in (0, 1):
            w = t[sec.boundary_ids[lane]][k] - t[sec.boundary_ids[lane + 1]][k]
            assert np.all((w >= 3.2) & (w <= 4.0)), "two through lanes 3.2-4.0 m wide"
    k = (model.s >= taper.s_start) & (model.s < taper.s_end)
    w = t[taper.boundary_ids[2]][k] - t[taper.boundary_ids[3]][k]
    assert w[0] > 2.5 and w[-1] < 0.1 and np.all(np.diff(w) <= 1e-9), "the entry lane narrows to zero"
