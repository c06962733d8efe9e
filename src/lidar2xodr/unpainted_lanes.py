"""Lanes beyond a broken outermost line: a broken line always has a lane on both sides.

A broken (lane) line separates two lanes of traffic; it never marks the edge of a carriageway
(edge lines are solid). Where the outermost kept line of the carriageway is broken, the lane
beyond it exists but its outer border was not seen: unpainted (roads that leave the inner edge
beside a narrow shoulder without a line, as roadgen's corridors do and real roads under
maintenance do), worn away, or beyond the sensor's reach. The lanes stage would otherwise stop
at the broken line and build one lane fewer, and the road centre half a lane off.

The lane's width comes from the data: the median width of the lane on the other side of the
broken line over the stretch where the line is outermost (lanes of one carriageway share their
width). Its outer border is written without a road mark ("none"). Only lines whose dash pattern
was measured (dash and gap lengths found) count as broken, so a solid line seen in pieces
(occlusions, sparse far returns) adds no lane.
"""

from __future__ import annotations

import numpy as np

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import TAPER_LANE_TYPES, LaneModel
from lidar2xodr.lanes.smoothing import _runs


def _taper_beside(on: np.ndarray, t: np.ndarray, b: int, side: float, s: int, e: int, narrow: float) -> bool:
    """A lane beyond line b closes onto it just before station s, or opens from it at station e.

    The line is outermost there because that lane ended (or has not begun): no lane lies beyond
    it, whatever its paint (a broken entry line runs on a little past the taper's end)."""
    for k in (s - 1, e):
        if 0 <= k < on.shape[1]:
            gap = side * (t[on[:, k], k] - t[b, k])
            if np.any((gap > 0.0) & (gap < narrow)):
                return True
    return False


def implied_edges(on: np.ndarray, t: np.ndarray, broken: np.ndarray, solid: np.ndarray, step: float,
                  cfg: LanesConfig) -> tuple[np.ndarray, np.ndarray]:
    """Outer borders of the lanes beyond broken outermost lines.

    Only where the carriageway's outermost line on the other side is a solid edge line over at
    least half of the stretch where the broken line is outermost: the carriageway is then known to
    lie on this side of that edge, so the lane beyond the broken line is one of its own. Without a
    seen edge the broken line may be the centre line of a two-way road (town roads with curbs and
    no edge paint), and the lane beyond it the opposite direction's. The vote is over the whole
    stretch, not per station: along an exit or entry the far edge line is broken for a few hundred
    metres, and the lane beyond the broken line does not stop there. Not where a lane beyond the
    line has just closed onto it or is about to open from it (a taper's end: the lane is known not
    to be there).

    on, t: (B, M) presence and lateral offset (left positive) of the kept lines at each station;
    broken: (B,) lines with a measured dash pattern; solid: (B,) solid lines. Returns (K, M)
    presence and offsets of the implied borders, one row per (broken line, side) that is
    outermost over at least `min_section_length_m`; K may be 0.
    """
    b_n, m = on.shape
    rows_on: list[np.ndarray] = []
    rows_t: list[np.ndarray] = []
    if b_n < 2 or m == 0 or not np.any(broken):
        return np.zeros((0, m), dtype=bool), np.full((0, m), np.nan)
    t_on = np.where(on, t, np.nan)
    count = on.sum(axis=0)
    min_run = max(int(round(cfg.min_section_length_m / step)), 1)
    with np.errstate(invalid="ignore"):
        for side in (1.0, -1.0):
            key = np.where(on, side * t, -np.inf)
            outer = np.argmax(key, axis=0)
            inner_key = key.copy()
            inner_key[outer, np.arange(m)] = -np.inf
            inner = np.argmax(inner_key, axis=0)
            far_edge = np.argmax(np.where(on, -side * t, -np.inf), axis=0)
            edged = solid[far_edge]
            for b in np.flatnonzero(broken):
                here = (outer == b) & on[b] & (count >= 2)
                runs = [(s, e) for s, e in _runs(here)
                        if e - s >= min_run and 2 * np.count_nonzero(edged[s:e]) >= e - s
                        and not _taper_beside(on, t, b, side, s, e, cfg.min_lane_width_m)]
                keep = np.zeros(m, dtype=bool)
                for s, e in runs:
                    keep[s:e] = True
                width = side * (t_on[b] - t_on[inner, np.arange(m)])
                lane_like = keep & (width >= cfg.min_lane_width_m) & (width <= cfg.max_lane_width_m)
                if not lane_like.any():
                    continue
                w = float(np.median(width[lane_like]))
                rows_on.append(keep)
                rows_t.append(np.where(keep, t[b] + side * w, np.nan))
    if not rows_on:
        return np.zeros((0, m), dtype=bool), np.full((0, m), np.nan)
    return np.array(rows_on), np.array(rows_t)


def type_implied_lanes(model: LaneModel) -> None:
    """An unpainted lane that goes on as an entry or exit lane (a typed taper lane beyond the same
    broken line in the next or previous section) is that lane: it takes its type."""
    by_id = {b.id: b for b in model.boundaries}
    secs = model.sections
    for j, sec in enumerate(secs):
        n = len(sec.boundary_ids) - 1
        for k in (0, n - 1):
            outer = sec.boundary_ids[k] if k == 0 else sec.boundary_ids[k + 1]
            inner = sec.boundary_ids[k + 1] if k == 0 else sec.boundary_ids[k]
            if by_id[outer].mark_type != "none":
                continue
            for nb in (j - 1, j + 1):
                if not 0 <= nb < len(secs) or secs[nb].lane_types is None or inner not in secs[nb].boundary_ids:
                    continue
                ids = secs[nb].boundary_ids
                i = ids.index(inner)
                lane = i - 1 if k == 0 else i
                if 0 <= lane < len(ids) - 1 and secs[nb].lane_types[lane] in TAPER_LANE_TYPES:
                    types = sec.lane_types or ["driving"] * n
                    types[k] = secs[nb].lane_types[lane]
                    sec.lane_types = types
                    break
