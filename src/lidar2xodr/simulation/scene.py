"""The static world as triangles: road surfaces, painted marks, verges, guard rails, bridges, gantries.

Everything is built from the map through the OpenDRIVE reader (to_world with elevation and
superelevation), binned into 50 m cells, and ray-cast per window with Open3D's RaycastingScene
(Embree). Coordinates are stored relative to a map-centred origin, and each window scene is
shifted to its own origin, so float32 keeps sub-millimetre precision on any map.

Decisions:
- Paint is its own polygon lifted 5 mm above the surface: solid lines in 10 m pieces, broken lines
  with the map's pattern (reader defaults 6 m / 12 m), double lines as two polygons; every dash
  and piece draws its own wear.
- Lane types: driving-like and shoulders are asphalt; border lanes gravel 3 cm lower; none/median
  lanes grass 5 cm lower; sidewalks and curbs concrete 12 cm higher.
- Verges beyond the outermost lane: 1.5 m gravel then 6.5 m grass falling to 0.7 m below the road
  (2 m on junction roads). Lower than any road, so they never cover another road's surface.
- Guard rails (W-beam 0.45-0.75 m on posts every 4 m) 1 m beyond both carriageway edges of roads
  longer than 100 m outside junctions, and in medians >= 1.5 m wide; delineator posts with
  retro-reflectors every 50 m. Both are left out wherever they would stand on another road.
- About one structure per km on roads longer than 400 m outside junctions: an overpass (deck
  5.5-6.5 m above the road, 12 m wide, abutments beyond the verges) or a sign gantry (beam at
  7.0-7.6 m, retro-reflective sign faces 2.5-3.5 m high with their lower edge 5.2-5.7 m above the
  road, facing each direction's traffic). Placement is seeded per road id.
- With the `roadside` option: terrain, vegetation, roadside signs and noise barriers beyond the
  verges (roadside.py).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from lidar2xodr.opendrive import OpenDriveMap, Road
from lidar2xodr.simulation import reflectivity as R
from lidar2xodr.simulation.route import PAVED, lane_side

CELL_M = 50.0
STEP_M = 1.0
PAINT_LIFT_M = 0.005

_GRAVEL_TYPES = frozenset({"border"})
_GRASS_TYPES = frozenset({"none", "median"})
_RAISED_TYPES = frozenset({"sidewalk", "curb", "walking"})


@dataclass
class StaticWorld:
    """All static triangles, sorted by 50 m cell."""

    origin: np.ndarray  # (3,) float64
    tri: np.ndarray  # (T, 3, 3) float32, relative to origin
    material: np.ndarray  # (T,) uint8
    base: np.ndarray  # (T,) float32 base reflectivity
    facing: np.ndarray  # (T, 3) float32: the front normal of sign faces (zero elsewhere)
    cell_start: np.ndarray  # (C + 1,)
    cell_centre: np.ndarray  # (C, 2) world xy

    def window(self, xy: np.ndarray, radius: float) -> WindowScene:
        """A ray-casting scene with every cell within `radius` of any of the points `xy`."""
        tree = cKDTree(self.cell_centre)
        hits = tree.query_ball_point(xy, radius + CELL_M * 0.75)
        cells = np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])) if len(hits) else []
        sel = np.concatenate([np.arange(self.cell_start[c], self.cell_start[c + 1]) for c in cells]) \
            if len(cells) else np.zeros(0, dtype=np.int64)
        centre = np.append(np.mean(xy, axis=0), 0.0)
        return WindowScene(self, sel, centre)


class WindowScene:
    """One Embree scene over part of the world, in coordinates relative to `origin`."""

    def __init__(self, world: StaticWorld, sel: np.ndarray, origin_world: np.ndarray) -> None:
        self.origin = origin_world
        shift = (world.origin - origin_world).astype(np.float32)
        tri = world.tri[sel] + shift
        self.material = world.material[sel]
        self.base = world.base[sel]
        self.facing = world.facing[sel]
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(sel):
            verts = np.ascontiguousarray(tri.reshape(-1, 3), dtype=np.float32)
            faces = np.arange(len(verts), dtype=np.uint32).reshape(-1, 3)
            self.scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(faces))
        self.empty = len(sel) == 0

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, ...]:
        """Range, material, base reflectivity and |cos incidence| of each ray's first hit (inf = none).

        `origins` are relative to this scene's origin; both arrays float32.
        """
        n = len(origins)
        if self.empty:
            return np.full(n, np.inf), np.zeros(n, np.uint8), np.zeros(n, np.float32), np.ones(n, np.float32)
        res = self.scene.cast_rays(o3d.core.Tensor(np.concatenate([origins, dirs], axis=1)))
        t = res["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        prim = np.where(hit, res["primitive_ids"].numpy(), 0).astype(np.int64)
        normal = res["primitive_normals"].numpy()
        dot = np.einsum("ij,ij->i", normal, dirs)
        mat = self.material[prim]
        mat[~hit] = 0
        base = self.base[prim]
        sign = hit & (mat == R.SIGN)
        if sign.any():
            back = np.einsum("ij,ij->i", self.facing[prim[sign]], dirs[sign]) > 0
            k = np.flatnonzero(sign)[back]
            mat[k] = R.STEEL
            base[k] = 0.35
        return t, mat, base, np.abs(dot)


class _Soup:
    """Collects triangles with their material, base reflectivity and (for signs) facing."""

    def __init__(self) -> None:
        self.tri: list[np.ndarray] = []
        self.mat: list[np.ndarray] = []
        self.base: list[np.ndarray] = []
        self.facing: list[np.ndarray] = []

    def add(self, tri: np.ndarray, material: int, base: np.ndarray | float, facing: np.ndarray | None = None) -> None:
        tri = tri.reshape(-1, 3, 3)
        if len(tri) == 0:
            return
        self.tri.append(tri)
        self.mat.append(np.full(len(tri), material, dtype=np.uint8))
        self.base.append(np.broadcast_to(np.asarray(base, dtype=np.float32), (len(tri),)).copy())
        f = np.zeros((len(tri), 3), np.float32) if facing is None else np.broadcast_to(facing, (len(tri), 3))
        self.facing.append(np.asarray(f, dtype=np.float32))

    def strip(self, a: np.ndarray, b: np.ndarray, material: int, base: np.ndarray | float,
              keep: np.ndarray | None = None) -> None:
        """Triangles between polylines a and b of shape (..., M, 3); base and keep per quad (..., M-1)."""
        a0, a1, b0, b1 = a[..., :-1, :], a[..., 1:, :], b[..., :-1, :], b[..., 1:, :]
        t1 = np.stack([a0, b0, b1], axis=-2)
        t2 = np.stack([a0, b1, a1], axis=-2)
        tri = np.stack([t1, t2], axis=-3)  # (..., M-1, 2, 3, 3)
        bb = np.broadcast_to(np.asarray(base, dtype=np.float32)[..., None], tri.shape[:-2])
        if keep is not None:
            tri, bb = tri[keep], bb[keep]
        self.add(tri, material, bb.reshape(-1))

    def box(self, corners: np.ndarray, material: int, base: float, faces: str = "all") -> None:
        """Boxes from corners (..., 8, 3): bottom 0-3 and top 4-7, counter-clockwise."""
        c = corners.reshape(-1, 8, 3)
        quads = [(0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
        if faces == "all":
            quads += [(0, 3, 2, 1), (4, 5, 6, 7)]
        tris = []
        for a, b, cc, d in quads:
            tris.append(np.stack([c[:, a], c[:, b], c[:, cc]], axis=1))
            tris.append(np.stack([c[:, a], c[:, cc], c[:, d]], axis=1))
        self.add(np.stack(tris, axis=1), material, base)


def build_world(odr: OpenDriveMap, roads: list[str], seed: int, roadside: bool = False) -> StaticWorld:
    """Every static triangle of the given roads (and the structures over them); `roadside` adds roadside.py."""
    from lidar2xodr.simulation.roadside import add_roadside

    soup = _Soup()
    clear = _Clearance(odr)
    for rid in roads:
        road = odr.roads[rid]
        rng = np.random.default_rng([seed, zlib.crc32(rid.encode())])
        _road_surface(soup, road, rng)
        _road_marks(soup, road, rng)
        _verges(soup, road)
        if road.junction == "-1" and road.length > 100.0:
            _rails(soup, road, clear, rng)
        if road.junction == "-1" and road.length > 400.0:
            _structures(soup, road, clear, rng)
        if roadside and road.junction == "-1" and road.length > 100.0:
            add_roadside(soup, road, clear, np.random.default_rng([seed, zlib.crc32(rid.encode()), 1]))
    if not soup.tri:
        tri = np.zeros((0, 3, 3))
        return StaticWorld(np.zeros(3), tri.astype(np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32),
                           np.zeros((0, 3), np.float32), np.zeros(1, np.int64), np.zeros((0, 2)))
    tri = np.concatenate(soup.tri)
    origin = np.round(0.5 * (tri.reshape(-1, 3).min(axis=0) + tri.reshape(-1, 3).max(axis=0)))
    centroid = tri.mean(axis=1)
    key = np.floor(centroid[:, :2] / CELL_M).astype(np.int64)
    cells, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    counts = np.bincount(inverse, minlength=len(cells))
    return StaticWorld(
        origin=origin,
        tri=(tri[order] - origin).astype(np.float32),
        material=np.concatenate(soup.mat)[order],
        base=np.concatenate(soup.base)[order],
        facing=np.concatenate(soup.facing)[order],
        cell_start=np.concatenate([[0], np.cumsum(counts)]),
        cell_centre=(cells + 0.5) * CELL_M,
    )


def _stations(s0: float, s1: float, step: float = STEP_M) -> np.ndarray:
    n = max(1, math.ceil((s1 - s0) / step - 1e-9))
    s = np.linspace(s0, s1, n + 1)
    s[-1] = max(s0, s1 - 1e-6)  # stay inside this section (border_t at s1 reads the next one)
    return s


def _lane_kind(kind: str) -> tuple[int, float, float]:
    """Material, base reflectivity and height of a lane type."""
    if kind in _GRAVEL_TYPES:
        return R.GRAVEL, 0.2, -0.03
    if kind in _GRASS_TYPES:
        return R.GRASS, 0.32, -0.05
    if kind in _RAISED_TYPES:
        return R.CONCRETE, 0.3, 0.12
    return R.ASPHALT, 0.08 if kind != "shoulder" else 0.1, 0.0


def _road_surface(soup: _Soup, road: Road, rng: np.random.Generator) -> None:
    for ls in road.lane_sections:
        s = _stations(ls.s, ls.s_end)
        for lid in ls.lane_ids():
            if lid == 0:
                continue
            side = 1 if lid > 0 else -1
            t_in = road.border_t(s, lid - side)
            t_out = road.border_t(s, lid)
            if not np.all(np.isfinite(t_in + t_out)) or np.max(np.abs(t_out - t_in)) < 0.01:
                continue
            mat, mean, h = _lane_kind(ls.lanes[lid].type)
            a = road.to_world(s, t_in, h)
            b = road.to_world(s, t_out, h)
            patch = np.floor((s[:-1] - ls.s) / 40.0).astype(np.int64)
            base = R.draw_base(mat, int(patch.max()) + 1, rng) * (mean / R._BASE[mat])
            soup.strip(a, b, mat, base[patch])


def _road_marks(soup: _Soup, road: Road, rng: np.random.Generator) -> None:
    for ls in road.lane_sections:
        for lid in ls.lane_ids():
            marks = ls.lanes[lid].road_marks
            for k, rm in enumerate(marks):
                m0 = ls.s + rm.s_offset
                m1 = ls.s + marks[k + 1].s_offset if k + 1 < len(marks) else ls.s_end
                if m1 - m0 < 0.05 or not rm.lines:
                    continue
                yellow = rm.color in ("yellow", "orange")
                for line in rm.lines:
                    _paint_line(soup, road, lid, ls.s, ls.s_end, m0, m1, line, yellow, rng)


def _paint_line(soup: _Soup, road: Road, lid: int, sec0: float, sec1: float, m0: float, m1: float, line,
                yellow: bool, rng: np.random.Generator) -> None:
    width = line.width if line.width > 0 else 0.12
    if line.space <= 0 or line.length <= 0:
        starts = np.arange(m0, m1, 10.0)
        ends = np.minimum(starts + 10.0, m1)
    else:
        period = line.length + line.space
        first = m0 + (line.s_offset % period)
        starts = np.arange(first - period, m1, period)
        ends = np.minimum(starts + line.length, m1)
        starts = np.maximum(starts, m0)
    keep = ends - starts > 0.02
    starts, ends = starts[keep], ends[keep]
    if len(starts) == 0:
        return
    m = max(2, math.ceil(float(np.max(ends - starts)) / STEP_M) + 1)
    f = np.linspace(0.0, 1.0, m)
    s = starts[:, None] + (ends - starts)[:, None] * f[None, :]
    s = np.clip(s, sec0, max(sec0, sec1 - 1e-6))
    flat = s.reshape(-1)
    t = road.border_t(flat, lid) + line.t_offset
    a = road.to_world(flat, t + 0.5 * width, PAINT_LIFT_M).reshape(len(starts), m, 3)
    b = road.to_world(flat, t - 0.5 * width, PAINT_LIFT_M).reshape(len(starts), m, 3)
    base = R.paint_base(len(starts), yellow, rng)
    soup.strip(a, b, R.PAINT_YELLOW if yellow else R.PAINT_WHITE, np.repeat(base[:, None], m - 1, axis=1))


def _edges(road: Road, ls, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outermost border t on the left and right of a section (the reference line if a side is empty)."""
    left = max((i for i in ls.lanes if i > 0), default=0)
    right = min((i for i in ls.lanes if i < 0), default=0)
    return road.border_t(s, left), road.border_t(s, right)


def _verges(soup: _Soup, road: Road) -> None:
    wide = road.junction == "-1"
    for ls in road.lane_sections:
        s = _stations(ls.s, ls.s_end, 2.0)
        left, right = _edges(road, ls, s)
        for edge, sign in ((left, 1.0), (right, -1.0)):
            a = road.to_world(s, edge, -0.05)
            b = road.to_world(s, edge + sign * 1.5, -0.12)
            pair = (a, b) if sign < 0 else (b, a)
            soup.strip(*pair, R.GRAVEL, 0.2)
            if wide:
                c = road.to_world(s, edge + sign * 8.0, -0.7)
                pair = (b, c) if sign < 0 else (c, b)
                soup.strip(*pair, R.GRASS, 0.32)


class _Clearance:
    """Where paved lanes of the whole map are: rails and walls must not stand on another road."""

    def __init__(self, odr: OpenDriveMap) -> None:
        pts, half, owner = [], [], []
        self.ids = {rid: k for k, rid in enumerate(odr.roads)}
        for rid, road in odr.roads.items():
            for ls in road.lane_sections:
                s = _stations(ls.s, ls.s_end, 2.0)
                for lid, lane in ls.lanes.items():
                    if lid == 0 or lane.type not in PAVED:
                        continue
                    side = 1 if lid > 0 else -1
                    t_in, t_out = road.border_t(s, lid - side), road.border_t(s, lid)
                    pts.append(road.to_world(s, 0.5 * (t_in + t_out))[:, :2])
                    half.append(0.5 * np.abs(t_out - t_in))
                    owner.append(np.full(len(s), self.ids[rid]))
        self.pts = np.concatenate(pts) if pts else np.zeros((0, 2))
        self.half = np.concatenate(half) if half else np.zeros(0)
        self.owner = np.concatenate(owner) if owner else np.zeros(0, np.int64)
        self.tree = cKDTree(self.pts) if len(self.pts) else None
        self.max_half = float(self.half.max()) if len(self.half) else 0.0
        self._other_trees: dict[str, tuple[cKDTree, np.ndarray] | None] = {}

    def blocked(self, xy: np.ndarray, road_id: str, margin: float) -> np.ndarray:
        """True where a paved lane of another road lies within `margin` of the points."""
        if self.tree is None or len(xy) == 0:
            return np.zeros(len(xy), dtype=bool)
        d, i = self.tree.query(xy, k=8, distance_upper_bound=self.max_half + margin + 1.5)
        ok = np.isfinite(d)
        i = np.where(ok, i, 0)
        near = ok & (d < self.half[i] + margin) & (self.owner[i] != self.ids[road_id])
        return near.any(axis=1)

    def distance(self, xy: np.ndarray, road_id: str, cap: float) -> np.ndarray:
        """Distance from the points to the nearest paved lane of another road (at most `cap`)."""
        others = self._others(road_id)
        if others is None or len(xy) == 0:
            return np.full(len(xy), cap)
        tree, half = others
        d, i = tree.query(xy, k=4, distance_upper_bound=cap + self.max_half)
        ok = np.isfinite(d)
        gap = np.where(ok, d - half[np.where(ok, i, 0)], np.inf)
        return np.clip(gap.min(axis=1), 0.0, cap)

    def _others(self, road_id: str) -> tuple[cKDTree, np.ndarray] | None:
        if road_id not in self._other_trees:
            m = self.owner != self.ids[road_id]
            self._other_trees[road_id] = (cKDTree(self.pts[m]), self.half[m]) if m.any() else None
        return self._other_trees[road_id]


def _rails(soup: _Soup, road: Road, clear: _Clearance, rng: np.random.Generator) -> None:
    for ls in road.lane_sections:
        s = _stations(ls.s, ls.s_end, 2.0)
        left, right = _edges(road, ls, s)
        lines = [(left + 1.0, -1.0), (right - 1.0, 1.0)]
        med = _median(road, ls, s)
        if med is not None:
            lines.append((med, 0.0))
        for t, inward in lines:
            foot = road.to_world(s, t, 0.0)
            blocked = clear.blocked(foot[:, :2], road.id, 0.6)
            lo = road.to_world(s, t, 0.45)
            hi = road.to_world(s, t, 0.75)
            ok = ~(blocked[:-1] | blocked[1:])
            soup.strip(lo[None], hi[None], R.STEEL, R.draw_base(R.STEEL, 1, rng)[0], keep=ok[None])
            posts = np.flatnonzero(~blocked)[::2]
            _posts(soup, road, s[posts], t[posts], 0.1, 0.7, R.STEEL, 0.3)
            if inward:
                every = np.flatnonzero(~blocked)[::25]
                td = t[every] + inward * 0.4
                _posts(soup, road, s[every], td, 0.12, 1.0, R.DELINEATOR, 0.6)
                _posts(soup, road, s[every], td, 0.13, 0.18, R.SIGN, 3.0, z0=0.72)


def _median(road: Road, ls, s: np.ndarray) -> np.ndarray | None:
    """t of the middle of the median between opposite driving lanes, when it is >= 1.5 m wide."""
    left = [i for i, lane in ls.lanes.items() if i > 0 and lane.type in PAVED]
    right = [i for i, lane in ls.lanes.items() if i < 0 and lane.type in PAVED]
    if not left or not right:
        return None
    inner_l = road.border_t(s, min(left) - 1)
    inner_r = road.border_t(s, max(right) + 1)
    if np.min(inner_l - inner_r) < 1.5:
        return None
    return 0.5 * (inner_l + inner_r)


def _posts(soup: _Soup, road: Road, s: np.ndarray, t: np.ndarray, size: float, height: float, material: int,
           base: float, z0: float = 0.0) -> None:
    if len(s) == 0:
        return
    x, y, hdg = road.reference(s)
    p = road.to_world(s, t, 0.0)
    c, sn = np.cos(hdg), np.sin(hdg)
    h = 0.5 * size
    corners = []
    for z in (z0, z0 + height):
        for du, dv in ((-h, -h), (h, -h), (h, h), (-h, h)):
            corners.append(p + np.column_stack([c * du - sn * dv, sn * du + c * dv, np.full(len(s), z)]))
    soup.box(np.stack(corners, axis=1), material, base)


def _structures(soup: _Soup, road: Road, clear: _Clearance, rng: np.random.Generator) -> None:
    s = float(rng.uniform(150.0, 600.0))
    k = 0
    while s < road.length - 60.0:
        if k % 2 == int(rng.integers(2)):
            _bridge(soup, road, s, clear, rng)
        else:
            _gantry(soup, road, s, clear, rng)
        s += float(rng.uniform(700.0, 1400.0))
        k += 1


def _span(road: Road, s: float) -> tuple[float, float]:
    ls = road.lane_sections[int(road.section_index(s)[0])]
    left, right = _edges(road, ls, np.array([s]))
    return float(left[0]), float(right[0])


def _slab(road: Road, s0: float, s1: float, t0: float, t1: float, z0: float, z1: float) -> np.ndarray:
    """Corners of a box over road coordinates [s0, s1] x [t0, t1], level between world z0 and z1."""
    ss = np.array([s0, s1, s1, s0])
    tt = np.array([t0, t0, t1, t1])
    xy = road.to_world(ss, tt)[:, :2]
    bottom = np.column_stack([xy, np.full(4, z0)])
    top = np.column_stack([xy, np.full(4, z1)])
    return np.concatenate([bottom, top])


def _bridge(soup: _Soup, road: Road, s: float, clear: _Clearance, rng: np.random.Generator) -> None:
    left, right = _span(road, s)
    z = float(road.to_world(s, 0.0)[0, 2])
    under = z + float(rng.uniform(5.5, 6.5)) + max(0.0, abs(left - right) * abs(float(road.superelevation(s)[0])))
    soup.box(_slab(road, s - 6.0, s + 6.0, right - 12.0, left + 12.0, under, under + 1.2), R.CONCRETE, 0.3)
    for t0, t1 in ((left + 9.0, left + 10.5), (right - 10.5, right - 9.0)):
        xy = road.to_world(np.array([s, s]), np.array([t0, t1]))[:, :2]
        if clear.blocked(xy, road.id, 0.5).any():
            continue
        soup.box(_slab(road, s - 5.0, s + 5.0, t0, t1, z - 1.5, under), R.CONCRETE, 0.3)


def _gantry(soup: _Soup, road: Road, s: float, clear: _Clearance, rng: np.random.Generator) -> None:
    left, right = _span(road, s)
    z = float(road.to_world(s, 0.0)[0, 2])
    beam = z + float(rng.uniform(7.0, 7.6))
    soup.box(_slab(road, s - 0.3, s + 0.3, right - 1.5, left + 1.5, beam, beam + 0.6), R.STEEL, 0.3)
    for t in (left + 1.5, right - 1.5):
        xy = road.to_world(np.array([s]), np.array([t]))[:, :2]
        if not clear.blocked(xy, road.id, 0.5).any():
            soup.box(_slab(road, s - 0.25, s + 0.25, t - 0.25, t + 0.25, z - 0.5, beam + 0.6), R.STEEL, 0.3)
    _, _, hdg = road.reference(s)
    along = np.array([math.cos(hdg[0]), math.sin(hdg[0]), 0.0])
    ls = road.lane_sections[int(road.section_index(s)[0])]
    for side in (-1, 1):
        face = -along * (1 if lane_side(road, 1) == side else -1)  # towards the approaching traffic
        ids = [i for i, lane in ls.lanes.items() if i * side > 0 and lane.type in PAVED]
        if not ids:
            continue
        outer = road.border_t(s, max(ids, key=abs))[0]
        inner = road.border_t(s, min(ids, key=abs) - side)[0]
        lo, hi = sorted((inner, outer))
        width = min(hi - lo, float(rng.uniform(3.5, 6.0)))
        mid = lo + (hi - lo) * float(rng.uniform(0.3, 0.7))
        bottom = z + float(rng.uniform(5.2, 5.7))
        top = bottom + float(rng.uniform(2.5, 3.5))
        ss = s + 0.4 * float(face @ along)
        pts = road.to_world(np.array([ss, ss]), np.array([mid - width / 2, mid + width / 2]))[:, :2]
        quad = np.array([[*pts[0], bottom], [*pts[1], bottom], [*pts[1], top], [*pts[0], top]])
        tri = np.array([[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]])
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        flip = (n @ face) < 0
        tri[flip] = tri[flip][:, [0, 2, 1]]
        soup.add(tri, R.SIGN, R.draw_base(R.SIGN, 1, rng)[0], facing=face.astype(np.float32))
