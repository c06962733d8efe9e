"""`lidar2xodr compare`: the paper's parametrisation-invariant lateral distance, made hard to fool.

Both maps are sampled every `sample_step_m` (0.5 m) along every lane section with the project's
OpenDRIVE reader. Distances are horizontal (x, y): from a sample to the nearest point of the other
map's polyline (nearest sample by scipy cKDTree, then the exact distance to its two adjacent
segments), so the result does not depend on where either map puts its samples or geometry pieces.

Carriageway (the same rule for both maps). In every lane section, each side of lane 0 is read as
OpenDRIVE defines it: right lanes travel along s and left lanes against it under rule="RHT" (the
other way round under "LHT"). A carriageway is a maximal run of adjacent driving lanes on one side;
driving lanes are the types in `DRIVING_TYPES` (driving, entry, exit, onRamp, offRamp,
connectingRamp, slipLane, mwyEntry, mwyExit, bidirectional, HOV, bus, taxi), i.e. every marked lane a
vehicle may travel on; shoulders, stop (hard shoulder), border, restricted, median, parking, biking
and sidewalks do not count, because a map built from lane markings cannot see their outer edge. Its
boundaries are the borders of its lanes (inner border of the innermost to outer border of the
outermost lane), its centre line is the midpoint between those two outermost borders, its
half-width half their distance, its lane count the number of its lanes at least
`lane_count_min_width_m` wide (opening and closing tapers are not lanes yet). Inside a junction,
connecting roads whose borders coincide side by side (`JUNCTION_BUNDLE_*`) form one carriageway
(inner to outer, sampled along the innermost): a junction written as one connecting road per lane
(roadgen, RoadRunner) is then the carriageway it is, not one-lane carriageways each half a
carriageway off its centre; a ramp's connecting road that turns away stays one of its own. The generated map's
centre line is derived the same way, not read from its planView: a lidar2xodr map's reference line
is the road centre, so the two coincide there, and deriving it keeps the metric symmetric
(`compare X X` is 0 for any map, wherever it puts its reference line).

Matching rule (the README quotes this):
1. Every generated sample is evaluated and nothing is dropped. A generated boundary sample is matched
   to the nearest boundary of ANY reference carriageway in the whole reference map whose travel
   direction is within `heading_tolerance_deg` (45 deg) of its own (its own heading taken on
   `HEADING_BIN_DEG` = 5 deg bins); a generated centre-line sample
   likewise to the nearest reference carriageway centre line. So a generated line far from every
   reference line counts with its full distance, and a line on the opposite carriageway is measured
   against the carriageway of its own direction. (Only if the reference holds no line of that
   direction at all is the nearest line of any direction used.)
2. A generated centre sample is "matched" when that nearest reference centre lies within
   (generated half-width at that sample + `near_m`) and the sample is beside it, not beyond its end
   (more than half a sample step past its first or last point); a reference centre sample is "near"
   when the nearest generated centre line (same heading rule) lies within (that generated
   half-width + `near_m`) and the sample is beside it.
3. `boundaries.*` and `centerline.*` are statistics of the generated-to-reference distances of rule 1,
   weighted by the length each sample represents; `eval_length_m` is the generated length evaluated
   (all boundaries summed, resp. the generated centre lines).
4. `lane_count_agreement` = generated centre length whose lane count equals the count of its nearest
   reference carriageway sample and that is matched (rule 2), divided by ALL generated centre length.
5. `lane_width.bias_m` / `std_m`: for matched samples, every generated lane of full width is paired
   with the reference lane of the matched sample whose centre is nearest, if the generated lane centre
   lies inside that reference lane; statistics of generated minus reference width (`pairs` counts
   them; bias and sigma are null when there is no pair: an unmatched map has no width error to show).
6. `coverage`: the evaluated reference part is, per reference road and side, the stretch of s between
   the first and the last "near" reference sample (rule 2); coverage = near length / that length.
   Gaps in the middle (the generated map wanders off or stops and restarts) lower it; reference roads
   the generated map never comes near are not part of the evaluation (a drive covers only part of a
   network). A gap spanning whole reference roads between two covered roads is not detected.

Frames: when both maps carry a geoReference and they differ, the generated map is projected into the
reference's frame with pyproj (headings rotated with it); otherwise both are taken to share one frame
(`frame` in the result says which). Elevation is not part of the lateral distance. `compare --align`
then moves the generated map rigidly in 2D onto the reference (registration of the two maps' lane
boundaries, as fusion.py aligns drives; `alignment` in the result): the map's shape without the
drive's GNSS bias, as the paper's drive-to-drive protocol compares drives of unbiased GNSS.

7. `elevation`: for every matched generated centre sample (rule 2), its z minus the reference centre
   line's z at the foot of the perpendicular (linear between the two reference samples around it):
   length-weighted RMSE, signed mean, sigma, 95th percentile and maximum of |dz|. Both z are the
   road surface as the files write it (elevation plus superelevation at the carriageway's centre);
   when the frames are projected, z is compared as written (no vertical datum shift).

8. `lane_graph`: does the generated map ROUTE a vehicle along the reference's lanes? Each reference
   driving lane's centre line is followed through the reference's lane links (lane sections, road
   links, junction connections), sampled every `lane_graph_step_m` (0.5 m); at each sample the
   generated driving lanes of the same travel direction whose lane polygon encloses it are found. A
   sample agrees when one of them is the generated route's lane or a linked successor of it (lane
   link, road link or junction connection in the GENERATED map) and it is at least
   `lane_graph_min_width_m` (1.75 m) wide there, or narrower within `lane_graph_taper_m` (60 m) of
   its lane's first or last end (a taper). A reference lane that opens from zero width starts at its
   first sample that wide (before it the holding lanes only seed the route). A `break` is a place
   where the next sample's lane is neither; the length from there on is wrong until a lane the
   generated links can reach holds the reference lane again. Coverage enters as in rule 6: only
   reference samples inside the covered stretch of their road and side count, and every one of them
   does, so uncovered or unheld length inside it is wrong, never agreement. `agreement` = agreeing
   length / evaluated reference lane length, `wrong_m` = the rest. Full rule:
   `lidar2xodr.lane_graph`.

9. `driven` (only with a trajectory: `compare --trajectory`, e.g. a simulated drive's
   truth/poses.csv): how much of the road the drive travelled became map. The path is resampled every
   `sample_step_m` by arc length, its heading taken from the path itself. A sample was driven on the
   road when the nearest reference carriageway centre of its travel direction (rule 1's heading rule,
   checked: no fallback to the other direction) lies within that carriageway's half-width and the
   sample is beside it (any carriageway of that direction may hold it, each judged at its own
   nearest centre vertex, not only the nearest one); the same test against the generated
   carriageways says it was built.
   `share` = built / driven length. The lateral metrics above only look at what was built: a change
   that builds less road (or the easy half of it) can lower them, so they are read beside this one.

10. `road_marks`: are the lines painted as the reference paints them? Every generated boundary sample
   of rule 1 whose nearest reference boundary lies within `mark_match_m` (1 m) is judged, unless that
   reference line lies within `mark_match_m` of another border of its carriageway (a lane opening or
   closing from zero width: its two lines' paint coincides, so either type is the paint seen). Both
   roadMark types are reduced to what a driver may do (`mark_class`): solid, broken, double (solid
   broken / broken solid), none, other. `agreement` = matched length of the same class / matched
   length; `confusion_m` = the metres of each disagreement as generated -> reference; `unmatched_m`
   the generated boundary length not judged. A lane change a simulated driver may make on the
   generated map but not on the road (broken -> solid), or the other way round, shows here and in no
   lateral metric.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table
from scipy.spatial import cKDTree

from lidar2xodr.angles import wrap_angle
from lidar2xodr.config import EvaluationConfig, FusionConfig
from lidar2xodr.errors import InputError
from lidar2xodr.lane_graph import lane_graph_agreement

DRIVING_TYPES = frozenset(
    t.lower()
    for t in (
        "driving", "entry", "exit", "onRamp", "offRamp", "connectingRamp", "slipLane", "mwyEntry", "mwyExit",
        "bidirectional", "HOV", "bus", "taxi",
    )
)
HEADING_BIN_DEG = 5.0
JUNCTION_BUNDLE_TOL_M = 0.1
"""Connecting roads of one junction whose borders coincide within this are lanes of one carriageway."""
JUNCTION_BUNDLE_SHARE = 0.9
"""...over this share of both borders' samples (a ramp that leaves the through lanes is its own)."""
JUNCTION_BUNDLE_HEADING_DEG = 20.0
"""...and travelling the same way within this."""
_K_NEAREST = 4
_K_ON = 16
"""Vertices searched for the carriageways that may hold a driven sample (8 m of one line at 0.5 m
samples: a neighbouring road's centre up to a half lane beside its end is among them)."""


@dataclass
class Lines:
    """Polylines flattened into one array: vertex i continues to nxt[i] (-1 at a line's end)."""

    xy: np.ndarray  # (n, 2)
    hdg: np.ndarray  # (n,) travel heading
    prv: np.ndarray  # (n,) int
    nxt: np.ndarray  # (n,) int
    weight: np.ndarray  # (n,) length each vertex represents

    @classmethod
    def con_cat(cls, parts: list[tuple[np.ndarray, np.ndarray]]) -> Lines:
        """Polylines given as (xy (m, 2), hdg (m,)) pieces."""
        xy, hdg, prv, nxt, weight = [], [], [], [], []
        base = 0
        for pxy, phdg in parts:
            m = len(pxy)
            idx = np.arange(base, base + m)
            prv.append(np.where(idx > base, idx - 1, -1))
            nxt.append(np.where(idx < base + m - 1, idx + 1, -1))
            seg = np.hypot(*np.diff(pxy, axis=0).T) if m > 1 else np.zeros(0)
            weight.append(0.5 * (np.concatenate([[0.0], seg]) + np.concatenate([seg, [0.0]])))
            xy.append(pxy)
            hdg.append(phdg)
            base += m
        if not parts:
            return cls(np.zeros((0, 2)), np.zeros(0), np.zeros(0, int), np.zeros(0, int), np.zeros(0))
        return cls(np.concatenate(xy), np.concatenate(hdg), np.concatenate(prv), np.concatenate(nxt),
                   np.concatenate(weight))


@dataclass
class Carriageways:
    """Sampled carriageways of one map: centre lines plus per-sample lanes (padded with NaN)."""

    centre: Lines
    half_width: np.ndarray  # (n,)
    group: np.ndarray  # (n,) index of (road, side): stations of one group share the road's s
    s: np.ndarray  # (n,)
    lane_xy: np.ndarray  # (n, L, 2) lane centres, NaN-padded, inner to outer
    lane_width: np.ndarray  # (n, L)
    centre_z: np.ndarray  # (n,) road surface height at the centre line
    boundaries: Lines
    boundary_query: np.ndarray  # (k,) bool: False for the duplicate outer border of a zero-width lane
    boundary_mark: np.ndarray  # (k,) mark class of each boundary sample (`mark_class`)
    boundary_gap: np.ndarray  # (k,) distance to the nearest other border of its carriageway (inf: none)
    group_keys: list[tuple[str, int]]  # (road id, side) of each group index

    def lane_count(self, min_width: float) -> np.ndarray:
        return np.sum(np.nan_to_num(self.lane_width, nan=0.0) >= min_width, axis=1)


def _cat(parts: list[np.ndarray], empty_shape: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(empty_shape)


def _runs(ids: list[int], types: dict[int, str]) -> list[list[int]]:
    """Maximal runs of adjacent driving lanes among `ids` (ordered inner to outer)."""
    runs: list[list[int]] = []
    current: list[int] = []
    for lid in ids:
        if types[lid].lower() in DRIVING_TYPES:
            current.append(lid)
        elif current:
            runs.append(current)
            current = []
    if current:
        runs.append(current)
    return runs


@dataclass
class _Piece:
    """One carriageway run of one lane section, sampled (see `carriageways`)."""

    key: tuple[str, int]
    junction: str
    s: np.ndarray
    travel: np.ndarray
    borders: list[np.ndarray]  # (n, 2) each, inner to outer
    border_z: list[np.ndarray]  # (n,) each
    border_t: list[np.ndarray]  # (n,) each
    border_mark: list[np.ndarray]  # (n,) roadMark type each


_DENSE = 5


def _dense(xy: np.ndarray) -> np.ndarray:
    """The polyline with `_DENSE` points per segment (nearest-vertex distances then err by < 1/10 step)."""
    if len(xy) < 2:
        return xy
    u = np.arange((len(xy) - 1) * _DENSE + 1) / _DENSE
    return np.stack([np.interp(u, np.arange(len(xy)), xy[:, k]) for k in range(2)], axis=1)


def _side_by_side(inner: _Piece, outer: _Piece, tol: float) -> bool:
    """`outer` runs along the outer border of `inner`, the same way, over (nearly) all of both."""
    d, idx = cKDTree(_dense(inner.borders[-1])).query(outer.borders[0])
    idx = np.minimum(idx // _DENSE, len(inner.travel) - 1)
    back, _ = cKDTree(_dense(outer.borders[0])).query(inner.borders[-1])
    same_way = np.abs(wrap_angle(outer.travel - inner.travel[idx])) < np.radians(JUNCTION_BUNDLE_HEADING_DEG)
    return bool(np.mean((d <= tol) & same_way) >= JUNCTION_BUNDLE_SHARE
                and np.mean(back <= tol) >= JUNCTION_BUNDLE_SHARE)


def _bundles(pieces: list[_Piece], tol: float) -> list[list[int]]:
    """Chains (inner to outer) of a junction's pieces that lie side by side: a carriageway whose lanes
    the map writes as one connecting road per lane. Pieces outside junctions stay alone."""
    outer_of: dict[int, int] = {}
    has_inner: set[int] = set()
    by_junction: dict[str, list[int]] = {}
    for i, p in enumerate(pieces):
        if p.junction != "-1":
            by_junction.setdefault(p.junction, []).append(i)
    for members in by_junction.values():
        for i in members:
            for j in members:
                if i != j and j not in has_inner and i not in outer_of and _side_by_side(pieces[i], pieces[j], tol):
                    outer_of[i] = j
                    has_inner.add(j)
    chains = []
    for i in range(len(pieces)):
        if i in has_inner:
            continue
        chain = [i]
        while chain[-1] in outer_of and outer_of[chain[-1]] not in chain:
            chain.append(outer_of[chain[-1]])
        chains.append(chain)
    return chains


def carriageways(odr: Any, step: float, transform: Any = None) -> Carriageways:
    """Sample every carriageway of a map (see the module docstring for what a carriageway is)."""
    pieces: list[_Piece] = []
    for sec in odr.sample(step):
        road = odr.roads[sec.road_id]
        rule = getattr(road, "rule", "RHT")
        border_xy = {lid: sec.border_xyz[lid][:, :2] for lid in sec.lane_ids}
        hdg = sec.hdg
        if transform is not None:
            border_xy, hdg = transform(border_xy, sec.xyz[:, :2], hdg)
        for side in (1, -1):
            along = (side == -1) == (str(rule).upper() != "LHT")
            travel = hdg if along else wrap_angle(hdg + np.pi)
            ids = sorted((i for i in sec.lane_ids if i * side > 0), key=abs)
            for run in _runs(ids, sec.lane_types):
                border_ids = [run[0] - side, *run]
                pieces.append(_Piece((sec.road_id, side), str(getattr(road, "junction", "-1")), sec.s, travel,
                                     [border_xy[b] for b in border_ids],
                                     [sec.border_xyz[b][:, 2] for b in border_ids],
                                     [sec.border_t[b] for b in border_ids],
                                     [sec.border_mark.get(b, np.full(len(sec.s), "none", dtype=object))
                                      for b in border_ids]))
    centres: list[tuple[np.ndarray, np.ndarray]] = []
    bounds: list[tuple[np.ndarray, np.ndarray]] = []
    query: list[np.ndarray] = []
    marks: list[np.ndarray] = []
    gaps: list[np.ndarray] = []
    half, group, s_all, lane_xy, lane_w, centre_z = [], [], [], [], [], []
    groups: dict[tuple[str, int], int] = {}
    for p in pieces:
        prev_t = None
        for i, (xy, t, mark) in enumerate(zip(p.borders, p.border_t, p.border_mark, strict=True)):
            bounds.append((xy, p.travel))
            marks.append(np.array([mark_class(m) for m in mark], dtype=object))
            near = [np.abs(t - p.border_t[j]) for j in (i - 1, i + 1) if 0 <= j < len(p.border_t)]
            gaps.append(np.min(near, axis=0) if near else np.full(len(t), np.inf))
            query.append(np.ones(len(t), bool) if prev_t is None else np.abs(t - prev_t) > 1e-3)
            prev_t = t
    for chain in _bundles(pieces, JUNCTION_BUNDLE_TOL_M):
        base = pieces[chain[0]]
        borders, z, widths = list(base.borders), list(base.border_z), [
            np.abs(b - a) for a, b in zip(base.border_t, base.border_t[1:], strict=False)]
        for j in chain[1:]:
            p = pieces[j]
            _, idx = cKDTree(p.borders[0]).query(borders[-1])
            borders += [b[idx] for b in p.borders[1:]]
            z += [b[idx] for b in p.border_z[1:]]
            widths += [np.abs(b - a)[idx] for a, b in zip(p.border_t, p.border_t[1:], strict=False)]
        inner, outer = borders[0], borders[-1]
        centres.append((0.5 * (inner + outer), base.travel))
        centre_z.append(0.5 * (z[0] + z[-1]))
        half.append(0.5 * (np.abs(base.border_t[-1] - base.border_t[0]) if len(chain) == 1
                           else np.hypot(*(outer - inner).T)))
        group.append(np.full(len(base.s), groups.setdefault(base.key, len(groups))))
        s_all.append(base.s)
        lane_xy.append(np.stack([0.5 * (a + b) for a, b in zip(borders, borders[1:], strict=False)], axis=1))
        lane_w.append(np.stack(widths, axis=1))
    n_lanes = max((w.shape[1] for w in lane_w), default=0)
    pad_xy = [np.pad(x, ((0, 0), (0, n_lanes - x.shape[1]), (0, 0)), constant_values=np.nan) for x in lane_xy]
    pad_w = [np.pad(w, ((0, 0), (0, n_lanes - w.shape[1])), constant_values=np.nan) for w in lane_w]
    return Carriageways(
        centre=Lines.con_cat(centres),
        half_width=_cat(half, (0,)),
        group=_cat(group, (0,)).astype(int),
        s=_cat(s_all, (0,)),
        lane_xy=_cat(pad_xy, (0, 0, 2)),
        lane_width=_cat(pad_w, (0, 0)),
        centre_z=_cat(centre_z, (0,)),
        boundaries=Lines.con_cat(bounds),
        boundary_query=_cat(query, (0,)).astype(bool),
        boundary_mark=np.concatenate(marks) if marks else np.zeros(0, dtype=object),
        boundary_gap=_cat(gaps, (0,)),
        group_keys=list(groups),
    )


def _segment_distance(lines: Lines, q: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from q (m, 2) to the segments around each candidate vertex cand (m, k).

    Also says whether q lies beyond the end of the candidate's polyline (farther past its first or
    last vertex than half the end segment, i.e. the sampling resolution): such a point is not beside
    the line.
    """
    a = lines.xy[cand]
    qa = q[:, None, :] - a
    best = np.hypot(qa[..., 0], qa[..., 1])
    beyond = np.zeros(cand.shape, bool)
    for nb, sign in ((lines.prv[cand], 1.0), (lines.nxt[cand], -1.0)):
        ok = nb >= 0
        b = lines.xy[np.where(ok, nb, cand)]
        ab = b - a
        dot = np.sum(qa * ab, axis=2)
        u = np.clip(dot / np.maximum(np.sum(ab * ab, axis=2), 1e-300), 0.0, 1.0)
        foot = qa - u[..., None] * ab
        best = np.where(ok, np.minimum(best, np.hypot(foot[..., 0], foot[..., 1])), best)
        other = lines.nxt[cand] if sign > 0 else lines.prv[cand]
        c = lines.xy[np.where(other >= 0, other, cand)]
        ac = a - c
        beyond |= ~ok & ((other < 0) | (np.sum(qa * ac, axis=2) > 0.5 * np.sum(ac * ac, axis=2)))
    beyond &= best > 1e-9
    return best, beyond


def _candidates_by_heading(lines: Lines, q: np.ndarray, q_hdg: np.ndarray, tol_rad: float, k_max: int,
                           any_heading: bool) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(query indices, their `k_max` nearest vertices of agreeing heading) per HEADING_BIN_DEG bin of the
    queries' headings; a line agrees when its heading is within `tol_rad` of the bin centre (one
    cKDTree per distinct set of agreeing vertices). Where no line agrees, every vertex is a candidate
    with `any_heading`, else the bin is skipped."""
    bin_rad = math.radians(HEADING_BIN_DEG)
    n_bins = round(2.0 * math.pi / bin_rad)
    q_bin = np.floor(np.mod(q_hdg, 2.0 * math.pi) / bin_rad).astype(int) % n_bins
    trees: dict[bytes, tuple[np.ndarray, cKDTree]] = {}
    for b in np.unique(q_bin):
        agree = np.abs(wrap_angle(lines.hdg - (b + 0.5) * bin_rad)) <= tol_rad
        if not agree.any():
            if not any_heading:
                continue
            agree = np.ones(len(lines.hdg), bool)
        key = np.packbits(agree).tobytes()
        if key not in trees:
            sub = np.flatnonzero(agree)
            trees[key] = (sub, cKDTree(lines.xy[sub]))
        sub, tree = trees[key]
        sel = np.flatnonzero(q_bin == b)
        k = min(k_max, len(sub))
        _, cand = tree.query(q[sel], k=k)
        yield sel, sub[np.asarray(cand).reshape(len(sel), k)]


def nearest(lines: Lines, q: np.ndarray, q_hdg: np.ndarray, tol_rad: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance from each query point to the nearest polyline of agreeing travel heading, its vertex,
    and whether the point lies beyond that polyline's end (see `_segment_distance`).

    Queries are grouped by their heading in HEADING_BIN_DEG bins; a line agrees when its heading is
    within `tol_rad` of the bin centre. Candidates are the nearest agreeing vertices (one cKDTree per
    distinct set of agreeing vertices); the distance is the exact one to the segments adjacent to
    them. Where no line of `lines` agrees, the heading is ignored.
    """
    dist = np.full(len(q), np.inf)
    vertex = np.full(len(q), -1)
    beyond = np.zeros(len(q), bool)
    for sel, cand in _candidates_by_heading(lines, q, q_hdg, tol_rad, _K_NEAREST, any_heading=True):
        d, past = _segment_distance(lines, q[sel], cand)
        j = np.argmin(d, axis=1)
        rows = np.arange(len(sel))
        dist[sel], vertex[sel], beyond[sel] = d[rows, j], cand[rows, j], past[rows, j]
    return dist, vertex, beyond


def _z_at(lines: Lines, z: np.ndarray, q: np.ndarray, vertex: np.ndarray) -> np.ndarray:
    """z of `lines` at the foot of the perpendicular from q (m, 2) on the segments around `vertex` (m,)."""
    best_d = np.full(len(q), np.inf)
    out = z[vertex].copy()
    a = lines.xy[vertex]
    for nb in (lines.prv[vertex], lines.nxt[vertex]):
        ok = nb >= 0
        b_idx = np.where(ok, nb, vertex)
        ab = lines.xy[b_idx] - a
        u = np.clip(np.sum((q - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0.0, 1.0)
        d = np.hypot(*(q - a - u[:, None] * ab).T)
        take = ok & (d < best_d)
        out[take] = ((1.0 - u) * z[vertex] + u * z[b_idx])[take]
        best_d = np.where(take, d, best_d)
    return out


def _elevation(gen: Carriageways, ref: Carriageways, matched: np.ndarray, v_c: np.ndarray) -> dict[str, float]:
    """Generated minus reference centre-line z on matched samples (rule 7)."""
    idx = np.flatnonzero(matched)
    if idx.size == 0:
        return {**_stats(np.zeros(0), np.zeros(0)), "mean_m": 0.0}
    dz = gen.centre_z[idx] - _z_at(ref.centre, ref.centre_z, gen.centre.xy[idx], v_c[idx])
    w = gen.centre.weight[idx]
    stats = _stats(np.abs(dz), w)
    stats["mean_m"] = float(np.sum(w * dz) / max(float(w.sum()), 1e-300))
    stats["std_m"] = float(math.sqrt(max(np.sum(w * (dz - stats["mean_m"]) ** 2) / max(float(w.sum()), 1e-300), 0.0)))
    return stats


def _stats(d: np.ndarray, w: np.ndarray) -> dict[str, float]:
    """Length-weighted RMSE, mean, sigma, 95th percentile and maximum of distances d."""
    total = float(w.sum())
    if len(d) == 0 or total <= 0:
        return {"rmse_m": 0.0, "mean_m": 0.0, "std_m": 0.0, "p95_m": 0.0, "max_m": 0.0, "eval_length_m": 0.0}
    mean = float(np.sum(w * d) / total)
    order = np.argsort(d, kind="stable")
    cum = np.cumsum(w[order])
    p95 = float(d[order][min(np.searchsorted(cum, 0.95 * total), len(d) - 1)])
    return {
        "rmse_m": float(math.sqrt(np.sum(w * d * d) / total)),
        "mean_m": mean,
        "std_m": float(math.sqrt(max(np.sum(w * (d - mean) ** 2) / total, 0.0))),
        "p95_m": p95,
        "max_m": float(d.max()),
        "eval_length_m": total,
    }


def _frame_transform(gen: Any, ref: Any, gen_path: Path) -> tuple[Any, str]:
    """Projection of generated coordinates into the reference frame when both geoReferences differ."""
    g, r = (" ".join(m.geo_reference.split()) if m.geo_reference else None for m in (gen, ref))
    if not g or not r:
        return None, "shared local frame (a map has no geoReference)"
    if g == r:
        return None, "shared geoReference"
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError

    try:
        tf = Transformer.from_crs(CRS.from_user_input(g), CRS.from_user_input(r), always_xy=True)
    except CRSError as exc:
        raise InputError(gen_path, f"geoReference cannot be used to align the maps: {exc}") from None

    def apply(border_xy: dict[int, np.ndarray], ref_xy: np.ndarray, hdg: np.ndarray
              ) -> tuple[dict[int, np.ndarray], np.ndarray]:
        out = {k: np.stack(tf.transform(v[:, 0], v[:, 1]), axis=1) for k, v in border_xy.items()}
        x0, y0 = tf.transform(ref_xy[:, 0], ref_xy[:, 1])
        x1, y1 = tf.transform(ref_xy[:, 0] + np.cos(hdg), ref_xy[:, 1] + np.sin(hdg))
        return out, np.arctan2(np.asarray(y1) - y0, np.asarray(x1) - x0)

    return apply, "generated map projected into the reference geoReference"


def _load(path: Path) -> Any:
    from lidar2xodr.opendrive import OpenDriveMap

    return OpenDriveMap.load(path)


def _rigid_alignment(gen: Carriageways, ref: Carriageways, transform: Any, align: FusionConfig
                     ) -> tuple[Any, dict[str, float]]:
    """`transform` followed by the 2D rigid motion that puts the generated boundaries on the reference's.

    The registration is fusion.py's (grid search within `align.search_radius_m`, then ICP): it takes
    out a constant GNSS bias or an odometry drive's unknown placement, so what remains is the
    map's shape. Heights are left as they are.
    """
    from lidar2xodr.fusion import align as register

    def xyz(cw: Carriageways) -> np.ndarray:
        return np.column_stack([cw.boundaries.xy, np.zeros(len(cw.boundaries.xy))])

    t, share, _ = register(xyz(ref), xyz(gen), align)
    rot, shift = t[:2, :2], t[:2, 3]
    yaw = math.atan2(rot[1, 0], rot[0, 0])

    def apply(border_xy: dict[int, np.ndarray], ref_xy: np.ndarray, hdg: np.ndarray
              ) -> tuple[dict[int, np.ndarray], np.ndarray]:
        if transform is not None:
            border_xy, hdg = transform(border_xy, ref_xy, hdg)
        return {k: v @ rot.T + shift for k, v in border_xy.items()}, wrap_angle(hdg + yaw)

    return apply, {"dx_m": float(shift[0]), "dy_m": float(shift[1]), "yaw_deg": math.degrees(yaw),
                   "inlier_share": share}


def compare_maps(generated: Path, reference: Path, cfg: EvaluationConfig, align: FusionConfig | None = None,
                 trajectory: np.ndarray | None = None) -> dict[str, Any]:
    """Metrics of a generated map against a reference map (rules in the module docstring).

    With `align`, the generated map is first moved rigidly in 2D onto the reference (`_rigid_alignment`).
    With `trajectory` ((n, 2) x, y in the reference's frame), also the share of the driven road that was
    built (rule 9).
    """
    generated, reference = Path(generated), Path(reference)
    gen_map, ref_map = _load(generated), _load(reference)
    transform, frame = _frame_transform(gen_map, ref_map, generated)
    gen = carriageways(gen_map, cfg.sample_step_m, transform)
    ref = carriageways(ref_map, cfg.sample_step_m)
    alignment = None
    if align is not None and len(gen.boundaries.xy) and len(ref.boundaries.xy):
        transform, alignment = _rigid_alignment(gen, ref, transform, align)
        gen = carriageways(gen_map, cfg.sample_step_m, transform)
        frame += (f"; then moved rigidly onto the reference: x {alignment['dx_m']:+.2f} m, y {alignment['dy_m']:+.2f}"
                  f" m, yaw {alignment['yaw_deg']:+.3f} deg, {alignment['inlier_share']:.0%} of its boundary points "
                  "matched")
    for cw, path in ((gen, generated), (ref, reference)):
        if len(cw.centre.xy) == 0:
            raise InputError(path, f"no driving lanes to evaluate (lane types counted: {sorted(DRIVING_TYPES)})")
    tol = math.radians(cfg.heading_tolerance_deg)

    q = gen.boundary_query
    d_b, v_b, _ = nearest(ref.boundaries, gen.boundaries.xy[q], gen.boundaries.hdg[q], tol)
    d_c, v_c, past_c = nearest(ref.centre, gen.centre.xy, gen.centre.hdg, tol)
    matched = (d_c <= gen.half_width + cfg.near_m) & ~past_c

    gen_count = gen.lane_count(cfg.lane_count_min_width_m)
    ref_count = ref.lane_count(cfg.lane_count_min_width_m)
    w_gen = gen.centre.weight
    agree = matched & (gen_count == ref_count[v_c])
    lane_count_agreement = float(np.sum(w_gen[agree]) / max(np.sum(w_gen), 1e-300))

    width = _lane_width(gen, ref, matched, v_c, cfg.lane_count_min_width_m)

    d_r, v_r, past_r = nearest(gen.centre, ref.centre.xy, ref.centre.hdg, tol)
    near = (d_r <= gen.half_width[v_r] + cfg.near_m) & ~past_r
    coverage, ref_length = _coverage(ref, near)
    lane_graph = lane_graph_agreement(gen_map, ref_map, cfg, DRIVING_TYPES, _covered_stretches(ref, near), transform)

    return {
        "boundaries": _stats(d_b, gen.boundaries.weight[q]),
        "centerline": _stats(d_c, w_gen),
        "lane_count_agreement": lane_count_agreement,
        "lane_width": width,
        "elevation": _elevation(gen, ref, matched, v_c),
        "coverage": coverage,
        "reference_eval_length_m": ref_length,
        "lane_graph": lane_graph,
        "road_marks": _road_marks(gen.boundary_mark[q], ref.boundary_mark[v_b], gen.boundaries.weight[q],
                                  (d_b <= cfg.mark_match_m) & (ref.boundary_gap[v_b] >= cfg.mark_match_m)),
        "driven": None if trajectory is None else _driven(gen, ref, trajectory, cfg.sample_step_m, tol),
        "frame": frame,
        "alignment": alignment,
        "settings": {
            "sample_step_m": cfg.sample_step_m,
            "near_m": cfg.near_m,
            "heading_tolerance_deg": cfg.heading_tolerance_deg,
            "lane_count_min_width_m": cfg.lane_count_min_width_m,
            "mark_match_m": cfg.mark_match_m,
            "lane_graph_step_m": cfg.lane_graph_step_m,
            "lane_graph_min_width_m": cfg.lane_graph_min_width_m,
            "lane_graph_taper_m": cfg.lane_graph_taper_m,
        },
    }


MARK_CLASSES = ("solid", "broken", "double", "none", "other")


def mark_class(mark_type: str) -> str:
    """The class of an OpenDRIVE roadMark type that decides what a driver may do (rule 10): solid (no
    crossing: solid, solid solid, curb, edge), broken (crossing allowed: broken, broken broken, botts
    dots), double (solid broken or broken solid: crossing one way only), none (no paint: none, grass),
    other (custom and anything else)."""
    kind = str(mark_type).strip().lower()
    if kind in ("solid", "solid solid", "curb", "edge"):
        return "solid"
    if kind in ("broken", "broken broken", "botts dots"):
        return "broken"
    if kind in ("solid broken", "broken solid"):
        return "double"
    if kind in ("none", "grass", ""):
        return "none"
    return "other"


def _road_marks(gen: np.ndarray, ref: np.ndarray, weight: np.ndarray, matched: np.ndarray) -> dict[str, Any]:
    """Rule 10: agreement of the road marks' classes on the matched boundary length, and the confusion
    in metres (generated class -> reference class)."""
    w = weight[matched]
    g, r = gen[matched], ref[matched]
    total = float(np.sum(w))
    confusion = {f"{a}->{b}": round(float(np.sum(w[(g == a) & (r == b)])), 1)
                 for a in MARK_CLASSES for b in MARK_CLASSES if a != b and np.any((g == a) & (r == b))}
    return {
        "agreement": float(np.sum(w[g == r]) / total) if total > 0 else None,
        "matched_m": total,
        "unmatched_m": float(np.sum(weight[~matched])),
        "confusion_m": confusion,
    }


def load_trajectory(path: Path) -> np.ndarray:
    """x, y of a drive's path from a CSV with a header naming x and y columns (rule 9)."""
    path = Path(path)
    try:
        with path.open(encoding="utf-8") as fh:
            header = [c.strip().lower() for c in fh.readline().split(",")]
            if "x" not in header or "y" not in header:
                raise InputError(path, f"a trajectory needs x and y columns; the header has {', '.join(header)}")
            cols = (header.index("x"), header.index("y"))
            xy = np.array([[float(row.split(",")[c]) for c in cols] for row in fh if row.strip()], dtype=np.float64)
    except OSError as exc:
        raise InputError(path, f"cannot read the trajectory: {exc.strerror or exc}") from None
    except (ValueError, IndexError, UnicodeDecodeError):
        raise InputError(path, "a trajectory row has no number in its x or y column") from None
    if len(xy) < 2 or not np.isfinite(xy).all():
        raise InputError(path, "a trajectory needs at least two rows of finite x and y")
    return xy


def _path_samples(path: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """A path resampled every `step` by arc length, with the heading of the path itself (rule 9)."""
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
    moved = np.concatenate([[True], np.diff(arc) > 1e-6])
    path, arc = path[moved], arc[moved]
    if arc[-1] < step:
        return np.zeros((0, 2)), np.zeros(0)
    u = np.arange(0.0, arc[-1], step)
    q = np.stack([np.interp(u, arc, path[:, k]) for k in range(2)], axis=1)
    ahead = np.stack([np.interp(np.minimum(u + step, arc[-1]), arc, path[:, k]) for k in range(2)], axis=1)
    behind = np.stack([np.interp(np.maximum(u - step, 0.0), arc, path[:, k]) for k in range(2)], axis=1)
    return q, np.arctan2(*(ahead - behind).T[::-1])


def _on_carriageway(cw: Carriageways, q: np.ndarray, hdg: np.ndarray, tol: float) -> np.ndarray:
    """Whether each sample lies on a carriageway of its own travel direction, beside it (rule 9).

    Each centre line among the `_K_ON` nearest vertices of agreeing heading is judged at its own
    nearest vertex, and any may hold the sample, not only the nearest line: where a lane appears at
    full width at a road's end, the next road's centre jumps sideways, and the samples just past the
    first road's end are nearest its last vertex, beyond it."""
    held = np.zeros(len(q), bool)
    if len(cw.centre.xy) == 0 or len(q) == 0:
        return held
    lines = cw.centre
    line_of = np.cumsum(lines.prv < 0) - 1
    for sel, cand in _candidates_by_heading(lines, q, hdg, tol, _K_ON, any_heading=False):
        d, past = _segment_distance(lines, q[sel], cand)
        line = line_of[cand]
        same_line = line[:, :, None] == line[:, None, :]
        order = np.arange(cand.shape[1])
        # a vertex is its line's own when no other of that line is nearer, ties to the nearer vertex (the
        # query's order): the last vertex of a line the sample is past, not the one before, at the same d
        ahead = (d[:, None, :] < d[:, :, None]) | ((d[:, None, :] == d[:, :, None]) & (order[None, :] < order[:, None]))
        nearest_of_line = ~np.any(same_line & ahead, axis=2)
        same_way = np.abs(wrap_angle(lines.hdg[cand] - hdg[sel, None])) <= tol
        held[sel] = np.any(nearest_of_line & (d <= cw.half_width[cand]) & ~past & same_way, axis=1)
    return held


def _driven(gen: Carriageways, ref: Carriageways, path: np.ndarray, step: float, tol: float) -> dict[str, float]:
    """Rule 9: the driven road length and the share of it the generated map holds."""
    q, hdg = _path_samples(path, step)
    driven = _on_carriageway(ref, q, hdg, tol)
    built = driven & _on_carriageway(gen, q, hdg, tol)
    driven_m, built_m = float(driven.sum()) * step, float(built.sum()) * step
    return {"share": built_m / driven_m if driven_m > 0 else 0.0, "driven_m": driven_m, "built_m": built_m}


def path_on_map(map_path: Path, path: np.ndarray, cfg: EvaluationConfig) -> dict[str, float]:
    """How much of a drive's own path (x, y in the map's frame) lies on the map's driving carriageways of
    its direction: a build's coverage of its drive, without a reference (U-turns and junctions the
    map does not model count as off the map)."""
    q, hdg = _path_samples(np.asarray(path, dtype=np.float64)[:, :2], cfg.sample_step_m)
    on = _on_carriageway(carriageways(_load(Path(map_path)), cfg.sample_step_m), q, hdg,
                         math.radians(cfg.heading_tolerance_deg))
    path_m, on_m = float(len(q)) * cfg.sample_step_m, float(on.sum()) * cfg.sample_step_m
    return {"share": on_m / path_m if path_m > 0 else 0.0, "path_m": path_m, "on_map_m": on_m}


def _lane_width(gen: Carriageways, ref: Carriageways, matched: np.ndarray, v_c: np.ndarray, min_w: float
                ) -> dict[str, float | int | None]:
    """Generated minus reference width of every full-width generated lane inside a reference lane."""
    idx = np.flatnonzero(matched)
    if idx.size == 0 or gen.lane_width.shape[1] == 0:
        return {"bias_m": None, "std_m": None, "pairs": 0}
    g_xy, g_w = gen.lane_xy[idx], gen.lane_width[idx]  # (m, Lg, 2), (m, Lg)
    r_xy, r_w = ref.lane_xy[v_c[idx]], ref.lane_width[v_c[idx]]  # (m, Lr, 2), (m, Lr)
    d = np.hypot(*(g_xy[:, :, None, :] - r_xy[:, None, :, :]).transpose(3, 0, 1, 2))  # (m, Lg, Lr)
    d = np.where(np.isnan(d), np.inf, d)
    j = np.argmin(d, axis=2)
    dj = np.take_along_axis(d, j[..., None], axis=2)[..., 0]
    rw = np.take_along_axis(r_w, j, axis=1)
    ok = np.isfinite(dj) & (dj < 0.5 * np.nan_to_num(rw, nan=0.0)) & (g_w >= min_w) & (rw >= min_w)
    diff = (g_w - rw)[ok]
    weights = np.broadcast_to(gen.centre.weight[idx][:, None], g_w.shape)[ok]
    if diff.size == 0 or weights.sum() <= 0:
        return {"bias_m": None, "std_m": None, "pairs": 0}
    bias = float(np.sum(weights * diff) / weights.sum())
    std = float(math.sqrt(np.sum(weights * (diff - bias) ** 2) / weights.sum()))
    return {"bias_m": bias, "std_m": std, "pairs": int(diff.size)}


def _covered_stretches(ref: Carriageways, near: np.ndarray) -> dict[tuple[str, int], tuple[float, float]]:
    """Per reference (road id, side): the s range between its first and last near sample (rule 6)."""
    out: dict[tuple[str, int], tuple[float, float]] = {}
    for g in np.unique(ref.group[near]):
        s = ref.s[near & (ref.group == g)]
        out[ref.group_keys[int(g)]] = (float(s.min()), float(s.max()))
    return out


def _coverage(ref: Carriageways, near: np.ndarray) -> tuple[float, float]:
    """Near reference length over the reference stretch between the first and last near sample per group."""
    n_groups = int(ref.group.max()) + 1 if len(ref.group) else 0
    s_min = np.full(n_groups, np.inf)
    s_max = np.full(n_groups, -np.inf)
    np.minimum.at(s_min, ref.group[near], ref.s[near])
    np.maximum.at(s_max, ref.group[near], ref.s[near])
    evaluated = (ref.s >= s_min[ref.group]) & (ref.s <= s_max[ref.group])
    w = ref.centre.weight
    total = float(np.sum(w[evaluated]))
    if total <= 0:
        return 0.0, 0.0
    return float(np.sum(w[evaluated & near]) / total), total


def print_metrics(metrics: dict[str, Any], console: Console) -> None:
    """The metrics as one rich table."""
    table = Table(title="generated vs reference (lateral distance, m)")
    for col in ("lines", "RMSE", "mean", "sigma", "p95", "max", "length (m)"):
        table.add_column(col, justify="right" if col != "lines" else "left", no_wrap=True)
    for key in ("boundaries", "centerline"):
        m = metrics[key]
        table.add_row(key, *(f"{m[k]:.3f}" for k in ("rmse_m", "mean_m", "std_m", "p95_m", "max_m")),
                      f"{m['eval_length_m']:.0f}")
    console.print(table)
    summary = Table(show_header=False)
    summary.add_column("item")
    summary.add_column("value", justify="right")
    summary.add_row("lane count agreement", f"{metrics['lane_count_agreement']:.3f}")
    width = metrics["lane_width"]
    summary.add_row("lane width bias (m)", "no matched lane" if width["bias_m"] is None else f"{width['bias_m']:+.3f}")
    summary.add_row("lane width sigma (m)", "no matched lane" if width["std_m"] is None else f"{width['std_m']:.3f}")
    z = metrics["elevation"]
    summary.add_row("elevation RMSE / mean / max (m)", f"{z['rmse_m']:.3f} / {z['mean_m']:+.3f} / {z['max_m']:.3f}")
    summary.add_row("coverage of the reference", f"{metrics['coverage']:.3f}")
    if metrics.get("driven"):
        dr = metrics["driven"]
        summary.add_row("driven road built", f"{dr['share']:.3f} ({dr['built_m']:.0f} of {dr['driven_m']:.0f} m)")
    graph = metrics["lane_graph"]
    summary.add_row("lane graph agreement / breaks / wrong (m)",
                    f"{graph['agreement']:.3f} / {graph['breaks']} / {graph['wrong_m']:.0f}")
    marks = metrics.get("road_marks")
    if marks:
        wrong = ", ".join(f"{k} {v:.0f} m" for k, v in sorted(marks["confusion_m"].items(), key=lambda kv: -kv[1]))
        summary.add_row("road mark agreement (solid / broken / double / none)",
                        "no matched boundary" if marks["agreement"] is None
                        else f"{marks['agreement']:.3f}" + (f" ({wrong})" if wrong else ""))
    summary.add_row("evaluated reference length (m)", f"{metrics['reference_eval_length_m']:.0f}")
    summary.add_row("frame", metrics["frame"])
    console.print(summary)
