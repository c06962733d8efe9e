"""The error along the road: where on the drive the generated map is off the reference, and by how much.

The same measure as `compare` (evaluation.py), kept per sample instead of summed: for every
sample of a generated carriageway centre line, its distance to the nearest reference centre line of
the same travel direction (what `centerline.rmse_m` summarises), and the lane counts of both maps
there (what `lane_count_agreement` counts), plotted against the station s of the generated road.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidar2xodr.config import EvaluationConfig
from lidar2xodr.evaluation import DRIVING_TYPES, _frame_transform, carriageways, nearest
from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.report.mapview import typed


@dataclass
class Profile:
    """One carriageway of the generated map: station, place, error and lane counts per sample."""

    label: str
    s: np.ndarray
    xy: np.ndarray
    error_m: np.ndarray
    lanes: np.ndarray
    reference_lanes: np.ndarray


def _labels(odr: OpenDriveMap, step: float) -> list[str]:
    """Names of the (road, side) groups in the order `carriageways` numbers them."""
    seen: dict[tuple[str, int], str] = {}
    for sec in odr.sample(step):
        for side in (1, -1):
            if any(i * side > 0 and sec.lane_types[i].lower() in DRIVING_TYPES for i in sec.lane_ids):
                seen.setdefault((sec.road_id, side), f"road {sec.road_id}" + (" (opposite)" if side > 0 else ""))
    return list(seen.values())


def error_profiles(generated: Path, reference: Path, cfg: EvaluationConfig, step: float) -> list[Profile]:
    """Per carriageway of the generated map, sampled every `step` m (coarser than `compare` is fine to draw)."""
    gen_map, ref_map = OpenDriveMap.load(generated), OpenDriveMap.load(reference)
    transform, _ = _frame_transform(gen_map, ref_map, Path(generated))
    gen = carriageways(gen_map, step, transform)
    ref = carriageways(ref_map, step)
    if len(gen.centre.xy) == 0 or len(ref.centre.xy) == 0:
        return []
    dist, vertex, _ = nearest(ref.centre, gen.centre.xy, gen.centre.hdg, math.radians(cfg.heading_tolerance_deg))
    own, other = gen.lane_count(cfg.lane_count_min_width_m), ref.lane_count(cfg.lane_count_min_width_m)[vertex]
    labels = _labels(gen_map, step)
    n_groups = int(gen.group.max()) + 1
    if len(labels) != n_groups:
        labels = [f"carriageway {k + 1}" for k in range(n_groups)]
    out = []
    for g in range(n_groups):
        m = gen.group == g
        order = np.argsort(gen.s[m], kind="stable")
        out.append(Profile(labels[g], gen.s[m][order], gen.centre.xy[m][order], dist[m][order], own[m][order],
                           other[m][order]))
    return out


def profile_figure(profiles: list[Profile], height: int = 420) -> dict[str, Any]:
    """Distance to the reference (top) and lane counts of both maps (bottom) against s; a click zooms the map."""
    colours = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf"]
    data: list[dict[str, Any]] = []
    for k, p in enumerate(profiles):
        colour = colours[k % len(colours)]
        common = {"type": "scatter", "mode": "lines", "x": typed(np.round(p.s, 1).astype(np.float32)),
                  "customdata": typed(np.round(p.xy, 1).astype(np.float32)), "legendgroup": p.label}
        data.append({**common, "y": typed(np.round(p.error_m, 3).astype(np.float32)), "name": p.label,
                     "line": {"color": colour, "width": 1.2}, "yaxis": "y",
                     "hovertemplate": "s %{x:.0f} m: %{y:.3f} m off the reference<extra>%{fullData.name}</extra>"})
        data.append({**common, "y": typed(p.lanes.astype(np.float32)), "name": f"{p.label}: lanes", "yaxis": "y2",
                     "showlegend": False, "line": {"color": colour, "width": 1.5, "shape": "hv"},
                     "hovertemplate": "s %{x:.0f} m: %{y} lanes<extra>generated</extra>"})
        data.append({**common, "y": typed(p.reference_lanes.astype(np.float32)), "name": "reference lanes",
                     "yaxis": "y2", "showlegend": k == 0, "line": {"color": "#e4572e", "width": 1.5, "dash": "dot",
                                                                    "shape": "hv"},
                     "hovertemplate": "s %{x:.0f} m: %{y} lanes<extra>reference</extra>"})
    grid = {"gridcolor": "#eeeeee", "zeroline": False}
    layout = {
        "height": height, "margin": {"l": 60, "r": 10, "t": 10, "b": 40}, "hovermode": "x",
        "font": {"family": "sans-serif", "size": 12}, "plot_bgcolor": "white", "paper_bgcolor": "white",
        "legend": {"orientation": "h", "y": 1.02, "yanchor": "bottom"},
        "xaxis": {**grid, "anchor": "y2", "title": {"text": "s along the generated road [m]"}},
        "yaxis": {**grid, "domain": [0.4, 1.0], "rangemode": "tozero", "title": {"text": "centre line off [m]"}},
        "yaxis2": {**grid, "domain": [0.0, 0.32], "rangemode": "tozero", "dtick": 1, "title": {"text": "lanes"}},
    }
    return {"data": data, "layout": layout}
