"""ASAM OpenDRIVE 1.4-1.8 reader and vectorised geometry evaluator: the project's ground truth.

Every function of the station s accepts scalars or arrays and returns arrays. Conventions:

- Station s is arc length along the reference line. poly3 and paramPoly3 are re-parametrised by
  arc length (as esmini and libOpenDRIVE do); a paramPoly3 whose true arc length differs from its
  declared length is traversed at constant speed so that [0, length] covers exactly its p range.
- The geometry at station s is the one whose [s, s + length) contains it; the last one also owns
  its end and extrapolates beyond it.
- Superelevation is the roll about the reference line, positive counter-clockwise around the
  s axis (left side up). A point (s, t, h) lies at horizontal offset t*cos(roll) - h*sin(roll)
  along the left normal and at z = elevation(s) + t*sin(roll) + h*cos(roll). `level` lanes and
  the lateral `shape` profile are read but not applied.
- A lane <border> polynomial gives the outer border's distance from the lane reference line
  (centre lane after laneOffset), positive outwards, as for widths.
- A section's last sample (its closed end) takes every profile's limit from below, so records
  that start exactly at the next section belong to that section only.
- Road marks without an explicit <type><line> pattern get one from their type (default_lines):
  see BROKEN_DASH_M, BROKEN_GAP_M, DOUBLE_LINE_GAP_M, MARK_WIDTH_M. A continuous line has space 0.
- Where OpenDRIVE 1.8 allows several lane predecessors/successors, the first one is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from lxml import etree
from scipy.special import fresnel

from lidar2xodr.errors import InputError, one_line

BROKEN_DASH_M = 6.0
"""Dash length of a broken line without an explicit pattern (German motorway, RMS)."""
BROKEN_GAP_M = 12.0
"""Gap of a broken line without an explicit pattern (German motorway, RMS)."""
DOUBLE_LINE_GAP_M = 0.12
"""Clear gap between the two lines of a double mark ('solid solid', 'solid broken', ...)."""
MARK_WIDTH_M = {"standard": 0.15, "bold": 0.30}
"""Line width by weight when a roadMark has no width (German motorway: 0.15 m narrow, 0.30 m bold)."""
BOTTS_DOT_M = (0.1, 1.0)
"""Dot length and spacing of 'botts dots' without an explicit pattern."""

OPENDRIVE_NAMESPACES = ("http://www.opendrive.org", "http://code.asam.net/simulation/standard/opendrive_schema")
"""Namespaces some exporters put on <OpenDRIVE> (the old opendrive.org one, ASAM's 1.8 schema): read as plain."""
NEGATIVE_WIDTH_TOL_M = 1e-3
"""A width below -this (1 mm, the project's leap limit) is negative; above it, rounding of the written
coefficients of a taper that ends at exactly 0 (our exporter's folded tapers dip to -2.3e-7 m)."""

_GL_X, _GL_W = np.polynomial.legendre.leggauss(6)
_FRESNEL_MAX_ARG = 50.0
"""Beyond this Fresnel argument (a clothoid piece far out on its spiral: large curvature, tiny
curvature rate) cancellation costs micrometres, so the heading is integrated by Gauss-Legendre."""


def _arr(s: float | np.ndarray) -> np.ndarray:
    return np.atleast_1d(np.asarray(s, dtype=np.float64))


def _lookup(starts: np.ndarray, s: np.ndarray, left: bool) -> np.ndarray:
    """Index of the record owning s: [start, next start) or, with left=True, (start, next start]."""
    return np.clip(np.searchsorted(starts, s, side="left" if left else "right") - 1, 0, None)


# --------------------------------------------------------------------------------------------
# piecewise cubic polynomials (elevation, superelevation, laneOffset, widths, borders)


@dataclass
class CubicRecords:
    """Piecewise cubics a + b*ds + c*ds^2 + d*ds^3 with ds measured from each record's start."""

    starts: np.ndarray  # (k,)
    coeffs: np.ndarray  # (k, 4)

    @classmethod
    def empty(cls) -> CubicRecords:
        return cls(np.zeros(0), np.zeros((0, 4)))

    def __call__(self, s: float | np.ndarray, derivative: int = 0, left: bool = False) -> np.ndarray:
        """Value (or derivative) at s; left=True takes the limit from below at record boundaries."""
        s = _arr(s)
        if len(self.starts) == 0:
            return np.zeros_like(s)
        i = _lookup(self.starts, s, left)
        ds = s - self.starts[i]
        a, b, c, d = self.coeffs[i].T
        if derivative == 0:
            return a + ds * (b + ds * (c + ds * d))
        if derivative == 1:
            return b + ds * (2 * c + 3 * ds * d)
        return 2 * c + 6 * ds * d


# --------------------------------------------------------------------------------------------
# planView geometries


@dataclass
class Geometry:
    """One planView record. `params` holds the kind's attributes (curvature, aU..dV, pRange ...)."""

    s: float
    x: float
    y: float
    hdg: float
    length: float
    kind: str  # line | arc | spiral | poly3 | paramPoly3
    params: dict[str, float | str] = field(default_factory=dict)
    _table: _ArcTable | None = field(default=None, repr=False, compare=False)

    def eval(self, ds: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, y and heading at local arc length ds (0 = the record's start)."""
        ds = _arr(ds)
        if self.kind == "line":
            u, v, th = ds, np.zeros_like(ds), np.zeros_like(ds)
        elif self.kind == "arc":
            u, v, th = _arc_local(ds, float(self.params["curvature"]))
        elif self.kind == "spiral":
            u, v, th = self._spiral_local(ds)
        else:
            u, v, th = self._cubic_local(ds)
        c, s = math.cos(self.hdg), math.sin(self.hdg)
        return self.x + c * u - s * v, self.y + s * u + c * v, self.hdg + th

    def _spiral_local(self, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k0, k1 = float(self.params["curvStart"]), float(self.params["curvEnd"])
        rate = (k1 - k0) / self.length
        heading = ds * (k0 + 0.5 * rate * ds)
        if rate == 0.0:
            u, v, _ = _arc_local(ds, k0)
            return u, v, heading
        # A piece of the normalised clothoid (curvature = rate * l) starting at l0 = k0 / rate.
        a = math.sqrt(math.pi / abs(rate))
        l0 = k0 / rate
        if max(abs(l0), abs(l0 + self.length)) / a > _FRESNEL_MAX_ARG:
            u, v = _integrate_heading(k0, rate, self.length, ds)
            return u, v, heading
        s0, c0 = fresnel(l0 / a)
        s1, c1 = fresnel((l0 + ds) / a)
        du, dv = a * (c1 - c0), math.copysign(a, rate) * (s1 - s0)
        rot = -0.5 * rate * l0 * l0
        cr, sr = math.cos(rot), math.sin(rot)
        return cr * du - sr * dv, sr * du + cr * dv, heading

    def _cubic_local(self, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        table = self._table
        if table is None:
            table = self._table = _ArcTable.for_geometry(self)
        p = table.p_at(ds * table.scale)
        u = _poly(table.cu, p)
        v = _poly(table.cv, p)
        th = np.arctan2(_dpoly(table.cv, p), _dpoly(table.cu, p))
        return u, v, th


def _poly(c: tuple[float, float, float, float], p: np.ndarray) -> np.ndarray:
    return c[0] + p * (c[1] + p * (c[2] + p * c[3]))


def _dpoly(c: tuple[float, float, float, float], p: np.ndarray) -> np.ndarray:
    return c[1] + p * (2 * c[2] + 3 * p * c[3])


def _integrate_heading(
    k0: float, rate: float, length: float, ds: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Local (u, v) of a curve with heading k0*l + rate*l^2/2: cumulative Gauss-Legendre on pieces
    that turn at most 0.25 rad, then one more Gauss-Legendre piece from the last node to ds."""
    turn = length * max(abs(k0), abs(k0 + rate * length))
    nodes = np.linspace(0.0, length, int(min(max(1, math.ceil(turn / 0.25)), 1_000_000)) + 1)

    def piece(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        half = 0.5 * (hi - lo)
        p = (0.5 * (lo + hi))[..., None] + half[..., None] * _GL_X
        th = p * (k0 + 0.5 * rate * p)
        return half * (np.cos(th) @ _GL_W), half * (np.sin(th) @ _GL_W)

    cu, cv = piece(nodes[:-1], nodes[1:])
    cu, cv = np.concatenate([[0.0], np.cumsum(cu)]), np.concatenate([[0.0], np.cumsum(cv)])
    i = np.clip(np.searchsorted(nodes, ds, side="right") - 1, 0, len(nodes) - 2)
    du, dv = piece(nodes[i], ds)
    return cu[i] + du, cv[i] + dv


def _arc_local(ds: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Circle of curvature k in the local frame; exact and stable for k -> 0."""
    th = k * ds
    u = ds * np.sinc(th / np.pi)
    v = ds * np.sin(0.5 * th) * np.sinc(th / (2 * np.pi))
    return u, v, th


@dataclass
class _ArcTable:
    """Arc length of a parametric cubic (u(p), v(p)) tabulated on [0, p_max], inverted by Newton."""

    cu: tuple[float, float, float, float]
    cv: tuple[float, float, float, float]
    nodes: np.ndarray
    cum: np.ndarray
    scale: float  # multiplies local ds to give the arc length along the polynomial

    @classmethod
    def for_geometry(cls, g: Geometry) -> _ArcTable:
        p = g.params
        if g.kind == "poly3":
            cu = (0.0, 1.0, 0.0, 0.0)
            cv = (float(p["a"]), float(p["b"]), float(p["c"]), float(p["d"]))
            p_max = g.length  # arc length >= u, so the end lies within [0, length]
        else:
            cu = (float(p["aU"]), float(p["bU"]), float(p["cU"]), float(p["dU"]))
            cv = (float(p["aV"]), float(p["bV"]), float(p["cV"]), float(p["dV"]))
            p_max = 1.0 if p.get("pRange", "normalized") == "normalized" else g.length
        n = int(min(max(16, math.ceil(g.length / 0.25)), 200_000))
        nodes = np.linspace(0.0, p_max, n + 1)
        pieces = _gauss_arc(cu, cv, nodes[:-1], nodes[1:])
        cum = np.concatenate([[0.0], np.cumsum(pieces)])
        table = cls(cu, cv, nodes, cum, 1.0)
        table.scale = 1.0 if g.kind == "poly3" else cum[-1] / g.length
        return table

    def p_at(self, arc: np.ndarray) -> np.ndarray:
        """Parameter p whose arc length from p = 0 is `arc` (linear extrapolation outside)."""
        i = np.clip(np.searchsorted(self.cum, arc, side="right") - 1, 0, len(self.nodes) - 2)
        p0, p1 = self.nodes[i], self.nodes[i + 1]
        c0, c1 = self.cum[i], self.cum[i + 1]
        p = p0 + (arc - c0) * (p1 - p0) / np.maximum(c1 - c0, 1e-300)
        for _ in range(4):
            speed = np.hypot(_dpoly(self.cu, p), _dpoly(self.cv, p))
            err = c0 + _gauss_arc(self.cu, self.cv, p0, p) - arc
            p = p - err / np.maximum(speed, 1e-12)
        return p


def _gauss_arc(cu: tuple, cv: tuple, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Arc length of the parametric cubic between parameters a and b (Gauss-Legendre)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    half = 0.5 * (b - a)
    p = (0.5 * (a + b))[..., None] + half[..., None] * _GL_X
    speed = np.hypot(_dpoly(cu, p), _dpoly(cv, p))
    return half * (speed @ _GL_W)


# --------------------------------------------------------------------------------------------
# lanes and marks


@dataclass
class MarkLine:
    """One painted line of a road mark. space == 0 means continuous; offsets relative to the border."""

    length: float
    space: float
    t_offset: float
    s_offset: float
    width: float
    rule: str | None = None


@dataclass
class RoadMark:
    """A roadMark record on a lane's outer border, valid from s_offset (relative to the section)."""

    s_offset: float
    type: str
    weight: str
    color: str
    width: float
    lane_change: str | None
    lines: list[MarkLine]
    explicit: bool = False  # lines came from <type><line>, not from the defaults


@dataclass
class Lane:
    """A lane of one lane section. Width (or border) records have ds relative to the section start."""

    id: int
    type: str
    level: bool = False
    predecessor: int | None = None
    successor: int | None = None
    road_marks: list[RoadMark] = field(default_factory=list)
    widths: CubicRecords = field(default_factory=CubicRecords.empty)
    borders: CubicRecords | None = None

    def width(self, ds: float | np.ndarray) -> np.ndarray:
        """Width at ds from the section start (0 for the centre lane; NaN for border-only lanes)."""
        if self.id == 0:
            return np.zeros_like(_arr(ds))
        if self.borders is not None and len(self.widths.starts) == 0:
            return np.full_like(_arr(ds), np.nan)
        return self.widths(ds)


@dataclass
class LaneSection:
    s: float
    s_end: float
    single_side: bool
    lanes: dict[int, Lane]

    def lane_ids(self) -> list[int]:
        return sorted(self.lanes)


@dataclass
class RoadType:
    """A <type> record of a road: its kind (motorway, rural, town, ...) and speed limit from s on."""

    s: float
    type: str
    speed_max_mps: float | None  # None: no <speed> or 'no limit' / 'undefined'


_SPEED_UNITS = {"m/s": 1.0, "km/h": 1 / 3.6, "mph": 0.44704}


@dataclass
class Link:
    element_type: str  # "road" | "junction"
    element_id: str
    contact_point: str | None  # "start" | "end" | None


# --------------------------------------------------------------------------------------------
# roads


@dataclass
class Road:
    id: str
    name: str
    length: float
    junction: str
    predecessor: Link | None
    successor: Link | None
    geometries: list[Geometry]
    lane_sections: list[LaneSection]
    elevation_profile: CubicRecords = field(default_factory=CubicRecords.empty)
    superelevation_profile: CubicRecords = field(default_factory=CubicRecords.empty)
    lane_offsets: CubicRecords = field(default_factory=CubicRecords.empty)
    rule: str = "RHT"
    types: list[RoadType] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._geo_starts = np.array([g.s for g in self.geometries])
        self._sec_starts = np.array([ls.s for ls in self.lane_sections])

    def reference(
        self, s: float | np.ndarray, left: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, y and heading of the reference line at station s (left: limit from below)."""
        s = _arr(s)
        idx = _lookup(self._geo_starts, s, left)
        x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
        for i in np.unique(idx):
            m = idx == i
            g = self.geometries[i]
            x[m], y[m], h[m] = g.eval(s[m] - g.s)
        return x, y, h

    def elevation(self, s: float | np.ndarray, left: bool = False) -> np.ndarray:
        return self.elevation_profile(s, left=left)

    def superelevation(self, s: float | np.ndarray, left: bool = False) -> np.ndarray:
        """Roll angle in radians, positive = left side up."""
        return self.superelevation_profile(s, left=left)

    def lane_offset(self, s: float | np.ndarray, left: bool = False) -> np.ndarray:
        return self.lane_offsets(s, left=left)

    def section_index(self, s: float | np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self._sec_starts, _arr(s), side="right") - 1, 0, None)

    def border_t(self, s: float | np.ndarray, lane_id: int) -> np.ndarray:
        """Lateral t of the outer border of lane_id at s (lane 0: the laneOffset); NaN where absent."""
        s = _arr(s)
        out = np.full_like(s, np.nan)
        sec = self.section_index(s)
        offset = self.lane_offset(s)
        for k in np.unique(sec):
            m = sec == k
            t = _section_border(self.lane_sections[k], s[m], offset[m], lane_id)
            if t is not None:
                out[m] = t
        return out

    def to_world(
        self, s: float | np.ndarray, t: float | np.ndarray, h: float | np.ndarray = 0.0
    ) -> np.ndarray:
        """(N, 3) world points of road coordinates (s, t, h), elevation and superelevation applied."""
        s = _arr(s)
        t = np.broadcast_to(np.asarray(t, dtype=np.float64), s.shape)
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), s.shape)
        x, y, hdg = self.reference(s)
        roll = self.superelevation(s)
        cr, sr = np.cos(roll), np.sin(roll)
        lateral = t * cr - h * sr
        z = self.elevation(s) + t * sr + h * cr
        return np.stack([x - np.sin(hdg) * lateral, y + np.cos(hdg) * lateral, z], axis=1)


def _section_border(
    ls: LaneSection, s: np.ndarray, offset: np.ndarray, lane_id: int, left: bool = False
) -> np.ndarray | None:
    if lane_id not in ls.lanes:
        return None
    if lane_id == 0:
        return offset
    side = 1 if lane_id > 0 else -1
    ds = s - ls.s
    t = offset.copy()
    for k in range(side, lane_id + side, side):
        lane = ls.lanes[k]
        if lane.borders is not None and len(lane.widths.starts) == 0:
            t = offset + side * lane.borders(ds, left=left)
        else:
            t = t + side * lane.widths(ds, left=left)
    return t


@dataclass
class SampledSection:
    """One lane section sampled along s (both ends included), in world coordinates."""

    road_id: str
    section: int
    s: np.ndarray
    xyz: np.ndarray
    hdg: np.ndarray
    lane_ids: list[int]
    border_t: dict[int, np.ndarray]
    border_xyz: dict[int, np.ndarray]
    lane_types: dict[int, str]
    border_mark: dict[int, np.ndarray] = field(default_factory=dict)  # roadMark type of each border ("none": no record)


@dataclass
class Connection:
    id: str
    incoming_road: str
    connecting_road: str
    contact_point: str | None
    lane_links: list[tuple[int, int]]  # (from lane of the incoming road, to lane of the connecting road)


@dataclass
class Junction:
    id: str
    name: str
    connections: list[Connection]


# --------------------------------------------------------------------------------------------
# the map


@dataclass
class OpenDriveMap:
    path: Path
    version: tuple[int, int]
    geo_reference: str | None
    roads: dict[str, Road]
    junctions: dict[str, Junction]

    @classmethod
    def load(cls, path: str | Path) -> OpenDriveMap:
        """Read an .xodr file; any malformed content raises InputError naming file, road and element."""
        path = Path(path)
        if not path.is_file():
            raise InputError(path, "OpenDRIVE file not found")
        try:
            root = etree.parse(str(path), etree.XMLParser(huge_tree=True, remove_comments=True)).getroot()
        except (etree.XMLSyntaxError, OSError) as exc:
            raise InputError(path, "malformed XML: " + one_line(exc)) from None
        return _Parser(path).map(strip_namespace(root))

    def negative_widths(self) -> list[NegativeWidth]:
        """Every lane width record that is negative somewhere on its range (see `negative_widths`)."""
        return [w for road in self.roads.values() for w in negative_widths(road)]

    def require_nonnegative_widths(self) -> None:
        """InputError naming file, road, lane and s of the first negative lane width."""
        bad = self.negative_widths()
        if bad:
            w = bad[0]
            more = f" (and {len(bad) - 1} more record(s))" if len(bad) > 1 else ""
            raise InputError(f"{self.path} road {w.road} lane {w.lane}",
                             f"lane width {w.width:.3f} m < 0 at s={w.s:.2f}{more}")

    def sample(self, step: float = 0.5) -> list[SampledSection]:
        """Every lane section of every road sampled at <= step spacing, both section ends included."""
        if not step > 0:
            raise ValueError("step must be positive")
        out: list[SampledSection] = []
        for road in self.roads.values():
            for k, ls in enumerate(road.lane_sections):
                n = max(1, math.ceil((ls.s_end - ls.s) / step - 1e-9))
                s = np.linspace(ls.s, ls.s_end, n + 1)
                out.append(_sample_section(road, k, ls, s))
        return out


def _sample_section(road: Road, k: int, ls: LaneSection, s: np.ndarray) -> SampledSection:
    """Samples of one section; its closed end takes every profile's limit from below.

    Records (laneOffset, elevation, widths) that start exactly at the next section's start belong
    to that section, not to this one's last sample.
    """
    ids = ls.lane_ids()
    parts = [_frame(road, ls, s[:-1], ids, False), _frame(road, ls, s[-1:], ids, True)]
    x, y, hdg, z, roll = (np.concatenate([p[i] for p in parts]) for i in range(5))
    border_t = {lid: np.concatenate([p[5][lid] for p in parts]) for lid in ids}
    cr, sr, nx, ny = np.cos(roll), np.sin(roll), -np.sin(hdg), np.cos(hdg)
    border_xyz = {
        lid: np.stack([x + nx * t * cr, y + ny * t * cr, z + t * sr], axis=1) for lid, t in border_t.items()
    }
    return SampledSection(
        road_id=road.id,
        section=k,
        s=s,
        xyz=np.stack([x, y, z], axis=1),
        hdg=hdg,
        lane_ids=ids,
        border_t=border_t,
        border_xyz=border_xyz,
        lane_types={lid: ls.lanes[lid].type for lid in ids},
        border_mark={lid: _marks_at(ls.lanes[lid], s - ls.s) for lid in ids},
    )


def _marks_at(lane: Lane, ds: np.ndarray) -> np.ndarray:
    """The type of the lane's roadMark record in force at each ds from its section's start ("none" before
    the first record or without any)."""
    if not lane.road_marks:
        return np.full(len(ds), "none", dtype=object)
    starts = np.array([m.s_offset for m in lane.road_marks])
    types = np.array([m.type for m in lane.road_marks], dtype=object)
    order = np.argsort(starts, kind="stable")
    at = np.searchsorted(starts[order], ds + 1e-9, side="right") - 1
    return np.where(at >= 0, types[order][np.maximum(at, 0)], "none")


def _frame(road: Road, ls: LaneSection, s: np.ndarray, ids: list[int], left: bool) -> tuple:
    x, y, hdg = road.reference(s, left)
    offset = road.lane_offset(s, left)
    borders = {lid: _section_border(ls, s, offset, lid, left) for lid in ids}
    return x, y, hdg, road.elevation(s, left), road.superelevation(s, left), borders


# --------------------------------------------------------------------------------------------
# parsing

_GEOMETRY_KINDS = ("line", "arc", "spiral", "poly3", "paramPoly3")
_GEOMETRY_ATTRS = {
    "line": (),
    "arc": ("curvature",),
    "spiral": ("curvStart", "curvEnd"),
    "poly3": ("a", "b", "c", "d"),
    "paramPoly3": ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV"),
}


def strip_namespace(root: etree._Element) -> etree._Element:
    """The tree with an OpenDRIVE namespace (OPENDRIVE_NAMESPACES) removed from every element, so it reads as plain."""
    ns = etree.QName(root).namespace
    if ns is None or ns not in OPENDRIVE_NAMESPACES:
        return root
    for el in root.iter(etree.Element):
        if etree.QName(el).namespace == ns:
            el.tag = etree.QName(el).localname
    etree.cleanup_namespaces(root)
    return root


@dataclass(frozen=True)
class NegativeWidth:
    """A lane width record whose polynomial drops below zero: where (road s) and how far."""

    road: str
    section: int
    lane: int
    s: float
    width: float


def negative_widths(road: Road) -> list[NegativeWidth]:
    """The width records of a road's lanes that are < -NEGATIVE_WIDTH_TOL_M somewhere on their range.

    Each cubic is checked at its range's ends and at the roots of its derivative inside it (its only
    possible minima), so a dip between samples is not missed.
    """
    out = []
    for k, sec in enumerate(road.lane_sections):
        for lane in sec.lanes.values():
            rec = lane.widths
            for i, (start, (a, b, c, d)) in enumerate(zip(rec.starts, rec.coeffs, strict=True)):
                end = rec.starts[i + 1] if i + 1 < len(rec.starts) else sec.s_end - sec.s
                if end < start:
                    continue
                at, value = cubic_minimum((a, b, c, d), end - start)
                if value < -NEGATIVE_WIDTH_TOL_M:
                    out.append(NegativeWidth(road.id, k, lane.id, float(sec.s + start + at), value))
    return out


def cubic_minimum(coeffs: tuple[float, float, float, float], length: float) -> tuple[float, float]:
    """(ds, value) of the smallest value of a + b ds + c ds^2 + d ds^3 on [0, length]: at an end or
    at a root of the derivative inside (its only possible minima), so no dip between samples is missed."""
    a, b, c, d = (float(v) for v in coeffs)
    roots = np.roots([3 * d, 2 * c, b]) if (b, c, d) != (0.0, 0.0, 0.0) else np.array([])
    inside = [r.real for r in roots if abs(r.imag) < 1e-12 and 0.0 < r.real < length]
    ds = np.array([0.0, length, *inside])
    vals = a + b * ds + c * ds**2 + d * ds**3
    j = int(np.argmin(vals))
    return float(ds[j]), float(vals[j])


class _Parser:
    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, where: str, problem: str) -> InputError:
        return InputError(f"{self.path} {where}".rstrip(), problem)

    def num(self, el: etree._Element, name: str, where: str, default: float | None = None) -> float:
        raw = el.get(name)
        if raw is None:
            if default is None:
                raise self.fail(where, f"<{el.tag}> lacks attribute {name}")
            return default
        try:
            val = float(raw)
        except ValueError:
            raise self.fail(where, f"<{el.tag}> attribute {name}={raw!r} is not a number") from None
        if not math.isfinite(val):
            raise self.fail(where, f"<{el.tag}> attribute {name}={raw!r} is not finite")
        return val

    def cubic(self, els: list[etree._Element], start: str, where: str, tag: str) -> CubicRecords:
        if not els:
            return CubicRecords.empty()
        starts = np.array([self.num(e, start, where, 0.0) for e in els])
        coeffs = np.array([[self.num(e, c, where, 0.0) for c in "abcd"] for e in els])
        if np.any(np.diff(starts) < 0):
            raise self.fail(where, f"<{tag}> records are not sorted by {start}")
        return CubicRecords(starts, coeffs)

    def map(self, root: etree._Element) -> OpenDriveMap:
        if root.tag != "OpenDRIVE":
            raise self.fail("", f"root element is <{root.tag}>, not <OpenDRIVE>")
        header = root.find("header")
        if header is None:
            raise self.fail("", "missing <header>")
        version = (
            int(self.num(header, "revMajor", "<header>", 1)),
            int(self.num(header, "revMinor", "<header>", 4)),
        )
        geo = header.find("geoReference")
        geo_ref = (geo.text or "").strip() or None if geo is not None else None
        roads: dict[str, Road] = {}
        for el in root.iterfind("road"):
            road = self.road(el)
            if road.id in roads:
                raise self.fail(f"road {road.id}", "duplicate road id")
            roads[road.id] = road
        junctions = {j.id: j for j in (self.junction(el) for el in root.iterfind("junction"))}
        return OpenDriveMap(self.path, version, geo_ref, roads, junctions)

    def link(self, el: etree._Element | None, where: str) -> Link | None:
        if el is None or el.get("elementId") is None:
            return None
        kind = el.get("elementType", "road")
        if kind not in ("road", "junction"):
            raise self.fail(where, f"<{el.tag}> elementType={kind!r} is neither road nor junction")
        cp = el.get("contactPoint")
        if cp not in (None, "start", "end"):
            raise self.fail(where, f"<{el.tag}> contactPoint={cp!r} is neither start nor end")
        return Link(kind, el.get("elementId"), cp)

    def road(self, el: etree._Element) -> Road:
        rid = el.get("id")
        if rid is None:
            raise self.fail("<road>", "road without id")
        where = f"road {rid}"
        length = self.num(el, "length", where)
        if not length > 0:
            raise self.fail(where, f"road length {length} is not positive")
        link = el.find("link")
        pred = self.link(link.find("predecessor"), where) if link is not None else None
        succ = self.link(link.find("successor"), where) if link is not None else None
        geometries = self.plan_view(el, where)
        lanes = el.find("lanes")
        if lanes is None:
            raise self.fail(where, "missing <lanes>")
        sections = self.lane_sections(lanes, length, where)
        elev = el.find("elevationProfile")
        lat = el.find("lateralProfile")
        return Road(
            id=rid,
            name=el.get("name", ""),
            length=length,
            junction=el.get("junction", "-1"),
            predecessor=pred,
            successor=succ,
            geometries=geometries,
            lane_sections=sections,
            elevation_profile=self.cubic(
                elev.findall("elevation") if elev is not None else [], "s", where, "elevation"
            ),
            superelevation_profile=self.cubic(
                lat.findall("superelevation") if lat is not None else [], "s", where, "superelevation"
            ),
            lane_offsets=self.cubic(lanes.findall("laneOffset"), "s", where, "laneOffset"),
            rule=el.get("rule", "RHT"),
            types=[self.road_type(t, where) for t in el.iterfind("type")],
        )

    def road_type(self, el: etree._Element, where: str) -> RoadType:
        speed = el.find("speed")
        limit = None
        if speed is not None and speed.get("max") not in (None, "no limit", "undefined"):
            unit = speed.get("unit", "m/s")
            if unit not in _SPEED_UNITS:
                raise self.fail(where, f"<speed> unit={unit!r} is none of {', '.join(_SPEED_UNITS)}")
            limit = self.num(speed, "max", where) * _SPEED_UNITS[unit]
        return RoadType(self.num(el, "s", where, 0.0), el.get("type", "unknown"), limit)

    def plan_view(self, road: etree._Element, where: str) -> list[Geometry]:
        pv = road.find("planView")
        if pv is None:
            raise self.fail(where, "missing <planView>")
        out: list[Geometry] = []
        for g in pv.iterfind("geometry"):
            s = self.num(g, "s", where)
            w = f"{where} <geometry s={s:g}>"
            length = self.num(g, "length", w)
            if length < 0:
                raise self.fail(w, f"negative length {length}")
            kids = [k for k in g if isinstance(k.tag, str) and k.tag in _GEOMETRY_KINDS]
            if len(kids) != 1:
                names = ", ".join(f"<{k.tag}>" for k in g if isinstance(k.tag, str)) or "nothing"
                raise self.fail(
                    w, f"unknown geometry: {names} (expected one of {', '.join(_GEOMETRY_KINDS)})"[:300]
                )
            kind = kids[0].tag
            params: dict[str, float | str] = {a: self.num(kids[0], a, w) for a in _GEOMETRY_ATTRS[kind]}
            if kind == "paramPoly3":
                p_range = kids[0].get("pRange", "normalized")
                if p_range not in ("normalized", "arcLength"):
                    raise self.fail(w, f"<paramPoly3> pRange={p_range!r} is neither normalized nor arcLength")
                params["pRange"] = p_range
            if kind in ("poly3", "paramPoly3") and length == 0:
                continue
            x, y, hdg = (self.num(g, a, w) for a in ("x", "y", "hdg"))
            out.append(Geometry(s, x, y, hdg, length, kind, params))
        if not out:
            raise self.fail(where, "<planView> has no geometry")
        starts = [g.s for g in out]
        if any(b < a for a, b in zip(starts, starts[1:], strict=False)):
            raise self.fail(where, "<planView> geometries are not sorted by s")
        return out

    def lane_sections(self, lanes: etree._Element, length: float, where: str) -> list[LaneSection]:
        els = lanes.findall("laneSection")
        if not els:
            raise self.fail(where, "<lanes> has no <laneSection>")
        starts = [self.num(e, "s", where) for e in els]
        for a, b in zip(starts, starts[1:], strict=False):
            if b < a:
                raise self.fail(where, f"<laneSection> s={b:g} follows s={a:g}: lane sections out of order")
        if starts[0] > 1e-6 or starts[-1] > length + 1e-6:
            span = f"{starts[0]:g}..{starts[-1]:g}"
            raise self.fail(where, f"<laneSection> starts {span} lie outside the road [0, {length:g}]")
        ends = starts[1:] + [length]
        return [self.lane_section(e, s0, s1, where) for e, s0, s1 in zip(els, starts, ends, strict=True)]

    def lane_section(self, el: etree._Element, s0: float, s1: float, where: str) -> LaneSection:
        w = f"{where} <laneSection s={s0:g}>"
        lanes: dict[int, Lane] = {}
        for side in ("left", "center", "right"):
            grp = el.find(side)
            if grp is None:
                continue
            for lel in grp.iterfind("lane"):
                lane = self.lane(lel, side, w)
                if lane.id in lanes:
                    raise self.fail(w, f"duplicate lane id {lane.id}")
                lanes[lane.id] = lane
        if 0 not in lanes:
            raise self.fail(w, "missing centre lane 0")
        for sign in (1, -1):
            ids = sorted(abs(i) for i in lanes if i * sign > 0)
            if ids != list(range(1, len(ids) + 1)):
                raise self.fail(w, f"lane ids {[sign * i for i in ids]} are not contiguous from {sign}")
        single = el.get("singleSide", "false").lower() == "true"
        return LaneSection(s0, s1, single, lanes)

    def lane(self, el: etree._Element, side: str, where: str) -> Lane:
        raw = el.get("id")
        try:
            lid = int(raw)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise self.fail(where, f"<lane> id={raw!r} is not an integer") from None
        w = f"{where} lane {lid}"
        expected = {"left": lid > 0, "center": lid == 0, "right": lid < 0}[side]
        if not expected:
            raise self.fail(w, f"lane id {lid} is in <{side}>")
        link = el.find("link")
        pred = succ = None
        if link is not None:
            p, q = link.find("predecessor"), link.find("successor")
            pred = int(self.num(p, "id", w)) if p is not None else None
            succ = int(self.num(q, "id", w)) if q is not None else None
        widths = self.cubic(el.findall("width"), "sOffset", w, "width")
        border_els = el.findall("border")
        borders = self.cubic(border_els, "sOffset", w, "border") if border_els else None
        if lid != 0 and len(widths.starts) == 0 and borders is None:
            raise self.fail(w, "lane has neither <width> nor <border>")
        return Lane(
            id=lid,
            type=el.get("type", "none"),
            level=el.get("level", "false").lower() in ("true", "1"),
            predecessor=pred,
            successor=succ,
            road_marks=[self.road_mark(m, lid, w) for m in el.iterfind("roadMark")],
            widths=widths,
            borders=borders,
        )

    def road_mark(self, el: etree._Element, lane_id: int, where: str) -> RoadMark:
        kind = el.get("type", "none")
        weight = el.get("weight", "standard")
        width = self.num(el, "width", where, MARK_WIDTH_M.get(weight, MARK_WIDTH_M["standard"]))
        explicit = el.find("type")
        if explicit is not None and explicit.find("line") is not None:
            lines = [
                MarkLine(
                    length=self.num(ln, "length", where, 0.0),
                    space=self.num(ln, "space", where, 0.0),
                    t_offset=self.num(ln, "tOffset", where, 0.0),
                    s_offset=self.num(ln, "sOffset", where, 0.0),
                    width=self.num(ln, "width", where, width),
                    rule=ln.get("rule"),
                )
                for ln in explicit.iterfind("line")
            ]
        else:
            lines = default_lines(kind, width, lane_id)
        return RoadMark(
            s_offset=self.num(el, "sOffset", where, 0.0),
            type=kind,
            weight=weight,
            color=el.get("color", "standard"),
            width=width,
            lane_change=el.get("laneChange"),
            lines=lines,
            explicit=explicit is not None and bool(lines),
        )

    def junction(self, el: etree._Element) -> Junction:
        jid = el.get("id")
        if jid is None:
            raise self.fail("<junction>", "junction without id")
        where = f"junction {jid}"
        conns = []
        for c in el.iterfind("connection"):
            links = []
            for ll in c.iterfind("laneLink"):
                links.append((int(self.num(ll, "from", where)), int(self.num(ll, "to", where))))
            conns.append(
                Connection(
                    id=c.get("id", ""),
                    incoming_road=c.get("incomingRoad", ""),
                    connecting_road=c.get("connectingRoad", c.get("linkedRoad", "")),
                    contact_point=c.get("contactPoint"),
                    lane_links=links,
                )
            )
        return Junction(jid, el.get("name", ""), conns)


def default_lines(kind: str, width: float, lane_id: int = 0) -> list[MarkLine]:
    """Painted lines of a roadMark type without explicit pattern, t_offset relative to the border.

    Words of a double type read from the inside to the outside of the lane, on the centre lane
    from left to right (OpenDRIVE 1.4 roadMark table), so 'solid broken' on lane 0 puts the solid
    line at +t. Double marks are centred on the border with DOUBLE_LINE_GAP_M between the lines.
    Physical or unpainted types (curb, grass, edge, none, custom) have no lines.
    """
    words = kind.split()
    one = {"solid": (0.0, 0.0), "broken": (BROKEN_DASH_M, BROKEN_GAP_M), "botts": BOTTS_DOT_M}
    if kind == "botts dots":
        words = ["botts"]
    if not words or any(w not in one for w in words):
        return []
    if len(words) == 1:
        offsets = [0.0]
    else:
        half = 0.5 * (DOUBLE_LINE_GAP_M + width)
        offsets = [-half, half] if lane_id > 0 else [half, -half]
    return [MarkLine(one[w][0], one[w][1], off, 0.0, width) for w, off in zip(words, offsets, strict=True)]
