"""The export's spline fit (`_spline_records`) solved as a sparse system: same splines as a dense solve."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from lidar2xodr.export_opendrive import _merge_records, _Records, _slope_rows, _spline_records


def _dense_coefficients(x, y, breaks, smooth, constraints, c1):
    """The formula the sparse solve replaced: the dense normal equations (with a KKT block)."""
    inner = np.repeat(breaks[1:-1], 2 if c1 else 1)
    knots = np.r_[[breaks[0]] * 4, inner, [breaks[-1]] * 4]
    nb = len(knots) - 4
    design = BSpline.design_matrix(np.clip(x, breaks[0], breaks[-1]), knots, 3).toarray()
    diff2 = np.diff(np.eye(nb), 2, axis=0)
    mu = smooth * len(x) / nb
    lhs = design.T @ design + mu * diff2.T @ diff2 + 1e-12 * np.eye(nb)
    rhs = design.T @ y
    if not constraints:
        return knots, np.linalg.solve(lhs, rhs)
    cx = np.array([c[0] for c in constraints])
    crow = BSpline.design_matrix(cx, knots, 3).toarray()
    slope = np.array([len(c) > 2 for c in constraints])
    if slope.any():
        crow[slope] = BSpline(knots, np.eye(nb), 3).derivative()(cx[slope])
    cval = np.array([c[1] for c in constraints])
    kkt = np.block([[lhs, crow.T], [crow, np.zeros((len(cval), len(cval)))]])
    return knots, np.linalg.solve(kkt, np.concatenate([rhs, cval]))[:nb]


@pytest.mark.parametrize("c1", [False, True])
def test_slope_rows_are_the_derivative_of_every_basis_function(c1: bool) -> None:
    breaks = np.array([0.0, 12.0, 30.0, 31.0, 70.0, 100.0])
    inner = np.repeat(breaks[1:-1], 2 if c1 else 1)
    knots = np.r_[[breaks[0]] * 4, inner, [breaks[-1]] * 4]
    x = np.array([0.0, 0.5, 12.0, 29.9, 30.5, 55.0, 99.99, 100.0])
    expected = BSpline(knots, np.eye(len(knots) - 4), 3).derivative()(x)
    assert np.allclose(_slope_rows(x, knots), expected, atol=1e-12)


@pytest.mark.parametrize("c1", [False, True])
@pytest.mark.parametrize("constraints", [(), ((0.0, 3.5), (200.0, 0.0, 1)), ((0.0, 0.0), (0.0, 0.0, 1), (200.0, 3.5))])
def test_the_sparse_solve_gives_the_dense_solution(c1: bool, constraints: tuple) -> None:
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0.0, 200.0, 800))
    y = 3.5 + 0.01 * x + 0.3 * np.sin(x / 15.0) + rng.normal(0.0, 0.02, len(x))
    breaks = np.linspace(0.0, 200.0, 9)
    rec = _spline_records(x, y, breaks, smooth=0.3, constraints=constraints, c1=c1)
    knots, coef = _dense_coefficients(x, y, breaks, 0.3, constraints, c1)
    s = np.linspace(0.0, 200.0, 2001)
    assert np.max(np.abs(rec(s) - BSpline(knots, coef, 3)(s))) < 1e-9
    for c in constraints:
        if len(c) == 2:
            assert rec(np.array([c[0]]))[0] == pytest.approx(c[1], abs=1e-9)


def test_contradictory_constraints_give_the_nearest_spline_not_an_error() -> None:
    x = np.linspace(0.0, 100.0, 200)
    rec = _spline_records(x, np.full(len(x), 2.0), np.linspace(0.0, 100.0, 5),
                          constraints=((50.0, 1.0), (50.0, 3.0)))
    values = rec(np.linspace(0.0, 100.0, 11))
    assert np.all(np.isfinite(values))
    assert rec(np.array([50.0]))[0] == pytest.approx(2.0, abs=0.05)


def _merge_records_loop(rec, end, tol=1e-6):
    """The per-record formula `_merge_records` replaced (each record evaluated through `_Records`)."""
    ends = np.r_[rec.starts[1:], end]
    coeffs = rec.coeffs.copy()
    for i in range(len(rec.starts)):
        ds = np.linspace(0.0, ends[i] - rec.starts[i], 9)
        vals = _Records(np.zeros(1), coeffs[i:i + 1])(ds)
        if np.ptp(vals) < tol:
            coeffs[i] = [0.5 * (vals.max() + vals.min()), 0.0, 0.0, 0.0]
    keep = [0]
    for i in range(1, len(rec.starts)):
        j = keep[-1]
        s = np.linspace(rec.starts[i], ends[i], 9)
        prev = _Records(rec.starts[j:j + 1], coeffs[j:j + 1])(s)
        if np.max(np.abs(prev - _Records(rec.starts[i:i + 1], coeffs[i:i + 1])(s))) >= tol:
            keep.append(i)
    return _Records(rec.starts[keep], coeffs[keep])


def test_merged_records_are_bitwise_those_of_the_per_record_formula() -> None:
    """Flat records (1e-8 m of noise on a constant width), records continuing their predecessor's
    cubic, a zero-length record and ordinary ones: the same starts and the same coefficient bits."""
    rng = np.random.default_rng(5)
    starts = np.r_[0.0, np.cumsum(rng.uniform(5.0, 40.0, 59))]
    starts[20] = starts[19]
    coeffs = rng.normal(0.0, [1.0, 0.05, 1e-3, 1e-5], (60, 4))
    coeffs[5:15] = [3.5, 0.0, 0.0, 0.0]
    coeffs[5:15, 1] += rng.normal(0.0, 1e-9, 10)
    for i in range(30, 40):  # one cubic across ten records
        h = starts[i] - starts[29]
        a, b, c, d = coeffs[29]
        coeffs[i] = [a + h * (b + h * (c + h * d)), b + h * (2 * c + 3 * h * d), c + 3 * h * d, d]
    for i in range(45, 51):  # each continues the one before it, 0.6 um higher: every second one is kept
        h = starts[i] - starts[i - 1]
        a, b, c, d = coeffs[i - 1]
        coeffs[i] = [a + h * (b + h * (c + h * d)) + 6e-7, b + h * (2 * c + 3 * h * d), c + 3 * h * d, d]
    rec = _Records(starts, coeffs)
    end = float(starts[-1] + 12.0)
    got, want = _merge_records(rec, end), _merge_records_loop(rec, end)
    assert len(got.starts) < len(starts)
    assert np.array_equal(got.starts, want.starts) and np.array_equal(got.coeffs, want.coeffs)
