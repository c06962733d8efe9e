"""Lanes from markings alone (paper Alg. 2): relative lookups, superlines, boundaries, sections.

The stage in the order it runs (`build.build_lane_model`): `lookups` (candidates -> relative and
global lookups -> superlines), `frame` (the station frame along the road), `tracks` (every line as
a fitted t(s), double lines folded, where it was seen, lines joined across gaps), `labels` (marking
points to lines), `structure` (the carriageway's lines at every station, tapers followed), `tapers`
(entry and exit lanes), `dividers` (directions on a paint-only two-way road), `sections`, `marks`
(dash pattern, painted width); `lanes_json` writes and reads the result.

Method and the decisions the paper leaves open (parameters in `LanesConfig`):
- Relative lookups (paper): in 2D, the left and right normals at the middle of every segment
  between consecutive centres of a candidate are intersected with the segments of all other
  candidates (`max_normal_length_m`; segments crossing at more than `max_intersect_angle_deg`
  or `z_tolerance_m` higher/lower are ignored). Each hit is (candidate, side, distance).
- The paper's "distance % 3.0 m": a distance is split into whole lane steps (the quotient is the
  lateral lane offset) and a remainder that refines the width (d / k = step + remainder / k). A
  fixed 3.0 m step miscounts lanes of 4.0 m (3 x 4.0 / 3.0 = 4) and lanes under 3.0 m, so we keep
  the decomposition with the step measured on the drive: the median nearest-neighbour distance
  within [min_lane_width_m, max_lane_width_m]; `lookup_modulo_m` is only its fallback floor.
- Global lookup (paper Fig. 4): two candidates are one line when both are hit by the normals of
  a shared neighbour at the same lateral offset (within `same_line_tolerance_m`) and one follows
  the other along that neighbour (gap up to `max_link_gap_m`). Candidates that see each other
  beside them at more than the tolerance never join (union-find with conflict sets), so a
  diverging edge line and the new line at its old place stay apart. The result: superlines.
- Frame and reference line: a first road axis is the smoothed middle of the lookups' cross
  sections, ordered by geodesic distance over a neighbour graph (no trajectory). Points are
  assigned to superlines (first by candidate, then by distance to the fitted curves, which may
  grow 30 m per pass but never onto another line) and each boundary t(s) is a robust
  (Tukey-weighted) Whittaker smoother with cutoff wavelength `boundary_smoothing_m`, fitted to
  the points rather than to the cluster centres; short islands (a dash, a blob) lying off the
  curve fitted without them are dropped, and across unobserved stretches over 20 m a line keeps
  its width to the best-observed neighbour. The reference line is the centre between the
  outermost kept boundaries, smoothed (`reference_smoothing_m`); the frame is replaced by it
  twice, so the final t(s) are offsets from the written reference line itself. Z comes from the
  marking points (a plane across the road per 5 m, evaluated at t = 0, smoothed along s).
- Lane structure per station: parallel lines closer than `same_line_tolerance_m` are one (the
  one that goes on where the other ends is kept, else the better supported); carriageways split
  at spacings above `carriageway_gap_m` (steady ones above `max_lane_width_m` beside the
  outermost line) and at a space between two solid lines with lines beyond both (a median);
  the one holding the ego trajectory is kept (else the one with
  most lines, then most points) and lines of the other are ignored with a warning. Every
  adjacency of two lines must contain a stable lane stretch (width within [min, max], changing
  less than `stable_lane_slope`) of `min_section_length_m`, otherwise the outer line (or the
  weaker of two inner ones) is dropped: guard rails, gores of diverging ramps and strays never
  make lanes. Boundaries that appear or end are followed back (forward) to where the lane
  between them and their neighbour has zero width (`max_taper_length_m`), so an added lane
  grows from zero; lines that only start late or end early near the ends of the drive (not yet
  or no longer observed) are carried to the ends at a constant offset from a neighbour. Two
  rounds, so extensions count as measured lines. Sections are stretches with a constant
  boundary set; shorter than `min_section_length_m` they join a neighbour.
- Entry and exit lanes that end or begin in a taper (`_taper_lanes`): a straight marking line that
  converges onto (diverges from) the carriageway's right edge at a steady angle never has a stable lane
  beside it, so the structure drops it; it is found again from the marking points beyond the edge (a
  windowed Hough vote, then least squares) and becomes a lane from where it is first (last) seen, at
  the width measured there, to where its width reaches zero (a section boundary at both ends), when it
  is long enough, straight, seen close to the edge and never farther out than a lane width, and the
  edge goes on as the outermost line past the meeting point (`taper_*` in `LanesConfig`). Its points
  are kept out of the edge's fit (the marking chains often join a converging line to the edge, which
  then bends towards it). Right-hand traffic: a lane narrowing to zero in the ego's direction is
  "entry", one widening from zero "exit" (`LaneSection.lane_types`); the other lanes are "driving"
  (an added lane that grows from zero and goes on cannot be told from an exit lane by its markings).
- Beyond the paper: solid/broken from the painted runs along s (length-weighted median run above
  `solid_min_run_m` = solid; dash and gap are medians of runs and gaps), and the marking width
  from the spread of the points across the fitted curve, unmixing the paint (uniform) from the
  noise (Gaussian) with two quantile ranges.
- Two directions separated only by paint (LaneSection.divider_id): a solid line with lanes on
  both sides over at least `divider_min_length_m`, never crossed by the ego and with the ego on
  the side of its travel direction under right-hand traffic (see `_mark_dividers`); a broken
  line only when the ego drove both ways beside it. The opposite lanes are exported only where
  their outermost line is a solid edge line (else only the ego's direction, with a warning). The
  trajectory only tells the side; it never connects markings or counts lanes. Carriageways split
  by a physical median (above) keep only the ego's one and get no divider.
- Boundary ids run left to right by median offset; `Candidate.superline` is that id (-1 for
  candidates whose line was ignored).
"""

from __future__ import annotations

from lidar2xodr.lanes.build import NoLanesError, build_lane_model, build_road_model
from lidar2xodr.lanes.frame import Frame
from lidar2xodr.lanes.lanes_json import FORMAT, load_lanes, model_dict, model_from, read_lanes_json, save_lanes
from lidar2xodr.lanes.lookups import (
    Lookups,
    Segments,
    candidate_segments,
    global_lookup,
    lane_step,
    relative_lookups,
    split_candidates,
)
from lidar2xodr.lanes.marks import marking_widths
from lidar2xodr.lanes.tapers import LANE_TYPES

__all__ = [
    "FORMAT",
    "Frame",
    "LANE_TYPES",
    "Lookups",
    "Segments",
    "NoLanesError",
    "build_lane_model",
    "build_road_model",
    "candidate_segments",
    "global_lookup",
    "lane_step",
    "load_lanes",
    "marking_widths",
    "model_dict",
    "model_from",
    "read_lanes_json",
    "relative_lookups",
    "save_lanes",
    "split_candidates",
]
