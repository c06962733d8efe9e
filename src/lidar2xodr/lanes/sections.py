"""Lane sections: stretches with a constant set of boundaries."""

from __future__ import annotations

import numpy as np

from lidar2xodr.data import LaneSection


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
