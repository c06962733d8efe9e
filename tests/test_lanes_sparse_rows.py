"""The lanes stage's (lines, stations) arrays are almost empty on a long drive (a 20 km corridor: 3557
rows x 20,000 stations, 0.1 % finite). The helpers that look only at the rows and stations that hold
something must give exactly what the plain whole-array formulas give (issue #14)."""

from __future__ import annotations

import numpy as np
import pytest

from lidar2xodr.config import LanesConfig
from lidar2xodr.lanes.dividers import _divided_left
from lidar2xodr.lanes.smoothing import _groups
from lidar2xodr.lanes.structure import _choose_carriageway, _sorted_columns
from lidar2xodr.lanes.tracks import _bridge_gaps, _Lines, _robust_curve, _robust_curve_window, _slope_at


def _sparse_lines(rng: np.random.Generator, n: int, m: int) -> np.ndarray:
    """n rows of short finite runs in NaN, some rows empty, with gaps inside some runs."""
    t = np.full((n, m), np.nan)
    for b in range(n):
        if rng.random() < 0.3:
            continue
        a = int(rng.integers(0, m - 1))
        e = int(rng.integers(a + 1, m + 1))
        t[b, a:e] = rng.normal(0.0, 5.0) + np.cumsum(rng.normal(0.0, 0.05, e - a))
        if e - a > 10 and rng.random() < 0.3:
            h = int(rng.integers(a + 1, e - 1))
            t[b, h : h + 3] = np.nan
    return t


@pytest.mark.parametrize("m", [1, 2, 3, 50])
def test_slope_at_points_is_np_gradient_there(m: int) -> None:
    rng = np.random.default_rng(m)
    t = _sparse_lines(rng, 12, m) if m > 1 else rng.normal(size=(12, 1))
    row, k = rng.integers(0, 12, 500), rng.integers(0, m, 500)
    full = np.abs(np.gradient(t, axis=1)) if m > 1 else np.zeros_like(t)
    assert np.array_equal(_slope_at(lambda r, j: t[r, j], row, k, m), full[row, k], equal_nan=True)
    lines = _Lines.from_dense(t, np.zeros(t.shape, dtype=bool))
    assert np.array_equal(_slope_at(lines.value_at, row, k, m), full[row, k], equal_nan=True)
    assert np.array_equal(lines.value_at(row, k), t[row, k], equal_nan=True)


def _divided_left_dense(t_fit: np.ndarray, on: np.ndarray, solid: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        top = np.max(np.where(on, t_fit, -np.inf), axis=0)
        beyond = ~on & np.isfinite(t_fit) & (t_fit > top[None, :] + 0.5)
    nearest = np.argmin(np.where(beyond, t_fit, np.inf), axis=0)
    return (beyond.sum(axis=0) >= 2) & solid[nearest]


@pytest.mark.parametrize("seed", range(6))
def test_divided_left_on_the_filled_rows_is_the_whole_array_answer(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = _sparse_lines(rng, 40, 200)
    on = np.isfinite(t) & (rng.random(t.shape) < 0.6) & (t < 2.0)
    solid = rng.random(40) < 0.5
    got = _divided_left(t, on, solid)
    assert np.array_equal(got, _divided_left_dense(t, on, solid))
    assert got.any() and not got.all()
    kept = np.flatnonzero(on.any(axis=1))
    assert np.array_equal(_divided_left(t, on[kept], solid, kept), got)


@pytest.mark.parametrize("seed", range(6))
def test_lines_bridged_by_their_spans_are_bridged_as_the_whole_array_was(seed: int) -> None:
    """Bridging the lines stored by their spans gives the whole (lines, stations) array's bridging."""
    rng = np.random.default_rng(100 + seed)
    t = _sparse_lines(rng, 30, 400)
    observed = np.isfinite(t) & (rng.random(t.shape) < 0.9)
    for b in range(len(t)):
        if rng.random() < 0.5:
            fin = np.flatnonzero(np.isfinite(t[b]))
            if len(fin) > 60:
                observed[b, fin[10] : fin[10] + 40] = False
    a = t.copy()
    _bridge_gaps_dense(a, observed, 20, 0.5)
    lines = _Lines.from_dense(t.copy(), observed)
    _bridge_gaps(lines, 20, 0.5)
    assert np.array_equal(lines.dense(np.arange(len(t))), a, equal_nan=True)
    assert not np.array_equal(a, t, equal_nan=True)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=False))


def _bridge_gaps_dense(t: np.ndarray, observed: np.ndarray, gap: int, parallel_m: float) -> None:
    """The bridging written on the whole array: every row against every row (a neighbour that strays
    from most other spanning rows inside the gap after those that do not, as `tracks._moves_within`)."""
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
            spanning = [nb for nb in range(len(t)) if nb != b and np.all(np.isfinite(t[nb, g0 - 1 : g1 + 1]))]
            for nb in spanning:
                drift = abs(float((t[b, g1] - t[nb, g1]) - (t[b, g0 - 1] - t[nb, g0 - 1])))
                share = float(observed[nb, g0:g1].mean())
                steps = int(drift / parallel_m) if np.isfinite(drift) else 0
                gaps = t[nb, g0 - 1 : g1] - t[[q for q in spanning if q != nb], g0 - 1 : g1]
                strays = np.max(np.abs(gaps - gaps[:, :1]), axis=1) > parallel_m
                key = (-steps, not 2 * int(strays.sum()) > len(strays), share, -abs(float(t[nb, g0] - t[b, g0])))
                if share >= 0.25 and (best_key is None or key > best_key):
                    best, best_key = nb, key
            if best is None:
                continue
            w0, w1 = t[b, g0 - 1] - t[best, g0 - 1], t[b, g1] - t[best, g1]
            f = (np.arange(g0, g1) - (g0 - 1)) / (g1 - g0 + 1)
            t[b, g0:g1] = t[best, g0:g1] + w0 + (w1 - w0) * f


@pytest.mark.parametrize("seed", range(8))
def test_a_line_fitted_on_the_stations_around_it_is_the_line_fitted_on_all(seed: int) -> None:
    """Dashes, a blob off the line, a piece beyond a gap at either end, near the drive's ends or in
    its middle, with and without a common drift: the windowed fit equals the fit over all stations."""
    rng = np.random.default_rng(seed)
    n = 3000
    a = int(rng.choice([5, 400, 1500]))
    length = int(rng.integers(60, 400))
    k = np.concatenate([np.arange(a + d, a + d + 3) for d in range(0, length, 12)])
    k = np.repeat(k, 3)
    t = -1.75 + 0.002 * (k - a) + rng.normal(0.0, 0.02, len(k))
    extras = [(a + length + int(rng.integers(25, 70)), 0.0), (a - int(rng.integers(25, 60)), 0.0),
              (a + length // 2 + 6, 1.2)]
    for at, off in extras:
        kk = np.repeat(np.arange(at, at + 4), 4)
        kk = kk[(kk >= 0) & (kk < n)]
        k = np.concatenate([k, kk])
        t = np.concatenate([t, -1.75 + 0.002 * (kk - a) + off + rng.normal(0.0, 0.02, len(kk))])
    drift = np.cumsum(rng.normal(0.0, 0.01, n)) if seed % 2 else None
    whole = _robust_curve_window(k, t, n, 1e4, drift=drift)
    window = _robust_curve(k, t, n, 1e4, drift=drift)
    for x, y in zip(whole, window, strict=True):
        assert np.array_equal(x, y, equal_nan=True)
    assert (window[1] == 0).any() or (window[1] < 1).any()


@pytest.mark.parametrize("at", [0, 1000, 2960])
def test_a_short_line_with_a_blob_before_it_is_judged_on_the_same_stations(at: int) -> None:
    """A blob 25 stations before 30 solid stations: the end-piece test looks 40 stations past the
    gap, beyond the line's last point, where the window must still hold the empty stations."""
    n = 3000
    k = np.concatenate([np.repeat(np.arange(at, at + 3), 2), np.repeat(np.arange(at + 28, at + 58), 6)])
    k = k[k < n]
    t = np.full(len(k), -1.75) + 0.01 * np.sin(k)
    whole = _robust_curve_window(k, t, n, 1e4)
    window = _robust_curve(k, t, n, 1e4)
    for x, y in zip(whole, window, strict=True):
        assert np.array_equal(x, y, equal_nan=True)


def _choose_carriageway_by_group(t: np.ndarray, on: np.ndarray, t_ego: np.ndarray | None, solid: np.ndarray,
                                 support: np.ndarray, cfg: LanesConfig) -> np.ndarray:
    """`_choose_carriageway` as it was written before: one pass over the whole array per group."""
    b_n, m = t.shape
    order, ts = _sorted_columns(t, on)
    present = np.isfinite(ts)
    gap = ts[:-1] - ts[1:]
    both_solid = solid[order[:-1]] & solid[order[1:]]
    beyond = np.vstack([np.zeros((1, m), dtype=bool), present[:-2]]) & np.vstack(
        [present[2:], np.zeros((1, m), dtype=bool)])
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


@pytest.mark.parametrize("seed", range(8))
def test_the_carriageway_chosen_per_station_at_once_is_the_one_chosen_group_by_group(seed: int) -> None:
    """Two carriageways beyond a median, lanes opening and ending, lines missing, equal supports and
    an ego that changes carriageway: the same lines kept at every station."""
    rng = np.random.default_rng(seed)
    m = 300
    offsets = np.array([10.5, 7.0, 3.5, 0.0, -3.5, -7.0, -7.5, -11.0, -14.5, -18.0, -21.5])
    t = offsets[:, None] + np.cumsum(rng.normal(0.0, 0.02, (len(offsets), m)), axis=1)
    on = rng.random(t.shape) < 0.85
    for b in rng.choice(len(offsets), 4, replace=False):
        a = int(rng.integers(0, m))
        on[b, a : a + int(rng.integers(20, 120))] = False
    t[~on & (rng.random(t.shape) < 0.5)] = np.nan
    solid = rng.random(len(offsets)) < 0.5
    solid[[5, 6]] = True
    support = rng.choice([100.0, 250.0, 250.0, 777.0], len(offsets)) * rng.random(len(offsets))
    t_ego = np.select([np.arange(m) < 100, np.arange(m) < 150], [-2.0, -7.25], -16.0) if seed % 3 else None
    if seed % 3 == 2:
        t_ego = np.where(rng.random(m) < 0.2, np.nan, t_ego)
    cfg = LanesConfig()
    got = _choose_carriageway(t, on, t_ego, solid, support, cfg)
    want = _choose_carriageway_by_group(t, on, t_ego, solid, support, cfg)
    assert np.array_equal(got, want)
    assert got.any() and (got.sum(axis=0) < on.sum(axis=0)).any()


@pytest.mark.parametrize("n", [0, 1, 40, 3000])
def test_items_grouped_by_one_sort_are_the_items_found_key_by_key(n: int) -> None:
    """The double-line fold's blocks: each block's points, ascending, as `np.flatnonzero(blocks == b)`
    over `np.unique(blocks)` gave them."""
    rng = np.random.default_rng(n)
    blocks = rng.integers(-3, max(n // 20, 1), n)
    got = _groups(blocks)
    want = [(int(b), np.flatnonzero(blocks == b)) for b in np.unique(blocks)]
    assert [b for b, _ in got] == [b for b, _ in want]
    assert all(np.array_equal(x, y) for (_, x), (_, y) in zip(got, want, strict=True))
