"""The cross-section, labelling and taper steps look only where a line can matter: the stations a
pair of lines shares, the curves that exist at a point's station, the stretch of road a straight
line can reach. On a 50 km drive the whole-array forms were cubic in its length (89 rows x 50,000
stations, 4 % filled; issue #14). Each rewrite must give exactly what the whole-array formula it
replaces gives; the references below are those formulas as they were written."""

from __future__ import annotations

import numpy as np
import pytest
from test_lanes_sparse_rows import _choose_carriageway_by_group

from lidar2xodr.config import LanesConfig
from lidar2xodr.lanes.labels import _hold_ends, _label_by_distance, _labelling_curves
from lidar2xodr.lanes.smoothing import _runs
from lidar2xodr.lanes.structure import (
    _check_adjacency,
    _choose_carriageway,
    _drop_duplicates,
    _finite_reach,
    _present_columns,
    _sorted_columns,
)
from lidar2xodr.lanes.tapers import _line_run, _SortedByS, _straight_lines

_LANES = np.array([7.0, 3.5, 0.0, -3.5, -7.0, -8.2, -10.5, -10.8, -25.0, -28.5])


def _road_rows(rng: np.random.Generator, n: int, m: int, lanes: np.ndarray = _LANES) -> np.ndarray:
    """n lines, each over its own stretch of m stations, at lane spacings (3.5 m, some 1-2.5 m or
    over 5 m wide, some within 0.5 m of another line), drifting, with gaps: more rows than any
    station holds."""
    t = np.full((n, m), np.nan)
    for b in range(n):
        a = int(rng.integers(0, m - 20))
        e = int(min(m, a + rng.integers(20, m // 3)))
        base = lanes[b % len(lanes)] + rng.normal(0.0, 0.1)
        t[b, a:e] = base + np.cumsum(rng.normal(0.0, 0.03, e - a)) + rng.choice([0.0, 0.0, 0.03]) * np.arange(e - a)
        if e - a > 40 and rng.random() < 0.4:
            h = int(rng.integers(a + 5, e - 10))
            t[b, h : h + int(rng.integers(2, 8))] = np.nan
    return t


def _cfg() -> LanesConfig:
    return LanesConfig()


def _check_adjacency_whole(t: np.ndarray, on: np.ndarray, rank: np.ndarray, step: float,
                           cfg: LanesConfig) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
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
        good = at & (w >= cfg.min_lane_width_m) & (w <= cfg.max_lane_width_m) & (slope < cfg.stable_lane_slope)
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


def _drop_duplicates_whole(t: np.ndarray, on: np.ndarray, rank: np.ndarray, tol: float, min_run: int) -> None:
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


@pytest.mark.parametrize("seed", range(8))
def test_adjacency_checked_on_each_pairs_own_stations_drops_what_the_whole_array_drops(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = _road_rows(rng, 40, 600)
    on = np.isfinite(t) & (rng.random(t.shape) < 0.97)
    rank = rng.permutation(len(t))
    step = float(rng.choice([0.5, 1.0]))
    got_on, got_dropped = _check_adjacency(t, on, rank, step, _cfg())
    want_on, want_dropped = _check_adjacency_whole(t, on, rank, step, _cfg())
    assert np.array_equal(got_on, want_on)
    assert got_dropped == want_dropped
    assert want_dropped and want_on.any()


def test_adjacency_of_lines_that_never_meet_drops_nothing() -> None:
    """One line at a station at most (or none at all): no pair of neighbours, nothing dropped."""
    t = np.full((3, 50), np.nan)
    t[0, :20], t[1, 30:] = 1.0, -2.0
    for on in (np.isfinite(t), np.zeros(t.shape, dtype=bool)):
        got, dropped = _check_adjacency(t, on, np.arange(3), 1.0, _cfg())
        assert np.array_equal(got, on) and dropped == []


@pytest.mark.parametrize("seed", range(8))
def test_duplicates_compared_on_overlapping_spans_only_are_the_whole_array_duplicates(seed: int) -> None:
    rng = np.random.default_rng(50 + seed)
    t = _road_rows(rng, 40, 600)
    on = np.isfinite(t) & (rng.random(t.shape) < 0.97)
    rank = rng.permutation(len(t))
    got, want = on.copy(), on.copy()
    _drop_duplicates(t, got, rank, 0.5, 30)
    _drop_duplicates_whole(t, want, rank, 0.5, 30)
    assert np.array_equal(got, want)
    assert (want != on).any()


@pytest.mark.parametrize("seed", range(6))
def test_the_carriageway_chosen_on_the_present_places_only_is_the_whole_arrays(seed: int) -> None:
    """More rows than any station holds: the places below the fullest station's are cut off."""
    rng = np.random.default_rng(80 + seed)
    t = _road_rows(rng, 40, 600, _LANES[:5] if seed % 2 else _LANES)
    on = np.isfinite(t) & (rng.random(t.shape) < 0.95)
    assert len(_present_columns(t, on)[0]) < len(t)
    solid = rng.random(len(t)) < 0.4
    support = rng.random(len(t)) * 100.0
    t_ego = np.full(600, -1.7) if seed % 2 else None
    got = _choose_carriageway(t, on, t_ego, solid, support, _cfg())
    assert np.array_equal(got, _choose_carriageway_by_group(t, on, t_ego, solid, support, _cfg()))
    assert got.any() and (got != on).any()


def _labelling_curves_whole(kept: np.ndarray, fitted: np.ndarray, tol: float) -> np.ndarray:
    out = kept.copy()
    for b in range(len(kept)):
        free = ~np.isfinite(kept[b]) & np.isfinite(fitted[b])
        if not free.any():
            continue
        close = np.abs(np.delete(kept, b, axis=0) - fitted[b][None, :]) < tol
        out[b] = np.where(free & ~close.any(axis=0), fitted[b], out[b])
    return out


def _hold_ends_whole(curves: np.ndarray, reach: int, tol: float) -> np.ndarray:
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


def _label_by_distance_whole(k: np.ndarray, t: np.ndarray, inside: np.ndarray, curves: np.ndarray,
                             cfg: LanesConfig) -> np.ndarray:
    label = np.full(len(t), -1, dtype=np.int64)
    d = np.abs(curves[:, k] - t[None, :])
    d = np.where(np.isfinite(d), d, np.inf)
    best = np.argmin(d, axis=0)
    ok = (d[best, np.arange(len(best))] <= cfg.assign_distance_m) & inside
    return np.where(ok, best, label)


@pytest.mark.parametrize("seed", range(8))
def test_labels_from_the_curves_at_each_station_are_the_whole_array_labels(seed: int) -> None:
    """Curves freed, held at their ends and searched per point: ties between two identical curves go
    to the lower row, points off every curve, outside the frame or without an offset get none."""
    rng = np.random.default_rng(200 + seed)
    fitted = _road_rows(rng, 40, 600)
    kept = np.where(np.isfinite(fitted) & (rng.random(fitted.shape) < 0.7), fitted, np.nan)
    kept[np.arange(len(kept)) % 3 == 1] = np.nan
    curves = _labelling_curves(kept, fitted, 0.5)
    assert np.array_equal(curves, _labelling_curves_whole(kept, fitted, 0.5), equal_nan=True)
    held = _hold_ends(curves, 100, 0.5)
    assert np.array_equal(held, _hold_ends_whole(curves, 100, 0.5), equal_nan=True)
    held[7] = held[4]  # an exact copy: every point near it is a tie
    n = 20000
    k = rng.integers(0, 600, n)
    row = rng.integers(0, len(held), n)
    t = held[row, k] + rng.normal(0.0, 0.4, n)
    t = np.where(np.isfinite(t), t, rng.normal(0.0, 10.0, n))
    t[:50] = np.nan
    inside = rng.random(n) < 0.95
    got = _label_by_distance(k, t, inside, held, _cfg())
    want = _label_by_distance_whole(k, t, inside, held, _cfg())
    assert np.array_equal(got, want)
    assert (want == 4).any() and not (want == 7).any() and (want == -1).any()
    assert np.array_equal(_label_by_distance(k, t, inside, np.full((3, 600), np.nan), _cfg()), np.full(n, -1))


def _line_run_whole(s: np.ndarray, w: np.ndarray, k: np.ndarray, line: tuple[float, float],
                    seed: tuple[float, float], step: float, cfg: LanesConfig) -> np.ndarray:
    on = np.flatnonzero(np.abs(w - (line[0] + line[1] * s)) < cfg.taper_line_tolerance_m)
    if len(on) == 0:
        return on
    ks = np.flatnonzero(np.bincount(k[on]))
    cut = np.flatnonzero(np.diff(ks) * step > cfg.taper_max_gap_m)
    firsts, lasts = ks[np.r_[0, cut + 1]], ks[np.r_[cut, len(ks) - 1]]
    stretch = np.zeros(len(ks), dtype=np.int64)
    stretch[cut + 1] = 1
    in_seed = (ks * step >= seed[0]) & (ks * step < seed[1])
    j = int(np.argmax(np.bincount(np.cumsum(stretch)[in_seed], minlength=len(firsts))))
    return on[(k[on] >= firsts[j]) & (k[on] <= lasts[j])]


@pytest.mark.parametrize("seed", range(6))
def test_a_taper_line_searched_on_the_stretch_it_can_reach_finds_the_points_of_a_search_over_all(
        seed: int) -> None:
    """Tapers, a guard rail, clutter and a line nearly parallel to the edge, on a long stretch with the
    points in no particular order: the same points on each line, in the same order."""
    rng = np.random.default_rng(300 + seed)
    step = 0.5
    parts = [rng.uniform(0.0, 5000.0, 4000), rng.uniform(0.0, 5000.0, 3000)]
    ws = [rng.uniform(0.5, 10.0, 4000), 1.2 + rng.normal(0.0, 0.05, 3000)]
    for s0 in rng.uniform(0.0, 4800.0, 6):
        s = np.sort(rng.uniform(s0, s0 + 120.0, 300))
        slope = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.02, 0.15))
        parts.append(s)
        ws.append(np.clip(3.0 + slope * (s - s0 - 60.0), 0.5, 9.5) + rng.normal(0.0, 0.05, len(s)))
    s = np.concatenate(parts)
    w = np.concatenate(ws)
    perm = rng.permutation(len(s))
    s, w = s[perm], w[perm]
    k = np.rint(s / step).astype(np.int64)
    cfg = _cfg()
    pts = _SortedByS.of(s, w, k)
    seeds = _straight_lines(s, w, k, step, cfg)
    lines = [(a, b, lo, hi) for a, b, lo, hi in seeds] + [
        (1.2, 0.0, 0.0, 5000.0), (1.2, 1e-8, 0.0, 5000.0), (1.2, 2e-4, 100.0, 200.0), (40.0, 0.05, 0.0, 100.0)]
    found = 0
    for a, b, lo, hi in lines:
        got = _line_run(pts, (a, b), (lo, hi), step, cfg)
        want = _line_run_whole(s, w, k, (a, b), (lo, hi), step, cfg)
        assert np.array_equal(got, want)
        found += len(want) > 0
    assert len(seeds) >= 3 and found >= 3


def _straight_lines_masked(s: np.ndarray, w: np.ndarray, k: np.ndarray, step: float,
                           cfg: LanesConfig) -> list[tuple[float, float, float, float]]:
    """`_straight_lines` with each window taken by a mask over all cells, as it was written."""
    import lidar2xodr.lanes.tapers as tapers

    tol = cfg.taper_line_tolerance_m
    half = np.arange(cfg.stable_lane_slope, cfg.taper_max_slope + 1e-9, tapers._SLOPE_STEP)
    slopes = np.concatenate([-half[::-1], half])
    window = 2.0 * cfg.taper_min_length_m
    near = w <= cfg.max_lane_width_m + tol
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


@pytest.mark.parametrize("step", [0.5, 1.0])
def test_taper_seeds_from_window_slices_are_the_seeds_from_masks(step: float) -> None:
    rng = np.random.default_rng(int(step * 10))
    s = rng.uniform(0.0, 2000.0, 6000)
    w = rng.uniform(0.5, 10.0, 6000)
    for s0 in (200.0, 900.0, 1500.0):
        ss = rng.uniform(s0, s0 + 100.0, 400)
        s, w = np.concatenate([s, ss]), np.concatenate([w, 4.0 - 0.04 * (ss - s0)])
    k = np.rint(s / step).astype(np.int64)
    got = _straight_lines(s, w, k, step, _cfg())
    assert got == _straight_lines_masked(s, w, k, step, _cfg())
    assert len(got) >= 3
