"""The lanes of an OpenDRIVE map as lane-level exporters need them (Lanelet2, GeoJSON).

- Every lane section is sampled along s at <= `step` and cut into pieces wherever a road mark of
  one of its lanes changes, so each piece of a border carries one mark.
- A border is the outer border of a lane (border 0: the centre lane, the laneOffset line); a lane
  lies between its inner border (id - sign) and its outer border (id).
- Travel direction: right lanes along s under right-hand traffic (left lanes against it), mirrored
  for rule="LHT"; lanes of type bidirectional are driven both ways.
- Joints: the lane ends that the map's links say are one lane continued, from lane links within a
  road, road-to-road links (contactPoint start/end) and junction connections (classic and direct).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidar2xodr.opendrive import LaneSection, OpenDriveMap, Road, RoadMark, RoadType, _sample_section

DRIVABLE_TYPES = frozenset({
    "driving", "entry", "exit", "onRamp", "offRamp", "connectingRamp", "slipLane", "mwyEntry", "mwyExit",
    "bidirectional",
})
"""OpenDRIVE lane types a car may drive in (1.4-1.8 names)."""

_BREAK_EPS_M = 1e-6


def road_order(road_id: str) -> tuple[int, int | str]:
    """Sort key of road ids: numeric ids by value, then the others by name."""
    return (0, int(road_id)) if road_id.isdigit() else (1, road_id)


def inner_border(lane_id: int) -> int:
    return lane_id - (1 if lane_id > 0 else -1)


def along_s(road: Road, lane_id: int) -> bool:
    """True when lane_id is driven in the direction of increasing s."""
    return (lane_id < 0) == (road.rule != "LHT")


def road_type_at(road: Road, s: float) -> RoadType | None:
    """The <type> record valid at s (None when the road has none)."""
    valid = [t for t in road.types if t.s <= s + _BREAK_EPS_M]
    return valid[-1] if valid else (road.types[0] if road.types else None)


@dataclass
class SectionSamples:
    """One lane section sampled along s, cut into pieces at road-mark changes."""

    road: Road
    index: int
    section: LaneSection
    s: np.ndarray
    breaks: list[int]  # sample indices of the piece ends, first 0, last len(s) - 1
    xyz: dict[int, np.ndarray]  # border id -> (n, 3) world points
    t: dict[int, np.ndarray]  # border id -> (n,) lateral offset

    def pieces(self) -> list[tuple[int, int]]:
        return list(zip(self.breaks[:-1], self.breaks[1:], strict=True))

    def mark(self, border: int, piece: tuple[int, int]) -> RoadMark | None:
        """The road mark drawn on a border over one piece (None: no mark record)."""
        ds = self.s[piece[0]] - self.section.s + _BREAK_EPS_M
        marks = [m for m in self.section.lanes[border].road_marks if m.s_offset <= ds]
        return marks[-1] if marks else None

    def width(self, lane_id: int) -> np.ndarray:
        return np.abs(self.t[lane_id] - self.t[inner_border(lane_id)])


def sample_sections(odr: OpenDriveMap, step: float) -> list[SectionSamples]:
    """Every lane section of every road (roads in id order), both ends included."""
    out = []
    for rid in sorted(odr.roads, key=road_order):
        road = odr.roads[rid]
        for k, ls in enumerate(road.lane_sections):
            knots = [ls.s]
            for cut in sorted({ls.s + m.s_offset for lane in ls.lanes.values() for m in lane.road_marks}):
                if knots[-1] + _BREAK_EPS_M < cut < ls.s_end - _BREAK_EPS_M:
                    knots.append(cut)
            knots.append(ls.s_end)
            parts, breaks = [knots[:1]], [0]
            for a, b in zip(knots[:-1], knots[1:], strict=True):
                n = max(1, math.ceil((b - a) / step - 1e-9))
                parts.append(np.linspace(a, b, n + 1)[1:])
                breaks.append(breaks[-1] + n)
            s = np.concatenate(parts)
            sampled = _sample_section(road, k, ls, s)
            out.append(SectionSamples(road, k, ls, s, breaks, sampled.border_xyz, sampled.border_t))
    return out


LaneEnd = tuple[str, int, bool, int]
"""(road id, lane section index, at the section's end (else its start), lane id)."""


def lane_joints(odr: OpenDriveMap) -> tuple[list[tuple[LaneEnd, LaneEnd]], list[str]]:
    """Pairs of lane ends that the map's links join (sorted, each pair once) and the junction lane
    links that name a lane the road does not have there (left out)."""
    pairs: set[tuple[LaneEnd, LaneEnd]] = set()
    warnings: list[str] = []

    def add(a: LaneEnd, b: LaneEnd) -> None:
        if a[3] != 0 and b[3] != 0:
            pairs.add((a, b) if (road_order(a[0]), a[1:]) <= (road_order(b[0]), b[1:]) else (b, a))

    def end_section(road: Road, at_end: bool) -> tuple[int, LaneSection]:
        k = len(road.lane_sections) - 1 if at_end else 0
        return k, road.lane_sections[k]

    for rid, road in odr.roads.items():
        secs = road.lane_sections
        for k in range(len(secs) - 1):
            for lid, lane in secs[k].lanes.items():
                if lane.successor is not None and lane.successor in secs[k + 1].lanes:
                    add((rid, k, True, lid), (rid, k + 1, False, lane.successor))
            for lid, lane in secs[k + 1].lanes.items():
                if lane.predecessor is not None and lane.predecessor in secs[k].lanes:
                    add((rid, k, True, lane.predecessor), (rid, k + 1, False, lid))
        for link, at_end in ((road.predecessor, False), (road.successor, True)):
            if link is None or link.element_type != "road" or link.element_id not in odr.roads:
                continue
            other = odr.roads[link.element_id]
            other_end = link.contact_point == "end" if link.contact_point else not at_end
            k, ls = end_section(road, at_end)
            ok, ols = end_section(other, other_end)
            for lid, lane in ls.lanes.items():
                target = lane.successor if at_end else lane.predecessor
                if target is not None and target in ols.lanes:
                    add((rid, k, at_end, lid), (other.id, ok, other_end, target))
    for jid, junction in odr.junctions.items():
        for conn in junction.connections:
            inc, con = odr.roads.get(conn.incoming_road), odr.roads.get(conn.connecting_road)
            if inc is None or con is None:
                continue
            inc_end = _junction_end(inc, jid)
            if inc_end is None:
                continue
            con_end = conn.contact_point == "end"
            k, ls = end_section(inc, inc_end)
            ck, cls_ = end_section(con, con_end)
            for a, b in conn.lane_links:
                if a in ls.lanes and b in cls_.lanes:
                    add((inc.id, k, inc_end, a), (con.id, ck, con_end, b))
                else:
                    warnings.append(f"junction {jid} connection {conn.id}: laneLink from {a} to {b} names a lane "
                                    f"that road {inc.id} or {con.id} lacks at the junction; left out")
    return sorted(pairs, key=lambda p: [(road_order(e[0]), e[1:]) for e in p]), warnings


def _junction_end(road: Road, junction_id: str) -> bool | None:
    """Which end of the road touches the junction (True: its end); None when neither link names it."""
    for link, at_end in ((road.successor, True), (road.predecessor, False)):
        if link is not None and link.element_type == "junction" and link.element_id == junction_id:
            return at_end
    return None


LaneKey = tuple[str, int, int]
"""(road id, lane section index, lane id)."""


def travel_successors(odr: OpenDriveMap, kept: set[LaneKey] | None = None) -> set[tuple[LaneKey, LaneKey]]:
    """Lane-to-lane successors in travel direction from the map's links, between drivable lanes.

    With `kept`, lanes outside it (too short to keep) are contracted: a -> t -> b becomes a -> b.
    """
    edges: set[tuple[LaneKey, LaneKey]] = set()
    joints, _ = lane_joints(odr)
    for a, b in joints:
        ends = []
        for rid, k, at_end, lid in (a, b):
            lane = odr.roads[rid].lane_sections[k].lanes[lid]
            ends.append(((rid, k, lid), along_s(odr.roads[rid], lid) == at_end, lane.type in DRIVABLE_TYPES))
        (ka, a_leaves, a_ok), (kb, b_leaves, b_ok) = ends
        if a_ok and b_ok and a_leaves != b_leaves:
            edges.add((ka, kb) if a_leaves else (kb, ka))
    if kept is not None:
        for t in sorted({k for e in edges for k in e} - kept, key=lambda k: (road_order(k[0]), k[1:])):
            into = {a for a, b in edges if b == t and a != t}
            out = {b for a, b in edges if a == t and b != t}
            edges = {e for e in edges if t not in e} | {(a, b) for a in into for b in out}
    return edges
