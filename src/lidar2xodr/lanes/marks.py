"""Road marks: the dash pattern and the painted width of every line, and where a line's paint changes."""

from __future__ import annotations

import numpy as np
from scipy.stats import norm

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import Boundary, LaneSection

_SPREAD: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
_MAX_HOLE_M = 2.5  # the longest hole a far, sparse line shows inside paint (the run-split limit's cap)


def _mark_pattern(s_pts: np.ndarray, cfg: LanesConfig) -> tuple[str, float | None, float | None]:
    """Solid or broken from the painted runs along s; dash and gap lengths for broken lines.

    Runs are split at holes over 1-2.5 m (10 median point spacings: far, sparse lines have holes
    inside their dashes); the length-weighted median run decides
    (occlusions shorten solid runs but leave them far longer than a dash); dash and gap are the
    medians of the runs and holes of dash size.
    """
    if len(s_pts) < 10:
        return "solid", None, None
    lengths, holes = _runs_and_holes(s_pts)
    order = np.argsort(lengths)
    cum = np.cumsum(lengths[order])
    if cum[-1] <= 0:
        return "solid", None, None
    weighted_median = lengths[order][np.searchsorted(cum, cum[-1] / 2.0)]
    if weighted_median > cfg.solid_min_run_m:
        return "solid", None, None
    dashes = lengths[(lengths >= 1.0) & (lengths <= cfg.solid_min_run_m)]
    holes = holes[holes <= 3.0 * cfg.solid_min_run_m]
    dash = round(float(np.median(dashes)), 2) if len(dashes) else None
    gap = round(float(np.median(holes)), 2) if len(holes) else None
    return "broken", dash, gap


def _runs_and_holes(s_pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lengths of the painted runs along s and of the holes between them (runs split at holes over 1-2.5 m:
    10 median point spacings, capped at `_MAX_HOLE_M`)."""
    s = np.sort(s_pts)
    spacing = np.diff(s)
    hole = float(np.clip(10.0 * np.median(spacing), 1.0, _MAX_HOLE_M))
    cut = np.flatnonzero(spacing > hole)
    first = np.concatenate([[0], cut + 1])
    last = np.concatenate([cut, [len(s) - 1]])
    return s[last] - s[first], s[first[1:]] - s[last[:-1]]


def section_marks(sections: list[LaneSection], boundaries: list[Boundary], row_s: dict[int, np.ndarray],
                  s0: float, cfg: LanesConfig) -> None:
    """`LaneSection.marks`: each painted boundary typed again from its own points inside each section
    (`_mark_pattern`), where they span `mark_stretch_min_m`; kept only where that differs from the
    boundary's type over its whole length, and only where the gaps agree: broken where the median gap
    is longer than any hole a solid line seen far away shows (`_MAX_HOLE_M`), solid where it is not. A
    stretch is less evidence than the whole line: a far solid edge's short runs between 1-2.5 m holes
    read as dashes, and one long run among dashes 12 m apart (paint across a junction) as solid.

    `row_s[id]`: the sorted stations of the boundary's points (absent: an implied, unpainted border);
    `s0`: the station of the model's s = 0.
    """
    for sec in sections:
        marks: dict[int, str] = {}
        for bid in sec.boundary_ids:
            b = boundaries[bid]
            s_pts = row_s.get(bid)
            if s_pts is None or b.mark_type == "none":
                continue
            part = s_pts[np.searchsorted(s_pts, sec.s_start + s0):np.searchsorted(s_pts, sec.s_end + s0)]
            if len(part) < 10 or part[-1] - part[0] < cfg.mark_stretch_min_m:
                continue
            kind = _mark_pattern(part, cfg)[0]
            holes = _runs_and_holes(part)[1]
            if (kind == "broken") != bool(len(holes) and np.median(holes) > _MAX_HOLE_M):
                continue
            if kind != b.mark_type:
                marks[bid] = kind
        sec.marks = marks or None


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
