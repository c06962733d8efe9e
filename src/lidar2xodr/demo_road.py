"""The project's own demo road: a 3 km German-style motorway carriageway, written with scenariogeneration.

Used by `make demo`, the tests and the benchmarks, so the project runs end to end without any
third-party data. It holds what makes the method hard: a left and a right curve joined by
clothoids (R = 1500 m and 2500 m), a crest (elevation), superelevation in the curves, three
3.75 m lanes with solid 0.30 m edge lines and broken 0.15 m 6 m / 12 m lane lines, and an
added lane on the right that grows from zero width, runs 260 m, and tapers out again.
Coordinates are local (the road starts at 0, 0); the geoReference places it near Stuttgart.
"""

from __future__ import annotations

from pathlib import Path

from lxml import etree
from scenariogeneration import xodr

from lidar2xodr.fileio import atomic_path

GEO_REFERENCE = "+proj=tmerc +lat_0=48.78 +lon_0=9.18 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
LANE_WIDTH = 3.75
ADDED_LANE = (1600.0, 2100.0)  # lane section of the added lane
TAPER = 120.0


def _ramp(a: float, b: float, length: float) -> tuple[float, float, float, float]:
    """Cubic with zero slope at both ends from a to b over `length`."""
    d = b - a
    return a, 0.0, 3 * d / length**2, -2 * d / length**3


def _marks(kind: str) -> xodr.RoadMark:
    if kind == "solid":
        return xodr.RoadMark(xodr.RoadMarkType.solid, 0.30)
    return xodr.RoadMark(xodr.RoadMarkType.broken, 0.15, length=6.0, space=12.0)


def _section(s: float, n_lanes: int, added: bool) -> xodr.LaneSection:
    center = xodr.Lane()
    center.add_roadmark(_marks("solid"))
    sec = xodr.LaneSection(s, center)
    median = xodr.Lane(xodr.LaneType.border, a=1.0)
    sec.add_left_lane(median)
    for i in range(n_lanes):
        lane = xodr.Lane(xodr.LaneType.driving, a=LANE_WIDTH)
        lane.add_roadmark(_marks("solid" if i == n_lanes - 1 and not added else "broken"))
        sec.add_right_lane(lane)
    if added:
        length = ADDED_LANE[1] - ADDED_LANE[0]
        extra = xodr.Lane(xodr.LaneType.driving, *_ramp(0.0, LANE_WIDTH, TAPER))
        extra.add_lane_width(LANE_WIDTH, 0, 0, 0, soffset=TAPER)
        extra.add_lane_width(*_ramp(LANE_WIDTH, 0.0, TAPER), soffset=length - TAPER)
        extra.add_roadmark(_marks("solid"))
        sec.add_right_lane(extra)
    sec.add_right_lane(xodr.Lane(xodr.LaneType.shoulder, a=2.5))
    return sec


def _link_sections(sections: list[xodr.LaneSection]) -> None:
    """Lane links both ways; the added lane has none, the shoulder moves one id outwards."""
    ids = [[-(i + 1) for i in range(len(sec.rightlanes))] for sec in sections]
    for k in range(len(sections) - 1):
        a, b = sections[k], sections[k + 1]
        na, nb = len(ids[k]), len(ids[k + 1])
        for i in range(min(na, nb) - 1):
            a.rightlanes[i].add_link("successor", ids[k + 1][i])
            b.rightlanes[i].add_link("predecessor", ids[k][i])
        a.rightlanes[-1].add_link("successor", ids[k + 1][-1])
        b.rightlanes[-1].add_link("predecessor", ids[k][-1])
        a.leftlanes[0].add_link("successor", 1)
        b.leftlanes[0].add_link("predecessor", 1)


def build_demo_road() -> xodr.OpenDrive:
    plan = xodr.PlanView(0.0, 0.0, 0.0)
    for geom in (
        xodr.Line(400),
        xodr.Spiral(0.0, 1 / 1500, 150),
        xodr.Arc(1 / 1500, 550),
        xodr.Spiral(1 / 1500, 0.0, 150),
        xodr.Line(450),
        xodr.Spiral(0.0, -1 / 2500, 150),
        xodr.Arc(-1 / 2500, 500),
        xodr.Spiral(-1 / 2500, 0.0, 150),
        xodr.Line(500),
    ):
        plan.add_geometry(geom)
    lanes = xodr.Lanes()
    sections = [
        _section(0.0, 3, added=False),
        _section(ADDED_LANE[0], 3, added=True),
        _section(ADDED_LANE[1], 3, added=False),
    ]
    _link_sections(sections)
    for sec in sections:
        lanes.add_lanesection(sec)
    road = xodr.Road(1, plan, lanes, name="demo motorway")

    # Crest: up at 2 %, flattening out at the end of the road.
    road.add_elevation(0.0, 0.0, 0.02, -0.02 / (2 * 3000.0), 0.0)
    # Superelevation: left curve banks left side down (negative roll), right curve the other way.
    for s, (a, b, c, d) in (
        (0.0, (0.0, 0, 0, 0)),
        (400.0, _ramp(0.0, -0.025, 150)),
        (550.0, (-0.025, 0, 0, 0)),
        (1100.0, _ramp(-0.025, 0.0, 150)),
        (1250.0, (0.0, 0, 0, 0)),
        (1700.0, _ramp(0.0, 0.025, 150)),
        (1850.0, (0.025, 0, 0, 0)),
        (2350.0, _ramp(0.025, 0.0, 150)),
        (2500.0, (0.0, 0, 0, 0)),
    ):
        road.add_superelevation(s, a, b, c, d)
    odr = xodr.OpenDrive("lidar2xodr demo motorway", revMajor="1", revMinor="8", geo_reference=GEO_REFERENCE)
    odr.add_road(road)
    odr.adjust_roads_and_lanes()
    return odr


def write_demo_road(path: str | Path) -> Path:
    """Write the demo road atomically; the header date is fixed so the bytes never change."""
    path = Path(path)
    odr = build_demo_road()
    root = odr.get_element()
    root.find("header").set("date", "2026-01-01T00:00:00")
    data = etree.tostring(etree.fromstring(_to_bytes(root)), pretty_print=True, xml_declaration=True,
                          encoding="utf-8")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def _to_bytes(element: object) -> bytes:
    import xml.etree.ElementTree as ET

    return ET.tostring(element)  # type: ignore[arg-type]
