"""Marking points labelled to the fitted lines (by their candidates, then by distance), forks followed."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import Candidate

_FORK_BACK = (20, 60)  # stations before a fork whose offset to the neighbour a continuing line keeps through it


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
        free = np.flatnonzero(~np.isfinite(kept[b]) & np.isfinite(fitted[b]))
        if not len(free):
            continue
        close = np.abs(kept[:, free] - fitted[b, free][None, :]) < tol  # row b is NaN there: never close
        take = free[~close.any(axis=0)]
        out[b, take] = fitted[b, take]
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
        others = np.delete(np.arange(len(curves)), b)
        for end, direction in ((fin[0], -1), (fin[-1], 1)):
            for i in range(1, reach + 1):
                k = end + direction * i
                if k < 0 or k >= m or np.any(np.abs(curves[others, k] - c[end]) < tol):
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
    """Superline of every point: the nearest fitted curve at its station, within assign_distance_m.

    Each point is measured only against the curves that exist at its station (a long drive's
    stations hold a few of its ~90 curves), in row order, so ties go to the lower row as in a
    search over all rows."""
    label = np.full(len(t), -1, dtype=np.int64)
    col, row = np.nonzero(np.isfinite(curves).T)  # by station, rows ascending
    depth = int(np.bincount(col, minlength=curves.shape[1]).max(initial=0))
    if depth == 0:
        return label
    place = np.arange(len(col)) - np.searchsorted(col, col)
    rows = np.zeros((curves.shape[1], depth), dtype=np.int64)
    vals = np.full((curves.shape[1], depth), np.inf)
    rows[col, place] = row
    vals[col, place] = curves[row, col]
    for a in range(0, len(t), 200000):
        sl = slice(a, a + 200000)
        d = np.abs(vals[k[sl]] - t[sl][:, None])
        d = np.where(np.isnan(d), np.inf, d)
        best = np.argmin(d, axis=1)
        at = np.arange(len(best))
        ok = (d[at, best] <= cfg.assign_distance_m) & inside[sl]
        label[sl] = np.where(ok, rows[k[sl], best], -1)
    return label
