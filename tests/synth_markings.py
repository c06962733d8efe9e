"""Synthetic marking clouds from a parametric road, with the truth to test against.

The road is a centreline built from pieces (straight, constant-radius arc, clothoid) with lanes
of given widths. Its lines are painted like a German motorway: solid 0.30 m edges, broken 0.15 m
6 m / 12 m lane lines. Points are drawn like an accumulated sparse LiDAR: a Poisson number of
points per painted area (`density` per square metre of paint, thinner away from the ego lane),
Gaussian point noise, a GNSS offset per scan, occlusion gaps on some lines, spurious bright points
and blobs, an optional added (exit) lane that appears and disappears along tapers, and an
optional guard-rail-like line of points far outside. Everything is seeded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidar2xodr.data import GeoOrigin, GroundPlanes, MarkingCloud, Trajectory


@dataclass
class Piece:
    """One centreline piece: curvature goes linearly from k0 to k1 (1/m, left positive) over length."""

    length: float
    k0: float = 0.0
    k1: float = 0.0


def straight(length: float) -> Piece:
    return Piece(length)


def arc(length: float, radius: float) -> Piece:
    return Piece(length, 1.0 / radius, 1.0 / radius)


def clothoid(length: float, k0: float, k1: float) -> Piece:
    return Piece(length, k0, k1)


@dataclass
class Line:
    """A painted line: offset t(s) from the base centreline (left positive), where it exists."""

    name: str
    offset: float
    kind: str  # solid | broken
    width: float
    s_start: float
    s_end: float
    dash: float = 6.0
    gap: float = 12.0
    phase: float = 0.0
    taper: tuple[float, float, float, float] | None = None  # (s_a, s_b, taper length, shift)
    gaps: list[tuple[float, float]] = field(default_factory=list)  # occluded s intervals

    def t(self, s: np.ndarray) -> np.ndarray:
        out = np.full(np.shape(s), self.offset, dtype=np.float64)
        if self.taper is not None:
            out += self.taper[3] * taper_ramp(np.asarray(s, dtype=np.float64), *self.taper[:3])
        return out


class _Diverging(Line):
    """A line leaving the road at a constant angle from station s0."""

    def __init__(self, line: Line, s0: float, slope: float) -> None:
        super().__init__(**vars(line))
        self._s0, self._slope = s0, slope

    def t(self, s: np.ndarray) -> np.ndarray:
        return self.offset + self._slope * np.maximum(np.asarray(s, dtype=np.float64) - self._s0, 0.0)


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def taper_ramp(s: np.ndarray, s_a: float, s_b: float, length: float) -> np.ndarray:
    """0 before s_a, rises to 1 over `length`, stays 1, falls back to 0 at s_b."""
    return smoothstep((s - s_a) / length) * smoothstep((s_b - s) / length)


@dataclass
class SynthRoad:
    """What was drawn: the cloud and the truth (centreline, lines, lane counts)."""

    cloud: MarkingCloud
    lines: list[Line]
    s: np.ndarray  # fine stations of the base centreline
    xy: np.ndarray  # (M, 2)
    normal: np.ndarray  # (M, 2) left normals
    z: np.ndarray  # (M,)
    exit_lane: tuple[float, float, float] | None  # (s_a, s_b, taper)
    lane_widths: list[float]

    def line_xy(self, line: Line, s: np.ndarray) -> np.ndarray:
        """World x, y of a line at base stations s."""
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        nx = np.interp(s, self.s, self.normal[:, 0])
        ny = np.interp(s, self.s, self.normal[:, 1])
        t = line.t(s)
        return np.stack([x + nx * t, y + ny * t], axis=1)

    def lane_count(self, s: np.ndarray) -> np.ndarray:
        """Lanes of the carriageway at base stations s (the added lane counts where it is open)."""
        n = np.full(np.shape(s), len(self.lane_widths), dtype=int)
        if self.exit_lane is not None:
            s_a, s_b, _ = self.exit_lane
            n += ((s > s_a) & (s < s_b)).astype(int)
        return n


def _centreline(pieces: list[Piece], step: float = 0.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    total = sum(p.length for p in pieces)
    s = np.arange(0.0, total + step, step)
    kappa = np.zeros_like(s)
    s0 = 0.0
    for p in pieces:
        m = (s >= s0) & (s <= s0 + p.length)
        kappa[m] = p.k0 + (p.k1 - p.k0) * (s[m] - s0) / p.length
        s0 += p.length
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * step)])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(heading[1:]) + np.cos(heading[:-1])) * step)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(heading[1:]) + np.sin(heading[:-1])) * step)])
    normal = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    return s, np.stack([x, y], axis=1), normal


def make_road(
    pieces: list[Piece] | None = None,
    lane_widths: tuple[float, ...] = (3.75, 3.75, 3.75),
    density: float = 200.0,
    noise: float = 0.03,
    gnss_noise: float = 0.0,
    occlusions: int = 6,
    spurious: int = 300,
    blobs: int = 20,
    exit_lane: tuple[float, float, float] | None = None,
    guard_rail: float | None = None,
    opposite: float | None = None,
    two_way: tuple[float, ...] | None = None,
    ramp: tuple[float, float] | None = None,
    double_line: tuple[int, float, float, float] | None = None,
    ego_lane: int = 1,
    lane_change_at: float | None = None,
    start_xy: tuple[float, float] = (5.0, 2.0),
    grade: float = 0.01,
    seed: int = 0,
) -> SynthRoad:
    """Draw a marking cloud; `exit_lane` = (s_a, s_b, taper) adds a lane on the right.

    `opposite` draws the other carriageway beyond a median of that width (sparse, half occluded);
    `two_way` = lane widths of the other direction, painted left of the left edge line (which then
    only divides the directions: a paint-only two-way road; sparse, a few occlusions);
    `lane_change_at` moves the ego one lane to the right over 100 m from that station; `ramp` =
    (s0, angle in degrees) draws the two solid edges of a ramp that leaves the right edge at s0;
    `double_line` = (line index, spacing, s_a, s_b) paints line `index` between s_a and s_b as a double
    line, a solid and a broken one that far apart on either side of it (the truth stays its midpoint).
    """
    rng = np.random.default_rng(seed)
    pieces = pieces or [straight(1000.0)]
    s_fine, xy, normal = _centreline(pieces)
    xy = xy + np.asarray(start_xy)
    length = float(s_fine[-1])
    z_fine = grade * s_fine + 0.5 * np.sin(s_fine / 400.0)

    total_w = float(sum(lane_widths))
    edges = total_w / 2.0 - np.concatenate([[0.0], np.cumsum(lane_widths)])
    lines: list[Line] = []
    for i, t in enumerate(edges):
        outer = i in (0, len(edges) - 1)
        phase = float(rng.uniform(0.0, 18.0))
        if outer:
            lines.append(Line(f"edge{i}", float(t), "solid", 0.30, 0.0, length))
        else:
            lines.append(Line(f"lane{i}", float(t), "broken", 0.15, 0.0, length, phase=phase))
    if exit_lane is not None:
        s_a, s_b, taper = exit_lane
        right = lines[-1]
        right.taper = (s_a, s_b, taper, -lane_widths[-1])
        lines.append(Line("exit", right.offset, "broken", 0.30, s_a, s_b, dash=6.0, gap=6.0, phase=s_a))
    for line in lines[1:]:
        for _ in range(occlusions // max(1, len(lines) - 1) + int(rng.uniform() < 0.5)):
            a = float(rng.uniform(0.0, length))
            lines_gap = (a, a + float(rng.uniform(5.0, 30.0)))
            line.gaps.append(lines_gap)

    ego_t = edges[ego_lane] - lane_widths[ego_lane] / 2.0
    others: list[Line] = []
    doubles: list[Line] = []
    if double_line is not None:
        i, spacing, s_a, s_b = double_line
        lines[i].gaps.append((s_a, s_b))
        doubles = [Line(f"{lines[i].name}_solid", lines[i].offset + spacing / 2, "solid", 0.15, s_a, s_b),
                   Line(f"{lines[i].name}_broken", lines[i].offset - spacing / 2, "broken", 0.15, s_a, s_b,
                        phase=s_a)]
    if opposite is not None:
        base = edges[0] + opposite
        for i, w in enumerate([0.0, *lane_widths]):
            base += w
            last = i == len(lane_widths)
            line = Line(
                f"opp{i}",
                float(base),
                "solid" if i in (0, len(lane_widths)) else "broken",
                0.30 if i == 0 or last else 0.15,
                0.0,
                length,
                phase=float(rng.uniform(0.0, 18.0)),
            )
            for a in rng.uniform(0.0, length, int(length / 60)):
                line.gaps.append((float(a), float(a) + 30.0))
            others.append(line)
    if two_way is not None:
        base = float(edges[0])
        for i, w in enumerate(two_way):
            base += w
            last = i == len(two_way) - 1
            line = Line(f"two{i}", base, "solid" if last else "broken", 0.30 if last else 0.15, 0.0, length,
                        phase=float(rng.uniform(0.0, 18.0)))
            for a in rng.uniform(0.0, length, int(length / 200)):
                line.gaps.append((float(a), float(a) + 20.0))
            others.append(line)
    if ramp is not None:
        s0, angle = ramp
        slope = -np.tan(np.radians(angle))
        for k, extra in enumerate((0.0, -lane_widths[-1])):
            line = Line(f"ramp{k}", float(edges[-1]) + extra, "solid", 0.30, s0, min(s0 + 250.0, length))
            line.taper = None
            others.append(_Diverging(line, s0, slope))
    chunks: list[np.ndarray] = []
    for line in lines:
        chunks.append(_paint(line, rng, density, ego_t))
    for line in others:
        chunks.append(_paint(line, rng, 0.5 * density, ego_t))
    for line in doubles:
        chunks.append(_paint(line, rng, density, ego_t))
    st = np.concatenate(chunks) if chunks else np.zeros((0, 2))
    if guard_rail is not None:
        s_g = rng.uniform(0.0, length, int(length * 30))
        t_g = edges[-1] - guard_rail + rng.normal(0.0, 0.05, len(s_g))
        st = np.concatenate([st, np.stack([s_g, t_g], axis=1)])
    if spurious:
        s_sp = rng.uniform(0.0, length, spurious)
        t_sp = rng.uniform(edges[-1] - 6.0, edges[0] + 6.0, spurious)
        st = np.concatenate([st, np.stack([s_sp, t_sp], axis=1)])
    for _ in range(blobs):
        c = np.array([rng.uniform(0.0, length), rng.uniform(edges[-1], edges[0])])
        blob = c + rng.uniform(-1.0, 1.0, (40, 2)) * np.array([1.0, 0.5])
        st = np.concatenate([st, blob])

    s_pts, t_pts = st[:, 0], st[:, 1]
    keep = (s_pts >= 0.0) & (s_pts <= length)
    s_pts, t_pts = s_pts[keep], t_pts[keep]
    px = np.interp(s_pts, s_fine, xy[:, 0]) + np.interp(s_pts, s_fine, normal[:, 0]) * t_pts
    py = np.interp(s_pts, s_fine, xy[:, 1]) + np.interp(s_pts, s_fine, normal[:, 1]) * t_pts
    pz = np.interp(s_pts, s_fine, z_fine) + 0.025 * t_pts
    xyz = np.stack([px, py, pz], axis=1) + rng.normal(0.0, noise, (len(s_pts), 3))

    scan_step = 2.5
    n_scans = int(length / scan_step) + 1
    scan = np.clip(((s_pts - rng.uniform(5.0, 60.0, len(s_pts))) / scan_step).astype(int), 0, n_scans - 1)
    if gnss_noise > 0:
        xyz += rng.normal(0.0, gnss_noise, (n_scans, 3))[scan]
    order = np.lexsort((xyz[:, 0], scan))
    xyz, scan = xyz[order], scan[order]

    s_scan = np.arange(n_scans) * scan_step
    t_scan = np.full(n_scans, ego_t)
    if lane_change_at is not None:
        t_scan -= lane_widths[ego_lane] * smoothstep((s_scan - lane_change_at) / 100.0)
    ex = np.interp(s_scan, s_fine, xy[:, 0]) + np.interp(s_scan, s_fine, normal[:, 0]) * t_scan
    ey = np.interp(s_scan, s_fine, xy[:, 1]) + np.interp(s_scan, s_fine, normal[:, 1]) * t_scan
    heading = np.arctan2(-np.interp(s_scan, s_fine, normal[:, 0]), np.interp(s_scan, s_fine, normal[:, 1]))
    poses = np.tile(np.eye(4), (n_scans, 1, 1))
    poses[:, 0, 0], poses[:, 0, 1] = np.cos(heading), -np.sin(heading)
    poses[:, 1, 0], poses[:, 1, 1] = np.sin(heading), np.cos(heading)
    poses[:, 0, 3], poses[:, 1, 3] = ex, ey
    poses[:, 2, 3] = np.interp(s_scan, s_fine, z_fine)
    times = s_scan / 30.0
    planes = GroundPlanes(times, np.tile([0.0, 0.0, 1.0], (n_scans, 1)), poses[:, :3, 3].copy())
    cloud = MarkingCloud(
        xyz=xyz,
        intensity=np.full(len(xyz), 0.8, dtype=np.float32),
        scan_index=scan.astype(np.int32),
        time=times[scan],
        planes=planes,
        trajectory=Trajectory(times, poses),
        origin=GeoOrigin(),
    )
    return SynthRoad(cloud, lines, s_fine, xy, normal, z_fine, exit_lane, list(lane_widths))


def _paint(line: Line, rng: np.random.Generator, density: float, ego_t: float) -> np.ndarray:
    """(s, t) points of one line: Poisson points on its paint, thinner far from the ego lane."""
    if line.kind == "solid":
        intervals = [(line.s_start, line.s_end)]
    else:
        period = line.dash + line.gap
        k0 = np.floor((line.s_start - line.phase) / period)
        starts = line.phase + period * np.arange(k0, np.ceil((line.s_end - line.phase) / period) + 1)
        intervals = [(max(a, line.s_start), min(a + line.dash, line.s_end)) for a in starts]
    thin = float(np.clip(1.0 - abs(line.offset - ego_t) / 25.0, 0.3, 1.0))
    out = []
    for a, b in intervals:
        if b <= a:
            continue
        n = rng.poisson(density * thin * line.width * (b - a))
        s = rng.uniform(a, b, n)
        for g0, g1 in line.gaps:
            s = s[(s < g0) | (s > g1)]
        t = line.t(s) + rng.uniform(-line.width / 2, line.width / 2, len(s))
        out.append(np.stack([s, t], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2))


def polyline_distance(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of each point to a polyline (inf where its foot falls outside the line)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    ln2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    from scipy.spatial import cKDTree

    _, k = cKDTree(0.5 * (a + b)).query(points, k=min(4, len(a)))
    k = np.atleast_2d(k.T).T if k.ndim == 1 else k
    best = np.full(len(points), np.inf)
    for j in range(k.shape[1]):
        seg = k[:, j]
        f = np.einsum("ij,ij->i", points - a[seg], ab[seg]) / ln2[seg]
        foot = a[seg] + np.clip(f, 0, 1)[:, None] * ab[seg]
        d = np.linalg.norm(points - foot, axis=1)
        d = np.where((f >= -1e-6) & (f <= 1 + 1e-6), d, np.inf)
        best = np.minimum(best, d)
    return best


def model_lines(model) -> dict[int, list[np.ndarray]]:
    """World x, y polylines of each boundary (one per stretch where it is defined)."""
    ref = np.asarray(model.reference)[:, :2]
    tan = np.gradient(ref, axis=0)
    tan /= np.linalg.norm(tan, axis=1)[:, None]
    nrm = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    out: dict[int, list[np.ndarray]] = {}
    for b in model.boundaries:
        ok = np.isfinite(b.t)
        d = np.diff(np.concatenate([[0], ok.astype(int), [0]]))
        for a0, a1 in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=False):
            if a1 - a0 >= 2:
                out.setdefault(b.id, []).append(ref[a0:a1] + nrm[a0:a1] * np.asarray(b.t)[a0:a1, None])
    return out


def evaluate(model, road: SynthRoad, margin: float = 20.0) -> dict:
    """Boundary RMSE and coverage per truth line, lane count agreement, lane width bias and sigma."""
    lines = model_lines(model)
    res: dict = {"lines": {}}
    all_d = []
    for line in road.lines:
        s = np.arange(line.s_start + margin, line.s_end - margin, 1.0)
        if line.name == "exit" and road.exit_lane is not None:
            s = s[road.lane_count(s) > len(road.lane_widths)]
        if len(s) == 0:
            continue
        pts = road.line_xy(line, s)
        best = None
        for bid, parts in lines.items():
            d = np.min([polyline_distance(pts, p) for p in parts], axis=0)
            cov = d < 0.5
            if best is None or cov.mean() > best[1]:
                best = (bid, float(cov.mean()), d)
        bid, cov, d = best
        ok = d < 0.5
        rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else np.inf
        res["lines"][line.name] = {"boundary": bid, "coverage": cov, "rmse": rmse}
        all_d.append(d[ok])
    res["rmse"] = float(np.sqrt(np.mean(np.concatenate(all_d) ** 2)))
    # lane count and widths at the model stations
    ref = np.asarray(model.reference)[:, :2]
    tan = np.gradient(ref, axis=0)
    tan /= np.linalg.norm(tan, axis=1)[:, None]
    nrm = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    base = _project_base(road, ref)
    counts = np.full(len(model.s), -1)
    widths_err = []
    for sec in model.sections:
        m = (model.s >= sec.s_start) & (model.s < sec.s_end)
        counts[m] = len(sec.boundary_ids) - 1
        tb = {b.id: np.asarray(b.t) for b in model.boundaries}
        for left, right in zip(sec.boundary_ids[:-1], sec.boundary_ids[1:], strict=False):
            w = tb[left][m] - tb[right][m]
            mid = ref[m] + nrm[m] * (0.5 * (tb[left][m] + tb[right][m]))[:, None]
            tw = _truth_width(road, mid)
            ok = np.isfinite(tw) & (tw > 3.0) & ~_in_taper(road, _project_base(road, mid), margin)
            widths_err.append(w[ok] - tw[ok])
    valid = np.isfinite(base) & (base > margin) & (base < road.s[-1] - margin)
    truth = road.lane_count(np.where(valid, base, 0.0))
    if road.exit_lane is not None:
        s_a, s_b, _ = road.exit_lane
        valid &= (np.abs(base - s_a) > margin) & (np.abs(base - s_b) > margin)
    res["lane_count_ok"] = float(np.mean(counts[valid] == truth[valid]))
    we = np.concatenate(widths_err) if widths_err else np.zeros(0)
    res["width_bias"] = float(np.mean(we)) if len(we) else np.nan
    res["width_sigma"] = float(np.std(we)) if len(we) else np.nan
    return res


def _in_taper(road: SynthRoad, s: np.ndarray, margin: float) -> np.ndarray:
    """Base stations where the added lane is opening or closing (its width changes)."""
    if road.exit_lane is None:
        return np.zeros(len(s), dtype=bool)
    s_a, s_b, taper = road.exit_lane
    return ((s > s_a - margin) & (s < s_a + taper + margin)) | (
        (s > s_b - taper - margin) & (s < s_b + margin)
    )


def _project_base(road: SynthRoad, xy: np.ndarray) -> np.ndarray:
    """Base-centreline station of each point."""
    from scipy.spatial import cKDTree

    _, k = cKDTree(road.xy).query(xy)
    return road.s[k]


def _truth_width(road: SynthRoad, xy: np.ndarray) -> np.ndarray:
    """Width of the truth lane holding each point (NaN outside the carriageway)."""
    from scipy.spatial import cKDTree

    _, k = cKDTree(road.xy).query(xy)
    s = road.s[k]
    t = np.einsum("ij,ij->i", xy - road.xy[k], road.normal[k])
    offs = []
    for line in road.lines:
        o = line.t(s)
        o = np.where((s >= line.s_start) & (s <= line.s_end), o, np.nan)
        offs.append(o)
    offs = np.array(offs)
    out = np.full(len(xy), np.nan)
    for i in range(len(xy)):
        o = np.sort(offs[:, i][np.isfinite(offs[:, i])])[::-1]
        for a, b in zip(o[:-1], o[1:], strict=False):
            if a >= t[i] >= b:
                out[i] = a - b
                break
    return out
