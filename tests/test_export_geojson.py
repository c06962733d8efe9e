"""GeoJSON export: RFC 7946 structure, WGS84 coordinates that go back to the map frame, valid polygons."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyproj
import pytest
from scipy.spatial import cKDTree
from shapely.geometry import LineString, Polygon, shape
from test_export_lanelet2 import _two_way
from test_export_network import _diverge

from lidar2xodr.cli import app
from lidar2xodr.config import ExportConfig, InterchangeConfig
from lidar2xodr.demo_road import GEO_REFERENCE, write_demo_road
from lidar2xodr.errors import InputError
from lidar2xodr.export_geojson import export_geojson
from lidar2xodr.export_opendrive import export_network
from lidar2xodr.opendrive import OpenDriveMap


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("geojson")
    xodr = write_demo_road(out / "demo.xodr")
    path = out / "demo.geojson"
    export_geojson(xodr, path)
    return xodr, json.loads(path.read_text())


def _by_kind(fc: dict, kind: str) -> list[dict]:
    return [f for f in fc["features"] if f["properties"]["kind"] == kind]


def test_feature_collection_is_rfc7946(demo) -> None:
    _, fc = demo
    assert fc["type"] == "FeatureCollection" and "crs" not in fc
    assert {f["geometry"]["type"] for f in fc["features"]} == {"LineString", "Polygon"}
    for f in fc["features"]:
        assert f["type"] == "Feature" and isinstance(f["properties"], dict)
        coords = f["geometry"]["coordinates"]
        flat = np.array(coords[0] if f["geometry"]["type"] == "Polygon" else coords)
        assert flat.shape[1] == 2
        # lon first: the demo road lies near Stuttgart, 9.18 E 48.78 N
        assert np.all(np.abs(flat[:, 0] - 9.18) < 0.1) and np.all(np.abs(flat[:, 1] - 48.78) < 0.1)


def test_coordinates_go_back_to_the_map_frame_within_1_cm(demo) -> None:
    """Independent check with pyproj: WGS84 -> the demo road's PROJ frame lands on the OpenDRIVE borders."""
    xodr, fc = demo
    road = OpenDriveMap.load(xodr).roads["1"]
    back = pyproj.Transformer.from_crs("EPSG:4326", pyproj.CRS.from_proj4(GEO_REFERENCE), always_xy=True)
    ref = np.array(_by_kind(fc, "reference_line")[0]["geometry"]["coordinates"])
    x, y = back.transform(ref[:, 0], ref[:, 1])
    s = np.linspace(0.0, road.length, len(ref))
    rx, ry, _ = road.reference(s)
    assert np.hypot(x - rx, y - ry).max() < 0.01
    for f in _by_kind(fc, "boundary")[:12]:
        p = f["properties"]
        ls = road.lane_sections[p["section"]]
        xy = np.array(f["geometry"]["coordinates"])
        bx, by = back.transform(xy[:, 0], xy[:, 1])
        # the border densely sampled over the section (its closed end as the limit from inside)
        ss = np.linspace(ls.s, ls.s_end - 1e-7, int((ls.s_end - ls.s) * 100) + 1)
        world = road.to_world(ss, road.border_t(ss, p["lane"]))[:, :2]
        d, _ = cKDTree(world).query(np.column_stack([bx, by]))
        assert d.max() < 0.01, (p, d.max())


def test_lane_polygons_are_valid_counter_clockwise_and_counted(demo) -> None:
    xodr, fc = demo
    odr = OpenDriveMap.load(xodr)
    lanes = _by_kind(fc, "lane")
    for f in lanes:
        ring = f["geometry"]["coordinates"][0]
        assert ring[0] == ring[-1] and len(ring) >= 4
        poly = shape(f["geometry"])
        assert isinstance(poly, Polygon) and poly.is_valid, f["properties"]
        assert poly.exterior.is_ccw, f["properties"]
        p = f["properties"]
        assert 0.0 <= p["width_min_m"] <= p["width_max_m"] < 10.0
    expected = {(rid, k, lid) for rid, r in odr.roads.items() for k, ls in enumerate(r.lane_sections)
                for lid in ls.lanes if lid != 0}
    assert {(f["properties"]["road"], f["properties"]["section"], f["properties"]["lane"]) for f in lanes} == expected
    driving = [f for f in lanes if f["properties"]["type"] == "driving"]
    assert sorted(len([f for f in driving if f["properties"]["section"] == k]) for k in range(3)) == [3, 3, 4]
    added = next(f for f in driving if f["properties"]["lane"] == -4)["properties"]
    assert added["width_min_m"] == 0.0 and added["width_max_m"] == pytest.approx(3.75, abs=1e-3)


def test_boundaries_carry_their_marks(demo) -> None:
    _, fc = demo
    marks = {(f["properties"]["lane"], f["properties"]["mark_type"]) for f in _by_kind(fc, "boundary")}
    assert (0, "solid") in marks and (-1, "broken") in marks
    for f in _by_kind(fc, "boundary"):
        assert LineString(f["geometry"]["coordinates"]).length > 0


def test_same_map_same_bytes_and_junction_maps(tmp_path: Path) -> None:
    xodr = tmp_path / "diverge.xodr"
    export_network(_diverge()[0], None, ExportConfig(), xodr)
    a, b = tmp_path / "a.geojson", tmp_path / "b.geojson"
    sa = export_geojson(xodr, a)
    export_geojson(xodr, b)
    assert a.read_bytes() == b.read_bytes()
    fc = json.loads(a.read_text())
    odr = OpenDriveMap.load(xodr)
    assert len(_by_kind(fc, "reference_line")) == len(odr.roads) == sa.reference_lines
    assert all(shape(f["geometry"]).is_valid for f in _by_kind(fc, "lane"))


def test_no_geo_reference_is_a_clear_error(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    xodr = _two_way(tmp_path / "local.xodr")
    out = tmp_path / "local.geojson"
    with pytest.raises(InputError, match="no geoReference"):
        export_geojson(xodr, out, InterchangeConfig())
    res = CliRunner().invoke(app, ["export-geojson", str(xodr), "-o", str(out)])
    assert res.exit_code == 2 and "local.xodr" in res.output and "Traceback" not in res.output
    assert not out.exists()


def test_carla_style_geo_reference_is_a_tmerc_at_its_origin() -> None:
    """CARLA writes '+lat_0=49 +lon_0=8' without +proj: read as a transverse Mercator there."""
    from lidar2xodr.georeference import ToWgs84

    geo = ToWgs84("+lat_0=4.9000000000000000e+1 +lon_0=8.0000000000000000e+0", "Town04.xodr")
    assert (geo.origin_lon, geo.origin_lat) == pytest.approx((8.0, 49.0), abs=1e-12)
    lon, lat = geo.lonlat(np.array([0.0, 1000.0]), np.array([1000.0, 0.0]))
    assert lat[0] == pytest.approx(49.0 + 1000.0 / 111_200.0, abs=2e-4) and lon[1] > 8.0
    with pytest.raises(InputError, match="not a usable PROJ string"):
        ToWgs84("+proj=nonsense", "bad.xodr")
