"""The export's spline fit (`_spline_records`) solved as a sparse system: same splines as a dense solve."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from lidar2xodr.export_opendrive import _slope_rows, _spline_records


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
