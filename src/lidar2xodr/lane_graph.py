"""Lane-graph agreement: does the generated map route a vehicle along the reference's lanes?

`compare`'s distances and lane count cannot see a lane graph that is wrong where its geometry is
right: a 0.54 m sliver lane between two through lanes to which the right lane links, so that a
simulator routes the car into the sliver (issue #13). This measure follows the links.

Rule (the evaluation docstring and the README quote it):
1. Nodes are the driving lanes (`evaluation.DRIVING_TYPES`) of each lane section of each road; a
   node's travel successors are the nodes its travel end is linked to in the SAME map: lane links
   between the sections of a road, lane links across road links (contact points honoured), and the
   laneLinks of junction connections. Travel direction is OpenDRIVE's: right lanes along s under
   rule="RHT", left lanes against it (the other way round under "LHT").
2. Every reference driving lane's centre line (the midpoint of its two borders) is sampled every
   `lane_graph_step_m` and followed in travel direction, lane section after lane section, through
   the reference's own links: a lane piece starts with the route state its reference predecessors
   ended with. Samples where the reference lane is narrower than `lane_graph_min_width_m` (its own
   tapers) are followed but not evaluated.
3. The generated lanes that hold a sample: driving lanes whose polygon (one quadrilateral per lane
   between consecutive generated stations, same step) encloses it, travelling within
   `heading_tolerance_deg` of the reference lane (found exactly: KD-trees of polygon centres,
   grouped by polygon size). A holding lane is full where it is at least `lane_graph_min_width_m`
   wide, or narrower within `lane_graph_taper_m` of its lane's first or last end (distance along
   the generated lane chain through its links).
4. The route is the set of generated lanes the vehicle may be in. A sample AGREES when one of its
   holding lanes is on the route or a linked successor of it (successors through sections shorter
   than two steps are followed on), and that lane is full; the route becomes those lanes. With no
   route yet (a reference lane's start) every holding lane starts it; a reference lane starts at
   its first evaluated sample (one that opens from zero width: before it, along its opening taper,
   a sliver whose samples fall into either generated neighbour by centimetres, the holding lanes
   only seed the route and nothing breaks). When no holding lane is on the
   route or a successor, that is a BREAK: the generated links take the vehicle elsewhere (a lane
   routed into a sliver or an exit, a missing link). Length counts as wrong from there until a
   holding lane is one the generated links can reach from the route (e.g. the sliver's end
   rejoining the through lane); only then is the next break counted (a break where the reference
   is not evaluated is counted at the first evaluated sample it makes wrong). A sample no generated lane
   holds is wrong (a gap, a missing lane, a lane beside the reference one) and restarts the route
   after it: links cannot be judged across a gap the map does not model.
5. Coverage: only samples inside the reference stretch `compare` evaluates (per reference road and
   side, between its first and last sample near the generated map: compare rule 6) count, so a
   drive of part of a network is not penalised for the rest; inside it every sample counts.
   `agreement` = agreeing length / evaluated reference lane length (0 when none is evaluated),
   `wrong_m` the rest (split into `unheld_m`, `narrow_m`, `off_route_m`), `breaks` the break count,
   `breaks_at` the first breaks' positions.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from lidar2xodr.angles import wrap_angle
from lidar2xodr.config import EvaluationConfig

NodeKey = tuple[str, int, int]  # road id, lane section index, lane id
_MAX_CANDIDATES = 8
_BORDER_EPS_M = 1e-6
"""A point this close to a lane polygon's edge is inside it (numerical ties on shared borders)."""
_MIN_CELL_AREA_M2 = 1e-6
"""Polygons of zero-width lanes hold nothing."""
_MAX_BREAKS_LISTED = 20
_GHOST_WIDTH_M = 0.01
"""Narrower everywhere in its section: a zero-width placeholder lane, not a lane (chain_distances)."""
_CHUNK = 20_000


def travels_along_s(lane_id: int, rule: str) -> bool:
    """OpenDRIVE's travel direction: right lanes along s under RHT, left lanes under LHT."""
    return (lane_id < 0) == (str(rule).upper() != "LHT")


@dataclass
class LaneGraph:
    """The driving lanes of one map as nodes and their travel successors (rule 1)."""

    keys: list[NodeKey]
    index: dict[NodeKey, int]
    succ: list[frozenset[int]]
    pred: list[frozenset[int]]
    length: np.ndarray  # (n,) lane section length
    max_width: np.ndarray  # (n,) widest along the section (NaN-free; border-defined lanes read as wide)
    section: np.ndarray  # (n,) id of the node's (road, lane section)
    _reach: dict[int, frozenset[int]] = field(default_factory=dict, repr=False)
    _closure: dict[frozenset[int], frozenset[int]] = field(default_factory=dict, repr=False)

    def reach(self, node: int, short_m: float) -> frozenset[int]:
        """Successors, and theirs through successors shorter than short_m (sections a step skips)."""
        hit = self._reach.get(node)
        if hit is None:
            out: set[int] = set()
            todo = [(s, 0) for s in self.succ[node]]
            while todo:
                n, depth = todo.pop()
                if n in out:
                    continue
                out.add(n)
                if self.length[n] < short_m and depth < 3:
                    todo.extend((s, depth + 1) for s in self.succ[n])
            hit = self._reach[node] = frozenset(out)
        return hit

    def closure(self, lanes: frozenset[int]) -> frozenset[int]:
        """Every lane reachable from `lanes` through successors, `lanes` included."""
        hit = self._closure.get(lanes)
        if hit is None:
            out, todo = set(lanes), list(lanes)
            while todo:
                for s in self.succ[todo.pop()]:
                    if s not in out:
                        out.add(s)
                        todo.append(s)
            hit = self._closure[lanes] = frozenset(out)
        return hit

    def chain_distances(self, cap: float) -> tuple[np.ndarray, np.ndarray]:
        """Distance from each node's travel start back to its lane chain's first end, and from its
        travel end on to the chain's last end, capped at `cap` (cycles without an end read as cap).
        A lane kept at zero width over a whole section (an exporter's placeholder before a lane
        opens) is no part of the chain: the lane opening after it starts there."""
        n = len(self.keys)
        ghost = self.max_width < _GHOST_WIDTH_M
        out = []
        for all_links in (self.pred, self.succ):
            links = [[a for a in x if not ghost[a]] for x in all_links]
            src = np.array([a for b in range(n) for a in links[b]], dtype=int)
            dst = np.array([b for b in range(n) for _ in links[b]], dtype=int)
            d = np.where(np.array([len(x) == 0 for x in links], bool), 0.0, cap)
            for _ in range(n + 1):
                new = d.copy()
                if len(src):
                    np.minimum.at(new, dst, np.minimum(d[src] + self.length[src], cap))
                if np.array_equal(new, d):
                    break
                d = new
            out.append(d)
        return out[0], out[1]


def build_lane_graph(odr: Any, driving: frozenset[str]) -> LaneGraph:
    """Nodes and travel successors of every driving lane of a map (rule 1)."""
    keys: list[NodeKey] = []
    lengths: list[float] = []
    widths: list[float] = []
    along: list[bool] = []
    for rid, road in odr.roads.items():
        for k, ls in enumerate(road.lane_sections):
            for lid in ls.lane_ids():
                if lid != 0 and ls.lanes[lid].type.lower() in driving:
                    keys.append((rid, k, lid))
                    lengths.append(ls.s_end - ls.s)
                    w = ls.lanes[lid].width(np.linspace(0.0, ls.s_end - ls.s, 21))
                    widths.append(math.inf if np.isnan(w).any() else float(np.max(np.abs(w))))
                    along.append(travels_along_s(lid, road.rule))
    index = {key: i for i, key in enumerate(keys)}
    sec_ids: dict[tuple[str, int], int] = {}
    section = np.array([sec_ids.setdefault(key[:2], len(sec_ids)) for key in keys], dtype=int)
    ports: dict[tuple[int, int], set[tuple[int, int]]] = {}

    def connect(a: NodeKey, a_port: int, b: NodeKey, b_port: int) -> None:
        ia, ib = index.get(a), index.get(b)
        if ia is not None and ib is not None:
            ports.setdefault((ia, a_port), set()).add((ib, b_port))
            ports.setdefault((ib, b_port), set()).add((ia, a_port))

    def end_of(road: Any, contact: str) -> tuple[int, int]:
        return (0, 0) if contact == "start" else (len(road.lane_sections) - 1, 1)

    for rid, road in odr.roads.items():
        secs = road.lane_sections
        for k in range(len(secs) - 1):
            for lid, lane in secs[k].lanes.items():
                if lane.successor is not None:
                    connect((rid, k, lid), 1, (rid, k + 1, lane.successor), 0)
            for lid, lane in secs[k + 1].lanes.items():
                if lane.predecessor is not None:
                    connect((rid, k, lane.predecessor), 1, (rid, k + 1, lid), 0)
        for link, port, attr in ((road.successor, 1, "successor"), (road.predecessor, 0, "predecessor")):
            if link is None or link.element_type != "road" or link.element_id not in odr.roads:
                continue
            other = odr.roads[link.element_id]
            o_sec, o_port = end_of(other, link.contact_point or ("start" if port == 1 else "end"))
            k = len(secs) - 1 if port == 1 else 0
            for lid, lane in secs[k].lanes.items():
                target = getattr(lane, attr)
                if target is not None:
                    connect((rid, k, lid), port, (link.element_id, o_sec, target), o_port)
    for jid, junction in odr.junctions.items():
        for conn in junction.connections:
            inc, con = odr.roads.get(conn.incoming_road), odr.roads.get(conn.connecting_road)
            if inc is None or con is None:
                continue
            c_sec, c_port = end_of(con, conn.contact_point or "start")
            i_port = _incoming_end(inc, con, c_port, jid)
            i_sec = len(inc.lane_sections) - 1 if i_port == 1 else 0
            for f, t in conn.lane_links:
                connect((inc.id, i_sec, f), i_port, (con.id, c_sec, t), c_port)

    n = len(keys)
    succ_sets: list[set[int]] = [set() for _ in range(n)]
    pred_sets: list[set[int]] = [set() for _ in range(n)]
    for i in range(n):
        exit_port = 1 if along[i] else 0
        for j, j_port in ports.get((i, exit_port), ()):
            if j_port == (0 if along[j] else 1) and j != i:
                succ_sets[i].add(j)
                pred_sets[j].add(i)
    return LaneGraph(keys, index, [frozenset(s) for s in succ_sets], [frozenset(p) for p in pred_sets],
                     np.asarray(lengths, float), np.asarray(widths, float), section)


def _incoming_end(inc: Any, con: Any, c_port: int, jid: str) -> int:
    """Which end (0 start, 1 end) of a junction's incoming road meets the connecting road."""
    ends = [p for p, link in ((1, inc.successor), (0, inc.predecessor))
            if link is not None and link.element_type == "junction" and link.element_id == jid]
    if len(ends) == 1:
        return ends[0]
    c_s = 0.0 if c_port == 0 else con.length
    cx, cy, _ = con.reference(c_s)
    best, best_d = 1, math.inf
    for port in ends or [1, 0]:
        x, y, _ = inc.reference(0.0 if port == 0 else inc.length)
        d = math.hypot(float(x[0] - cx[0]), float(y[0] - cy[0]))
        if d < best_d:
            best, best_d = port, d
    return best


@dataclass
class _Cells:
    """Lane polygons of the generated map: one quadrilateral per lane between consecutive stations."""

    corners: np.ndarray  # (c, 4, 2)
    centre: np.ndarray  # (c, 2)
    radius: np.ndarray  # (c,) farthest corner from the centre
    node: np.ndarray  # (c,)
    hdg: np.ndarray  # (c,) travel heading
    full: np.ndarray  # (c,) bool: wide enough or a taper at both stations (rule 3)


def _cells(sections: list[Any], odr: Any, graph: LaneGraph, cfg: EvaluationConfig,
           transform: Callable | None) -> _Cells:
    start_d, end_d = graph.chain_distances(cfg.lane_graph_taper_m + 1.0)
    parts: list[tuple[np.ndarray, ...]] = []
    for sec in sections:
        if len(sec.s) < 2:
            continue
        rule = odr.roads[sec.road_id].rule
        border_xy = {lid: sec.border_xyz[lid][:, :2] for lid in sec.lane_ids}
        hdg = sec.hdg
        if transform is not None:
            border_xy, hdg = transform(border_xy, sec.xyz[:, :2], hdg)
        for lid in sec.lane_ids:
            node = graph.index.get((sec.road_id, sec.section, lid))
            if node is None:
                continue
            side = 1 if lid > 0 else -1
            inner, outer = border_xy[lid - side], border_xy[lid]
            width = np.abs(sec.border_t[lid] - sec.border_t[lid - side])
            along = travels_along_s(lid, rule)
            s_in = sec.s - sec.s[0] if along else sec.s[-1] - sec.s
            s_out = graph.length[node] - s_in
            full = ((width >= cfg.lane_graph_min_width_m) | (start_d[node] + s_in <= cfg.lane_graph_taper_m)
                    | (end_d[node] + s_out <= cfg.lane_graph_taper_m))
            corners = np.stack([inner[:-1], inner[1:], outer[1:], outer[:-1]], axis=1)
            travel = hdg[:-1] if along else wrap_angle(hdg[:-1] + np.pi)
            parts.append((corners, np.full(len(corners), node), travel, full[:-1] & full[1:]))
    if not parts:
        return _Cells(np.zeros((0, 4, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, int), np.zeros(0),
                      np.zeros(0, bool))
    corners, node, hdg, full = (np.concatenate(c) for c in zip(*parts, strict=True))
    x, y = corners[..., 0], corners[..., 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))
    keep = area > _MIN_CELL_AREA_M2  # shoelace area of the quadrilateral
    corners, node, hdg, full = corners[keep], node[keep], hdg[keep], full[keep]
    centre = corners.mean(axis=1)
    radius = np.max(np.hypot(*(corners - centre[:, None, :]).transpose(2, 0, 1)), axis=1)
    return _Cells(corners, centre, radius, node.astype(int), hdg, full.astype(bool))


def _inside(corners: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Whether q (n, 2) lies in the lane quadrilaterals corners (n, k, 4, 2) (inner_i, inner_i+1,
    outer_i+1, outer_i), borders included. Tested as two triangles, so a quadrilateral folded by
    a turn tighter than its lane's offset (a town junction's corner) still holds its own centre."""
    hit = np.zeros(corners.shape[:2], bool)
    for tri in ((0, 1, 2), (0, 2, 3)):
        pts = corners[:, :, tri, :]
        edge = np.roll(pts, -1, axis=2) - pts
        rel = q[:, None, None, :] - pts
        cross = (edge[..., 0] * rel[..., 1] - edge[..., 1] * rel[..., 0]) / np.maximum(
            np.hypot(edge[..., 0], edge[..., 1]), 1e-12)
        hit |= np.all(cross >= -_BORDER_EPS_M, axis=2) | np.all(cross <= _BORDER_EPS_M, axis=2)
    return hit


def holding_lanes(cells: _Cells, q: np.ndarray, q_hdg: np.ndarray, tol_rad: float) -> np.ndarray:
    """Generated lanes that hold each query point (rule 3): (n, _MAX_CANDIDATES) codes node*2 + full,
    -1 padded, unique nodes in descending code order.

    Exact, not a nearest-k guess: cells are grouped by size (radius up to 2^j m); within a group the
    k nearest cell centres are tried, and k grows for the points whose k-th centre is still closer
    than the group's largest radius (a holding cell lies within its radius of the point).
    """
    out = np.full((len(q), _MAX_CANDIDATES), -1, dtype=np.int64)
    if not len(cells.node) or not len(q):
        return out
    size = np.ceil(np.log2(np.maximum(cells.radius, 1.0))).astype(int)
    for j in np.unique(size):
        sub = np.flatnonzero(size == j)
        tree, r_max = cKDTree(cells.centre[sub]), float(cells.radius[sub].max())
        todo, k = np.arange(len(q)), 16
        while len(todo):
            k = min(k, len(sub))
            unsure = np.zeros(len(todo), bool)
            step = max(1, _CHUNK // k)
            for a in range(0, len(todo), step):
                rows = todo[a:a + step]
                dist, idx = tree.query(q[rows], k=k)
                dist, idx = np.asarray(dist).reshape(len(rows), k), sub[np.asarray(idx).reshape(len(rows), k)]
                hit = (_inside(cells.corners[idx], q[rows])
                       & (np.abs(wrap_angle(cells.hdg[idx] - q_hdg[rows, None])) <= tol_rad))
                code = np.where(hit, cells.node[idx] * 2 + cells.full[idx], -1)
                out[rows] = _unique_codes(np.concatenate([out[rows], code], axis=1), _MAX_CANDIDATES)
                unsure[a:a + step] = dist[:, -1] <= r_max
            if k == len(sub):
                break
            todo, k = todo[unsure], 4 * k
    return out


def _unique_codes(code: np.ndarray, width: int) -> np.ndarray:
    """Per row: unique nodes (a full code wins over a narrow one), descending, -1 padded to `width`."""
    code = -np.sort(-code, axis=1)
    dup = np.zeros_like(code, dtype=bool)
    dup[:, 1:] = (code[:, 1:] // 2 == code[:, :-1] // 2) & (code[:, 1:] >= 0)
    code = -np.sort(-np.where(dup, -1, code), axis=1)
    out = np.full((len(code), width), -1, dtype=np.int64)
    m = min(width, code.shape[1])
    out[:, :m] = code[:, :m]
    return out


@dataclass
class _Piece:
    """One reference lane of one lane section, sampled in travel direction."""

    node: int
    first: int  # index range into the flattened samples
    stop: int


def _reference_samples(sections: list[Any], odr: Any, graph: LaneGraph) -> tuple[dict[str, np.ndarray], list[_Piece]]:
    xy, hdg, w, width, s, side, road = [], [], [], [], [], [], []
    pieces: list[_Piece] = []
    base = 0
    for sec in sections:
        rule = odr.roads[sec.road_id].rule
        for lid in sec.lane_ids:
            node = graph.index.get((sec.road_id, sec.section, lid))
            if node is None:
                continue
            sgn = 1 if lid > 0 else -1
            centre = 0.5 * (sec.border_xyz[lid][:, :2] + sec.border_xyz[lid - sgn][:, :2])
            lw = np.abs(sec.border_t[lid] - sec.border_t[lid - sgn])
            h, ss = sec.hdg, sec.s
            if not travels_along_s(lid, rule):
                centre, lw, h, ss = centre[::-1], lw[::-1], wrap_angle(h[::-1] + np.pi), ss[::-1]
            seg = np.hypot(*np.diff(centre, axis=0).T) if len(centre) > 1 else np.zeros(0)
            xy.append(centre)
            hdg.append(h)
            w.append(0.5 * (np.concatenate([[0.0], seg]) + np.concatenate([seg, [0.0]])))
            width.append(lw)
            s.append(ss)
            side.append(np.full(len(ss), sgn))
            road.append(np.full(len(ss), sec.road_id, dtype=object))
            pieces.append(_Piece(node, base, base + len(ss)))
            base += len(ss)

    def cat(parts: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
        return np.concatenate(parts) if parts else np.zeros(shape)

    return ({"xy": cat(xy, (0, 2)), "hdg": cat(hdg, (0,)), "weight": cat(w, (0,)), "width": cat(width, (0,)),
             "s": cat(s, (0,)), "side": cat(side, (0,)).astype(int), "road": cat(road, (0,))}, pieces)


@dataclass
class _Route:
    lanes: frozenset[int] = frozenset()
    on: bool = True
    counted: bool = True  # off the route: its break was counted (it is counted at the first evaluated sample)
    started: bool = False  # an evaluated sample was met: before it the route is only seeded (rule 4)


@dataclass
class _Tally:
    agree: float = 0.0
    unheld: float = 0.0
    narrow: float = 0.0
    off_route: float = 0.0
    breaks: int = 0
    breaks_at: list[dict[str, Any]] = field(default_factory=list)


def _follow(piece: _Piece, route: _Route, codes: np.ndarray, evaluated: np.ndarray, samples: dict[str, np.ndarray],
            graph: LaneGraph, short_m: float, tally: _Tally, ref_key: Any) -> _Route:
    """Walk one reference lane piece (rule 4), grouping consecutive samples with the same holding lanes."""
    rows = codes[piece.first:piece.stop]
    ev = evaluated[piece.first:piece.stop]
    change = np.ones(len(rows), bool)
    change[1:] = np.any(rows[1:] != rows[:-1], axis=1) | (ev[1:] != ev[:-1])
    starts = np.flatnonzero(change)
    ends = np.append(starts[1:], len(rows))
    weight = samples["weight"][piece.first:piece.stop]
    lanes, on, counted, started = route.lanes, route.on, route.counted, route.started
    for a, b in zip(starts, ends, strict=True):
        row = rows[a]
        w = float(weight[a:b].sum()) if ev[a] else 0.0
        held = frozenset(int(c) // 2 for c in row if c >= 0)
        full = frozenset(int(c) // 2 for c in row if c >= 0 and c % 2)
        started = started or bool(ev[a])
        if not started:
            lanes, on, counted = held, True, True
            continue
        if not held:
            tally.unheld += w
            lanes, on = frozenset(), True
            continue
        if on:
            nxt = set(lanes)
            for n in lanes:
                nxt |= graph.reach(n, short_m)
        else:
            nxt = graph.closure(lanes)
        hit = held & nxt
        if hit or not lanes:
            hit = hit or held
            on = True
            lanes = (hit & full) or hit
            if hit & full:
                tally.agree += w
            else:
                tally.narrow += w
            continue
        if on:
            on, counted = False, False
        if ev[a] and not counted:
            counted = True
            tally.breaks += 1
            if len(tally.breaks_at) < _MAX_BREAKS_LISTED:
                x, y = samples["xy"][piece.first + a]
                tally.breaks_at.append({"x": round(float(x), 2), "y": round(float(y), 2),
                                        "reference_road": ref_key[0], "reference_lane": ref_key[2]})
        tally.off_route += w
    return _Route(lanes, on, counted, started)


def lane_graph_agreement(gen_map: Any, ref_map: Any, cfg: EvaluationConfig, driving: frozenset[str],
                         covered: dict[tuple[str, int], tuple[float, float]],
                         transform: Callable | None = None) -> dict[str, Any]:
    """`lane_graph.*` of compare (rules in the module docstring). `covered` maps a reference (road id,
    side) to the s range compare evaluates there (compare rule 6)."""
    step = cfg.lane_graph_step_m
    gen_graph, ref_graph = build_lane_graph(gen_map, driving), build_lane_graph(ref_map, driving)
    cells = _cells(gen_map.sample(step), gen_map, gen_graph, cfg, transform)
    samples, pieces = _reference_samples(ref_map.sample(step), ref_map, ref_graph)
    codes = holding_lanes(cells, samples["xy"], samples["hdg"], math.radians(cfg.heading_tolerance_deg))
    lo = np.array([covered.get((r, sd), (math.inf, -math.inf))[0] for r, sd in zip(samples["road"], samples["side"],
                                                                                     strict=True)])
    hi = np.array([covered.get((r, sd), (math.inf, -math.inf))[1] for r, sd in zip(samples["road"], samples["side"],
                                                                                     strict=True)])
    eps = 1e-6
    evaluated = ((samples["s"] >= lo - eps) & (samples["s"] <= hi + eps)
                 & (samples["width"] >= cfg.lane_graph_min_width_m))
    tally = _Tally()
    piece_of = {p.node: i for i, p in enumerate(pieces)}
    final: dict[int, _Route] = {}
    order = sorted(range(len(pieces)), key=lambda i: ref_graph.keys[pieces[i].node])
    sources = [i for i in order if not ref_graph.pred[pieces[i].node]]
    queue = list(reversed(sources))
    remaining = list(reversed(order))
    while queue or remaining:
        if not queue:
            i = remaining.pop()
            if pieces[i].node in final:
                continue
            queue.append(i)
        p = pieces[queue.pop()]
        if p.node in final:
            continue
        before = [final[n] for n in sorted(ref_graph.pred[p.node]) if n in final]
        on = any(r.on for r in before) or not before
        start = _Route(frozenset().union(*(r.lanes for r in before)), on, on or any(r.counted for r in before),
                       any(r.started for r in before))
        final[p.node] = _follow(p, start, codes, evaluated, samples, gen_graph, 2.0 * step, tally,
                                ref_graph.keys[p.node])
        queue.extend(piece_of[n] for n in sorted(ref_graph.succ[p.node], reverse=True)
                     if n in piece_of and n not in final)
    total = float(np.sum(samples["weight"][evaluated]))
    return {
        "agreement": tally.agree / total if total > 0 else 0.0,
        "breaks": tally.breaks,
        "wrong_m": max(total - tally.agree, 0.0),
        "eval_length_m": total,
        "unheld_m": tally.unheld,
        "narrow_m": tally.narrow,
        "off_route_m": tally.off_route,
        "breaks_at": tally.breaks_at,
    }
