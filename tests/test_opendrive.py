"""OpenDRIVE reader: tiny hand-made maps with known answers, bad input, cross-checks on every shared map."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad

from lidar2xodr.errors import InputError
from lidar2xodr.opendrive import BROKEN_DASH_M, BROKEN_GAP_M, DOUBLE_LINE_GAP_M, OpenDriveMap

LANES = """<lanes>{offset}<laneSection s="0"><left><lane id="1" type="driving">
 <width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></left>
 <center><lane id="0" type="none"/></center><right><lane id="-1" type="driving">
 <width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></right></laneSection></lanes>"""


def xodr(
    geometry: str,
    length: float,
    lanes: str = LANES,
    extra: str = "",
    road_attrs: str = "",
    minor: int = 8,
    offset: str = "",
) -> str:
    """A one-road map; `geometry` is the inner planView text."""
    return (
        f'<?xml version="1.0"?><OpenDRIVE><header revMajor="1" revMinor="{minor}">'
        f"<geoReference><![CDATA[+proj=tmerc +lat_0=48 +lon_0=11]]></geoReference></header>"
        f'<road id="7" name="r" length="{length}" junction="-1" {road_attrs}>'
        f"<planView>{geometry}</planView>{extra}{lanes.format(offset=offset)}</road></OpenDRIVE>"
    )


def load(tmp_path: Path, text: str, name: str = "m.xodr") -> OpenDriveMap:
    path = tmp_path / name
    path.write_text(text)
    return OpenDriveMap.load(path)


def geom(kind: str, length: float, x: float = 0.0, y: float = 0.0, hdg: float = 0.0, s: float = 0.0) -> str:
    return f'<geometry s="{s}" x="{x}" y="{y}" hdg="{hdg}" length="{length}">{kind}</geometry>'


# ---------------------------------------------------------------------------------------------
# geometry kinds


def test_line_and_header(tmp_path: Path) -> None:
    m = load(tmp_path, xodr(geom("<line/>", 100, x=10, y=5, hdg=math.pi / 2), 100))
    assert m.version == (1, 8)
    assert m.geo_reference == "+proj=tmerc +lat_0=48 +lon_0=11"
    x, y, h = m.roads["7"].reference([0, 40, 100])
    np.testing.assert_allclose(x, 10, atol=1e-12)
    np.testing.assert_allclose(y, [5, 45, 105], atol=1e-12)
    np.testing.assert_allclose(h, math.pi / 2)


@pytest.mark.parametrize("k", [1 / 50, -1 / 50, 1e-12])
def test_arc_lies_on_its_circle(tmp_path: Path, k: float) -> None:
    length = 60.0
    m = load(tmp_path, xodr(geom(f'<arc curvature="{k}"/>', length, x=3, y=-2, hdg=0.3), length))
    s = np.linspace(0, length, 50)
    x, y, h = m.roads["7"].reference(s)
    np.testing.assert_allclose(h, 0.3 + k * s, atol=1e-12)
    if abs(k) > 1e-6:
        cx, cy = 3 - math.sin(0.3) / k, -2 + math.cos(0.3) / k
        np.testing.assert_allclose(np.hypot(x - cx, y - cy), 1 / abs(k), atol=1e-9)
        end = (cx + math.sin(0.3 + k * length) / k, cy - math.cos(0.3 + k * length) / k)
        np.testing.assert_allclose([x[-1], y[-1]], end, atol=1e-9)
    else:
        np.testing.assert_allclose([x[-1], y[-1]], [3 + length * math.cos(0.3), -2 + length * math.sin(0.3)])


@pytest.mark.parametrize(("k0", "k1"), [(0.0, 0.02), (0.01, -0.005), (-0.004, -0.0041), (0.003, 0.003)])
def test_spiral_matches_numerical_integration(tmp_path: Path, k0: float, k1: float) -> None:
    length = 80.0
    spiral = f'<spiral curvStart="{k0}" curvEnd="{k1}"/>'
    m = load(tmp_path, xodr(geom(spiral, length, x=1, y=2, hdg=-0.4), length))
    road = m.roads["7"]
    rate = (k1 - k0) / length

    def heading(u: float) -> float:
        return -0.4 + k0 * u + 0.5 * rate * u * u

    for s in (13.0, 47.5, length):
        xe = 1 + quad(lambda u: math.cos(heading(u)), 0, s, epsabs=1e-13)[0]
        ye = 2 + quad(lambda u: math.sin(heading(u)), 0, s, epsabs=1e-13)[0]
        x, y, h = road.reference(s)
        assert abs(x[0] - xe) < 1e-9 and abs(y[0] - ye) < 1e-9
        assert abs(h[0] - heading(s)) < 1e-12
    # end curvature from the heading derivative
    eps = 1e-3
    _, _, h2 = road.reference([length - 2 * eps, length - eps, length])
    assert abs((h2[2] - h2[1]) / eps - k1) < 1e-5


def test_poly3_is_arc_length_parametrised(tmp_path: Path) -> None:
    a, b, c, d = 0.0, 0.1, 0.002, -1e-5
    u_end = 50.0
    true_len = quad(lambda u: math.hypot(1, b + 2 * c * u + 3 * d * u * u), 0, u_end, epsabs=1e-12)[0]
    m = load(tmp_path, xodr(geom(f'<poly3 a="{a}" b="{b}" c="{c}" d="{d}"/>', true_len, hdg=0.5), true_len))
    x, y, h = m.roads["7"].reference([0.0, true_len])
    ve = a + b * u_end + c * u_end**2 + d * u_end**3
    end = (u_end * math.cos(0.5) - ve * math.sin(0.5), u_end * math.sin(0.5) + ve * math.cos(0.5))
    np.testing.assert_allclose([x[1], y[1]], end, atol=1e-7)
    np.testing.assert_allclose(h[1], 0.5 + math.atan(b + 2 * c * u_end + 3 * d * u_end**2), atol=1e-9)
    # equal steps in s are equal steps along the curve
    s = np.linspace(0, true_len, 201)
    x, y, _ = m.roads["7"].reference(s)
    np.testing.assert_allclose(np.hypot(np.diff(x), np.diff(y)), true_len / 200, rtol=1e-5)


def test_parampoly3_normalized_equals_arclength(tmp_path: Path) -> None:
    """p runs over [0, length] (arcLength) or [0, 1] (normalized); traversed at constant speed."""
    d = 40.0
    cv, dv = 0.01, 0.0002
    arc = f'<paramPoly3 aU="0" bU="1" cU="0" dU="0" aV="0" bV="0" cV="{cv}" dV="{dv}" pRange="arcLength"/>'
    norm = (
        f'<paramPoly3 aU="0" bU="{d}" cU="0" dU="0" aV="0" bV="0" cV="{cv * d * d}" dV="{dv * d**3}" '
        'pRange="normalized"/>'
    )
    m1 = load(tmp_path, xodr(geom(arc, d, x=5, hdg=1.0), d), "a.xodr")
    m2 = load(tmp_path, xodr(geom(norm, d, x=5, hdg=1.0), d), "n.xodr")
    s = np.linspace(0, d, 101)
    for a_, b_ in zip(m1.roads["7"].reference(s), m2.roads["7"].reference(s), strict=True):
        np.testing.assert_allclose(a_, b_, atol=1e-9)
    x, y, h = m1.roads["7"].reference(s)
    ve = cv * d * d + dv * d**3
    np.testing.assert_allclose(
        [x[-1], y[-1]], [5 + d * math.cos(1) - ve * math.sin(1), d * math.sin(1) + ve * math.cos(1)]
    )
    assert h[-1] == pytest.approx(1.0 + math.atan(2 * cv * d + 3 * dv * d * d))
    true_len = quad(lambda p: math.hypot(1, 2 * cv * p + 3 * dv * p * p), 0, d, epsabs=1e-12)[0]
    np.testing.assert_allclose(np.hypot(np.diff(x), np.diff(y)), true_len / 100, rtol=1e-5)


def test_geometry_lookup_is_half_open(tmp_path: Path) -> None:
    g = geom("<line/>", 10) + geom('<arc curvature="0.1"/>', 10, x=10, s=10)
    m = load(tmp_path, xodr(g, 20))
    road = m.roads["7"]
    _, _, h = road.reference([9.999, 10.0, 20.0])
    np.testing.assert_allclose(h, [0.0, 0.0, 1.0])
    assert road.geometries[1].kind == "arc"


# ---------------------------------------------------------------------------------------------
# profiles and lanes


def test_elevation_superelevation_and_to_world(tmp_path: Path) -> None:
    extra = (
        '<elevationProfile><elevation s="0" a="1" b="0.02" c="0" d="0"/>'
        '<elevation s="50" a="2" b="0" c="0.001" d="0"/></elevationProfile>'
        '<lateralProfile><superelevation s="0" a="0.05" b="0" c="0" d="0"/></lateralProfile>'
    )
    m = load(tmp_path, xodr(geom("<line/>", 100), 100, extra=extra))
    road = m.roads["7"]
    np.testing.assert_allclose(road.elevation([0, 25, 50, 60]), [1, 1.5, 2, 2.1])
    np.testing.assert_allclose(road.superelevation(30), 0.05)
    p = road.to_world([30.0], [2.0], 0.5)[0]
    # positive superelevation lifts the left side (t > 0)
    assert p[2] == pytest.approx(1.6 + 2 * math.sin(0.05) + 0.5 * math.cos(0.05))
    assert p[1] == pytest.approx(2 * math.cos(0.05) - 0.5 * math.sin(0.05))
    assert p[0] == pytest.approx(30.0)
    right = road.to_world(30.0, -2.0)[0]
    assert right[2] < 1.6 < p[2]


def test_lane_widths_with_soffset_and_lane_offset(tmp_path: Path) -> None:
    lanes = """<lanes>{offset}<laneSection s="0"><left><lane id="1" type="driving">
      <width sOffset="0" a="3"/></lane></left><center><lane id="0"/></center><right>
      <lane id="-1" type="driving"><width sOffset="0" a="3.5"/></lane>
      <lane id="-2" type="shoulder"><width sOffset="0" a="2"/></lane></right></laneSection>
      <laneSection s="40"><center><lane id="0"/></center><right><lane id="-1" type="driving">
      <width sOffset="0" a="3.5"/><width sOffset="10" a="3.5" b="0.1"/></lane></right></laneSection>
      </lanes>"""
    offset = '<laneOffset s="0" a="0.5" b="0" c="0" d="0"/>'
    m = load(tmp_path, xodr(geom("<line/>", 100), 100, lanes=lanes, offset=offset))
    road = m.roads["7"]
    s = np.array([10.0, 45.0, 60.0])
    np.testing.assert_allclose(road.border_t(s, 0), 0.5)
    np.testing.assert_allclose(road.border_t(s, 1), [3.5, np.nan, np.nan])
    np.testing.assert_allclose(road.border_t(s, -2), [-5.0, np.nan, np.nan])
    np.testing.assert_allclose(road.border_t(s, -1), [-3.0, -3.0, -4.0])
    np.testing.assert_allclose(road.section_index([0, 39.9, 40, 100]), [0, 0, 1, 1])
    secs = m.sample(1.0)
    assert [(sec.section, sec.s[0], sec.s[-1], len(sec.s)) for sec in secs] == [
        (0, 0, 40, 41),
        (1, 40, 100, 61),
    ]
    assert secs[1].lane_ids == [-1, 0]
    assert secs[0].lane_types == {-2: "shoulder", -1: "driving", 0: "none", 1: "driving"}
    np.testing.assert_allclose(secs[0].border_xyz[-2][:, 1], -5.0)
    np.testing.assert_allclose(secs[0].xyz[:, 1], 0.0)


def test_road_marks_links_and_junctions(tmp_path: Path) -> None:
    lanes = """<lanes><laneSection s="0"><left><lane id="1" type="driving"><link>
      <predecessor id="2"/><successor id="1"/></link><width sOffset="0" a="3.5"/>
      <roadMark sOffset="0" type="broken" weight="standard" color="white" laneChange="both"/></lane></left>
      <center><lane id="0"><roadMark sOffset="0" type="solid broken" width="0.2"/></lane></center>
      <right><lane id="-1" type="driving"><width sOffset="0" a="3.5"/>
      <roadMark sOffset="5" type="broken" width="0.15"><type name="x" width="0.15">
      <line length="3" space="9" tOffset="0" sOffset="1" width="0.15" rule="caution"/></type></roadMark>
      </lane></right></laneSection></lanes>"""
    link = (
        '<link><predecessor elementType="junction" elementId="9"/>'
        '<successor elementType="road" elementId="8" contactPoint="start"/></link>'
    )
    text = xodr(geom("<line/>", 50), 50, lanes=lanes).replace("<planView>", link + "<planView>", 1)
    text = text.replace(
        "</OpenDRIVE>",
        '<junction id="9" name="j"><connection id="0" incomingRoad="8" connectingRoad="7" contactPoint="end">'
        '<laneLink from="-1" to="1"/></connection></junction></OpenDRIVE>',
    )
    m = load(tmp_path, text)
    road = m.roads["7"]
    assert road.predecessor is not None and road.predecessor.element_type == "junction"
    assert road.predecessor.element_id == "9" and road.predecessor.contact_point is None
    assert road.successor is not None and (road.successor.element_id, road.successor.contact_point) == (
        "8",
        "start",
    )
    lanes_ = road.lane_sections[0].lanes
    assert (lanes_[1].predecessor, lanes_[1].successor) == (2, 1)
    broken = lanes_[1].road_marks[0]
    assert broken.lane_change == "both" and broken.color == "white" and broken.width == 0.15
    assert [(ln.length, ln.space) for ln in broken.lines] == [(BROKEN_DASH_M, BROKEN_GAP_M)]
    double = lanes_[0].road_marks[0]
    assert [ln.space for ln in double.lines] == [0.0, BROKEN_GAP_M]  # solid on the left (+t)
    gap = double.lines[0].t_offset - double.lines[1].t_offset - double.lines[0].width
    assert gap == pytest.approx(DOUBLE_LINE_GAP_M)
    explicit = lanes_[-1].road_marks[0]
    assert explicit.s_offset == 5 and explicit.explicit
    assert [(ln.length, ln.space, ln.s_offset, ln.rule) for ln in explicit.lines] == [(3, 9, 1, "caution")]
    conn = m.junctions["9"].connections[0]
    assert (conn.incoming_road, conn.connecting_road, conn.contact_point, conn.lane_links) == (
        "8",
        "7",
        "end",
        [(-1, 1)],
    )


# ---------------------------------------------------------------------------------------------
# bad input


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (xodr(geom("<clothoid/>", 10), 10), "unknown geometry"),
        (xodr(geom("<line/>", 10), 0), "not positive"),
        (xodr(geom('<arc curvature="abc"/>', 10), 10), "not a number"),
        (xodr(geom("<arc/>", 10), 10), "lacks attribute curvature"),
        (xodr("", 10), "no geometry"),
        (
            xodr(
                geom("<line/>", 10),
                10,
                lanes=LANES.replace('<laneSection s="0">', '<laneSection s="5">', 1).replace(
                    "</lanes>", '<laneSection s="2"><center><lane id="0"/></center></laneSection></lanes>'
                ),
            ),
            "out of order",
        ),
        (xodr(geom("<line/>", 10), 10, lanes=LANES.replace('id="-1"', 'id="-2"')), "not contiguous"),
        (xodr(geom("<line/>", 10), 10, lanes="<lanes/>"), "no <laneSection>"),
        (
            xodr(
                geom('<paramPoly3 aU="0" bU="1" cU="0" dU="0" aV="0" bV="0" cV="0" dV="0" pRange="xy"/>', 10),
                10,
            ),
            "pRange",
        ),
    ],
)
def test_bad_input_names_road_and_element(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "bad.xodr"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        OpenDriveMap.load(path)
    msg = str(err.value)
    assert str(path) in msg and "road 7" in msg and needle in msg


def test_bad_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        OpenDriveMap.load(tmp_path / "missing.xodr")
    (tmp_path / "broken.xodr").write_text("<OpenDRIVE><header></OpenDRIVE>")
    with pytest.raises(InputError, match="malformed XML"):
        OpenDriveMap.load(tmp_path / "broken.xodr")
