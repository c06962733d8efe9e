"""True vehicle poses from the agent states: a fine pose grid for the ego, scan-rate poses for traffic.

The vehicle frame sits on the road surface under the reference point, x forward along the velocity,
z along the surface normal. The ego body adds a little pitch and roll on top (suspension: 0.003 rad
pitch per m/s^2 of acceleration, nose down when braking, plus 0.05 deg of smooth vibration), which
the sensor sees and the true poses contain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.signal import lfilter

from lidar2xodr.simulation.route import Route
from lidar2xodr.simulation.traffic import Agents

POSE_HZ = 200.0


@dataclass
class PoseTrack:
    """Poses on a regular time grid (relative seconds), interpolated linearly in between."""

    t0: float
    hz: float
    pos: np.ndarray  # (N, 3)
    rot: np.ndarray  # (N, 3, 3) columns forward, left, up
    u: np.ndarray  # (N,) route coordinate
    lam: np.ndarray  # (N,)

    @property
    def times(self) -> np.ndarray:
        return self.t0 + np.arange(len(self.pos)) / self.hz

    def slot(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = np.clip((np.asarray(t) - self.t0) * self.hz, 0.0, len(self.pos) - 1.000001)
        k = np.floor(f).astype(np.int64)
        return k, f - k

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k, w = self.slot(t)
        pos = self.pos[k] + w[:, None] * (self.pos[k + 1] - self.pos[k])
        rot = self.rot[k] + w[:, None, None] * (self.rot[k + 1] - self.rot[k])
        return pos, rot


def ego_track(route: Route, agents: Agents, t_start: float, rng: np.random.Generator) -> PoseTrack:
    """The ego's true pose at POSE_HZ over the whole drive."""
    t = agents.times
    u, lam = agents.ego_u, agents.ego_lam
    fu = PchipInterpolator(t, u)
    fl = PchipInterpolator(t, lam)
    grid = np.arange(0.0, t[-1] + 1e-9, 1.0 / POSE_HZ)
    ug, lg = fu(grid), fl(grid)
    du = fu(grid, 1)
    dl = fl(grid, 1)
    pos, rot = route.frames(ug, lg, dl / np.maximum(du, 1.0))
    acc = np.convolve(np.clip(fu(grid, 2), -6.0, 6.0), np.ones(100) / 100, mode="same")
    n = len(grid)
    pitch = -0.003 * acc + _smooth_noise(n, 0.0009, 0.5 * POSE_HZ, rng)
    roll = _smooth_noise(n, 0.0009, 0.5 * POSE_HZ, rng)
    body = _body_rotation(roll, pitch)
    return PoseTrack(t_start, POSE_HZ, pos, rot @ body, ug, lg)


def _smooth_noise(n: int, sigma: float, corr_samples: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary first-order Gauss-Markov noise with the given sigma and correlation length."""
    phi = np.exp(-1.0 / corr_samples)
    w = rng.standard_normal(n) * sigma * np.sqrt(1 - phi * phi)
    w[0] = rng.standard_normal() * sigma
    return lfilter([1.0], [1.0, -phi], w)


def _body_rotation(roll: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Ry(pitch) Rx(roll) per sample (small angles, positive pitch = nose down)."""
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    z, o = np.zeros_like(roll), np.ones_like(roll)
    ry = np.stack([np.stack([cp, z, sp], -1), np.stack([z, o, z], -1), np.stack([-sp, z, cp], -1)], -2)
    rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cr, -sr], -1), np.stack([z, sr, cr], -1)], -2)
    return ry @ rx


@dataclass
class TrafficPoses:
    """Traffic boxes at each sim step: for step k, rows start[k]:start[k+1] of the flat arrays."""

    start: np.ndarray  # (T + 1,)
    agent: np.ndarray  # (M,) agent column
    centre: np.ndarray  # (M, 3) box centre
    yaw: np.ndarray  # (M,)
    velocity: np.ndarray  # (M, 3)

    def step(self, k: int) -> slice:
        return slice(int(self.start[k]), int(self.start[k + 1]))


def traffic_poses(route: Route, agents: Agents, every: int) -> TrafficPoses:
    """Box centres, yaw and velocity of all traffic at every `every`-th sim step (the scan boundaries)."""
    steps = np.arange(0, len(agents.times), every)
    rows = np.concatenate([np.arange(agents.start[k], agents.start[k + 1]) for k in steps]) \
        if len(steps) else np.zeros(0, dtype=np.int64)
    counts = agents.start[steps + 1] - agents.start[steps]
    cols = agents.agent[rows]
    u, lam, dlam = agents.u[rows], agents.lam[rows], agents.dlam[rows]
    sign = agents.heading_sign[cols]
    v = agents.v[rows]
    pos, rot = route.frames(u, lam, dlam / (np.maximum(v, 1.0) * sign))
    fwd = rot[:, :, 0] * sign[:, None]
    yaw = np.arctan2(fwd[:, 1], fwd[:, 0])
    h = agents.size[cols, 2]
    centre = pos + rot[:, :, 2] * (agents.clearance[cols] + 0.5 * (h - agents.clearance[cols]))[:, None]
    velocity = fwd * v[:, None] + rot[:, :, 1] * dlam[:, None]
    start = np.concatenate([[0], np.cumsum(counts)])
    return TrafficPoses(start, cols, centre, yaw, velocity)
