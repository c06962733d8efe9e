"""Lanelet2 (.osm) copy of an OpenDRIVE map, written with the lanelet2 library, for Autoware users.

- One lanelet per drivable lane (map_lanes.DRIVABLE_TYPES) and lane-section piece (a section is
  cut where a road mark changes), pointing along the travel direction: the bounds of a lane driven
  against s are the reversed border linestrings (left lanes under right-hand traffic).
- Borders are LineStrings shared by the two lanes beside them (the Lanelet2 convention that lets
  the routing graph see neighbours), tagged with the OpenDRIVE road mark: type line_thin (line_thick
  for weight bold), subtype solid / dashed / solid_solid / solid_dashed / dashed_solid in the
  linestring's own direction (along s, OpenDRIVE's words read from the inside of the lane out);
  curbstone / road_border for curbs and grass or edge marks; virtual where there is no mark.
- The lane ends that the map links (lanes across sections, road links, junction connections) are
  one point, so `RoutingGraph.following` joins them; linked ends farther apart than
  `join_tolerance_m` are left apart with a warning.
- Lanelet tags: subtype highway on motorways (else road), location urban for town* and lowSpeed
  roads (else `default_location`), one_way=yes (no for bidirectional lanes), speed_limit in km/h
  from the road's <speed> (Autoware's tag), and odr:road / odr:section / odr:lane naming the
  OpenDRIVE lane it came from.
- Positions: the map's local x, y go to WGS84 through its geoReference (pyproj), then into the
  local frame of a lanelet2 UtmProjector whose origin is the map's (0, 0); heights are the map's z.
  A map without geoReference is placed with georeference.LOCAL_PLACEHOLDER, with a warning.
- A lane section shorter than `min_lanelet_length_m` is bridged: no lanelets of its own, the
  lanelets before and after it share their end points.
- Ids are assigned in road, section, border, sample order: the same map gives the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import count
from pathlib import Path

import lanelet2
import numpy as np
from lanelet2.core import AttributeMap, GPSPoint, Lanelet, LaneletMap, LineString3d, Point3d
from lanelet2.io import Origin
from lanelet2.projection import UtmProjector

from lidar2xodr.config import InterchangeConfig
from lidar2xodr.errors import InputError, OutputError
from lidar2xodr.fileio import atomic_path
from lidar2xodr.georeference import LOCAL_PLACEHOLDER, ToWgs84
from lidar2xodr.map_lanes import (
    DRIVABLE_TYPES,
    LaneEnd,
    SectionSamples,
    along_s,
    inner_border,
    lane_joints,
    road_order,
    road_type_at,
    sample_sections,
)
from lidar2xodr.opendrive import OpenDriveMap, RoadMark, RoadType

_URBAN_TYPES = ("town", "lowSpeed", "pedestrian", "bicycle")
_NONURBAN_TYPES = ("motorway", "rural")
_WORDS = {"solid": "solid", "broken": "dashed", "botts": "dashed"}


@dataclass
class Lanelet2Summary:
    """What was written: counts, the projector origin and anything the user should know."""

    path: Path
    lanelets: int
    linestrings: int
    points: int
    joined_ends: int
    origin_lat: float
    origin_lon: float
    warnings: list[str] = field(default_factory=list)


def projector_for(odr: OpenDriveMap) -> tuple[UtmProjector, ToWgs84, list[str]]:
    """The lanelet2 projector of a map (origin = the map's local 0, 0) and the local -> WGS84 transform."""
    warnings = []
    geo = odr.geo_reference
    if geo is None:
        warnings.append(f"{odr.path} has no geoReference: the Lanelet2 map is placed with the local "
                        f"placeholder {LOCAL_PLACEHOLDER!r} (origin 0 N, 0 E)")
        geo = LOCAL_PLACEHOLDER
    to_geo = ToWgs84(geo, f"{odr.path} <geoReference>")
    return UtmProjector(Origin(to_geo.origin_lat, to_geo.origin_lon)), to_geo, warnings


def mark_tags(mark: RoadMark | None) -> dict[str, str]:
    """Lanelet2 linestring tags of an OpenDRIVE road mark on a border linestring running along s."""
    if mark is None or mark.type in ("none", "custom"):
        return {"type": "virtual"}
    if mark.type == "curb":
        return {"type": "curbstone", "subtype": "high"}
    if mark.type in ("grass", "edge"):
        return {"type": "road_border"}
    words = ["botts"] if mark.type == "botts dots" else mark.type.split()
    if not words or any(w not in _WORDS for w in words):
        return {"type": "virtual"}
    subtype = "_".join(_WORDS[w] for w in words[:2])
    if subtype == "dashed_dashed":
        subtype = "dashed"
    tags = {"type": "line_thick" if mark.weight == "bold" else "line_thin", "subtype": subtype}
    if mark.color not in ("standard", "white"):
        tags["color"] = mark.color
    return tags


def _oriented(tags: dict[str, str], border: int) -> dict[str, str]:
    """A double mark's words read from the lane inside out; on the centre lane from +t to -t.

    The linestring runs along s, so its left is +t: a left lane's (id > 0) inside is on the right.
    """
    sub = tags.get("subtype", "")
    if border > 0 and sub in ("solid_dashed", "dashed_solid"):
        return {**tags, "subtype": "dashed_solid" if sub == "solid_dashed" else "solid_dashed"}
    return tags


class _Ends:
    """Union-find over section-end samples of borders: (road, section, at_end, border)."""

    def __init__(self) -> None:
        self.parent: dict[LaneEnd, LaneEnd] = {}

    def find(self, key: LaneEnd) -> LaneEnd:
        root = key
        while self.parent.get(root, root) != root:
            root = self.parent[root]
        self.parent[key] = root
        return root

    def union(self, a: LaneEnd, b: LaneEnd) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            lo, hi = sorted((ra, rb), key=lambda k: (road_order(k[0]), k[1:]))
            self.parent[hi] = lo


def _join_ends(
    sections: list[SectionSamples], odr: OpenDriveMap, cfg: InterchangeConfig
) -> tuple[_Ends, int, list[str]]:
    """Merge the border ends of every lane joint that lie within tolerance, and both ends of the
    borders of every bridged (too short) section."""
    tol = cfg.join_tolerance_m
    pos = {}
    ends = _Ends()
    for sec in sections:
        if _bridged(sec, cfg):
            for border in sec.xyz:
                ends.union((sec.road.id, sec.index, False, border), (sec.road.id, sec.index, True, border))
        for border, xyz in sec.xyz.items():
            pos[(sec.road.id, sec.index, False, border)] = xyz[0]
            pos[(sec.road.id, sec.index, True, border)] = xyz[-1]
    joints, warnings = lane_joints(odr)
    joined = 0
    for a, b in joints:
        pairs = [((*a[:3], ba), (*b[:3], bb)) for ba, bb in ((inner_border(a[3]), inner_border(b[3])), (a[3], b[3]))]
        pairs = [(ka, kb) for ka, kb in pairs if ka in pos and kb in pos]
        gaps = [float(np.linalg.norm(pos[ka] - pos[kb])) for ka, kb in pairs]
        for (ka, kb), gap in zip(pairs, gaps, strict=True):
            if gap <= tol:
                ends.union(ka, kb)
                joined += 1
        if gaps and max(gaps) > tol:
            warnings.append(f"road {a[0]} lane {a[3]} and road {b[0]} lane {b[3]} are linked but their borders "
                            f"are up to {max(gaps):.3f} m apart: not joined in the Lanelet2 map")
    return ends, joined, warnings


def build_lanelet_map(odr: OpenDriveMap, cfg: InterchangeConfig) -> tuple[LaneletMap, UtmProjector, Lanelet2Summary]:
    """The Lanelet2 map of an OpenDRIVE map, in the projector's local frame."""
    projector, to_geo, warnings = projector_for(odr)
    sections = sample_sections(odr, cfg.sample_step_m)
    ends, joined, join_warnings = _join_ends(sections, odr, cfg)
    builder = _Builder(projector, to_geo, ends, cfg)
    for sec in sections:
        if not _bridged(sec, cfg):
            builder.add_lanelets(sec, builder.border_strings(sec))
    if builder.lanelets == 0:
        raise InputError(odr.path, "the map has no drivable lane to write as a lanelet")
    summary = Lanelet2Summary(Path(), builder.lanelets, builder.strings, builder.points, joined,
                              to_geo.origin_lat, to_geo.origin_lon, warnings + join_warnings)
    return builder.map, projector, summary


class _Builder:
    """Adds points, border linestrings and lanelets section by section; ids in creation order."""

    def __init__(self, projector: UtmProjector, to_geo: ToWgs84, ends: _Ends, cfg: InterchangeConfig) -> None:
        self.projector, self.to_geo, self.ends, self.cfg = projector, to_geo, ends, cfg
        self.map = LaneletMap()
        self.ids = count(1)
        self.shared: dict[LaneEnd, Point3d] = {}
        self.points = self.strings = self.lanelets = 0

    def _local(self, xyz: np.ndarray) -> list[tuple[float, float, float]]:
        """Map x, y, z to the projector's frame (through WGS84; z stays)."""
        lon, lat = self.to_geo.lonlat(xyz[:, 0], xyz[:, 1])
        out = []
        for la, lo, z in zip(lat.tolist(), lon.tolist(), xyz[:, 2].tolist(), strict=True):
            p = self.projector.forward(GPSPoint(la, lo, z))
            out.append((p.x, p.y, z))
        return out

    def _border_points(self, sec: SectionSamples, border: int) -> list[Point3d]:
        """The border's points; its two end points are shared with every lane end joined to them."""
        n = len(sec.s)
        keys = {0: self.ends.find((sec.road.id, sec.index, False, border)),
                n - 1: self.ends.find((sec.road.id, sec.index, True, border))}
        pts = []
        for i, c in enumerate(self._local(sec.xyz[border])):
            p = self.shared.get(keys[i]) if i in keys else None
            if p is None:
                p = Point3d(next(self.ids), *c)
                self.points += 1
                if i in keys:
                    self.shared[keys[i]] = p
            pts.append(p)
        return pts

    def border_strings(self, sec: SectionSamples) -> dict[tuple[int, int], LineString3d]:
        """One linestring per border and piece, along s, tagged with the piece's road mark."""
        strings = {}
        for border in sorted(sec.xyz, key=lambda b: (abs(b), b)):
            pts = self._border_points(sec, border)
            for p, (i0, i1) in enumerate(sec.pieces()):
                tags = _oriented(mark_tags(sec.mark(border, (i0, i1))), border)
                strings[(border, p)] = LineString3d(next(self.ids), pts[i0:i1 + 1], AttributeMap(tags))
                self.strings += 1
        return strings

    def add_lanelets(self, sec: SectionSamples, strings: dict[tuple[int, int], LineString3d]) -> None:
        """A lanelet per drivable lane and piece, its bounds reversed where the lane runs against s."""
        for p, piece in enumerate(sec.pieces()):
            rtype = road_type_at(sec.road, float(sec.s[piece[0]]))
            for lane_id in sorted(sec.section.lanes, key=lambda b: (abs(b), b)):
                lane = sec.section.lanes[lane_id]
                if lane_id == 0 or lane.type not in DRIVABLE_TYPES:
                    continue
                inner, outer = strings[(inner_border(lane_id), p)], strings[(lane_id, p)]
                left, right = (inner, outer) if lane_id < 0 else (outer, inner)
                if not (along_s(sec.road, lane_id) or lane.type == "bidirectional"):
                    left, right = right.invert(), left.invert()
                tags = _lanelet_tags(rtype, self.cfg, lane.type)
                tags.update({"odr:road": sec.road.id, "odr:section": str(sec.index), "odr:lane": str(lane_id)})
                self.map.add(Lanelet(next(self.ids), left, right, AttributeMap(tags)))
                self.lanelets += 1


def _bridged(sec: SectionSamples, cfg: InterchangeConfig) -> bool:
    return sec.section.s_end - sec.section.s < cfg.min_lanelet_length_m


def _lanelet_tags(rtype: RoadType | None, cfg: InterchangeConfig, lane_type: str) -> dict[str, str]:
    """Lanelet tags from the OpenDRIVE road type valid there and the lane's type."""
    kind = rtype.type if rtype is not None else "unknown"
    location = "urban" if kind.startswith(_URBAN_TYPES) else "nonurban" if kind in _NONURBAN_TYPES else None
    tags = {
        "type": "lanelet",
        "subtype": "highway" if kind == "motorway" else "road",
        "location": location or cfg.default_location,
        "one_way": "no" if lane_type == "bidirectional" else "yes",
    }
    if rtype is not None and rtype.speed_max_mps is not None:
        tags["speed_limit"] = f"{round(rtype.speed_max_mps * 3.6, 1):g}"
    return tags


def export_lanelet2(map_path: str | Path, out: str | Path, cfg: InterchangeConfig | None = None) -> Lanelet2Summary:
    """Read an OpenDRIVE map and write its Lanelet2 .osm atomically."""
    cfg = cfg or InterchangeConfig()
    odr = OpenDriveMap.load(map_path)
    lmap, projector, summary = build_lanelet_map(odr, cfg)
    out = Path(out)
    with atomic_path(out, suffix=".osm") as tmp:
        errors = lanelet2.io.writeRobust(str(tmp), lmap, projector)
        if errors:
            raise OutputError(out, f"lanelet2 could not write the map: {'; '.join(errors[:3])}")
    summary.path = out
    return summary
