"""Lanes from markings alone (paper Alg. 2): relative lookups, superlines, boundaries, sections.

Method and the decisions the paper leaves open (parameters in `LanesConfig`):
- Relative lookups (paper): in 2D, the left and right normals at the middle of every segment
  between consecutive centres of a candidate are intersected with the segments of all other
  candidates (`max_normal_length_m`; segments crossing at more than `max_intersect_angle_deg`
  or `z_tolerance_m` higher/lower are ignored). Each hit is (candidate, side, distance).
- The paper's "distance % 3.0 m": a distance is split into whole lane steps (the quotient is the
  lateral lane offset) and a remainder that refines the width (d / k = step + remainder / k). A
  fixed 3.0 m step miscounts lanes of 4.0 m (3 x 4.0 / 3.0 = 4) and lanes under 3.0 m, so we keep
  the decomposition with the step measured on the drive: the median nearest-neighbour distance
  within [min_lane_width_m, max_lane_width_m]; `lookup_modulo_m` is only its fallback floor.
- Global lookup (paper Fig. 4): two candidates are one line when both are hit by the normals of
  a shared neighbour at the same lateral offset (within `same_line_tolerance_m`) and one follows
  the other along that neighbour (gap up to `max_link_gap_m`). Candidates that see each other
  beside them at more than the tolerance never join (union-find with conflict sets), so a
  diverging edge line and the new line at its old place stay apart. The result: superlines.
- Frame and reference line: a first road axis is the smoothed middle of the lookups' cross
  sections, ordered by geodesic distance over a neighbour graph (no trajectory). Points are
  assigned to superlines (first by candidate, then by distance to the fitted curves, which may
  grow 30 m per pass but never onto another line) and each boundary t(s) is a robust
  (Tukey-weighted) Whittaker smoother with cutoff wavelength `boundary_smoothing_m`, fitted to
  the points rather than to the cluster centres; short islands (a dash, a blob) lying off the
  curve fitted without them are dropped, and across unobserved stretches over 20 m a line keeps
  its width to the best-observed neighbour. The reference line is the centre between the
  outermost kept boundaries, smoothed (`reference_smoothing_m`); the frame is replaced by it
  twice, so the final t(s) are offsets from the written reference line itself. Z comes from the
  marking points (a plane across the road per 5 m, evaluated at t = 0, smoothed along s).
- Lane structure per station: parallel lines closer than `same_line_tolerance_m` are one (the
  one that goes on where the other ends is kept, else the better supported); carriageways split
  at spacings above `carriageway_gap_m` (steady ones above `max_lane_width_m` beside the
  outermost line) and at a space between two solid lines with lines beyond both (a median);
  the one holding the ego trajectory is kept (else the one with
  most lines, then most points) and lines of the other are ignored with a warning. Every
  adjacency of two lines must contain a stable lane stretch (width within [min, max], changing
  less than `stable_lane_slope`) of `min_section_length_m`, otherwise the outer line (or the
  weaker of two inner ones) is dropped: guard rails, gores of diverging ramps and strays never
  make lanes. Boundaries that appear or end are followed back (forward) to where the lane
  between them and their neighbour has zero width (`max_taper_length_m`), so an added lane
  grows from zero; lines that only start late or end early near the ends of the drive (not yet
  or no longer observed) are carried to the ends at a constant offset from a neighbour. Two
  rounds, so extensions count as measured lines. Sections are stretches with a constant
  boundary set; shorter than `min_section_length_m` they join a neighbour.
- Entry and exit lanes that end or begin in a taper (`_taper_lanes`): a straight marking line that
  converges onto (diverges from) the carriageway's right edge at a steady angle never has a stable lane
  beside it, so the structure drops it; it is found again from the marking points beyond the edge (a
  windowed Hough vote, then least squares) and becomes a lane from where it is first (last) seen, at
  the width measured there, to where its width reaches zero (a section boundary at both ends), when it
  is long enough, straight, seen close to the edge and never farther out than a lane width, and the
  edge goes on as the outermost line past the meeting point (`taper_*` in `LanesConfig`). Its points
  are kept out of the edge's fit (the marking chains often join a converging line to the edge, which
  then bends towards it). Right-hand traffic: a lane narrowing to zero in the ego's direction is
  "entry", one widening from zero "exit" (`LaneSection.lane_types`); the other lanes are "driving"
  (an added lane that grows from zero and goes on cannot be told from an exit lane by its markings).
- Beyond the paper: solid/broken from the painted runs along s (length-weighted median run above
  `solid_min_run_m` = solid; dash and gap are medians of runs and gaps), and the marking width
  from the spread of the points across the fitted curve, unmixing the paint (uniform) from the
  noise (Gaussian) with two quantile ranges.
- Two directions separated only by paint (LaneSection.divider_id): a solid line with lanes on
  both sides over at least `divider_min_length_m`, never crossed by the ego and with the ego on
  the side of its travel direction under right-hand traffic (see `_mark_dividers`); a broken
  line only when the ego drove both ways beside it. The opposite lanes are exported only where
  their outermost line is a solid edge line (else only the ego's direction, with a warning). The
  trajectory only tells the side; it never connects markings or counts lanes. Carriageways split
  by a physical median (above) keep only the ego's one and get no divider.
- Boundary ids run left to right by median offset; `Candidate.superline` is that id (-1 for
  candidates whose line was ignored).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.linalg import solveh_banded
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree
from scipy.stats import norm

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import MARK_TYPES, Boundary, Candidate, GeoOrigin, LaneModel, LaneSection, MarkingCloud
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import write_text

FORMAT = "lidar2xodr.lanes/1"
_CHUNK = 20000
_ABSENT_RUN = 20  # stations (m) a line must be seen to be absent before it is no longer carried
_ALONG_SLOPE = 0.1  # lines joined across a gap run along the road there (within ~6 deg of the frame)
_LINE_FRAME_GAIN = 1.5  # the longest line replaces the first frame only when this much more paint runs along it
_FORK_BACK = (20, 60)  # stations before a fork whose offset to the neighbour a continuing line keeps through it
_HOP_RADIUS_M = 500.0  # tightest curve a step beside another is allowed to follow (motorway minimum ~ 700 m)


# --------------------------------------------------------------------------------------------
# relative lookups


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


# --------------------------------------------------------------------------------------------
# global lookup -> superlines


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


# --------------------------------------------------------------------------------------------
# frame (road axis with stations) and smoothing


class Frame:
    """A polyline with stations s (arc length), unit tangents and left normals; projects points."""

    def __init__(self, xy: np.ndarray, step: float) -> None:
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-9])
        xy = xy[keep]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        n = max(int(math.floor(arc[-1] / step)) + 1, 2)
        self.s = np.arange(n) * step
        self.xy = np.stack([np.interp(self.s, arc, xy[:, 0]), np.interp(self.s, arc, xy[:, 1])], axis=1)
        tan = np.gradient(self.xy, axis=0)
        self.tangent = tan / np.maximum(np.linalg.norm(tan, axis=1), 1e-12)[:, None]
        self.normal = np.stack([-self.tangent[:, 1], self.tangent[:, 0]], axis=1)
        self._tree = cKDTree(self.xy)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Station, signed offset (left positive) and whether the foot lies inside the frame."""
        _, k = self._tree.query(xy)
        best_s = np.zeros(len(xy))
        best_t = np.zeros(len(xy))
        best_d = np.full(len(xy), np.inf)
        inside = np.zeros(len(xy), dtype=bool)
        last = len(self.s) - 1
        for j0 in (k - 1, k):
            j0 = np.clip(j0, 0, last - 1)
            a, b = self.xy[j0], self.xy[j0 + 1]
            ab = b - a
            ln2 = np.einsum("ij,ij->i", ab, ab)
            f = np.einsum("ij,ij->i", xy - a, ab) / ln2
            fc = np.clip(f, 0.0, 1.0)
            foot = a + fc[:, None] * ab
            d = np.linalg.norm(xy - foot, axis=1)
            nrm = np.stack([-ab[:, 1], ab[:, 0]], axis=1) / np.sqrt(ln2)[:, None]
            t = np.einsum("ij,ij->i", xy - foot, nrm)
            better = d < best_d
            best_d = np.where(better, d, best_d)
            best_s = np.where(better, self.s[j0] + fc * np.sqrt(ln2), best_s)
            best_t = np.where(better, t, best_t)
            ins = ((f >= 0) | (j0 > 0)) & ((f <= 1) | (j0 < last - 1))
            inside = np.where(better, ins, inside)
        return best_s, best_t, inside

    def point(self, t: np.ndarray) -> np.ndarray:
        """World x, y at every station with lateral offset t."""
        return self.xy + self.normal * t[:, None]


def _whittaker(y: np.ndarray, w: np.ndarray, lam: float) -> np.ndarray:
    """Weighted Whittaker smoother (second differences), banded solve."""
    n = len(y)
    if n < 4 or np.count_nonzero(w) < 2:
        mean = float(np.sum(w * y) / max(np.sum(w), 1e-12))
        return np.full(n, mean)
    ab = np.zeros((3, n))
    main = np.full(n, 6.0)
    main[[0, -1]] = 1.0
    main[[1, -2]] = 5.0
    off1 = np.full(n - 1, -4.0)
    off1[[0, -1]] = -2.0
    ab[0, 2:] = lam
    ab[1, 1:] = lam * off1
    ab[2] = lam * main + w + 1e-9
    return solveh_banded(ab, w * y)


def _lam(cutoff_m: float, step: float) -> float:
    """Whittaker weight whose half-power wavelength is `cutoff_m`."""
    return (cutoff_m / (2.0 * math.pi * step)) ** 4


def _robust_curve(
    k: np.ndarray, t: np.ndarray, n: int, lam: float, iters: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust t(s) on stations: Whittaker over the points' span with Tukey weights; NaN outside.

    Short islands of points (at most 10 m: a dash, a blob) that sit off the curve fitted without
    them (local refit over +-80 m) are dropped: a blob in a gap or an occluded stretch would
    otherwise bend the line towards it. Returns the curve, the points' final weights and which
    stations are observed (3 points or more, in runs of 3 stations or more).
    """
    out = np.full(n, np.nan)
    w_pt = np.ones(len(t))
    observed = np.zeros(n, dtype=bool)
    if len(t) == 0:
        return out, w_pt, observed
    observed = np.bincount(k, minlength=n) >= 3
    for a, b in _runs(observed):
        if b - a < 3:
            observed[a:b] = False
    w_pt, scale = _tukey_fit(k, t, w_pt, n, lam, iters)
    has_points = np.bincount(k, minlength=n) > 0
    for a, b in _runs(has_points | (np.convolve(has_points, np.ones(3), "same") >= 2)):
        if b - a > 10:
            continue
        island = (k >= a - 2) & (k < b + 2)
        lo, hi = max(a - 80, 0), min(b + 80, n)
        near = (k >= lo) & (k < hi) & ~island & (w_pt > 0)
        if near.sum() < 10:
            continue
        z = _whittaker_points(k[near] - lo, t[near], w_pt[near], hi - lo, lam)
        span = np.flatnonzero(np.isfinite(z))
        pred = z[np.clip(k[island] - lo, span[0], span[-1])]
        if abs(float(np.median(t[island] - pred))) > max(0.2, 3.0 * scale):
            w_pt[island] = 0.0
            observed[a:b] = False
    _drop_end_islands(k, w_pt, observed)
    keep = w_pt > 0
    if keep.sum() < 2:
        return out, w_pt, observed
    lo, hi = int(k[keep].min()), int(k[keep].max())
    out[lo : hi + 1] = _whittaker_points(k[keep] - lo, t[keep], w_pt[keep], hi - lo + 1, lam)
    return out, w_pt, observed


def _refit_double(curve: np.ndarray, k: np.ndarray, t: np.ndarray, k_free: np.ndarray, t_free: np.ndarray, m: int,
                  lam: float, double: tuple[float, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A line's `_robust_curve` again where its points (k, t), with the unlabelled points (sorted by
    station) within `double[0]` of its curve, form a double line (`_fold_double_lines`): the second
    line's points lie farther from the first than points are labelled to it, so they are not the
    line's yet. None where there is no double line."""
    fin = np.flatnonzero(np.isfinite(curve))
    if double[0] <= 0.0 or len(fin) == 0:
        return None
    lo, hi = np.searchsorted(k_free, [fin[0], fin[-1] + 1])
    near = np.abs(t_free[lo:hi] - curve[k_free[lo:hi]]) <= double[0]
    k_all = np.concatenate([k, k_free[lo:hi][near]])
    t_all = np.concatenate([t, t_free[lo:hi][near]])
    t_fold, folded = _fold_double_lines(k_all, t_all, m, lam, double)
    if not folded.any():
        return None
    keep = (np.arange(len(k_all)) < len(k)) | folded
    return _robust_curve(k_all[keep], t_fold[keep], m, lam)


def _two_modes(r: np.ndarray) -> tuple[float, float, np.ndarray] | None:
    """Two 1D clusters of residuals r (split where the between-class variance is largest, Otsu's
    rule): their centres and membership, or None when they are not two resolved modes (each >= 15 %
    of the points, centres >= 4 sigma of either apart)."""
    n = len(r)
    if n < 20:
        return None
    srt = np.sort(r)
    cum = np.cumsum(srt)
    i = np.arange(1, n)
    lo_mean = cum[:-1] / i
    hi_mean = (cum[-1] - cum[:-1]) / (n - i)
    split = int(np.argmax(i * (n - i) * (hi_mean - lo_mean) ** 2))
    cut = 0.5 * (srt[split] + srt[split + 1])
    hi = r > cut
    share = float(hi.mean())
    if min(share, 1.0 - share) < 0.15:
        return None
    c0, c1 = float(r[~hi].mean()), float(r[hi].mean())
    if c1 - c0 < 4.0 * max(float(r[~hi].std()), float(r[hi].std())):
        return None
    return c0, c1, hi


def _fold_double_lines(k: np.ndarray, t: np.ndarray, n: int, lam: float, double: tuple[float, int]
                       ) -> tuple[np.ndarray, np.ndarray]:
    """One line's points with every double line folded onto its midpoint.

    A double line (two parallel lines, solid or broken, painted on one lane border: a no-overtaking
    centre line, a 2+1 road's divider) gives one boundary two modes of points a few decimetres apart;
    the robust fit would keep one of them, or hop between them. Per block of `double[1]` stations
    the points' offsets from a smooth trend through all of them are split into two clusters; blocks
    whose two clusters are resolved (`_two_modes`) and at most `double[0]` apart, in runs of three
    blocks or more with the same spacing (within `_DOUBLE_SPACING_SPREAD_M`: the two lines of a
    taper or a gore converge or spread),
    move each cluster by half the spacing onto the midpoint. Other points are returned unchanged.
    Returns the offsets and which points lie in a double line's blocks.
    """
    max_spacing, block = double
    folded = np.zeros(len(t), dtype=bool)
    if max_spacing <= 0.0 or len(t) < 40:
        return t, folded
    trend = _whittaker_points(k, t, np.ones(len(t)), n, 256.0 * lam)
    r = t - trend[k]
    blocks = k // block
    found: dict[int, tuple[float, float, np.ndarray, np.ndarray]] = {}
    for b in np.unique(blocks):
        idx = np.flatnonzero(blocks == b)
        modes = _two_modes(r[idx])
        if modes is not None and modes[1] - modes[0] <= max_spacing:
            found[int(b)] = (modes[0], modes[1], idx, modes[2])
    if not found:
        return t, folded
    out = t.copy()
    keys = sorted(found)
    runs, cur = [], [keys[0]]
    for b in keys[1:]:
        if b == cur[-1] + 1:
            cur.append(b)
        else:
            runs.append(cur)
            cur = [b]
    runs.append(cur)
    for run in runs:
        spacing = np.array([found[b][1] - found[b][0] for b in run])
        if len(run) < 3 or np.ptp(spacing) > _DOUBLE_SPACING_SPREAD_M:
            continue
        for b in run:
            lo, hi_c, idx, hi = found[b]
            mid = 0.5 * (lo + hi_c)
            out[idx] = t[idx] - np.where(hi, hi_c - mid, lo - mid)
            folded[idx] = True
    return out, folded


def _drop_end_islands(k: np.ndarray, w_pt: np.ndarray, observed: np.ndarray) -> None:
    """Points of a line's first or last piece, when that piece spans fewer than `_ABSENT_RUN`
    stations and lies `_ABSENT_RUN` stations or more from the rest of the line (pieces: stations
    with points, joined across shorter gaps), get weight 0 when the rest of the line next to the gap
    (its `2 * _ABSENT_RUN` stations) is solid (points on 80 % of them) and the piece holds fewer
    than half as many points per station as that rest: a solid line that ended is not carried on
    across the gap by a blob or a diverging ramp's paint beyond it (an exit lane was carried into the
    junction after it). A broken line's end piece is its next dash after a missed one, and a dense
    piece is the line itself beyond an occlusion: both stay."""
    for _ in range(2):
        has = np.zeros(len(observed), dtype=bool)
        has[k[w_pt > 0]] = True
        occupied = np.flatnonzero(has)
        if len(occupied) < 2:
            return
        cuts = np.flatnonzero(np.diff(occupied) >= _ABSENT_RUN)
        if len(cuts) == 0:
            return
        reach = 2 * _ABSENT_RUN
        first = (int(occupied[0]), int(occupied[cuts[0]]) + 1, int(occupied[cuts[0] + 1]))
        last = (int(occupied[cuts[-1] + 1]), int(occupied[-1]) + 1, int(occupied[cuts[-1]]) + 1 - reach)
        for a, b, rest in (first, last):
            lo = max(rest, 0)
            window = has[lo : rest + reach]
            if b - a >= _ABSENT_RUN or len(window) == 0 or window.mean() < 0.8:
                continue
            piece = (k >= a) & (k < b) & (w_pt > 0)
            near = (k >= lo) & (k < rest + reach) & (w_pt > 0)
            if piece.sum() / has[a:b].sum() < 0.5 * near.sum() / window.sum():
                w_pt[piece] = 0.0
                observed[a:b] = False


def _whittaker_points(k: np.ndarray, t: np.ndarray, w: np.ndarray, m: int, lam: float) -> np.ndarray:
    """Whittaker curve through weighted points binned on stations 0..m-1 (NaN outside their span)."""
    out = np.full(m, np.nan)
    lo, hi = int(k.min()), int(k.max())
    kk = k - lo
    sw = np.bincount(kk, w, hi - lo + 1)
    st = np.bincount(kk, w * t, hi - lo + 1)
    out[lo : hi + 1] = _whittaker(np.where(sw > 0, st / np.maximum(sw, 1e-12), 0.0), sw, lam)
    return out


def _tukey_fit(
    k: np.ndarray, t: np.ndarray, w_pt: np.ndarray, n: int, lam: float, iters: int
) -> tuple[np.ndarray, float]:
    """Iteratively reweighted Whittaker fit: Tukey biweights of the points and the residual scale."""
    scale = 0.03
    for _ in range(iters):
        z = _whittaker_points(k, t, w_pt, n, lam)
        r = t - z[k]
        scale = max(1.4826 * float(np.median(np.abs(r))), 0.03)
        u = r / (4.685 * scale)
        w_pt = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
    return w_pt, scale


def _order_along(points: np.ndarray) -> np.ndarray:
    """Geodesic position along a band of points (double sweep over a k-nearest-neighbour graph)."""
    n = len(points)
    if n < 3:
        return np.arange(n, dtype=np.float64)
    cell = np.floor(points / 2.0).astype(np.int64)
    _, rep, inv = np.unique(cell, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    pts = points[rep]
    m = len(pts)
    k = min(9, m)
    tree = cKDTree(pts)
    d, j = tree.query(pts, k)
    rows = np.repeat(np.arange(m), k - 1)
    graph = coo_matrix((d[:, 1:].ravel() + 1e-6, (rows, j[:, 1:].ravel())), shape=(m, m)).tocsr()
    ncomp, comp = connected_components(graph, directed=False)
    if ncomp > 1:
        extra_r, extra_c, extra_w = [], [], []
        sizes = np.bincount(comp)
        main = int(np.argmax(sizes))
        joined = comp == main
        while not joined.all():
            t_in = cKDTree(pts[joined])
            idx_out = np.flatnonzero(~joined)
            dd, jj = t_in.query(pts[idx_out])
            q = int(np.argmin(dd))
            a, b = int(idx_out[q]), int(np.flatnonzero(joined)[jj[q]])
            extra_r.append(a)
            extra_c.append(b)
            extra_w.append(float(dd[q]) + 1e-6)
            joined |= comp == comp[a]
        graph = graph + coo_matrix((extra_w, (extra_r, extra_c)), shape=(m, m)).tocsr()
    d0 = dijkstra(graph, directed=False, indices=0)
    a = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
    da = dijkstra(graph, directed=False, indices=a)
    b = int(np.argmax(np.where(np.isfinite(da), da, -1)))
    if np.linalg.norm(pts[b, :2]) < np.linalg.norm(pts[a, :2]):
        da = dijkstra(graph, directed=False, indices=b)
    return da[inv]


def _line_frame(pieces: list[Candidate], cfg: LanesConfig) -> Frame | None:
    """Road axis along the longest marking line (a candidate piece), extended 40 m at both ends.

    The first frame from the cross-sections' middles bends where segments of different lines see
    different far lines (a verge's clutter on one side, the other carriageway on the other: on the
    130 m aiMotive drive the middles fall into two groups 5 m apart and the lanes stage found no
    road). `build_lane_model` takes this axis instead only where the first frame is evidently poor: the
    line spans the road (90 % of the first frame's length) and `_LINE_FRAME_GAIN` times as much marking
    length runs along it (`_parallel_length`; measured: aiMotive 1.26 and 1.86 with two extractions,
    the first frame working in the first case only; simple_highway 1.01, where the line axis, an edge's
    raw cluster centres, made the map worse: boundaries 0.047 -> 0.264 m). Otherwise it is the second
    axis tried, where the first frame finds no stretch with two lines a lane apart (the aiMotive
    sample with one middle frame unreadable: the first frame's middles bend by 1.5 m, the dashes of
    the broken line no longer join, and the build ended in exit 2); a drive that builds on the first
    frame is not changed by it.
    """
    best, length = None, 0.0
    for c in pieces:
        xy = np.asarray(c.centers, dtype=np.float64)[:, :2]
        arc = float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))) if len(xy) > 1 else 0.0
        if len(xy) >= 3 and arc > length:
            best, length = xy, arc
    if best is None:
        return None
    ext = np.arange(2.0, 40.0 + 1e-9, 2.0)[:, None]
    head_dir = (best[0] - best[1]) / np.linalg.norm(best[0] - best[1])
    tail_dir = (best[-1] - best[-2]) / np.linalg.norm(best[-1] - best[-2])
    return Frame(np.vstack([best[0] + ext[::-1] * head_dir, best, best[-1] + ext * tail_dir]), cfg.station_step_m)


def _parallel_length(frame: Frame, segs: Segments, cfg: LanesConfig) -> float:
    """Length of the segments that run along the frame (within 3 deg, at most `max_normal_length_m` off it):
    how well a candidate road axis follows the markings."""
    mid = 0.5 * (segs.p0[:, :2] + segs.p1[:, :2])
    s, t, inside = frame.project(mid)
    k = np.clip(np.rint(s / (frame.s[1] - frame.s[0])).astype(np.int64), 0, len(frame.s) - 1)
    d = segs.p1[:, :2] - segs.p0[:, :2]
    length = np.linalg.norm(d, axis=1)
    along = np.abs(np.einsum("ij,ij->i", d, frame.tangent[k])) >= math.cos(math.radians(3.0)) * length
    return float(np.sum(length[inside & along & (np.abs(t) <= cfg.max_normal_length_m)]))


def _first_frame(segs: Segments, lookups: Lookups, cfg: LanesConfig) -> Frame:
    """Road axis from the middle of each normal's cross-section, ordered and smoothed."""
    origin = 0.5 * (segs.p0 + segs.p1)
    n_seg = len(origin)
    lo = np.zeros(n_seg)
    hi = np.zeros(n_seg)
    if len(lookups.dist):
        np.minimum.at(lo, lookups.seg_a, lookups.dist)
        np.maximum.at(hi, lookups.seg_a, lookups.dist)
    d = segs.p1[:, :2] - segs.p0[:, :2]
    tangent = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    mid = origin.copy()
    mid[:, :2] += normal * (0.5 * (lo + hi))[:, None]
    seen = np.bincount(lookups.seg_a, minlength=n_seg) > 0
    if seen.sum() >= 10:
        # a segment no normal links to any line (a chain across lines, clutter where the ego turned) is no road
        mid = mid[seen]
    u = _order_along(mid * np.array([1.0, 1.0, 3.0]))
    bins = np.floor(u / 10.0).astype(np.int64)
    uniq, inv = np.unique(bins, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv)
    xy = np.stack([_group_median(mid[:, k], inv, len(uniq)) for k in range(2)], axis=1)
    uu = np.bincount(inv, u) / cnt
    fine = np.arange(uu[0], uu[-1] + 1e-9, 2.0) if uu[-1] > uu[0] else uu
    lam = _lam(2.0 * cfg.reference_smoothing_m, 2.0)
    path = np.stack(
        [_whittaker(np.interp(fine, uu, xy[:, k]), np.ones(len(fine)), lam) for k in range(2)], axis=1
    )
    if len(path) < 3:
        raise InputError("marking cloud", "the markings cover less than a few metres of road")
    ext = np.arange(2.0, 40.0 + 1e-9, 2.0)[:, None]
    head = path[0] - ext[::-1] * (path[1] - path[0]) / np.linalg.norm(path[1] - path[0])
    tail = path[-1] + ext * (path[-1] - path[-2]) / np.linalg.norm(path[-1] - path[-2])
    path = np.vstack([head, path, tail])
    return Frame(path, cfg.station_step_m)


# --------------------------------------------------------------------------------------------
# lane structure per station


@dataclass
class _Structure:
    on: np.ndarray  # (B, M) boundary kept at station
    t: np.ndarray  # (B, M) offsets including taper extensions


def _lane_structure(
    t_fit: np.ndarray,
    support: np.ndarray,
    solid: np.ndarray,
    t_ego: np.ndarray | None,
    step: float,
    w_lane: float,
    cfg: LanesConfig,
    seen: _Observed | None = None,
) -> _Structure:
    """Which boundaries form the carriageway at each station, with tapers followed to zero width.

    `seen` (where marking points were measured, see `_Observed`) keeps lines from being carried
    towards the drive's ends where they were seen to be absent.

    Two rounds: the extensions found in the first (tapers, lines carried to the drive's ends) are
    measured lines in the second, which decides presence again from scratch, so a line dropped
    only because its neighbour had not been carried yet comes back.
    """
    rank = np.argsort(np.argsort(-support, kind="stable"), kind="stable")
    min_run = max(int(round(cfg.min_section_length_m / step)), 1)
    t = t_fit.copy()
    on = np.isfinite(t)
    for _ in range(2):
        on = np.isfinite(t)
        _drop_duplicates(t, on, rank, cfg.same_line_tolerance_m, min_run)
        for _ in range(3):
            on = _choose_carriageway(t, on, t_ego, solid, support, cfg)
            on, _ = _check_adjacency(t, on, rank, step, cfg)
            on = _clean_runs(on, min_run)
        t_ext, on = _follow_tapers(t, on, step, w_lane, cfg, seen, solid)
        t = np.where(on, t_ext, t)
    return _Structure(on, np.where(on, t, np.nan))


def _drop_duplicates(t: np.ndarray, on: np.ndarray, rank: np.ndarray, tol: float, min_run: int) -> None:
    """Where two lines run closer than `tol`, keep one: the one that goes on where the other ends
    (a lane closing onto its neighbour), else the one with more support."""
    b_n, m = t.shape
    finite = np.isfinite(t)
    for i in range(b_n):
        for j in range(i + 1, b_n):
            close = on[i] & on[j] & (np.abs(t[i] - t[j]) < tol)
            for c0, c1 in _runs(close):
                bi, ai = _finite_reach(finite[i], c0, c1)
                bj, aj = _finite_reach(finite[j], c0, c1)
                ends_i = (ai < min_run <= aj) or (bi < min_run <= bj)
                ends_j = (aj < min_run <= ai) or (bj < min_run <= bi)
                if ends_i != ends_j:
                    victim = i if ends_i else j
                else:
                    victim = i if rank[i] > rank[j] else j
                on[victim, c0:c1] = False


def _finite_reach(finite: np.ndarray, c0: int, c1: int) -> tuple[int, int]:
    """How far a line goes on (measured) before station c0 and after station c1."""
    gaps_before = np.flatnonzero(~finite[:c0])
    gaps_after = np.flatnonzero(~finite[c1:])
    before = c0 - 1 - (gaps_before[-1] if len(gaps_before) else -1)
    after = gaps_after[0] if len(gaps_after) else len(finite) - c1
    return int(before), int(after)


def _sorted_columns(t: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per station: boundary indices ordered left to right (present first) and their offsets."""
    key = np.where(on, -t, np.inf)
    order = np.argsort(key, axis=0, kind="stable")
    return order, np.take_along_axis(np.where(on, t, np.nan), order, axis=0)


def _choose_carriageway(
    t: np.ndarray,
    on: np.ndarray,
    t_ego: np.ndarray | None,
    solid: np.ndarray,
    support: np.ndarray,
    cfg: LanesConfig,
) -> np.ndarray:
    """Split into carriageways and keep the one with the ego (else the most lines, then most points).

    Splits: spacings above `carriageway_gap_m`; steady spacings above `max_lane_width_m` between
    the outermost two lines (inside, or while a taper opens, such a space holds a lane whose
    line was not seen); and a
    space between two solid lines that both have lines beyond them (the median between two
    carriageways: each edge line has its own lanes on its other side).
    """
    b_n, m = t.shape
    if b_n == 0 or m == 0:
        return np.zeros_like(on)
    order, ts = _sorted_columns(t, on)
    present = np.isfinite(ts)
    gap = ts[:-1] - ts[1:]
    both_solid = solid[order[:-1]] & solid[order[1:]]
    beyond = np.vstack([np.zeros((1, m), dtype=bool), present[:-2]]) & np.vstack(
        [present[2:], np.zeros((1, m), dtype=bool)]
    )
    median = both_solid & beyond & present[:-1] & present[1:]
    none = np.zeros((1, m), dtype=bool)
    outer = ~np.vstack([none, present[:-2]]) | ~np.vstack([present[2:], none])
    cols = np.arange(m)
    ahead, back = np.minimum(cols + 5, m - 1), np.maximum(cols - 5, 0)
    width_then = t[order[:-1], ahead] - t[order[1:], ahead]
    width_before = t[order[:-1], back] - t[order[1:], back]
    steady = np.abs(width_then - width_before) < cfg.stable_lane_slope * (ahead - back) * 1.0
    wide_edge = outer & (gap > cfg.max_lane_width_m) & steady
    split = np.vstack([none, ~(gap <= cfg.carriageway_gap_m) | median | wide_edge])
    group = np.cumsum(split, axis=0)
    n_groups = group.max() + 1
    score = np.zeros((n_groups, m))
    weight = support[order] / max(float(support.max()), 1e-9)
    for g in range(n_groups):
        sel = present & (group == g)
        score[g] = sel.sum(axis=0) + 1e-3 * np.where(sel, weight, 0.0).sum(axis=0)
    choice = np.argmax(score, axis=0)
    if t_ego is not None:
        for g in range(n_groups):
            sel = present & (group == g)
            top = np.max(np.where(sel, ts, -np.inf), axis=0)
            bot = np.min(np.where(sel, ts, np.inf), axis=0)
            holds = (t_ego <= top + 0.5) & (t_ego >= bot - 0.5) & np.isfinite(t_ego)
            choice = np.where(holds, g, choice)
    keep_sorted = present & (group == choice[None, :])
    keep = np.zeros_like(on)
    np.put_along_axis(keep, order, keep_sorted, axis=0)
    return keep & on


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of every run of True."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=False))


def _check_adjacency(
    t: np.ndarray, on: np.ndarray, rank: np.ndarray, step: float, cfg: LanesConfig
) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Every pair of neighbouring lines must hold a stable lane somewhere along their adjacency."""
    b_n, m = t.shape
    order, ts = _sorted_columns(t, on)
    need = max(int(round(cfg.min_section_length_m / step)), 1)
    upper, lower = order[:-1], order[1:]
    valid = np.isfinite(ts[:-1]) & np.isfinite(ts[1:])
    width = ts[:-1] - ts[1:]
    key = np.where(valid, upper * b_n + lower, -1)
    stable_len: dict[int, int] = {}
    for key_value in np.unique(key[valid]):
        at = (key == key_value).any(axis=0)
        w = np.where(key == key_value, width, 0.0).sum(axis=0)
        slope = np.abs(np.gradient(w)) / step
        good = (
            at & (w >= cfg.min_lane_width_m) & (w <= cfg.max_lane_width_m) & (slope < cfg.stable_lane_slope)
        )
        stable_len[int(key_value)] = max((e - s for s, e in _runs(good)), default=0)
    count = on.sum(axis=0)
    on = on.copy()
    dropped: list[tuple[int, int, int]] = []
    for key_value, length in sorted(stable_len.items()):
        if length >= need:
            continue
        a, b = divmod(key_value, b_n)
        rows, cols = np.nonzero(key == key_value)
        first_row = np.all(rows == 0)
        last_row = np.all(count[cols] == rows + 2)
        if first_row and not last_row:
            victim = a
        elif last_row and not first_row:
            victim = b
        else:
            victim = a if rank[a] > rank[b] else b
        on[victim, cols] = False
        dropped.append((int(victim), int(cols.min()), int(cols.max())))
    return on, dropped


def _clean_runs(on: np.ndarray, min_run: int) -> np.ndarray:
    """Drop presence runs shorter than `min_run` stations."""
    out = on.copy()
    for b in range(len(on)):
        for s, e in _runs(on[b]):
            if e - s < min_run:
                out[b, s:e] = False
    return out


def _follow_tapers(
    t: np.ndarray, on: np.ndarray, step: float, w_lane: float, cfg: LanesConfig, seen: _Observed | None = None,
    solid: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Extend boundaries that appear or end back (forward) to where their new lane has zero width."""
    t = t.copy()
    on = on.copy()
    b_n, m = t.shape
    reach = int(round(cfg.max_taper_length_m / step))
    min_run = max(int(round(cfg.min_section_length_m / step)), 1)
    probe = max(int(round(40.0 / step)), 2)
    road = np.flatnonzero(on.sum(axis=0) >= 2)
    if len(road) == 0:
        return t, on
    for _ in range(3):
        before = on.sum()
        for b in range(b_n):
            for s, e in _runs(on[b]):
                for start, edge, inward in ((s, s, 1), (e - 1, e, -1)):
                    if (inward == 1 and edge == 0) or (inward == -1 and edge == m):
                        continue
                    if not _extend(t, on, b, start, inward, probe, reach, w_lane) \
                            and not (e - s >= min_run
                                     and _open_beside_edge(t, on, b, start, inward, reach, cfg.min_lane_width_m)):
                        end = road[0] if inward == 1 else road[-1]
                        if abs(start - end) <= reach:
                            _hold_to(t, on, b, start, end, seen if solid is not None and solid[b] else None)
        if on.sum() == before:
            break
    return t, on


def _hold_to(
    t: np.ndarray, on: np.ndarray, b: int, start: int, end: int, seen: _Observed | None = None
) -> None:
    """Carry boundary b from `start` to the road's end `end` at a constant offset from a neighbour.

    The neighbour is the nearest of those that reach furthest towards the end. Lines start late or
    end early near the ends of a drive because they were not yet (or no longer) observed, not
    because the lane count changes. A line that ends on another one (within 1 m: a lane that
    closed) is not carried. The outermost line (none kept beyond it on that side), when it is solid
    (`seen` given), is not carried past the first stretch of `_ABSENT_RUN` stations where marking
    points were measured more than 1 m beyond it but none where it would run (those would be the
    line itself, only not fitted there; a shorter stretch can be a patch of clutter): the sensor
    saw that far there, and a solid line would have been seen (a broken line's far dashes are
    missed where a solid line beyond is still seen), so the line was absent, not unobserved (a
    lane that appears at full width near the start of a short drive, a ramp joining). Inner lines
    are carried as before: a broken line's last dash may end a gap early.
    """
    span = np.arange(start - 1, end - 1, -1) if end < start else np.arange(start + 1, end + 1)
    others = [j for j in range(len(t)) if j != b and on[j, start]]
    if not others or len(span) == 0:
        return
    nb = max(others, key=lambda j: (round(float(on[j, span].mean()), 1), -abs(t[j, start] - t[b, start])))
    offset = t[b, start] - t[nb, start]
    if min(abs(t[j, start] - t[b, start]) for j in others) < 1.0:
        return
    if seen is not None and not any(np.sign(offset) * (t[j, start] - t[b, start]) > 0 for j in others):
        carried = t[nb, span] + offset
        absent = seen.beyond(span, carried, float(np.sign(offset))) & ~seen.near(span, carried)
        runs = [a for a, e in _runs(absent) if e - a >= _ABSENT_RUN]
        span = span[: runs[0] if runs else len(span)]
    span = span[on[nb, span] & ~on[b, span]]
    t[b, span] = t[nb, span] + offset
    on[b, span] = True


def _open_beside_edge(t: np.ndarray, on: np.ndarray, b: int, start: int, inward: int, reach: int,
                      min_width: float) -> bool:
    """Carry line b back (forward) at its offset to its inner neighbour p while the lane beyond it opens
    (closes) along the carriageway's edge e (`_follow_tapers` asks only for a line kept over at least
    `min_section_length_m`: a line seen for a few metres at a drive's end shows no lane).

    An entry or exit lane whose line is painted only where the lane has its full width: the line
    starts with a whole lane between it and the edge, and before its start the edge comes in towards
    p until the edge is one lane (b's) from p. The edge's course, not b's paint, shows the taper, so
    `_extend` (which measures the taper along b) does not see it. Only when e is the outermost line,
    the lane beyond b is at least `min_width` wide where b starts, and the edge's spacing to p shrinks
    without a jump to b's spacing within `reach` stations (the taper's far end, where b meets e),
    while p keeps its spacing to every other line seen there (it is e that moves, not p: on a 2+1
    road the centre line moves across while the edges stay, and a new lane line beside the edge is
    not carried along the centre line); and only when this holds on one side of b."""
    rows = [j for j in range(len(t)) if j != b and on[j, start]]
    tb = t[b, start]
    found: list[tuple[int, int, float, float, list[int]]] = []
    for d in (1.0, -1.0):
        beyond = [j for j in rows if d * (t[j, start] - tb) > 0]
        inner = [j for j in rows if d * (t[j, start] - tb) < 0]
        if len(beyond) != 1 or not inner:
            continue
        e = beyond[0]
        p = min(inner, key=lambda j: abs(t[j, start] - tb))
        g_in, g_out = d * (tb - t[p, start]), d * (t[e, start] - tb)
        if g_out < min_width:
            continue
        walked: list[int] = []
        previous = g_out
        closed = False
        for i in range(1, reach + 1):
            k = start - inward * i
            if not 0 <= k < t.shape[1] or on[b, k] or not (on[e, k] and on[p, k]):
                break
            width = d * (t[e, k] - t[p, k]) - g_in
            if width > previous + 0.1 or (i == 1 and abs(width - g_out) > 0.5):
                break
            walked.append(k)
            if width <= 0.05:
                closed = True
                break
            previous = min(previous, width)
        if not closed:
            continue
        others = [q for q in rows if q not in (e, p) and on[q, walked].all()]
        moved = [float(np.max(np.abs((t[p, walked] - t[q, walked]) - (t[p, start] - t[q, start])))) for q in others]
        if others and max(moved) < 0.2 * g_out:
            found.append((e, p, d, g_in, walked))
    if len(found) != 1:
        return False
    e, p, d, g_in, walked = found[0]
    for k in walked[:-1]:
        t[b, k] = t[p, k] + d * g_in
    t[b, walked[-1]] = t[e, walked[-1]]
    on[b, walked] = True
    return True


def _extend(
    t: np.ndarray, on: np.ndarray, b: int, start: int, inward: int, probe: int, reach: int, w_lane: float
) -> bool:
    """Follow boundary b from station `start` outwards (against `inward`) while its new lane closes."""
    window = np.arange(start, start + inward * probe, inward)
    window = window[(window >= 0) & (window < t.shape[1])]
    tb = t[b, start]
    others = [j for j in range(len(t)) if j != b and on[j, start]]
    left = [j for j in others if t[j, start] > tb]
    right = [j for j in others if t[j, start] < tb]
    nb_left = min(left, key=lambda j: t[j, start] - tb) if left else None
    nb_right = max(right, key=lambda j: t[j, start] - tb) if right else None
    best = None
    for grow, other in ((nb_left, nb_right), (nb_right, nb_left)):
        if grow is None:
            continue
        w = np.abs(t[grow, window] - t[b, window])
        ok = np.isfinite(w) & on[grow, window] & on[b, window]
        if ok.sum() < 2:
            continue
        x = (window[ok] - start) * inward
        slope = np.polyfit(x, w[ok], 1)[0]
        w0 = abs(t[grow, start] - tb)
        if slope <= 1e-4 or w0 > 0.8 * w_lane:
            continue
        if best is None or w0 < best[0]:
            best = (w0, grow, other, slope)
    if best is None:
        return False
    w0, grow, other, slope = best
    sign = 1.0 if t[grow, start] > tb else -1.0
    previous = w0
    for i in range(1, reach + 1):
        k = start - inward * i
        if k < 0 or k >= t.shape[1] or on[b, k] or not np.isfinite(t[grow, k]):
            return True
        if other is not None and np.isfinite(t[other, k]):
            tk = t[other, k] + (tb - t[other, start])
        elif other is None:
            tk = t[grow, k] - sign * max(w0 - slope * i, 0.0)
        else:
            return True
        width = sign * (t[grow, k] - tk)
        if width <= 0.05 or (width < 0.5 and width >= previous):
            t[b, k] = t[grow, k]
            on[b, k] = True
            return True
        previous = width
        t[b, k] = tk
        on[b, k] = True
    return True


# --------------------------------------------------------------------------------------------
# entry and exit lanes that end or begin in a taper


LANE_TYPES = ("driving", "entry", "exit")
_DOUBLE_SPACING_SPREAD_M = 0.1  # a double line's two lines keep their spacing within this over its blocks
_SLOPE_STEP = 0.005  # slope grid of the taper line search: 0.25 m over a 50 m window


@dataclass
class _Taper:
    """A lane between the carriageway's edge (row `outer`) and a straight line converging onto it.

    `t` is the line's offset at every station (NaN outside the lane's stations k0..k1, 0 width at the
    narrow end), `points` the marking points on it, `narrow_last` whether its width shrinks along s,
    `side` -1 for the right of the carriageway in s/t (+1 left), `first_width` its width at the wide
    end, where the line was first (last) seen.
    """

    row: int
    outer: int
    k0: int
    k1: int
    t: np.ndarray
    points: np.ndarray
    narrow_last: bool
    side: int
    first_width: float
    angle_deg: float


def _straight_lines(s: np.ndarray, w: np.ndarray, k: np.ndarray, step: float,
                    cfg: LanesConfig) -> list[tuple[float, float, float, float]]:
    """Seeds (a, b, s_lo, s_hi) of straight lines w = a + b s with a taper's slope in the points (s, w).

    Per window of 2 x `taper_min_length_m` (half overlapping): a Hough vote over a grid of slopes
    (`stable_lane_slope` to `taper_max_slope`, both signs) and intercept bands `taper_line_tolerance_m`
    wide (two grids half a band apart), where every station votes once per band (a blob or a line
    crossing the road at one station does not outvote a line along it). A window's best band is a
    seed when it holds points at a quarter of `taper_min_length_m` of stations or more.
    """
    tol = cfg.taper_line_tolerance_m
    half = np.arange(cfg.stable_lane_slope, cfg.taper_max_slope + 1e-9, _SLOPE_STEP)
    slopes = np.concatenate([-half[::-1], half])
    window = 2.0 * cfg.taper_min_length_m
    near = w <= cfg.max_lane_width_m + tol
    if not near.any():
        return []
    cell = np.unique(np.stack([k[near], np.floor(w[near] / 0.1).astype(np.int64)], axis=1), axis=0)
    kc, wc = cell[:, 0], (cell[:, 1] + 0.5) * 0.1
    sc = kc * step
    need = 0.25 * cfg.taper_min_length_m / step
    n_k = int(kc.max()) + 1
    seeds = []
    for lo in np.arange(sc.min(), sc.max() + 1e-9, 0.5 * window):
        m = (sc >= lo) & (sc < lo + window)
        if len(np.unique(kc[m])) < need:
            continue
        mid = lo + 0.5 * window
        c = wc[m][None, :] - slopes[:, None] * (sc[m][None, :] - mid)
        best = (0, 0.0, 0.0)
        for shift in (0.0, 0.5):
            band = np.floor(c / tol + shift).astype(np.int64)
            b0 = int(band.min())
            n_band = int(band.max()) - b0 + 1
            code = np.arange(len(slopes))[:, None] * n_band + (band - b0)
            votes = np.bincount(np.unique(code * n_k + kc[m][None, :]) // n_k)
            j = int(np.argmax(votes))
            if votes[j] > best[0]:
                i_slope, i_band = divmod(j, n_band)
                best = (int(votes[j]), float(slopes[i_slope]), (i_band + b0 + 0.5 - shift) * tol)
        if best[0] >= need:
            seeds.append((best[2] - best[1] * mid, best[1], float(lo), float(lo + window)))
    return seeds


def _line_run(s: np.ndarray, w: np.ndarray, k: np.ndarray, line: tuple[float, float], seed: tuple[float, float],
              step: float, cfg: LanesConfig) -> np.ndarray:
    """Indices of the points on the line (within `taper_line_tolerance_m`) in its stretch that overlaps
    the seed window most, stretches being split at gaps over `taper_max_gap_m` without points."""
    on = np.flatnonzero(np.abs(w - (line[0] + line[1] * s)) < cfg.taper_line_tolerance_m)
    if len(on) == 0:
        return on
    ks = np.unique(k[on])
    cut = np.flatnonzero(np.diff(ks) * step > cfg.taper_max_gap_m)
    firsts, lasts = ks[np.r_[0, cut + 1]], ks[np.r_[cut, len(ks) - 1]]
    inside = [np.sum((ks >= a) & (ks <= b) & (ks * step >= seed[0]) & (ks * step < seed[1]))
              for a, b in zip(firsts, lasts, strict=True)]
    j = int(np.argmax(inside))
    return on[(k[on] >= firsts[j]) & (k[on] <= lasts[j])]


def _taper_lanes(pts: _Points, structure: _Structure, side: int, step: float,
                 cfg: LanesConfig) -> tuple[list[_Taper], list[str]]:
    """Entry and exit lanes on the `side` of the carriageway from straight lines converging onto its edge.

    A marking line that runs at a steady angle onto the outermost kept line (or away from it) bounds a
    lane that ends (begins) where the two meet: a taper. Such a line never has a stable lane beside it,
    so the lane structure drops it; here it is found again from the marking points lying more than
    `assign_distance_m` beyond the edge (`_straight_lines`, then refitted by least squares on the points
    of its stretch until that stretch stops changing) and kept only when all of these hold:
    - points lie on it at stations spanning `taper_min_length_m`, its width changes by
      `stable_lane_slope` to `taper_max_slope` per metre and the points' RMS distance to it is at most
      half `taper_line_tolerance_m` (one consistent angle: clutter, posts and blobs are not straight);
    - it is seen within `taper_meet_width_m` of the edge (its meeting point, where the width reaches
      zero, is extrapolated from there) and nowhere farther out than `max_lane_width_m` (a ramp's edge
      goes on diverging beyond a lane width; a guard rail never comes that close at an angle);
    - the edge it meets is one line over the whole lane and goes on as the outermost line for
      `min_section_length_m` beyond the meeting point (or to the end of the road): no lane lies
      outside it there (where a ramp's edge meets the road at a gore, the ramp's lane goes on outside);
    - the lane, from where its line is first (last) seen to the meeting point, is at least
      `min_section_length_m` long (a shorter one could not be a lane section; a note says so).
    Its points are all those within `taper_line_tolerance_m` of the line on the lane's stations, the line
    taken both as a width from the edge and as a straight line in the frame's own offsets (an edge bent
    towards it, or a frame bent by such an edge, does not hide its points), also those close to the edge
    near the meeting point and up to `taper_meet_width_m` / slope beyond it (an edge bent by them puts
    the meeting point too far out): they are kept out of the edge's fit, which they would bend towards
    the line.
    The lane starts where its line is first seen (ends where last seen), at the width measured there:
    nothing tells what the unseen road before it holds. Its border is the fitted straight line, so the
    width falls linearly to exactly zero at the meeting station. Overlapping lanes: the one with points
    at most stations wins. Returns the tapers (rows not yet assigned) and notes.
    """
    on, t = structure.on, structure.t
    n_rows, m = on.shape
    valid = on.sum(axis=0) >= 2
    key = np.where(on, side * np.where(on, t, 0.0), -np.inf)
    outer_row = np.argmax(key, axis=0)
    edge = t[outer_row, np.arange(m)]
    k_all = pts.k
    use = pts.inside & valid[k_all]
    w_all = side * (pts.t - np.where(use, edge[k_all], 0.0))
    sel = np.flatnonzero(use & (w_all > cfg.assign_distance_m) & (w_all < 2.0 * cfg.max_lane_width_m))
    if len(sel) < 10:
        return [], []
    s, w, k = pts.s[sel], w_all[sel], k_all[sel]
    tol = cfg.taper_line_tolerance_m
    found: list[tuple[int, _Taper]] = []
    notes: list[str] = []
    seen_lines: set[tuple[int, int]] = set()
    for a, b, lo, hi in _straight_lines(s, w, k, step, cfg):
        run = _line_run(s, w, k, (a, b), (lo, hi), step, cfg)
        for _ in range(20):
            if len(run) < 3:
                break
            slope, icpt = np.polyfit(s[run], w[run], 1)
            again = _line_run(s, w, k, (float(icpt), float(slope)), (lo, hi), step, cfg)
            if np.array_equal(again, run):
                break
            run = again
        if len(run) < 3:
            continue
        slope, icpt = np.polyfit(s[run], w[run], 1)
        line = (float(icpt), float(slope))
        ks = np.unique(k[run])
        if (int(ks[0]), int(ks[-1])) in seen_lines:
            continue
        seen_lines.add((int(ks[0]), int(ks[-1])))
        a, b = line
        rms = float(np.sqrt(np.mean((w[run] - (a + b * s[run])) ** 2)))
        if (len(ks) * step < cfg.taper_min_length_m or not cfg.stable_lane_slope <= abs(b) <= cfg.taper_max_slope
                or rms > 0.5 * tol or float(w[run].max()) > cfg.max_lane_width_m + tol):
            continue
        narrow_last = b < 0
        k_near, k_far = (int(ks[-1]), int(ks[0])) if narrow_last else (int(ks[0]), int(ks[-1]))
        if a + b * k_near * step > cfg.taper_meet_width_m:
            continue
        k_meet = int(round(-a / b / step))
        if not 0 <= k_meet < m or not valid[k_meet]:
            continue
        k0, k1 = (k_far, k_meet) if narrow_last else (k_meet, k_far)
        rows = np.unique(outer_row[k0 : k1 + 1])
        if len(rows) != 1 or not valid[k0 : k1 + 1].all():
            continue
        clear = int(round(cfg.min_section_length_m / step))
        beyond = np.arange(k_meet + 1, k_meet + clear + 1) if narrow_last else np.arange(k_meet - clear, k_meet)
        beyond = beyond[(beyond >= 0) & (beyond < m)]
        beyond = beyond[valid[beyond]]
        if np.any(outer_row[beyond] != rows[0]):
            continue
        if (k1 - k0 + 1) * step < cfg.min_section_length_m:
            s_at = float(np.flatnonzero(valid)[0]) * step
            notes.append(f"a line converging onto the carriageway's edge on s {k0 * step - s_at:.0f}-"
                         f"{k1 * step - s_at:.0f} m makes no lane: shorter than {cfg.min_section_length_m:g} m")
            continue
        kk = np.arange(k0, k1 + 1)
        width = np.clip(a + b * kk * step, 0.0, None)
        width[kk == k_meet] = 0.0
        row_t = np.full(m, np.nan)
        row_t[kk] = edge[kk] + side * width
        in_frame = np.polyfit(s[run], pts.t[sel[run]], 1)
        line_w = a + b * pts.s
        on_line = (np.abs(pts.t - np.polyval(in_frame, pts.s)) < tol) | (
            use & (line_w > tol) & (np.abs(w_all - line_w) < tol))
        ext = int(round(cfg.taper_meet_width_m / abs(b) / step))
        lo_k, hi_k = (k0, k1 + ext) if narrow_last else (k0 - ext, k1)
        near = pts.inside & (pts.k >= lo_k) & (pts.k <= hi_k) & on_line
        taper = _Taper(-1, int(rows[0]), k0, k1, row_t, np.flatnonzero(near), narrow_last, side,
                       float(a + b * k_far * step), float(np.degrees(np.arctan(abs(b)))))
        found.append((len(ks), taper))
    kept: list[_Taper] = []
    for _, taper in sorted(found, key=lambda x: (-x[0], x[1].k0)):
        if all(taper.k1 < other.k0 or taper.k0 > other.k1 for other in kept):
            kept.append(taper)
    for i, taper in enumerate(sorted(kept, key=lambda x: x.k0)):
        taper.row = n_rows + i
    return sorted(kept, key=lambda x: x.k0), notes


def _add_tapers(fit: _Fit, structure: _Structure, label: np.ndarray, tapers: list[_Taper]) -> None:
    """Append each taper's line as a measured, kept boundary row and give it its points."""
    for taper in tapers:
        fit.t = np.vstack([fit.t, taper.t[None, :]])
        fit.support = np.append(fit.support, float(len(taper.points)))
        structure.on = np.vstack([structure.on, np.isfinite(taper.t)[None, :]])
        structure.t = np.vstack([structure.t, taper.t[None, :]])
        label[taper.points] = taper.row


def _travel_sign(frame: Frame, ego: np.ndarray | None) -> int:
    """+1 when the ego first travels along s on the frame (the kept carriageway is the one it drove
    first), -1 against; +1 without a trajectory.

    The stage turns a frame the ego first drives against, so s runs the way the drive went (the
    paper's "away from the world origin" with the origin at the highway entry, i.e. the drive's
    start): a one-way carriageway's lanes are right lanes along s. The frame's own orientation comes
    from the markings and the local frame's origin, which can lie anywhere (a roadgen corridor
    driven towards its origin was built as the opposite direction's road: 16 m boundaries RMSE).
    """
    if ego is None or len(ego) < 2:
        return 1
    s, _, inside = frame.project(ego)
    ds = np.gradient(s)
    moving = np.flatnonzero(inside & (np.abs(ds) > 1e-3))
    return 1 if len(moving) == 0 or ds[moving[0]] > 0 else -1


def _type_tapers(model: LaneModel, tapers: list[_Taper], new_id: np.ndarray, travel: int) -> None:
    """Lane types of the taper lanes in the model's sections, and a warning per lane built.

    Right-hand traffic: the lane travels like the ego (`travel`: +1 along s); one whose width shrinks
    to zero in its travel direction is an entry (acceleration) lane, one that grows from zero an exit
    (deceleration) lane.
    """
    for taper in tapers:
        bid = int(new_id[taper.row])
        kind = "entry" if taper.narrow_last == (travel > 0) else "exit"
        secs = []
        for sec in model.sections:
            ids = sec.boundary_ids
            end = ids[0] if taper.side > 0 else ids[-1]
            if end != bid:
                continue
            lane = 0 if taper.side > 0 else len(ids) - 2
            sec.lane_types = list(sec.lane_types or ["driving"] * (len(ids) - 1))
            sec.lane_types[lane] = kind
            secs.append(sec)
        side = "right" if taper.side * travel < 0 else "left"
        if not secs:
            model.warnings.append(f"an {kind} lane on the {side} (boundary {bid}) was left out of the lane sections")
            continue
        outer = [i for i in secs[0].boundary_ids if i != bid][-1 if taper.side < 0 else 0]
        s0, s1 = secs[0].s_start, secs[-1].s_end
        verb = "closes onto" if kind == "entry" else "opens from"
        seen = "first" if kind == "entry" else "last"
        model.warnings.append(
            f"{kind} lane on the {side} on s {s0:.0f}-{s1:.0f} m: a taper, its outer line (boundary {bid}) "
            f"{verb} boundary {outer} at {taper.angle_deg:.1f} deg ({taper.first_width:.1f} m wide where "
            f"{seen} seen)"
        )


def _lane_between(ids: list[int], a: int, b: int) -> bool:
    """Whether boundaries a and b are neighbours in a section's ordered boundary ids (a lane between them)."""
    return a in ids and b in ids and abs(ids.index(a) - ids.index(b)) == 1


def _type_by_width(model: LaneModel, travel: int, cfg: LanesConfig) -> None:
    """An outermost lane that opens from zero width where its section begins and is still at full
    width where its section ends is an exit lane (an entry lane mirrored): its measured taper is its
    narrow end, and it leaves the road at its wide end (a ramp's lane) rather than closing. Typed
    like `_type_tapers`' lanes, so it keeps its width there instead of a taper being invented.

    At the narrow end the lane must be new, whichever of its lines is (the section beside holds no
    lane between them: the inner line may begin at the taper's narrow end, `_open_beside_edge`); at
    the wide end its outer line must end there (a lane at full width beside an outer line that goes
    on is a ramp's merge or diverge for the junction builder). A lane still widening at its end by
    `branch_widening_m` is left to the junction builder (branches.find_events)."""
    by_id = {b.id: b for b in model.boundaries}
    secs = model.sections
    for j, sec in enumerate(secs):
        ids = sec.boundary_ids
        n = len(ids) - 1
        if n < 2:
            continue
        ks = np.flatnonzero((model.s >= sec.s_start - 1e-9) & (model.s <= sec.s_end + 1e-9))
        if len(ks) < 10:
            continue
        for lane in (0, n - 1):
            if lane == 0 and sec.divider_id is not None:
                continue
            if sec.lane_types is not None and sec.lane_types[lane] != "driving":
                continue
            w = by_id[ids[lane]].t[ks] - by_id[ids[lane + 1]].t[ks]
            w = w[np.isfinite(w)]
            if len(w) < 10:
                continue
            med = float(np.median(w))
            if med < cfg.min_lane_width_m:
                continue
            pair, outer = (ids[lane], ids[lane + 1]), ids[0 if lane == 0 else -1]
            lane_before = j > 0 and _lane_between(secs[j - 1].boundary_ids, *pair)
            lane_after = j < len(secs) - 1 and _lane_between(secs[j + 1].boundary_ids, *pair)
            outer_before = j > 0 and outer in secs[j - 1].boundary_ids
            outer_after = j < len(secs) - 1 and outer in secs[j + 1].boundary_ids
            head, tail = float(np.mean(w[:3])), float(np.mean(w[-3:]))
            opens = not lane_before and head < 0.5 * med and tail >= 0.8 * med
            closes = not lane_after and tail < 0.5 * med and head >= 0.8 * med
            if opens and not outer_after and j < len(secs) - 1 and tail <= med + cfg.branch_widening_m:
                narrow_last = False
            elif closes and not outer_before and j > 0:
                narrow_last = True
            else:
                continue
            types = list(sec.lane_types or ["driving"] * n)
            types[lane] = "entry" if narrow_last == (travel > 0) else "exit"
            sec.lane_types = types


def _sections(
    on: np.ndarray, t: np.ndarray, s: np.ndarray, min_len: float
) -> tuple[list[LaneSection], np.ndarray, np.ndarray]:
    """Runs of a constant boundary set (left to right); short runs and holes join a neighbour.

    A merged stretch takes the neighbour's boundaries; their offsets are interpolated (held at
    the ends) where they were not measured, so sections are contiguous and every listed boundary
    has offsets in its section. Returns the sections and the updated presence and offsets.
    """
    on, t = on.copy(), t.copy()
    m = on.shape[1]
    codes = [tuple(np.flatnonzero(on[:, k])) if on[:, k].sum() >= 2 else () for k in range(m)]
    runs: list[list] = []
    for k, c in enumerate(codes):
        if runs and runs[-1][2] == c:
            runs[-1][1] = k
        else:
            runs.append([k, k, c])

    def length(r: list) -> float:
        return float(s[min(r[1] + 1, m - 1)] - s[r[0]]) if r[2] else -1.0

    while len(runs) > 1:
        i = min(range(len(runs)), key=lambda j: (length(runs[j]), j))
        if runs[i][2] and length(runs[i]) >= min_len:
            break
        nbs = [j for j in (i - 1, i + 1) if 0 <= j < len(runs) and runs[j][2]]
        if not nbs:
            break
        j = max(nbs, key=lambda q: (length(runs[q]), -q))
        a, b = runs[i][0], runs[i][1]
        on[:, a : b + 1] = False
        for x in runs[j][2]:
            on[x, a : b + 1] = True
            fin = np.flatnonzero(np.isfinite(t[x]))
            gap = np.arange(a, b + 1)
            miss = gap[~np.isfinite(t[x, gap])]
            if len(miss):
                t[x, miss] = np.interp(miss, fin, t[x, fin])
        runs[j] = [min(a, runs[j][0]), max(b, runs[j][1]), runs[j][2]]
        runs.pop(i)
        merged: list[list] = []
        for r in runs:
            if merged and merged[-1][2] == r[2]:
                merged[-1][1] = r[1]
            else:
                merged.append(r)
        runs = merged
    runs = [r for r in runs if r[2]]
    out = []
    for k, (a, b, c) in enumerate(runs):
        ids = sorted(c, key=lambda x: -float(np.nanmedian(t[x, a : b + 1])))
        s_end = s[b + 1] if k + 1 < len(runs) else s[b]
        out.append(LaneSection(float(s[a]), float(s_end), [int(i) for i in ids]))
    return out, on, np.where(on, t, np.nan)


# --------------------------------------------------------------------------------------------
# marking type and width


def _mark_pattern(s_pts: np.ndarray, cfg: LanesConfig) -> tuple[str, float | None, float | None]:
    """Solid or broken from the painted runs along s; dash and gap lengths for broken lines.

    Runs are split at holes over 1-2.5 m (10 median point spacings: far, sparse lines have holes
    inside their dashes); the length-weighted median run decides
    (occlusions shorten solid runs but leave them far longer than a dash); dash and gap are the
    medians of the runs and holes of dash size.
    """
    if len(s_pts) < 10:
        return "solid", None, None
    s = np.sort(s_pts)
    spacing = np.diff(s)
    hole = float(np.clip(10.0 * np.median(spacing), 1.0, 2.5))
    cut = np.flatnonzero(spacing > hole)
    first = np.concatenate([[0], cut + 1])
    last = np.concatenate([cut, [len(s) - 1]])
    lengths = s[last] - s[first]
    order = np.argsort(lengths)
    cum = np.cumsum(lengths[order])
    if cum[-1] <= 0:
        return "solid", None, None
    weighted_median = lengths[order][np.searchsorted(cum, cum[-1] / 2.0)]
    if weighted_median > cfg.solid_min_run_m:
        return "solid", None, None
    dashes = lengths[(lengths >= 1.0) & (lengths <= cfg.solid_min_run_m)]
    holes = s[first[1:]] - s[last[:-1]]
    holes = holes[holes <= 3.0 * cfg.solid_min_run_m]
    dash = round(float(np.median(dashes)), 2) if len(dashes) else None
    gap = round(float(np.median(holes)), 2) if len(holes) else None
    return "broken", dash, gap


def _spread_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For paint of width 1 blurred by noise sigma = k: (q90 - q10) / (q75 - q25) and (q90 - q10)."""
    ks = np.linspace(0.0, 3.0, 61)
    x = np.linspace(-8.0, 8.0, 8001)
    ratio, spread = [], []
    for k in ks:
        if k == 0:
            cdf = np.clip(x + 0.5, 0.0, 1.0)
        else:
            a, b = (x + 0.5) / k, (x - 0.5) / k
            cdf = (x + 0.5) * norm.cdf(a) - (x - 0.5) * norm.cdf(b) + k * (norm.pdf(a) - norm.pdf(b))
        q = np.interp([0.1, 0.25, 0.75, 0.9], cdf, x)
        ratio.append((q[3] - q[0]) / (q[2] - q[1]))
        spread.append(q[3] - q[0])
    return ks, np.array(ratio), np.array(spread)


_SPREAD: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def marking_widths(residuals: list[np.ndarray]) -> list[float | None]:
    """Paint widths from lateral residuals: uniform paint blurred by Gaussian noise, by quantiles.

    Each line's (q90 - q10) / (q75 - q25) gives its noise-to-width ratio; the noise is one
    property of the drive, so its median over the well-sampled lines (1000 points or more) is
    used for every line, and each width then follows from its own q90 - q10. None when a line
    has fewer than 30 points.
    """
    global _SPREAD
    if _SPREAD is None:
        _SPREAD = _spread_table()
    ks, ratio, spread = _SPREAD
    stats = []
    for r in residuals:
        if len(r) < 30:
            stats.append(None)
            continue
        q10, q25, q75, q90 = np.quantile(r, [0.1, 0.25, 0.75, 0.9])
        stats.append((len(r), q25, q75, q10, q90))
    sigmas = []
    for st in stats:
        if st is None or st[0] < 1000 or st[2] <= st[1]:
            continue
        k = float(np.interp(np.clip((st[4] - st[3]) / (st[2] - st[1]), ratio[0], ratio[-1]), ratio, ks))
        width = (st[4] - st[3]) / float(np.interp(k, ks, spread))
        sigmas.append(k * width)
    noise = float(np.median(sigmas)) if sigmas else None
    out: list[float | None] = []
    for st in stats:
        if st is None:
            out.append(None)
            continue
        r1090 = st[4] - st[3]
        if noise is None:
            k = float(np.interp(np.clip(r1090 / max(st[2] - st[1], 1e-9), ratio[0], ratio[-1]), ratio, ks))
            out.append(float(r1090 / np.interp(k, ks, spread)))
            continue
        lo, hi = 1e-3, 2.0
        for _ in range(50):
            w = 0.5 * (lo + hi)
            if w * float(np.interp(noise / w, ks, spread, right=spread[-1] * (noise / w) / ks[-1])) < r1090:
                lo = w
            else:
                hi = w
        out.append(float(0.5 * (lo + hi)) if hi < 2.0 else None)
    return out


# --------------------------------------------------------------------------------------------
# the stage


def build_lane_model(
    cloud: MarkingCloud, candidates: list[Candidate], cfg: LanesConfig, where: str = "marking cloud"
) -> LaneModel:
    """Paper Alg. 2 and beyond: superlines, boundaries t(s), sections and the reference line."""
    xyz = np.asarray(cloud.xyz, dtype=np.float64)
    if len(xyz) == 0:
        raise InputError(where, "no marking points: nothing to build lanes from")
    if not candidates:
        raise InputError(where, "no candidate lines were found in the markings")
    step = cfg.station_step_m
    pieces, owner = split_candidates(candidates, cfg)
    segs = candidate_segments(pieces)
    lookups = relative_lookups(segs, cfg)
    w_lane = lane_step(lookups, cfg)
    if w_lane is None:
        raise InputError(
            where,
            "found no two parallel marking lines "
            f"{cfg.min_lane_width_m:g}-{cfg.max_lane_width_m:g} m apart: a single line "
            "(or none) cannot give lanes",
        )
    superline = global_lookup(len(pieces), lookups, w_lane, cfg)
    frame = _first_frame(segs, lookups, cfg)
    along_line = _line_frame(pieces, cfg)
    frames = [frame]
    if along_line is not None:
        if (along_line.length >= 0.9 * frame.length
                and _parallel_length(along_line, segs, cfg) > _LINE_FRAME_GAIN * _parallel_length(frame, segs, cfg)):
            frames.insert(0, along_line)
        else:
            frames.append(along_line)
    for attempt, frame in enumerate(frames):
        try:
            return _build_on_frame(cloud, candidates, cfg, where, xyz, pieces, owner, superline, frame, step, w_lane)
        except _NoRoad:
            if attempt == len(frames) - 1:
                raise InputError(where, "no stretch of road has two marking lines a lane apart") from None
    raise AssertionError("unreachable")


class _NoRoad(Exception):
    """No station of a frame has two kept lines: the road axis may be poor (`build_lane_model` tries the next)."""


def _build_on_frame(cloud: MarkingCloud, candidates: list[Candidate], cfg: LanesConfig, where: str, xyz: np.ndarray,
                    pieces: list[Candidate], owner: np.ndarray, superline: np.ndarray, frame: Frame, step: float,
                    w_lane: float) -> LaneModel:
    """`build_lane_model` along one road axis; `_NoRoad` when no stretch has two lines a lane apart on it."""
    warnings: list[str] = []
    label = _label_by_candidates(xyz[:, :2], pieces, superline, cfg)
    n_sl = int(superline.max()) + 1
    ego = cloud.trajectory.positions[:, :2] if len(cloud.trajectory) else None
    lam = _lam(cfg.boundary_smoothing_m, step)
    structure = fit = None
    if _travel_sign(frame, ego) < 0:
        frame = Frame(frame.xy[::-1], step)
    travel = _travel_sign(frame, ego)
    tapers: list[_Taper] = []
    taper_notes: list[str] = []
    off = np.zeros(len(xyz), dtype=bool)  # points of taper lines found: refitted without them (they bend the edge)
    double = (cfg.double_line_max_spacing_m, max(int(round(cfg.double_line_block_m / step)), 1))
    for it in range(3):
        k_pt, t_pt, inside, s_pt = _stations(frame, xyz[:, :2])
        t_ego = _ego_offsets(frame, ego)
        for _ in range(3):
            use = np.where(off, -1, label)
            fit = _fit_boundaries(k_pt, t_pt, use, inside, n_sl, len(frame.s), lam, int(round(20.0 / step)),
                                  cfg.same_line_tolerance_m, double)
            root = _continuations(fit.t, int(round(cfg.line_join_gap_m / step)), cfg.same_line_tolerance_m,
                                  int(round(10.0 / step)))
            if np.any(root != np.arange(n_sl)):
                label = np.where(label >= 0, root[np.maximum(label, 0)], -1)
                use = np.where(off, -1, label)
                superline = root[superline]
                fit = _fit_boundaries(k_pt, t_pt, use, inside, n_sl, len(frame.s), lam, int(round(20.0 / step)),
                                      cfg.same_line_tolerance_m, double)
            crossing = _crossing_points(fit.t, use, k_pt, t_pt, cfg.assign_distance_m)
            short = np.isfinite(fit.t).sum(axis=1) * step < cfg.min_section_length_m
            n_short = int(np.sum(short & np.isfinite(fit.t).any(axis=1)))
            fit.t[short] = np.nan
            active = np.flatnonzero(np.isfinite(fit.t).any(axis=1))
            solid = np.array(
                [_mark_pattern(s_pt[(use == b) & inside], cfg)[0] == "solid" for b in active], dtype=bool
            )
            seen = _observed(k_pt[inside], t_pt[inside], ~crossing[inside], len(frame.s))
            sub = _lane_structure(fit.t[active], fit.support[active], solid, t_ego, step, w_lane, cfg, seen)
            structure = _Structure(np.zeros(fit.t.shape, dtype=bool), np.full(fit.t.shape, np.nan))
            structure.on[active], structure.t[active] = sub.on, sub.t
            if not np.any(structure.on.sum(axis=0) >= 2):
                raise _NoRoad
            tapers, taper_notes = _taper_lanes(_Points(k_pt, t_pt, s_pt, inside, use, xyz[:, 2]), structure,
                                               -travel, step, cfg)
            found = np.zeros(len(label), dtype=bool)
            for taper in tapers:
                found[taper.points] = True
            if not np.any(found & ~off):
                break
            off |= found
            # the edge bent towards a taper's line had left its own paint unlabelled: label again
            curves = _hold_ends(_labelling_curves(sub.t, fit.t[active], cfg.same_line_tolerance_m),
                                int(round(100.0 / step)), cfg.same_line_tolerance_m)
            nearest = _label_by_distance(k_pt, t_pt, inside, curves, cfg)
            label = np.where(nearest >= 0, active[np.maximum(nearest, 0)], -1)
        curves = _labelling_curves(sub.t, fit.t[active], cfg.same_line_tolerance_m)
        curves = _hold_ends(curves, int(round(100.0 / step)), cfg.same_line_tolerance_m)
        curves = _fork_curves(curves, sub.on, cfg.min_lane_width_m)
        nearest = _label_by_distance(k_pt, t_pt, inside, curves, cfg)
        label = np.where(nearest >= 0, active[np.maximum(nearest, 0)], -1)
        if it < 2:
            frame = _recentre(frame, structure, cfg)
    assert structure is not None and fit is not None
    if n_short:
        warnings.append(
            f"ignored {n_short} marking pieces shorter than {cfg.min_section_length_m:g} m "
            "(stray returns, blobs, arrows)"
        )
    pts = _Points(k_pt, t_pt, s_pt, inside, np.where(off, -1, label), xyz[:, 2])
    _add_tapers(fit, structure, pts.label, tapers)
    warnings.extend(taper_notes)
    model, new_id = _assemble(cloud, pieces, superline, frame, fit, structure, pts, warnings, cfg)
    solid_rows = np.zeros(len(fit.t), dtype=bool)
    solid_rows[active] = solid
    first = int(np.argmin(np.linalg.norm(frame.xy - model.reference[0, :2], axis=1)))
    divided = _divided_left(fit.t, structure.on, solid_rows)[first : first + len(model.s)]
    _mark_dividers(model, _ego_track(frame, ego, model), cfg, divided)
    _type_tapers(model, tapers, new_id, travel)
    _type_by_width(model, travel, cfg)
    from lidar2xodr.unpainted_lanes import type_implied_lanes

    type_implied_lanes(model)
    counts = [len(sec.boundary_ids) - 1 for sec in model.sections]
    if len(set(counts)) > 1:
        model.warnings.append(
            "lane count changes along the road: "
            + ", ".join(f"{n} from s {sec.s_start:.0f} m" for n, sec in zip(counts, model.sections, strict=True))
        )
    longest: dict[int, tuple[int, int]] = {}
    for piece, i in zip(pieces, owner, strict=True):
        if i not in longest or len(piece.centers) > longest[i][0]:
            longest[i] = (len(piece.centers), piece.superline)
    for i, c in enumerate(candidates):
        c.superline = longest[i][1]
    model.candidates = candidates
    return model


@dataclass
class _Fit:
    t: np.ndarray  # (B, M)
    support: np.ndarray  # (B,) points used


def _stations(frame: Frame, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest station, offset, inside flag and exact station of every point."""
    s, t, inside = frame.project(xy)
    k = np.clip(np.rint(s / (frame.s[1] - frame.s[0])).astype(np.int64), 0, len(frame.s) - 1)
    return k, t, inside, s


def _fit_boundaries(
    k: np.ndarray,
    t: np.ndarray,
    label: np.ndarray,
    inside: np.ndarray,
    n_sl: int,
    m: int,
    lam: float,
    gap: int,
    parallel_m: float,
    double: tuple[float, int] = (0.0, 1),
) -> _Fit:
    """Every labelled line's t(s) (`_robust_curve` of its points, double lines folded onto their
    midpoint: `double` = (largest spacing, block stations), see `_fold_double_lines`), bridged across
    unobserved stretches."""
    out = np.full((n_sl, m), np.nan)
    support = np.zeros(n_sl)
    use = (label >= 0) & inside
    order = np.argsort(label[use], kind="stable")
    lab, kk, tt = label[use][order], k[use][order], t[use][order]
    bounds = np.searchsorted(lab, np.arange(n_sl + 1))
    free = (label < 0) & inside
    by_k = np.argsort(k[free], kind="stable")
    k_free, t_free = k[free][by_k], t[free][by_k]
    observed = np.zeros((n_sl, m), dtype=bool)
    for b in range(n_sl):
        sl = slice(bounds[b], bounds[b + 1])
        if bounds[b + 1] - bounds[b] < 10:
            continue
        out[b], w, observed[b] = _robust_curve(kk[sl], tt[sl], m, lam)
        again = _refit_double(out[b], kk[sl], tt[sl], k_free, t_free, m, lam, double)
        if again is not None:
            out[b], w, observed[b] = again
        support[b] = float(w.sum())
    _bridge_gaps(out, observed, gap, parallel_m)
    return _Fit(out, support)


def _continuations(t: np.ndarray, gap_max: int, tol: float, probe: int) -> np.ndarray:
    """Row each fitted line joins: a line that ends where another begins, at the same offset, goes on in it.

    Marking chains break where every line is hard to follow at once (a tight curve, an occlusion by
    a truck): the paper's global lookup then finds no neighbour beside both pieces and the boundary
    would jump between two fits. Only lines fitted over more than `probe` stations take part (dots,
    posts and single dashes are the global lookup's business). b continues a when b starts at most
    `gap_max` stations after a ends (or overlaps it by at most `probe` stations, agreeing within
    `tol` there) and both reach the same offset within `tol` at the middle of the gap: kept at their
    offset to a line that is present across the whole gap (the nearest such neighbour), else each
    extrapolated linearly from its last (first) `probe` stations; both run along the road there
    (`_ALONG_SLOPE`: a ramp or a crossing line is no continuation in this frame). Pairs are taken
    best first, one successor and one predecessor per line; chains follow.
    """
    n = len(t)
    fin = np.isfinite(t)
    rows = [b for b in range(n) if fin[b].sum() > probe]
    span = {b: (int(np.flatnonzero(fin[b])[0]), int(np.flatnonzero(fin[b])[-1])) for b in rows}
    pairs = []
    for a in rows:
        a0, ea = span[a]
        for b in rows:
            sb, b1 = span[b]
            if b == a or sb <= a0 or b1 <= ea or sb - ea > gap_max or ea - sb > probe:
                continue
            if not (_along(t[a, max(ea - probe, a0) : ea + 1]) and _along(t[b, sb : min(sb + probe, b1) + 1])):
                continue
            if sb <= ea:
                miss = float(np.max(np.abs(t[a, sb : ea + 1] - t[b, sb : ea + 1])))
            else:
                miss = _gap_mismatch(t, fin, a, b, ea, sb, probe, span)
            if miss <= tol:
                pairs.append((miss, a, b))
    root = np.arange(n)
    nxt: set[int] = set()
    prev: set[int] = set()
    for _, a, b in sorted(pairs):
        if a in nxt or b in prev:
            continue
        nxt.add(a)
        prev.add(b)
        root[b] = a
    for b in range(n):
        r = b
        while root[r] != r:
            r = root[r]
        root[b] = r
    return root


def _along(t_end: np.ndarray) -> bool:
    """The piece of a line runs along the road: its offset changes by at most `_ALONG_SLOPE` per station."""
    return len(t_end) < 2 or float(np.max(np.abs(np.diff(t_end)))) <= _ALONG_SLOPE


def _gap_mismatch(t: np.ndarray, fin: np.ndarray, a: int, b: int, ea: int, sb: int, probe: int,
                  span: dict[int, tuple[int, int]]) -> float:
    """Offset difference of line a's end and line b's start across the gap ea..sb (see `_continuations`)."""
    across = [c for c in span if c not in (a, b) and fin[c, ea : sb + 1].all()]
    if across:
        c = min(across, key=lambda c: abs(t[a, ea] - t[c, ea]))
        return float(abs((t[a, ea] - t[c, ea]) - (t[b, sb] - t[c, sb])))
    mid = 0.5 * (ea + sb)
    ka = np.arange(ea - probe, ea + 1)
    kb = np.arange(sb, sb + probe + 1)
    if ka[0] < span[a][0] or kb[-1] > span[b][1]:
        return float("inf")
    fa, fb = np.polyfit(ka - ea, t[a, ka], 1), np.polyfit(kb - sb, t[b, kb], 1)
    return float(abs(np.polyval(fa, mid - ea) - np.polyval(fb, mid - sb)))


def _bridge_gaps(t: np.ndarray, observed: np.ndarray, gap: int, parallel_m: float) -> None:
    """Across unobserved stretches longer than `gap` stations a line keeps its lane width to the
    neighbour best observed there (interpolated between the ends), instead of a straight chord in
    the frame, which bends wherever the frame does. Neighbours whose offset to the line changes
    least across the gap (in steps of `parallel_m`) come first: one that diverges from the line
    there (an exit lane's edge leaving where the edge line turns into a broken one) would carry
    the bridge out with it."""
    for b in range(len(t)):
        fin = np.flatnonzero(np.isfinite(t[b]))
        if len(fin) == 0:
            continue
        inner = np.zeros(t.shape[1], dtype=bool)
        inner[fin[0] : fin[-1] + 1] = True
        for g0, g1 in _runs(inner & ~observed[b]):
            if g1 - g0 < gap or g0 == 0 or g1 >= t.shape[1]:
                continue
            best, best_key = None, None
            for nb in range(len(t)):
                if nb == b or not np.all(np.isfinite(t[nb, g0 - 1 : g1 + 1])):
                    continue
                drift = abs(float((t[b, g1] - t[nb, g1]) - (t[b, g0 - 1] - t[nb, g0 - 1])))
                share = float(observed[nb, g0:g1].mean())
                steps = int(drift / parallel_m) if math.isfinite(drift) else 0
                key = (-steps, share, -abs(float(t[nb, g0] - t[b, g0])))
                if share >= 0.25 and (best_key is None or key > best_key):
                    best, best_key = nb, key
            if best is None:
                continue
            w0, w1 = t[b, g0 - 1] - t[best, g0 - 1], t[b, g1] - t[best, g1]
            f = (np.arange(g0, g1) - (g0 - 1)) / (g1 - g0 + 1)
            t[b, g0:g1] = t[best, g0:g1] + w0 + (w1 - w0) * f


@dataclass
class _Observed:
    """Marking points counted per block of stations and lateral bin: where the sensor saw paint
    (a bin counts with `least` points or more, so one stray return does not)."""

    counts: np.ndarray  # (blocks, bins) every point
    free: np.ndarray  # (blocks, bins) points not on a line that crosses the road there
    t0: float
    bin_m: float
    block: int

    def near(self, k: np.ndarray, t: np.ndarray, least: int = 3) -> np.ndarray:
        """At stations k: paint was seen within about `bin_m` of offset t (False where t is NaN): a
        line there, only not fitted; paint of a line crossing the road there is no such evidence."""
        blocks = np.minimum(k // self.block, len(self.counts) - 1)
        ok = np.isfinite(t)
        col = np.floor((np.where(ok, t, self.t0) - self.t0) / self.bin_m).astype(np.int64)
        n_bins = self.counts.shape[1]
        out = np.zeros(len(k), dtype=bool)
        for d in (-1, 0, 1):
            out |= self.free[blocks, np.clip(col + d, 0, n_bins - 1)] >= least
        return out & ok

    def beyond(self, k: np.ndarray, t: np.ndarray, side: float, least: int = 3) -> np.ndarray:
        """At stations k: paint was seen more than 1 m beyond offset t (`side`: +1 left, -1 right)."""
        blocks = np.minimum(k // self.block, len(self.counts) - 1)
        ok = np.isfinite(t)
        col = np.floor((np.where(ok, t, self.t0) - self.t0) / self.bin_m).astype(np.int64)
        n_bins = self.counts.shape[1]
        edge = col + int(side * np.ceil(1.0 / self.bin_m))
        cum = np.cumsum(self.counts >= least, axis=1)
        if side > 0:
            out = cum[blocks, -1] - cum[blocks, np.clip(edge, 0, n_bins - 1)] > 0
        else:
            out = (cum[blocks, np.clip(edge - 1, 0, n_bins - 1)] > 0) & (edge > 0)
        return out & ok


def _crossing_points(t_fit: np.ndarray, label: np.ndarray, k: np.ndarray, t: np.ndarray, tol: float) -> np.ndarray:
    """Points on a fitted line that runs across the road there (offset changing by more than
    `_ALONG_SLOPE` per station: a ramp, a crossing line), not along it."""
    slope = np.abs(np.gradient(t_fit, axis=1)) if t_fit.shape[1] > 1 else np.zeros_like(t_fit)
    row = np.maximum(label, 0)
    with np.errstate(invalid="ignore"):
        return (label >= 0) & (np.abs(t - t_fit[row, k]) <= tol) & (slope[row, k] > _ALONG_SLOPE)


def _observed(k: np.ndarray, t: np.ndarray, free: np.ndarray, m: int, block: int = 10,
              bin_m: float = 0.5) -> _Observed:
    """Counts of marking points (all, and those with `free` set) per `block` stations and `bin_m` of offset."""
    n_blocks = max((m + block - 1) // block, 1)
    if len(k) == 0:
        empty = np.zeros((n_blocks, 1), dtype=np.int64)
        return _Observed(empty, empty.copy(), 0.0, bin_m, block)
    t0 = float(np.floor(t.min()))
    n_bins = int(np.ceil((t.max() - t0) / bin_m)) + 1
    cell = (np.minimum(k // block, n_blocks - 1), ((t - t0) / bin_m).astype(np.int64))
    counts = np.zeros((n_blocks, n_bins), dtype=np.int64)
    np.add.at(counts, cell, 1)
    loose = np.zeros((n_blocks, n_bins), dtype=np.int64)
    np.add.at(loose, (cell[0][free], cell[1][free]), 1)
    return _Observed(counts, loose, t0, bin_m, block)


def _ego_offsets(frame: Frame, ego: np.ndarray | None) -> np.ndarray | None:
    """The ego's offset at every station (NaN beyond its samples), from the samples that travel the way
    it first travelled on the frame: a drive that turns round passes the stations twice, on a divided
    road once on each carriageway, and one curve through both passes would jump between them."""
    if ego is None or len(ego) < 2:
        return None
    s, t, inside = frame.project(ego)
    ds = np.gradient(s)
    moving = inside & (np.abs(ds) > 1e-3)
    if moving.sum() >= 2:
        inside = moving & (np.sign(ds) == np.sign(ds[np.flatnonzero(moving)[0]]))
    if inside.sum() < 2:
        return None
    order = np.argsort(s[inside])
    return np.interp(frame.s, s[inside][order], t[inside][order], left=np.nan, right=np.nan)


@dataclass
class _EgoTrack:
    """Trajectory samples on the model's stations: index, offset, and +1/-1 travelling along/against s."""

    k: np.ndarray
    t: np.ndarray
    direction: np.ndarray


def _ego_track(frame: Frame, ego: np.ndarray | None, model: LaneModel) -> _EgoTrack | None:
    """The trajectory on the model's stations (the model starts at a station of `frame`).

    Only samples heading within 14 degrees of the road axis are kept (a lane change takes a few):
    a U-turn at the end of the drive (or a stop) has no travel direction along the road, so it
    cannot tell a divider's side.
    """
    if ego is None or len(ego) < 3:
        return None
    s_e, t_e, inside = frame.project(ego)
    ds = np.gradient(s_e)
    moving = (np.abs(ds) > 1e-3) & (np.abs(np.gradient(t_e)) < 0.25 * np.abs(ds))
    step = float(frame.s[1] - frame.s[0])
    first = int(np.argmin(np.linalg.norm(frame.xy - model.reference[0, :2], axis=1)))
    k = np.rint(s_e / step).astype(np.int64) - first
    keep = inside & moving
    return _EgoTrack(k[keep], t_e[keep], np.sign(ds[keep]).astype(np.int64))


def _divided_left(t_fit: np.ndarray, on: np.ndarray, solid: np.ndarray) -> np.ndarray:
    """Stations where another carriageway lies left of the kept one beyond a median: the nearest
    measured line left of the leftmost kept line is solid (its left edge line) and has a line beyond it."""
    with np.errstate(invalid="ignore"):
        top = np.max(np.where(on, t_fit, -np.inf), axis=0)
        beyond = ~on & np.isfinite(t_fit) & (t_fit > top[None, :] + 0.5)
    count = beyond.sum(axis=0)
    nearest = np.argmin(np.where(beyond, t_fit, np.inf), axis=0)
    return (count >= 2) & solid[nearest]


def _mark_dividers(model: LaneModel, ego: _EgoTrack | None, cfg: LanesConfig,
                   divided: np.ndarray | None = None) -> None:
    """Set `LaneSection.divider_id` where a painted line separates the two directions.

    Evidence (right-hand traffic), none of it from the trajectory's shape connecting markings, and
    only from trajectory samples on the carriageway (within 1 m of its outermost lines: beyond a
    median the ego drives another carriageway): the line is solid, has lanes on both sides over
    sections of at least `divider_min_length_m` together, and every trajectory sample beside it
    lies on the side of its own travel direction (right of it while moving along s, left while
    moving against s), over at least
    `divider_min_length_m` of stations, up to `divider_max_wrong_side_m` of stations (projection
    noise where a U-turn ends the drive): the ego never crossed it. A broken (or other non-solid)
    centre line qualifies only when the ego drove both ways beside it, each over
    `divider_min_length_m` (along s right of it, against s left of it): a one-way carriageway is
    never driven against s; a solid candidate wins over broken ones, and several broken ones alone
    (every line between the two tracks qualifies) are ambiguous, so none is set. A solid line inside one
    carriageway (an exit lane's, a lane drop's) is short, or crossed, or has the ego on its wrong
    side, so it is no divider. A road shorter than `divider_min_length_m` cannot show that
    much line: there `divider_short_share` of its length stands in for it, and every line (solid
    too) needs the decisive evidence, the ego driving both ways beside it (along s right of it,
    against s left of it) each over that share; a solid no-lane-change line between lanes of one
    direction (near a junction) is never driven against s, so it cannot qualify. Without a
    trajectory no divider is set (the side cannot be known); where several lines qualify,
    the one nearest the ego bounds its carriageway. Sections where the
    line is the outermost one (the opposite lanes not seen) keep no divider. A line beside which
    another carriageway lies left of this one beyond a median over more than half its stations
    (`divided`, from `_divided_left`) is no divider whatever the ego did: under right-hand traffic
    that carriageway is the opposite direction, so this one is one-way (a drive that turned round
    on it drove it the wrong way).
    """
    if ego is None or not model.sections or len(ego.k) == 0:
        return
    by_id = {b.id: b for b in model.boundaries}
    step = float(model.s[1] - model.s[0]) if len(model.s) > 1 else 1.0
    inner: dict[int, list[int]] = {}
    for j, sec in enumerate(model.sections):
        for bid in sec.boundary_ids[1:-1]:
            inner.setdefault(bid, []).append(j)
    ok = np.flatnonzero((ego.k >= 0) & (ego.k < len(model.s)))
    # only samples on this carriageway: beyond a median the ego drives another one
    ts = np.array([b.t for b in model.boundaries])
    with np.errstate(invalid="ignore"):
        top, bottom = np.nanmax(ts, axis=0), np.nanmin(ts, axis=0)
    ok = ok[(ego.t[ok] <= top[ego.k[ok]] + 1.0) & (ego.t[ok] >= bottom[ego.k[ok]] - 1.0)]
    k, t_e, direction = ego.k[ok], ego.t[ok], ego.direction[ok]
    road = float(model.s[-1] - model.s[0])
    short = road < cfg.divider_min_length_m
    need = cfg.divider_short_share * road if short else cfg.divider_min_length_m
    closeness: dict[int, float] = {}
    along: dict[int, bool] = {}
    for bid, secs in inner.items():
        length = sum(model.sections[j].s_end - model.sections[j].s_start for j in secs)
        if length < need:
            continue
        if divided is not None and float(np.mean(divided[np.isfinite(by_id[bid].t)])) > 0.5:
            continue
        t_b = by_id[bid].t[k]
        beside = np.isfinite(t_b)
        if not beside.any():
            continue
        right_side = t_e[beside] < t_b[beside]
        consistent = np.where(direction[beside] > 0, right_side, ~right_side)
        covered = _covered_m(k[beside], step)
        wrong = len(np.unique(k[beside][~consistent])) * step
        both = [_covered_m(k[beside][consistent & (direction[beside] == sign)], step) for sign in (1, -1)]
        if (short or by_id[bid].mark_type != "solid") and min(both) < need:
            continue
        if wrong <= cfg.divider_max_wrong_side_m and covered >= need:
            closeness[bid] = float(np.median(np.abs(t_e[beside] - t_b[beside])))
            along[bid] = bool(np.median(direction[beside]) > 0)
    for j, sec in enumerate(model.sections):
        found = [bid for bid in closeness if j in inner[bid]]
        solid = [bid for bid in found if by_id[bid].mark_type == "solid"]
        if solid or len(found) > 1:
            found = solid
        sec.divider_id = min(found, key=lambda b: (closeness[b], b)) if found else None
    _drop_partial_opposite(model, along)


def _covered_m(k: np.ndarray, step: float, max_gap_m: float = 5.0) -> float:
    """Length of road the samples at stations k cover: the stations between neighbouring samples up
    to `max_gap_m` apart count (poses a few metres apart cover the road between them)."""
    u = np.unique(k)
    if len(u) == 0:
        return 0.0
    cap = max(int(round(max_gap_m / step)), 1)
    return float(np.sum(np.minimum(np.diff(u), cap)) + 1) * step


def _drop_partial_opposite(model: LaneModel, along: dict[int, bool]) -> None:
    """Keep the opposite carriageway only where it was seen whole.

    A carriageway is complete when its outermost line is a solid edge line. In every section whose
    outermost line beyond the divider (the side the ego does not drive) is not solid, the opposite
    lanes are left out: the divider becomes the leftmost boundary (lane 0 stays on it) and only the
    ego's direction is exported there, with a warning. A wrong lane count is worse than a missing
    carriageway. Only done when the ego drives along s (the opposite lanes are left of the
    divider); against s the section is left as it is, because a one-way export runs along s.
    """
    by_id = {b.id: b for b in model.boundaries}
    cut_at: list[str] = []
    for sec in model.sections:
        d = sec.divider_id
        if d is None or not along.get(d, False) or by_id[sec.boundary_ids[0]].mark_type == "solid":
            continue
        cut_at.append(f"{sec.s_start:.0f}-{sec.s_end:.0f}")
        sec.boundary_ids = sec.boundary_ids[sec.boundary_ids.index(d) :]
        sec.divider_id = None
    if not cut_at:
        return
    merged: list[LaneSection] = []
    for sec in model.sections:
        prev = merged[-1] if merged else None
        if prev and prev.boundary_ids == sec.boundary_ids and prev.divider_id == sec.divider_id:
            prev.s_end = sec.s_end
        else:
            merged.append(sec)
    model.sections = merged
    model.warnings.append(
        "the opposite carriageway was seen only partly on s " + ", ".join(cut_at) + " m (its outermost "
        "line is not a solid edge line): only the ego's direction is exported there"
    )


def _label_by_candidates(
    xy: np.ndarray, candidates: list[Candidate], superline: np.ndarray, cfg: LanesConfig
) -> np.ndarray:
    """Superline of every point through the nearest candidate polyline (dash ends included)."""
    pts, owner = [], []
    for i, c in enumerate(candidates):
        ctr = np.asarray(c.centers, dtype=np.float64)[:, :2]
        dirs = np.asarray(c.directions, dtype=np.float64)
        ext = np.vstack([ctr[0] - 3.0 * dirs[0], ctr, ctr[-1] + 3.0 * dirs[-1]])
        seg = np.diff(ext, axis=0)
        n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / 0.25).astype(np.int64), 1)
        f = np.concatenate([np.arange(k) / k for k in n])
        base = np.repeat(np.arange(len(seg)), n)
        pts.append(ext[base] + seg[base] * f[:, None])
        owner.append(np.full(len(f), superline[i]))
    samples, owner_arr = np.vstack(pts), np.concatenate(owner)
    d, j = cKDTree(samples).query(xy, distance_upper_bound=cfg.assign_distance_m)
    ok = np.isfinite(d)
    return np.where(ok, owner_arr[np.minimum(j, len(owner_arr) - 1)], -1)


def _labelling_curves(kept: np.ndarray, fitted: np.ndarray, tol: float) -> np.ndarray:
    """Curves that attract points: kept boundaries, and fitted lines where no kept boundary runs
    within `tol` (ignored lines keep their points; a dropped duplicate gives its points up)."""
    out = kept.copy()
    for b in range(len(kept)):
        free = ~np.isfinite(kept[b]) & np.isfinite(fitted[b])
        if not free.any():
            continue
        close = np.abs(np.delete(kept, b, axis=0) - fitted[b][None, :]) < tol
        out[b] = np.where(free & ~close.any(axis=0), fitted[b], out[b])
    return out


def _hold_ends(curves: np.ndarray, reach: int, tol: float) -> np.ndarray:
    """Curves held at their first and last value for up to `reach` stations, so lines can grow while
    labelling, but never onto another line (a lane closing onto its neighbour must not take it over)."""
    out = curves.copy()
    m = curves.shape[1]
    for b, c in enumerate(curves):
        fin = np.flatnonzero(np.isfinite(c))
        if len(fin) == 0:
            continue
        others = np.delete(curves, b, axis=0)
        for end, direction in ((fin[0], -1), (fin[-1], 1)):
            for i in range(1, reach + 1):
                k = end + direction * i
                if k < 0 or k >= m or np.any(np.abs(others[:, k] - c[end]) < tol):
                    break
                out[b, k] = c[end]
    return out


def _outermost(curves: np.ndarray, fin: np.ndarray, row: int, ks: np.ndarray, side: float) -> bool:
    """No other kept line lies beyond `row` on `side` at stations ks."""
    with np.errstate(invalid="ignore"):
        beyond = fin[:, ks] & (side * (curves[:, ks] - curves[row, ks][None, :]) > 0.1)
    beyond[row] = False
    return not bool(beyond.any())


def _fork_curves(curves: np.ndarray, on: np.ndarray, min_width: float) -> np.ndarray:
    """Labelling curves at forks: where a kept line q begins (ends) within `min_width` of a line r that goes on
    past it at the carriageway's edge (r outermost before the fork, q outermost after it: an exit lane's
    edge leaving the edge line, an entry's joining it; not a line inside the carriageway, such as a 2+1
    road's centre line moving across), r is taken parallel to its neighbour p on its other side, at its
    offset to p 20-60 m before (after) the fork (`_FORK_BACK`: where q's paint, which starts leaving r
    before q is kept, has not bent r yet), for as long as q stays within `min_width` of that course; and
    q is carried on straight (its first 20 stations' slope against that course) back to where it meets
    the course, since its paint leaves r before q is kept. The paint of r there (the broken line the
    edge turns into) is then found again, and q's paint, which the fitted r had been bent towards, goes
    to q."""
    out = curves.copy()
    b_n, m = curves.shape
    fin = np.isfinite(curves) & on
    for q in range(b_n):
        ks = np.flatnonzero(fin[q])
        if len(ks) == 0:
            continue
        for end, step in ((int(ks[0]), 1), (int(ks[-1]), -1)):
            before = end - step
            if not 0 <= before < m:
                continue
            for r in range(b_n):
                if r == q or not (fin[r, before] and fin[r, end]) or abs(curves[q, end] - curves[r, end]) >= min_width:
                    continue
                along = ks[:20] if step > 0 else ks[-20:]
                side = float(np.sign(np.nanmedian(curves[q, along] - curves[r, along])))
                if side == 0.0 or not _outermost(curves, fin, q, along, side) \
                        or not _outermost(curves, fin, r, np.array([before]), side):
                    continue
                others = [p for p in range(b_n) if p not in (q, r) and fin[p, before] and fin[p, end]
                          and np.sign(curves[p, end] - curves[r, end]) == -side]
                if not others:
                    continue
                p = min(others, key=lambda x: abs(curves[x, end] - curves[r, end]))
                back = np.arange(end - step * _FORK_BACK[1], end - step * _FORK_BACK[0], step)
                back = back[(back >= 0) & (back < m)]
                back = back[fin[r, back] & fin[p, back]]
                if len(back) == 0:
                    continue
                offset = float(np.median(curves[r, back] - curves[p, back]))
                k = end
                while 0 <= k < m and fin[q, k] and fin[p, k]:
                    course = curves[p, k] + offset
                    if abs(curves[q, k] - course) >= min_width:
                        break
                    out[r, k] = course
                    k += step
                first = ks[:20] if step > 0 else ks[-20:]
                rel = curves[q, first] - (curves[p, first] + offset)
                slope = np.polyfit(first.astype(float), rel, 1)[0] if len(first) >= 5 else 0.0
                k = end - step
                while 0 <= k < m and fin[p, k] and fin[r, k] and abs(slope) > 1e-3:
                    gap = float(rel[0] if step > 0 else rel[-1]) - slope * (end - k)
                    if gap * side <= 0.1:
                        break
                    out[r, k] = curves[p, k] + offset
                    out[q, k] = curves[p, k] + offset + gap
                    k -= step
    return out


def _label_by_distance(
    k: np.ndarray, t: np.ndarray, inside: np.ndarray, curves: np.ndarray, cfg: LanesConfig
) -> np.ndarray:
    """Superline of every point: the nearest fitted curve at its station, within assign_distance_m."""
    label = np.full(len(t), -1, dtype=np.int64)
    for a in range(0, len(t), 200000):
        sl = slice(a, a + 200000)
        d = np.abs(curves[:, k[sl]] - t[sl][None, :])
        d = np.where(np.isfinite(d), d, np.inf)
        best = np.argmin(d, axis=0)
        ok = (d[best, np.arange(len(best))] <= cfg.assign_distance_m) & inside[sl]
        label[sl] = np.where(ok, best, -1)
    return label


def _centre_offsets(structure: _Structure, cfg: LanesConfig, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Offset of the road centre at each station (NaN-free, smoothed) and where it is measured."""
    valid = structure.on.sum(axis=0) >= 2
    top = np.max(np.where(structure.on, structure.t, -np.inf), axis=0)
    bottom = np.min(np.where(structure.on, structure.t, np.inf), axis=0)
    centre = np.where(valid, 0.5 * (np.where(valid, top, 0.0) + np.where(valid, bottom, 0.0)), 0.0)
    w = valid.astype(np.float64)
    if w.sum() == 0:
        return np.zeros(len(centre)), valid
    lam = _lam(cfg.reference_smoothing_m, step)
    sm = _whittaker(centre, w, lam)
    return sm, valid


def _recentre(frame: Frame, structure: _Structure, cfg: LanesConfig) -> Frame:
    """The road centre as the next frame (trimmed to where the road is measured)."""
    centre, valid = _centre_offsets(structure, cfg, frame.s[1] - frame.s[0])
    idx = np.flatnonzero(valid)
    margin = int(round(20.0 / (frame.s[1] - frame.s[0])))
    a, b = max(idx[0] - margin, 0), min(idx[-1] + margin + 1, len(frame.s))
    return Frame(frame.point(centre)[a:b], frame.s[1] - frame.s[0])


def _reference_z(
    k: np.ndarray, t: np.ndarray, z: np.ndarray, use: np.ndarray, m: int, step: float
) -> np.ndarray:
    """Height of the road at t = 0: a plane across the road per 5 m window, smoothed along s.

    A window whose points do not lie on both sides of t = 0 (the drive's ends, a single line seen)
    gives its mean height at 5 % weight instead of a plane extrapolated to the centre: at the end of
    a 1 km straight_3000m drive such extrapolations ramped the road up 2.2 m in its last 15 m.
    """
    k, t, z = k[use], t[use], z[use]
    if len(z) == 0:
        return np.zeros(m)
    win = max(int(round(5.0 / step)), 1)
    g = k // win
    n = m // win + 1
    s1 = np.bincount(g, minlength=n).astype(np.float64)
    st, stt = np.bincount(g, t, n), np.bincount(g, t * t, n)
    sz, stz = np.bincount(g, z, n), np.bincount(g, t * z, n)
    den = s1 * stt - st**2
    spread_ok = den > 1e-6 * np.maximum(s1, 1) ** 2
    t_lo, t_hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(t_lo, g, t)
    np.maximum.at(t_hi, g, t)
    straddle = (t_lo < -1.0) & (t_hi > 1.0)
    plane = spread_ok & straddle
    a = np.where(plane, (sz * stt - st * stz) / np.where(plane, den, 1.0), sz / np.maximum(s1, 1))
    w = np.where(s1 > 0, np.where(plane, 1.0, 0.05), 0.0)
    centres = (np.arange(n) + 0.5) * win
    zz = _whittaker(np.where(w > 0, a, 0.0), w, _lam(50.0, win * step))
    return np.interp(np.arange(m), centres, zz)


@dataclass
class _Points:
    """Marking points in the current frame: station index, offset, station, inside flag, superline."""

    k: np.ndarray
    t: np.ndarray
    s: np.ndarray
    inside: np.ndarray
    label: np.ndarray
    z: np.ndarray


def _assemble(
    cloud: MarkingCloud,
    candidates: list[Candidate],
    superline: np.ndarray,
    frame: Frame,
    fit: _Fit,
    structure: _Structure,
    pts: _Points,
    warnings: list[str],
    cfg: LanesConfig,
) -> tuple[LaneModel, np.ndarray]:
    """Trim to the measured road, number boundaries left to right, classify them, write the model.

    Also returns the boundary id of every row (-1 for rows not used)."""
    label, k_pt, t_pt, inside, s_pt = pts.label, pts.k, pts.t, pts.inside, pts.s
    step = frame.s[1] - frame.s[0]
    on, t = structure.on, structure.t
    valid = on.sum(axis=0) >= 2
    idx = np.flatnonzero(valid)
    a, b = int(idx[0]), int(idx[-1]) + 1
    s = frame.s[a:b] - frame.s[a]
    on, t = on[:, a:b], t[:, a:b]
    used = np.flatnonzero(on.any(axis=1))
    med = np.array([np.nanmedian(t[i]) for i in used])
    ordered = used[np.argsort(-med, kind="stable")]
    patterns = [_mark_pattern(s_pt[(label == old) & inside], cfg) for old in ordered]
    residuals = []
    for old in ordered:
        sel = (label == old) & inside
        resid = t_pt[sel] - fit.t[old, k_pt[sel]]
        residuals.append(resid[np.isfinite(resid)])
    widths = marking_widths(residuals)
    rows = [
        Boundary(id=-1, t=np.where(on[old], t[old], np.nan), mark_type=kind,
                 mark_width=round(width, 3) if width is not None else 0.15, dash_length=dash, gap_length=gap)
        for old, width, (kind, dash, gap) in zip(ordered, widths, patterns, strict=True)
    ]
    rows_on, rows_t = on[ordered], t[ordered]
    if cfg.unpainted_lanes:
        from lidar2xodr.unpainted_lanes import implied_edges  # it uses this module's helpers
        broken = np.array([kind == "broken" and dash is not None and gap is not None
                           for kind, dash, gap in patterns], dtype=bool)
        solid = np.array([kind == "solid" for kind, _, _ in patterns], dtype=bool)
        extra_on, extra_t = implied_edges(rows_on, rows_t, broken, solid, step, cfg)
        if len(extra_on):
            rows_on, rows_t = np.vstack([rows_on, extra_on]), np.vstack([rows_t, extra_t])
            rows += [Boundary(id=-1, t=row, mark_type="none", mark_width=0.0) for row in extra_t]
            warnings.append(
                f"{len(extra_on)} lane(s) beyond a broken outermost line built without a seen outer edge "
                "(a broken line has a lane on both sides; width from its neighbour)"
            )
    final = np.argsort(-np.array([np.nanmedian(r.t) for r in rows]), kind="stable")
    rows_on, rows_t = rows_on[final], rows_t[final]
    boundaries = [rows[i] for i in final]
    for i, bnd in enumerate(boundaries):
        bnd.id = i
    position = np.argsort(final, kind="stable")
    new_id = np.full(len(on), -1, dtype=np.int64)
    new_id[ordered] = position[: len(ordered)]
    z_ref = _reference_z(k_pt, t_pt, pts.z, inside & (label >= 0) & np.isin(label, used), len(frame.s), step)
    reference = np.column_stack([frame.xy[a:b], z_ref[a:b]])
    sections, on_new, t_new = _sections(rows_on, rows_t, s, cfg.min_section_length_m)
    for i, bnd in enumerate(boundaries):
        bnd.t = t_new[i]
    for i, c in enumerate(candidates):
        c.superline = int(new_id[superline[i]]) if superline[i] < len(new_id) else -1
    warnings.extend(_unused_notes(fit.t[:, a:b], on_new, {int(old): int(new_id[old]) for old in ordered}, s))
    model = LaneModel(
        s=s,
        reference=reference,
        boundaries=boundaries,
        sections=sections,
        candidates=candidates,
        origin=cloud.origin,
        warnings=warnings,
    )
    return model, new_id


def _unused_notes(t_fit: np.ndarray, on: np.ndarray, row: dict[int, int], s: np.ndarray) -> list[str]:
    """One warning per measured line (row: its boundary id) for the stretches where it is not a lane boundary."""
    notes = []
    for x in range(len(t_fit)):
        used = on[row[x]] if x in row else np.zeros(len(s), dtype=bool)
        unused = np.isfinite(t_fit[x]) & ~used
        spans = [(a, b) for a, b in _runs(unused) if s[b - 1] - s[a] >= 1.0]
        if not spans:
            continue
        where = ", ".join(f"{s[a]:.0f}-{s[b - 1]:.0f}" for a, b in spans[:3]) + (
            " ..." if len(spans) > 3 else ""
        )
        t_med = float(np.nanmedian(t_fit[x][unused]))
        name = f"boundary {row[x]}" if x in row else "a marking line"
        notes.append(
            f"{name} ({t_med:+.1f} m from the reference) ignored on s {where} m: off the carriageway, "
            "a duplicate, or no stable lane beside it"
        )
    return notes


# --------------------------------------------------------------------------------------------
# lanes.json


def _num(a: np.ndarray) -> list:
    """Array as nested lists with NaN as null (JSON has no NaN)."""
    arr = np.asarray(a, dtype=np.float64)
    return (
        [None if not math.isfinite(v) else float(v) for v in arr.ravel()]
        if arr.ndim == 1
        else [_num(row) for row in arr]
    )


def save_lanes(model: LaneModel, path: str | Path, network: dict | None = None) -> None:
    """Write the lane model as JSON (format `lidar2xodr.lanes/1`, NaN written as null), atomically.

    Each section carries `divider_id` (null: one direction) and `lane_types` (one of `LANE_TYPES` per
    lane, left to right; null: every lane driving); files written before them load with no divider
    and driving lanes. `network` (from `branches.save_network`) adds the roads and junction links of a
    carriageway that splits or merges; readers of the single road ignore it."""
    data = model_dict(model)
    if network is not None:
        data["network"] = network
    write_text(path, json.dumps(data, separators=(",", ":"), sort_keys=True) + "\n")


def model_dict(model: LaneModel) -> dict:
    """The JSON-ready dictionary of one lane model (NaN as null)."""
    return {
        "format": FORMAT,
        "s": _num(model.s),
        "reference": _num(model.reference),
        "boundaries": [
            {
                "id": b.id,
                "t": _num(b.t),
                "mark_type": b.mark_type,
                "mark_width": float(b.mark_width),
                "dash_length": b.dash_length,
                "gap_length": b.gap_length,
            }
            for b in model.boundaries
        ],
        "sections": [
            {
                "s_start": sec.s_start,
                "s_end": sec.s_end,
                "boundary_ids": list(sec.boundary_ids),
                "divider_id": sec.divider_id,
                "lane_types": None if sec.lane_types is None else list(sec.lane_types),
            }
            for sec in model.sections
        ],
        "candidates": [
            {
                "id": c.id,
                "superline": c.superline,
                "centers": _num(c.centers),
                "directions": _num(c.directions),
                "cluster_ids": [int(i) for i in c.cluster_ids],
            }
            for c in model.candidates
        ],
        "origin": {
            "lat": model.origin.lat,
            "lon": model.origin.lon,
            "alt": model.origin.alt,
            "proj": model.origin.proj,
        },
        "warnings": list(model.warnings),
    }


def _arr(value: object, shape_tail: tuple[int, ...], where: str, name: str) -> np.ndarray:
    try:
        arr = np.array(
            [[np.nan if v is None else v for v in row] for row in value]
            if shape_tail
            else [np.nan if v is None else v for v in value],
            dtype=np.float64,
        )  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise InputError(where, f"{name} is not a list of numbers") from None
    if len(arr) == 0 and shape_tail:
        arr = arr.reshape(0, *shape_tail)
    if arr.shape[1:] != shape_tail:
        raise InputError(
            where,
            f"{name} has shape {arr.shape}, expected (n, {', '.join(map(str, shape_tail))})"
            if shape_tail
            else f"{name} has shape {arr.shape}, expected (n,)",
        )
    return arr


def _lane_types(value: object, n_lanes: int, where: str) -> list[str] | None:
    """A section's lane types as read (absent or null: every lane driving, as files written before them)."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != n_lanes or not all(v in LANE_TYPES for v in value):
        raise InputError(where, f"lane_types {value!r} is not a list of {n_lanes} of {', '.join(LANE_TYPES)}")
    return [str(v) for v in value]


def load_lanes(path: str | Path) -> LaneModel:
    """Read lanes.json written by `save_lanes`; InputError naming the file and element when malformed."""
    return model_from(read_lanes_json(path), path)


def read_lanes_json(path: str | Path) -> dict:
    """The parsed lanes.json, checked to be a lane model; InputError naming the file otherwise."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "lane model not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read the lane model: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(path, f"not a lane model (expected format {FORMAT!r})")
    return data


def model_from(data: dict, path: str | Path) -> LaneModel:
    """A lane model from its dictionary (`model_dict`); InputError naming `path` when malformed."""
    try:
        s = _arr(data["s"], (), str(path), "s")
        ref = _arr(data["reference"], (3,), str(path), "reference")
        if len(ref) != len(s):
            raise InputError(path, f"reference has {len(ref)} rows for {len(s)} stations")
        boundaries = []
        for i, b in enumerate(data["boundaries"]):
            where = f"{path} boundary {b.get('id', i)}"
            t = _arr(b["t"], (), where, "t")
            if len(t) != len(s):
                raise InputError(where, f"t has {len(t)} values for {len(s)} stations")
            if b["mark_type"] not in MARK_TYPES:
                raise InputError(where, f"mark_type {b['mark_type']!r} (solid, broken or none)")
            boundaries.append(
                Boundary(
                    int(b["id"]),
                    t,
                    str(b["mark_type"]),
                    float(b["mark_width"]),
                    None if b["dash_length"] is None else float(b["dash_length"]),
                    None if b["gap_length"] is None else float(b["gap_length"]),
                )
            )
        ids = {b.id for b in boundaries}
        sections = []
        for j, sec in enumerate(data["sections"]):
            bad = [i for i in sec["boundary_ids"] if i not in ids]
            if bad:
                raise InputError(f"{path} section {j}", f"names unknown boundaries {bad}")
            divider = sec.get("divider_id")
            if divider is not None and divider not in sec["boundary_ids"][1:-1]:
                raise InputError(
                    f"{path} section {j}", f"divider_id {divider} is not an inner boundary of the section"
                )
            sections.append(
                LaneSection(
                    float(sec["s_start"]),
                    float(sec["s_end"]),
                    [int(i) for i in sec["boundary_ids"]],
                    None if divider is None else int(divider),
                    _lane_types(sec.get("lane_types"), len(sec["boundary_ids"]) - 1, f"{path} section {j}"),
                )
            )
        candidates = []
        for c in data["candidates"]:
            where = f"{path} candidate {c.get('id')}"
            candidates.append(
                Candidate(
                    int(c["id"]),
                    _arr(c["centers"], (3,), where, "centers"),
                    _arr(c["directions"], (2,), where, "directions"),
                    np.asarray(c["cluster_ids"], dtype=np.int64),
                    int(c["superline"]),
                )
            )
        o = data["origin"]
        origin = GeoOrigin(o["lat"], o["lon"], float(o["alt"]), o["proj"])
        warnings = [str(w) for w in data["warnings"]]
    except (KeyError, TypeError, AttributeError) as exc:
        raise InputError(path, f"malformed lane model: missing or wrong field {exc}") from None
    return LaneModel(
        s=s,
        reference=ref,
        boundaries=boundaries,
        sections=sections,
        candidates=candidates,
        origin=origin,
        warnings=warnings,
    )
