"""`compare`'s lane-graph agreement: a map whose links route a vehicle out of its lane scores low.

The maps are written here: a motorway of two right lanes with an exit (a junction whose connecting
roads overlap at the gore), the same road with a 0.54 m sliver lane between its two through lanes
(issue #13's highway_exit build), and copies with a wrong or missing link.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from lidar2xodr.config import EvaluationConfig
from lidar2xodr.evaluation import DRIVING_TYPES, compare_maps
from lidar2xodr.lane_graph import build_lane_graph
from lidar2xodr.opendrive import OpenDriveMap

CFG = EvaluationConfig()
LANE = 3.5
SLIVER = 0.54


def _lane(lid: int, width: float, kind: str = "driving", pred: int | None = None, succ: int | None = None,
          widening: float = 0.0) -> str:
    link = "".join(f'<{tag} id="{v}"/>' for tag, v in (("predecessor", pred), ("successor", succ)) if v is not None)
    return (f'<lane id="{lid}" type="{kind}" level="false"><link>{link}</link>'
            f'<width sOffset="0" a="{width}" b="{widening}" c="0" d="0"/></lane>')


def _section(s: float, right: list[str], left: list[str] | None = None) -> str:
    left_xml = f"<left>{''.join(left)}</left>" if left else ""
    return (f'<laneSection s="{s}">{left_xml}<center><lane id="0" type="none" level="false"/></center>'
            f"<right>{''.join(right)}</right></laneSection>")


def _road(rid: str, length: float, sections: list[str], x: float = 0.0, y: float = 0.0, hdg: float = 0.0,
          geom: str = "<line/>", pred: tuple[str, str, str] | None = None, succ: tuple[str, str, str] | None = None,
          junction: str = "-1", offset: float = 0.0) -> str:
    links = "".join(
        f'<{tag} elementType="{kind}" elementId="{eid}"' + (f' contactPoint="{cp}"/>' if cp else "/>")
        for tag, ref in (("predecessor", pred), ("successor", succ)) if ref is not None
        for kind, eid, cp in [ref]
    )
    return (f'<road id="{rid}" length="{length}" junction="{junction}" rule="RHT"><link>{links}</link>'
            f'<planView><geometry s="0" x="{x}" y="{y}" hdg="{hdg}" length="{length}">{geom}</geometry></planView>'
            f'<lanes><laneOffset s="0" a="{offset}" b="0" c="0" d="0"/>{"".join(sections)}</lanes></road>')


def _write(path: Path, *parts: str) -> Path:
    path.write_text('<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header revMajor="1" revMinor="6" '
                    f'name="t" version="1"/>{"".join(parts)}</OpenDRIVE>\n', encoding="utf-8")
    return path


EXIT_K = -0.01  # the exit's connecting road curves right at R = 100 m
EXIT_L = 30.0


def _exit_map(path: Path, through_right_link: bool = True) -> Path:
    """Road 1 (300 m, lanes -1, -2) -> junction 100 -> road 2 (through) and, from lane -2, road 3 (exit).

    Connecting road 10 carries both lanes on; connecting road 11 leaves from lane -2 (its reference
    line on the lane -1/-2 border), curving right, and overlaps road 10's lane -2 at the gore.
    `through_right_link=False` drops the laneLink -2 -> -2 of road 10: the right lane then routes
    only into the exit.
    """
    h = EXIT_K * EXIT_L
    ex = 300.0 + math.sin(h) / EXIT_K
    ey = -LANE + (1.0 - math.cos(h)) / EXIT_K
    links = '<laneLink from="-1" to="-1"/>' + ('<laneLink from="-2" to="-2"/>' if through_right_link else "")
    junction = (f'<junction id="100" name="exit"><connection id="0" incomingRoad="1" connectingRoad="10" '
                f'contactPoint="start">{links}</connection><connection id="1" incomingRoad="1" '
                'connectingRoad="11" contactPoint="start"><laneLink from="-2" to="-1"/></connection></junction>')
    return _write(
        path,
        _road("1", 300.0, [_section(0, [_lane(-1, LANE), _lane(-2, LANE)])], succ=("junction", "100", "")),
        _road("10", 20.0, [_section(0, [_lane(-1, LANE, pred=-1, succ=-1),
                                        _lane(-2, LANE, pred=-2 if through_right_link else None, succ=-2)])],
              x=300.0, pred=("road", "1", "end"), succ=("road", "2", "start"), junction="100"),
        _road("11", EXIT_L, [_section(0, [_lane(-1, LANE, pred=-2, succ=-1)])], x=300.0, y=-LANE,
              geom=f'<arc curvature="{EXIT_K}"/>', pred=("road", "1", "end"), succ=("road", "3", "start"),
              junction="100"),
        _road("2", 300.0, [_section(0, [_lane(-1, LANE, pred=-1), _lane(-2, LANE, pred=-2)])], x=320.0,
              pred=("junction", "100", "")),
        _road("3", 200.0, [_section(0, [_lane(-1, LANE, pred=-1)])], x=ex, y=ey, hdg=h,
              pred=("junction", "100", "")),
        junction,
    )


def _two_lane_road(path: Path) -> Path:
    """1000 m, two lanes each way, one lane section."""
    both = [_lane(-1, LANE), _lane(-2, LANE)]
    return _write(path, _road("1", 1000.0, [_section(0, both, [_lane(1, LANE), _lane(2, LANE)])]))


def _sliver_road(path: Path, links_follow_ids: bool = True) -> Path:
    """The two-lane road with a SLIVER-wide lane -2 between the through lanes over s = 350..650.

    `links_follow_ids`: the through lane -2 links into the sliver (-2) and the outer through lane -3
    has no predecessor, as a builder numbering lanes from the centre writes it (issue #13). Otherwise
    the links are right: -2 -> -3 -> -2, the sliver a lane of its own without links.
    """
    left = [_lane(1, LANE), _lane(2, LANE)]
    if links_follow_ids:
        a = [_lane(-1, LANE, succ=-1), _lane(-2, LANE, succ=-2)]
        b = [_lane(-1, LANE, pred=-1, succ=-1), _lane(-2, SLIVER, pred=-2, succ=-2), _lane(-3, LANE)]
        c = [_lane(-1, LANE, pred=-1), _lane(-2, LANE, pred=-2)]
    else:
        a = [_lane(-1, LANE, succ=-1), _lane(-2, LANE, succ=-3)]
        b = [_lane(-1, LANE, pred=-1, succ=-1), _lane(-2, SLIVER), _lane(-3, LANE, pred=-2, succ=-2)]
        c = [_lane(-1, LANE, pred=-1), _lane(-2, LANE, pred=-3)]
    left_links = [_lane(1, LANE, pred=1, succ=1), _lane(2, LANE, pred=2, succ=2)]
    return _write(path, _road("1", 1000.0, [_section(0, a, left_links), _section(350, b, left_links),
                                            _section(650, c, left)]))


def test_graph_links_follow_travel_direction(tmp_path: Path) -> None:
    g = build_lane_graph(OpenDriveMap.load(_exit_map(tmp_path / "exit.xodr")), DRIVING_TYPES)
    succ = {g.keys[i]: {g.keys[j] for j in g.succ[i]} for i in range(len(g.keys))}
    assert succ[("1", 0, -2)] == {("10", 0, -2), ("11", 0, -1)}
    assert succ[("1", 0, -1)] == {("10", 0, -1)}
    assert succ[("11", 0, -1)] == {("3", 0, -1)} and succ[("10", 0, -2)] == {("2", 0, -2)}
    assert succ[("2", 0, -1)] == set()
    road = OpenDriveMap.load(_sliver_road(tmp_path / "sliver.xodr"))
    g = build_lane_graph(road, DRIVING_TYPES)
    succ = {g.keys[i]: {g.keys[j] for j in g.succ[i]} for i in range(len(g.keys))}
    assert succ[("1", 0, -2)] == {("1", 1, -2)} and succ[("1", 1, -3)] == set()
    # left lanes travel against s: their successor is the section before
    assert succ[("1", 2, 1)] == {("1", 1, 1)} and succ[("1", 1, 2)] == {("1", 0, 2)}


def test_identical_junction_map_agrees_fully(tmp_path: Path) -> None:
    path = _exit_map(tmp_path / "exit.xodr")
    graph = compare_maps(path, path, CFG)["lane_graph"]
    assert graph["agreement"] == pytest.approx(1.0)
    assert graph["breaks"] == 0 and graph["wrong_m"] == pytest.approx(0.0, abs=1e-6)
    # both lanes of roads 1, 10, 2 and the exit's connecting road and road 3 (the arc's centre line is longer)
    assert graph["eval_length_m"] == pytest.approx(2 * 620 + EXIT_L * (1 + 5.25 * 0.01) + 200, rel=0.01)


def test_identical_shared_junction_map_agrees_fully(shared_data: Path) -> None:
    path = shared_data / "maps" / "asam" / "Ex_Entry_Exit.xodr"
    graph = compare_maps(path, path, CFG)["lane_graph"]
    assert graph["agreement"] == pytest.approx(1.0) and graph["breaks"] == 0
    assert graph["eval_length_m"] > 1000


def test_sliver_lane_with_wrong_links_scores_low(tmp_path: Path) -> None:
    ref = _two_lane_road(tmp_path / "ref.xodr")
    m = compare_maps(_sliver_road(tmp_path / "sliver.xodr"), ref, CFG)
    graph = m["lane_graph"]
    assert m["lane_count_agreement"] >= 0.98  # what the old measure saw
    assert graph["breaks"] >= 1
    assert graph["agreement"] < 0.95
    # the outer through lane is off its route over the 300 m sliver stretch, nothing else is wrong
    assert graph["off_route_m"] == pytest.approx(300.0, abs=1.0)
    assert graph["wrong_m"] == pytest.approx(300.0, abs=1.0)


def test_sliver_lane_with_right_links_routes_through(tmp_path: Path) -> None:
    """The control: the same geometry, links that keep the outer lane on its through lane."""
    ref = _two_lane_road(tmp_path / "ref.xodr")
    graph = compare_maps(_sliver_road(tmp_path / "sliver.xodr", links_follow_ids=False), ref, CFG)["lane_graph"]
    assert graph["breaks"] == 0 and graph["agreement"] == pytest.approx(1.0)


def test_right_lane_routed_into_the_exit_scores_low(tmp_path: Path) -> None:
    ref = _exit_map(tmp_path / "ref.xodr")
    m = compare_maps(_exit_map(tmp_path / "gen.xodr", through_right_link=False), ref, CFG)
    graph = m["lane_graph"]
    assert m["lane_count_agreement"] == pytest.approx(1.0)  # geometry and lane count are all right
    assert graph["breaks"] == 1
    # the right through lane is wrong from the gore on: most of road 10 and all of road 2
    assert 300.0 < graph["wrong_m"] < 321.0
    assert graph["agreement"] < 0.8


def test_narrow_lane_counts_only_as_a_taper(tmp_path: Path) -> None:
    """A generated lane 1.74 m wide along a 300 m road holds the reference lane's centre: only its
    first and last 60 m are a taper."""
    ref = _write(tmp_path / "ref.xodr", _road("1", 300.0, [_section(0, [_lane(-1, LANE)])]))
    gen = _write(tmp_path / "gen.xodr", _road("1", 300.0, [_section(0, [_lane(-1, 1.74)])], offset=-0.9))
    graph = compare_maps(gen, ref, CFG)["lane_graph"]
    assert graph["agreement"] == pytest.approx(120.0 / 300.0, abs=0.01)
    assert graph["narrow_m"] == pytest.approx(180.0, abs=1.5) and graph["breaks"] == 0
    wide = _write(tmp_path / "wide.xodr", _road("1", 300.0, [_section(0, [_lane(-1, 1.76)])], offset=-0.9))
    assert compare_maps(wide, ref, CFG)["lane_graph"]["agreement"] == pytest.approx(1.0)


def test_coverage_and_gaps(tmp_path: Path) -> None:
    """Only the stretch the generated map covers is evaluated; a gap in it is wrong, not a break."""
    ref = _write(tmp_path / "ref.xodr", _road("1", 300.0, [_section(0, [_lane(-1, LANE), _lane(-2, LANE)])]))
    lanes = [_section(0, [_lane(-1, LANE), _lane(-2, LANE)])]
    half = _write(tmp_path / "half.xodr", _road("1", 150.0, lanes))
    graph = compare_maps(half, ref, CFG)["lane_graph"]
    assert graph["agreement"] == pytest.approx(1.0)
    assert graph["eval_length_m"] == pytest.approx(300.0, abs=2.0)
    gap = _write(tmp_path / "gap.xodr", _road("1", 100.0, lanes), _road("2", 100.0, lanes, x=200.0))
    graph = compare_maps(gap, ref, CFG)["lane_graph"]
    assert graph["agreement"] == pytest.approx(2 / 3, abs=0.01) and graph["breaks"] == 0
    assert graph["unheld_m"] == pytest.approx(200.0, abs=1.5)
    # the same two roads touching but not linked: the links break where they meet
    touching = _write(tmp_path / "touch.xodr", _road("1", 150.0, lanes), _road("2", 150.0, lanes, x=150.0))
    graph = compare_maps(touching, ref, CFG)["lane_graph"]
    assert graph["breaks"] == 2 and graph["agreement"] < 0.6


def test_a_zero_width_placeholder_is_no_part_of_the_taper_chain(tmp_path: Path) -> None:
    """An outer lane kept at width 0 over the section before it opens (the exporter's
    fold_appearing_lanes): the opening lane's taper starts where it opens, not 300 m earlier."""
    def road(before: float) -> Path:
        a = [_lane(-1, LANE, succ=-1), _lane(-2, before, succ=-2)]
        b = [_lane(-1, LANE, pred=-1), _lane(-2, LANE, pred=-2)]
        return _write(tmp_path / f"r{before}.xodr", _road("1", 600.0, [_section(0, a), _section(300, b)]))

    for before, start in ((0.0, 0.0), (1.0, 60.0 + 1.0)):
        g = build_lane_graph(OpenDriveMap.load(road(before)), DRIVING_TYPES)
        start_d, _ = g.chain_distances(61.0)
        assert start_d[g.index[("1", 1, -2)]] == pytest.approx(start)
        assert start_d[g.index[("1", 1, -1)]] == pytest.approx(61.0)


def test_a_reference_lane_starts_where_it_is_evaluated(tmp_path: Path) -> None:
    """The generated lane -2 loses its link at s = 50, inside the reference lane's 1 m wide first
    100 m (not evaluated, no lane a vehicle drives in): the reference lane starts at s = 100, where
    the generated lane -2 holds it; a link lost at s = 150, inside the evaluated length, breaks."""
    ref = _write(tmp_path / "ref.xodr", _road("1", 300.0, [
        _section(0, [_lane(-1, LANE, succ=-1), _lane(-2, 1.0, succ=-2)]),
        _section(100, [_lane(-1, LANE, pred=-1, succ=-1), _lane(-2, LANE, pred=-2, succ=-2)]),
        _section(150, [_lane(-1, LANE, pred=-1), _lane(-2, LANE, pred=-2)])]))
    early = _write(tmp_path / "early.xodr", _road("1", 300.0, [
        _section(0, [_lane(-1, LANE, succ=-1), _lane(-2, LANE)]),
        _section(50, [_lane(-1, LANE, pred=-1), _lane(-2, LANE)])]))
    graph = compare_maps(early, ref, CFG)["lane_graph"]
    assert graph["breaks"] == 0 and graph["agreement"] == pytest.approx(1.0)
    assert graph["eval_length_m"] == pytest.approx(500.0, abs=1.0)
    late = _write(tmp_path / "late.xodr", _road("1", 300.0, [
        _section(0, [_lane(-1, LANE, succ=-1), _lane(-2, LANE)]),
        _section(150, [_lane(-1, LANE, pred=-1), _lane(-2, LANE)])]))
    graph = compare_maps(late, ref, CFG)["lane_graph"]
    assert graph["breaks"] == 1 and graph["breaks_at"][0]["x"] == pytest.approx(150.0, abs=0.6)
    assert graph["off_route_m"] == pytest.approx(150.0, abs=1.0)


def test_an_opening_lane_whose_sliver_falls_into_its_neighbour_does_not_break(tmp_path: Path) -> None:
    """two_plus_one's inner lane opens from zero width beside the centre line (s 100-150) while the
    through lane moves out to -2. The generated map has the same lanes and links, its opening 5 m
    later: the reference sliver's first samples fall into the generated -1, then -2, then the new
    -1 (not linked from -2). The sliver is no lane yet; the route starts where it is one."""
    def road(start: float, length: float) -> str:
        return _road("1", 300.0, [
            _section(0, [_lane(-1, LANE, succ=-2)]),
            _section(start, [_lane(-1, 0.0, succ=-1, widening=LANE / length), _lane(-2, LANE, pred=-1, succ=-2)]),
            _section(start + length, [_lane(-1, LANE, pred=-1), _lane(-2, LANE, pred=-2)])])
    ref = _write(tmp_path / "ref.xodr", road(100.0, 50.0))
    gen = _write(tmp_path / "gen.xodr", road(105.0, 45.0))
    graph = compare_maps(gen, ref, CFG)["lane_graph"]
    assert graph["breaks"] == 0 and graph["agreement"] == pytest.approx(1.0, abs=0.01)
