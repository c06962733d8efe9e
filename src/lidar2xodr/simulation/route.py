"""The route: a chain of roads through the network, repeated into laps, sampled with its lanes.

Decisions:
- Roads are nodes (road, direction); direction +1 drives along +s in the right-hand lanes (left
  ones under rule="LHT"), -1 along -s in the other side's lanes. Links follow the roads' own
  predecessor/successor records and, in junctions, the connecting roads that touch the incoming
  road's end. A node is usable when its side has a lane of type "driving".
- Default route: the longest chain (sum of road lengths) that never drives a road twice, found by
  a depth-first search over every start on a non-junction road (bounded to 300 000 expansions,
  deterministic order). --start-road fixes the first road (its longer direction wins).
- Laps (--length-m longer than the route): a closed route (its last road links back to its first)
  is driven round and round. Otherwise the ego drives back and forth: at each end it slows down and
  makes a U-turn (two arcs of 6 m radius, a "light-bulb" turn when the lanes are closer than 12 m)
  from the rightmost to the leftmost lane, and drives the chain back. On roads without lanes for
  the way back (one-way carriageways) the way back uses the same lanes against their direction,
  traffic included, which a LiDAR sees like the other carriageway of a mirrored road. At most
  MAX_LAPS passes; a route too short to turn on cannot be repeated.
- Lateral position is lambda, metres to the left of the travel direction, continuous across road
  transitions (each leg carries an offset c with lambda = direction * t + c).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lidar2xodr.errors import InputError
from lidar2xodr.opendrive import OpenDriveMap, Road

DRIVING = frozenset({"driving"})
PAVED = frozenset({
    "driving", "entry", "exit", "onRamp", "offRamp", "connectingRamp", "shoulder", "stop", "restricted",
    "parking", "biking", "bidirectional", "slipLane", "mwyEntry", "mwyExit", "special1", "special2", "special3",
})
MAX_LAPS = 200
TURN_RADIUS_M = 6.0
SAMPLE_M = 1.0
USABLE_WIDTH_M = 2.6
MAX_LANES = 8
_SEARCH_BUDGET = 300_000

Node = tuple[str, int]


def lane_side(road: Road, direction: int) -> int:
    """Sign of the lane ids that carry traffic travelling in `direction` on `road`."""
    side = -1 if direction > 0 else 1
    return -side if road.rule.upper() == "LHT" else side


def has_driving(road: Road, side: int) -> bool:
    return any(
        lane.type in DRIVING and lane.id * side > 0 for ls in road.lane_sections for lane in ls.lanes.values()
    )


def _natural(rid: str) -> tuple:
    return (0, int(rid), rid) if rid.lstrip("-").isdigit() else (1, 0, rid)


class RoadGraph:
    """Successors of (road, direction) nodes, following road links and junction connecting roads."""

    def __init__(self, odr: OpenDriveMap) -> None:
        self.odr = odr
        self._succ: dict[Node, list[Node]] = {}

    def valid(self, node: Node) -> bool:
        road = self.odr.roads.get(node[0])
        return road is not None and has_driving(road, lane_side(road, node[1]))

    def successors(self, node: Node) -> list[Node]:
        if node not in self._succ:
            self._succ[node] = [n for n in self._raw_successors(node) if self.valid(n)]
        return self._succ[node]

    def _raw_successors(self, node: Node) -> list[Node]:
        road = self.odr.roads[node[0]]
        link = road.successor if node[1] > 0 else road.predecessor
        my_cp = "end" if node[1] > 0 else "start"
        if link is None:
            return []
        if link.element_type == "road":
            nxt = self.odr.roads.get(link.element_id)
            if nxt is None:
                return []
            cp = link.contact_point or self._nearest_end(road, my_cp, nxt)
            return [(nxt.id, 1 if cp == "start" else -1)]
        jid = link.element_id
        junction = self.odr.junctions.get(jid)
        pairs = [(c.connecting_road, c.contact_point) for c in junction.connections if c.incoming_road == road.id] \
            if junction else []
        if not pairs:
            pairs = [(r.id, None) for r in self.odr.roads.values() if r.junction == jid]
        out: list[Node] = []
        for name, cp in dict.fromkeys(pairs):
            c = self.odr.roads.get(name)
            if c is None:
                continue
            if _touches(c.predecessor, road.id, my_cp):
                out.append((c.id, 1))
            elif _touches(c.successor, road.id, my_cp):
                out.append((c.id, -1))
            elif cp in ("start", "end") and _in_junction(c.predecessor if cp == "start" else c.successor, jid):
                out.append((c.id, 1 if cp == "start" else -1))  # direct junction: roads meet without connectors
        return sorted(set(out), key=lambda n: (_natural(n[0]), n[1]))

    def _nearest_end(self, road: Road, my_cp: str, nxt: Road) -> str:
        p = road.to_world(road.length if my_cp == "end" else 0.0, 0.0)[0, :2]
        a = nxt.to_world(0.0, 0.0)[0, :2]
        b = nxt.to_world(nxt.length, 0.0)[0, :2]
        return "start" if np.linalg.norm(p - a) <= np.linalg.norm(p - b) else "end"


def _touches(link, road_id: str, cp: str) -> bool:
    return (
        link is not None and link.element_type == "road" and link.element_id == road_id
        and link.contact_point in (None, cp)
    )


def _in_junction(link, jid: str) -> bool:
    return link is not None and link.element_type == "junction" and link.element_id == jid


def longest_chain(graph: RoadGraph, start_road: str | None, where: str) -> list[Node]:
    """The longest chain of nodes (by road length) that drives no road twice."""
    odr = graph.odr
    if start_road is not None:
        if start_road not in odr.roads:
            raise InputError(where, f"--start-road {start_road}: no such road (roads: {_few(odr.roads)})")
        starts = [n for n in ((start_road, 1), (start_road, -1)) if graph.valid(n)]
        if not starts:
            raise InputError(where, f"road {start_road} has no lane of type driving to start in")
    else:
        nodes = [(rid, d) for rid in sorted(odr.roads, key=_natural) for d in (1, -1) if graph.valid((rid, d))]
        if not nodes:
            raise InputError(where, "the map has no lane of type driving: nothing to drive on")
        plain = [n for n in nodes if odr.roads[n[0]].junction == "-1"] or nodes
        has_pred = {m for n in nodes for m in graph.successors(n)}
        starts = [n for n in plain if n not in has_pred] + [n for n in plain if n in has_pred]
    best: list[Node] = []
    best_len = -1.0
    budget = _SEARCH_BUDGET
    for start in starts:
        path, seen = [start], {start[0]}
        lengths = [odr.roads[start[0]].length]
        stack = [iter(graph.successors(start))]
        if lengths[-1] > best_len:
            best, best_len = list(path), lengths[-1]
        while stack and budget > 0:
            budget -= 1
            nxt = next(stack[-1], None)
            if nxt is None:
                stack.pop()
                seen.discard(path.pop()[0])
                lengths.pop()
                continue
            if nxt[0] in seen:
                continue
            path.append(nxt)
            seen.add(nxt[0])
            lengths.append(lengths[-1] + odr.roads[nxt[0]].length)
            stack.append(iter(graph.successors(nxt)))
            if lengths[-1] > best_len + 1e-9:
                best, best_len = list(path), lengths[-1]
        if budget <= 0:
            break
    return best


def _few(d: dict) -> str:
    keys = sorted(d, key=_natural)
    return ", ".join(keys[:10]) + (" ..." if len(keys) > 10 else "")


@dataclass
class TurnPath:
    """A U-turn in the local frame of its start (x forward, y left), sampled by arc length."""

    origin: np.ndarray  # (3,) world start point
    forward: np.ndarray  # (2,)
    left: np.ndarray  # (2,)
    z_end: float
    sigma: np.ndarray  # (M,) arc length
    xy: np.ndarray  # (M, 2) local
    residual: float = 0.0  # lateral error of the ego at entry, blended out over the first 10 m

    @property
    def length(self) -> float:
        return float(self.sigma[-1])

    def world(self, sigma: np.ndarray) -> np.ndarray:
        x = np.interp(sigma, self.sigma, self.xy[:, 0])
        y = np.interp(sigma, self.sigma, self.xy[:, 1])
        y = y + self.residual * (1.0 - _smooth(sigma / 10.0))
        xy = self.origin[:2] + x[:, None] * self.forward + y[:, None] * self.left
        z = self.origin[2] + (self.z_end - self.origin[2]) * _smooth(sigma / max(self.length, 1e-9))
        return np.column_stack([xy, z])


def _smooth(x: np.ndarray) -> np.ndarray:
    """Quintic 0 -> 1 on [0, 1] with zero velocity and acceleration at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10 + x * (-15 + 6 * x))


def turn_shape(d: float, radius: float = TURN_RADIUS_M) -> tuple[np.ndarray, np.ndarray]:
    """Local U-turn from (0, 0) heading +x to (0, d) heading -x: arc length samples and xy."""
    d = max(d, 0.0)
    if d >= 2 * radius:
        # quarter arc, straight across, quarter arc
        segs = [(radius, math.pi / 2), (math.inf, d - 2 * radius), (radius, math.pi / 2)]
    else:
        alpha = math.acos((d + 2 * radius) / (4 * radius))
        segs = [(-radius, alpha), (radius, math.pi + 2 * alpha), (-radius, alpha)]
    pts, sig = [np.zeros(2)], [0.0]
    pos, hdg, total = np.zeros(2), 0.0, 0.0
    for r, a in segs:
        length = a if math.isinf(r) else abs(r) * a
        n = max(2, int(math.ceil(length / 0.1)))
        ds = np.linspace(0.0, length, n + 1)[1:]
        if math.isinf(r):
            p = pos + np.outer(ds, [math.cos(hdg), math.sin(hdg)])
            h = np.full(n, hdg)
        else:
            k = 1.0 / r
            h = hdg + k * ds
            p = pos + np.column_stack([np.sin(h) - math.sin(hdg), -np.cos(h) + math.cos(hdg)]) / k
        pts.append(p)
        sig.append(total + ds)
        pos, hdg, total = p[-1], float(h[-1]), total + length
    xy = np.vstack([pts[0][None], *pts[1:]])
    return np.concatenate([[0.0], *sig[1:]]), xy


@dataclass
class Leg:
    kind: str  # "road" | "turn"
    u0: float
    u1: float
    lap: int
    road: str = ""
    direction: int = 1
    s0: float = 0.0  # station at u0
    c: float = 0.0  # lambda = direction * t + c
    wrong_way: bool = False
    turn: TurnPath | None = None

    def s_at(self, u: np.ndarray) -> np.ndarray:
        return self.s0 + self.direction * (u - self.u0)

    @property
    def s1(self) -> float:
        return self.s0 + self.direction * (self.u1 - self.u0)


@dataclass
class LaneSet:
    """Lanes at each route sample, sorted by lambda (NaN padded to MAX_LANES)."""

    lam: np.ndarray  # (n, K) centre lambda
    half: np.ndarray  # (n, K) half width
    lane_id: np.ndarray  # (n, K) int, 0 where absent
    track: np.ndarray  # (n, K) int, -1 where absent
    remaining: np.ndarray  # (n, K) metres of usable lane ahead (inf = until the route or lap ends)


@dataclass
class Route:
    """Legs over the route coordinate u, samples every SAMPLE_M with their lanes and speed limits."""

    odr: OpenDriveMap
    nodes: list[Node]
    closed: bool
    legs: list[Leg]
    u: np.ndarray
    leg_index: np.ndarray
    same: LaneSet  # lanes carrying traffic in the travel direction
    oncoming: LaneSet  # lanes of the other direction on the same roads (traffic towards the ego)
    v_limit: np.ndarray  # comfortable speed limit from curvature (m/s)
    chain_length: float
    _leg_u0: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self._leg_u0 = np.array([leg.u0 for leg in self.legs])
        self._is_turn = np.array([leg.kind == "turn" for leg in self.legs], dtype=bool)

    @property
    def length(self) -> float:
        return self.legs[-1].u1

    def leg_of(self, u: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self._leg_u0, u, side="right") - 1, 0, len(self.legs) - 1)

    def index(self, u: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(np.asarray(u) / SAMPLE_M).astype(np.int64), 0, len(self.u) - 1)

    def world(self, u: np.ndarray, lam: np.ndarray, h: float | np.ndarray = 0.0) -> np.ndarray:
        """(N, 3) world points at route coordinates (u, lambda) and height h above the surface."""
        u = np.atleast_1d(np.asarray(u, dtype=np.float64))
        lam = np.broadcast_to(np.asarray(lam, dtype=np.float64), u.shape)
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), u.shape)
        out = np.empty((len(u), 3))
        li = self.leg_of(u)
        for k in np.unique(li):
            m = li == k
            leg = self.legs[k]
            if leg.kind == "turn":
                assert leg.turn is not None
                p = leg.turn.world(u[m] - leg.u0)
                p[:, 2] += h[m]
                out[m] = p
            else:
                road = self.odr.roads[leg.road]
                out[m] = road.to_world(leg.s_at(u[m]), leg.direction * (lam[m] - leg.c), h[m])
        return out

    def frames(self, u: np.ndarray, lam: np.ndarray, dlam_du: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 3) and rotations (N, 3, 3) [forward, left, up] of vehicles on the surface."""
        u = np.atleast_1d(np.asarray(u, dtype=np.float64))
        lam = np.broadcast_to(np.asarray(lam, dtype=np.float64), u.shape)
        eps = 0.5
        p = self.world(u, lam)
        pu = (self.world(u + eps, lam) - self.world(u - eps, lam)) / (2 * eps)
        pl = (self.world(u, lam + eps) - self.world(u, lam - eps)) / (2 * eps)
        turn = self._is_turn[self.leg_of(u)]
        up = np.cross(pu, pl)
        up[turn] = (0.0, 0.0, 1.0)
        up /= np.linalg.norm(up, axis=1, keepdims=True)
        fwd = pu + np.where(turn[:, None], 0.0, pl * np.asarray(dlam_du)[:, None])
        left = np.cross(up, fwd)
        left /= np.linalg.norm(left, axis=1, keepdims=True)
        fwd = np.cross(left, up)
        return p, np.stack([fwd, left, up], axis=2)

    def lane_at(self, u: float, lam: float) -> tuple[str, int]:
        """Road id and lane id under the point (u, lambda); lane 0 when between lanes or on a turn."""
        i = int(self.index(u))
        leg = self.legs[int(self.leg_index[i])]
        if leg.kind == "turn":
            return "", 0
        for ls in (self.same, self.oncoming):
            d = np.abs(ls.lam[i] - lam)
            k = int(np.nanargmin(d)) if np.isfinite(d).any() else -1
            if k >= 0 and d[k] <= ls.half[i, k] + 1e-6:
                return leg.road, int(ls.lane_id[i, k])
        return leg.road, 0


def build_route(odr: OpenDriveMap, nodes: list[Node], closed: bool, needed_m: float, where: str) -> Route:
    """Legs covering at least `needed_m` (laps as documented above), then samples and lanes."""
    graph_len = sum(odr.roads[r].length for r, _ in nodes)
    legs: list[Leg] = []
    u = 0.0
    lap = 0
    c = 0.0
    chain = list(nodes)
    while u < needed_m:
        if lap >= MAX_LAPS:
            raise InputError(where, f"--length-m {needed_m:.0f} needs more than {MAX_LAPS} passes over the "
                             f"{graph_len:.0f} m route")
        start_s: float | None = None
        if legs and legs[-1].kind == "turn":
            start_s = legs[-2].s1
        for k, (rid, d) in enumerate(chain):
            road = odr.roads[rid]
            s0 = (0.0 if d > 0 else road.length) if not (k == 0 and start_s is not None) else start_s
            s1 = road.length if d > 0 else 0.0
            if legs and legs[-1].kind == "road":
                c = legs[-1].c + _lateral_step(odr, legs[-1], road, s0, d)
            elif legs:
                c = 0.0
            wrong = not has_driving(road, lane_side(road, d))
            legs.append(Leg("road", u, u + abs(s1 - s0), lap, rid, d, s0, c, wrong))
            u += abs(s1 - s0)
            if u >= needed_m:
                break
        if u >= needed_m:
            break
        lap += 1
        if closed:
            continue
        turn = _make_turn(odr, legs, lap, where, graph_len)
        u = turn.u1
        legs.append(turn)
        chain = [(r, -d) for r, d in reversed(chain)]
    return _sample(odr, nodes, closed, legs, graph_len)


def _lateral_step(odr: OpenDriveMap, prev: Leg, road: Road, s0: float, d: int) -> float:
    """Offset that keeps lambda continuous from the end of `prev` into `road` at s0."""
    pr = odr.roads[prev.road]
    x0, y0, h0 = (a[0] for a in pr.reference(prev.s1))
    x1, y1, _ = (a[0] for a in road.reference(s0))
    nx, ny = -math.sin(h0) * prev.direction, math.cos(h0) * prev.direction
    return (x1 - x0) * nx + (y1 - y0) * ny


def _make_turn(odr: OpenDriveMap, legs: list[Leg], lap: int, where: str, graph_len: float) -> Leg:
    """Shorten the last road leg and append a U-turn from its rightmost to its leftmost lane."""
    last = legs[-1]
    road = odr.roads[last.road]
    probe = np.array([last.s1 - last.direction * min(20.0, 0.5 * abs(last.s1 - last.s0))])
    lanes = _lanes_at(road, probe, last.direction, last.c)
    lams = sorted(lam for lam, _, _ in lanes)
    if not lams:
        raise InputError(where, f"road {road.id}: no lane to turn around in")
    lam_r, lam_l = lams[0], lams[-1]
    sigma, xy = turn_shape(lam_l - lam_r)
    extent = float(xy[:, 0].max())
    need = extent + 10.0
    total_leg = abs(last.s1 - last.s0)
    if graph_len < 2 * need + 20.0 or total_leg < 1.0:
        raise InputError(where, f"the {graph_len:.0f} m route is too short to turn around and drive it again; "
                         f"use --length-m <= {graph_len:.0f}")
    cut = min(need, total_leg - 1.0)
    s_turn = last.s1 - last.direction * cut
    last.u1 -= cut
    p = road.to_world(s_turn, last.direction * (lam_r - last.c))[0]
    _, _, hdg = road.reference(s_turn)
    fwd = np.array([math.cos(hdg[0]), math.sin(hdg[0])]) * last.direction
    left = np.array([-fwd[1], fwd[0]])
    z_end = float(road.to_world(s_turn, last.direction * (lam_l - last.c))[0, 2])
    path = TurnPath(p, fwd, left, z_end, sigma, xy)
    return Leg("turn", last.u1, last.u1 + path.length, lap, road.id, last.direction, s_turn, 0.0, turn=path)


def _lanes_at(road: Road, s: np.ndarray, d: int, c: float) -> list[tuple[float, float, int]]:
    """(lambda, half width, lane id) of the driving lanes on both sides at one station."""
    ls = road.lane_sections[int(road.section_index(s)[0])]
    out = []
    for lid, lane in ls.lanes.items():
        if lid != 0 and lane.type in DRIVING:
            side = 1 if lid > 0 else -1
            t_in = road.border_t(s, lid - side)[0]
            t_out = road.border_t(s, lid)[0]
            out.append((d * 0.5 * (t_in + t_out) + c, 0.5 * abs(t_out - t_in), lid))
    return out


def _sample(odr: OpenDriveMap, nodes: list[Node], closed: bool, legs: list[Leg], chain_len: float) -> Route:
    total = legs[-1].u1
    n = int(math.floor(total / SAMPLE_M)) + 1
    u = np.arange(n) * SAMPLE_M
    leg_u0 = np.array([leg.u0 for leg in legs])
    leg_index = np.clip(np.searchsorted(leg_u0, u, side="right") - 1, 0, len(legs) - 1)
    same = _empty_lanes(n)
    onc = _empty_lanes(n)
    blocks: list[tuple[int, np.ndarray]] = []  # (leg, sample indices) of one lane section
    for k, leg in enumerate(legs):
        idx = np.flatnonzero(leg_index == k)
        if leg.kind == "turn" or len(idx) == 0:
            blocks.append((k, np.zeros(0, dtype=np.int64)))
            continue
        road = odr.roads[leg.road]
        s = np.clip(leg.s_at(u[idx]), 0.0, road.length)
        sec = road.section_index(s)
        for j in np.unique(sec):
            sub = idx[sec == j]
            ss = s[sec == j]
            ls = road.lane_sections[int(j)]
            side = lane_side(road, leg.direction) * (-1 if leg.wrong_way else 1)
            _fill(same, sub, road, ls, ss, side, leg)
            if not leg.wrong_way:
                _fill(onc, sub, road, ls, ss, -side, leg)
            blocks.append((k, sub))
    _link_tracks(same, blocks, legs)
    v_limit = _speed_limits(odr, legs, u, leg_index)
    return Route(odr, nodes, closed, legs, u, leg_index, same, onc, v_limit, chain_len)


def _empty_lanes(n: int) -> LaneSet:
    return LaneSet(
        np.full((n, MAX_LANES), np.nan), np.full((n, MAX_LANES), np.nan), np.zeros((n, MAX_LANES), dtype=np.int64),
        np.full((n, MAX_LANES), -1, dtype=np.int64), np.full((n, MAX_LANES), np.inf),
    )


def _fill(ls_out: LaneSet, idx: np.ndarray, road: Road, ls, s: np.ndarray, side: int, leg: Leg) -> None:
    ids = sorted((lid for lid, lane in ls.lanes.items() if lid * side > 0 and lane.type in DRIVING), key=abs)
    if not ids:
        return
    lam, half = [], []
    for lid in ids:
        t_in = road.border_t(s, lid - side)
        t_out = road.border_t(s, lid)
        lam.append(leg.direction * 0.5 * (t_in + t_out) + leg.c)
        half.append(0.5 * np.abs(t_out - t_in))
    lam_a = np.array(lam).T  # (m, L)
    order = np.argsort(np.nanmean(lam_a, axis=0), kind="stable")[:MAX_LANES]
    L = len(order)
    ls_out.lam[idx, :L] = lam_a[:, order]
    ls_out.half[idx, :L] = np.array(half).T[:, order]
    ls_out.lane_id[idx, :L] = np.array(ids)[order]


def _link_tracks(ls: LaneSet, blocks: list[tuple[int, np.ndarray]], legs: list[Leg]) -> None:
    """Give each lane a track id that follows it across sections and roads (by lateral continuity)."""
    next_id = 0
    prev: np.ndarray | None = None  # last sample index of the previous block
    for _k, idx in blocks:
        if len(idx) == 0:
            prev = None
            continue
        first, valid = idx[0], ~np.isnan(ls.lam[idx[0]])
        tracks = np.full(MAX_LANES, -1, dtype=np.int64)
        if prev is not None:
            pl, ph, pt = ls.lam[prev], ls.half[prev], ls.track[prev]
            for j in np.flatnonzero(valid):
                d = np.abs(pl - ls.lam[first, j])
                d[np.isnan(d)] = np.inf
                i = int(np.argmin(d))
                if d[i] < max(1.0, 0.5 * min(ph[i], ls.half[first, j])) and pt[i] >= 0 and pt[i] not in tracks:
                    tracks[j] = pt[i]
        for j in np.flatnonzero(valid):
            if tracks[j] < 0:
                tracks[j] = next_id
                next_id += 1
        ls.track[idx] = np.where(valid, tracks, -1)[None, :]
        prev = idx[-1]
    _remaining(ls, legs)


def _remaining(ls: LaneSet, legs: list[Leg]) -> None:
    """Usable length of each lane ahead: until it narrows below USABLE_WIDTH_M or ends."""
    n = len(ls.track)
    rows, cols = np.nonzero(ls.track >= 0)
    if len(rows) == 0:
        return
    tid = ls.track[rows, cols]
    order = np.lexsort((rows, tid))
    rows, cols, tid = rows[order], cols[order], tid[order]
    usable = 2 * ls.half[rows, cols] >= USABLE_WIDTH_M
    u = rows * SAMPLE_M
    cuts = np.flatnonzero(np.diff(tid)) + 1
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(tid)], strict=True):
        last = rows[b - 1]
        open_end = last + 1 >= n or not (ls.track[last + 1] >= 0).any()
        end_u = np.inf if open_end else u[b - 1] + SAMPLE_M
        stop = np.where(usable[a:b], np.inf, u[a:b])
        stop = np.minimum.accumulate(stop[::-1])[::-1]
        ls.remaining[rows[a:b], cols[a:b]] = np.minimum(stop, end_u) - u[a:b]


def _speed_limits(odr: OpenDriveMap, legs: list[Leg], u: np.ndarray, leg_index: np.ndarray) -> np.ndarray:
    """Curve speed for 1.8 m/s^2 lateral acceleration, braking at 1.2 m/s^2 before curves and turns."""
    heading = np.zeros(len(u))
    turn = np.zeros(len(u), dtype=bool)
    for k, leg in enumerate(legs):
        m = leg_index == k
        if leg.kind == "turn":
            turn[m] = True
            continue
        _, _, h = odr.roads[leg.road].reference(leg.s_at(u[m]))
        heading[m] = h + (math.pi if leg.direction < 0 else 0.0)
    kappa = np.abs(np.gradient(np.unwrap(heading), SAMPLE_M)) if len(u) > 1 else np.zeros(len(u))
    kappa = np.convolve(kappa, np.ones(9) / 9, mode="same")
    v = np.sqrt(1.8 / np.maximum(kappa, 1e-6))
    v = np.minimum(v, 45.0)
    v[turn] = 4.5
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * 1.2 * SAMPLE_M))
    return v
