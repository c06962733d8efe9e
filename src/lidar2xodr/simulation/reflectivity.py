"""Materials, the intensity model and the sensor noise: what makes a hit a point, and how bright.

Model (decisions):
- Each triangle carries a base reflectivity drawn at scene build time (per dash, per 10 m of solid
  line, per lane strip, per vehicle), so wear and paint batches vary like on a real road.
- Apparent reflectivity = base * cos(incidence)^p * lognormal(0.08). p is 0.6 for rough asphalt
  (more back-scatter than Lambert's p = 1), 0.1 for paint (its glass beads retro-reflect), 0 for
  retro-reflective sheeting. So paint stays above 50 % out to ~40 m while grazing asphalt fades.
- A hit returns only within the sensor's reflectivity-dependent range (see sensors.py), with a
  +-8 % per-ray jitter of that limit and a 0.5 % random dropout.
- Range noise is Gaussian along the ray (sigma from the preset, 2 cm).
- 0.3 % of the returns are multipath ghosts: pushed 0.5-20 m further along the ray, with a bright
  apparent reflectivity of 55-100 %. They are isolated, so the outlier filter must remove them.
- Retro-reflectors (sign faces, licence plates) report above the diffuse scale: Livox 151-255,
  Hesai 101-255 (raw = scale + 1 + (254 - scale) * min(1, (apparent - 1) / 3)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

(ASPHALT, PAINT_WHITE, PAINT_YELLOW, GRASS, GRAVEL, CONCRETE, STEEL, SIGN, VEHICLE, PLATE, DELINEATOR, FOLIAGE,
 WOOD) = range(13)

MATERIAL_NAMES = (
    "asphalt", "paint_white", "paint_yellow", "grass", "gravel", "concrete", "steel", "sign", "vehicle",
    "plate", "delineator", "foliage", "wood",
)
# Base reflectivity (mean, relative spread) and incidence exponent p of each material.
# Foliage is green vegetation like the grass (a rough canopy returns about a third at 905 nm), bark like dry wood.
_BASE = np.array([0.08, 0.8, 0.62, 0.32, 0.2, 0.3, 0.35, 3.0, 0.3, 2.0, 0.6, 0.35, 0.25])
_SPREAD = np.array([0.18, 0.1, 0.1, 0.25, 0.2, 0.15, 0.15, 0.1, 0.0, 0.1, 0.1, 0.25, 0.2])
_EXPONENT = np.array([0.6, 0.1, 0.1, 0.8, 0.7, 0.7, 0.5, 0.0, 0.7, 0.0, 0.5, 0.4, 0.7])

_EXPONENT32 = _EXPONENT.astype(np.float32)

MULTIPATH_SHARE = 0.003
DROPOUT_SHARE = 0.005


def is_paint(material: np.ndarray) -> np.ndarray:
    return (material == PAINT_WHITE) | (material == PAINT_YELLOW)


def draw_base(material: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """n base reflectivities of one material (one per dash, strip or panel)."""
    rel = rng.normal(1.0, _SPREAD[material], n).clip(0.5, 1.5)
    return (_BASE[material] * rel).astype(np.float32)


def paint_base(n: int, yellow: bool, rng: np.random.Generator) -> np.ndarray:
    """Paint with wear: mostly fresh, some dashes worn down to ~60 %."""
    wear = np.where(rng.random(n) < 0.15, rng.uniform(0.6, 0.85, n), rng.uniform(0.9, 1.05, n))
    return (draw_base(PAINT_YELLOW if yellow else PAINT_WHITE, n, rng) * wear).astype(np.float32)


@dataclass
class Returns:
    """The returned subset of the cast rays: indices into the rays, ranges and apparent reflectivity."""

    index: np.ndarray
    rng_m: np.ndarray
    reflectivity: np.ndarray


def returns(
    hit_range: np.ndarray,
    material: np.ndarray,
    base: np.ndarray,
    cos_incidence: np.ndarray,
    detection_range,
    min_range: float,
    sigma: float,
    rng: np.random.Generator,
) -> Returns:
    """Apply the intensity model, range limit, dropout, range noise and multipath to the hits."""
    idx = np.flatnonzero(np.isfinite(hit_range) & (hit_range > min_range))
    n = len(idx)
    mat = material[idx]
    refl = base[idx] * np.power(np.clip(cos_incidence[idx], 1e-3, 1.0), _EXPONENT32[mat])
    noise = rng.standard_normal((4, n), dtype=np.float32)
    refl *= np.exp(0.08 * noise[3])
    limit = detection_range(refl) * (1.0 + 0.08 * noise[0])
    r = hit_range[idx]
    ok = (r < limit) & (rng.random(n, dtype=np.float32) >= DROPOUT_SHARE)
    idx, refl = idx[ok], refl[ok]
    r = r[ok] + sigma * noise[1, ok]
    a = refl + 0.004 * np.abs(noise[2, ok])
    ghost = rng.random(len(idx), dtype=np.float32) < MULTIPATH_SHARE
    k = int(ghost.sum())
    if k:
        r[ghost] += rng.uniform(0.5, 20.0, k)
        a[ghost] = rng.uniform(0.55, 1.0, k)
    return Returns(idx, r, a.astype(np.float32))


def to_raw(reflectivity: np.ndarray, scale: float) -> np.ndarray:
    """Apparent reflectivity (1.0 = 100 % diffuse) to the sensor's integer scale, as float32."""
    diffuse = np.minimum(reflectivity, 1.0) * scale
    retro = scale + 1.0 + (254.0 - scale) * np.clip((reflectivity - 1.0) / 3.0, 0.0, 1.0)
    return np.rint(np.where(reflectivity > 1.0, retro, diffuse)).clip(0, 255).astype(np.float32)
