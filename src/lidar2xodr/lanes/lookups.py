"""Relative and global lookups: candidate lines grouped into superlines (paper Alg. 2)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import Candidate

_CHUNK = 20000
_HOP_RADIUS_M = 500.0  # tightest curve a step beside another is allowed to follow (motorway minimum ~ 700 m)


@dataclass
class Segments:
    """All segments between consecutive centres of all candidates."""

    p0: np.ndarray  # (S, 3)
    p1: np.ndarray  # (S, 3)
    cand: np.ndarray  # (S,) candidate index (position in the list)
    arc0: np.ndarray  # (S,) arc position of p0 along its candidate

    @property
    def length(self) -> np.ndarray:
        return np.linalg.norm(self.p1[:, :2] - self.p0[:, :2], axis=1)


@dataclass
class Lookups:
    """Relative lookups: the normal at segment `seg_a` of candidate `cand_a` hits `cand_b`.

    `dist` is signed along the left normal of a (left positive); `offset_b` is the position of
    the normal's foot relative to b (left of b positive); `pos_b` the arc position of the hit on b.
    """

    seg_a: np.ndarray
    cand_a: np.ndarray
    cand_b: np.ndarray
    dist: np.ndarray
    offset_b: np.ndarray
    pos_b: np.ndarray


def split_candidates(candidates: list[Candidate], cfg: LanesConfig) -> tuple[list[Candidate], np.ndarray]:
    """Candidates cleaned for the lookups: a lone centre that kinks the line out and back (a blob
    Combine took in) is left out, and the line is cut where it still turns by more than
    `max_intersect_angle_deg`, leaps further than `max_link_gap_m` / 8 or steps more than half
    `min_lane_width_m` sideways to its neighbouring steps (a line does none of these; a chain
    through junk or across to the next line does). Returns the pieces and the candidate index of each; pieces keep the
    candidate's id."""
    cos_max = math.cos(math.radians(cfg.max_intersect_angle_deg))
    pieces: list[Candidate] = []
    owner: list[int] = []
    for i, c in enumerate(candidates):
        ctr = np.asarray(c.centers, dtype=np.float64)
        keep = np.ones(len(ctr), dtype=bool)
        for k in range(1, len(ctr) - 1):
            if _turn_cos(ctr[k - 1], ctr[k], ctr[k + 1]) < cos_max:
                nxt = ctr[k + 2] if k + 2 < len(ctr) else None
                prev = ctr[k - 2] if k >= 2 and keep[k - 2] else None
                around = [_turn_cos(a, ctr[k - 1], ctr[k + 1]) for a in (prev,) if a is not None]
                around += [_turn_cos(ctr[k - 1], ctr[k + 1], b) for b in (nxt,) if b is not None]
                if all(v >= cos_max for v in around):
                    keep[k] = False
        idx = np.flatnonzero(keep)
        ctr_k = ctr[idx]
        d = np.diff(ctr_k[:, :2], axis=0)
        ln = np.linalg.norm(d, axis=1)
        u = d / np.maximum(ln, 1e-9)[:, None]
        cut = np.zeros(len(ctr_k), dtype=bool)
        if len(ctr_k) > 2:
            cut[1:-1] = np.einsum("ij,ij->i", u[1:], u[:-1]) < cos_max
        leap = np.flatnonzero(ln > cfg.max_link_gap_m / 8.0)
        hop = _sideways_steps(ctr_k[:, :2], 0.5 * cfg.min_lane_width_m)
        bounds = sorted(
            {0, len(ctr_k), *np.flatnonzero(cut).tolist(), *(leap + 1).tolist(), *(hop + 1).tolist()}
        )
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            sel = idx[a:b]
            pieces.append(
                Candidate(c.id, ctr[sel], np.asarray(c.directions)[sel], np.asarray(c.cluster_ids)[sel])
            )
            owner.append(i)
    return pieces, np.asarray(owner, dtype=np.int64)


def _sideways_steps(xy: np.ndarray, tol: float) -> np.ndarray:
    """Steps (index of their first centre) that move more than `tol` sideways to the direction of
    the steps before and after them: a chain that crossed to the neighbouring lane line. Cutting
    on both sides of the step drops it, so each part joins its own superline instead of one
    crossing piece bending the road axis. The allowance grows as a curve of radius `_HOP_RADIUS_M`
    would need beside a step whose neighbours are unequal (one side only at a chain's end)."""
    if len(xy) < 3:
        return np.zeros(0, dtype=np.int64)
    d = np.diff(xy, axis=0)
    u = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
    ref = np.zeros_like(u)
    ref[1:] += u[:-1]
    ref[:-1] += u[1:]
    ref /= np.maximum(np.linalg.norm(ref, axis=1), 1e-9)[:, None]
    lateral = np.abs(d[:, 0] * ref[:, 1] - d[:, 1] * ref[:, 0])
    ln = np.linalg.norm(d, axis=1)
    near = np.maximum(np.r_[0.0, ln[:-1]], np.r_[ln[1:], 0.0])
    return np.flatnonzero(lateral > tol + ln * (ln + near) / (2.0 * _HOP_RADIUS_M))


def _turn_cos(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Cosine of the turn at b on the way a -> b -> c (1 = straight on)."""
    u, v = b[:2] - a[:2], c[:2] - b[:2]
    return float(u @ v / max(float(np.linalg.norm(u) * np.linalg.norm(v)), 1e-12))


def candidate_segments(candidates: list[Candidate], half_dash: float = 3.0) -> Segments:
    """Segments of every candidate; a single-centre candidate is a dash-long segment along its direction."""
    p0, p1, cand, arc0 = [], [], [], []
    for i, c in enumerate(candidates):
        ctr = np.asarray(c.centers, dtype=np.float64)
        if len(ctr) == 1:
            d = np.zeros(3)
            d[:2] = np.asarray(c.directions, dtype=np.float64)[0] * half_dash
            ctr = np.vstack([ctr[0] - d, ctr[0] + d])
        seg = np.linalg.norm(np.diff(ctr[:, :2], axis=0), axis=1)
        p0.append(ctr[:-1])
        p1.append(ctr[1:])
        cand.append(np.full(len(seg), i))
        arc0.append(np.concatenate([[0.0], np.cumsum(seg)[:-1]]))
    if not p0:
        z = np.zeros((0, 3))
        return Segments(z, z, np.zeros(0, dtype=np.int64), np.zeros(0))
    return Segments(np.vstack(p0), np.vstack(p1), np.concatenate(cand), np.concatenate(arc0))


def relative_lookups(segs: Segments, cfg: LanesConfig) -> Lookups:
    """Paper Alg. 2: intersect the left/right normal of every segment with all other candidates."""
    empty = np.zeros(0)
    if len(segs.cand) == 0:
        return Lookups(empty.astype(int), empty.astype(int), empty.astype(int), empty, empty, empty)
    length = segs.length
    good = length > 1e-6
    d_xy = segs.p1[:, :2] - segs.p0[:, :2]
    tangent = d_xy / np.maximum(length, 1e-9)[:, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    origin = 0.5 * (segs.p0 + segs.p1)
    step = 2.0
    n_s = np.maximum(np.ceil(length / step).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(length)), n_s + 1)
    frac = np.concatenate([np.arange(k + 1) / k for k in n_s])
    samples = segs.p0[owner, :2] + d_xy[owner] * frac[:, None]
    tree = cKDTree(samples)
    radius = cfg.max_normal_length_m + step
    cos_max = math.cos(math.radians(cfg.max_intersect_angle_deg))
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("seg_a", "seg_b", "dist", "mu")}
    rays = np.flatnonzero(good)
    for a in range(0, len(rays), _CHUNK):
        r = rays[a : a + _CHUNK]
        hits = tree.query_ball_point(origin[r, :2], radius)
        counts = np.array([len(h) for h in hits])
        if counts.sum() == 0:
            continue
        ray = np.repeat(r, counts)
        seg = owner[np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])]
        key = np.unique(ray * len(length) + seg)
        ray, seg = key // len(length), key % len(length)
        keep = (segs.cand[ray] != segs.cand[seg]) & good[seg]
        ray, seg = ray[keep], seg[keep]
        n, dvec = normal[ray], d_xy[seg]
        w = segs.p0[seg, :2] - origin[ray, :2]
        den = n[:, 0] * dvec[:, 1] - n[:, 1] * dvec[:, 0]
        ok = np.abs(den) >= cos_max * length[seg]
        den = np.where(ok, den, 1.0)
        lam = (w[:, 0] * dvec[:, 1] - w[:, 1] * dvec[:, 0]) / den
        mu = (w[:, 0] * n[:, 1] - w[:, 1] * n[:, 0]) / den
        z_hit = segs.p0[seg, 2] + mu * (segs.p1[seg, 2] - segs.p0[seg, 2])
        ok &= (mu >= 0) & (mu <= 1) & (np.abs(lam) <= cfg.max_normal_length_m) & (np.abs(lam) > 1e-6)
        ok &= np.abs(z_hit - origin[ray, 2]) <= cfg.z_tolerance_m
        for k, v in (("seg_a", ray[ok]), ("seg_b", seg[ok]), ("dist", lam[ok]), ("mu", mu[ok])):
            out[k].append(v)
    if not out["seg_a"]:
        return Lookups(empty.astype(int), empty.astype(int), empty.astype(int), empty, empty, empty)
    seg_a, seg_b = np.concatenate(out["seg_a"]), np.concatenate(out["seg_b"])
    dist, mu = np.concatenate(out["dist"]), np.concatenate(out["mu"])
    # one hit per (ray, side, candidate): the nearest
    side = (dist > 0).astype(np.int64)
    order = np.lexsort((np.abs(dist), segs.cand[seg_b], side, seg_a))
    seg_a, seg_b, dist, mu, side = seg_a[order], seg_b[order], dist[order], mu[order], side[order]
    first = np.ones(len(seg_a), dtype=bool)
    first[1:] = (
        (seg_a[1:] != seg_a[:-1]) | (side[1:] != side[:-1]) | (segs.cand[seg_b][1:] != segs.cand[seg_b][:-1])
    )
    seg_a, seg_b, dist, mu = seg_a[first], seg_b[first], dist[first], mu[first]
    hit = segs.p0[seg_b, :2] + mu[:, None] * d_xy[seg_b]
    offset_b = np.einsum("ij,ij->i", origin[seg_a, :2] - hit, normal[seg_b])
    pos_b = segs.arc0[seg_b] + mu * length[seg_b]
    return Lookups(seg_a, segs.cand[seg_a], segs.cand[seg_b], dist, offset_b, pos_b)


def lane_step(lookups: Lookups, cfg: LanesConfig) -> float | None:
    """The lane step of the paper's distance decomposition, measured on the drive (None: no lanes)."""
    if len(lookups.dist) == 0:
        return None
    side = lookups.dist > 0
    key = lookups.seg_a * 2 + side
    order = np.lexsort((np.abs(lookups.dist), key))
    first = np.ones(len(order), dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    nearest = np.abs(lookups.dist[order][first])
    lane = nearest[(nearest >= cfg.min_lane_width_m) & (nearest <= cfg.max_lane_width_m)]
    if len(lane) < 3:
        return None
    return max(float(np.median(lane)), cfg.lookup_modulo_m)


class _Groups:
    """Union-find over candidates that refuses to join groups in conflict (seen side by side)."""

    def __init__(self, n: int, conflicts: list[set[int]]) -> None:
        self.parent = list(range(n))
        self.members = {i: {i} for i in range(n)}
        self.conflicts = {i: set(conflicts[i]) for i in range(n)}

    def find(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def join(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb or self.conflicts[ra] & self.members[rb]:
            return False
        keep, gone = min(ra, rb), max(ra, rb)
        self.parent[gone] = keep
        self.members[keep] |= self.members.pop(gone)
        self.conflicts[keep] |= self.conflicts.pop(gone)
        return True


def global_lookup(n_cand: int, lookups: Lookups, step: float, cfg: LanesConfig) -> np.ndarray:
    """Superline index per candidate: pieces at one offset from a shared neighbour, one after the other."""
    tol = cfg.same_line_tolerance_m
    conflicts: list[set[int]] = [set() for _ in range(n_cand)]
    same: list[tuple[float, float, int, int]] = []
    if len(lookups.dist):
        pair = lookups.cand_a * n_cand + lookups.cand_b
        uniq, inv, cnt = np.unique(pair, return_inverse=True, return_counts=True)
        med = (
            np.array([np.median(np.abs(lookups.dist[inv == k])) for k in range(len(uniq))])
            if len(uniq) < 2000
            else _group_median(np.abs(lookups.dist), inv, len(uniq))
        )
        for key, m, c in zip(uniq, med, cnt, strict=False):
            a, b = int(key // n_cand), int(key % n_cand)
            if c >= 2 and m > tol:
                conflicts[a].add(b)
                conflicts[b].add(a)
            elif c >= 2:
                same.append((0.0, float(m), a, b))
        same += _links_via_neighbours(lookups, n_cand, tol, step, cfg)
    groups = _Groups(n_cand, conflicts)
    for _, _, a, b in sorted(same):
        groups.join(a, b)
    roots = np.array([groups.find(i) for i in range(n_cand)], dtype=np.int64)
    _, superline = np.unique(roots, return_inverse=True)
    return superline.ravel()


def _group_median(values: np.ndarray, inv: np.ndarray, n: int) -> np.ndarray:
    order = np.lexsort((values, inv))
    counts = np.bincount(inv, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return 0.5 * (values[order][starts + (counts - 1) // 2] + values[order][starts + counts // 2])


def _links_via_neighbours(
    lookups: Lookups, n_cand: int, tol: float, step: float, cfg: LanesConfig
) -> list[tuple[float, float, int, int]]:
    """Paper's global lookup: X then Y along a shared neighbour B at the same offset from B."""
    pair = lookups.cand_b * n_cand + lookups.cand_a
    order = np.lexsort((lookups.pos_b, pair))
    pair_s, pos, off = pair[order], lookups.pos_b[order], lookups.offset_b[order]
    bounds = np.flatnonzero(np.diff(pair_s)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [len(pair_s)]])
    rows = []
    for s0, s1 in zip(starts, ends, strict=False):
        if s1 - s0 < 2:
            continue
        p, o = pos[s0:s1], off[s0:s1]
        head = np.median(o[p <= max(p[0] + 30.0, p[min(4, len(p) - 1)])])
        tail = np.median(o[p >= min(p[-1] - 30.0, p[max(len(p) - 5, 0)])])
        if round(abs(head) / step) == 0 and round(abs(tail) / step) == 0:
            continue
        rows.append(
            (
                int(pair_s[s0] // n_cand),
                int(pair_s[s0] % n_cand),
                float(p[0]),
                float(p[-1]),
                float(head),
                float(tail),
            )
        )
    links = []
    by_b: dict[int, list[tuple[int, float, float, float, float]]] = {}
    for b, x, p0, p1, head, tail in rows:
        by_b.setdefault(b, []).append((x, p0, p1, head, tail))
    for entries in by_b.values():
        for x, _, x1, _, x_tail in entries:
            best = None
            for y, y0, _, y_head, _ in entries:
                gap = y0 - x1
                if y == x or gap < -5.0 or gap > cfg.max_link_gap_m or abs(y_head - x_tail) > tol:
                    continue
                cand = (max(gap, 0.0), abs(y_head - x_tail), x, y)
                best = cand if best is None or cand < best else best
            if best is not None:
                links.append(best)
    return links
