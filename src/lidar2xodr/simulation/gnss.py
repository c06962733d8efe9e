"""GNSS/INS pose errors: correlated plus white noise, and optional outages with INS drift.

Decisions:
- Horizontal error per axis = first-order Gauss-Markov noise (correlation time 20 s, sigma
  0.916 * --gnss-noise-m) + white noise (0.4 * --gnss-noise-m): the total per-axis standard
  deviation is --gnss-noise-m, and the 100 Hz output stays smooth like an INS-filtered solution.
  Vertical errors are 1.5 times larger. Attitude errors scale with the same option (at 0.05 m:
  roll/pitch 0.02 deg, yaw 0.08 deg, correlated over 60 s). Zero means perfect poses.
- --gnss-outage: one outage of 20-45 s per started 5 minutes of driving (none in the first and
  last 10 %). During an outage the INS dead-reckons: the error grows as v0 * t + a * t^2 / 2
  (v0 ~ 0.05 m/s, a ~ 0.01 m/s^2 per axis, yaw drift ~ 0.1 deg/min) and converges back within
  3 s once satellites are back. Outage intervals are listed in truth/route.json.
- --gnss-bias-m: on top, a constant horizontal offset for the whole drive (`drive.gnss_bias`),
  what GNSS without correction services gives on one day; listed in truth/route.json.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

HORIZONTAL_CORR_S = 20.0
ATTITUDE_CORR_S = 60.0


def gauss_markov(n: int, dt: float, sigma: float, corr_s: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary first-order Gauss-Markov sequence (exponential autocorrelation)."""
    phi = np.exp(-dt / corr_s)
    w = rng.standard_normal(n) * sigma * np.sqrt(1 - phi * phi)
    w[0] = rng.standard_normal() * sigma
    return lfilter([1.0], [1.0, -phi], w)


def pose_errors(
    times: np.ndarray, sigma_m: float, outage: bool, rng: np.random.Generator
) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """Errors (N, 6) = dx, dy, dz, droll, dpitch, dyaw at the given regular times, and the outages."""
    n = len(times)
    err = np.zeros((n, 6))
    if n == 0:
        return err, []
    dt = float(times[1] - times[0]) if n > 1 else 0.01
    scale = sigma_m / 0.05
    for axis, mult in ((0, 1.0), (1, 1.0), (2, 1.5)):
        s = sigma_m * mult
        err[:, axis] = gauss_markov(n, dt, 0.916 * s, HORIZONTAL_CORR_S, rng) + rng.normal(0.0, 0.4 * s, n)
    for axis, deg in ((3, 0.02), (4, 0.02), (5, 0.08)):
        err[:, axis] = gauss_markov(n, dt, np.radians(deg) * scale, ATTITUDE_CORR_S, rng)
    outages: list[tuple[float, float]] = []
    if outage and n > 1:
        duration = float(times[-1] - times[0])
        count = max(1, int(np.ceil(duration / 300.0)))
        lo, hi = times[0] + 0.1 * duration, times[-1] - 0.1 * duration
        slots = np.linspace(lo, hi, count + 1)
        for a, b in zip(slots[:-1], slots[1:], strict=True):
            length = min(float(rng.uniform(20.0, 45.0)), 0.8 * (b - a))
            if length < 2.0:
                continue
            t0 = float(rng.uniform(a, b - length))
            outages.append((t0, t0 + length))
            _drift(err, times, t0, t0 + length, rng)
    return err, outages


def _drift(err: np.ndarray, times: np.ndarray, t0: float, t1: float, rng: np.random.Generator) -> None:
    inside = (times >= t0) & (times < t1)
    tau = times[inside] - t0
    after = (times >= t1) & (times < t1 + 3.0)
    for axis in (0, 1, 2):
        v0 = rng.normal(0.0, 0.05)
        a = rng.normal(0.0, 0.01 if axis < 2 else 0.003)
        d = v0 * tau + 0.5 * a * tau * tau
        err[inside, axis] += d
        if after.any() and len(d):
            fade = 1.0 - (times[after] - t1) / 3.0
            err[after, axis] += d[-1] * fade
    yaw_rate = np.radians(rng.normal(0.0, 0.1)) / 60.0
    err[inside, 5] += yaw_rate * tau
