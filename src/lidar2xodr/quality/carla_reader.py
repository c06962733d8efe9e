"""CARLA's own OpenDRIVE parser (PyPI `carla`, offline: `carla.Map(name, xodr_text)`, no server) as a reader.

What a CARLA user meets, checked against what the map itself says (read by the project's reader):

* `loads`: the map parses (an exception is an error; a crash is caught by the caller, which runs
  this in a child process).
* waypoints: every driving lane of every lane section yields a waypoint at the section's middle
  (`get_waypoint_xodr`); lanes narrower than `EMPTY_LANE_M` everywhere in a section are skipped
  (there is no lane to drive). `max_centre_dev_m` is how far CARLA's waypoint lies from our lane
  centre there; CARLA's y axis is mirrored (Unreal's left-handed frame), so (x, -y) is compared.
* walk: from each such lane's start (in its driving direction: right lanes along s, left against
  it; the other way round on a road with rule="LHT"), `wp.next(WALK_STEP_M)` must stay on the
  lane to within one step of the section's end and, where the map links the lane on (to the next
  section's lane, the next road's, or a junction's connecting road), give a waypoint beyond it, no
  farther than `JUMP_FACTOR` steps away. A walk that stops short, finds no continuation or jumps
  is an error naming road, lane and s.
* topology: the pairs of roads `get_topology()` joins must be the pairs the map's own road and
  lane links join between driving lanes (a junction: incoming road to connecting road). A pair the
  map links and CARLA does not is an error; a pair CARLA joins and the map does not, a warning.
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path
from typing import Any

import numpy as np

WALK_STEP_M = 1.0
"""Step of the wp.next() walk: short enough that a break of one lane section (>= 1 m) cannot be jumped."""
JUMP_FACTOR = 2.0
"""A step of the walk that moves more than this many steps in space is a break (a link to the wrong end)."""
EMPTY_LANE_M = 0.05
"""A lane narrower than this over a whole section has no room for a vehicle; CARLA need not offer it."""
_MAX_MESSAGES = 50


def _driving_lanes(road: Any, k: int) -> list[Any]:
    sec = road.lane_sections[k]
    ds = np.linspace(0.0, sec.s_end - sec.s, 9)
    return [ln for lid, ln in sorted(sec.lanes.items())
            if lid != 0 and ln.type == "driving" and np.nanmax(ln.width(ds)) >= EMPTY_LANE_M]


def _continues(odr: Any, road: Any, k: int, lane: Any, forward: bool) -> bool:
    """Does the map link this lane on beyond its section's end in its driving direction?"""
    last = len(road.lane_sections) - 1 if forward else 0
    target = lane.successor if forward else lane.predecessor
    if k != last:
        return target is not None
    link = road.successor if forward else road.predecessor
    if link is None:
        return False
    if link.element_type == "road":
        return target is not None
    junction = odr.junctions.get(link.element_id)
    return junction is not None and any(
        c.incoming_road == road.id and any(a == lane.id for a, _ in c.lane_links) for c in junction.connections)


def _end_lane(road: Any, at_start: bool, lane_id: int | None) -> Any:
    if lane_id is None or not road.lane_sections:
        return None
    return road.lane_sections[0 if at_start else -1].lanes.get(lane_id)


def map_road_pairs(odr: Any) -> set[frozenset[str]]:
    """Pairs of roads the map's links join between driving lanes (road links and junction connections)."""
    pairs: set[frozenset[str]] = set()
    for road in odr.roads.values():
        if not road.lane_sections:
            continue
        for link, at_start in ((road.predecessor, True), (road.successor, False)):
            if link is None:
                continue
            mine = road.lane_sections[0 if at_start else -1].lanes
            if link.element_type == "road" and link.element_id in odr.roads:
                other = odr.roads[link.element_id]
                for lane in mine.values():
                    target = lane.predecessor if at_start else lane.successor
                    theirs = _end_lane(other, link.contact_point != "end", target)
                    if lane.type == "driving" and theirs is not None and theirs.type == "driving":
                        pairs.add(frozenset((road.id, other.id)))
            elif link.element_type == "junction" and link.element_id in odr.junctions:
                for conn in odr.junctions[link.element_id].connections:
                    other = odr.roads.get(conn.connecting_road)
                    if conn.incoming_road != road.id or other is None:
                        continue
                    for a, b in conn.lane_links:
                        theirs = _end_lane(other, conn.contact_point != "end", b)
                        if mine.get(a) is not None and mine[a].type == "driving" and theirs is not None \
                                and theirs.type == "driving":
                            pairs.add(frozenset((road.id, other.id)))
    return {p for p in pairs if len(p) == 2}


def _walk(cmap: Any, odr: Any, road: Any, k: int, lane: Any) -> str | None:
    """None when CARLA walks the lane through its section and on as the map links it; else the problem."""
    sec = road.lane_sections[k]
    forward = (lane.id < 0) != (road.rule.upper() == "LHT")
    eps = min(0.01, (sec.s_end - sec.s) / 4)
    s0 = sec.s + eps if forward else sec.s_end - eps
    wp = cmap.get_waypoint_xodr(int(road.id), lane.id, s0)
    if wp is None:
        return None  # reported by the waypoint check
    start_s = wp.s
    nxt: list[Any] = []
    for _ in range(int((sec.s_end - sec.s) / WALK_STEP_M) + 3):
        nxt = list(wp.next(WALK_STEP_M))
        same = [c for c in nxt if c.road_id == wp.road_id and c.section_id == wp.section_id
                and c.lane_id == wp.lane_id and (c.s - wp.s) * (1 if forward else -1) > 0]
        if not same:
            break
        wp = same[0]
    covered = abs(wp.s - start_s)
    need = sec.s_end - sec.s - 2 * eps
    if need - covered > WALK_STEP_M + 0.01:
        return (f"road {road.id} lane {lane.id}: wp.next() stops at s={wp.s:.2f}, "
                f"{need - covered:.2f} m before the end of its lane section [{sec.s:.2f}, {sec.s_end:.2f}]")
    end = sec.s_end if forward else sec.s
    if _continues(odr, road, k, lane, forward) and not nxt:
        return f"road {road.id} lane {lane.id}: no waypoint beyond s={end:.2f}, where the map links the lane on"
    if nxt:
        here = wp.transform.location
        jump = min(here.distance(c.transform.location) for c in nxt)
        if jump > JUMP_FACTOR * WALK_STEP_M:
            c = nxt[0]
            return (f"road {road.id} lane {lane.id}: wp.next() jumps {jump:.2f} m at s={end:.2f} "
                    f"(to road {c.road_id} lane {c.lane_id} s={c.s:.2f})")
    return None


def run_carla(path: Path, odr: Any | None) -> dict[str, Any]:
    """Load the map in CARLA's parser and run the checks of the module docstring (in this process)."""
    try:
        import carla
    except ImportError:
        return {"available": False, "note": "CARLA's Python package (PyPI carla) not installed: not checked"}
    out: dict[str, Any] = {"available": True, "reader": "CARLA", "version": importlib.metadata.version("carla"),
                           "warnings": [], "errors": []}
    try:
        cmap = carla.Map(Path(path).stem, Path(path).read_text(encoding="utf-8", errors="replace"))
        topology = cmap.get_topology()
    except Exception as exc:  # the parser's verdict on the file
        out.update(loads=False, ok=False)
        out["errors"].append(f"{type(exc).__name__}: {exc}")
        return out
    out.update(loads=True, topology_segments=len(topology))
    if odr is None:
        out["warnings"].append("the project's reader cannot read the map: lanes, walk and topology not checked")
        out["ok"] = False
        return out
    lanes = walked = 0
    dev = 0.0
    for road in odr.roads.values():
        if not road.id.lstrip("-").isdigit():
            out["warnings"].append(f"road id {road.id!r} is not an integer: CARLA cannot address it")
            continue
        for k, sec in enumerate(road.lane_sections):
            s_mid = 0.5 * (sec.s + sec.s_end)
            for lane in _driving_lanes(road, k):
                lanes += 1
                wp = cmap.get_waypoint_xodr(int(road.id), lane.id, s_mid)
                if wp is None:
                    out["errors"].append(f"road {road.id} lane {lane.id}: no waypoint at s={s_mid:.2f}")
                    continue
                inner = lane.id + (1 if lane.id < 0 else -1)
                t = 0.5 * (road.border_t(s_mid, lane.id)[0] + road.border_t(s_mid, inner)[0])
                ours = road.to_world(np.array([s_mid]), np.array([t]))[0]
                loc = wp.transform.location
                dev = max(dev, float(np.hypot(loc.x - ours[0], -loc.y - ours[1])))
                problem = _walk(cmap, odr, road, k, lane)
                walked += problem is None
                if problem:
                    out["errors"].append(problem)
    carla_pairs = {frozenset((str(a.road_id), str(b.road_id))) for a, b in topology if a.road_id != b.road_id}
    ours_pairs = map_road_pairs(odr)
    missing = sorted(tuple(sorted(p)) for p in ours_pairs - carla_pairs)
    extra = sorted(tuple(sorted(p)) for p in carla_pairs - ours_pairs)
    out["errors"] += [f"roads {a} and {b}: the map links their driving lanes, CARLA's topology does not join them"
                      for a, b in missing]
    out["warnings"] += [f"roads {a} and {b}: CARLA's topology joins them, the map links no driving lanes between them"
                        for a, b in extra]
    out.update(driving_lanes=lanes, lanes_walked=walked, max_centre_dev_m=dev, road_pairs=len(ours_pairs),
               road_pairs_missing=len(missing), road_pairs_extra=len(extra))
    for key in ("errors", "warnings"):
        if len(out[key]) > _MAX_MESSAGES:
            out[key] = out[key][:_MAX_MESSAGES] + [f"... {len(out[key]) - _MAX_MESSAGES} more"]
    out["ok"] = not out["errors"] and not out["warnings"]
    return out
