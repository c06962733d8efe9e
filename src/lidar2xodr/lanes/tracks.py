"""Line tracks: every marking line as a fitted offset t(s) along the frame, with where it was seen."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidar2xodr.lanes.smoothing import _groups, _runs, _tukey_fit, _whittaker, _whittaker_points

_ABSENT_RUN = 20  # stations (m) a line must be seen to be absent before it is no longer carried
_ALONG_SLOPE = 0.1  # lines joined across a gap run along the road there (within ~6 deg of the frame)
_DOUBLE_SPACING_SPREAD_M = 0.1  # a double line's two lines keep their spacing within this over its blocks


_SHIFT_BLOCK = 10  # stations per block of the lines' common shift (half a dash period: each dash counts)
_SHIFT_MIN_LINE = 60  # stations a line is fitted over to tell a shift of the road (short pieces are clutter)
_SHIFT_MIN_M = 0.3  # a line this far off its curve in a block is off it
_SHIFT_PAD = 2  # blocks either side of a shift smoothed with it, back to 0
_SHIFT_ROUNDS = 3  # the first fits follow a shift in part: what is left is found again on the refits
_WINDOW_PAD = 2 * _ABSENT_RUN + 90  # stations around a line's points its fit looks at (end pieces: 2 * _ABSENT_RUN)


def _robust_curve(
    k: np.ndarray, t: np.ndarray, n: int, lam: float, iters: int = 3, drift: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_robust_curve_window` on the stations around the line's points only (`_WINDOW_PAD` either
    side, within 0..n-1): every step of the fit looks no farther, so the numbers are the same as on
    all n stations, and a long drive's many short lines cost their own length, not the drive's."""
    out = np.full(n, np.nan)
    observed = np.zeros(n, dtype=bool)
    if len(t) == 0:
        return out, np.ones(0), observed
    base, curve, w_pt, seen = _robust_curve_span(k, t, n, lam, iters, drift)
    out[base : base + len(curve)], observed[base : base + len(curve)] = curve, seen
    return out, w_pt, observed


def _robust_curve_span(
    k: np.ndarray, t: np.ndarray, n: int, lam: float, iters: int = 3, drift: np.ndarray | None = None
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """`_robust_curve` as (first station, curve and observed flags from there on, the points' weights):
    NaN and False on every station outside them. k must not be empty."""
    base, end = max(int(k.min()) - _WINDOW_PAD, 0), min(int(k.max()) + _WINDOW_PAD + 1, n)
    local = None if drift is None else drift[base:end]
    curve, w_pt, seen = _robust_curve_window(k - base, t, end - base, lam, iters, local)
    return base, curve, w_pt, seen


def _robust_curve_window(
    k: np.ndarray, t: np.ndarray, n: int, lam: float, iters: int = 3, drift: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust t(s) on stations: Whittaker over the points' span with Tukey weights; NaN outside.

    Short islands of points (at most 10 m: a dash, a blob) that sit off the curve fitted without
    them (local refit over +-80 m) are dropped: a blob in a gap or an occluded stretch would
    otherwise bend the line towards it. Beyond the refit's end the line is continued parallel to the
    frame, or, with `drift` (the lines' common offset along the stations, `_common_drift`), parallel
    to the other lines. Returns the curve, the points' final weights and which stations are observed
    (3 points or more, in runs of 3 stations or more).
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
    by_station = np.argsort(k, kind="stable")
    k_sorted = k[by_station]

    def on_stations(first: int, end: int) -> np.ndarray:
        """Indices of the points on stations first..end-1, in their given order (sums over them stay exact)."""
        i, j = np.searchsorted(k_sorted, [first, end])
        return np.sort(by_station[i:j])

    for a, b in _runs(has_points | (np.convolve(has_points, np.ones(3), "same") >= 2)):
        if b - a > 10:
            continue
        island = on_stations(a - 2, b + 2)
        lo, hi = max(a - 80, 0), min(b + 80, n)
        near = on_stations(lo, hi)
        near = near[((k[near] < a - 2) | (k[near] >= b + 2)) & (w_pt[near] > 0)]
        if len(near) < 10:
            continue
        z = _whittaker_points(k[near] - lo, t[near], w_pt[near], hi - lo, lam)
        span = np.flatnonzero(np.isfinite(z))
        edge = np.clip(k[island] - lo, span[0], span[-1])
        pred = z[edge]
        if drift is not None:
            pred = pred + drift[k[island]] - drift[edge + lo]
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


def _refit_double(base: int, curve: np.ndarray, k: np.ndarray, t: np.ndarray, k_free: np.ndarray,
                  t_free: np.ndarray, m: int, lam: float, double: tuple[float, int],
                  drift: np.ndarray | None = None) -> tuple[int, np.ndarray, np.ndarray, np.ndarray] | None:
    """A line's `_robust_curve_span` again where its points (k, t), with the unlabelled points (sorted
    by station) within `double[0]` of its curve (on stations base.., NaN where not fitted), form a
    double line (`_fold_double_lines`): the second line's points lie farther from the first than
    points are labelled to it, so they are not the line's yet. None where there is no double line."""
    fin = np.flatnonzero(np.isfinite(curve))
    if double[0] <= 0.0 or len(fin) == 0:
        return None
    lo, hi = np.searchsorted(k_free, [base + fin[0], base + fin[-1] + 1])
    near = np.abs(t_free[lo:hi] - curve[k_free[lo:hi] - base]) <= double[0]
    k_all = np.concatenate([k, k_free[lo:hi][near]])
    t_all = np.concatenate([t, t_free[lo:hi][near]])
    t_fold, folded = _fold_double_lines(k_all, t_all, lam, double)
    if not folded.any():
        return None
    keep = (np.arange(len(k_all)) < len(k)) | folded
    return _robust_curve_span(k_all[keep], t_fold[keep], m, lam, drift=drift)


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


def _fold_double_lines(k: np.ndarray, t: np.ndarray, lam: float, double: tuple[float, int]
                       ) -> tuple[np.ndarray, np.ndarray]:
    """One line's points with every double line folded onto its midpoint.

    A double line (two parallel lines, solid or broken, painted on one lane border: a no-overtaking
    centre line, a 2+1 road's divider) gives one boundary two modes of points a few decimetres apart;
    the robust fit would keep one of them, or hop between them. Per block of `double[1]` stations
    the points' offsets from a smooth trend through all of them are split into two clusters; blocks
    whose two clusters are resolved (`_two_modes`) and at most `double[0]` apart, in runs of three
    blocks or more with the same spacing (within `_DOUBLE_SPACING_SPREAD_M`: the two lines of a
    taper or a gore converge or spread), move each cluster by half the spacing onto the midpoint.
    Other points are returned unchanged. Returns the offsets and which points lie in a double line's
    blocks.
    """
    max_spacing, block = double
    folded = np.zeros(len(t), dtype=bool)
    if max_spacing <= 0.0 or len(t) < 40:
        return t, folded
    k0 = int(k.min())
    trend = _whittaker_points(k - k0, t, np.ones(len(t)), int(k.max()) - k0 + 1, 256.0 * lam)
    r = t - trend[k - k0]
    found: dict[int, tuple[float, float, np.ndarray, np.ndarray]] = {}
    for b, idx in _groups(k // block):
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


@dataclass
class _Fit:
    """The lines that can be kept (`rows` of all B lines; most of a long drive's are short pieces that
    never are) on every station."""

    t: np.ndarray  # (R, M)
    support: np.ndarray  # (B,) points used, every line
    rows: np.ndarray | None = None  # (R,) ascending row of each among the B lines (None: 0..R-1)

    def __post_init__(self) -> None:
        if self.rows is None:
            self.rows = np.arange(len(self.t))

    def row_of(self, line: np.ndarray | int) -> np.ndarray:
        """Row of t holding each line (every one must be held)."""
        return np.searchsorted(self.rows, line)


@dataclass
class _Lines:
    """Every fitted line by its span: line b's offsets `t[b]` and observed flags `observed[b]` on
    stations lo[b].. (NaN and False on all others; empty, with lo m, where it is not fitted). A 20 km
    drive fits 2,257 lines 35 stations long on average, on 20,000 stations."""

    m: int
    lo: np.ndarray  # (B,)
    t: list[np.ndarray]
    observed: list[np.ndarray]
    support: np.ndarray  # (B,) points used

    @classmethod
    def from_spans(cls, m: int, fits: dict[int, tuple[int, np.ndarray, np.ndarray]], support: np.ndarray
                   ) -> _Lines:
        """Lines from (first station, curve, observed) of each fitted line, kept on the curve's finite span."""
        n = len(support)
        lo = np.full(n, m, dtype=np.int64)
        t = [np.empty(0)] * n
        observed = [np.zeros(0, dtype=bool)] * n
        for b, (base, curve, seen) in fits.items():
            fin = np.flatnonzero(np.isfinite(curve))
            if len(fin):
                lo[b], t[b], observed[b] = base + fin[0], curve[fin[0] : fin[-1] + 1], seen[fin[0] : fin[-1] + 1]
        return cls(m, lo, t, observed, support)

    @classmethod
    def from_dense(cls, t: np.ndarray, observed: np.ndarray) -> _Lines:
        """Lines from a (B, M) array of offsets (NaN where none) and its observed flags."""
        fits = {b: (0, t[b], observed[b]) for b in range(len(t))}
        return cls.from_spans(t.shape[1], fits, np.zeros(len(t)))

    def spans(self) -> tuple[np.ndarray, np.ndarray]:
        """First and last station of every line (m and -1 where none)."""
        lens = np.array([len(x) for x in self.t], dtype=np.int64)
        return self.lo, np.where(lens > 0, self.lo + lens - 1, -1)

    def finite_counts(self) -> np.ndarray:
        return np.array([int(np.isfinite(x).sum()) for x in self.t], dtype=np.int64)

    def dense(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), M) offsets of the lines `rows`, NaN where not fitted."""
        out = np.full((len(rows), self.m), np.nan)
        for i, b in enumerate(rows):
            out[i, self.lo[b] : self.lo[b] + len(self.t[b])] = self.t[b]
        return out

    def value_at(self, row: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Offset of line row[i] at station k[i] (NaN where it has none)."""
        return self.lookup()(row, k)

    def lookup(self) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """`value_at` with the lines laid end to end once, for several lookups while they do not change."""
        lens = np.array([len(x) for x in self.t], dtype=np.int64)
        start = np.concatenate([[0], np.cumsum(lens)[:-1]]) if len(lens) else lens
        flat = np.concatenate(self.t) if len(self.t) else np.empty(0)

        def value_at(row: np.ndarray, k: np.ndarray) -> np.ndarray:
            j = k - self.lo[row]
            ok = (j >= 0) & (j < lens[row])
            out = np.full(len(k), np.nan)
            out[ok] = flat[start[row[ok]] + j[ok]]
            return out

        return value_at


def _follow_shift(fit: Callable[[np.ndarray], _Lines], k: np.ndarray, t: np.ndarray, label: np.ndarray,
                  inside: np.ndarray, lam_shift: float, max_double: float) -> _Lines:
    """The lines `fit` gives for offsets t; where the road as a whole moves across the frame faster
    than a line's smoothing follows (`_common_shift`), every line fitted again to its offsets less
    that shift, and the shift added back (`_SHIFT_ROUNDS` rounds: the first fits follow it in part)."""
    lines = fit(t)
    shift = np.zeros(lines.m)
    for _ in range(_SHIFT_ROUNDS):
        more = _common_shift(lines, k, t - shift[k], label, inside, lam_shift, max_double)
        if more is None:
            break
        shift = shift + more
        lines = fit(t - shift[k])
    if not shift.any():
        return lines
    for b in range(len(lines.t)):
        lines.t[b] = lines.t[b] + shift[lines.lo[b] : lines.lo[b] + len(lines.t[b])]
    return lines


def _common_shift(lines: _Lines, k: np.ndarray, t: np.ndarray, label: np.ndarray, inside: np.ndarray,
                  lam_shift: float, max_double: float = 0.0) -> np.ndarray | None:
    """The road's lateral shift across the frame where the lines' own fits cannot follow it, or None.

    A lane shift (road works; a carriageway moved over at an interchange: 1-3 m across 30-60 m) moves
    every line alike; each line's smoothing (`boundary_smoothing_m`) draws it straight through, and
    the dashes in the shift, each off the curve, are dropped one by one as blobs. Per block of
    `_SHIFT_BLOCK` stations each long line (fitted over `_SHIFT_MIN_LINE` stations or more) with 3
    points or more there gives the median offset of its points from its curve (on a double line, whose
    curve runs between its two lines, a block holds one of them or both: where its points over the
    block and `_SHIFT_PAD` blocks each side form two modes within `max_double`, the offset is taken
    from the nearer mode to their midpoint, as the fold takes it); where two or more lines
    do, two thirds of them lie off by more than `_SHIFT_MIN_M` on one side and none that far on the
    other, the block's shift is their median (else 0: one line leaving the others is a ramp or a
    taper, lines moving apart a lane opening, not the road moving). A dense solid line's fit follows
    a shift in part, so it is the broken lines, whose dashes are dropped, that show it most.
    Shifted blocks (with `_SHIFT_PAD` blocks either side) are smoothed with `lam_shift`; the shift is
    exactly 0 elsewhere, so lines away from it are fitted as before."""
    starts, ends = lines.spans()
    long_line = (ends - starts + 1) >= _SHIFT_MIN_LINE
    use = (label >= 0) & inside
    use[use] = long_line[label[use]]
    if not use.any():
        return None
    lab, kk = label[use], k[use]
    r = t[use] - lines.value_at(lab, kk)
    ok = np.isfinite(r)
    lab, kk, r = lab[ok], kk[ok], r[ok]
    n_blk = int(lines.m // _SHIFT_BLOCK) + 1
    key = lab.astype(np.int64) * n_blk + kk // _SHIFT_BLOCK
    order = np.lexsort((r, key))
    key_s, r_s = key[order], r[order]
    uniq, first, count = np.unique(key_s, return_index=True, return_counts=True)
    enough = count >= 3
    med = r_s[first[enough] + count[enough] // 2]
    if max_double > 0.0:
        for i, g in enumerate(uniq[enough]):
            own = g - g % n_blk  # the line's first key: the window stays on its own points
            lo, hi = np.searchsorted(key_s, [max(g - _SHIFT_PAD, own), min(g + _SHIFT_PAD + 1, own + n_blk)])
            modes = _two_modes(r_s[lo:hi])
            if modes is not None and modes[1] - modes[0] <= max_double:
                near = modes[1] if abs(med[i] - modes[1]) < abs(med[i] - modes[0]) else modes[0]
                med[i] += 0.5 * (modes[0] + modes[1]) - near
    g_blk = (uniq[enough] % n_blk).astype(np.int64)
    by_blk = np.argsort(g_blk, kind="stable")
    g_blk, med = g_blk[by_blk], med[by_blk]
    value = np.zeros(n_blk)
    known = np.zeros(n_blk, dtype=bool)
    shifted = np.zeros(n_blk, dtype=bool)
    b_ids, b_first, b_count = np.unique(g_blk, return_index=True, return_counts=True)
    for bid, f, c in zip(b_ids, b_first, b_count, strict=True):
        if c < 2:
            continue
        v = med[f : f + c]
        known[bid] = True
        for sign in (1.0, -1.0):
            if 3 * np.count_nonzero(sign * v > _SHIFT_MIN_M) >= 2 * c and not np.any(sign * v < -_SHIFT_MIN_M):
                value[bid] = float(np.median(v))
                shifted[bid] = True
    if not shifted.any():
        return None
    shift = np.zeros(lines.m)
    for a, b in _runs(shifted):
        a, b = max(a - _SHIFT_PAD, 0), min(b + _SHIFT_PAD, n_blk)
        lo, hi = a * _SHIFT_BLOCK, min(b * _SHIFT_BLOCK, lines.m)
        if hi - lo < 4:
            continue
        kb = np.flatnonzero(known[a:b]) + a
        centre = np.minimum(kb * _SHIFT_BLOCK + _SHIFT_BLOCK // 2, hi - 1) - lo
        y = np.zeros(hi - lo)
        w = np.zeros(hi - lo)
        y[centre], w[centre] = value[kb], 1.0
        y[[0, -1]], w[[0, -1]] = 0.0, 1.0  # the shift starts and ends at 0
        shift[lo:hi] = _whittaker(y, w, lam_shift)
    return shift


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
    end_dash_drift: bool = False,
    lam_shift: float | None = None,
) -> _Lines:
    """Every labelled line's t(s) (`_robust_curve` of its points, double lines folded onto their
    midpoint: `double` = (largest spacing, block stations), see `_fold_double_lines`), bridged across
    unobserved stretches. With `end_dash_drift` (`LanesConfig.end_dash_drift`), a line whose end dash
    was dropped is fitted again, its end dashes judged against the line continued with the lines'
    common drift (`_common_drift`). With `lam_shift`, lane shifts are followed (`_follow_shift`)."""
    if lam_shift is not None:
        def fit(offsets: np.ndarray) -> _Lines:
            return _fit_boundaries(k, offsets, label, inside, n_sl, m, lam, gap, parallel_m, double, end_dash_drift)

        return _follow_shift(fit, k, t, label, inside, lam_shift, double[0])
    support = np.zeros(n_sl)
    use = (label >= 0) & inside
    order = np.argsort(label[use], kind="stable")
    lab, kk, tt = label[use][order], k[use][order], t[use][order]
    bounds = np.searchsorted(lab, np.arange(n_sl + 1))
    free = (label < 0) & inside
    by_k = np.argsort(k[free], kind="stable")
    k_free, t_free = k[free][by_k], t[free][by_k]
    fits: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
    cut_end: list[int] = []
    for b in range(n_sl):
        sl = slice(bounds[b], bounds[b + 1])
        if bounds[b + 1] - bounds[b] < 10:
            continue
        base, curve, w, seen = _robust_curve_span(kk[sl], tt[sl], m, lam)
        again = _refit_double(base, curve, kk[sl], tt[sl], k_free, t_free, m, lam, double)
        if again is not None:
            base, curve, w, seen = again
        fits[b] = (base, curve, seen)
        support[b] = float(w.sum())
        if end_dash_drift and _dropped_beyond_ends(kk[sl], base, curve):
            cut_end.append(b)
    if cut_end:
        drift = _common_drift(_Lines.from_spans(m, fits, support).dense(np.array(sorted(fits), dtype=np.int64)))
        for b in cut_end:
            sl = slice(bounds[b], bounds[b + 1])
            base, curve, w, seen = _robust_curve_span(kk[sl], tt[sl], m, lam, drift=drift)
            again = _refit_double(base, curve, kk[sl], tt[sl], k_free, t_free, m, lam, double, drift)
            if again is not None:
                base, curve, w, seen = again
            fits[b] = (base, curve, seen)
            support[b] = float(w.sum())
    lines = _Lines.from_spans(m, fits, support)
    _bridge_gaps(lines, gap, parallel_m)
    return lines


def _dropped_beyond_ends(k: np.ndarray, base: int, curve: np.ndarray) -> bool:
    """Whether some of a line's points lie before or after its fitted curve (on stations base..; an
    end dash was dropped)."""
    fin = np.flatnonzero(np.isfinite(curve))
    return len(fin) > 0 and bool(np.any((k < base + fin[0]) | (k > base + fin[-1])))


def _common_drift(curves: np.ndarray) -> np.ndarray:
    """The lines' common offset along the stations: the median slope of the fitted lines at each
    station, summed (0 where no line is fitted). Where the frame runs at an angle to the road (its
    first stretch, built from fewer lines), every line's offset drifts alike; a line continued
    parallel to the frame would leave its own next dash behind, and each dropped dash makes the next
    one the line's end."""
    slope = np.diff(curves, axis=1)
    has = np.isfinite(slope).any(axis=0)
    g = np.zeros(slope.shape[1])
    g[has] = np.nanmedian(slope[:, has], axis=0)
    return np.concatenate([[0.0], np.cumsum(g)])


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


def _bridge_gaps(lines: _Lines, gap: int, parallel_m: float) -> None:
    """Across unobserved stretches longer than `gap` stations a line keeps its lane width to the
    neighbour best observed there (interpolated between the ends), instead of a straight chord in
    the frame, which bends wherever the frame does. Neighbours whose offset to the line changes
    least across the gap (in steps of `parallel_m`) come first: one that diverges from the line
    there (an exit lane's edge leaving where the edge line turns into a broken one) would carry
    the bridge out with it. Among those, a neighbour that keeps its spacing to the other lines inside
    the gap comes before one that strays from them and comes back (`_moves_within`: on a 2+1 road the
    centre line moves across a lane and back, the passing lane's line was bridged along it out to the
    edge). Only lines whose spans hold the gap's ends are looked at."""
    first, last = lines.spans()
    m, ts, obs = lines.m, lines.t, lines.observed

    def at(b: int, j: int) -> float:
        i = j - int(first[b])
        return float(ts[b][i]) if 0 <= i < len(ts[b]) else math.nan

    for b in range(len(ts)):
        if last[b] < 0:
            continue
        for r0, r1 in _runs(~obs[b]):
            g0, g1 = int(first[b] + r0), int(first[b] + r1)
            if g1 - g0 < gap or g0 == 0 or g1 >= m:
                continue
            best, best_key = None, None
            spanning = [int(nb) for nb in np.flatnonzero((first <= g0 - 1) & (last >= g1)) if nb != b
                        and np.all(np.isfinite(ts[nb][g0 - 1 - int(first[nb]) : g1 + 1 - int(first[nb])]))]
            for nb in spanning:
                f = int(first[nb])
                drift = abs((at(b, g1) - at(nb, g1)) - (at(b, g0 - 1) - at(nb, g0 - 1)))
                share = float(obs[nb][g0 - f : g1 - f].mean())
                steps = int(drift / parallel_m) if math.isfinite(drift) else 0
                key = (-steps, not _moves_within(ts, first, nb, spanning, g0, g1, parallel_m), share,
                       -abs(at(nb, g0) - at(b, g0)))
                if share >= 0.25 and (best_key is None or key > best_key):
                    best, best_key = int(nb), key
            if best is None:
                continue
            w0, w1 = at(b, g0 - 1) - at(best, g0 - 1), at(b, g1) - at(best, g1)
            f = (np.arange(g0, g1) - (g0 - 1)) / (g1 - g0 + 1)
            fb = int(first[best])
            ts[b][r0:r1] = ts[best][g0 - fb : g1 - fb] + w0 + (w1 - w0) * f


def _strays(own: np.ndarray, others: np.ndarray, tol: float) -> bool:
    """Whether a line's spacing to more than half of the other lines changes by over `tol` from its
    spacing at the first station. own (n,), others (K, n): offsets on the same stations, NaN where a
    line is absent; a line absent on every station after the first does not count."""
    shift = np.abs((own[None, :] - others) - (own[0] - others[:, :1]))
    seen = np.isfinite(shift[:, 1:]).any(axis=1)
    far = np.any(np.nan_to_num(shift, nan=0.0) > tol, axis=1)
    return 2 * int(np.sum(far & seen)) > int(seen.sum())


def _moves_within(ts: list[np.ndarray], first: np.ndarray, nb: int, spanning: list[int], g0: int, g1: int,
                  parallel_m: float) -> bool:
    """Whether line nb strays inside the gap g0..g1 from most other lines spanning it (`_strays`, from
    their spacing where the gap begins: a 2+1 road's centre line moving across a lane and back)."""
    def piece(j: int) -> np.ndarray:
        f = int(first[j])
        return ts[j][g0 - 1 - f : g1 - f]

    rest = [piece(q) for q in spanning if q != nb]
    return _strays(piece(nb), np.array(rest).reshape(len(rest), g1 - g0 + 1), parallel_m)


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


def _crossing_points(lines: _Lines, label: np.ndarray, k: np.ndarray, t: np.ndarray, tol: float) -> np.ndarray:
    """Points on a fitted line that runs across the road there (offset changing by more than
    `_ALONG_SLOPE` per station: a ramp, a crossing line), not along it."""
    row = np.maximum(label, 0)
    value_at = lines.lookup()
    with np.errstate(invalid="ignore"):
        return (label >= 0) & (np.abs(t - value_at(row, k)) <= tol) & (
            _slope_at(value_at, row, k, lines.m) > _ALONG_SLOPE)


def _slope_at(value_at: Callable[[np.ndarray, np.ndarray], np.ndarray], row: np.ndarray, k: np.ndarray,
              m: int) -> np.ndarray:
    """|np.gradient| along the stations (m of them) of the offsets `value_at(row, k)`, at (row, k) only:
    the same numbers without the whole (rows, stations) array."""
    if m < 2:
        return np.zeros(len(k))
    lo, hi = np.maximum(k - 1, 0), np.minimum(k + 1, m - 1)
    d = value_at(row, hi) - value_at(row, lo)
    return np.abs(np.where((k > 0) & (k < m - 1), d / 2.0, d))


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
