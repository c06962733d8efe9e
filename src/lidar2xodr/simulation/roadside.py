"""Roadside scenery beyond the verges: terrain, vegetation, signs and noise barriers.

A real motorway is lined with things a LiDAR sees along the road. Guard rails and the road surface
alone have no structure along it, so LiDAR odometry on a drive without them finds no forward
motion (issue 4). Everything here is seeded per road on its own stream, so the road surface,
paint, rails and structures keep their random draws.

Decisions (roads outside junctions longer than 100 m, like the rails; each side of the road):
- Terrain from the verge's end (8 m beyond the carriageway edge, 0.7 m below the road) out to 48 m:
  grass on a grid of 2 m along the road and 2-12 m across. Its height follows a random profile
  along the road (knots every 50 m: level, a cutting up to 4 m high or an embankment down to 3 m),
  reached 12 m out, plus 0.2 m (sigma) roughness per vertex. Where another road's pavement is
  nearer than 60 m it flattens (ramps and parallel carriageways stay in sight); within 4 m of it
  there is none. On the inside of a curve it stops at 60 % of the edge's radius (no folds).
- Vegetation in 50 m stretches drawn as open field (30 %), scattered (45 %) or a wood's edge
  (25 %): bushes (0.5-2 m, irregular 80-triangle blobs) and trees (trunk 1.5-4 m, round or
  slender crown, up to ~15 m), foliage 35 % reflective like the grass. None within 8 m of another road's pavement.
- Signs: every 300-900 m on each side with traffic, a post 2.5 m beyond the edge with a
  1-2.5 m retro-reflective plate facing that side's traffic.
- Noise barriers: per km and side a 20 % chance of a 150-400 m wall, 3-5 m high, 3 m beyond the
  edge, on steel H-posts every 4 m that stand 0.2 m proud of it on the road side.
Not modelled: lamp posts (German motorways are lit only at junctions), fences, buildings.
"""

from __future__ import annotations

import math

import numpy as np

from lidar2xodr.opendrive import Road
from lidar2xodr.simulation import reflectivity as R
from lidar2xodr.simulation.route import PAVED, lane_side
from lidar2xodr.simulation.scene import _Clearance, _edges, _posts, _Soup, _stations

TERRAIN_D = np.array([8.0, 10.0, 13.0, 17.0, 22.0, 28.0, 36.0, 48.0])
"""Terrain columns, metres beyond the carriageway edge (the first is the verge's outer end)."""
VERGE_H = -0.7
RAMP_M = 12.0
KNOT_M = 50.0
ROUGH_M = 0.2
FLAT_NEAR_M, FLAT_FAR_M = 20.0, 60.0
TERRAIN_GAP_M = 4.0
PLANT_GAP_M = 8.0
STRETCH_M = 50.0
# per stretch kind (open, scattered, wood): probability, mean bushes, mean trees, nearest tree (m)
_STRETCH_P = np.array([0.3, 0.45, 0.25])
_BUSHES = np.array([1.0, 6.0, 4.0])
_TREES = np.array([0.3, 3.0, 12.0])
_TREE_NEAR = np.array([10.0, 10.0, 14.0])


def add_roadside(soup: _Soup, road: Road, clear: _Clearance, rng: np.random.Generator) -> None:
    """Terrain, vegetation, signs and noise barriers along both sides of one road."""
    knots = np.arange(0.0, road.length + KNOT_M, KNOT_M)
    rises = {side: _rise_profile(len(knots), rng) for side in (1, -1)}
    barriers = {side: _barrier_spans(road.length, rng) for side in (1, -1)}
    for ls in road.lane_sections:
        if ls.s_end - ls.s < 4.0:
            continue
        s = _stations(ls.s, ls.s_end, 2.0)
        left, right = _edges(road, ls, s)
        for edge, side in ((left, 1), (right, -1)):
            reach = _reach(road, s, edge, side)
            ground = _Ground(road, ls, side, knots, rises[side], clear)
            if reach >= TERRAIN_D[2]:
                _terrain(soup, road, s, edge, side, reach, ground, rng)
            _vegetation(soup, road, ls.s, ls.s_end, side, reach, ground, clear, rng)
            for a, b in barriers[side]:
                lo, hi = max(a, ls.s), min(b, ls.s_end)
                if hi - lo > 4.0:
                    _barrier(soup, road, ls, side, lo, hi, clear, rng)
    _signs(soup, road, rng)


def _rise_profile(n: int, rng: np.random.Generator) -> np.ndarray:
    """Terrain height at each knot, 12 m beyond the verge: level, cutting or embankment."""
    kind = rng.choice(3, size=n, p=[0.4, 0.35, 0.25])
    level = rng.normal(0.0, 0.3, n)
    cut = rng.uniform(1.0, 4.0, n)
    bank = rng.uniform(-3.0, -0.5, n)
    return np.choose(kind, [level, cut, bank])


def _barrier_spans(length: float, rng: np.random.Generator) -> list[tuple[float, float]]:
    spans = []
    for k in range(int(math.ceil(length / 1000.0))):
        hit, start, size = rng.random() < 0.2, rng.uniform(0.0, 1000.0), rng.uniform(150.0, 400.0)
        if hit:
            a = k * 1000.0 + start
            spans.append((a, min(a + size, length)))
    return spans


def _reach(road: Road, s: np.ndarray, edge: np.ndarray, side: int) -> float:
    """How far beyond the edge the roadside may reach before it folds over on the inside of a curve."""
    _, _, hdg = road.reference(s)
    curv = np.gradient(np.unwrap(hdg), s)
    inner = curv * side > 1e-6
    if not inner.any():
        return float(TERRAIN_D[-1])
    radius = 1.0 / np.abs(curv[inner]) - np.abs(edge[inner])
    return float(min(TERRAIN_D[-1], 0.6 * radius.min()))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


class _Ground:
    """Smooth terrain height (no roughness) of one side of a lane section: where plants stand."""

    def __init__(self, road: Road, ls, side: int, knots: np.ndarray, rise: np.ndarray, clear: _Clearance) -> None:
        self.road, self.ls, self.side = road, ls, side
        self.knots, self.rise, self.clear = knots, rise, clear

    def edge(self, s: np.ndarray) -> np.ndarray:
        left, right = _edges(self.road, self.ls, s)
        return left if self.side > 0 else right

    def at(self, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (x, y, z) at `d` beyond the edge, and the distance to another road's pavement."""
        edge = self.edge(s)
        xy = self.road.to_world(s, edge + self.side * d)[:, :2]
        base = self.road.to_world(s, edge + self.side * TERRAIN_D[0], VERGE_H)[:, 2]
        other = self.clear.distance(xy, self.road.id, FLAT_FAR_M)
        flat = np.clip((other - FLAT_NEAR_M) / (FLAT_FAR_M - FLAT_NEAR_M), 0.0, 1.0)
        ramp = _smoothstep((d - TERRAIN_D[0]) / RAMP_M)
        z = base + np.interp(s, self.knots, self.rise) * ramp * flat
        return np.column_stack([xy, z]), other


def _terrain(soup: _Soup, road: Road, s: np.ndarray, edge: np.ndarray, side: int, reach: float, ground: _Ground,
             rng: np.random.Generator) -> None:
    d = TERRAIN_D[TERRAIN_D <= reach]
    ss, dd = np.repeat(s, len(d)), np.tile(d, len(s))
    pts, other = ground.at(ss, dd)
    rough = rng.normal(0.0, ROUGH_M, len(ss)) * (dd > TERRAIN_D[0])
    pts[:, 2] += rough
    grid = pts.reshape(len(s), len(d), 3).transpose(1, 0, 2)
    ok = (other >= TERRAIN_GAP_M).reshape(len(s), len(d)).T
    keep = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]
    inner, outer = grid[:-1], grid[1:]
    pair = (outer, inner) if side > 0 else (inner, outer)
    soup.strip(*pair, R.GRASS, R.draw_base(R.GRASS, 1, rng)[0], keep=keep)


_ICO: tuple[np.ndarray, np.ndarray] | None = None


def icosphere() -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere of 42 vertices and 80 triangles (an icosahedron subdivided once)."""
    global _ICO
    if _ICO is None:
        g = (1.0 + math.sqrt(5.0)) / 2.0
        v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g], [0, -1, -g],
                      [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], dtype=np.float64)
        f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                      [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                      [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = len(v) + inv.reshape(3, -1).T  # midpoint vertex of edges (01, 12, 20) of each face
        v = np.concatenate([v, 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])])
        a, b, c = f.T
        ab, bc, ca = mid.T
        f = np.concatenate([np.column_stack(t) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
        _ICO = (v / np.linalg.norm(v, axis=1, keepdims=True), f)
    return _ICO


def _blobs(soup: _Soup, centre: np.ndarray, radii: np.ndarray, material: int, rng: np.random.Generator) -> None:
    """Irregular closed blobs (bushes, crowns): an icosphere with every vertex pushed in or out."""
    if len(centre) == 0:
        return
    v, f = icosphere()
    bump = rng.uniform(0.7, 1.25, (len(centre), len(v), 1))
    verts = centre[:, None, :] + v[None] * radii[:, None, :] * bump
    soup.add(verts[:, f], material, R.draw_base(material, len(centre), rng).repeat(len(f)))


def _vegetation(soup: _Soup, road: Road, s0: float, s1: float, side: int, reach: float, ground: _Ground,
                clear: _Clearance, rng: np.random.Generator) -> None:
    starts = np.arange(s0, s1, STRETCH_M)
    kind = rng.choice(3, size=len(starts), p=_STRETCH_P)
    n_bush = rng.poisson(_BUSHES[kind])
    n_tree = rng.poisson(_TREES[kind])
    bush_s = np.repeat(starts, n_bush) + rng.uniform(0.0, STRETCH_M, n_bush.sum())
    bush_d = rng.uniform(TERRAIN_D[0] + 1.0, 36.0, len(bush_s))
    wide = rng.uniform(0.5, 2.0, len(bush_s))
    bush_r = np.column_stack([wide, wide, rng.uniform(0.5, 1.5, len(bush_s))])
    tree_s = np.repeat(starts, n_tree) + rng.uniform(0.0, STRETCH_M, n_tree.sum())
    tree_d = np.repeat(_TREE_NEAR[kind], n_tree) + rng.uniform(0.0, 1.0, len(tree_s)) * \
        (TERRAIN_D[-1] - np.repeat(_TREE_NEAR[kind], n_tree))
    slender = rng.random(len(tree_s)) < 0.35
    crown = np.where(slender, rng.uniform(1.0, 2.2, len(tree_s)), rng.uniform(1.5, 4.0, len(tree_s)))
    crown_h = np.where(slender, rng.uniform(3.0, 6.0, len(tree_s)), crown * rng.uniform(0.8, 1.4, len(tree_s)))
    trunk = rng.uniform(1.5, 4.0, len(tree_s))
    trunk_w = rng.uniform(0.2, 0.45, len(tree_s))

    def place(s: np.ndarray, d: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ok = (s < s1 - 0.5) & (d + r <= reach)
        pts, other = ground.at(np.minimum(s, s1 - 1e-6), d) if len(s) else (np.zeros((0, 3)), np.zeros(0))
        ok &= other >= r + PLANT_GAP_M
        return pts, ok

    pts, ok = place(bush_s, bush_d, bush_r[:, 0])
    centre = pts[ok] + np.column_stack([np.zeros((ok.sum(), 2)), 0.6 * bush_r[ok, 2] - 0.2])
    _blobs(soup, centre, bush_r[ok], R.FOLIAGE, rng)
    pts, ok = place(tree_s, tree_d, crown)
    pts, trunk, trunk_w, crown, crown_h = pts[ok], trunk[ok], trunk_w[ok], crown[ok], crown_h[ok]
    top = pts[:, 2] + trunk + 0.7 * crown_h
    h = 0.5 * trunk_w[:, None]
    corners = [np.column_stack([pts[:, 0] + du * h[:, 0], pts[:, 1] + dv * h[:, 0], z])
               for z in (pts[:, 2] - 0.3, top) for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    if len(pts):
        soup.box(np.stack(corners, axis=1), R.WOOD, float(R._BASE[R.WOOD]), faces="sides")
    centre = np.column_stack([pts[:, :2], top])
    _blobs(soup, centre, np.column_stack([crown, crown, crown_h]), R.FOLIAGE, rng)


def _signs(soup: _Soup, road: Road, rng: np.random.Generator) -> None:
    s = rng.uniform(50.0, 400.0)
    while s < road.length - 20.0:
        ls = road.lane_sections[int(road.section_index(s)[0])]
        left, right = _edges(road, ls, np.array([s]))
        _, _, hdg = road.reference(s)
        along = np.array([math.cos(hdg[0]), math.sin(hdg[0]), 0.0])
        for edge, side in ((left[0], 1), (right[0], -1)):
            if not any(i * side > 0 and lane.type in PAVED for i, lane in ls.lanes.items()):
                continue
            t = edge + side * 2.5
            post_h = float(rng.uniform(2.0, 3.0))
            width, height = float(rng.uniform(1.0, 2.5)), float(rng.uniform(0.8, 1.8))
            _posts(soup, road, np.array([s]), np.array([t]), 0.1, post_h + height, R.STEEL, 0.35, z0=-0.3)
            face = -along * (1 if lane_side(road, 1) == side else -1)
            ss = s + 0.08 * float(face @ along)
            z = float(road.to_world(s, t, 0.0)[0, 2])
            pts = road.to_world(np.array([ss, ss]), np.array([t - width / 2, t + width / 2]))[:, :2]
            quad = np.array([[*pts[0], z + post_h], [*pts[1], z + post_h], [*pts[1], z + post_h + height],
                             [*pts[0], z + post_h + height]])
            tri = np.array([[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]])
            soup.add(tri, R.SIGN, R.draw_base(R.SIGN, 1, rng)[0], facing=face.astype(np.float32))
        s += float(rng.uniform(300.0, 900.0))


def _barrier(soup: _Soup, road: Road, ls, side: int, s0: float, s1: float, clear: _Clearance,
             rng: np.random.Generator) -> None:
    s = _stations(s0, s1, 2.0)
    left, right = _edges(road, ls, s)
    t = (left if side > 0 else right) + side * 3.0
    height = float(rng.uniform(3.0, 5.0))
    lo, hi = road.to_world(s, t, -0.6), road.to_world(s, t, height)
    blocked = clear.blocked(lo[:, :2], road.id, 1.0)
    ok = ~(blocked[:-1] | blocked[1:])
    soup.strip(lo[None], hi[None], R.CONCRETE, R.draw_base(R.CONCRETE, 1, rng)[0], keep=ok[None])
    posts = np.flatnonzero(~blocked)[::2]
    _posts(soup, road, s[posts], t[posts] - side * 0.08, 0.25, height + 0.7, R.STEEL, 0.35, z0=-0.6)
