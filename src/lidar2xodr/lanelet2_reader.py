"""Lanelet2 as a reader of an OpenDRIVE map: write it as .osm, load it back, route on it.

What a Lanelet2 user (Autoware) relies on, checked with lanelet2's own code: the file loads
(`lanelet2.io.loadRobust` reports no error), the routing graph (German traffic rules, vehicle) has
nothing to say in `checkValidity()`, and every lane link of the map, in travel direction, is a
`following` relation between the lanelets of the two lanes (lane sections, road links, junctions),
and every drivable lane has its lanelets.
The result has the shape of check.py's other readers: available, reader, version, warnings,
errors, ok, plus lanelets and links (linked lane pairs) and missing (those the graph does not route).
"""

from __future__ import annotations

import importlib.metadata
import tempfile
from pathlib import Path
from typing import Any

from lidar2xodr.config import InterchangeConfig
from lidar2xodr.errors import InputError
from lidar2xodr.map_lanes import DRIVABLE_TYPES, LaneKey, travel_successors
from lidar2xodr.opendrive import OpenDriveMap

_SHOWN = 10


def run_lanelet2(path: str | Path, cfg: InterchangeConfig | None = None) -> dict[str, Any]:
    """Export, load back and route; never raises for the map's sake (its problems are errors here)."""
    try:
        import lanelet2
        from lanelet2.routing import RoutingGraph
        from lanelet2.traffic_rules import Locations, Participants
    except ImportError:
        return {"available": False, "note": "lanelet2 not installed: not checked"}
    from lidar2xodr.export_lanelet2 import export_lanelet2, projector_for

    cfg = cfg or InterchangeConfig()
    out: dict[str, Any] = {"available": True, "reader": "lanelet2", "version": importlib.metadata.version("lanelet2"),
                           "warnings": [], "errors": []}
    try:
        odr = OpenDriveMap.load(path)
        with tempfile.TemporaryDirectory(prefix="lidar2xodr-lanelet2-") as tmp:
            osm = Path(tmp) / "map.osm"
            summary = export_lanelet2(path, osm, cfg)
            projector, _, _ = projector_for(odr)
            lmap, load_errors = lanelet2.io.loadRobust(str(osm), projector)
    except InputError as exc:
        out["errors"].append(str(exc))
        out["ok"] = False
        return out
    out["warnings"] += [w for w in summary.warnings if "no geoReference" not in w]
    out["errors"] += [f"load: {e}" for e in load_errors]
    graph = RoutingGraph(lmap, lanelet2.traffic_rules.create(Locations.Germany, Participants.Vehicle))
    out["errors"] += [f"routing graph: {e}" for e in graph.checkValidity()]
    got: set[tuple[LaneKey, LaneKey]] = set()
    kept: set[LaneKey] = set()
    for ll in lmap.laneletLayer:
        key = _key(ll)
        kept.add(key)
        got.update((key, _key(f)) for f in graph.following(ll) if _key(f) != key)
    short = cfg.min_lanelet_length_m
    lanes = {(rid, k, lid) for rid, road in odr.roads.items() for k, ls in enumerate(road.lane_sections)
             if ls.s_end - ls.s >= short for lid, lane in ls.lanes.items() if lid and lane.type in DRIVABLE_TYPES}
    if lanes - kept:
        out["errors"].append(f"{len(lanes - kept)} drivable lane(s) without a lanelet: {sorted(lanes - kept)[:_SHOWN]}")
    links = travel_successors(odr, kept)
    missing = sorted(links - got, key=str)
    if missing:
        shown = ", ".join(f"{a[0]}/{a[2]} -> {b[0]}/{b[2]}" for a, b in missing[:_SHOWN])
        out["errors"].append(f"{len(missing)} lane link(s) the routing graph does not follow (road/lane): {shown}")
    out.update(lanelets=summary.lanelets, links=len(links), missing=len(missing))
    out["ok"] = not out["errors"] and not out["warnings"]
    return out


def _key(ll: Any) -> LaneKey:
    a = ll.attributes
    return a["odr:road"], int(a["odr:section"]), int(a["odr:lane"])
