"""`compare`: the lateral distance must be exact for known offsets and impossible to fool."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from lxml import etree
from typer.testing import CliRunner

from lidar2xodr.cli import app
from lidar2xodr.config import EvaluationConfig
from lidar2xodr.errors import InputError
from lidar2xodr.evaluation import compare_maps, load_trajectory, path_on_map

CFG = EvaluationConfig()
DRV = ("driving", 3.5)
MEDIAN = ("border", 1.0)
ARC = '<arc curvature="0.002"/>'
TMERC = "+proj=tmerc +lat_0=48.78 +lon_0=9.18 +k=1 +x_0={x0} +y_0={y0} +ellps=WGS84 +units=m +no_defs"


def _lanes(tag: str, spec: tuple, sign: int) -> str:
    items = "".join(
        f'<lane id="{sign * (i + 1)}" type="{t}" level="false"><width sOffset="0" a="{w}" b="0" c="0" d="0"/></lane>'
        for i, (t, w) in enumerate(spec)
    )
    return f"<{tag}>{items}</{tag}>" if spec else ""


def _road(rid: str, length: float, right: tuple = (MEDIAN, DRV, DRV), left: tuple = (), x: float = 0.0,
          y: float = 0.0, hdg: float = 0.0, offset: float = 0.0, geom: str = "<line/>") -> str:
    """A one-section road; lanes given inner to outer as (type, width)."""
    return (
        f'<road id="{rid}" length="{length}" junction="-1" rule="RHT"><planView>'
        f'<geometry s="0" x="{x}" y="{y}" hdg="{hdg}" length="{length}">{geom}</geometry></planView>'
        f'<lanes><laneOffset s="0" a="{offset}" b="0" c="0" d="0"/><laneSection s="0">{_lanes("left", left, 1)}'
        f'<center><lane id="0" type="none" level="false"/></center>{_lanes("right", right, -1)}'
        "</laneSection></lanes></road>"
    )


def _map(path: Path, *roads: str, geo: str | None = None) -> Path:
    geo_el = f"<geoReference><![CDATA[{geo}]]></geoReference>" if geo else ""
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header revMajor="1" revMinor="8" name="t" '
        f'version="1">{geo_el}</header>{"".join(roads)}</OpenDRIVE>\n',
        encoding="utf-8",
    )
    return path


def _both(length: float = 300.0, **kw: object) -> str:
    """A divided motorway in one road: median border lanes, two 3.5 m lanes each way."""
    return _road("1", length, right=(MEDIAN, DRV, DRV), left=(MEDIAN, DRV, DRV), **kw)  # type: ignore[arg-type]


def _shift_lane_offsets(src: Path, dst: Path, dt: float) -> Path:
    """Copy of a map with every lane moved dt sideways (laneOffset + dt on every road)."""
    tree = etree.parse(str(src))
    for lanes in tree.getroot().iter("lanes"):
        offsets = lanes.findall("laneOffset")
        if not offsets:
            offsets = [etree.Element("laneOffset", s="0", a="0", b="0", c="0", d="0")]
            lanes.insert(0, offsets[0])
        for el in offsets:
            el.set("a", repr(float(el.get("a")) + dt))
    tree.write(str(dst))
    return dst


def _assert_zero(m: dict) -> None:
    for key in ("boundaries", "centerline"):
        assert m[key]["rmse_m"] == pytest.approx(0.0, abs=1e-9)
        assert m[key]["max_m"] == pytest.approx(0.0, abs=1e-9)
        assert m[key]["eval_length_m"] > 0
    assert m["lane_count_agreement"] == pytest.approx(1.0)
    assert m["lane_width"]["bias_m"] == pytest.approx(0.0, abs=1e-9) and m["lane_width"]["pairs"] > 0
    assert m["coverage"] == pytest.approx(1.0)
    assert m["elevation"]["rmse_m"] == pytest.approx(0.0, abs=1e-9) and m["elevation"]["eval_length_m"] > 0


def _with_elevation(src: Path, dst: Path, a: float, b: float) -> Path:
    """Copy of a one-road map whose elevation is a + b s."""
    tree = etree.parse(str(src))
    road = tree.getroot().find("road")
    prof = etree.Element("elevationProfile")
    etree.SubElement(prof, "elevation", s="0", a=repr(a), b=repr(b), c="0", d="0")
    road.find("planView").addnext(prof)
    tree.write(str(dst))
    return dst


def test_elevation_difference_is_measured_along_the_road(tmp_path: Path) -> None:
    """A map raised 0.3 m and tilted by 1 % against its flat self: z differs by 0.3 + 0.01 s, lateral not at all."""
    ref = _map(tmp_path / "ref.xodr", _road("1", 300.0, geom=ARC))
    gen = _with_elevation(ref, tmp_path / "gen.xodr", 0.3, 0.01)
    m = compare_maps(gen, ref, CFG)
    assert m["centerline"]["rmse_m"] == pytest.approx(0.0, abs=1e-9)
    z = m["elevation"]
    assert z["mean_m"] == pytest.approx(0.3 + 0.01 * 150.0, rel=0.01)
    assert z["max_m"] == pytest.approx(0.3 + 0.01 * 300.0, rel=0.01)
    back = compare_maps(ref, gen, CFG)["elevation"]
    assert back["mean_m"] == pytest.approx(-z["mean_m"], rel=1e-3)
    assert back["rmse_m"] == pytest.approx(z["rmse_m"], rel=1e-3)


def test_identical_tiny_map_is_zero(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _both(geom=ARC))
    m = compare_maps(ref, ref, CFG)
    _assert_zero(m)
    # Two carriageways x three boundaries x ~300 m (the arc shifts the borders' length a little).
    assert m["boundaries"]["eval_length_m"] == pytest.approx(6 * 300, rel=0.02)
    assert m["reference_eval_length_m"] == pytest.approx(600, rel=0.02)


def test_identical_shared_highway_is_zero(shared_data: Path) -> None:
    path = shared_data / "maps" / "asam" / "AB_RQ31_R2000.xodr"
    m = compare_maps(path, path, CFG)
    _assert_zero(m)
    assert m["boundaries"]["eval_length_m"] > 10_000


@pytest.mark.parametrize("dt", [0.30, -0.30])
def test_tiny_map_shifted_sideways(tmp_path: Path, dt: float) -> None:
    ref = _map(tmp_path / "ref.xodr", _both(geom=ARC))
    gen = _shift_lane_offsets(ref, tmp_path / "gen.xodr", dt)
    m = compare_maps(gen, ref, CFG)
    for key in ("boundaries", "centerline"):
        assert m[key]["mean_m"] == pytest.approx(0.30, abs=1e-3)
        assert m[key]["rmse_m"] == pytest.approx(0.30, abs=1e-3)
        assert m[key]["max_m"] == pytest.approx(0.30, abs=1e-3)
    assert m["lane_count_agreement"] == pytest.approx(1.0)
    assert m["lane_width"]["bias_m"] == pytest.approx(0.0, abs=1e-9)
    assert m["coverage"] == pytest.approx(1.0)


def test_shared_highway_shifted_sideways(shared_data: Path, tmp_path: Path) -> None:
    ref = shared_data / "maps" / "asam" / "AB_RQ31_R2000.xodr"
    m = compare_maps(_shift_lane_offsets(ref, tmp_path / "gen.xodr", 0.30), ref, CFG)
    assert m["boundaries"]["mean_m"] == pytest.approx(0.30, abs=1e-3)
    assert m["boundaries"]["rmse_m"] == pytest.approx(0.30, abs=1e-3)
    assert m["centerline"]["rmse_m"] == pytest.approx(0.30, abs=1e-3)


def test_align_takes_out_a_rigid_offset_and_reports_it(tmp_path: Path) -> None:
    """`compare --align`: a map moved 0.8 m / -1.1 m (a GNSS bias) has its shape measured, its offset reported."""
    ref = _map(tmp_path / "ref.xodr", _both(geom=ARC))
    gen = _map(tmp_path / "gen.xodr", _both(geom=ARC, x=0.8, y=-1.1))
    from lidar2xodr.config import FusionConfig

    plain = compare_maps(gen, ref, CFG)
    assert plain["boundaries"]["mean_m"] > 0.5 and plain["alignment"] is None
    m = compare_maps(gen, ref, CFG, FusionConfig())
    a = m["alignment"]
    assert a["dx_m"] == pytest.approx(-0.8, abs=0.1) and a["dy_m"] == pytest.approx(1.1, abs=0.1), a
    assert a["inlier_share"] > 0.95 and abs(a["yaw_deg"]) < 0.05
    assert m["boundaries"]["rmse_m"] < 0.02 and m["lane_count_agreement"] == pytest.approx(1.0, abs=0.01)
    assert "moved rigidly" in m["frame"]
    out = tmp_path / "m.json"
    res = CliRunner().invoke(app, ["compare", str(gen), str(ref), "--align", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text())["boundaries"]["rmse_m"] == pytest.approx(m["boundaries"]["rmse_m"])


def test_missing_lane_lowers_lane_count_agreement(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _both())
    gen = _map(tmp_path / "gen.xodr", _road("1", 300, right=(MEDIAN, DRV, ("shoulder", 3.5)),
                                            left=(MEDIAN, DRV, DRV)))
    m = compare_maps(gen, ref, CFG)
    assert m["lane_count_agreement"] == pytest.approx(0.5, abs=0.01)  # right carriageway: 1 lane, not 2
    assert m["boundaries"]["max_m"] == pytest.approx(0.0, abs=1e-9)  # what is there is right
    assert m["centerline"]["max_m"] == pytest.approx(1.75, abs=1e-6)  # its centre moves half a lane


def test_far_away_map_is_not_small(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _both())
    gen = _map(tmp_path / "gen.xodr", _both(y=-50.0))
    m = compare_maps(gen, ref, CFG)
    assert m["boundaries"]["mean_m"] > 35.0 and m["boundaries"]["max_m"] >= 50.0 - 1e-6
    assert m["centerline"]["mean_m"] == pytest.approx(50.0, abs=1e-6)
    assert m["lane_count_agreement"] == 0.0 and m["coverage"] == 0.0
    assert m["lane_width"] == {"bias_m": None, "std_m": None, "pairs": 0}
    res = CliRunner().invoke(app, ["compare", str(gen), str(ref)])
    assert res.exit_code == 0 and "no matched lane" in res.output


def test_opposite_direction_is_not_matched(tmp_path: Path) -> None:
    """A generated carriageway drawn exactly on the reference's right lanes but travelling the wrong way."""
    ref = _map(tmp_path / "ref.xodr", _both())
    # Heading pi: its right lanes lie at +y from its reference line, i.e. on y in [-8, -1].
    gen = _map(tmp_path / "gen.xodr", _road("9", 300, x=300.0, y=-8.0, hdg=3.141592653589793,
                                            right=(DRV, DRV, MEDIAN)))
    m = compare_maps(gen, ref, CFG)
    # Its borders at y = -8, -4.5, -1 are measured against the -x carriageway's at y = 1, 4.5, 8: 9, 5.5, 2 m.
    assert m["boundaries"]["mean_m"] == pytest.approx(5.5, abs=1e-6)
    assert m["lane_count_agreement"] == 0.0


def test_one_carriageway_against_a_divided_road(tmp_path: Path) -> None:
    """The opposite carriageway of the reference is neither evaluated nor needed for full coverage."""
    ref = _map(tmp_path / "ref.xodr", _both(geom=ARC))
    gen = _map(tmp_path / "gen.xodr", _road("7", 300, geom=ARC))
    m = compare_maps(gen, ref, CFG)
    _assert_zero(m)
    assert m["reference_eval_length_m"] == pytest.approx(300, rel=0.02)


def test_gap_and_overhang_are_counted(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _road("1", 300))
    gen = _map(tmp_path / "gen.xodr", _road("1", 100), _road("2", 100, x=200.0))
    m = compare_maps(gen, ref, CFG)
    assert m["coverage"] == pytest.approx(2 / 3, abs=0.01)
    assert m["boundaries"]["max_m"] == pytest.approx(0.0, abs=1e-9)
    longer = _map(tmp_path / "long.xodr", _road("1", 400))
    m = compare_maps(longer, ref, CFG)
    assert m["boundaries"]["max_m"] == pytest.approx(100.0, abs=1e-6)  # 100 m past the reference's end
    assert m["lane_count_agreement"] == pytest.approx(0.75, abs=0.005)  # the overhang matches nothing
    assert m["coverage"] == pytest.approx(1.0)


def test_lane_width_bias(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _road("1", 300))
    gen = _map(tmp_path / "gen.xodr", _road("1", 300, right=(MEDIAN, ("driving", 3.6), ("driving", 3.6))))
    m = compare_maps(gen, ref, CFG)
    assert m["lane_width"]["bias_m"] == pytest.approx(0.10, abs=1e-9)
    assert m["lane_width"]["std_m"] == pytest.approx(0.0, abs=1e-9)
    assert m["lane_count_agreement"] == pytest.approx(1.0)
    # Boundaries at 0, 0.1 and 0.2 m from their reference lines.
    assert m["boundaries"]["mean_m"] == pytest.approx(0.10, abs=1e-3)
    assert m["centerline"]["mean_m"] == pytest.approx(0.10, abs=1e-6)


def test_geo_references_are_aligned(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _both(), geo=TMERC.format(x0=0, y0=0))
    # The same road, stored 100 m east and 50 m north in a frame whose false origin says exactly that.
    gen = _map(tmp_path / "gen.xodr", _both(x=100.0, y=50.0), geo=TMERC.format(x0=100, y0=50))
    m = compare_maps(gen, ref, CFG)
    assert "projected" in m["frame"]
    assert m["boundaries"]["max_m"] < 1e-6 and m["coverage"] == pytest.approx(1.0)
    unaligned = _map(tmp_path / "gen2.xodr", _both(x=100.0, y=50.0))
    assert compare_maps(unaligned, ref, CFG)["boundaries"]["mean_m"] > 10.0


def test_cli_json_is_deterministic(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _both(geom=ARC))
    gen = _shift_lane_offsets(ref, tmp_path / "gen.xodr", 0.3)
    outs = []
    for name in ("a.json", "b.json"):
        res = CliRunner().invoke(app, ["compare", str(gen), str(ref), "--json", str(tmp_path / name)])
        assert res.exit_code == 0, res.output
        outs.append((tmp_path / name).read_bytes())
    assert outs[0] == outs[1]
    data = json.loads(outs[0])
    assert set(data["boundaries"]) >= {"rmse_m", "mean_m", "std_m", "p95_m", "max_m", "eval_length_m"}
    assert {"lane_count_agreement", "coverage", "lane_width", "centerline", "lane_graph"} <= set(data)
    assert {"agreement", "breaks", "wrong_m"} <= set(data["lane_graph"])
    res = CliRunner().invoke(app, ["compare", str(gen), str(ref)])
    assert "lane graph agreement" in res.output


def test_bad_input(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _both())
    no_lanes = _map(tmp_path / "none.xodr", _road("1", 100, right=(("shoulder", 2.0),)))
    with pytest.raises(InputError, match="no driving lanes"):
        compare_maps(no_lanes, ref, CFG)
    with pytest.raises(InputError, match="not found"):
        compare_maps(tmp_path / "absent.xodr", ref, CFG)
    res = CliRunner().invoke(app, ["compare", str(no_lanes), str(ref)])
    assert res.exit_code == 2 and "Traceback" not in res.output


def _lane_roads_junction(tmp_path: Path, ramp: str = "<line/>") -> Path:
    """Road 1 (0-100 m), a junction of one 20 m connecting road per lane (10, 11; 11's geometry `ramp`),
    road 2 (120-300 m): the way some tools (roadgen, RoadRunner) write a carriageway through a junction."""
    def in_junction(road: str, pred: str, succ: str) -> str:
        road = road.replace('junction="-1"', 'junction="1"')
        return road.replace("<planView>", f'<link><predecessor elementType="road" elementId="{pred}" '
                            f'contactPoint="end"/><successor elementType="road" elementId="{succ}" '
                            'contactPoint="start"/></link><planView>')
    a = _road("1", 100.0).replace("<planView>", '<link><successor elementType="junction" elementId="1"/></link>'
                                  "<planView>")
    b = _road("2", 180.0, x=120.0).replace("<planView>", '<link><predecessor elementType="junction" '
                                           'elementId="1"/></link><planView>')
    lane1 = in_junction(_road("10", 20.0, right=(DRV,), x=100.0, offset=-1.0), "1", "2")
    lane2 = in_junction(_road("11", 20.0, right=(DRV,), x=100.0, offset=-4.5, geom=ramp), "1", "2")
    junction = ('<junction id="1" name="j">'
                '<connection id="0" incomingRoad="1" connectingRoad="10" contactPoint="start">'
                '<laneLink from="-2" to="-1"/></connection>'
                '<connection id="1" incomingRoad="1" connectingRoad="11" contactPoint="start">'
                '<laneLink from="-3" to="-1"/></connection></junction>')
    return _map(tmp_path / "lanes_junction.xodr", a, b, lane1, lane2, junction)


def test_a_junction_of_one_road_per_lane_is_one_carriageway(tmp_path: Path) -> None:
    """Connecting roads that lie side by side are the lanes of one carriageway: a one-road map of the same
    lanes is 0 away (read one by one, every connecting road was a one-lane carriageway, its centre
    1.75 m from the true one, and the lane count was wrong over the junction)."""
    ref = _lane_roads_junction(tmp_path)
    gen = _map(tmp_path / "gen.xodr", _road("7", 300.0))
    m = compare_maps(gen, ref, CFG)
    assert m["centerline"]["max_m"] == pytest.approx(0.0, abs=1e-6)
    assert m["boundaries"]["max_m"] == pytest.approx(0.0, abs=1e-6)
    assert m["lane_count_agreement"] == pytest.approx(1.0)
    back = compare_maps(ref, gen, CFG)
    assert back["centerline"]["max_m"] == pytest.approx(0.0, abs=1e-6)
    assert back["lane_count_agreement"] == pytest.approx(1.0)


def test_a_connecting_road_that_leaves_is_not_part_of_the_carriageway(tmp_path: Path) -> None:
    """A ramp's connecting road that turns away from the through lane stays a carriageway of its own:
    a map that keeps both lanes together through the junction gets the lane count wrong there."""
    ref = _lane_roads_junction(tmp_path, ramp='<arc curvature="-0.004"/>')
    gen = _map(tmp_path / "gen.xodr", _road("7", 300.0))
    m = compare_maps(gen, ref, CFG)
    assert 0.85 < m["lane_count_agreement"] < 0.97
    assert m["centerline"]["max_m"] > 1.0


def _trajectory(path: Path, xy: list[tuple[float, float]]) -> Path:
    path.write_text("time,x,y,z\n" + "".join(f"{i},{x},{y},0\n" for i, (x, y) in enumerate(xy)), encoding="utf-8")
    return path


def test_driven_share_is_the_built_part_of_the_road_the_drive_travelled(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _road("1", 300.0))
    half = _map(tmp_path / "half.xodr", _road("1", 150.0))
    along = _trajectory(tmp_path / "along.csv", [(float(x), -2.75) for x in range(0, 301, 10)])
    back = _trajectory(tmp_path / "back.csv", [(float(x), -2.75) for x in range(300, -1, -10)])
    m = compare_maps(half, ref, CFG, trajectory=load_trajectory(along))
    assert m["driven"]["driven_m"] == pytest.approx(300.0, abs=1.0)
    assert m["driven"]["share"] == pytest.approx(0.5, abs=0.01)
    assert compare_maps(ref, ref, CFG, trajectory=load_trajectory(along))["driven"]["share"] == pytest.approx(1.0)
    assert compare_maps(ref, ref, CFG)["driven"] is None
    assert path_on_map(half, load_trajectory(along), CFG)["share"] == pytest.approx(0.5, abs=0.01), "no reference"
    wrong_way = compare_maps(ref, ref, CFG, trajectory=load_trajectory(back))["driven"]
    assert wrong_way["driven_m"] == 0.0, "against the only carriageway's travel direction: not a driven road"


def test_the_drive_is_on_the_map_across_a_seam_where_a_lane_appears_at_full_width(tmp_path: Path) -> None:
    """Road 1 (two lanes) ends where road 2 (three lanes, the third at full width: an on-ramp's lane)
    begins. Road 2's carriageway centre lies 1.75 m beside road 1's, so the samples just past road
    1's end are nearest its last vertex, beyond it; road 2 holds them, and the drive is on the map."""
    seam = _map(tmp_path / "seam.xodr", _road("1", 150.0),
                _road("2", 150.0, right=(MEDIAN, DRV, DRV, DRV), x=150.0))
    along = _trajectory(tmp_path / "along.csv", [(float(x), -2.75) for x in range(0, 301, 10)])
    assert path_on_map(seam, load_trajectory(along), CFG)["share"] == pytest.approx(1.0)


def test_compare_trajectory_bad_input_is_one_line(tmp_path: Path) -> None:
    ref = _map(tmp_path / "ref.xodr", _road("1", 300.0))
    bad = tmp_path / "bad.csv"
    bad.write_text("time,lat,lon\n0,1,2\n", encoding="utf-8")
    with pytest.raises(InputError, match="x and y columns"):
        load_trajectory(bad)
    result = CliRunner().invoke(app, ["compare", str(ref), str(ref), "--trajectory", str(bad)])
    assert result.exit_code != 0 and "bad.csv" in result.output and "Traceback" not in result.output
    good = _trajectory(tmp_path / "good.csv", [(0.0, -2.75), (300.0, -2.75)])
    result = CliRunner().invoke(app, ["compare", str(ref), str(ref), "--trajectory", str(good),
                                      "--json", str(tmp_path / "m.json")])
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "m.json").read_text())["driven"]["share"] == pytest.approx(1.0)


def _marked(src: Path, dst: Path, marks: dict[int, list[tuple[float, str]]]) -> Path:
    """Copy of a one-road map with roadMark records (sOffset, type) on the lanes named by id."""
    tree = etree.parse(str(src))
    for lane in tree.getroot().iter("lane"):
        for s, kind in marks.get(int(lane.get("id")), []):
            etree.SubElement(lane, "roadMark", sOffset=repr(s), type=kind, weight="standard", color="white",
                             width="0.15")
    tree.write(str(dst))
    return dst


# right carriageway of `_road`: median border lane -1, driving lanes -2 and -3 (3.5 m each)
_MARKS = {-1: [(0.0, "solid")], -2: [(0.0, "broken")], -3: [(0.0, "solid")]}


def test_road_marks_of_a_map_against_itself_agree(tmp_path: Path) -> None:
    ref = _marked(_map(tmp_path / "r.xodr", _road("1", 300.0, geom=ARC)), tmp_path / "ref.xodr", _MARKS)
    marks = compare_maps(ref, ref, CFG)["road_marks"]
    assert marks["agreement"] == pytest.approx(1.0)
    assert marks["confusion_m"] == {}
    assert marks["matched_m"] == pytest.approx(3 * 300.0, rel=0.02)


def test_a_line_typed_solid_where_it_is_broken_is_counted_with_its_length(tmp_path: Path) -> None:
    """The lane divider solid instead of broken on its last 200 m: a third of the matched length of the
    three lines disagrees, as solid -> broken; a map without any roadMark has no paint anywhere."""
    base = _map(tmp_path / "b.xodr", _road("1", 300.0, geom=ARC))
    ref = _marked(base, tmp_path / "ref.xodr", _MARKS)
    wrong = {**_MARKS, -2: [(0.0, "broken"), (100.0, "solid")]}
    gen = _marked(base, tmp_path / "gen.xodr", wrong)
    marks = compare_maps(gen, ref, CFG)["road_marks"]
    assert marks["confusion_m"]["solid->broken"] == pytest.approx(200.0, rel=0.03)
    assert marks["agreement"] == pytest.approx(700.0 / 900.0, rel=0.02)
    bare = compare_maps(base, ref, CFG)["road_marks"]
    assert bare["agreement"] == pytest.approx(0.0)
    assert set(bare["confusion_m"]) == {"none->solid", "none->broken"}


def test_road_marks_are_not_judged_where_two_reference_lines_coincide(tmp_path: Path) -> None:
    """A reference lane 0.3 m wide (an opening taper: its broken divider and solid edge paint one line):
    the generated line there is neither right nor wrong, so only the other lines are judged."""
    ref_road = _road("1", 300.0, right=(MEDIAN, DRV, DRV, ("driving", 0.3)), geom=ARC)
    ref = _marked(_map(tmp_path / "r.xodr", ref_road), tmp_path / "ref.xodr",
                  {**_MARKS, -3: [(0.0, "broken")], -4: [(0.0, "solid")]})
    gen = _marked(_map(tmp_path / "g.xodr", _road("1", 300.0, geom=ARC)), tmp_path / "gen.xodr", _MARKS)
    marks = compare_maps(gen, ref, CFG)["road_marks"]
    assert marks["agreement"] == pytest.approx(1.0)
    assert marks["matched_m"] == pytest.approx(2 * 300.0, rel=0.02)


def test_mark_classes() -> None:
    from lidar2xodr.evaluation import mark_class

    assert [mark_class(k) for k in ("solid", "solid solid", "curb", "edge")] == ["solid"] * 4
    assert [mark_class(k) for k in ("broken", "broken broken", "botts dots")] == ["broken"] * 3
    assert [mark_class(k) for k in ("solid broken", "broken solid")] == ["double"] * 2
    assert [mark_class(k) for k in ("none", "grass")] == ["none"] * 2
    assert mark_class("custom") == "other"
