"""Sensor presets: mount pose, range model, intensity scale and the scan pattern of each LiDAR.

Patterns are functions of absolute time, so consecutive scans continue the pattern instead of
repeating it (the Livox rosette keeps filling its field of view while integrating).

Decisions:
- Range limit ~ sqrt(reflectivity) (returned power ~ reflectivity / range^2): livox-horizon
  reaches 260 m at 80 % (so 90 m at 10 %), pandar64 200 m at 10 %; both capped at the data-sheet
  maximum. The reflectivity used is the one the sensor sees (after incidence-angle falloff).
- Intensity scales follow the vendors: Livox reports 0-150 for 0-100 % diffuse reflectivity and
  151-255 for retro-reflectors; Hesai 0-100 for diffuse and 101-255 for retro-reflectors. So
  `intensity_scale` (the raw value meaning 100 %) is 150 and 100.
- The Livox Horizon pattern is modelled as six laser channels side by side, each tracing a
  two-prism rosette (sum of two counter-rotating phasors with incommensurate frequencies),
  clipped to the 81.7 x 25.1 deg field of view. Density peaks near the centre of each petal
  fan, as on the real sensor.
- Pandar64: 64 channels at the data sheet's uneven elevations (fine 1/6 deg steps between -6 and
  +2 deg), 0.2 deg azimuth steps at 10 Hz (1800 x 64 = 115 200 rays per scan), clockwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorPreset:
    """What the simulator needs to know about one LiDAR model."""

    name: str
    mount_xyz: tuple[float, float, float]  # in the vehicle frame (origin on the road, x forward)
    mount_rpy: tuple[float, float, float]  # roll, pitch (positive = nose down), yaw in rad
    rate_hz: float
    rays_per_scan: int
    max_range_m: float  # hard data-sheet limit
    ref_range_m: float  # detection range at ref_reflectivity
    ref_reflectivity: float
    min_range_m: float
    range_sigma_m: float
    intensity_scale: float  # raw value that means 100 % diffuse reflectivity
    fov_h_deg: float
    fov_v_deg: tuple[float, float]  # min, max elevation

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    def mount_matrix(self) -> np.ndarray:
        """T_vehicle_sensor (4x4)."""
        m = np.eye(4)
        m[:3, :3] = rpy_matrix(*self.mount_rpy)
        m[:3, 3] = self.mount_xyz
        return m

    def detection_range(self, reflectivity: np.ndarray) -> np.ndarray:
        """Maximum range at which a surface of this apparent reflectivity still returns."""
        r = self.ref_range_m * np.sqrt(np.maximum(reflectivity, 0.0) / self.ref_reflectivity)
        return np.minimum(r, self.max_range_m)

    def rays(self, t0: float, t_ref: float) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions (N, 3) float32 in the sensor frame and their absolute times (N,) float64.

        `t0` is the scan start; `t_ref` the drive start (the pattern phase is counted from it so
        float64 keeps full precision).
        """
        if self.name == "pandar64":
            return _pandar_rays(self, t0, t_ref)
        return _livox_rays(self, t0, t_ref)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (ISO 8855 / aerospace order)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


LIVOX_HORIZON = SensorPreset(
    name="livox-horizon",
    mount_xyz=(1.6, 0.0, 1.8),
    mount_rpy=(0.0, math.radians(1.5), 0.0),
    rate_hz=10.0,
    rays_per_scan=24_000,
    max_range_m=260.0,
    ref_range_m=260.0,
    ref_reflectivity=0.8,
    min_range_m=0.5,
    range_sigma_m=0.02,
    intensity_scale=150.0,
    fov_h_deg=81.7,
    fov_v_deg=(-12.55, 12.55),
)

PANDAR64 = SensorPreset(
    name="pandar64",
    mount_xyz=(1.3, 0.0, 1.95),
    mount_rpy=(0.0, 0.0, 0.0),
    rate_hz=10.0,
    rays_per_scan=115_200,
    max_range_m=200.0,
    ref_range_m=200.0,
    ref_reflectivity=0.1,
    min_range_m=0.3,
    range_sigma_m=0.02,
    intensity_scale=100.0,
    fov_h_deg=360.0,
    fov_v_deg=(-25.0, 15.0),
)

PRESETS: dict[str, SensorPreset] = {p.name: p for p in (LIVOX_HORIZON, PANDAR64)}

_LIVOX_CHANNELS = 6
_LIVOX_F1 = 329.27  # Hz, first prism (per channel slightly detuned below)
_LIVOX_F2 = -222.84  # Hz, second prism, counter-rotating; f1/f2 irrational-ish: the rosette precesses


_LIVOX_CACHE: dict[int, tuple[np.ndarray, ...]] = {}


def _livox_rays(p: SensorPreset, t0: float, t_ref: float) -> tuple[np.ndarray, np.ndarray]:
    n = p.rays_per_scan
    if n not in _LIVOX_CACHE:
        k = np.arange(n)
        ch = k % _LIVOX_CHANNELS
        dt = (k + 0.5) * (p.period / n)
        det = 1.0 + 0.0137 * np.arange(_LIVOX_CHANNELS)
        # phasors of each ray relative to its scan start: the scan start only rotates them per channel
        z1 = np.exp(2j * np.pi * (_LIVOX_F1 * det[ch] * dt + 0.31 * ch))
        z2 = np.exp(2j * np.pi * (_LIVOX_F2 * det[ch] * dt + 0.17 * ch))
        _LIVOX_CACHE[n] = (ch, dt, det, z1, z2)
    ch, dt, det, z1, z2 = _LIVOX_CACHE[n]
    tau = t0 - t_ref
    r1 = np.exp(2j * np.pi * np.mod(_LIVOX_F1 * det * tau, 1.0))
    r2 = np.exp(2j * np.pi * np.mod(_LIVOX_F2 * det * tau, 1.0))
    z = 0.5 * (z1 * r1[ch] + z2 * r2[ch])
    half_h = 0.5 * p.fov_h_deg
    lobe = half_h / _LIVOX_CHANNELS * 1.45
    centres = np.linspace(-half_h + lobe * 0.8, half_h - lobe * 0.8, _LIVOX_CHANNELS)
    lo, hi = p.fov_v_deg
    az = np.radians(np.clip(centres[ch] + lobe * z.real, -half_h, half_h))
    el = np.radians(np.clip(0.5 * (lo + hi) + 0.5 * (hi - lo) * 1.04 * z.imag, lo, hi))
    return _unit(az, el), t0 + dt


def pandar64_elevations() -> np.ndarray:
    """The 64 channel elevations (deg), top to bottom, after the Pandar64 data sheet."""
    top = [15.0, 11.0, 8.0, 5.0, 3.0]
    fine = list(np.linspace(2.0, -6.0, 49))
    coarse = [-7.0, -8.0, -9.0, -10.0, -11.0, -12.0, -13.0, -14.0]
    return np.array(top + fine + coarse + [-19.0, -25.0])


_PANDAR_AZ_OFFSETS = np.tile(np.array([-1.042, 1.042, 3.125, -3.125]), 16)


def _pandar_rays(p: SensorPreset, t0: float, t_ref: float) -> tuple[np.ndarray, np.ndarray]:
    n_ch = 64
    n_az = p.rays_per_scan // n_ch
    block_dt = p.period / n_az
    b = np.repeat(np.arange(n_az), n_ch)
    c = np.tile(np.arange(n_ch), n_az)
    times = t0 + b * block_dt + c * (0.9 * block_dt / n_ch)
    # Clockwise from behind the vehicle; the start phase continues with absolute time.
    rev = (times - t_ref) * p.rate_hz
    az = np.pi - 2 * np.pi * (rev - np.floor(rev)) + np.radians(_PANDAR_AZ_OFFSETS[c])
    el = np.radians(pandar64_elevations()[c])
    return _unit(az, el), times


def _unit(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Unit vectors (float32: ample for directions, and twice as fast) from azimuth and elevation."""
    az, el = az.astype(np.float32), el.astype(np.float32)
    ce = np.cos(el)
    out = np.empty((len(az), 3), dtype=np.float32)
    out[:, 0] = ce * np.cos(az)
    out[:, 1] = ce * np.sin(az)
    out[:, 2] = np.sin(el)
    return out
