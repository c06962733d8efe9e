"""Lanelet2 export, judged by lanelet2 itself: its loader, its routing graph and its validity check.

Maps: the project's own (a carriageway whose lane count changes between lane sections, the diverge
and merge networks of test_export_network with classic and direct junctions, the demo road), a
small hand-written two-way road (left lanes, a road joined end to end, a mark change inside a
section, no geoReference) and, when the shared data is there, esmini's highway_exit.
The expected routes come from the OpenDRIVE links, turned into travel direction by the oracle below.
"""

from __future__ import annotations

import json
from pathlib import Path

import lanelet2
import numpy as np
import pytest
from conftest import shared_maps
from lanelet2.core import BasicPoint3d
from lanelet2.routing import RoutingGraph
from lanelet2.traffic_rules import Locations, Participants
from scipy.spatial import cKDTree
from test_export_network import _diverge, _merge
from test_export_sections import _road

from lidar2xodr.cli import app
from lidar2xodr.config import ExportConfig, InterchangeConfig
from lidar2xodr.errors import InputError
from lidar2xodr.export_lanelet2 import export_lanelet2, projector_for
from lidar2xodr.export_opendrive import export_network, export_opendrive
from lidar2xodr.georeference import ToWgs84
from lidar2xodr.opendrive import OpenDriveMap

DRIVABLE = ("driving", "entry", "exit", "onRamp", "offRamp")
Key = tuple[str, int, int]


def _two_way(path: Path) -> Path:
    """Road 1 (100 m, sections at 0 and 60, the -1 mark broken then solid from s=30) -> road 2 (100 m)
    -> road 3 (50 m, drawn backwards: joined end to end, so road 2's right lanes are its left lanes)."""
    def lane(lid: int, mark: str, links: str = "", extra: str = "") -> str:
        return (f'<lane id="{lid}" type="driving" level="false"><link>{links}</link>'
                f'<width sOffset="0" a="3.5" b="0" c="0" d="0"/>'
                f'<roadMark sOffset="0" type="{mark}" weight="standard" color="standard" width="0.15"/>{extra}</lane>')

    def section(s: float, lanes: dict[int, str], links: dict[int, str], extra: dict[int, str] | None = None) -> str:
        extra = extra or {}
        left = "".join(lane(i, lanes[i], links.get(i, ""), extra.get(i, "")) for i in sorted(lanes) if i > 0)
        right = "".join(lane(i, lanes[i], links.get(i, ""), extra.get(i, "")) for i in sorted(lanes, reverse=True)
                        if i < 0)
        return (f'<laneSection s="{s}"><left>{left}</left><center><lane id="0" type="none" level="false">'
                f'<roadMark sOffset="0" type="solid" weight="standard" color="standard" width="0.15"/></lane>'
                f'</center><right>{right}</right></laneSection>')

    def succ(i: int) -> str:
        return f'<successor id="{i}"/>'

    def pred(i: int) -> str:
        return f'<predecessor id="{i}"/>'

    marks = {1: "solid", -1: "broken", -2: "solid"}
    later = '<roadMark sOffset="30" type="solid" weight="standard" color="standard" width="0.15"/>'
    road1 = section(0, marks, {i: succ(i) for i in marks}, {-1: later}) + section(
        60, marks, {1: pred(1) + succ(1), -1: pred(-1) + succ(-1), -2: pred(-2) + succ(-2)})
    road2 = section(0, marks, {1: pred(1) + succ(-1), -1: pred(-1) + succ(1), -2: pred(-2) + succ(2)})
    road3 = section(0, {-1: "solid", 1: "broken", 2: "solid"}, {-1: succ(1), 1: succ(-1), 2: succ(-2)})
    town = '<type s="0" type="town"><speed max="50" unit="km/h"/></type>'

    def road(rid: int, x: float, hdg: float, length: float, link: str, lanes: str) -> str:
        return (f'<road id="{rid}" junction="-1" length="{length}" rule="RHT"><link>{link}</link>{town}'
                f'<planView><geometry s="0" x="{x}" y="0" hdg="{hdg}" length="{length}"><line/></geometry>'
                f'</planView><lanes>{lanes}</lanes></road>')

    xml = ('<?xml version="1.0"?><OpenDRIVE><header revMajor="1" revMinor="6" name="two-way"/>'
           + road(1, 0.0, 0.0, 100.0, '<successor elementType="road" elementId="2" contactPoint="start"/>', road1)
           + road(2, 100.0, 0.0, 100.0, '<predecessor elementType="road" elementId="1" contactPoint="end"/>'
                  '<successor elementType="road" elementId="3" contactPoint="end"/>', road2)
           + road(3, 250.0, np.pi, 50.0, '<successor elementType="road" elementId="2" contactPoint="end"/>', road3)
           + "</OpenDRIVE>")
    path.write_text(xml)
    return path


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("lanelet2")
    res = {"two_way": _two_way(out / "two_way.xodr")}
    export_opendrive(_road(), None, ExportConfig(fold_appearing_lanes=False), out / "sections.xodr")
    res["sections"] = out / "sections.xodr"
    for name, make in (("diverge", _diverge), ("merge", _merge)):
        for key, direct in ((f"{name}-classic", False), (f"{name}-direct", True)):  # direct: the exporter's first form
            export_network(make()[0], None, ExportConfig(), out / f"{key}.xodr", _direct=direct)
            res[key] = out / f"{key}.xodr"
    return res


def _key(ll) -> Key:
    a = ll.attributes
    return a["odr:road"], int(a["odr:section"]), int(a["odr:lane"])


def _travel_edges(odr: OpenDriveMap) -> set[tuple[Key, Key]]:
    """Lane-to-lane successors in travel direction, read from the map's links (links to missing lanes dropped)."""
    edges: set[tuple[Key, Key]] = set()

    def drivable(rid: str, k: int, lid: int) -> bool:
        lane = odr.roads[rid].lane_sections[k].lanes.get(lid)
        return lid != 0 and lane is not None and lane.type in DRIVABLE

    def join(a: tuple[str, int, bool, int], b: tuple[str, int, bool, int]) -> None:
        if not (drivable(a[0], a[1], a[3]) and drivable(b[0], b[1], b[3])):
            return
        a_leaves, b_leaves = _along_s(odr, a[0], a[3]) == a[2], _along_s(odr, b[0], b[3]) == b[2]
        if a_leaves != b_leaves:
            src, dst = (a, b) if a_leaves else (b, a)
            edges.add(((src[0], src[1], src[3]), (dst[0], dst[1], dst[3])))

    for rid, road in odr.roads.items():
        secs = road.lane_sections
        for k in range(len(secs) - 1):
            for lid, lane in secs[k].lanes.items():
                if lane.successor in secs[k + 1].lanes:
                    join((rid, k, True, lid), (rid, k + 1, False, lane.successor))
        for link, at_end in ((road.predecessor, False), (road.successor, True)):
            if link is None or link.element_type != "road":
                continue
            other = odr.roads[link.element_id]
            o_end = link.contact_point == "end"
            k, ok = (len(secs) - 1 if at_end else 0), (len(other.lane_sections) - 1 if o_end else 0)
            for lid, lane in secs[k].lanes.items():
                target = lane.successor if at_end else lane.predecessor
                if target is not None and target in other.lane_sections[ok].lanes:
                    join((rid, k, at_end, lid), (other.id, ok, o_end, target))
    for jid, junction in odr.junctions.items():
        for c in junction.connections:
            inc, con = odr.roads[c.incoming_road], odr.roads[c.connecting_road]
            at_end = inc.successor is not None and inc.successor.element_id == jid
            c_end = c.contact_point == "end"
            k, ck = (len(inc.lane_sections) - 1 if at_end else 0), (len(con.lane_sections) - 1 if c_end else 0)
            for a, b in c.lane_links:
                join((inc.id, k, at_end, a), (con.id, ck, c_end, b))
    return edges


def _bridge(edges: set[tuple[Key, Key]], kept: set[Key]) -> set[tuple[Key, Key]]:
    """The edges with every lane not in `kept` (too short for a lanelet) contracted: a -> t -> b is a -> b."""
    edges = set(edges)
    for t in sorted({k for e in edges for k in e} - kept):
        into = {a for a, b in edges if b == t and a != t}
        out = {b for a, b in edges if a == t and b != t}
        edges = {e for e in edges if t not in e} | {(a, b) for a in into for b in out}
    return edges


def _along_s(odr: OpenDriveMap, rid: str, lid: int) -> bool:
    """Right lanes are driven along s under right-hand traffic, left lanes under left-hand traffic."""
    return (lid < 0) == (odr.roads[rid].rule != "LHT")


def _load(xodr: Path, osm: Path):
    """The written map loaded back with the exporter's projector, and lanelet2's routing graph of it."""
    projector, to_geo, _ = projector_for(OpenDriveMap.load(xodr))
    lmap = lanelet2.io.load(str(osm), projector)
    rules = lanelet2.traffic_rules.create(Locations.Germany, Participants.Vehicle)
    return lmap, RoutingGraph(lmap, rules), projector, to_geo


def _map_xy(points, projector, to_geo: ToWgs84) -> np.ndarray:
    """Lanelet2 points (projector frame) back in the OpenDRIVE map's frame, through WGS84."""
    gps = [projector.reverse(BasicPoint3d(p.x, p.y, p.z)) for p in points]
    x, y = to_geo.local(np.array([g.lon for g in gps]), np.array([g.lat for g in gps]))
    return np.column_stack([x, y])


def _routes_as_linked(xodr: Path, tmp_path: Path) -> tuple:
    osm = tmp_path / (xodr.stem + ".osm")
    summary = export_lanelet2(xodr, osm)
    lmap, graph, projector, to_geo = _load(xodr, osm)
    assert graph.checkValidity() == []
    odr = OpenDriveMap.load(xodr)
    lanelets = list(lmap.laneletLayer)
    assert len(lanelets) == summary.lanelets
    short = InterchangeConfig().min_lanelet_length_m
    drivable = {(rid, k, lid) for rid, r in odr.roads.items() for k, ls in enumerate(r.lane_sections)
                for lid, lane in ls.lanes.items() if lid != 0 and lane.type in DRIVABLE and ls.s_end - ls.s >= short}
    assert {_key(ll) for ll in lanelets} == drivable
    got: set[tuple[Key, Key]] = set()
    for ll in lanelets:
        nxt = graph.following(ll)
        same = [f for f in nxt if _key(f) == _key(ll)]
        assert len(same) <= 1 and (not same or len(nxt) == 1), f"{_key(ll)} splits inside its own lane"
        got.update((_key(ll), _key(f)) for f in nxt if _key(f) != _key(ll))
    assert got == _bridge(_travel_edges(odr), drivable)
    return odr, lmap, graph, (projector, to_geo), summary


def _lane_changes(odr: OpenDriveMap, lmap, graph, frame) -> int:
    """Neighbouring lanes of one direction: lanelet2 changes lanes over broken lines, never over solid ones."""
    checked = 0
    for ll in lmap.laneletLayer:
        rid, k, lid = _key(ll)
        road, ls = odr.roads[rid], odr.roads[rid].lane_sections[k]
        fwd = _along_s(odr, rid, lid)
        outer = lid - 1 if fwd else lid + 1  # the neighbour on the right in travel direction
        outer = outer or (-1 if fwd else 1)
        if outer not in ls.lanes or ls.lanes[outer].type not in DRIVABLE or _along_s(odr, rid, outer) != fwd:
            assert graph.right(ll) is None and graph.adjacentRight(ll) is None
            continue
        border = (1 if lid > 0 else -1) * min(abs(lid), abs(outer))
        # the road mark on the border between them in the lanelet's middle
        mid = _map_xy([ll.centerline[len(ll.centerline) // 2]], *frame)[0]
        s = np.linspace(ls.s, ls.s_end, 4001)
        x, y, _ = road.reference(s)
        ds = float(s[np.argmin(np.hypot(x - mid[0], y - mid[1]))] - ls.s)
        marks = [m for m in ls.lanes[border].road_marks if m.s_offset <= ds]
        kind = marks[-1].type if marks else "none"
        if " " in kind:
            continue
        neighbour = graph.right(ll) if kind == "broken" else graph.adjacentRight(ll)
        assert neighbour is not None and _key(neighbour) == (rid, k, outer), (rid, k, lid, kind)
        if kind != "broken":
            assert graph.right(ll) is None
        checked += 1
    return checked


def test_two_way_road_routes_and_changes_lanes_as_the_map_says(maps, tmp_path: Path) -> None:
    odr, lmap, graph, frame, summary = _routes_as_linked(maps["two_way"], tmp_path)
    assert any("no geoReference" in w for w in summary.warnings)
    assert (summary.origin_lat, summary.origin_lon) == (0.0, 0.0)
    by_key = {}
    for ll in lmap.laneletLayer:
        by_key.setdefault(_key(ll), []).append(ll)
    # the -1 mark turns solid at s = 30: two lanelets, lane change over the first only
    first, second = sorted(by_key[("1", 0, -1)], key=lambda ll: ll.centerline[0].x)
    assert graph.right(first) is not None and _key(graph.right(first)) == ("1", 0, -2)
    assert graph.right(second) is None and _key(graph.adjacentRight(second)) == ("1", 0, -2)
    assert graph.following(first)[0] == second
    # left lanes point against s: lane 1 of road 1 runs from x = 100 to x = 60
    ll = by_key[("1", 1, 1)][0]
    assert ll.centerline[0].x > ll.centerline[-1].x
    assert ll.attributes["location"] == "urban" and ll.attributes["speed_limit"] == "50"
    assert ll.attributes["subtype"] == "road" and ll.attributes["one_way"] == "yes"
    # opposite directions share the centre line, but are never left/right of each other
    assert graph.left(by_key[("1", 1, -1)][0]) is None
    assert ll.leftBound.id == by_key[("1", 1, -1)][0].leftBound.id
    # across road 2 into road 3, drawn backwards: one route from road 1 to the end of road 3
    route = graph.getRoute(by_key[("1", 0, -2)][0], by_key[("3", 0, 2)][0])
    assert route is not None
    back = graph.getRoute(by_key[("3", 0, -1)][0], by_key[("1", 0, 1)][0])
    assert back is not None and len(back.shortestPath()) == 4


def test_sections_and_junctions_route_as_the_lane_links(maps, tmp_path: Path) -> None:
    for name in ("sections", "diverge-classic", "diverge-direct", "merge-classic", "merge-direct"):
        odr, lmap, graph, frame, summary = _routes_as_linked(maps[name], tmp_path)
        assert not summary.warnings, (name, summary.warnings)
        assert _lane_changes(odr, lmap, graph, frame) > 0
    # the diverge: A's right lane reaches the branch C, its left lane the continuation B, not C
    odr, lmap, graph, _, _ = _routes_as_linked(maps["diverge-classic"], tmp_path)
    lanelets = {_key(ll): ll for ll in lmap.laneletLayer}
    last_a = max(k for k in lanelets if k[0] == "1")[1]
    first_c = min(k[1] for k in lanelets if k[0] == "3")
    branch = lanelets[("3", first_c, -1)]
    assert graph.getRoute(lanelets[("1", last_a, -2)], branch) is not None
    assert graph.getRoute(lanelets[("1", last_a, -1)], branch, 0, False) is None  # no lane change allowed


def test_points_are_where_the_opendrive_borders_are(maps, tmp_path: Path) -> None:
    """Loaded back with the projector, lanelet2's points lie on the OpenDRIVE borders (the origin is right)."""
    path = maps["sections"]
    odr = OpenDriveMap.load(path)
    osm = tmp_path / "sections.osm"
    export_lanelet2(path, osm)
    lmap, _, projector, to_geo = _load(path, osm)
    road = odr.roads["1"]
    xy = _map_xy(list(lmap.pointLayer), projector, to_geo)
    s = np.linspace(0.0, road.length, int(road.length * 100) + 1)  # 1 cm apart
    border_xy = np.vstack([road.to_world(s, road.border_t(s, lid))[:, :2] for lid in (0, -1, -2, -3, -4)])
    border_xy = border_xy[np.isfinite(border_xy).all(axis=1)]
    dist, _ = cKDTree(border_xy).query(xy)
    assert dist.max() < 0.006  # half the sample spacing plus projection round trips


def test_same_map_same_bytes(maps, tmp_path: Path) -> None:
    a, b = tmp_path / "a.osm", tmp_path / "b.osm"
    export_lanelet2(maps["diverge-classic"], a)
    export_lanelet2(maps["diverge-classic"], b)
    assert a.read_bytes() == b.read_bytes()


def test_demo_road_routes_through_its_added_lane(tmp_path: Path) -> None:
    from lidar2xodr.demo_road import write_demo_road

    odr, lmap, graph, frame, summary = _routes_as_linked(write_demo_road(tmp_path / "demo.xodr"), tmp_path)
    assert (round(summary.origin_lat, 6), round(summary.origin_lon, 6)) == (48.78, 9.18)
    assert _lane_changes(odr, lmap, graph, frame) > 0
    # no road <type> in the demo road: plain road, the configured default location, no speed limit
    assert not odr.roads["1"].types
    tags = {(ll.attributes["subtype"], ll.attributes["location"], "speed_limit" in ll.attributes)
            for ll in lmap.laneletLayer}
    assert tags == {("road", InterchangeConfig().default_location, False)}


@pytest.mark.slow
@pytest.mark.parametrize("path", shared_maps(), ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_every_shared_map_routes_as_linked(path: Path, tmp_path: Path) -> None:
    """Third-party maps (esmini, ASAM examples, CARLA Town04, maliput): lanelet2 routes them as their links do."""
    odr, lmap, graph, frame, summary = _routes_as_linked(path, tmp_path)
    _lane_changes(odr, lmap, graph, frame)
    assert not [w for w in summary.warnings if "not joined" in w]
    from lidar2xodr.lanelet2_reader import run_lanelet2

    reader = run_lanelet2(path)
    assert not reader["errors"] and reader["missing"] == 0, reader


def test_esmini_highway_exit(shared_data: Path, tmp_path: Path) -> None:
    path = shared_data / "maps" / "esmini" / "highway_exit.xodr"
    if not path.is_file():
        pytest.skip(f"{path} not in the shared data")
    odr, lmap, graph, frame, summary = _routes_as_linked(path, tmp_path)
    assert _lane_changes(odr, lmap, graph, frame) > 0
    assert {ll.attributes["speed_limit"] for ll in lmap.laneletLayer if ll.attributes["odr:road"] == "0"} == {"110"}
    assert not [w for w in summary.warnings if "not joined" in w]


def test_bad_map_is_one_line_and_exit_2(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    bad = tmp_path / "bad.xodr"
    bad.write_text("<OpenDRIVE><header/>")
    out = tmp_path / "out.osm"
    res = CliRunner().invoke(app, ["export-lanelet2", str(bad), "-o", str(out)])
    assert res.exit_code == 2 and "bad.xodr" in res.output and "Traceback" not in res.output
    assert not out.exists()
    with pytest.raises(InputError):
        export_lanelet2(bad, out, InterchangeConfig())


@pytest.mark.slow
def test_build_writes_lanelet2_and_geojson_next_to_the_map(tmp_path: Path) -> None:
    """`build --lanelet2 --geojson` on a simulated drive: both files, routable and the same lanes as the map."""
    from typer.testing import CliRunner

    from lidar2xodr.demo_road import write_demo_road
    from lidar2xodr.simulation import SimOptions, simulate

    drive = tmp_path / "drive"
    simulate(write_demo_road(tmp_path / "truth.xodr"), drive, SimOptions(length_m=400.0, seed=1, traffic="none"))
    xodr, osm, gj = tmp_path / "map.xodr", tmp_path / "map.osm", tmp_path / "map.geojson"
    res = CliRunner().invoke(app, ["build", str(drive), "-o", str(xodr), "--lanelet2", str(osm), "--geojson", str(gj)])
    assert res.exit_code == 0, res.output
    again = tmp_path / "again"
    again.mkdir()
    _routes_as_linked(xodr, again)
    assert (again / "map.osm").read_bytes() == osm.read_bytes()  # what build wrote is what routes

    lanes = {(f["properties"]["road"], f["properties"]["section"], f["properties"]["lane"])
             for f in json.loads(gj.read_text())["features"] if f["properties"]["kind"] == "lane"}
    expected = set()
    for rid, road in OpenDriveMap.load(xodr).roads.items():
        for k, ls in enumerate(road.lane_sections):
            s = np.linspace(ls.s, ls.s_end - 1e-7, 200)
            for lid in ls.lanes:
                inner = lid - (1 if lid > 0 else -1)
                if lid and np.abs(road.border_t(s, lid) - road.border_t(s, inner)).max() > 1e-3:
                    expected.add((rid, k, lid))
    assert lanes == expected  # every lane with an area, nothing else


def test_lanelet2_reader_finds_what_routes_and_what_does_not(maps, tmp_path: Path) -> None:
    """run_lanelet2 (a reader for `check`): clean on a sound map; a linked road moved 1 m away is unrouted."""
    from lidar2xodr.lanelet2_reader import run_lanelet2

    good = run_lanelet2(maps["diverge-classic"])
    assert good["ok"] and good["links"] > 0 and good["missing"] == 0 and good["lanelets"] > 0, good
    moved = tmp_path / "moved.xodr"
    moved.write_text(maps["two_way"].read_text().replace('x="100.0" y="0"', 'x="101.0" y="0"'))
    bad = run_lanelet2(moved)
    assert not bad["ok"] and bad["missing"] == 6, bad  # both ends of road 2: three lanes each
    assert any("1.000 m apart" in w for w in bad["warnings"])
    broken = tmp_path / "broken.xodr"
    broken.write_text("<OpenDRIVE/>")
    assert run_lanelet2(broken)["errors"] and not run_lanelet2(broken)["ok"]
