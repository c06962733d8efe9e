"""Whittaker smoothing of offsets along the stations, robust (Tukey) and banded."""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solveh_banded


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


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of every run of True."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=False))


def _groups(keys: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """(key, ascending indices of its items) for every distinct key, keys ascending: one stable sort
    instead of a comparison over all items per key (a long line has hundreds of blocks)."""
    order = np.argsort(keys, kind="stable")
    ids, first = np.unique(keys[order], return_index=True)
    return list(zip(ids.tolist(), np.split(order, first[1:]), strict=True)) if len(keys) else []
