"""OpenDRIVE export of a LaneModel or a RoadNetwork (paper Alg. 3, made continuous by construction).

Reference line (paper): the road centre of LaneModel is split into equal pieces of at most
`piece_length_m` (n = ceil(L / 100 m), so no short stub is left at the end), each written as one
paramPoly3. Each piece's cubic is fitted to its own stations plus a look-back and look-ahead of
`look_fraction` of the piece length (its cubic extrapolated there; used for the fit only), with
p = station offset / piece length and the samples nearest p = 0 and p = 1 weighted by
`endpoint_weight`.

Beyond the paper:
- Continuity by construction: instead of independent per-piece fits (1-3 cm gaps) or a chain of
  constrained fits (we tried: errors propagate and grow without look-ahead), all pieces come from
  ONE weighted least-squares solve for the position P_k and tangent D_k at every break; piece k is
  the cubic Hermite curve of (P_k, D_k, P_k+1, D_k+1), so neighbours share end point and tangent.
  Each piece is then written in the frame of its start tangent (aU = aV = bV = 0), starting at
  the end of the previous piece as a reader evaluates the written (repr-exact) numbers: leaps are
  ~1e-13 m, kinks ~1e-16 rad.
- Heading: the paper rotates each piece by the heading of the mean of its marking centres to fit
  U and V and writes that heading with the piece. A weighted cubic fit of U(p), V(p) is
  rotation-equivariant, so that rotation never changes the curve; we write the start tangent as
  hdg instead, which is what makes the heading continuous across pieces.
- pRange="normalized" and length = arc length of the fitted curve (32-point Gauss-Legendre); the
  next piece's s = previous s + that length. Coordinates stay in the local world frame of the
  LaneModel (origin at the drive's start); the header's geoReference places it on the earth.
  Known limit: a 100 m cubic cannot follow a curvature kink (clothoid meets arc) inside a piece;
  on an R = 800 m S-curve with 150 m clothoids that costs up to 2 cm.
- Lanes of a one-way carriageway in right-hand traffic: the reference line stays on the road
  centre (paper) and a <laneOffset> moves lane 0 onto the leftmost boundary, so every driving
  lane is a right lane (-1, -2, ... from left to right). A two-way road whose directions are only
  separated by paint (LaneSection.divider_id) gets lane 0 on that divider instead: the lanes right
  of it are right lanes (along s), the lanes left of it left lanes (1, 2, ... outwards; under
  rule="RHT" they travel against s), each side with its own widths, road marks and links (never
  across lane 0). laneOffset and lane widths are C1 cubic
  splines (least squares, tiny P-spline penalty) written as one cubic record every
  ~`lane_record_m`; C1 rather than C2 so tapers (whose width has a curvature kink) are followed
  to millimetres. Before fitting, every boundary's world points (reference + t * left normal of
  the LaneModel) are projected onto the written reference line, so borders follow the boundaries
  even where the fitted centre deviates; t is divided by cos(superelevation) because OpenDRIVE
  measures t along the banked surface. Records that vary less than 1 um are flattened and
  repeated records merged (the ASAM checker flags redundant records).
- Lane sections follow LaneModel.sections. Lanes are linked (predecessor and successor, both ways)
  when their lateral extents overlap at the section change. A lane without predecessor starts at
  width 0 and one without successor ends at width 0; where its markings start at full width it
  opens along a smoothstep over `taper_length_m`, and where they open by themselves (under half
  its width over the first tenth of that length, at 90 % of it only after half) it follows them.
  Linked lanes continue with the same width. An outer lane that opens from width 0 is then folded
  into the section before (width 0 there; see export_sections.py: SUMO warns about the section
  change, links would be ASAM errors).
- Lane types from LaneSection.lane_types (None: all "driving"): "entry" / "exit" for an acceleration /
  deceleration lane that ends / begins in a taper. Such a lane goes to width 0 only at its narrow end;
  at its wide end, where its outer line was first (last) seen, it starts (ends) at the measured width
  without a link: the lane goes on unobserved (a ramp's lane), so it does not open along the taper.
- Road marks: every lane's outer border and the centre lane (leftmost boundary or divider) carry the
  boundary's solid/broken mark with its width, laneChange none/both, and for broken lines with a
  known dash/gap an explicit <type><line length space/>.
- Elevation: C2 cubic spline of the reference z, by default one record per planView piece (paper:
  cubic per piece; continuity in value, slope and curvature is ours). `elevation_record_m` = 25
  writes a record every ~25 m instead: on curves_elevation the map's z went from 0.34 m RMS /
  0.86 m max off the truth to 0.078 / 0.18 m (the markings' own accuracy), grade error 0.013 ->
  0.0011 RMS; not the default yet because its records can repeat each other on flat stretches
  (ASAM warning "redundant elevation declaration" on the classic-junction test network).
  Superelevation: roll of each scan's ground plane about the road (positive = left side up, as
  OpenDRIVE), running median over scans, lightly smoothed C1 spline with one record per piece (C1
  so the linear roll ramps of road design are followed to ~1 mrad); a single zero record without
  planes.
- Optional lanes outside the measured lines: a 'shoulder' right of the rightmost line
  (`right_shoulder_m`) and a 'border' left of the leftmost (`left_border_m`); off by default
  because they are not measured.
- Header: OpenDRIVE 1.`opendrive_minor`, name, vendor, bounding box, road type, geoReference from
  model.origin.proj (else a tmerc at the origin's lat/lon, else a tmerc at 0,0 with a comment
  saying the frame is local). The date is the first ground plane's time when that is a plausible
  UNIX time (2000-2100), otherwise omitted, so the same input always gives the same bytes.

Networks (`export_network`; `export_opendrive` is a network of one road, same bytes as before):
- Road ids 1..N in network order, each road fitted as above on its own data (the shared ground
  planes near it give its superelevation). Links sharing an incoming road's end (diverge) or an
  outgoing road's start (merge) form one OpenDRIVE 1.8 `<junction type="direct">` (scenariogeneration's
  Junction/Connection with JunctionType.direct); junction ids follow the road ids (N+1, ...), so
  every id in the file is unique. One <connection incomingRoad linkedRoad contactPoint="start"> per
  link with its laneLinks (incoming lane -> outgoing lane); the roads' <link> name the junction
  (elementType="junction"), and lanes carry no predecessor/successor across roads (the standard's
  lane-linkage rule: lanes that end or start in a junction are linked by the junction only).
- Continuity rule: one end of every link is ANCHORED to the other road's written cross-section at
  the junction; roads are built in an order where the partner is written first (a cycle is an
  error). A continuation anchors the outgoing road's start: its first piece starts at the incoming
  road's written end point and heading (given as the start pose: leap and kink exactly 0). A
  branch link anchors the branch: the outgoing road at a diverge (or a lone link), the incoming
  road at a merge; its reference starts (ends) on the main road's cross-section at the t of the
  middle of the linked lanes, with the main road's heading. At an anchored end the Hermite solve
  fixes the end point and tangent direction (equality constraints); the linked lanes take the
  main road's widths and width slopes, the left border of the first linked lane the main road's t
  and dt/ds (a laneOffset constraint given the widths), elevation its value and slope (surface
  height at that t), superelevation its roll. Linked borders therefore meet to ~1e-12 m with the
  same direction. Lanes of a junction end linked to nothing start (end) at width 0 along the taper;
  a lane linked into a branch simply ends at full width (it goes on there), and so does a lane that
  leaves to or joins from a road that was not built (`RoadLink.open_in` / `open_out`).
- A branch's model (within ~0.3 m at the junction) is first bent onto its anchor: the middle of its
  linked lanes moves onto the anchor point and its heading turns onto the anchor's, the rotation
  and shift fading with a smoothstep over `junction_blend_m` (30 m, or the road's length), so the
  hard constraints agree with the data and beyond the blend the road stays on its markings (a
  synthetic 0.2 m error: 2 mm off the markings beyond 30 m; constraints alone leave 1.5 cm there
  and overshoot 10 cm nearer). The summary's deviations compare with the model as given, so the
  snap shows in them.
- Junction form: always a classic junction with connecting roads. The direct junction the roads
  are first joined by is not written: no reader available here loads it (SUMO 1.28 netconvert
  stops with "Attribute 'connectingRoad' is missing", which the 1.8 schema forbids there; CARLA
  0.9.16 raises IndexError('_Map_base::at')). The classic form
  is derived from the written direct one by cutting, not refitting (`_classic_junctions`): each link
  gets a connecting road of ~`connecting_road_m` (20 m; snapped to the nearest lane-record, section or
  geometry break within half a lane record, at most the end lane section and half the road)
  cut from the branch side: the outgoing road's start at a diverge, the incoming road's end at a merge.
  The cut keeps the curves (a paramPoly3 is cut at that arc length and re-expressed from the cut,
  cubic records are re-expanded there; records that then repeat their neighbour within 1 um are
  merged, as the ASAM checker flags them), so the map is the direct one to ~1e-12 m and `compare`
  does not change. Right lanes enter from the incoming road (contactPoint start), left lanes
  (against s) from the road after the connecting road (contactPoint end; two connections for one
  connecting road, which OpenDRIVE 1.8 allows). Connecting-road lanes link to the lanes on both
  sides; the roads outside link no lanes into the junction. Road ids 1..N stay the carriageway roads,
  junction ids follow, connecting roads come last (written after the outer roads).
- Measured on the written XML: leap and kink within roads, across continuations and across every
  cut, and `max_junction_gap_m` (check.junction_gaps on the project's reader: the largest 3D distance
  between the borders of lanes linked across a junction, at both ends of a connecting road).
- What SUMO 1.15 still warns about (reported by `check`, not fixable in the file): a lane that
  appears inside a two-way road ("Lane '-1#1_0' is not connected from any incoming edge"). SUMO gives
  a lane at most one successor and warns at a node with more than one incoming edge, which a two-way
  road's section boundary always has (the left lanes' edge); the link that would silence it (the
  appearing lane as a successor of its neighbour) is an ASAM error (road.lane.link.new_lane_appear).
  One-way roads with appearing lanes read without a warning.

Written with scenariogeneration. Patches after writing (lxml), because scenariogeneration cannot
express them: the header date (it writes now()), north/south/east/west (it writes 0), a vendor,
the geoReference as CDATA and the comment for a local frame. The paramPoly3 length is passed
through a subclass so scenariogeneration does not replace it by its own quadrature.
"""

from __future__ import annotations

import copy
import math
import tempfile
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from lxml import etree
from scenariogeneration import xodr
from scipy import sparse
from scipy.interpolate import BSpline, PPoly
from scipy.ndimage import median_filter
from scipy.sparse.linalg import MatrixRankWarning, spsolve
from scipy.spatial import cKDTree

from lidar2xodr.angles import wrap_angle
from lidar2xodr.config import ExportConfig
from lidar2xodr.data import MARK_TYPES, TAPER_LANE_TYPES, Boundary, GroundPlanes, LaneModel, RoadLink, RoadNetwork
from lidar2xodr.errors import InputError
from lidar2xodr.export_sections import fold_appearing_lanes
from lidar2xodr.fileio import write_bytes
from lidar2xodr.georeference import LOCAL_PLACEHOLDER, origin_proj

_GL_X, _GL_W = np.polynomial.legendre.leggauss(32)
_GL_X = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W
_GEOMETRY_SMOOTH = 1e-6  # P-spline penalty that only bridges data gaps (geometry, widths, elevation)
_LINK_MIN_OVERLAP_M = 0.3
_WHERE = "lane model"
_CUT_EPS = 1e-9


@dataclass
class ExportSummary:
    """What the exporter measured while writing (plain numbers, JSON-ready).

    Leap, kink and length error are re-measured on the written XML text (the length error against
    a 64-point Gauss-Legendre arc length); the deviations compare the fitted curves with the
    LaneModel: lateral distance of its reference points from the written reference line, and of
    each boundary's t from the written lane border (so tapers imposed on abrupt lanes show here).
    """

    length_m: float
    pieces: int
    lane_sections: int
    max_leap_m: float
    max_kink_rad: float
    max_length_error_m: float
    max_reference_dev_m: float
    max_border_dev_m: float
    roads: int = 1
    junctions: int = 0
    max_junction_gap_m: float = 0.0
    connecting_roads: int = 0


# --------------------------------------------------------------------------------------------
# the written reference line


@dataclass
class _Plan:
    """paramPoly3 pieces exactly as written: start s, x, y, hdg, length and local u/v coefficients."""

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    hdg: np.ndarray
    length: np.ndarray
    u: np.ndarray  # (n, 4) a, b, c, d
    v: np.ndarray

    def derivs(self, k: np.ndarray, p: np.ndarray, order: int) -> np.ndarray:
        """World-frame d^order C / dp^order of pieces k at p, shape (m, 2)."""
        if order == 0:
            basis = np.stack([np.ones_like(p), p, p**2, p**3], axis=1)
        elif order == 1:
            basis = np.stack([np.zeros_like(p), np.ones_like(p), 2 * p, 3 * p**2], axis=1)
        else:
            basis = np.stack([np.zeros_like(p), np.zeros_like(p), 2 * np.ones_like(p), 6 * p], axis=1)
        lu = np.sum(self.u[k] * basis, axis=1)
        lv = np.sum(self.v[k] * basis, axis=1)
        c, s = np.cos(self.hdg[k]), np.sin(self.hdg[k])
        out = np.stack([c * lu - s * lv, s * lu + c * lv], axis=1)
        if order == 0:
            out += np.stack([self.x[k], self.y[k]], axis=1)
        return out

    def arc(self, k: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Arc length from p = 0 to p on pieces k (Gauss-Legendre)."""
        q = p[:, None] * _GL_X[None, :]
        kk = np.repeat(k, len(_GL_X))
        speed = np.linalg.norm(self.derivs(kk, q.ravel(), 1), axis=1).reshape(q.shape)
        return p * (speed @ _GL_W)

    def project(self, pts: np.ndarray, k: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Foot points of `pts` on the curve by Newton from a guess (k, p): returns station s and left offset t."""
        k, p = k.copy(), p.astype(np.float64).copy()
        n = len(self.s)
        for _ in range(12):
            r = self.derivs(k, p, 0) - pts
            d1 = self.derivs(k, p, 1)
            d2 = self.derivs(k, p, 2)
            f = np.sum(r * d1, axis=1)
            fp = np.sum(d1 * d1, axis=1) + np.sum(r * d2, axis=1)
            step = f / np.where(np.abs(fp) > 1e-9, fp, 1e-9)
            p = p - step
            up = (p > 1.0) & (k < n - 1)
            down = (p < 0.0) & (k > 0)
            p[up] = (p[up] - 1.0) * self.length[k[up]] / self.length[k[up] + 1]
            k[up] += 1
            p[down] = 1.0 + p[down] * self.length[k[down]] / self.length[k[down] - 1]
            k[down] -= 1
            if np.max(np.abs(step)) < 1e-13 and not (up.any() or down.any()):
                break
        d1 = self.derivs(k, p, 1)
        normal = np.stack([-d1[:, 1], d1[:, 0]], axis=1) / np.linalg.norm(d1, axis=1)[:, None]
        t = np.sum((pts - self.derivs(k, p, 0)) * normal, axis=1)
        return self.s[k] + self.arc(k, p), t


def _local_end(u: np.ndarray, v: np.ndarray, x: float, y: float, h: float) -> tuple[float, float, float]:
    """End point and heading of a written paramPoly3 (as a reader evaluates it)."""
    eu, ev = float(np.sum(u)), float(np.sum(v))
    du, dv = float(u[1] + 2 * u[2] + 3 * u[3]), float(v[1] + 2 * v[2] + 3 * v[3])
    c, s = math.cos(h), math.sin(h)
    return x + c * eu - s * ev, y + s * eu + c * ev, h + math.atan2(dv, du)


def _hermite(p: np.ndarray) -> np.ndarray:
    """Cubic Hermite basis (h00, h10, h01, h11) at p, shape (m, 4)."""
    p2, p3 = p * p, p * p * p
    return np.stack([2 * p3 - 3 * p2 + 1, p3 - 2 * p2 + p, 3 * p2 - 2 * p3, p3 - p2], axis=1)


Pose = tuple[float, float, float]  # x, y, heading


def _fit_hermite(s: np.ndarray, xy: np.ndarray, breaks: np.ndarray, cfg: ExportConfig,
                 start: Pose | None = None, end: Pose | None = None, where: str = _WHERE) -> tuple[np.ndarray, ...]:
    """One least-squares solve for positions P and tangents D (per metre of station) at every break.

    Piece k is the Hermite cubic of (P_k, D_k, P_k+1, D_k+1), so neighbours share end point and
    tangent by construction. Its residuals cover its own stations plus the look-back and look-ahead
    (its cubic extrapolated), and the samples nearest its ends are weighted up (paper Alg. 3).
    `start` / `end` fix the first / last break's position and tangent direction exactly (a road
    joined to another at a junction; equality constraints, so x and y are solved together).
    """
    n = len(breaks) - 1
    look = cfg.look_fraction * cfg.piece_length_m
    origin = xy[0]
    normal = np.zeros((2 * (n + 1), 2 * (n + 1)))
    rhs = np.zeros((2 * (n + 1), 2))
    for k in range(n):
        a, b = breaks[k], breaks[k + 1]
        span = b - a
        m = np.flatnonzero((s >= a - look - 1e-9) & (s <= b + look + 1e-9))
        p = (s[m] - a) / span
        w = np.ones(len(p))
        w[np.argmin(np.abs(p))] = cfg.endpoint_weight
        w[np.argmin(np.abs(p - 1.0))] = cfg.endpoint_weight
        basis = _hermite(p) * np.array([1.0, span, 1.0, span])
        cols = [2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3]  # P_k, D_k, P_k+1, D_k+1
        normal[np.ix_(cols, cols)] += basis.T @ (basis * w[:, None])
        rhs[cols] += basis.T @ ((xy[m] - origin) * w[:, None])
    if start is None and end is None:
        sol = np.linalg.solve(normal, rhs)  # x and y share the normal matrix
        return sol[0::2] + origin, sol[1::2]
    size = 2 * (n + 1)
    lhs = np.zeros((2 * size, 2 * size))
    lhs[:size, :size] = lhs[size:, size:] = normal
    rows: list[np.ndarray] = []
    vals: list[float] = []
    fixed = [(i, pose) for i, pose in ((0, start), (n, end)) if pose is not None]
    for i, (x, y, h) in fixed:
        for col, val in ((2 * i, x - origin[0]), (size + 2 * i, y - origin[1])):
            row = np.zeros(2 * size)
            row[col] = 1.0
            rows.append(row)
            vals.append(val)
        row = np.zeros(2 * size)
        row[2 * i + 1], row[size + 2 * i + 1] = -math.sin(h), math.cos(h)  # tangent along the heading
        rows.append(row)
        vals.append(0.0)
    con = np.array(rows)
    kkt = np.block([[lhs, con.T], [con, np.zeros((len(rows), len(rows)))]])
    sol = np.linalg.solve(kkt, np.r_[rhs[:, 0], rhs[:, 1], vals])
    pos = np.stack([sol[0:size:2], sol[size:2 * size:2]], axis=1) + origin
    tan = np.stack([sol[1:size:2], sol[size + 1:2 * size:2]], axis=1)
    for i, (_, _, h) in fixed:
        if tan[i, 0] * math.cos(h) + tan[i, 1] * math.sin(h) <= 0.0:
            raise InputError(where, f"the road runs against the road it joins at its {'end' if i else 'start'}")
    return pos, tan


def _fit_plan(s: np.ndarray, xy: np.ndarray, breaks: np.ndarray, cfg: ExportConfig,
              start_pose: Pose | None = None, end_pose: Pose | None = None, where: str = _WHERE) -> _Plan:
    """Hermite fit, then each piece written in the frame of its start tangent, chained on the written numbers.

    Piece k+1 starts at the end of piece k as a reader evaluates the written attributes, with its
    heading, so rounding never opens a gap or a kink. A `start_pose` is written as given (the exact
    end of the road this one continues); an `end_pose` is met to rounding (~1e-10 m).
    """
    pos, tan = _fit_hermite(s, xy, breaks, cfg, start_pose, end_pose, where)
    rows: list[tuple[float, float, float, float, float, np.ndarray, np.ndarray]] = []
    start = start_pose or (float(pos[0, 0]), float(pos[0, 1]), math.atan2(tan[0, 1], tan[0, 0]))
    s_odr = 0.0
    for k in range(len(breaks) - 1):
        span = breaks[k + 1] - breaks[k]
        c1 = span * tan[k]
        c2 = -3 * pos[k] - 2 * span * tan[k] + 3 * pos[k + 1] - span * tan[k + 1]
        c3 = 2 * pos[k] + span * tan[k] - 2 * pos[k + 1] + span * tan[k + 1]
        x0, y0, hdg = start[0], start[1], float(wrap_angle(start[2]))
        ch, sh = math.cos(hdg), math.sin(hdg)
        u = np.array([0.0, float(np.hypot(*c1)), ch * c2[0] + sh * c2[1], ch * c3[0] + sh * c3[1]])
        v = np.array([0.0, 0.0, -sh * c2[0] + ch * c2[1], -sh * c3[0] + ch * c3[1]])
        speed = np.hypot(u[1] + 2 * u[2] * _GL_X + 3 * u[3] * _GL_X**2, v[1] + 2 * v[2] * _GL_X + 3 * v[3] * _GL_X**2)
        length = float(speed @ _GL_W)
        rows.append((s_odr, x0, y0, hdg, length, u, v))
        start = _local_end(u, v, x0, y0, hdg)
        s_odr = s_odr + length
    cols = list(zip(*rows, strict=True))
    return _Plan(*(np.array(c, dtype=np.float64) for c in cols[:5]), np.array(cols[5]), np.array(cols[6]))


# --------------------------------------------------------------------------------------------
# smoothing splines written as cubic records


@dataclass
class _Records:
    """Cubic records a + b ds + c ds^2 + d ds^3 from each start (what OpenDRIVE stores)."""

    starts: np.ndarray
    coeffs: np.ndarray  # (k, 4)

    def __call__(self, s: np.ndarray, der: int = 0) -> np.ndarray:
        i = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.starts) - 1)
        ds = s - self.starts[i]
        a, b, c, d = self.coeffs[i].T
        if der == 0:
            return a + ds * (b + ds * (c + ds * d))
        return b + ds * (2 * c + 3 * ds * d)


def _spline_records(x: np.ndarray, y: np.ndarray, breaks: np.ndarray, smooth: float = _GEOMETRY_SMOOTH,
                    constraints: tuple[tuple[float, ...], ...] = (), c1: bool = False) -> _Records:
    """Least-squares cubic B-spline on `breaks` with a P-spline penalty and equality constraints.

    C2 at the breaks, or only C1 with `c1` (double interior knots). Each constraint is (x, value)
    or (x, value, 1) for the first derivative. Returns one record per break interval.
    """
    inner = np.repeat(breaks[1:-1], 2 if c1 else 1)
    knots = np.r_[[breaks[0]] * 4, inner, [breaks[-1]] * 4]
    nb = len(knots) - 4
    design = BSpline.design_matrix(np.clip(x, breaks[0], breaks[-1]), knots, 3).tocsc()
    diff2 = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(max(nb - 2, 0), nb), format="csc")
    mu = smooth * max(len(x), 1) / nb
    lhs = design.T @ design + mu * (diff2.T @ diff2) + 1e-12 * sparse.identity(nb, format="csc")
    rhs = design.T @ y
    if constraints:
        cx = np.clip([c[0] for c in constraints], breaks[0], breaks[-1])
        crow = BSpline.design_matrix(cx, knots, 3).toarray()
        slope = np.array([len(c) > 2 and c[2] == 1 for c in constraints])
        if slope.any():
            crow[slope] = _slope_rows(cx[slope], knots)
        cval = np.array([c[1] for c in constraints])
        kkt = sparse.bmat([[lhs, sparse.csc_matrix(crow.T)], [sparse.csc_matrix(crow), None]], format="csc")
        coef = _sparse_solve(kkt, np.concatenate([rhs, cval]))[:nb]
    else:
        coef = _sparse_solve(lhs, rhs)
    pp = PPoly.from_spline(BSpline(knots, coef, 3))
    keep = np.flatnonzero(np.diff(pp.x) > 1e-9)
    return _merge_records(_Records(pp.x[keep].copy(), pp.c[::-1, keep].T.copy()), float(breaks[-1]))


def _slope_rows(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """d/dx of every cubic B-spline basis function at x (one row per x): the derivative of sum c_j B_j
    is sum 3 (c_j+1 - c_j) / (t_j+4 - t_j+1) of the quadratic basis on the inner knots (de Boor)."""
    nb = len(knots) - 4
    quad = BSpline.design_matrix(x, knots[1:-1], 2).toarray()
    scale = 3.0 / (knots[4 : nb + 3] - knots[1:nb])
    rows = np.zeros((len(x), nb))
    rows[:, 1:] += quad * scale
    rows[:, :-1] -= quad * scale
    return rows


def _sparse_solve(a: sparse.csc_matrix, b: np.ndarray) -> np.ndarray:
    """a x = b by sparse LU (the spline systems are banded: linear in the road's length, where a dense
    solve was cubic: 6.9 s of a 50 km corridor's export); least squares where a is singular
    (contradictory constraints: the nearest solution)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MatrixRankWarning)
        try:
            x = spsolve(a, b)
        except RuntimeError:  # SuperLU: "Factor is exactly singular"
            x = np.full(len(b), np.nan)
    if np.all(np.isfinite(x)):
        return np.asarray(x, dtype=np.float64)
    return np.linalg.lstsq(a.toarray(), b, rcond=None)[0]


def _non_negative(rec: _Records, end: float) -> _Records:
    """Width records with every cubic that dips below zero (by more than the check's tolerance) replaced.

    A smoothing spline pinned to zero width where a lane opens or closes can overshoot just beside
    that end (-0.001 to -0.06 m in the sweep: a negative width, so the map was refused). The record
    becomes the cubic Hermite between its end values (clipped at 0) whose end slopes are limited to
    m0 >= -3 w0 / h and m1 <= 3 w1 / h, which keeps it non-negative; records that do not dip are
    left as they are, so maps that passed keep their bytes.
    """
    from lidar2xodr.opendrive import NEGATIVE_WIDTH_TOL_M, cubic_minimum

    ends = np.append(rec.starts[1:], end)
    coeffs = rec.coeffs.copy()
    for i, (start, stop) in enumerate(zip(rec.starts, ends, strict=True)):
        h = float(stop - start)
        if h <= 0 or cubic_minimum(tuple(coeffs[i]), h)[1] >= -NEGATIVE_WIDTH_TOL_M:
            continue
        a, b, c, d = coeffs[i]
        w0, w1 = max(a, 0.0), max(a + h * (b + h * (c + h * d)), 0.0)
        m0 = max(b, -3.0 * w0 / h)
        m1 = min(b + h * (2.0 * c + 3.0 * h * d), 3.0 * w1 / h)
        dw = w1 - w0
        coeffs[i] = [w0, m0, (3.0 * dw / h - 2.0 * m0 - m1) / h, (m0 + m1 - 2.0 * dw / h) / h**2]
    return _Records(rec.starts.copy(), coeffs)


def _horner(c: np.ndarray, ds: np.ndarray) -> np.ndarray:
    """a + b ds + c ds^2 + d ds^3 as `_Records` evaluates it (the same operations, so the same bits)."""
    return c[0] + ds * (c[1] + ds * (c[2] + ds * c[3]))


def _merge_records(rec: _Records, end: float, tol: float = 1e-6) -> _Records:
    """Flatten records that vary less than `tol` and drop records that continue the previous polynomial.

    The ASAM checker flags consecutive records describing (nearly) the same polynomial as redundant;
    numerical noise of 1e-8 m on a constant lane width would otherwise produce exactly that.
    Values change by less than `tol` (1 um).
    """
    ends = np.r_[rec.starts[1:], end]
    coeffs = rec.coeffs.copy()
    if len(coeffs) == 0:
        return _Records(rec.starts.copy(), coeffs)
    length = ends - rec.starts
    ds = np.arange(9.0)[None, :] * (length / 8.0)[:, None]  # np.linspace(0, length, 9) of every record, exactly
    vals = _horner(coeffs.T[:, :, None], ds)
    flat = np.ptp(vals, axis=1) < tol
    coeffs[flat] = np.column_stack([0.5 * (vals[flat].max(axis=1) + vals[flat].min(axis=1)),
                                    np.zeros((int(flat.sum()), 3))])
    keep = [0]
    for i in range(1, len(rec.starts)):
        j = keep[-1]
        s = np.linspace(rec.starts[i], ends[i], 9)
        if np.max(np.abs(_horner(coeffs[j], s - rec.starts[j]) - _horner(coeffs[i], s - rec.starts[i]))) >= tol:
            keep.append(i)
    return _Records(rec.starts[keep], coeffs[keep])


def _uniform_breaks(a: float, b: float, step: float) -> np.ndarray:
    return np.linspace(a, b, max(1, math.ceil((b - a) / step - 1e-9)) + 1)


# --------------------------------------------------------------------------------------------
# lanes


@dataclass
class _SectionFit:
    s0: float
    s1: float
    ids: list[int]
    widths: list[_Records]
    pred: dict[int, int]  # lane index -> predecessor lane index in the previous section
    succ: dict[int, int]
    centre: int = 0  # position in `ids` of the boundary lane 0 lies on
    types: list[str] | None = None  # OpenDRIVE lane type of each lane (None: all driving)

    def lane_id(self, i: int) -> int:
        """OpenDRIVE id of lane i (between ids[i] and ids[i + 1]): right of lane 0 negative, left positive."""
        return -(i - self.centre + 1) if i >= self.centre else self.centre - i

    def borders(self, offset: np.ndarray, s: np.ndarray, der: int = 0) -> list[np.ndarray]:
        """t (or dt/ds with der=1 and offset's slope) of every boundary in `ids` as written: lane 0 at
        `offset`, widths outwards on both sides."""
        out: list[np.ndarray] = [offset] * len(self.ids)
        for i in range(self.centre, len(self.widths)):
            out[i + 1] = out[i] - self.widths[i](s, der)
        for i in range(self.centre - 1, -1, -1):
            out[i] = out[i + 1] + self.widths[i](s, der)
        return out


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _taper(w: np.ndarray, dist: np.ndarray, taper: float) -> np.ndarray:
    """Width target of a lane that opens at dist = 0: within `taper` the data, capped by a smoothstep from 0.

    Markings that taper by themselves (under half the lane's width over the first tenth of the taper,
    at 90 % of it only after half the taper) stay as measured, wherever they run below or above the
    smoothstep (highway_exit s2: a cap under a 50 m taper pulled its edge 0.5 m in). A lane whose
    markings start at full width, reach it within a few metres (a line cut where a lane leaves) or
    start wide and narrow again (a ramp's line seen across the lane) opens along the smoothstep to its
    median width beyond the taper.
    """
    far = dist >= taper
    full = float(np.median(w[far])) if far.any() else float(np.max(w))
    wide = (dist >= 0) & (w >= 0.9 * full)
    near = (dist >= 0) & (dist < 0.1 * taper)
    if wide.any() and float(np.min(dist[wide])) >= 0.5 * taper and near.any() \
            and float(np.median(w[near])) < 0.5 * full:
        return w
    cap = np.where(far, np.inf, full * _smoothstep(dist / taper))
    return np.minimum(w, cap)


def link_lanes(prev_iv: np.ndarray, next_iv: np.ndarray) -> dict[int, int]:
    """One-to-one links (next lane -> previous lane) by lateral overlap at a section change."""
    pairs = []
    for i, (r0, l0) in enumerate(prev_iv):
        for j, (r1, l1) in enumerate(next_iv):
            ov = min(l0, l1) - max(r0, r1)
            if ov > max(_LINK_MIN_OVERLAP_M, 0.5 * min(l0 - r0, l1 - r1)):
                pairs.append((-ov, i, j))
    links: dict[int, int] = {}
    used: set[int] = set()
    for _, i, j in sorted(pairs):
        if j not in links and i not in used:
            links[j] = i
            used.add(i)
    return links


@dataclass
class _LaneEnd:
    """Lane constraints at a road end that lies in a junction (lane indices of the end section).

    `zero`: lanes linked to nothing there; they start (end) at width 0 and open along the taper.
    `widths`: lanes that must have this width and width slope there. `border`: (boundary position,
    t, dt/ds) the laneOffset must produce there, given the widths.
    """

    zero: set[int]
    widths: dict[int, tuple[float, float]] = field(default_factory=dict)
    border: tuple[int, float, float] | None = None


def _lane_fit(grid_s: np.ndarray, t_data: dict[int, np.ndarray],
              sections: list[tuple[float, float, list[int], int]],
              cfg: ExportConfig, start: _LaneEnd | None = None, end: _LaneEnd | None = None,
              where: str = _WHERE, lane_types: list[list[str] | None] | None = None,
              ) -> tuple[_Records, list[_SectionFit]]:
    """laneOffset and per-section widths from the boundaries' t on the common station grid.

    Each section names the position of its centre boundary (lane 0) in its boundary list. Lanes are
    linked only to lanes on the same side of lane 0 (the two directions never continue each other).
    `start` / `end` constrain the road's first / last cross-section where it meets a junction.
    `lane_types` (per section, per lane; None: driving): an entry or exit lane (a taper) starts or ends
    at zero width only at its narrow end (measured under half its widest); at its wide end, where its
    outer line was first or last seen, it keeps the measured width (the lane goes on unobserved: a
    ramp's lane), rather than opening along the taper like a lane that appears.
    """
    masks = [(grid_s >= s0 - 1e-9) & (grid_s <= s1 + 1e-9) for s0, s1, _, _ in sections]
    targets: list[np.ndarray] = []  # per section: (n_boundaries, n_samples)
    for j, ((s0, s1, ids, _), m) in enumerate(zip(sections, masks, strict=True)):
        rows = []
        for bid in ids:
            t = t_data[bid][m]
            ok = np.isfinite(t)
            if ok.sum() < 2:
                raise InputError(where, f"boundary {bid} has no offsets in lane section {j} "
                                         f"(s {s0:.1f}-{s1:.1f} m of the written road)")
            rows.append(np.interp(grid_s[m], grid_s[m][ok], t[ok]))
        arr = np.array(rows)
        if np.any(np.median(-np.diff(arr, axis=0), axis=1) <= 0):
            raise InputError(where, f"lane section {j}: boundaries {ids} are not ordered left to right")
        targets.append(arr)

    def edges(j: int, at_end: bool) -> np.ndarray:
        s = grid_s[masks[j]]
        near = s >= s[-1] - 5.0 if at_end else s <= s[0] + 5.0
        t = targets[j][:, near].mean(axis=1)
        return np.stack([t[1:], t[:-1]], axis=1)  # (lanes, [right, left])

    preds = [{} for _ in sections]
    succs = [{} for _ in sections]
    for j in range(1, len(sections)):
        c0, c1 = sections[j - 1][3], sections[j][3]
        links = link_lanes(edges(j - 1, True), edges(j, False))
        preds[j] = {jj: i for jj, i in links.items() if (jj >= c1) == (i >= c0)}
        succs[j - 1] = {i: jj for jj, i in preds[j].items()}

    offset_s: list[np.ndarray] = []
    offset_t: list[np.ndarray] = []
    fits: list[_SectionFit] = []
    last = len(sections) - 1
    for j, ((s0, s1, ids, c), m) in enumerate(zip(sections, masks, strict=True)):
        s = grid_s[m]
        arr = targets[j]
        taper = min(cfg.taper_length_m, 0.5 * (s1 - s0))
        lead = arr[c].copy()
        breaks = _uniform_breaks(s0, s1, cfg.lane_record_m)
        widths = []
        types = lane_types[j] if lane_types is not None else None
        for i in range(len(ids) - 1):
            w = arr[i] - arr[i + 1]
            cons: list[tuple[float, ...]] = []
            opens = j > 0 and i not in preds[j] or j == 0 and start is not None and i in start.zero
            ends = j < last and i not in succs[j] or j == last and end is not None and i in end.zero
            if types is not None and types[i] in TAPER_LANE_TYPES:
                wide = 0.5 * float(np.max(w))
                opens = opens and float(np.mean(w[s <= s0 + 5.0])) < wide
                ends = ends and float(np.mean(w[s >= s1 - 5.0])) < wide
            if opens:
                w = _taper(w, s - s0, taper)
                cons.append((s0, 0.0))
            elif j > 0 and i in preds[j]:
                cons.append((s0, float(fits[j - 1].widths[preds[j][i]](np.array([s0]))[0])))
            elif start is not None and i in start.widths:
                cons += [(s0, start.widths[i][0]), (s0, start.widths[i][1], 1)]
            if ends:
                w = _taper(w, s1 - s, taper)
                cons.append((s1, 0.0))
            elif j == last and end is not None and i in end.widths:
                cons += [(s1, end.widths[i][0]), (s1, end.widths[i][1], 1)]
            tapered = opens or ends
            if tapered and i == c:
                lead = arr[c + 1] + w
            elif tapered and i == c - 1:
                lead = arr[c - 1] - w
            widths.append(_non_negative(_spline_records(s, w, breaks, constraints=tuple(cons), c1=True), s1))
        fits.append(_SectionFit(s0, s1, ids, widths, preds[j], succs[j], c, types))
        offset_s.append(s)
        offset_t.append(lead)
    all_breaks = np.unique(np.concatenate([_uniform_breaks(a, b, cfg.lane_record_m) for a, b, _, _ in sections]))
    ocons: list[tuple[float, ...]] = []
    for spec, fit, at in ((start, fits[0], sections[0][0]), (end, fits[-1], sections[-1][1])):
        if spec is not None and spec.border is not None:
            pos, t, slope = spec.border
            rel = [float(fit.borders(np.zeros(1), np.array([at]), der)[pos][0]) for der in (0, 1)]
            ocons += [(at, t - rel[0]), (at, slope - rel[1], 1)]
    offset = _spline_records(np.concatenate(offset_s), np.concatenate(offset_t), all_breaks,
                             constraints=tuple(ocons), c1=True)
    return offset, fits


# --------------------------------------------------------------------------------------------
# input checks and resampling


def _check_model(model: LaneModel, cfg: ExportConfig, where: str = _WHERE) -> None:
    if cfg.piece_length_m <= 1.0 or not 0.0 <= cfg.look_fraction < 1.0 or cfg.lane_record_m <= 0.5 \
            or cfg.junction_blend_m <= 0.0:
        raise InputError("configuration export", "piece_length_m > 1, 0 <= look_fraction < 1, "
                                                 "lane_record_m > 0.5 and junction_blend_m > 0 are required")
    s = np.asarray(model.s, dtype=np.float64)
    ref = np.asarray(model.reference, dtype=np.float64)
    if s.ndim != 1 or ref.shape != (len(s), 3):
        raise InputError(where, f"reference has shape {ref.shape} for {len(s)} stations (expected (M, 3))")
    if len(s) < 4 or not np.all(np.isfinite(s)) or not np.all(np.isfinite(ref[:, :2])):
        raise InputError(where, "the reference line needs at least 4 finite stations and x, y")
    if np.any(np.diff(s) <= 0):
        raise InputError(where, "reference stations s are not strictly increasing")
    if s[-1] - s[0] < 5.0:
        raise InputError(where, f"the road is {s[-1] - s[0]:.2f} m long; at least 5 m are needed")
    known = {b.id for b in model.boundaries}
    for b in model.boundaries:
        if np.shape(b.t) != s.shape:
            raise InputError(where, f"boundary {b.id}: {np.size(b.t)} offsets for {len(s)} stations")
        if b.mark_type not in MARK_TYPES:
            raise InputError(where, f"boundary {b.id}: mark type {b.mark_type!r} (solid, broken or none)")
    for j, sec in enumerate(model.sections):
        for bid, kind in (sec.marks or {}).items():
            if bid not in sec.boundary_ids or kind not in MARK_TYPES:
                raise InputError(where, f"lane section {j}: mark {kind!r} of boundary {bid} (a boundary of the "
                                         "section; solid, broken or none)")
    if not model.sections:
        raise InputError(where, "no lane sections")
    for j, sec in enumerate(model.sections):
        if len(sec.boundary_ids) < 2:
            raise InputError(where, f"lane section {j} has {len(sec.boundary_ids)} boundaries (at least 2)")
        missing = [i for i in sec.boundary_ids if i not in known]
        if missing:
            raise InputError(where, f"lane section {j} names unknown boundaries {missing}")
        if sec.divider_id is not None and sec.divider_id not in sec.boundary_ids[1:-1]:
            raise InputError(where, f"lane section {j}: divider {sec.divider_id} is not one of its inner "
                                     f"boundaries {sec.boundary_ids}")
        if sec.s_end <= sec.s_start:
            raise InputError(where, f"lane section {j} is empty (s {sec.s_start} to {sec.s_end})")
        types = sec.lane_types
        if types is not None and (len(types) != len(sec.boundary_ids) - 1
                                  or not all(v in xodr.LaneType.__members__ for v in types)):
            raise InputError(where, f"lane section {j}: lane_types {types!r} are not one OpenDRIVE lane type "
                                     f"per lane ({len(sec.boundary_ids) - 1} lanes)")
        if j and abs(sec.s_start - model.sections[j - 1].s_end) > 0.5:
            raise InputError(where, f"lane section {j} starts at {sec.s_start:.2f} m but section {j - 1} "
                                     f"ends at {model.sections[j - 1].s_end:.2f} m")


def _resample(model: LaneModel) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """Uniform station grid (at most 1 m) with the reference and every boundary's t on it."""
    s = np.asarray(model.s, dtype=np.float64)
    step = min(1.0, float(np.median(np.diff(s))))
    grid = np.linspace(s[0], s[-1], math.ceil((s[-1] - s[0]) / step - 1e-9) + 1)
    ref = np.asarray(model.reference, dtype=np.float64)
    z = ref[:, 2]
    ok = np.isfinite(z)
    z = np.interp(s, s[ok], z[ok]) if ok.any() else np.zeros_like(s)
    out = np.stack([np.interp(grid, s, ref[:, 0]), np.interp(grid, s, ref[:, 1]), np.interp(grid, s, z)], axis=1)
    t = {b.id: np.interp(grid, s, np.asarray(b.t, dtype=np.float64)) for b in model.boundaries}
    return grid, out, t


# --------------------------------------------------------------------------------------------
# superelevation


def _superelevation(planes: GroundPlanes | None, grid_xy: np.ndarray, grid_odr: np.ndarray, left: np.ndarray,
                    breaks: np.ndarray, cfg: ExportConfig,
                    constraints: tuple[tuple[float, float], ...] = ()) -> _Records:
    """Roll of the ground planes about the road, left side up positive; 0 without planes.

    `constraints` (station, roll) pin the roll where the road meets another at a junction; without
    planes near the road the roll then fades from there to 0.
    """
    flat = np.zeros(len(grid_odr))
    zero = _Records(np.array([0.0]), np.zeros((1, 4)))
    if constraints:
        zero = _spline_records(grid_odr, flat, breaks, smooth=cfg.superelevation_smoothing,
                               constraints=constraints, c1=True)
    if planes is None or len(planes.normals_world) == 0:
        return zero
    normals = np.asarray(planes.normals_world, dtype=np.float64)
    points = np.asarray(planes.points_world, dtype=np.float64)
    ok = np.all(np.isfinite(normals), axis=1) & np.all(np.isfinite(points), axis=1) & (normals[:, 2] > 0.5)
    dist, idx = cKDTree(grid_xy).query(points[ok, :2])
    near = dist <= cfg.plane_max_offset_m
    if near.sum() < 2:
        return zero
    n, i = normals[ok][near], idx[near]
    roll = np.arctan2(-np.sum(n[:, :2] * left[i], axis=1), n[:, 2])
    order = np.argsort(grid_odr[i], kind="stable")
    s_pl = grid_odr[i][order]
    roll = median_filter(roll[order], size=max(1, cfg.superelevation_median_scans), mode="nearest")
    target = np.interp(grid_odr, s_pl, roll)
    return _spline_records(grid_odr, target, breaks, smooth=cfg.superelevation_smoothing,
                           constraints=constraints, c1=True)


# --------------------------------------------------------------------------------------------
# writing


class _ParamPoly3(xodr.ParamPoly3):
    """paramPoly3 that keeps our Gauss-Legendre length (scenariogeneration would re-integrate it)."""

    def get_end_data(self, x: float, y: float, h: float) -> tuple[float, float, float, float]:
        eu = self.au + self.bu + self.cu + self.du
        ev = self.av + self.bv + self.cv + self.dv
        hdg = h + math.atan2(self.bv + 2 * self.cv + 3 * self.dv, self.bu + 2 * self.cu + 3 * self.du)
        return x + eu * math.cos(h) - ev * math.sin(h), y + eu * math.sin(h) + ev * math.cos(h), hdg, self.length


def _mark(b: Boundary) -> xodr.RoadMark:
    if b.mark_type == "broken":
        pattern = b.dash_length is not None and b.gap_length is not None
        return xodr.RoadMark(xodr.RoadMarkType.broken, float(b.mark_width),
                             length=float(b.dash_length) if pattern else None,
                             space=float(b.gap_length) if pattern else None,
                             laneChange=xodr.LaneChange.both)
    if b.mark_type == "none":
        return xodr.RoadMark(xodr.RoadMarkType.none, laneChange=xodr.LaneChange.none)
    return xodr.RoadMark(xodr.RoadMarkType.solid, float(b.mark_width), laneChange=xodr.LaneChange.none)


def _lane(lane_type: xodr.LaneType, records: _Records, s0: float) -> xodr.Lane:
    a, b, c, d = (float(v) for v in records.coeffs[0])
    lane = xodr.Lane(lane_type, a, b, c, d, soffset=float(records.starts[0] - s0))
    for start, (a, b, c, d) in zip(records.starts[1:], records.coeffs[1:], strict=True):
        lane.add_lane_width(float(a), float(b), float(c), float(d), soffset=float(start - s0))
    return lane


def _constant(width: float, s0: float) -> _Records:
    return _Records(np.array([s0]), np.array([[width, 0.0, 0.0, 0.0]]))


def _build_lanes(offset: _Records, fits: list[_SectionFit], bounds: list[dict[int, Boundary]],
                 cfg: ExportConfig) -> xodr.Lanes:
    """The lanes of every section; `bounds[j]`: the boundaries by id with their mark in section j."""
    lanes = xodr.Lanes()
    for start, (a, b, c, d) in zip(offset.starts, offset.coeffs, strict=True):
        lanes.add_laneoffset(xodr.LaneOffset(float(start), float(a), float(b), float(c), float(d)))
    built: list[xodr.LaneSection] = []
    for j, fit in enumerate(fits):
        centre = xodr.Lane()
        centre.add_roadmark(_mark(bounds[j][fit.ids[fit.centre]]))
        sec = xodr.LaneSection(float(fit.s0), centre)
        order = list(range(fit.centre - 1, -1, -1)) + list(range(fit.centre, len(fit.widths)))
        for i in order:
            kind = xodr.LaneType.driving if fit.types is None else getattr(xodr.LaneType, fit.types[i])
            lane = _lane(kind, fit.widths[i], fit.s0)
            if i in fit.pred:
                lane.add_link("predecessor", fits[j - 1].lane_id(fit.pred[i]))
            if i in fit.succ:
                lane.add_link("successor", fits[j + 1].lane_id(fit.succ[i]))
            if i < fit.centre:
                lane.add_roadmark(_mark(bounds[j][fit.ids[i]]))
                sec.add_left_lane(lane)
            else:
                lane.add_roadmark(_mark(bounds[j][fit.ids[i + 1]]))
                sec.add_right_lane(lane)
        if cfg.left_border_m > 0:
            border = _lane(xodr.LaneType.border, _constant(cfg.left_border_m, fit.s0), fit.s0)
            if j > 0:
                border.add_link("predecessor", fits[j - 1].centre + 1)
            if j < len(fits) - 1:
                border.add_link("successor", fits[j + 1].centre + 1)
            sec.add_left_lane(border)
        if cfg.right_shoulder_m > 0:
            shoulder = _lane(xodr.LaneType.shoulder, _constant(cfg.right_shoulder_m, fit.s0), fit.s0)
            if j > 0:
                shoulder.add_link("predecessor", -(len(fits[j - 1].widths) - fits[j - 1].centre) - 1)
            if j < len(fits) - 1:
                shoulder.add_link("successor", -(len(fits[j + 1].widths) - fits[j + 1].centre) - 1)
            sec.add_right_lane(shoulder)
        built.append(sec)
    for sec in built:
        lanes.add_lanesection(sec)
    return lanes


def _geo_reference(model: LaneModel) -> tuple[str, bool]:
    """PROJ string of the local frame and whether it is a true geodetic placement."""
    proj = origin_proj(model.origin)
    return (proj, True) if proj else (LOCAL_PLACEHOLDER, False)


def _date(planes: GroundPlanes | None) -> str | None:
    if planes is None or len(planes.times) == 0:
        return None
    t0 = float(np.min(planes.times))
    if not 946684800.0 <= t0 <= 4102444800.0:  # 2000..2100 as UNIX time
        return None
    return datetime.fromtimestamp(t0, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")


def _serialise(odr: xodr.OpenDrive, geo: str, geodetic: bool, date: str | None, bbox: np.ndarray) -> bytes:
    root = etree.fromstring(ET.tostring(odr.get_element()))
    header = root.find("header")
    if date is None:
        header.attrib.pop("date", None)
    else:
        header.set("date", date)
    for key, val in zip(("north", "south", "east", "west"), (bbox[3], bbox[1], bbox[2], bbox[0]), strict=True):
        header.set(key, repr(float(val)))
    header.set("vendor", "lidar2xodr")
    ref = header.find("geoReference")
    ref.text = etree.CDATA(geo)
    if not geodetic:
        ref.addprevious(etree.Comment(" no GNSS: the frame is local; the geoReference is a placeholder at 0, 0 "))
    return etree.tostring(root, pretty_print=True, xml_declaration=True, encoding="UTF-8")


# --------------------------------------------------------------------------------------------
# measuring what was written


def _measure(data: bytes, joins: list[tuple[str, str]]) -> tuple[float, float, float]:
    """Largest leap, kink and |declared - integrated length| between the written geometries.

    Within every road, and across every join whose reference lines must meet (`joins`: the id of the
    road whose last geometry ends where the other road's first begins): continuations, and the cuts
    of classic junctions.
    """
    root = etree.fromstring(data)
    leap = kink = lerr = 0.0
    xs, ws = np.polynomial.legendre.leggauss(64)
    pgl = 0.5 * (xs + 1)
    first: dict[str, tuple[float, float, float]] = {}
    last: dict[str, tuple[float, float, float]] = {}
    for road in root.findall("road"):
        prev_end: tuple[float, float, float] | None = None
        for g in road.findall("planView/geometry"):
            pp = g.find("paramPoly3")
            u = np.array([float(pp.get(k)) for k in ("aU", "bU", "cU", "dU")])
            v = np.array([float(pp.get(k)) for k in ("aV", "bV", "cV", "dV")])
            x, y, h, length = (float(g.get(k)) for k in ("x", "y", "hdg", "length"))
            start = (x + u[0] * math.cos(h) - v[0] * math.sin(h), y + u[0] * math.sin(h) + v[0] * math.cos(h),
                     h + math.atan2(v[1], u[1]))
            if prev_end is None:
                first[road.get("id")] = start
            else:
                leap = max(leap, math.hypot(start[0] - prev_end[0], start[1] - prev_end[1]))
                kink = max(kink, abs(float(wrap_angle(start[2] - prev_end[2]))))
            prev_end = _local_end(u, v, x, y, h)
            speed = np.hypot(u[1] + 2 * u[2] * pgl + 3 * u[3] * pgl**2, v[1] + 2 * v[2] * pgl + 3 * v[3] * pgl**2)
            lerr = max(lerr, abs(0.5 * float(speed @ ws) - length))
        if prev_end is not None:
            last[road.get("id")] = prev_end
    for a, b in joins:
        end, start = last[a], first[b]
        leap = max(leap, math.hypot(start[0] - end[0], start[1] - end[1]))
        kink = max(kink, abs(float(wrap_angle(start[2] - end[2]))))
    return leap, kink, lerr


def _junction_gap(data: bytes) -> float:
    """Largest distance between linked lane borders across the junctions, as the project's reader sees them."""
    from lidar2xodr.check import junction_gaps
    from lidar2xodr.opendrive import OpenDriveMap

    with tempfile.TemporaryDirectory(prefix="lidar2xodr-") as tmp:
        written = Path(tmp) / "map.xodr"
        written.write_bytes(data)
        return float(junction_gaps(OpenDriveMap.load(written))["max_junction_gap_m"])


# --------------------------------------------------------------------------------------------
# roads joined by direct junctions


@dataclass
class _End:
    """A written road end as readers evaluate it: reference pose, profiles and the lanes of its end section."""

    x: float
    y: float
    hdg: float
    z: float
    dz: float
    roll: float
    borders: list[float]  # t of every boundary of the end section, left to right
    border_slopes: list[float]  # their dt/ds
    widths: list[float]  # width of every lane of the end section
    width_slopes: list[float]


@dataclass
class _Join:
    """One end of a road is anchored to an end of road `other` (`other_end`: its end, else its start).

    `pairs`: (lane of this road, lane of the other road) in the two end sections, left to right.
    """

    other: int
    other_end: bool
    pairs: list[tuple[int, int]]
    continuation: bool


@dataclass
class _Anchor:
    """What an anchored road end must meet, taken from the written cross-section of the road it joins."""

    pose: Pose  # the reference point and heading the road has there
    z: float
    dz: float
    roll: float
    lanes: _LaneEnd
    blend: tuple[int, int] | None  # a branch: its first and last linked lane (the model is bent onto the anchor)


@dataclass
class _Built:
    """One written road and what the network needs from it."""

    road: xodr.Road
    fits: list[_SectionFit]
    length: float
    pieces: int
    start: _End
    end: _End
    outline: np.ndarray  # world xy of the reference line and every lane border
    reference_dev: float
    border_dev: float


def _anchor(other: _End, join: _Join, zero: set[int]) -> _Anchor:
    """Continuation: the reference goes on exactly. Branch: it starts (ends) on the other road's
    cross-section at the middle of the linked lanes, with its heading. Either way the linked lanes
    take the other road's widths and width slopes there, and the left border of the first one its t
    and dt/ds, so linked borders meet with the same direction (to the small curvature term)."""
    own, oth = [p[0] for p in join.pairs], [p[1] for p in join.pairs]
    t_ref = 0.0 if join.continuation else 0.5 * (other.borders[oth[0]] + other.borders[oth[-1] + 1])
    lateral = t_ref * math.cos(other.roll)
    pose = (other.x - math.sin(other.hdg) * lateral, other.y + math.cos(other.hdg) * lateral, other.hdg)
    widths = {o: (other.widths[t], other.width_slopes[t]) for o, t in join.pairs}
    lanes = _LaneEnd(zero, widths, (own[0], other.borders[oth[0]] - t_ref, other.border_slopes[oth[0]]))
    return _Anchor(pose, other.z + t_ref * math.sin(other.roll), other.dz, other.roll, lanes,
                   None if join.continuation else (own[0], own[-1]))


_END_HEADING_M = 10.0


def _end_heading(grid: np.ndarray, xy: np.ndarray, at_end: bool) -> float:
    """Heading of a line at one end: tangent of a line fit over its last `_END_HEADING_M`.

    Short, because a branch starts to curve within metres of its junction (highway_split: a quadratic
    over 20 m of the reference tilted the start 0.06 rad the wrong way, and the blend bent the branch
    0.6 m off its markings).
    """
    s_end = grid[-1] if at_end else grid[0]
    near = np.abs(grid - s_end) <= min(_END_HEADING_M, 0.5 * (grid[-1] - grid[0])) + 1e-9
    d = grid[near] - s_end
    return math.atan2(np.polyfit(d, xy[near, 1], 1)[0], np.polyfit(d, xy[near, 0], 1)[0])


def _blend(grid: np.ndarray, ref: np.ndarray, left: np.ndarray, t_grid: dict[int, np.ndarray], ids: list[int],
           anchor: _Anchor, at_end: bool, cfg: ExportConfig) -> tuple[np.ndarray, np.ndarray]:
    """Bend a branch's model onto its anchor near the junction end; the rest stays where the markings are.

    The middle of its linked lanes at that end moves onto the anchor point (a shift, and a height shift,
    that fade with a smoothstep over `junction_blend_m`, or the road's length if shorter) and its heading
    turns onto the anchor's by the least sideways bend: a cubic offset theta * d * (1 - d / L)^2 at
    distance d from the end, which turns the end by theta and vanishes with its slope at L. Rotating
    the branch about its end instead swung it 0.26 * theta * L off its markings, the bend moves it
    0.15 * theta * L at most. Boundaries move with the reference: their normals turn with its heading.
    """
    e = len(grid) - 1 if at_end else 0
    first, last = anchor.blend
    t_mid = 0.0
    for bid in (ids[first], ids[last + 1]):
        ok = np.flatnonzero(np.isfinite(t_grid[bid]))
        t_mid += 0.5 * float(t_grid[bid][ok[np.argmin(np.abs(ok - e))]]) if len(ok) else 0.0
    pivot = ref[e, :2] + t_mid * left[e]
    dist = grid[-1] - grid if at_end else grid - grid[0]
    length = min(cfg.junction_blend_m, grid[-1] - grid[0])
    u = np.clip(dist / length, 0.0, 1.0)
    fade = 1.0 - _smoothstep(u)
    both = np.isfinite(t_grid[ids[first]]) & np.isfinite(t_grid[ids[last + 1]])
    if both.sum() >= 2:  # the heading of the linked lanes' middle, which the reference may not follow
        middle = ref[both, :2] + 0.5 * (t_grid[ids[first]][both] + t_grid[ids[last + 1]][both])[:, None] * left[both]
        end_heading = _end_heading(grid[both], middle, at_end)
    else:
        end_heading = _end_heading(grid, ref[:, :2], at_end)
    theta0 = float(wrap_angle(anchor.pose[2] - end_heading))
    sideways = theta0 * length * u * (1.0 - u) ** 2 * (-1.0 if at_end else 1.0)
    theta = theta0 * (1.0 - u) * (1.0 - 3.0 * u)
    c, s = np.cos(theta), np.sin(theta)
    turned = np.stack([c * left[:, 0] - s * left[:, 1], s * left[:, 0] + c * left[:, 1]], axis=1)
    out = ref.copy()
    out[:, :2] = ref[:, :2] + sideways[:, None] * left + fade[:, None] * (np.array(anchor.pose[:2]) - pivot)
    out[:, 2] = ref[:, 2] + fade * (anchor.z - ref[e, 2])
    return out, turned


def _project_boundaries(plan: _Plan, xy: np.ndarray, left: np.ndarray, t_grid: dict[int, np.ndarray],
                        grid_odr: np.ndarray, k: np.ndarray, p: np.ndarray) -> dict[int, np.ndarray]:
    """Every boundary's world points projected onto the written reference line, as t on `grid_odr`."""
    out: dict[int, np.ndarray] = {}
    for bid, t in t_grid.items():
        ok = np.isfinite(t)
        out[bid] = np.full(len(grid_odr), np.nan)
        if ok.sum() >= 2:
            s_b, t_b = plan.project(xy[ok] + t[ok, None] * left[ok], k[ok], p[ok])
            order = np.argsort(s_b)
            out[bid][ok] = np.interp(grid_odr[ok], s_b[order], t_b[order])
    return out


def _road_end(plan: _Plan, offset: _Records, fits: list[_SectionFit], elevation: _Records,
              superelevation: _Records, total: float, at_end: bool) -> _End:
    if at_end:
        x, y, hdg = _local_end(plan.u[-1], plan.v[-1], float(plan.x[-1]), float(plan.y[-1]), float(plan.hdg[-1]))
        s, fit = np.array([total]), fits[-1]
    else:
        x, y, hdg = float(plan.x[0]), float(plan.y[0]), float(plan.hdg[0])
        s, fit = np.array([0.0]), fits[0]
    return _End(x, y, hdg, float(elevation(s)[0]), float(elevation(s, der=1)[0]), float(superelevation(s)[0]),
                [float(b[0]) for b in fit.borders(offset(s), s)],
                [float(b[0]) for b in fit.borders(offset(s, der=1), s, der=1)],
                [float(w(s)[0]) for w in fit.widths], [float(w(s, der=1)[0]) for w in fit.widths])


def _build_road(model: LaneModel, planes: GroundPlanes | None, cfg: ExportConfig, road_id: int, name: str,
                start: _Anchor | _LaneEnd | None, end: _Anchor | _LaneEnd | None, where: str) -> _Built:
    """Fit and build one road; an _Anchor end meets the road it joins exactly, a _LaneEnd only ends its lanes."""
    anchors = {False: start if isinstance(start, _Anchor) else None, True: end if isinstance(end, _Anchor) else None}
    lane_ends = [a.lanes if isinstance(a, _Anchor) else a for a in (start, end)]
    grid, ref, t_grid = _resample(model)
    tangent = np.gradient(ref[:, :2], grid, axis=0)
    left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1) / np.linalg.norm(tangent, axis=1)[:, None]
    given_ref, given_left = ref, left
    for at_end, anchor in anchors.items():
        if anchor is not None and anchor.blend is not None:
            ids = model.sections[-1 if at_end else 0].boundary_ids
            ref, left = _blend(grid, ref, left, t_grid, ids, anchor, at_end, cfg)
    length_m = grid[-1] - grid[0]
    n_pieces = max(1, math.ceil(length_m / cfg.piece_length_m - 1e-9))
    breaks = np.linspace(grid[0], grid[-1], n_pieces + 1)
    poses = [None if a is None else a.pose for a in anchors.values()]
    plan = _fit_plan(grid, ref[:, :2], breaks, cfg, poses[0], poses[1], where)

    k = np.clip(np.searchsorted(breaks, grid, side="right") - 1, 0, n_pieces - 1)
    p = (grid - breaks[k]) / (breaks[k + 1] - breaks[k])
    grid_odr, ref_t = plan.project(ref[:, :2], k, p)
    t_odr = _project_boundaries(plan, ref[:, :2], left, t_grid, grid_odr, k, p)

    total = float(plan.s[-1] + plan.length[-1])
    geo_breaks = np.r_[plan.s, total]
    z_cons: list[tuple[float, ...]] = []
    roll_cons: list[tuple[float, float]] = []
    for at, anchor in zip((0.0, total), anchors.values(), strict=True):
        if anchor is not None:
            z_cons += [(at, anchor.z), (at, anchor.dz, 1)]
            roll_cons.append((at, anchor.roll))
    z_breaks = _uniform_breaks(0.0, total, cfg.elevation_record_m) if cfg.elevation_record_m else geo_breaks
    elevation = _spline_records(grid_odr, ref[:, 2], z_breaks, constraints=tuple(z_cons))
    superelevation = _superelevation(planes, ref[:, :2], grid_odr, left, geo_breaks, cfg, tuple(roll_cons))
    slant = 1.0 / np.cos(superelevation(grid_odr))  # t runs along the banked surface
    t_odr = {bid: t * slant for bid, t in t_odr.items()}
    sec_s = np.interp([sec.s_start for sec in model.sections], grid, grid_odr)
    sec_s[0] = 0.0
    sec_e = np.r_[sec_s[1:], total]
    sections = [(float(a), float(b), list(sec.boundary_ids),
                 0 if sec.divider_id is None else list(sec.boundary_ids).index(sec.divider_id))
                for a, b, sec in zip(sec_s, sec_e, model.sections, strict=True)]
    offset, fits = _lane_fit(grid_odr, t_odr, sections, cfg, lane_ends[0], lane_ends[1], where,
                             [sec.lane_types for sec in model.sections])

    planview = xodr.PlanView()
    for i in range(len(plan.s)):
        geom = _ParamPoly3(*(float(c) for c in plan.u[i]), *(float(c) for c in plan.v[i]),
                           prange="normalized", length=float(plan.length[i]))
        planview.add_fixed_geometry(geom, float(plan.x[i]), float(plan.y[i]), float(plan.hdg[i]), s=float(plan.s[i]))
    bounds = [{b.id: b if sec.mark_of(b) == b.mark_type else replace(b, mark_type=sec.mark_of(b))
               for b in model.boundaries} for sec in model.sections]
    road = xodr.Road(road_id, planview, _build_lanes(offset, fits, bounds, cfg), name=name, rule=xodr.TrafficRule.RHT)
    road.add_type(getattr(xodr.RoadType, cfg.road_type), 0.0)
    for rec_start, (a, b, c, d) in zip(elevation.starts, elevation.coeffs, strict=True):
        road.add_elevation(float(rec_start), float(a), float(b), float(c), float(d))
    for rec_start, (a, b, c, d) in zip(superelevation.starts, superelevation.coeffs, strict=True):
        road.add_superelevation(float(rec_start), float(a), float(b), float(c), float(d))

    t_dev = t_odr
    if ref is not given_ref:  # deviations from the model as given, so a branch's junction snap shows
        _, ref_t = plan.project(given_ref[:, :2], k, p)
        t_dev = {bid: t * slant for bid, t in _project_boundaries(plan, given_ref[:, :2], given_left, t_grid,
                                                                    grid_odr, k, p).items()}
    border_dev = 0.0
    outline: list[np.ndarray] = [ref[:, :2]]
    for fit in fits:
        m = (grid_odr >= fit.s0) & (grid_odr <= fit.s1)
        for bid, border in zip(fit.ids, fit.borders(offset(grid_odr[m]), grid_odr[m]), strict=True):
            ok = np.isfinite(t_dev[bid][m])
            if ok.any():
                border_dev = max(border_dev, float(np.max(np.abs(border[ok] - t_dev[bid][m][ok]))))
            outline.append(ref[m, :2] + border[:, None] * left[m])
    ends = [_road_end(plan, offset, fits, elevation, superelevation, total, at_end) for at_end in (False, True)]
    return _Built(road, fits, total, len(plan.s), ends[0], ends[1], np.vstack(outline),
                  float(np.max(np.abs(ref_t))), border_dev)


_NET = "road network"


def _check_network(network: RoadNetwork, cfg: ExportConfig) -> list[str]:
    """Validate every road and link; returns the name each road's errors carry."""
    n = len(network.roads)
    if n == 0:
        raise InputError(_NET, "no roads")
    wheres = [_WHERE] if n == 1 else [f"{_WHERE} of road {k + 1}" for k in range(n)]
    for model, where in zip(network.roads, wheres, strict=True):
        _check_model(model, cfg, where)
    if any(model.origin != network.roads[0].origin for model in network.roads):
        raise InputError(_NET, "the roads have different origins (one local frame is needed)")
    seen: set[tuple[int, int]] = set()
    continued: set[tuple[int, bool]] = set()
    for q, link in enumerate(network.links):
        a, b = link.incoming, link.outgoing
        if not (0 <= a < n and 0 <= b < n) or a == b:
            raise InputError(_NET, f"link {q} joins road indices {a} -> {b} (two different roads of 0..{n - 1})")
        name = f"link {q} (road {a + 1} -> road {b + 1})"
        if (a, b) in seen:
            raise InputError(_NET, f"{name}: the two roads are already linked")
        seen.add((a, b))
        n_in = len(network.roads[a].sections[-1].boundary_ids) - 1
        n_out = len(network.roads[b].sections[0].boundary_ids) - 1
        pairs = sorted((int(i), int(j)) for i, j in link.lanes)
        if not pairs:
            raise InputError(_NET, f"{name} links no lanes")
        if any(not (0 <= i < n_in and 0 <= j < n_out) for i, j in pairs):
            raise InputError(_NET, f"{name}: lane pairs {pairs} outside the {n_in} lanes of the incoming road's last "
                                   f"section or the {n_out} of the outgoing road's first")
        if np.any(np.diff([i for i, _ in pairs]) != 1) or np.any(np.diff([j for _, j in pairs]) != 1):
            raise InputError(_NET, f"{name}: lane pairs {pairs} must be neighbouring lanes in the same order "
                                   "on both roads")
        if link.continuation:
            for key in ((a, True), (b, False)):
                if key in continued:
                    raise InputError(_NET, f"{name}: road {key[0] + 1} already continues at its "
                                           f"{'end' if key[1] else 'start'} (one continuation per road end)")
                continued.add(key)
    return wheres


def _plan_joins(network: RoadNetwork) -> tuple[dict[tuple[int, bool], _Join], list[int]]:
    """Which road end is anchored to which (continuations first), and a build order that honours it.

    A continuation anchors the outgoing road's start. A branch link anchors the branch: the outgoing
    road at a diverge (its incoming road has several outgoing links, or the link is alone), the
    incoming road at a merge (its outgoing road has several incoming links). Where that end is
    already anchored the other end of the link is used.
    """
    links = network.links
    leaving = {a: sum(lk.incoming == a for lk in links) for a in range(len(network.roads))}
    joining = {b: sum(lk.outgoing == b for lk in links) for b in range(len(network.roads))}
    joins: dict[tuple[int, bool], _Join] = {}
    for link in sorted(links, key=lambda lk: not lk.continuation):
        pairs = sorted((int(i), int(j)) for i, j in link.lanes)
        forward = ((link.outgoing, False), _Join(link.incoming, True, [(j, i) for i, j in pairs], link.continuation))
        back = ((link.incoming, True), _Join(link.outgoing, False, pairs, False))
        options = [forward] if link.continuation else (
            [forward, back] if leaving[link.incoming] > 1 or joining[link.outgoing] < 2 else [back, forward])
        for key, join in options:
            if key not in joins:
                joins[key] = join
                break
        else:
            raise InputError(_NET, f"road {link.incoming + 1} -> road {link.outgoing + 1}: both ends are already "
                                   "joined exactly to other roads")
    needs = {r: {j.other for (road, _), j in joins.items() if road == r} for r in range(len(network.roads))}
    order: list[int] = []
    while len(order) < len(network.roads):
        ready = [r for r in range(len(network.roads)) if r not in order and needs[r] <= set(order)]
        if not ready:
            raise InputError(_NET, "the links form a cycle of roads whose ends depend on each other")
        order.append(ready[0])
    return joins, order


def _junction_groups(links: list[RoadLink]) -> list[list[int]]:
    """Links sharing an incoming road (a diverge) or an outgoing road (a merge) form one junction."""
    root = list(range(len(links)))

    def find(i: int) -> int:
        while root[i] != i:
            i = root[i]
        return i

    for i, a in enumerate(links):
        for j in range(i):
            if a.incoming == links[j].incoming or a.outgoing == links[j].outgoing:
                root[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(links)):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values())


def _junction_name(links: list[RoadLink]) -> str:
    if len(links) > 1 and len({lk.incoming for lk in links}) == 1:
        return "diverge"
    if len(links) > 1 and len({lk.outgoing for lk in links}) == 1:
        return "merge"
    return "junction"


# --------------------------------------------------------------------------------------------
# classic junctions: the written direct junctions rewritten with connecting roads


def _fmt(v: float) -> str:
    return repr(float(v))


def _cubic_at(coeffs: list[float], ds: float) -> list[float]:
    """A cubic record re-expanded at ds: value, slope, curvature/2 and d (same polynomial)."""
    a, b, c, d = coeffs
    return [a + ds * (b + ds * (c + ds * d)), b + ds * (2 * c + 3 * ds * d), c + 3 * d * ds, d]


def _cut_records(parent: etree._Element, tag: str, key: str, cut: float, head: bool, cubic: bool) -> None:
    """Keep the records of `parent` (children `tag`, position attribute `key`) before or after `cut`.

    Head: records starting before the cut stay (the first always). Tail: the record active at the cut
    starts the tail at 0 (a cubic re-expanded there, the same polynomial), later ones move by -cut.
    """
    recs = parent.findall(tag)
    if not recs:
        return
    pos = [float(r.get(key)) for r in recs]
    active = max([i for i, p in enumerate(pos) if p <= cut + _CUT_EPS] or [0])
    for i, (rec, p) in enumerate(zip(recs, pos, strict=True)):
        if head:
            if i > 0 and p >= cut - _CUT_EPS:
                parent.remove(rec)
        elif i < active:
            parent.remove(rec)
        elif i == active:
            if cubic and p < cut - _CUT_EPS:
                vals = _cubic_at([float(rec.get(k)) for k in "abcd"], cut - p)
                for k, val in zip("abcd", vals, strict=True):
                    rec.set(k, _fmt(val))
            rec.set(key, _fmt(0.0) if key == "s" else "0")
        else:
            rec.set(key, _fmt(p - cut))


def _split_piece(geom: etree._Element, ds: float) -> tuple[etree._Element, etree._Element]:
    """A paramPoly3 (pRange normalized) cut at arc length ds into two, each in the frame of its start tangent."""
    pp = geom.find("paramPoly3")
    u = np.array([float(pp.get(k)) for k in ("aU", "bU", "cU", "dU")])
    v = np.array([float(pp.get(k)) for k in ("aV", "bV", "cV", "dV")])
    x, y, h = (float(geom.get(k)) for k in ("x", "y", "hdg"))

    def speed(p: np.ndarray) -> np.ndarray:
        return np.hypot(u[1] + 2 * u[2] * p + 3 * u[3] * p**2, v[1] + 2 * v[2] * p + 3 * v[3] * p**2)

    def arc(p: float) -> float:
        return p * float(speed(p * _GL_X) @ _GL_W)

    p = ds / float(geom.get("length"))
    for _ in range(50):
        step = (arc(p) - ds) / float(speed(np.array([p]))[0])
        p -= step
        if abs(step) < 1e-15:
            break
    scale = np.array([1.0, p, p * p, p**3])
    r = 1.0 - p
    taylor = np.array([[1, p, p * p, p**3], [0, r, 2 * p * r, 3 * p * p * r],
                       [0, 0, r * r, 3 * p * r * r], [0, 0, 0, r**3]])
    tu, tv = taylor @ u, taylor @ v
    turn = math.atan2(tv[1], tu[1])
    ct, st = math.cos(turn), math.sin(turn)
    rows = [(u * scale, v * scale, x, y, h),
            (np.r_[0.0, ct * tu[1:] + st * tv[1:]], np.r_[0.0, 0.0, -st * tu[2:] + ct * tv[2:]],
             x + math.cos(h) * tu[0] - math.sin(h) * tv[0], y + math.sin(h) * tu[0] + math.cos(h) * tv[0],
             float(wrap_angle(h + turn)))]
    pieces = []
    for cu, cv, px, py, ph in rows:
        piece = copy.deepcopy(geom)
        sp = np.hypot(cu[1] + 2 * cu[2] * _GL_X + 3 * cu[3] * _GL_X**2,
                      cv[1] + 2 * cv[2] * _GL_X + 3 * cv[3] * _GL_X**2)
        piece.set("length", _fmt(sp @ _GL_W))
        for k, val in (("x", px), ("y", py), ("hdg", ph)):
            piece.set(k, _fmt(val))
        ppe = piece.find("paramPoly3")
        for names, coeffs in ((("aU", "bU", "cU", "dU"), cu), (("aV", "bV", "cV", "dV"), cv)):
            for k, val in zip(names, coeffs, strict=True):
                ppe.set(k, _fmt(val))
        pieces.append(piece)
    return pieces[0], pieces[1]


def _lanes_of(section: etree._Element) -> dict[int, etree._Element]:
    return {int(lane.get("id")): lane for side in ("left", "right") for lane in section.findall(f"{side}/lane")}


def _set_lane_link(lane: etree._Element, kind: str, target: int | None) -> None:
    """Set (or with None remove) a lane's predecessor/successor, keeping predecessor before successor."""
    link = lane.find("link")
    if link is None:
        link = etree.Element("link")
        lane.insert(0, link)
    old = link.find(kind)
    if old is not None:
        link.remove(old)
    if target is not None:
        el = etree.Element(kind, id=str(target))
        link.insert(0 if kind == "predecessor" else len(link), el)


def _lane_link(lane: etree._Element, kind: str) -> int | None:
    el = lane.find(f"link/{kind}")
    return None if el is None else int(el.get("id"))


def _split_road(road: etree._Element, cut: float) -> tuple[etree._Element, etree._Element]:
    """Cut a written road at station `cut` into two roads (deep copies) that continue each other exactly.

    Geometry, elevation, superelevation, laneOffset, road type, lane sections, widths and road marks
    are cut; a cubic active at the cut is re-expanded there (the same polynomial), a paramPoly3 is cut
    at that arc length. Lanes keep their links across the cut (a section cut in two: to their own id).
    """
    geoms = road.findall("planView/geometry")
    starts = [float(g.get("s")) for g in geoms]
    k = max(i for i, s in enumerate(starts) if s <= cut + _CUT_EPS)
    head, tail = copy.deepcopy(road), copy.deepcopy(road)
    head_pv, tail_pv = head.find("planView"), tail.find("planView")
    for g in list(head_pv):
        head_pv.remove(g)
    for g in list(tail_pv):
        tail_pv.remove(g)
    for g in geoms[:k]:
        head_pv.append(copy.deepcopy(g))
    if cut - starts[k] > _CUT_EPS:
        first, second = _split_piece(geoms[k], cut - starts[k])
        head_pv.append(first)
        rest = [second] + [copy.deepcopy(g) for g in geoms[k + 1:]]
        cut = starts[k] + float(first.get("length"))
    else:
        cut = starts[k]
        rest = [copy.deepcopy(g) for g in geoms[k:]]
    s = 0.0
    for g in rest:
        g.set("s", _fmt(s))
        s += float(g.get("length"))
        tail_pv.append(g)
    head.set("length", _fmt(cut))
    tail.set("length", _fmt(s))

    for path, tag in (("elevationProfile", "elevation"), ("lateralProfile", "superelevation"), ("lanes", "laneOffset")):
        for part, is_head in ((head, True), (tail, False)):
            parent = part.find(path)
            if parent is not None:
                _cut_records(parent, tag, "s", cut, is_head, cubic=True)
    for part, is_head in ((head, True), (tail, False)):
        _cut_records(part, "type", "s", cut, is_head, cubic=False)

    sec_s = [float(sec.get("s")) for sec in road.findall("lanes/laneSection")]
    j = max(i for i, s0 in enumerate(sec_s) if s0 <= cut + _CUT_EPS)
    straddles = cut - sec_s[j] > _CUT_EPS
    head_secs, tail_secs = head.findall("lanes/laneSection"), tail.findall("lanes/laneSection")
    for i, sec in enumerate(head_secs):
        if i > j or (i == j and not straddles):
            sec.getparent().remove(sec)
    for i, sec in enumerate(tail_secs):
        if i < j:
            sec.getparent().remove(sec)
        else:
            sec.set("s", _fmt(0.0 if i == j else sec_s[i] - cut))
    if straddles:
        ds = cut - sec_s[j]
        for lane in _lanes_of(head_secs[j]).values():
            _set_lane_link(lane, "successor", int(lane.get("id")))
            _cut_records(lane, "width", "sOffset", ds, head=True, cubic=True)
            _cut_records(lane, "roadMark", "sOffset", ds, head=True, cubic=False)
        for lane in _lanes_of(tail_secs[j]).values():
            _set_lane_link(lane, "predecessor", int(lane.get("id")))
            _cut_records(lane, "width", "sOffset", ds, head=False, cubic=True)
            _cut_records(lane, "roadMark", "sOffset", ds, head=False, cubic=False)
        centre = tail_secs[j].find("center/lane")
        if centre is not None:
            _cut_records(centre, "roadMark", "sOffset", ds, head=False, cubic=False)
    return head, tail


def _tidy_records(parent: etree._Element, tag: str, key: str, end: float) -> None:
    """Records near the cut that now continue their neighbour within 1 um are merged (see `_merge_records`)."""
    recs = parent.findall(tag)
    if len(recs) < 2:
        return
    starts = np.array([float(r.get(key)) for r in recs])
    coeffs = np.array([[float(r.get(k)) for k in "abcd"] for r in recs])
    merged = _merge_records(_Records(starts, coeffs), end)
    for rec, start, old in zip(recs, starts, coeffs, strict=True):
        i = np.flatnonzero(merged.starts == start)
        if len(i) == 0:
            parent.remove(rec)
        elif np.any(merged.coeffs[i[0]] != old):
            for k, val in zip("abcd", merged.coeffs[i[0]], strict=True):
                rec.set(k, _fmt(val))


def _tidy_road(road: etree._Element) -> None:
    length = float(road.get("length"))
    for path, tag in (("elevationProfile", "elevation"), ("lateralProfile", "superelevation"), ("lanes", "laneOffset")):
        parent = road.find(path)
        if parent is not None:
            _tidy_records(parent, tag, "s", length)
    secs = road.findall("lanes/laneSection")
    ends = [float(sec.get("s")) for sec in secs[1:]] + [length]
    for sec, end in zip(secs, ends, strict=True):
        for lane in _lanes_of(sec).values():
            _tidy_records(lane, "width", "sOffset", end - float(sec.get("s")))


def _set_road_link(road: etree._Element, kind: str, element_type: str, element_id: str,
                   contact: str | None = None) -> None:
    link = road.find("link")
    if link is None:
        link = etree.Element("link")
        road.insert(0, link)
    old = link.find(kind)
    if old is not None:
        link.remove(old)
    el = etree.Element(kind, elementType=element_type, elementId=element_id)
    if contact is not None:
        el.set("contactPoint", contact)
    link.insert(0 if kind == "predecessor" else len(link), el)


@dataclass
class _Cut:
    """One connecting road cut from a road end: `road` (id), at its start or end, for a junction connection."""

    road: str
    at_end: bool
    junction: str
    other: str  # the road at the other side of the connection
    pairs: list[tuple[int, int]]  # (lane of the incoming road, lane of the outgoing road)


def _connection(junction: etree._Element, incoming: str, connecting: str, contact: str,
                links: list[tuple[int, int]]) -> None:
    if not links:
        return
    conn = etree.SubElement(junction, "connection", id=str(len(junction.findall("connection"))),
                            incomingRoad=incoming, connectingRoad=connecting, contactPoint=contact)
    for a, b in links:
        etree.SubElement(conn, "laneLink", attrib={"from": str(a), "to": str(b)})


def _classic_junctions(root: etree._Element, cfg: ExportConfig,
                       continuations: set[tuple[str, str]]) -> list[tuple[str, str]]:
    """Rewrite the direct junctions of a written map as classic junctions with connecting roads (in place).

    Each direct connection incoming -> linked becomes a connecting road cut from one of the two roads:
    from the linked road's start when it is linked once in the junction (a diverge: every branch),
    else from the incoming road's end (a merge). It is `connecting_road_m` long, at most the end lane
    section and half the road (a third when both ends are cut), snapped to the nearest laneOffset
    record, section or geometry break within half a lane record or half its length (so the lane
    records stay as fitted). The cut is exact (the same curves), so the connecting road continues
    both roads without a gap. Right lanes enter the junction from the incoming road (contactPoint
    start), left lanes (travelling against s) from the linked road (contactPoint end); the
    connecting road's lanes link both ways, the lanes of the roads outside stay unlinked at the
    junction (the junction links them). Returns (road whose end, road whose start) pairs whose
    reference lines must meet: every cut and every continuation.
    """
    roads = {r.get("id"): r for r in root.findall("road")}
    cuts: list[_Cut] = []
    for junction in root.findall("junction"):
        conns = junction.findall("connection")
        inc = [c.get("incomingRoad") for c in conns]
        out = [c.get("linkedRoad") for c in conns]
        for c, a, b in zip(conns, inc, out, strict=True):
            pairs = [(int(ll.get("from")), int(ll.get("to"))) for ll in c.findall("laneLink")]
            if out.count(b) == 1:
                cuts.append(_Cut(b, False, junction.get("id"), a, pairs))
            elif inc.count(a) == 1:
                cuts.append(_Cut(a, True, junction.get("id"), b, pairs))
            else:
                raise InputError(_NET, f"junction {junction.get('id')}: road {a} -> road {b} shares both roads "
                                       "with other links, so no connecting road can be cut from either")
    next_id = 1 + max(int(e.get("id")) for e in root.findall("road") + root.findall("junction"))
    joins: list[tuple[str, str]] = []
    made: dict[int, str] = {}
    for at_end in (True, False):  # end cuts first: a road cut at both ends keeps its start geometry in place
        for q, cut in enumerate(cuts):
            if cut.at_end != at_end:
                continue
            road = roads[cut.road]
            length = float(road.get("length"))
            secs = [float(s.get("s")) for s in road.findall("lanes/laneSection")] + [length]
            n_cuts = sum(c.road == cut.road for c in cuts)
            end_sec = secs[-1] - secs[-2] if at_end else secs[1] - secs[0]
            want = min(cfg.connecting_road_m, end_sec, length / (n_cuts + 1))
            at = length - want if at_end else want
            snaps = [float(e.get("s")) for e in road.findall("planView/geometry") + road.findall("lanes/laneOffset")]
            inside = (max(secs[-2], 1.0), length - 1.0) if at_end else (1.0, min(secs[1], length - 1.0))
            reach = 0.5 * min(cfg.lane_record_m, want)
            near = [s for s in snaps + secs if abs(s - at) <= reach and inside[0] <= s <= inside[1]]
            if near:
                at = min(near, key=lambda s: abs(s - at))
            head, tail = _split_road(road, at)
            for part in (head, tail):
                _tidy_road(part)
            conn_road, outer = (tail, head) if at_end else (head, tail)
            conn_id = str(next_id)
            next_id += 1
            made[q] = conn_id
            conn_road.set("id", conn_id)
            conn_road.set("junction", cut.junction)
            conn_road.set("name", f"{road.get('name')} junction {cut.junction}")
            road.addprevious(head)
            road.addprevious(tail)
            road.getparent().remove(road)
            roads[cut.road] = outer
            roads[conn_id] = conn_road
            joins.append((head.get("id"), tail.get("id")))
            link = conn_road.find("link")
            if link is not None:
                conn_road.remove(link)
            incoming, outgoing = (cut.road, cut.other) if at_end else (cut.other, cut.road)
            _set_road_link(conn_road, "predecessor", "road", incoming, "end")
            _set_road_link(conn_road, "successor", "road", outgoing, "start")
            outer_secs = outer.findall("lanes/laneSection")
            conn_secs = conn_road.findall("lanes/laneSection")
            for lane in _lanes_of(outer_secs[-1 if at_end else 0]).values():
                _set_lane_link(lane, "successor" if at_end else "predecessor", None)
            far = {(i if at_end else j): (j if at_end else i) for i, j in cut.pairs}
            for lane_id, lane in _lanes_of(conn_secs[-1 if at_end else 0]).items():
                _set_lane_link(lane, "successor" if at_end else "predecessor", far.get(lane_id))
            if (incoming, outgoing) in continuations:
                joins.append((incoming, conn_id) if not at_end else (conn_id, outgoing))
    for conn_id in made.values():  # the roads outside the junctions first (ids 1..N), then the connecting roads
        root.find("junction").addprevious(roads[conn_id])
    for junction in root.findall("junction"):
        junction.set("type", "default")
        for conn in junction.findall("connection"):
            junction.remove(conn)
    for q, cut in enumerate(cuts):
        junction = next(j for j in root.findall("junction") if j.get("id") == cut.junction)
        conn_id = made[q]
        conn_road = roads[conn_id]
        first, last = conn_road.findall("lanes/laneSection")[0], conn_road.findall("lanes/laneSection")[-1]
        if cut.at_end:  # the incoming road's end was cut: its lanes all enter; the linked road's left lanes
            right = [(_lane_link(lane, "predecessor"), k) for k, lane in _lanes_of(first).items() if k < 0]
            left = [(j, i) for i, j in cut.pairs if i > 0]
            _connection(junction, cut.road, conn_id, "start", sorted(r for r in right if r[0] is not None))
            _connection(junction, cut.other, conn_id, "end", sorted(left))
        else:  # the linked road's start was cut
            right = [(i, j) for i, j in cut.pairs if i < 0]
            left = [(_lane_link(lane, "successor"), k) for k, lane in _lanes_of(last).items() if k > 0]
            _connection(junction, cut.other, conn_id, "start", sorted(right))
            _connection(junction, cut.road, conn_id, "end", sorted(r for r in left if r[0] is not None))
    return joins


# --------------------------------------------------------------------------------------------


def export_network(network: RoadNetwork, planes: GroundPlanes | None, cfg: ExportConfig,
                   path: Path, *, _direct: bool = False) -> ExportSummary:
    """Write the roads of `network` (ids 1..N in order) joined by classic junctions to `path` (atomically).

    The roads are first joined by direct junctions, then rewritten as classic ones by cutting
    (`_classic_junctions`). `_direct` keeps that intermediate form, for tests of the joins only: no
    reader available here loads it (SUMO 1.28: "connectingRoad is missing", CARLA 0.9.16:
    IndexError). Junction ids follow the road ids (N + 1, ...), so every id in the file is unique.
    Roads are built in an order where every anchored end's partner is already written (see
    `_plan_joins`, `_anchor`).
    """
    wheres = _check_network(network, cfg)
    n = len(network.roads)
    joins, order = _plan_joins(network)
    linked: dict[tuple[int, bool], set[int]] = {}
    for link in network.links:
        linked.setdefault((link.incoming, True), set()).update([int(i) for i, _ in link.lanes] + link.open_in)
        linked.setdefault((link.outgoing, False), set()).update([int(j) for _, j in link.lanes] + link.open_out)

    built: dict[int, _Built] = {}
    for r in order:
        model = network.roads[r]
        ends: list[_Anchor | _LaneEnd | None] = []
        for at_end in (False, True):
            if (r, at_end) not in linked:
                ends.append(None)
                continue
            n_lanes = len(model.sections[-1 if at_end else 0].boundary_ids) - 1
            zero = set(range(n_lanes)) - linked[(r, at_end)]
            join = joins.get((r, at_end))
            if join is None:
                ends.append(_LaneEnd(zero))
            else:
                other = built[join.other]
                ends.append(_anchor(other.end if join.other_end else other.start, join, zero))
        name = cfg.road_name if n == 1 else f"{cfg.road_name} {r + 1}"
        built[r] = _build_road(model, planes, cfg, r + 1, name, ends[0], ends[1], wheres[r])

    odr_junctions: list[xodr.Junction] = []
    for g, group in enumerate(_junction_groups(network.links)):
        jid = n + 1 + g
        links = [network.links[q] for q in group]
        junction = xodr.Junction(_junction_name(links), jid, xodr.JunctionType.direct)
        for link in links:
            connection = xodr.Connection(link.incoming + 1, link.outgoing + 1, xodr.ContactPoint.start)
            for i, j in sorted(link.lanes):
                connection.add_lanelink(built[link.incoming].fits[-1].lane_id(int(i)),
                                        built[link.outgoing].fits[0].lane_id(int(j)))
            junction.add_connection(connection)
        for r in sorted({lk.incoming for lk in links}):
            built[r].road.add_successor(xodr.ElementType.junction, jid)
        for r in sorted({lk.outgoing for lk in links}):
            built[r].road.add_predecessor(xodr.ElementType.junction, jid)
        odr_junctions.append(junction)

    geo, geodetic = _geo_reference(network.roads[0])
    odr = xodr.OpenDrive(cfg.road_name, revMajor="1", revMinor=str(cfg.opendrive_minor), geo_reference=geo)
    for r in range(n):
        odr.add_road(built[r].road)
    for junction in odr_junctions:
        odr.add_junction(junction)
    pts = np.vstack([built[r].outline for r in range(n)])
    margin = max(cfg.right_shoulder_m, cfg.left_border_m)
    bbox = np.r_[pts.min(axis=0) - margin, pts.max(axis=0) + margin]

    data = _serialise(odr, geo, geodetic, _date(planes), bbox)
    joins = [(str(lk.incoming + 1), str(lk.outgoing + 1)) for lk in network.links if lk.continuation]
    connecting = 0
    root = etree.fromstring(data, etree.XMLParser(remove_blank_text=True, strip_cdata=False))
    if network.links and not _direct:
        joins = _classic_junctions(root, cfg, set(joins))
        connecting = len(root.findall("road")) - n
    folded = fold_appearing_lanes(root) if cfg.fold_appearing_lanes else []
    for road in dict.fromkeys(folded):
        _tidy_road(road)
    data = etree.tostring(root, pretty_print=True, xml_declaration=True, encoding="UTF-8")
    leap, kink, lerr = _measure(data, joins)
    gap = _junction_gap(data) if network.links else 0.0
    write_bytes(path, data)
    roads = list(built.values())
    return ExportSummary(length_m=float(sum(b.length for b in roads)), pieces=sum(b.pieces for b in roads),
                         lane_sections=sum(len(b.fits) for b in roads) - len(folded), max_leap_m=leap,
                         max_kink_rad=kink,
                         max_length_error_m=lerr, max_reference_dev_m=max(b.reference_dev for b in roads),
                         max_border_dev_m=max(b.border_dev for b in roads), roads=n, junctions=len(odr_junctions),
                         max_junction_gap_m=gap, connecting_roads=connecting)


def export_opendrive(model: LaneModel, planes: GroundPlanes | None, cfg: ExportConfig, path: Path) -> ExportSummary:
    """Write `model` as one OpenDRIVE road to `path` (atomically) and return what was measured."""
    return export_network(RoadNetwork([model]), planes, cfg, path)

