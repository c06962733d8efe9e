"""OpenDRIVE export: written maps read back with pyxodr and the project's reader reproduce the LaneModel."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from lxml import etree
from pyxodr.road_objects.network import RoadNetwork
from scipy.integrate import cumulative_trapezoid, quad
from scipy.spatial import cKDTree

from lidar2xodr.check import polyline_distance
from lidar2xodr.config import ExportConfig
from lidar2xodr.data import Boundary, GeoOrigin, GroundPlanes, LaneModel, LaneSection
from lidar2xodr.errors import InputError
from lidar2xodr.export_opendrive import ExportSummary, export_opendrive
from lidar2xodr.opendrive import OpenDriveMap

LANE = 3.5
EXTRA = (800.0, 1100.0, 100.0)  # appearing lane: start, end, taper length


def _roll(s: np.ndarray) -> np.ndarray:
    return 0.03 * np.sin(s / 600.0)


def _make_road(length: float, kappa: list[tuple[float, float]], z=None, extra: tuple[float, float, float] | None = None,
               lanes: int = 3, origin: GeoOrigin | None = None, step: float = 1.0) -> LaneModel:
    """Road centre from a piecewise-linear curvature (clothoids), boundaries at constant offsets."""
    fine = np.arange(0.0, length + 1e-9, 0.05)
    k = np.interp(fine, [a for a, _ in kappa], [b for _, b in kappa])
    h = 0.4 + cumulative_trapezoid(k, fine, initial=0.0)
    x = 12.0 + cumulative_trapezoid(np.cos(h), fine, initial=0.0)
    y = -7.0 + cumulative_trapezoid(np.sin(h), fine, initial=0.0)
    s = np.arange(0.0, length + 1e-9, step)
    idx = np.round(s / 0.05).astype(int)
    zz = z(s) if z is not None else np.zeros_like(s)
    ref = np.stack([x[idx], y[idx], zz], axis=1)
    ts = [lanes * LANE / 2 - i * LANE for i in range(lanes + 1)]
    bounds = [Boundary(i, np.full(len(s), t), "solid" if i in (0, lanes) else "broken",
                       0.3 if i in (0, lanes) else 0.15, 6.0 if 0 < i < lanes else None,
                       12.0 if 0 < i < lanes else None) for i, t in enumerate(ts)]
    ids = list(range(lanes + 1))
    sections = [LaneSection(0.0, float(s[-1]), ids)]
    if extra:
        a, b, taper = extra
        d = np.clip(np.minimum(s - a, b - s) / taper, 0.0, 1.0)
        w = np.where((s >= a) & (s <= b), LANE * d * d * (3 - 2 * d), np.nan)
        bounds.append(Boundary(lanes + 1, ts[-1] - w, "solid", 0.3))
        sections = [LaneSection(0.0, a, ids), LaneSection(a, b, ids + [lanes + 1]), LaneSection(b, float(s[-1]), ids)]
    return LaneModel(s=s, reference=ref, boundaries=bounds, sections=sections, origin=origin or GeoOrigin())


def _planes(model: LaneModel, seed: int = 0) -> GroundPlanes:
    """One ground plane every 2.5 m below a car in lane -2, rolled by _roll(s), with noise and outliers."""
    rng = np.random.default_rng(seed)
    idx = np.arange(0, len(model.s), 2)
    xy = model.reference[:, :2]
    tan = np.gradient(xy, model.s, axis=0)
    left = np.stack([-tan[:, 1], tan[:, 0]], axis=1) / np.linalg.norm(tan, axis=1)[:, None]
    roll = _roll(model.s[idx]) + rng.normal(0.0, 0.004, len(idx))
    roll[rng.choice(len(idx), 20, replace=False)] += 0.2  # RANSAC failures
    normals = np.column_stack([-np.sin(roll)[:, None] * left[idx], np.cos(roll)])
    points = model.reference[idx] + np.column_stack([-1.75 * left[idx], np.zeros(len(idx))])
    return GroundPlanes(times=1.7e9 + model.s[idx] / 25.0, normals_world=normals, points_world=points)


def _two_way_road() -> LaneModel:
    """2 lanes against s, a solid divider, 3 lanes along s (+ an added lane on the right mid-way)."""
    model = _make_road(1600.0, [(0, 0), (300, 0), (600, -1 / 1500), (1600, -1 / 1500)], lanes=5,
                       extra=(500.0, 1100.0, 120.0))
    model.boundaries[2].mark_type, model.boundaries[2].mark_width = "solid", 0.3
    model.boundaries[2].dash_length = model.boundaries[2].gap_length = None
    for sec in model.sections:
        sec.divider_id = 2
    return model


ROADS = {
    "straight": lambda: _make_road(800.0, [(0, 0), (800, 0)]),
    "r2000": lambda: _make_road(1200.0, [(0, 1 / 2000), (1200, 1 / 2000)],
                                origin=GeoOrigin(48.78, 9.18, 250.0, "+proj=tmerc +lat_0=48.78 +lon_0=9.18 +k=1 "
                                                 "+x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs")),
    "scurve": lambda: _make_road(1500.0, [(0, 0), (200, 0), (350, 1 / 800), (650, 1 / 800), (950, -1 / 800),
                                          (1250, -1 / 800), (1400, 0), (1500, 0)]),
    "clothoid5km": lambda: _make_road(5000.0, [(0, 0), (400, 0), (600, 1 / 1500), (1500, 1 / 1500), (1800, 0),
                                               (2300, 0), (2600, -1 / 2500), (3600, -1 / 2500), (3900, 0),
                                               (5000, 0)],
                                      z=lambda s: 15.0 * np.sin(2 * np.pi * s / 4000.0) + 0.01 * s),
    "extra": lambda: _make_road(2000.0, [(0, 1 / 3000), (2000, 1 / 3000)], extra=EXTRA),
    "twoway": _two_way_road,
}
FOLDED = ("twoway",)


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[LaneModel, Path, ExportSummary]]:
    out = tmp_path_factory.mktemp("xodr")
    res = {}
    for name, make in ROADS.items():
        model = make()
        planes = _planes(model) if name == "clothoid5km" else None
        path = out / f"{name}.xodr"
        res[name] = (model, path, export_opendrive(model, planes, ExportConfig(), path))
    for name in FOLDED:  # the opt-in fold of appearing lanes into the section before (test_export_sections.py)
        model = ROADS[name]()
        path = out / f"{name}_folded.xodr"
        res[f"{name}_folded"] = (model, path, export_opendrive(model, None, ExportConfig(fold_appearing_lanes=True),
                                                               path))
    return res


def _left_normals(model: LaneModel) -> np.ndarray:
    tan = np.gradient(model.reference[:, :2], model.s, axis=0)
    return np.stack([-tan[:, 1], tan[:, 0]], axis=1) / np.linalg.norm(tan, axis=1)[:, None]


def _boundary_points(model: LaneModel, section: LaneSection, bid: int, trim: float = 1.0) -> np.ndarray:
    t = next(b.t for b in model.boundaries if b.id == bid)
    m = (model.s >= section.s_start + trim) & (model.s <= section.s_end - trim) & np.isfinite(t)
    return model.reference[m, :2] + t[m, None] * _left_normals(model)[m]


def _geometries(path: Path) -> list[dict[str, float]]:
    root = etree.parse(str(path)).getroot()
    out = []
    for g in root.iterfind("road/planView/geometry"):
        pp = g.find("paramPoly3")
        assert pp is not None, "every geometry is a paramPoly3"
        row = {k: float(g.get(k)) for k in ("s", "x", "y", "hdg", "length")}
        row.update({k: float(pp.get(k)) for k in ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV")})
        row["pRange"] = pp.get("pRange")
        out.append(row)
    return out


def _end(g: dict[str, float]) -> tuple[float, float, float]:
    eu = g["aU"] + g["bU"] + g["cU"] + g["dU"]
    ev = g["aV"] + g["bV"] + g["cV"] + g["dV"]
    du = g["bU"] + 2 * g["cU"] + 3 * g["dU"]
    dv = g["bV"] + 2 * g["cV"] + 3 * g["dV"]
    c, s = math.cos(g["hdg"]), math.sin(g["hdg"])
    return g["x"] + c * eu - s * ev, g["y"] + s * eu + c * ev, g["hdg"] + math.atan2(dv, du)


@pytest.mark.parametrize("name", list(ROADS))
def test_reference_line_reproduced_by_both_readers(written, name: str) -> None:
    model, path, summary = written[name]
    road = next(iter(OpenDriveMap.load(path).roads.values()))
    s = np.linspace(0.0, road.length, int(road.length / 0.05) + 1)
    x, y, _ = road.reference(s)
    dev = polyline_distance(model.reference[:, :2], np.stack([x, y], axis=1))
    assert dev.max() <= 0.02, f"project reader: reference off by {dev.max():.4f} m"
    assert summary.max_reference_dev_m <= 0.02
    ref = RoadNetwork(str(path), resolution=0.2).get_roads()[0].reference_line
    dev_pyxodr = polyline_distance(model.reference[:, :2], ref[:, :2])
    assert dev_pyxodr.max() <= 0.02, f"pyxodr: reference off by {dev_pyxodr.max():.4f} m"
    assert abs(road.length - (model.s[-1] - model.s[0])) < 0.05


@pytest.mark.parametrize("name", ["scurve", "clothoid5km", "extra", "twoway"])
def test_lane_borders_reproduce_boundaries(written, name: str) -> None:
    model, path, summary = written[name]
    sections = OpenDriveMap.load(path).sample(step=0.05)
    assert len(sections) == len(model.sections)
    worst = 0.0
    for sec, sampled in zip(model.sections, sections, strict=True):
        centre = 0 if sec.divider_id is None else sec.boundary_ids.index(sec.divider_id)
        for i, bid in enumerate(sec.boundary_ids):
            pts = _boundary_points(model, sec, bid)
            dev = polyline_distance(pts, sampled.border_xyz[centre - i][:, :2])
            worst = max(worst, float(dev.max()))
    assert worst <= 0.03, f"lane border off by {worst:.4f} m"
    assert summary.max_border_dev_m <= 0.03


def test_lane_borders_in_pyxodr(written) -> None:
    model, path, _ = written["extra"]
    road = RoadNetwork(str(path), resolution=0.2).get_roads()[0]
    assert len(road.lane_sections) == 3
    offset_dev = polyline_distance(_boundary_points(model, model.sections[0], 0), road.lane_offset_line[:, :2])
    assert offset_dev.max() <= 0.03
    for sec, ls in zip(model.sections, road.lane_sections, strict=True):
        lanes = {lane.id: lane for lane in ls.right_lanes}
        assert sorted(lanes) == list(range(-(len(sec.boundary_ids) - 1), 0))
        for i, bid in enumerate(sec.boundary_ids[1:], start=1):
            dev = polyline_distance(_boundary_points(model, sec, bid, trim=2.0), lanes[-i].boundary_line[:, :2])
            assert dev.max() <= 0.03, f"pyxodr: lane {-i} border off by {dev.max():.4f} m"


@pytest.mark.parametrize("name", list(ROADS))
def test_pieces_join_without_leaps_or_kinks(written, name: str) -> None:
    _, path, summary = written[name]
    geoms = _geometries(path)
    assert len(geoms) == summary.pieces == max(1, math.ceil(len(ROADS[name]().s) / 100.5))
    for prev, nxt in zip(geoms, geoms[1:], strict=False):
        x, y, h = _end(prev)
        assert math.hypot(nxt["x"] - x, nxt["y"] - y) <= 1e-3
        start_h = nxt["hdg"] + math.atan2(nxt["bV"], nxt["bU"])
        assert abs((start_h - h + math.pi) % (2 * math.pi) - math.pi) <= 1e-3
        assert nxt["s"] == pytest.approx(prev["s"] + prev["length"], abs=1e-9)
    assert summary.max_leap_m <= 1e-3 and summary.max_kink_rad <= 1e-3
    assert summary.max_leap_m < 1e-9 and summary.max_kink_rad < 1e-12, "exact by construction, not by luck"


@pytest.mark.parametrize("name", ["scurve", "clothoid5km"])
def test_declared_length_is_arc_length(written, name: str) -> None:
    _, path, summary = written[name]
    for g in _geometries(path):
        assert g["pRange"] == "normalized"
        assert g["aU"] == g["aV"] == g["bV"] == 0.0, "hdg is the start tangent"
        arc = quad(lambda p, g=g: math.hypot(g["bU"] + 2 * g["cU"] * p + 3 * g["dU"] * p * p,
                                             g["bV"] + 2 * g["cV"] * p + 3 * g["dV"] * p * p), 0.0, 1.0)[0]
        assert abs(arc - g["length"]) <= 1e-3
    assert summary.max_length_error_m <= 1e-6
    assert abs(_geometries(path)[0]["x"]) < 100 and abs(_geometries(path)[0]["y"]) < 100, "local coordinates"


def _sections_xml(path: Path) -> list[etree._Element]:
    return etree.parse(str(path)).getroot().findall("road/lanes/laneSection")


def _width(lane: etree._Element, ds: float) -> float:
    recs = sorted((float(w.get("sOffset")), w) for w in lane.findall("width"))
    off, w = [r for r in recs if r[0] <= ds + 1e-9][-1]
    d = ds - off
    return sum(float(w.get(k)) * d**i for i, k in enumerate("abcd"))


def test_appearing_lane_starts_and_ends_at_zero_width_and_links_both_ways(written) -> None:
    _, path, _ = written["extra"]
    secs = _sections_xml(path)
    assert [len(s.findall("right/lane")) for s in secs] == [3, 4, 3]
    new = secs[1].find("right/lane[@id='-4']")
    assert new.find("link/predecessor") is None and new.find("link/successor") is None
    length = float(secs[2].get("s")) - float(secs[1].get("s"))
    assert abs(_width(new, 0.0)) < 1e-9 and abs(_width(new, length)) < 1e-9
    assert _width(new, length / 2) == pytest.approx(LANE, abs=0.01)
    for a, b in zip(secs, secs[1:], strict=False):
        pairs_fwd = {(int(ln.get("id")), int(ln.find("link/successor").get("id")))
                     for ln in a.findall("right/lane") if ln.find("link/successor") is not None}
        pairs_back = {(int(ln.find("link/predecessor").get("id")), int(ln.get("id")))
                      for ln in b.findall("right/lane") if ln.find("link/predecessor") is not None}
        assert pairs_fwd == pairs_back == {(-1, -1), (-2, -2), (-3, -3)}
        for lid in (-1, -2, -3):  # linked lanes continue with the same width
            la, lb = a.find(f"right/lane[@id='{lid}']"), b.find(f"right/lane[@id='{lid}']")
            end = float(b.get("s")) - float(a.get("s"))
            assert _width(la, end) == pytest.approx(_width(lb, 0.0), abs=1e-6)


def test_road_marks_and_lane_offset(written) -> None:
    _, path, _ = written["extra"]
    root = etree.parse(str(path)).getroot()
    sec = root.find("road/lanes/laneSection")
    centre = sec.find("center/lane/roadMark")
    assert centre.get("type") == "solid" and float(centre.get("width")) == 0.3
    inner = sec.find("right/lane[@id='-1']/roadMark")
    assert inner.get("type") == "broken" and inner.get("laneChange") == "both"
    line = inner.find("type/line")
    assert float(line.get("length")) == 6.0 and float(line.get("space")) == 12.0
    assert sec.find("right/lane[@id='-3']/roadMark").get("type") == "solid"
    assert sec.find("left") is None, "a one-way carriageway has only right lanes"
    offsets = root.findall("road/lanes/laneOffset")
    assert offsets and float(offsets[0].get("a")) == pytest.approx(1.5 * LANE, abs=0.01)


def test_header_profiles_and_geo_reference(written, tmp_path: Path) -> None:
    _, path, _ = written["r2000"]
    root = etree.parse(str(path)).getroot()
    header = root.find("header")
    assert (header.get("revMajor"), header.get("revMinor")) == ("1", "8")
    assert header.get("date") is None, "no time in the input: no date (same bytes every run)"
    assert "+lat_0=48.78" in header.find("geoReference").text
    assert float(header.get("north")) > float(header.get("south"))
    road = root.find("road")
    assert road.find("elevationProfile/elevation") is not None
    assert road.find("lateralProfile/superelevation") is not None
    assert float(road.find("lateralProfile/superelevation").get("a")) == 0.0

    _, path5, _ = written["clothoid5km"]
    assert etree.parse(str(path5)).getroot().find("header").get("date", "").startswith("2023-11-14")
    text = path5.read_text()
    assert "no GNSS" in text and "+lat_0=0 +lon_0=0" in text


def test_elevation_and_superelevation(written) -> None:
    model, path, _ = written["clothoid5km"]
    road = next(iter(OpenDriveMap.load(path).roads.values()))
    s = model.s[5:-5]
    z_err = np.abs(road.elevation(s) - model.reference[5:-5, 2])
    assert z_err.max() <= 0.02
    starts = road.elevation_profile.starts[1:]
    for der in (0, 1):  # continuous in value and slope
        jump = road.elevation_profile(starts, der) - road.elevation_profile(starts - 1e-7, der)
        assert np.abs(jump).max() < 1e-5
    roll = road.superelevation(s)
    assert np.abs(roll - _roll(s)).max() <= 0.004, "left side up is positive, noise and outliers smoothed"
    assert np.corrcoef(roll, _roll(s))[0, 1] > 0.99
    starts = road.superelevation_profile.starts[1:]
    assert len(starts) > 10
    jump = road.superelevation_profile(starts) - road.superelevation_profile(starts - 1e-7)
    assert np.abs(jump).max() < 1e-6


def test_elevation_follows_short_vertical_curves(tmp_path: Path) -> None:
    """Elevation records every `elevation_record_m` follow a 150 m crest/sag wave; one cubic per 100 m piece cannot."""
    model = _make_road(900.0, [(0, 0), (900, 0)], z=lambda s: 1.5 * np.sin(2 * np.pi * s / 150.0))
    s = model.s[5:-5]
    errs = {}
    for rec in (None, 25.0):
        path = tmp_path / f"z{rec}.xodr"
        export_opendrive(model, None, ExportConfig(elevation_record_m=rec), path)
        road = next(iter(OpenDriveMap.load(path).roads.values()))
        errs[rec] = float(np.abs(road.elevation(s) - model.reference[5:-5, 2]).max())
    assert errs[25.0] <= 0.02 and errs[None] > 0.1, errs


def _demo_lane_model(demo: OpenDriveMap) -> tuple[LaneModel, GroundPlanes]:
    """What a perfect lanes stage would report for the project's demo road: centre of the three
    regular lanes as reference, horizontal offsets of the driving-lane borders, ground planes."""
    road = next(iter(demo.roads.values()))
    s = np.linspace(0.0, road.length, int(road.length) + 1)
    ref = road.to_world(s, -1.5 * 3.75)
    _, _, h = road.reference(s)
    left = np.stack([-np.sin(h), np.cos(h)], axis=1)
    added = road.lane_sections[1]
    ts = []
    for lid in (0, -1, -2, -3, -4):
        t = road.border_t(s, lid)
        th = np.sum((road.to_world(s, np.nan_to_num(t))[:, :2] - ref[:, :2]) * left, axis=1)
        if lid == -4:
            t = np.where((s >= added.s) & (s < added.s_end), t, np.nan)
        ts.append(np.where(np.isfinite(t), th, np.nan))
    marks = [("solid", 0.3), ("broken", 0.15), ("broken", 0.15), ("solid", 0.3), ("solid", 0.3)]
    bounds = [Boundary(i, t, kind, w, 6.0 if kind == "broken" else None, 12.0 if kind == "broken" else None)
              for i, (t, (kind, w)) in enumerate(zip(ts, marks, strict=True))]
    sections = [LaneSection(ls.s, ls.s_end, [0, 1, 2, 3] + ([4] if k == 1 else []))
                for k, ls in enumerate(road.lane_sections)]
    idx = np.arange(0, len(s), 3)
    roll = road.superelevation(s[idx])
    planes = GroundPlanes(times=1.7e9 + s[idx] / 25.0, normals_world=np.column_stack(
        [-np.sin(roll)[:, None] * left[idx], np.cos(roll)]), points_world=ref[idx])
    return LaneModel(s=s, reference=ref, boundaries=bounds, sections=sections,
                     origin=GeoOrigin(proj=demo.geo_reference)), planes


def test_demo_road_round_trip(tmp_path: Path) -> None:
    """Demo motorway (clothoids, crest, banking, added lane) -> LaneModel -> export -> the paper's metric."""
    from lidar2xodr.config import EvaluationConfig
    from lidar2xodr.demo_road import write_demo_road
    from lidar2xodr.evaluation import compare_maps

    demo_path = write_demo_road(tmp_path / "demo.xodr")
    demo = OpenDriveMap.load(demo_path)
    model, planes = _demo_lane_model(demo)
    out = tmp_path / "rt.xodr"
    export_opendrive(model, planes, ExportConfig(), out)
    metrics = compare_maps(out, demo_path, EvaluationConfig())
    assert metrics["boundaries"]["rmse_m"] < 0.005 and metrics["boundaries"]["max_m"] < 0.02
    assert metrics["lane_count_agreement"] > 0.99 and metrics["coverage"] > 0.99
    gen_road, demo_road = next(iter(OpenDriveMap.load(out).roads.values())), next(iter(demo.roads.values()))
    s = np.linspace(5.0, demo_road.length - 5.0, 2000)
    assert np.abs(gen_road.superelevation(s) - demo_road.superelevation(s)).max() < 0.002
    gen_edge = np.vstack([sec.border_xyz[-3] for sec in OpenDriveMap.load(out).sample(0.5)])[10:-10]
    demo_edge = np.vstack([sec.border_xyz[-3] for sec in demo.sample(0.05)])
    _, i = cKDTree(demo_edge[:, :2]).query(gen_edge[:, :2])
    assert np.abs(gen_edge[:, 2] - demo_edge[i, 2]).max() < 0.02, "banked edge line at the right height"


def test_same_input_same_bytes(tmp_path: Path) -> None:
    model = ROADS["extra"]()
    planes = _planes(model)
    a, b = tmp_path / "a.xodr", tmp_path / "b.xodr"
    export_opendrive(model, planes, ExportConfig(), a)
    export_opendrive(ROADS["extra"](), _planes(model), ExportConfig(), b)
    assert a.read_bytes() == b.read_bytes()


def test_shoulder_and_border_lanes(tmp_path: Path) -> None:
    path = tmp_path / "shoulder.xodr"
    export_opendrive(ROADS["extra"](), None, ExportConfig(right_shoulder_m=2.5, left_border_m=0.5), path)
    secs = _sections_xml(path)
    for k, sec in enumerate(secs):
        right = sec.findall("right/lane")
        assert right[-1].get("type") == "shoulder" and _width(right[-1], 0.0) == 2.5
        assert sec.find("left/lane[@id='1']").get("type") == "border"
        if k:
            prev_id = secs[k - 1].findall("right/lane")[-1].get("id")
            assert right[-1].find("link/predecessor").get("id") == prev_id


def test_bad_input_is_one_error_and_writes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "bad.xodr"
    model = ROADS["straight"]()
    model.s[10] = model.s[9]
    with pytest.raises(InputError, match="strictly increasing"):
        export_opendrive(model, None, ExportConfig(), path)
    model = ROADS["straight"]()
    model.sections[0].boundary_ids = [0, 1, 7]
    with pytest.raises(InputError, match="unknown boundaries"):
        export_opendrive(model, None, ExportConfig(), path)
    model = ROADS["straight"]()
    model.sections[0].boundary_ids = [3, 2, 1, 0]
    with pytest.raises(InputError, match="left to right"):
        export_opendrive(model, None, ExportConfig(), path)
    assert not path.exists() and not list(tmp_path.iterdir())


@pytest.mark.slow
def test_asam_checker_and_independent_readers_accept_the_map(written) -> None:
    """0 ASAM issues; SUMO netconvert and pyxodr read a one-way road with an appearing lane without a warning."""
    from lidar2xodr.check import check_file

    _, path, _ = written["extra"]
    verdict = check_file(path)
    assert verdict["ok"], verdict
    assert verdict["asam"]["errors"] == 0 and verdict["asam"]["warnings"] == 0, verdict["asam"]["issues"][:5]
    pyx = verdict["readers"]["pyxodr"]
    assert pyx["ok"] and pyx["max_reference_dev_m"] <= 0.005, pyx
    sumo = verdict["readers"]["netconvert"]
    if not sumo["available"]:
        pytest.skip(sumo["note"])
    assert sumo["ok"], (sumo["errors"], sumo["warnings"])
    # an edge per lane section, more where SUMO splits the tapers at its minimum lane width (1.8 m)
    assert sumo["edges"] >= 3 and sumo["lanes"] >= 3 + 4 + 3, (sumo["edges"], sumo["lanes"])


@pytest.mark.slow
def test_sumo_warns_about_an_appearing_lane_unless_folded(written) -> None:
    """What the opt-in fold (export_sections.py) buys: with the appearing lane in a section of its own SUMO warns.

    SUMO (1.15 and 1.28) gives each lane at most one successor, so a lane that appears has no incoming connection;
    it warns when the node has more than one incoming edge, which on a two-way road it always has (the
    left lanes' edge). Linking the appearing lane to its neighbour would be an ASAM error
    (road.lane.link.new_lane_appear). Folded into the section before at width 0, it loads cleanly.
    """
    from lidar2xodr.check import check_file

    for name, n_warnings in (("twoway_folded", 0), ("twoway", 1)):
        _, path, _ = written[name]
        verdict = check_file(path)
        assert verdict["ok"] and verdict["asam"]["errors"] == 0, verdict["reasons"]
        assert verdict["asam"]["warnings"] == 0, verdict["asam"]["issues"][:5]
        assert verdict["readers"]["pyxodr"]["ok"], verdict["readers"]["pyxodr"]
        sumo = verdict["readers"]["netconvert"]
        if not sumo["available"]:
            pytest.skip(sumo["note"])
        assert sumo["returncode"] == 0 and not sumo["errors"]
        assert len(sumo["warnings"]) == n_warnings, (name, sumo["warnings"])
    assert re.fullmatch(r"Warning: Lane '-1#1_0' is not connected from any incoming edge at junction '1#1'\.",
                        sumo["warnings"][0]), sumo["warnings"]


def test_a_line_whose_paint_changes_gets_its_mark_per_section(tmp_path: Path) -> None:
    """The right edge (boundary 3, solid) is the broken divider of the lane added beside it in the middle
    section (`LaneSection.marks`): lane -3 carries it broken there and solid before and after."""
    model = _make_road(1500.0, [(0.0, 0.0), (1500.0, 0.0)], extra=EXTRA)
    model.sections[1].marks = {3: "broken"}
    path = tmp_path / "marks.xodr"
    export_opendrive(model, None, ExportConfig(), path)
    secs = _sections_xml(path)
    assert [sec.find("right/lane[@id='-3']/roadMark").get("type") for sec in secs] == ["solid", "broken", "solid"]
    assert secs[1].find("right/lane[@id='-3']/roadMark").get("laneChange") == "both"
    assert secs[1].find("right/lane[@id='-4']/roadMark").get("type") == "solid"
    model.sections[0].marks = {4: "broken"}
    with pytest.raises(InputError, match="lane section 0: mark 'broken' of boundary 4"):
        export_opendrive(model, None, ExportConfig(), tmp_path / "bad.xodr")


def test_section_marks_survive_lanes_json(tmp_path: Path) -> None:
    """`lanes` + `export` write what `build` writes: a model with a section's own mark exports the same
    bytes straight and through lanes.json."""
    from lidar2xodr.lanes import load_lanes, save_lanes

    model = _make_road(1500.0, [(0.0, 0.0), (1500.0, 0.0)], extra=EXTRA)
    model.sections[1].marks = {3: "broken"}
    export_opendrive(model, None, ExportConfig(), tmp_path / "direct.xodr")
    save_lanes(model, tmp_path / "lanes.json")
    export_opendrive(load_lanes(tmp_path / "lanes.json"), None, ExportConfig(), tmp_path / "via.xodr")
    assert (tmp_path / "via.xodr").read_bytes() == (tmp_path / "direct.xodr").read_bytes()
    assert b'type="broken"' in (tmp_path / "via.xodr").read_bytes()


def test_two_way_road_has_left_lanes_on_the_divider(written) -> None:
    """Lane 0 on the divider: left lanes 1, 2 outwards, right lanes -1.. , links only on their own side."""
    model, path, _ = written["twoway"]
    root = etree.parse(str(path)).getroot()
    assert root.find("road").get("rule") == "RHT"
    secs = _sections_xml(path)
    assert [sorted(int(ln.get("id")) for ln in sec.findall("left/lane")) for sec in secs] == [[1, 2]] * 3
    assert [len(sec.findall("right/lane")) for sec in secs] == [3, 4, 3]
    assert secs[0].find("center/lane/roadMark").get("type") == "solid"
    assert secs[0].find("left/lane[@id='1']/roadMark").get("type") == "broken"
    assert secs[0].find("left/lane[@id='2']/roadMark").get("type") == "solid"
    offsets = root.findall("road/lanes/laneOffset")
    assert float(offsets[0].get("a")) == pytest.approx(0.5 * LANE, abs=0.01), "t of the divider"
    for a, b in zip(secs, secs[1:], strict=False):
        fwd = {(int(ln.get("id")), int(ln.find("link/successor").get("id")))
               for ln in a.findall("*/lane") if ln.find("link/successor") is not None}
        back = {(int(ln.find("link/predecessor").get("id")), int(ln.get("id")))
                for ln in b.findall("*/lane") if ln.find("link/predecessor") is not None}
        assert fwd == back == {(2, 2), (1, 1), (-1, -1), (-2, -2), (-3, -3)}
    from lidar2xodr.check import check_file

    verdict = check_file(path)
    assert verdict["ok"] and verdict["asam"]["errors"] == 0, verdict["asam"]["issues"][:5]


def test_divider_must_be_an_inner_boundary(tmp_path: Path) -> None:
    model = _two_way_road()
    model.sections[0].divider_id = 0
    with pytest.raises(InputError, match="divider"):
        export_opendrive(model, None, ExportConfig(), tmp_path / "x.xodr")
    assert not (tmp_path / "x.xodr").exists()


def test_a_width_record_dipping_below_zero_is_replaced_by_a_non_negative_one() -> None:
    """A lane opening from zero width: the smoothing spline's first record overshoots to -1.25 cm
    (the sweep's refused maps); it becomes a non-negative cubic with the same end values."""
    from lidar2xodr.export_opendrive import _non_negative, _Records

    rec = _Records(np.array([0.0, 20.0]), np.array([[0.0, -0.01, 0.002, 0.0], [0.6, 0.07, -0.002, 0.0]]))
    before = rec(np.linspace(0.0, 20.0, 2001))
    assert before.min() < -0.01
    fixed = _non_negative(rec, 40.0)
    s = np.linspace(0.0, 40.0, 8001)
    assert fixed(s).min() >= -1e-12
    assert fixed(np.array([0.0]))[0] == 0.0 and fixed(np.array([20.0]))[0] == pytest.approx(0.6)
    assert fixed(np.array([20.0 - 1e-9]))[0] == pytest.approx(0.6, abs=1e-6), "the width jumps at the record's end"
    assert np.array_equal(fixed.coeffs[1], rec.coeffs[1]), "a record that does not dip is left as it is"
    untouched = _Records(np.array([0.0]), np.array([[3.5, 0.0, 0.0, 0.0]]))
    assert np.array_equal(_non_negative(untouched, 100.0).coeffs, untouched.coeffs)


def test_a_lane_whose_markings_open_by_themselves_follows_them() -> None:
    """The smoothstep opens a lane whose markings start at full width; markings that open by
    themselves over a shorter stretch are not pulled under it (an exit's edge 0.5 m inside)."""
    from lidar2xodr.export_opendrive import _taper

    dist = np.arange(0.0, 120.0, 1.0)
    linear = np.clip(dist / 40.0, 0.0, 1.0) * 3.5
    assert np.array_equal(_taper(linear, dist, 60.0), linear)
    full = np.full(len(dist), 3.5)
    capped = _taper(full, dist, 60.0)
    assert capped[0] == 0.0 and 1.7 < capped[30] < 1.8 and np.all(capped[60:] == 3.5)
    cut = np.clip(dist / 10.0, 0.0, 1.0) * 3.5  # full within 10 m: a line cut where a lane leaves
    assert np.array_equal(_taper(cut, dist, 60.0), np.minimum(cut, capped))
    swing = np.where(dist < 20.0, 2.2, linear)  # starts wide, narrows, then opens: a ramp's line seen across
    assert np.array_equal(_taper(swing, dist, 60.0), np.minimum(swing, capped))
