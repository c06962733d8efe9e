"""Lane widths a map must not or should not have, as `check` reports them under `lane_widths`.

* `negative` (an error: fails the verdict): a width record whose cubic drops below 0 on its range
  (opendrive.negative_widths: its ends and its derivative's roots are checked, so a dip between
  samples is found).
* `zero_width` (a warning): a driving lane (evaluation.DRIVING_TYPES) narrower than
  `zero_width_m` over more than `zero_width_max_m` of a lane section: a lane that exists only for a
  reader's sake; CARLA spawns vehicles on it and SUMO widens it to its minimum lane width.
* `narrow` (a warning): a driving lane at least `zero_width_m` but narrower than `narrow_lane_m`
  over more than `narrow_lane_max_m`, not counting its taper: where its width is 0 at the section's
  start (or end), its first (or last) `taper_m` are a taper, not a sliver.
* `wide` (a warning): a driving lane wider than `wide_lane_m` over more than `wide_lane_max_m`: no
  lane is that wide, so two lanes were built as one (a line missed) or a line that left the road
  (a ramp's edge) was kept as this lane's border.

Widths are sampled every `width_step_m` along each lane section; a stretch is measured between its
first and last sample, per lane section (a lane continued by a link into the next section is
measured in each).
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

import numpy as np

from lidar2xodr.config import CheckConfig


def _runs(mask: np.ndarray, s: np.ndarray) -> list[tuple[float, float]]:
    """(first s, last s) of every run of True samples."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return [(float(s[a]), float(s[b - 1])) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _stretch(road: Any, k: int, lane: Any, run: tuple[float, float], w: np.ndarray, ds: np.ndarray) -> dict:
    """A finding: where (road s) a lane's stretch lies, how long it is, its smallest and largest width."""
    inside = (ds >= run[0]) & (ds <= run[1])
    s0 = road.lane_sections[k].s
    return {"road": road.id, "section": k, "lane": lane.id, "type": lane.type, "s_start": round(s0 + run[0], 2),
            "s_end": round(s0 + run[1], 2), "length_m": round(run[1] - run[0], 2),
            "min_width_m": round(float(np.min(w[inside])), 3), "max_width_m": round(float(np.max(w[inside])), 3)}


def lane_widths(odr: Any, cfg: CheckConfig | None = None) -> dict[str, Any]:
    """Negative width records, and zero-width, narrow and wide stretches of driving lanes (module docstring)."""
    from lidar2xodr.evaluation import DRIVING_TYPES

    cfg = cfg or CheckConfig()
    zero: list[dict] = []
    narrow: list[dict] = []
    wide: list[dict] = []
    for road in odr.roads.values():
        for k, sec in enumerate(road.lane_sections):
            length = sec.s_end - sec.s
            n = max(1, math.ceil(length / cfg.width_step_m))
            ds = np.linspace(0.0, length, n + 1)
            for lane in sec.lanes.values():
                if lane.id == 0 or lane.type.lower() not in DRIVING_TYPES:
                    continue
                w = lane.width(ds)
                if not np.all(np.isfinite(w)):
                    continue  # border-only lane: no width records to judge
                is_zero = w < cfg.zero_width_m
                zero += [_stretch(road, k, lane, r, w, ds) for r in _runs(is_zero, ds)
                         if r[1] - r[0] > cfg.zero_width_max_m]
                sliver = (w < cfg.narrow_lane_m) & ~is_zero
                if is_zero[0]:
                    sliver &= ds > cfg.taper_m
                if is_zero[-1]:
                    sliver &= ds < length - cfg.taper_m
                narrow += [_stretch(road, k, lane, r, w, ds) for r in _runs(sliver, ds)
                           if r[1] - r[0] > cfg.narrow_lane_max_m]
                wide += [_stretch(road, k, lane, r, w, ds) for r in _runs(w > cfg.wide_lane_m, ds)
                         if r[1] - r[0] > cfg.wide_lane_max_m]
    warnings = [f"road {z['road']} lane {z['lane']}: zero width (< {cfg.zero_width_m} m) over {z['length_m']:.1f} m "
                f"(s {z['s_start']:.1f}-{z['s_end']:.1f})" for z in zero]
    warnings += [f"road {x['road']} lane {x['lane']}: narrower than {cfg.narrow_lane_m} m over {x['length_m']:.1f} m, "
                 f"not a taper (s {x['s_start']:.1f}-{x['s_end']:.1f}, down to {x['min_width_m']:.2f} m)"
                 for x in narrow]
    warnings += [f"road {x['road']} lane {x['lane']}: wider than {cfg.wide_lane_m} m over {x['length_m']:.1f} m "
                 f"(s {x['s_start']:.1f}-{x['s_end']:.1f}, up to {x['max_width_m']:.2f} m): two lanes as one, or a "
                 "border that left the road" for x in wide]
    return {"negative": [asdict(w) for w in odr.negative_widths()], "zero_width": zero, "narrow": narrow,
            "wide": wide, "warnings": warnings}

