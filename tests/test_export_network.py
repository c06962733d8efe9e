"""OpenDRIVE export of a RoadNetwork: roads joined by junctions, continuous across them.

The joins are tested on the direct form the exporter builds first (`_direct=True`, never written
for users) and on the classic form derived from it.

Hand-made networks: a diverge (A: 2 lanes, B continues A's left lane, C a 1-lane branch curving
away to the right from A's right lane) and a merge (A: 1 lane, B: 2 lanes, ramp R joins B's right
lane). The branch models are 0.2 m off near the junction (fading over ~15 m), as a lanes stage that
misjudged the gore would be; the exporter must snap them onto the main road.
"""

from __future__ import annotations

import math
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from lxml import etree
from scipy.integrate import cumulative_trapezoid

from lidar2xodr.check import find_netconvert, find_qc_venv, junction_gaps, polyline_distance
from lidar2xodr.config import ExportConfig
from lidar2xodr.data import Boundary, GroundPlanes, LaneModel, LaneSection, RoadLink, RoadNetwork
from lidar2xodr.errors import InputError
from lidar2xodr.export_opendrive import ExportSummary, export_network, export_opendrive
from lidar2xodr.opendrive import OpenDriveMap, Road

LANE = 3.5
ERROR_M = 0.2
GRADE = 0.01
ROLL = 0.02


def _curve(p0: np.ndarray, h0: float, length: float, kappa: list[tuple[float, float]]) -> tuple[np.ndarray, ...]:
    """Stations (1 m), xy and heading of a curve with piecewise-linear curvature."""
    fine = np.arange(0.0, length + 1e-9, 0.05)
    k = np.interp(fine, [a for a, _ in kappa], [b for _, b in kappa])
    h = h0 + cumulative_trapezoid(k, fine, initial=0.0)
    x = p0[0] + cumulative_trapezoid(np.cos(h), fine, initial=0.0)
    y = p0[1] + cumulative_trapezoid(np.sin(h), fine, initial=0.0)
    s = np.arange(0.0, length + 1e-9, 1.0)
    i = np.round(s / 0.05).astype(int)
    return s, np.stack([x[i], y[i]], axis=1), h[i]


def _model(s: np.ndarray, xy: np.ndarray, ts: list[float], z: np.ndarray) -> LaneModel:
    bounds = [Boundary(i, np.full(len(s), t), "solid" if i in (0, len(ts) - 1) else "broken", 0.15,
                       6.0 if 0 < i < len(ts) - 1 else None, 12.0 if 0 < i < len(ts) - 1 else None)
              for i, t in enumerate(ts)]
    return LaneModel(s=s, reference=np.column_stack([xy, z]), boundaries=bounds,
                     sections=[LaneSection(0.0, float(s[-1]), list(range(len(ts))))])


def _misjudged(model: LaneModel, heading: np.ndarray, at_end: bool) -> LaneModel:
    """The model ERROR_M to the left at its junction end, the error fading over ~15 m."""
    d = model.s[-1] - model.s if at_end else model.s - model.s[0]
    left = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    model.reference[:, :2] += (ERROR_M * np.exp(-d / 15.0))[:, None] * left
    return model


def _junction_frame() -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Road A: 200 m straight at heading 0.3 rising at GRADE; returns its s, xy, end heading, end normal, z."""
    s, xy, h = _curve(np.array([10.0, -5.0]), 0.3, 200.0, [(0, 0), (200, 0)])
    normal = np.array([-math.sin(h[-1]), math.cos(h[-1])])
    return s, xy, float(h[-1]), normal, 5.0 + GRADE * s


def _diverge() -> tuple[RoadNetwork, LaneModel]:
    """A (2 lanes) -> B (A's left lane, continuation) and C (A's right lane, a branch curving right)."""
    sa, xa, h_end, normal, za = _junction_frame()
    a = _model(sa, xa, [LANE, 0.0, -LANE], za)
    sb, xb, _ = _curve(xa[-1], h_end, 300.0, [(0, 0), (300, 0)])
    b = _model(sb, xb, [LANE, 0.0], za[-1] + GRADE * sb)
    sc, xc, hc = _curve(xa[-1] - 0.5 * LANE * normal, h_end, 150.0, [(0, 0), (60, -1 / 250), (150, -1 / 250)])
    zc = za[-1] - 0.5 * LANE * math.sin(ROLL) + GRADE * sc
    truth = _model(sc, xc.copy(), [LANE / 2, -LANE / 2], zc)
    c = _misjudged(_model(sc, xc.copy(), [LANE / 2, -LANE / 2], zc.copy()), hc, at_end=False)
    links = [RoadLink(0, 1, [(0, 0)], continuation=True), RoadLink(0, 2, [(1, 0)], continuation=False)]
    return RoadNetwork([a, b, c], links), truth


def _merge() -> tuple[RoadNetwork, LaneModel]:
    """A (1 lane) -> B (2 lanes, continuation of A's lane as its left lane); ramp R -> B's right lane."""
    sa, xa, h_end, normal, za = _junction_frame()
    a = _model(sa, xa, [LANE, 0.0], za)
    sb, xb, _ = _curve(xa[-1], h_end, 300.0, [(0, 0), (300, 0)])
    b = _model(sb, xb, [LANE, 0.0, -LANE], za[-1] + GRADE * sb)
    # drawn backwards from B's right lane centre, turning left while going back: it comes from the right
    sr, xr, hr = _curve(xa[-1] - 0.5 * LANE * normal, h_end + math.pi, 150.0, [(0, 0), (60, 1 / 250), (150, 1 / 250)])
    xr, hr = xr[::-1].copy(), hr[::-1] + math.pi
    zr = za[-1] - GRADE * sr[::-1]
    truth = _model(sr, xr.copy(), [LANE / 2, -LANE / 2], zr)
    r = _misjudged(_model(sr, xr.copy(), [LANE / 2, -LANE / 2], zr.copy()), hr, at_end=True)
    links = [RoadLink(0, 1, [(0, 0)], continuation=True), RoadLink(2, 1, [(0, 1)], continuation=False)]
    return RoadNetwork([a, b, r], links), truth


def _planes(network: RoadNetwork) -> GroundPlanes:
    """One plane every 2 m below the main roads (the ego drove A then B), rolled by ROLL (left side up)."""
    refs = [network.roads[0].reference[::2], network.roads[1].reference[::2]]
    xyz = np.vstack(refs)
    tan = np.vstack([np.gradient(r[:, :2], axis=0) for r in refs])
    left = np.stack([-tan[:, 1], tan[:, 0]], axis=1) / np.linalg.norm(tan, axis=1)[:, None]
    normals = np.column_stack([-math.sin(ROLL) * left, np.full(len(xyz), math.cos(ROLL))])
    return GroundPlanes(times=np.arange(len(xyz)) * 0.1, normals_world=normals, points_world=xyz)


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[RoadNetwork, LaneModel, Path, ExportSummary]]:
    out = tmp_path_factory.mktemp("network")
    res = {}
    for name, make in (("diverge", _diverge), ("merge", _merge)):
        for key, direct in ((name, True), (f"{name}-classic", False)):
            network, truth = make()
            planes = _planes(network) if name == "diverge" else None
            path = out / f"{key}.xodr"
            res[key] = (network, truth, path, export_network(network, planes, ExportConfig(), path, _direct=direct))
    return res


def _border(road: Road, s: float, lane_id: int) -> np.ndarray:
    """World xyz of the inner and outer border of a lane at s."""
    inner = lane_id - (1 if lane_id > 0 else -1)
    t = np.array([road.border_t(s, inner)[0], road.border_t(s, lane_id)[0]])
    return road.to_world(np.array([s, s]), t)


def _pose(road: Road, s: float) -> tuple[float, float, float]:
    x, y, h = road.reference(np.array([s]), left=s > 0)
    return float(x[0]), float(y[0]), float(h[0])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _boundary_xy(model: LaneModel, bid: int) -> np.ndarray:
    tan = np.gradient(model.reference[:, :2], model.s, axis=0)
    left = np.stack([-tan[:, 1], tan[:, 0]], axis=1) / np.linalg.norm(tan, axis=1)[:, None]
    return model.reference[:, :2] + model.boundaries[bid].t[:, None] * left


def test_roads_junction_and_links_are_written(written) -> None:
    for name, incoming, outgoing in (("diverge", ["1"], ["2", "3"]), ("merge", ["1", "3"], ["2"])):
        _, _, path, summary = written[name]
        root = etree.parse(str(path)).getroot()
        assert [r.get("id") for r in root.findall("road")] == ["1", "2", "3"]
        assert all(r.get("junction") == "-1" for r in root.findall("road"))
        junctions = root.findall("junction")
        assert len(junctions) == 1 and junctions[0].get("type") == "direct" and junctions[0].get("id") == "4"
        assert junctions[0].get("name") == name
        assert summary.roads == 3 and summary.junctions == 1
        for rid in incoming:
            succ = root.find(f"road[@id='{rid}']/link/successor")
            assert (succ.get("elementType"), succ.get("elementId")) == ("junction", "4")
            assert root.find(f"road[@id='{rid}']/link/predecessor") is None
        for rid in outgoing:
            pred = root.find(f"road[@id='{rid}']/link/predecessor")
            assert (pred.get("elementType"), pred.get("elementId")) == ("junction", "4")
        conns = {(c.get("incomingRoad"), c.get("linkedRoad")): c for c in junctions[0].findall("connection")}
        assert all(c.get("contactPoint") == "start" and c.get("connectingRoad") is None for c in conns.values())
        links = {k: [(int(ll.get("from")), int(ll.get("to"))) for ll in c.findall("laneLink")]
                 for k, c in conns.items()}
        if name == "diverge":
            assert links == {("1", "2"): [(-1, -1)], ("1", "3"): [(-2, -1)]}
        else:
            assert links == {("1", "2"): [(-1, -1)], ("3", "2"): [(-1, -2)]}
        # lanes never link across roads themselves: the junction's laneLinks do (OpenDRIVE lane linkage rule)
        assert not root.xpath("road/lanes/laneSection/*/lane/link/*")


def test_continuation_goes_on_exactly(written) -> None:
    for name in ("diverge", "merge"):
        _, _, path, summary = written[name]
        odr = OpenDriveMap.load(path)
        a, b = odr.roads["1"], odr.roads["2"]
        xa, ya, ha = _pose(a, a.length)
        xb, yb, hb = _pose(b, 0.0)
        assert math.hypot(xb - xa, yb - ya) <= 1e-6 and abs(_wrap(hb - ha)) <= 1e-9
        assert summary.max_leap_m <= 1e-6 and summary.max_kink_rad <= 1e-9
        assert abs(b.lane_offset(0.0)[0] - a.lane_offset(a.length, left=True)[0]) <= 1e-6
        gap = np.linalg.norm(_border(a, a.length, -1) - _border(b, 0.0, -1), axis=1).max()
        assert gap <= 1e-3, f"{name}: continuing lane borders {gap:.2e} m apart"
        assert abs(b.elevation(0.0)[0] - a.elevation(a.length, left=True)[0]) <= 1e-6


@pytest.mark.parametrize("name", ["diverge", "merge"])
def test_branch_is_snapped_onto_the_main_road(written, name: str) -> None:
    network, truth, path, summary = written[name]
    odr = OpenDriveMap.load(path)
    branch = odr.roads["3"]
    if name == "diverge":
        main, s_main, s_branch, main_lane = odr.roads["1"], odr.roads["1"].length, 0.0, -2
    else:
        main, s_main, s_branch, main_lane = odr.roads["2"], 0.0, branch.length, -2
    gap = np.linalg.norm(_border(main, s_main, main_lane) - _border(branch, s_branch, -1), axis=1).max()
    assert gap <= 0.01, f"branch lane borders {gap:.4f} m from the main road's"
    assert abs(_wrap(_pose(branch, s_branch)[2] - _pose(main, s_main)[2])) <= 1e-9, "the branch leaves tangentially"
    assert summary.max_junction_gap_m <= 0.01
    assert junction_gaps(odr)["max_junction_gap_m"] == pytest.approx(summary.max_junction_gap_m, abs=1e-9)

    model, end = network.roads[2], (0 if name == "diverge" else -1)
    sampled = [sec for sec in odr.sample(0.25) if sec.road_id == "3"]
    far_from_junction = 0.0
    for lane_id, bid in ((0, 0), (-1, 1)):
        pts = np.vstack([sec.border_xyz[lane_id][:, :2] for sec in sampled])
        s = np.concatenate([sec.s for sec in sampled])
        at_junction = pts[0] if name == "diverge" else pts[-1]
        moved = np.linalg.norm(at_junction - _boundary_xy(model, bid)[end])
        assert moved == pytest.approx(ERROR_M, abs=0.02), "the model was 0.2 m off at the junction: the export moved it"
        assert np.linalg.norm(at_junction - _boundary_xy(truth, bid)[end]) <= 0.01
        dist_junction = s if name == "diverge" else branch.length - s
        far = (dist_junction > ExportConfig().junction_blend_m + 5.0) & (dist_junction < branch.length - 5.0)
        far_from_junction = max(far_from_junction, float(polyline_distance(pts[far], _boundary_xy(model, bid)).max()))
    # hard end constraints alone would leave 1.5 cm there (and overshoot 10 cm nearer): the blend bends the model
    assert far_from_junction <= 0.006, f"beyond the blend the branch stays on its markings ({far_from_junction:.4f} m)"


def test_lane_into_the_branch_ends_at_full_width_and_new_lanes_start_at_zero(written) -> None:
    _, _, path, _ = written["diverge"]
    odr = OpenDriveMap.load(path)
    a = odr.roads["1"]
    width = a.lane_sections[-1].lanes[-2].width(np.array([a.length - a.lane_sections[-1].s]))[0]
    assert width == pytest.approx(LANE, abs=0.02), "no taper: the lane goes on in the branch"
    one_lane = _diverge()[0]
    one_lane.links = [RoadLink(0, 1, [(0, 0)], continuation=True)]  # A's right lane now leads nowhere
    path2 = path.parent / "ends.xodr"
    export_network(one_lane, None, ExportConfig(), path2, _direct=True)
    a2 = OpenDriveMap.load(path2).roads["1"]
    ls = a2.lane_sections[-1]
    assert abs(ls.lanes[-2].width(np.array([a2.length - ls.s]))[0]) <= 1e-6, "a lane linked to nothing ends at 0"
    assert ls.lanes[-1].width(np.array([a2.length - ls.s]))[0] == pytest.approx(LANE, abs=0.02)


def test_a_lane_into_a_branch_that_was_not_built_ends_at_full_width(written) -> None:
    """A lane that leaves into a branch seen too little to be built (the link's `open_in`) goes on
    there: it ends at its measured width, not in a taper to 0 (on highway_split the drive followed one
    branch, and the lane of the other closed over the last 50 m before the junction)."""
    _, _, path, _ = written["diverge"]
    one_lane = _diverge()[0]
    one_lane.links = [RoadLink(0, 1, [(0, 0)], continuation=True, open_in=[1])]
    path2 = path.parent / "open.xodr"
    export_network(one_lane, None, ExportConfig(), path2, _direct=True)
    a2 = OpenDriveMap.load(path2).roads["1"]
    ls = a2.lane_sections[-1]
    assert ls.lanes[-2].width(np.array([a2.length - ls.s]))[0] == pytest.approx(LANE, abs=0.02)
    assert ls.lanes[-1].width(np.array([a2.length - ls.s]))[0] == pytest.approx(LANE, abs=0.02)


def test_a_lane_from_a_ramp_that_was_not_built_starts_at_full_width(tmp_path: Path) -> None:
    """A lane that joins from an on-ramp seen too little to be built (one painted line: the link's
    `open_out`) starts at the junction at its measured width; without it, it opens from 0 over the
    taper (on roadgen corridors and Ex_Entry_Exit the acceleration lane was under 1.75 m wide for its
    first ~30 m while the truth's is full width from the junction)."""
    network = _merge()[0]
    a, b = network.roads[0], network.roads[1]
    widths = {}
    for name, open_out in (("taper", []), ("open", [1])):
        net = RoadNetwork([a, b], [RoadLink(0, 1, [(0, 0)], continuation=True, open_out=open_out)])
        path = tmp_path / f"{name}.xodr"
        export_network(net, None, ExportConfig(), path, _direct=True)
        road = OpenDriveMap.load(path).roads["2"]
        ls = road.lane_sections[0]
        widths[name] = [float(ls.lanes[-2].width(np.array([d]))[0]) for d in (0.0, 10.0)]
    assert widths["open"] == pytest.approx([LANE, LANE], abs=0.02)
    assert widths["taper"][0] <= 1e-6 and widths["taper"][1] < 0.5 * LANE


def test_elevation_and_banking_meet_at_the_junction(written) -> None:
    _, _, path, _ = written["diverge"]
    odr = OpenDriveMap.load(path)
    a, c = odr.roads["1"], odr.roads["3"]
    assert a.superelevation(a.length, left=True)[0] == pytest.approx(ROLL, abs=2e-3), "planes were used"
    assert abs(c.superelevation(0.0)[0] - a.superelevation(a.length, left=True)[0]) <= 1e-9
    z_gap = np.abs(_border(a, a.length, -2)[:, 2] - _border(c, 0.0, -1)[:, 2]).max()
    assert z_gap <= 1e-6, f"branch borders {z_gap:.2e} m off in height"
    slope_a = a.elevation_profile(a.length, derivative=1, left=True)[0]
    assert c.elevation_profile(0.0, derivative=1)[0] == pytest.approx(slope_a, abs=1e-9)


def _direction(road: Road, s0: float, s1: float, lane_id: int) -> float:
    p = road.to_world(np.array([s0, s1]), road.border_t(np.array([s0, s1]), lane_id))
    return math.atan2(p[1, 1] - p[0, 1], p[1, 0] - p[0, 0])


def test_lane_borders_keep_their_direction_across_the_junction(written, tmp_path: Path) -> None:
    """Linked lanes take the other road's width and border slopes: borders are C1 across the junction."""
    for name, joins in (("diverge", [("1", -1, "2", -1), ("1", -2, "3", -1), ("1", -1, "3", 0)]),
                        ("merge", [("1", -1, "2", -1), ("3", -1, "2", -2), ("3", 0, "2", -1)])):
        odr = OpenDriveMap.load(written[name][2])
        for ra, la, rb, lb in joins:
            a, b = odr.roads[ra], odr.roads[rb]
            turn = _wrap(_direction(b, 0.0, 1e-3, lb) - _direction(a, a.length - 1e-3, a.length, la))
            assert abs(turn) <= 1e-5, f"{name}: border of lane {la} of road {ra} turns {turn:.1e} rad into road {rb}"
    # A's right lane widens towards the junction, B's narrows after it: B's lane takes A's width slope
    network, _ = _diverge()
    a, b = network.roads[0], network.roads[1]
    a.boundaries[2].t = -LANE - np.clip((a.s - 100.0) / 200.0, 0.0, None)
    b.boundaries = [Boundary(i, np.full(len(b.s), t), "solid", 0.15) for i, t in enumerate([LANE, 0.0])]
    b.boundaries.append(Boundary(2, -LANE - np.clip(0.5 - b.s / 200.0, 0.0, None), "solid", 0.15))
    b.sections = [LaneSection(0.0, float(b.s[-1]), [0, 1, 2])]
    network.roads, network.links = [a, b], [RoadLink(0, 1, [(0, 0), (1, 1)], continuation=True)]
    export_network(network, None, ExportConfig(), tmp_path / "widening.xodr", _direct=True)
    odr = OpenDriveMap.load(tmp_path / "widening.xodr")
    ra, rb = odr.roads["1"], odr.roads["2"]
    slope_a = ra.lane_sections[-1].lanes[-2].widths(ra.length - ra.lane_sections[-1].s, derivative=1, left=True)[0]
    slope_b = rb.lane_sections[0].lanes[-2].widths(0.0, derivative=1)[0]
    assert slope_a == pytest.approx(0.005, abs=1e-3), "the widening was measured"
    assert slope_b == pytest.approx(slope_a, abs=1e-6)
    assert abs(_wrap(_direction(rb, 0.0, 1e-3, -2) - _direction(ra, ra.length - 1e-3, ra.length, -2))) <= 1e-5


def test_a_split_without_continuation_anchors_both_branches(tmp_path: Path) -> None:
    network, _ = _diverge()
    network.links = [RoadLink(0, 1, [(0, 0)], continuation=False), RoadLink(0, 2, [(1, 0)], continuation=False)]
    summary = export_network(network, None, ExportConfig(), tmp_path / "split.xodr", _direct=True)
    assert summary.junctions == 1 and summary.max_junction_gap_m <= 0.01
    odr = OpenDriveMap.load(tmp_path / "split.xodr")
    a, b = odr.roads["1"], odr.roads["2"]
    assert abs(_wrap(_pose(b, 0.0)[2] - _pose(a, a.length)[2])) <= 1e-9


def test_same_input_same_bytes_and_one_road_is_export_opendrive(tmp_path: Path) -> None:
    a, b = tmp_path / "a.xodr", tmp_path / "b.xodr"
    export_network(_diverge()[0], _planes(_diverge()[0]), ExportConfig(), a)
    export_network(_diverge()[0], _planes(_diverge()[0]), ExportConfig(), b)
    assert a.read_bytes() == b.read_bytes()
    model = _diverge()[0].roads[0]
    one = export_network(RoadNetwork([model]), None, ExportConfig(), tmp_path / "one.xodr")
    export_opendrive(model, None, ExportConfig(), tmp_path / "single.xodr")
    assert (tmp_path / "one.xodr").read_bytes() == (tmp_path / "single.xodr").read_bytes()
    assert (one.roads, one.junctions, one.max_junction_gap_m) == (1, 0, 0.0)
    root = etree.parse(str(tmp_path / "one.xodr")).getroot()
    assert root.find("junction") is None and root.find("road/link/successor") is None


@pytest.mark.parametrize("links, match", [
    ([RoadLink(0, 5, [(0, 0)])], "road indices"),
    ([RoadLink(0, 1, [(0, 0)]), RoadLink(0, 1, [(1, 0)], continuation=False)], "already linked"),
    ([RoadLink(0, 1, [(3, 0)])], "outside"),
    ([RoadLink(0, 1, [])], "links no lanes"),
    ([RoadLink(0, 2, [(0, 0), (1, 0)], continuation=False)], "neighbouring lanes"),
    ([RoadLink(0, 1, [(0, 0)]), RoadLink(0, 2, [(1, 0)])], "one continuation per road end"),
    ([RoadLink(0, 1, [(0, 0)]), RoadLink(1, 0, [(0, 0)])], "cycle"),
])
def test_bad_networks_are_one_error_and_write_nothing(tmp_path: Path, links: list[RoadLink], match: str) -> None:
    network, _ = _diverge()
    network.links = links
    with pytest.raises(InputError, match=match):
        export_network(network, None, ExportConfig(), tmp_path / "bad.xodr")
    assert not list(tmp_path.iterdir())


def test_bad_road_is_named(tmp_path: Path) -> None:
    network, _ = _diverge()
    network.roads[2].s[5] = network.roads[2].s[4]
    with pytest.raises(InputError, match="strictly increasing") as info:
        export_network(network, None, ExportConfig(), tmp_path / "bad.xodr")
    assert "road 3" in str(info.value.where)
    assert not list(tmp_path.iterdir())


def test_junction_gap_measures_a_shifted_road(shared_data: Path, tmp_path: Path) -> None:
    """The check's measure on a third-party map: ~0 as published, the shift when a linked road is moved 5 cm."""
    source = shared_data / "maps" / "esmini" / "highway_exit.xodr"
    assert junction_gaps(OpenDriveMap.load(source))["max_junction_gap_m"] < 1e-6
    tree = etree.parse(str(source))
    junction = tree.getroot().find("junction")
    moved = junction.find("connection").get("connectingRoad")
    for g in tree.getroot().findall(f"road[@id='{moved}']/planView/geometry"):
        g.set("y", repr(float(g.get("y")) + 0.05))
    tree.write(str(tmp_path / "moved.xodr"))
    gaps = junction_gaps(OpenDriveMap.load(tmp_path / "moved.xodr"))
    assert gaps["max_junction_gap_m"] == pytest.approx(0.05, abs=2e-3)
    assert gaps["worst"]["junction"] == junction.get("id")


def _two_way() -> RoadNetwork:
    """A two-way road (one lane each way, lane 0 on the paint between them) with a right exit lane that leaves as C."""
    sa, xa, h_end, normal, za = _junction_frame()
    a = _model(sa, xa, [LANE, 0.0, -LANE, -2 * LANE], za)
    sb, xb, _ = _curve(xa[-1], h_end, 300.0, [(0, 0), (300, 0)])
    b = _model(sb, xb, [LANE, 0.0, -LANE], za[-1] + GRADE * sb)
    a.sections[0].divider_id = b.sections[0].divider_id = 1
    sc, xc, _ = _curve(xa[-1] - 1.5 * LANE * normal, h_end, 150.0, [(0, 0), (60, -1 / 250), (150, -1 / 250)])
    c = _model(sc, xc, [LANE / 2, -LANE / 2], za[-1] + GRADE * sc)
    links = [RoadLink(0, 1, [(0, 0), (1, 1)], continuation=True), RoadLink(0, 2, [(2, 0)], continuation=False)]
    return RoadNetwork([a, b, c], links)


def test_classic_junction_has_connecting_roads_cut_from_the_roads(written) -> None:
    """Default form: each link becomes a connecting road cut from the branch side (diverge: the outgoing roads)."""
    for name, cut, conns in (("diverge", {"5": ("1", "2"), "6": ("1", "3")},
                              {("1", "5"): [(-1, -1)], ("1", "6"): [(-2, -1)]}),
                             ("merge", {"5": ("1", "2"), "6": ("3", "2")},
                              {("1", "5"): [(-1, -1)], ("3", "6"): [(-1, -1)]})):
        _, _, path, summary = written[f"{name}-classic"]
        root = etree.parse(str(path)).getroot()
        assert [r.get("id") for r in root.findall("road")] == ["1", "2", "3", "5", "6"]
        assert (summary.roads, summary.junctions, summary.connecting_roads) == (3, 1, 2)
        junction = root.find("junction")
        assert (junction.get("id"), junction.get("type"), junction.get("name")) == ("4", "default", name)
        got = {(c.get("incomingRoad"), c.get("connectingRoad")): [(int(ll.get("from")), int(ll.get("to")))
                                                                  for ll in c.findall("laneLink")]
               for c in junction.findall("connection")}
        assert got == conns
        assert all(c.get("contactPoint") == "start" and c.get("linkedRoad") is None
                   for c in junction.findall("connection"))
        for rid, (pred, succ) in cut.items():
            road = root.find(f"road[@id='{rid}']")
            assert road.get("junction") == "4"
            links = {e.tag: (e.get("elementType"), e.get("elementId"), e.get("contactPoint"))
                     for e in road.find("link")}
            assert links == {"predecessor": ("road", pred, "end"), "successor": ("road", succ, "start")}
            lane = road.find("lanes/laneSection/right/lane")
            assert lane.find("link/predecessor") is not None and lane.find("link/successor") is not None
        outer = root.xpath("road[@junction='-1']")
        assert all(e.get("elementType") == "junction" for r in outer for e in r.find("link"))
        # the roads outside link no lanes into the junction: its connections and the connecting roads do
        assert not root.xpath("road[@junction='-1']/lanes/laneSection/*/lane/link/*")


@pytest.mark.parametrize("name", ["diverge", "merge"])
def test_classic_junction_cuts_the_roads_exactly(written, name: str) -> None:
    """The connecting road and the rest of its road are the direct form's road, cut: same borders, height, roll."""
    direct = OpenDriveMap.load(written[name][2])
    classic = OpenDriveMap.load(written[f"{name}-classic"][2])
    summary = written[f"{name}-classic"][3]
    assert summary.max_leap_m <= 1e-9 and summary.max_kink_rad <= 1e-9 and summary.max_junction_gap_m <= 1e-9
    pairs = [("2", "5", False), ("3", "6", False)] if name == "diverge" else [("1", "5", True), ("3", "6", True)]
    for rid, cid, at_end in pairs:
        whole, outer, conn = direct.roads[rid], classic.roads[rid], classic.roads[cid]
        assert 15.0 <= conn.length <= 35.0 and outer.length + conn.length == pytest.approx(whole.length, abs=1e-9)
        first, second = (outer, conn) if at_end else (conn, outer)
        s = np.linspace(0.0, whole.length, 301)
        in_first = s < first.length
        for part, m, shift in ((first, in_first, 0.0), (second, ~in_first, first.length)):
            for lane_id in [lid for lid in part.lane_sections[0].lanes if lid != 0]:
                got = part.to_world(s[m] - shift, part.border_t(s[m] - shift, lane_id))
                want = whole.to_world(s[m], whole.border_t(s[m], lane_id))
                assert np.abs(got - want).max() <= 1e-6, f"{name} road {rid} lane {lane_id}"
            assert np.abs(part.superelevation(s[m] - shift) - whole.superelevation(s[m])).max() <= 1e-9


def test_classic_two_way_road_enters_the_junction_from_both_sides(tmp_path: Path) -> None:
    """Left lanes travel against s: they enter the connecting road from the road after it (contactPoint end)."""
    path = tmp_path / "two_way.xodr"
    summary = export_network(_two_way(), None, ExportConfig(), path)
    assert summary.max_junction_gap_m <= 1e-9 and summary.max_leap_m <= 1e-9
    junction = etree.parse(str(path)).getroot().find("junction")
    got = {(c.get("incomingRoad"), c.get("connectingRoad"), c.get("contactPoint")):
           [(int(ll.get("from")), int(ll.get("to"))) for ll in c.findall("laneLink")]
           for c in junction.findall("connection")}
    assert got == {("1", "5", "start"): [(-1, -1)], ("2", "5", "end"): [(1, 1)], ("1", "6", "start"): [(-2, -1)]}
    gaps = junction_gaps(OpenDriveMap.load(path))
    # 3 laneLinks, and the connecting roads' own lane links at both ends (road 5: 2 lanes, road 6: 1)
    assert gaps["lane_links"] == 3 + 2 * 2 + 2 * 1 and gaps["max_junction_gap_m"] <= 1e-9


def test_classic_junction_on_a_short_branch(tmp_path: Path) -> None:
    """A 12 m branch: its connecting road takes half of it at most, both parts stay real roads, gap 0."""
    network, _ = _diverge()
    c = network.roads[2]
    keep = c.s <= 12.0
    bounds = [Boundary(b.id, b.t[keep], b.mark_type, b.mark_width) for b in c.boundaries]
    network.roads[2] = LaneModel(s=c.s[keep], reference=c.reference[keep], boundaries=bounds,
                                 sections=[LaneSection(0.0, 12.0, [0, 1])])
    summary = export_network(network, None, ExportConfig(), tmp_path / "short.xodr")
    odr = OpenDriveMap.load(tmp_path / "short.xodr")
    conn, rest = odr.roads["6"], odr.roads["3"]
    assert conn.junction == "4" and 1.0 <= conn.length <= 6.0 + 1e-3 and rest.length >= 6.0 - 1e-3
    assert summary.max_junction_gap_m <= 1e-9 and summary.max_leap_m <= 1e-9


@pytest.mark.slow
def test_asam_checker_sumo_and_pyxodr_accept_the_classic_junctions(written, tmp_path: Path) -> None:
    """The default form: 0 ASAM issues, SUMO 1.28, pyxodr and CARLA read it without a warning, join the right lanes."""
    try:
        find_qc_venv()
    except InputError as exc:
        pytest.skip(f"ASAM checker environment missing: {exc}")
    from lidar2xodr.check import check_file

    two_way = tmp_path / "two_way.xodr"
    export_network(_two_way(), None, ExportConfig(), two_way)
    maps = {"diverge": written["diverge-classic"][2], "merge": written["merge-classic"][2], "two_way": two_way}
    verdicts = {name: check_file(path) for name, path in maps.items()}
    for name, verdict in verdicts.items():
        assert verdict["ok"], verdict["reasons"]
        assert verdict["asam"]["errors"] == 0 and verdict["asam"]["warnings"] == 0, verdict["asam"]["issues"][:5]
        pyx = verdict["readers"]["pyxodr"]
        assert pyx["ok"], (name, pyx["errors"], pyx["warnings"])
        assert pyx["roads"] == 5 and pyx["junctions"] == 1 and pyx["max_reference_dev_m"] <= 0.005
        carla = verdict["readers"]["carla"]
        if carla["available"]:  # CARLA walks every lane through the junction and joins the linked roads
            assert carla["ok"], (name, carla["errors"], carla["warnings"])
            assert carla["lanes_walked"] == carla["driving_lanes"] > 0 and carla["road_pairs_missing"] == 0
            assert carla["road_pairs"] >= 4 and carla["max_centre_dev_m"] <= 0.005
    sumo = verdicts["diverge"]["readers"]["netconvert"]
    if not sumo["available"]:
        pytest.skip(sumo["note"])
    # SUMO edge "-N" carries road N's right lanes (along s), "N" its left lanes; lane 0 is the rightmost
    expected = {"diverge": {("-1", "-2", "1", "0"), ("-1", "-3", "0", "0")},
                "merge": {("-1", "-2", "0", "1"), ("-3", "-2", "0", "0")},
                "two_way": {("-1", "-2", "1", "0"), ("-1", "-3", "0", "0"), ("2", "1", "0", "0")}}
    nc = find_netconvert()
    for name, path in maps.items():
        sumo = verdicts[name]["readers"]["netconvert"]
        assert sumo["ok"] and sumo["returncode"] == 0, (name, sumo["errors"], sumo["warnings"])
        net = tmp_path / f"{name}.net.xml"
        subprocess.run([str(nc.exe), "--opendrive-files", str(path), "-o", str(net)], check=True,
                       capture_output=True, env=nc.env(), timeout=120)
        joined = {(c.get("from"), c.get("to"), c.get("fromLane"), c.get("toLane"))
                  for c in etree.parse(str(net)).getroot().findall("connection")
                  if not c.get("from").startswith(":") and c.get("dir") != "t"}
        assert joined == expected[name], (name, joined)


def test_direct_junctions_are_not_an_option() -> None:
    """No reader here loads a direct junction (SUMO 1.28, CARLA 0.9.16): the option is gone; naming it fails."""
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="junction_type"):
        ExportConfig(junction_type="direct")


@pytest.mark.slow
def test_the_direct_form_is_valid_but_no_reader_here_loads_it(written) -> None:
    """Why only the classic junction is written: the direct intermediate passes the ASAM checker, but
    SUMO 1.28 stops with "connectingRoad is missing" and CARLA 0.9.16 with IndexError."""
    try:
        find_qc_venv()
    except InputError as exc:
        pytest.skip(f"ASAM checker environment missing: {exc}")
    from lidar2xodr.check import check_file, run_in_subprocess, run_netconvert

    for name in ("diverge", "merge"):
        _, _, path, summary = written[name]
        verdict = check_file(path, readers=False)
        assert verdict["ok"], verdict["reasons"]
        assert verdict["asam"]["errors"] == 0 and verdict["asam"]["warnings"] == 0, verdict["asam"]["issues"][:5]
        assert verdict["continuity"]["max_junction_gap_m"] == pytest.approx(summary.max_junction_gap_m, abs=1e-9)
        sumo, carla = run_netconvert(path), run_in_subprocess("carla", path)
        if sumo["available"]:
            assert sumo["returncode"] != 0 and sumo["errors"]
            assert all(re.search("connectingRoad' is missing", ln) for ln in sumo["errors"]), sumo["errors"]
        if carla["available"]:
            assert not carla["ok"] and carla["errors"] == ["IndexError: _Map_base::at"], carla


def test_a_branch_that_curves_soon_after_the_junction_is_not_turned_by_the_blend() -> None:
    """highway_split s1: the branch leaves straight and curves from 6 m on, and its reference wobbles by 0.1 m
    (both split lines' paint at the gore). Its heading at the junction is its linked lanes' middle over the
    first metres; a quadratic of the reference over 20 m read 0.06 rad there and the blend turned the branch
    0.6 m off its markings."""
    from lidar2xodr.export_opendrive import _Anchor, _blend

    grid = np.arange(0.0, 58.0, 1.0)
    bend = np.where(grid > 6.0, -0.004 * (grid - 6.0) ** 2, 0.0)
    wobble = 0.1 * np.exp(-0.5 * ((grid - 8.0) / 2.0) ** 2)
    ref = np.column_stack([grid, bend + wobble, np.zeros_like(grid)])
    left = np.tile([0.0, 1.0], (len(grid), 1))
    t_grid = {0: LANE / 2 - wobble, 1: -LANE / 2 - wobble}
    anchor = _Anchor(pose=(0.0, 0.0, 0.0), z=0.0, dz=0.0, roll=0.0, lanes=None, blend=(0, 0))  # type: ignore[arg-type]
    out, _ = _blend(grid, ref, left, t_grid, [0, 1], anchor, False, ExportConfig())
    middle_before = ref[:, :2] + (0.5 * (t_grid[0] + t_grid[1]))[:, None] * left
    middle_after = out[:, :2] + (0.5 * (t_grid[0] + t_grid[1]))[:, None] * left
    assert np.abs(middle_after - middle_before).max() <= 0.05


def test_the_blend_turns_a_branch_end_with_the_least_sideways_move() -> None:
    """A branch that ends 0.2 rad off the road it joins (a merge whose junction is reached at an angle) is
    bent, not swung: its end takes the anchor's heading and no point moves sideways by more than 0.15 of
    the turn times the blend length. Rotating the whole branch about its end (the blend before) moved it
    0.26 x that (highway_merge s3: the ramp 2-3.5 m off its markings)."""
    from lidar2xodr.export_opendrive import _Anchor, _blend

    cfg = ExportConfig()
    grid = np.arange(0.0, 80.0, 1.0)
    ref = np.column_stack([grid, np.zeros_like(grid), np.zeros_like(grid)])
    left = np.tile([0.0, 1.0], (len(grid), 1))
    t_grid = {0: np.full(len(grid), LANE / 2), 1: np.full(len(grid), -LANE / 2)}
    turn = 0.2
    anchor = _Anchor(pose=(79.0, 0.0, turn), z=0.0, dz=0.0, roll=0.0, lanes=None, blend=(0, 0))  # type: ignore[arg-type]
    out, _ = _blend(grid, ref, left, t_grid, [0, 1], anchor, True, cfg)
    d = grid[-6:] - grid[-1]
    heading = np.arctan2(np.polyfit(d, out[-6:, 1], 2)[1], np.polyfit(d, out[-6:, 0], 2)[1])
    assert abs(heading - turn) <= 0.01
    assert np.abs(out[:, 1]).max() <= 0.15 * turn * cfg.junction_blend_m
    assert np.allclose(out[grid <= 79.0 - cfg.junction_blend_m, :2], ref[grid <= 79.0 - cfg.junction_blend_m, :2])
