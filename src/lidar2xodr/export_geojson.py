"""GeoJSON (RFC 7946) copy of an OpenDRIVE map for GIS tools: lanes, lane borders, reference lines.

A FeatureCollection in WGS84 (lon, lat; no "crs" member), projected from the map's geoReference
with pyproj. A map without geoReference is refused: its coordinates have no place on the earth
(our own exporter's placeholder frame at 0 N, 0 E is written, with a warning). Features, in road-id order:

- `reference_line`: LineString per road (properties road, name, junction, length_m);
- `lane`: Polygon per lane and lane section, the outer ring counter-clockwise from the inner border
  along s back over the outer border (properties road, section, lane, type, width_min_m,
  width_max_m); a lane of width 0 over its whole section has no area and is left out;
- `boundary`: LineString per lane border and lane-section piece between road-mark changes
  (properties road, section, lane = the lane whose outer border it is, 0 = centre line; mark_type,
  mark_weight, mark_color, mark_width_m; mark_type "none" where the map has no mark).

Coordinates have `geojson_decimals` decimals; one feature per line, keys sorted: the same map gives
the same bytes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidar2xodr.config import InterchangeConfig
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import write_text
from lidar2xodr.georeference import LOCAL_PLACEHOLDER, ToWgs84, horizontal
from lidar2xodr.map_lanes import SectionSamples, inner_border, road_order, sample_sections
from lidar2xodr.opendrive import OpenDriveMap

_MIN_AREA_M2 = 1e-6


@dataclass
class GeoJsonSummary:
    path: Path
    reference_lines: int
    lanes: int
    boundaries: int
    warnings: list[str] = field(default_factory=list)


def _coords(to_geo: ToWgs84, xy: np.ndarray, decimals: int) -> list[list[float]]:
    lon, lat = to_geo.lonlat(xy[:, 0], xy[:, 1])
    return [[round(a, decimals), round(b, decimals)] for a, b in zip(lon.tolist(), lat.tolist(), strict=True)]


def _feature(geometry: dict[str, Any], props: dict[str, Any]) -> dict[str, Any]:
    return {"type": "Feature", "geometry": geometry, "properties": props}


def _dedupe(xy: np.ndarray) -> np.ndarray:
    keep = np.concatenate([[True], np.any(np.abs(np.diff(xy, axis=0)) > 1e-9, axis=1)])
    return xy[keep]


def _lane_ring(sec: SectionSamples, lane_id: int) -> np.ndarray | None:
    """Closed counter-clockwise ring (local x, y) of a lane over its section; None when it has no area."""
    inner, outer = sec.xyz[inner_border(lane_id)][:, :2], sec.xyz[lane_id][:, :2]
    ring = _dedupe(np.vstack([inner, outer[::-1]]))
    if len(ring) > 1 and np.allclose(ring[0], ring[-1], rtol=0.0, atol=1e-9):
        ring = ring[:-1]
    if len(ring) < 3:
        return None
    x, y = ring[:, 0], ring[:, 1]
    area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    if abs(area) < _MIN_AREA_M2:
        return None
    ring = ring if area > 0 else ring[::-1]
    return np.vstack([ring, ring[:1]])


def build_features(odr: OpenDriveMap, cfg: InterchangeConfig, to_geo: ToWgs84) -> tuple[list[dict], list[int]]:
    """All features and the counts (reference lines, lanes, boundaries)."""
    dec = cfg.geojson_decimals
    refs, lanes, bounds = [], [], []
    for rid in sorted(odr.roads, key=road_order):
        road = odr.roads[rid]
        n = max(1, math.ceil(road.length / cfg.sample_step_m - 1e-9))
        x, y, _ = road.reference(np.linspace(0.0, road.length, n + 1))
        refs.append(_feature({"type": "LineString", "coordinates": _coords(to_geo, np.column_stack([x, y]), dec)},
                             {"kind": "reference_line", "road": rid, "name": road.name, "junction": road.junction,
                              "length_m": round(road.length, 3)}))
    for sec in sample_sections(odr, cfg.sample_step_m):
        rid = sec.road.id
        for lane_id in sorted(sec.section.lanes, key=lambda b: (abs(b), b)):
            if lane_id == 0:
                continue
            ring = _lane_ring(sec, lane_id)
            if ring is None:
                continue
            width = sec.width(lane_id)
            lanes.append(_feature({"type": "Polygon", "coordinates": [_coords(to_geo, ring, dec)]},
                                  {"kind": "lane", "road": rid, "section": sec.index, "lane": lane_id,
                                   "type": sec.section.lanes[lane_id].type,
                                   "width_min_m": round(float(width.min()), 3),
                                   "width_max_m": round(float(width.max()), 3)}))
        for border in sorted(sec.xyz, key=lambda b: (abs(b), b)):
            for piece in sec.pieces():
                mark = sec.mark(border, piece)
                xy = sec.xyz[border][piece[0]:piece[1] + 1, :2]
                bounds.append(_feature({"type": "LineString", "coordinates": _coords(to_geo, xy, dec)},
                                       {"kind": "boundary", "road": rid, "section": sec.index, "lane": border,
                                        "s_start_m": round(float(sec.s[piece[0]]), 3),
                                        "mark_type": mark.type if mark else "none",
                                        "mark_weight": mark.weight if mark else None,
                                        "mark_color": mark.color if mark else None,
                                        "mark_width_m": round(mark.width, 3) if mark else None}))
    return refs + lanes + bounds, [len(refs), len(lanes), len(bounds)]


def export_geojson(map_path: str | Path, out: str | Path, cfg: InterchangeConfig | None = None) -> GeoJsonSummary:
    """Read an OpenDRIVE map and write its GeoJSON FeatureCollection atomically."""
    cfg = cfg or InterchangeConfig()
    odr = OpenDriveMap.load(map_path)
    if odr.geo_reference is None:
        raise InputError(map_path, "the map has no geoReference, so its coordinates cannot be placed in WGS84 "
                         "for GeoJSON (add a <geoReference> PROJ string to the header)")
    warnings = []
    if horizontal(odr.geo_reference).split() == LOCAL_PLACEHOLDER.split():
        warnings.append(f"{map_path}: the geoReference is the local placeholder at 0 N, 0 E (built without "
                        "GNSS): the GeoJSON lies there, not where the drive was")
    to_geo = ToWgs84(odr.geo_reference, f"{map_path} <geoReference>")
    features, (n_ref, n_lanes, n_bounds) = build_features(odr, cfg, to_geo)
    lines = ",\n".join(json.dumps(f, sort_keys=True, separators=(",", ":"), allow_nan=False) for f in features)
    write_text(out, '{"type":"FeatureCollection","features":[\n' + lines + "\n]}\n")
    return GeoJsonSummary(Path(out), n_ref, n_lanes, n_bounds, warnings)
