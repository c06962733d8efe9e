"""The station frame: the road axis the lanes are measured along, and points projected onto it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import Candidate
from lidar2xodr.errors import InputError
from lidar2xodr.lanes.lookups import Lookups, Segments, _group_median
from lidar2xodr.lanes.smoothing import _lam, _whittaker

_PROJECT_BLOCK = 1 << 18  # points per block of `Frame.project`
_LINE_FRAME_GAIN = 1.5  # the longest line replaces the first frame only when this much more paint runs along it
_LINE_EXT_M = 40.0  # the line axis runs on this far beyond both ends of its line


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
        """Station, signed offset (left positive) and whether the foot lies inside the frame.

        In blocks of `_PROJECT_BLOCK` points: the working memory stays the same on any drive."""
        if len(xy) <= _PROJECT_BLOCK:
            return self._project(xy)
        parts = [self._project(xy[a:a + _PROJECT_BLOCK]) for a in range(0, len(xy), _PROJECT_BLOCK)]
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))  # type: ignore[return-value]

    def _project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    frame is not changed by it, unless its road explains less than half this line's span
    (`build._along_longest_line`).
    """
    best, length = None, 0.0
    for c in pieces:
        xy = np.asarray(c.centers, dtype=np.float64)[:, :2]
        arc = float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))) if len(xy) > 1 else 0.0
        if len(xy) >= 3 and arc > length:
            best, length = xy, arc
    if best is None:
        return None
    ext = np.arange(2.0, _LINE_EXT_M + 1e-9, 2.0)[:, None]
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


def _stations(frame: Frame, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest station, offset, inside flag and exact station of every point."""
    s, t, inside = frame.project(xy)
    k = np.clip(np.rint(s / (frame.s[1] - frame.s[0])).astype(np.int64), 0, len(frame.s) - 1)
    return k, t, inside, s


@dataclass
class _Points:
    """Marking points in the current frame: station index, offset, station, inside flag, superline."""

    k: np.ndarray
    t: np.ndarray
    s: np.ndarray
    inside: np.ndarray
    label: np.ndarray
    z: np.ndarray
