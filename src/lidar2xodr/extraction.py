"""Stage 1 (paper Sec. III-B): lane-marking points from every scan, accumulated in one world frame.

Per scan, in the vehicle frame (`filter_scan`): crop to the maximum range, to `lateral_crop_m`
left and right, and below the sensor mount height; fit the ground plane with a seeded,
vectorised RANSAC; keep the road band from `ground_below_m` below the ground to
`ground_margin_m` (paper: 0.15 m) above it; keep the paint. Then move the points into the world
frame: with poses, each point at its own time (SLERP rotation, linear translation: motion
compensation), else with LiDAR odometry (`odometry.py`). Finally the trails of moving objects
are removed (`moving_object_mask`, ours) and a radius outlier removal (paper: fewer than 4
neighbours within 0.5 m) cleans the accumulated cloud.

Decisions beyond the paper:
- Ground: the scan's plane is fitted to points within `ransac_range_m`, with normals within
  `ransac_max_tilt_deg` of vehicle z, hypotheses drawn from and scored on the points within
  `ground_prior_m` of the vehicle's road level, and planes passing farther from the vehicle
  origin rejected (the origin is on the road). Beyond `ransac_range_m`, `ground_rings` range
  rings get planes of their own (`ground_heights`): one plane to 200 m lost far paint on crests
  and let far embankments in. A scan where no plane is found falls back to z = 0 (counted).
- Paint (`auto_threshold`, `auto_method`): 'local' (default) judges every bright point against
  the road surface around it (`local_paint_mask`): a robust outlier in intensity, on a flat
  surface. Intensity falling with range, lasers calibrated differently, and bright, rough verges
  need no sensor model; the real aiMotive night drive (dashes 0.33 on 0.17 asphalt, verge
  0.3..0.5) is what no single threshold separates. Points with no road surface around them (far
  range, where dark asphalt no longer returns) are judged by the fixed `reflectivity_threshold`.
  'drive' is the former per-drive threshold from the first `auto_threshold_scans` scans:
  max(Otsu, median + `auto_threshold_mad_k` robust sigmas). `auto_threshold: false` is the
  paper: the fixed threshold (50 %) everywhere.
- Moving objects (`moving_object_mask`): a bright vehicle driving with the ego left a false lane
  line on simple_highway (380 points 0.14-0.42 m above the road, from 33 scans: 70 m ahead the
  40-80 m ring plane was refitted on 120 points of which 41 were the car's rear, which raised
  the ground 0.3 m there; dark asphalt returns little that far). Paint is re-observed as the
  sensor approaches; a vehicle's trail is seen once per spot and advances with time: transient
  points that move like one object over 3+ scans are tracked and removed, thin trails along a
  line (a spinning sensor's ring sliding along it) stay. 0.1-0.3 s per million points.
- Scans whose per-point time windows overlap (aiMotive: 100 ms revolutions every 66.7 ms) carry
  the same returns twice; points not newer than the previous scan's last point are not
  accumulated again (the local test still sees the whole revolution).
- Streaming: only the marking points (and, while a per-drive threshold is unknown, the ground
  band) are kept; memory does not grow with the drive beyond the marking cloud. Reading,
  `filter_scan` and GNSS placement are pure and seeded per scan, so `workers` (default 'auto':
  the CPUs this process may use, at most 8) processes read, filter and place whole scans (fork,
  8 consecutive scans per task) and the parent takes them in recording order: the same bytes as
  one process. Odometry stays in the parent (it is sequential).
- Speed (10 km demo drive, default sensor, 4303 scans, 38 M points, on the shared 2-core machine
  with other work beside it): 2.6 ms per scan in one process (paint test 1.3 ms, most of it the
  k-nearest query; ground plane 0.4; reading 0.3; placement 0.1); `extract` 6.6-6.9 s = 62-65x
  real time with 2 workers (the whole command 7.6-7.8 s = 55x), 12.8 s = 33x with 1. With the
  simulator's roadside scenery (57 M points) 46-50x. numpy loops over rows of 3 when it
  broadcasts onto (N, 3) points, reduces or copies them row-wise (5-10x slower than by column):
  the hot paths work by column or through BLAS products.
"""

from __future__ import annotations

import os
import time as _time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lidar2xodr.config import ExtractionConfig
from lidar2xodr.data import GeoOrigin, GroundPlanes, MarkingCloud, Scan, Trajectory
from lidar2xodr.datasets.base import Dataset, ReadStats, ScanFileDataset
from lidar2xodr.errors import InputError


@dataclass
class ExtractionReport:
    """What happened, for the command's summary line and for benchmarks.

    `threshold`: the fixed or per-drive threshold; with the local test, the median over scans of
    the median local threshold the accepted paint passed. `moving_removed` points in
    `moving_trails` trails of moving objects were removed (before the outlier removal, whose count
    excludes them); `marking_points_raw` counts both.
    """

    scans_total: int = 0
    scans_used: int = 0
    bad_scans: list[tuple[str, str]] = field(default_factory=list)
    empty_scans: int = 0
    points_read: int = 0
    dropped_points: int = 0
    ground_fallbacks: int = 0
    band_points: int = 0
    marking_points_raw: int = 0
    outliers_removed: int = 0
    moving_removed: int = 0
    moving_trails: int = 0
    marking_points: int = 0
    threshold: float = 0.0
    threshold_auto: bool = False
    odometry: str = ""
    start_speed_mps: float | None = None
    drive_length_m: float = 0.0
    duration_s: float = 0.0
    wall_s: float = 0.0
    warnings: list[str] = field(default_factory=list)


# --- per-scan filters -------------------------------------------------------------------------


def fit_ground_plane(
    xyz: np.ndarray, cfg: ExtractionConfig, rng: np.random.Generator, max_offset: float | None = None
) -> tuple[np.ndarray, float] | None:
    """Seeded RANSAC plane (n, d) with n . p + d = 0, n up; all hypotheses scored at once.

    `ransac_iterations` triples are drawn together; each is scored by its inliers among
    `ransac_sample_points` random points; the best is refined twice by least squares (the
    smallest eigenvector of the inliers' scatter) on its inliers among up to 4 x
    `ransac_sample_points` random points. With `max_offset` (vehicle frame: the origin is on the
    road) triples are drawn from, and scored on, the points within that height of the origin, and
    planes passing farther from it are rejected: on a motorway with embankments, guard rails and
    vegetation only a fifth of the low points are road, and hypotheses scored on all of them
    often settle on a slope, or on a plane crossing road and slope. None when fewer than 3 points
    or no hypothesis is level enough.
    """
    if len(xyz) < 3:
        return None
    cos_tilt = np.cos(np.radians(cfg.ransac_max_tilt_deg))
    seeds = xyz
    if max_offset is not None:
        near = np.compress(np.abs(xyz[:, 2]) < max_offset, xyz, axis=0)
        seeds = near if len(near) >= 3 else xyz
    m = min(len(seeds), cfg.ransac_sample_points)
    sample_t = (seeds.take(rng.integers(0, len(seeds), size=m), axis=0) if m < len(seeds) else seeds).T.copy()
    tri = seeds.take(rng.integers(0, len(seeds), size=(cfg.ransac_iterations, 3)), axis=0)
    a, b = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                         a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n = n / np.where(ok, norm, 1.0)[:, None]
    n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
    ok &= n[:, 2] >= cos_tilt
    d = -np.einsum("ij,ij->i", n, tri[:, 0])
    if max_offset is not None:
        ok &= np.abs(d) <= max_offset
    if not ok.any():
        return None
    dist = n @ sample_t
    dist += d[:, None]
    np.abs(dist, out=dist)
    score = np.count_nonzero(dist < cfg.ransac_distance_m, axis=1)
    score[~ok] = -1
    best = int(np.argmax(score))
    normal, offset = n[best], float(d[best])
    cap = 4 * cfg.ransac_sample_points
    refine = xyz if len(xyz) <= cap else xyz.take(rng.integers(0, len(xyz), size=cap), axis=0)
    for _ in range(2):
        inl = np.compress(np.abs(refine @ normal + offset) < cfg.ransac_distance_m, refine, axis=0)
        if len(inl) < 3:
            break
        c, cand = _plane_fit(inl)
        if cand[2] < cos_tilt or (max_offset is not None and abs(cand @ c) > max_offset):
            break
        normal, offset = cand, float(-cand @ c)
    return normal, offset


def _plane_fit(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and upward unit normal of the least-squares plane: the scatter's smallest eigenvector.

    Sums as BLAS products (a mean over the rows of an (N, 3) array is 20x slower).
    """
    c = np.ones(len(pts)) @ pts / len(pts)
    _, vec = np.linalg.eigh(pts.T @ pts / len(pts) - np.outer(c, c))
    return c, (vec[:, 0] if vec[2, 0] >= 0 else -vec[:, 0])


def estimate_mount(xyz: np.ndarray, max_range_m: float = 200.0) -> np.ndarray:
    """T_vehicle_sensor of a sensor of unknown mount: levelled on the ground plane, yaw kept, at its height.

    Used by readers whose points are in the sensor frame without calibration: the sensor is
    assumed roughly level (within 15 deg), facing forward, above the vehicle origin.
    """
    cfg = ExtractionConfig()
    r = np.linalg.norm(xyz[:, :2], axis=1)
    near = xyz[(r < min(cfg.ransac_range_m, max_range_m)) & (r > 1.0)]
    low = near[near[:, 2] <= np.percentile(near[:, 2], 50)] if len(near) > 100 else near
    plane = fit_ground_plane(low, cfg, np.random.default_rng(cfg.seed))
    if plane is None:
        raise InputError("first scan", "cannot find the ground to estimate the sensor mount")
    n, d = plane
    rot, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [n])
    T = np.eye(4)
    T[:3, :3] = rot.as_matrix()
    T[2, 3] = d  # distance of the sensor origin above the plane (n . 0 + d)
    return T


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of values in 0..1 (maximal between-class variance of a 256-bin histogram)."""
    hist, edges = np.histogram(values, bins=bins, range=(0.0, 1.0))
    centres = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(hist).astype(np.float64)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    return float(edges[int(np.argmax(w0 * w1 * (mu0 - mu1) ** 2)) + 1])


def auto_threshold(values: np.ndarray, mad_k: float) -> float:
    """Per-drive marking threshold from road-band intensities: max(Otsu, median + k * 1.4826 * MAD).

    Otsu separates asphalt from paint when the histogram is bimodal (simulated drives, calibrated
    sensors). Real roads add a third, middle mode (shoulders, vegetation, worn asphalt: aiMotive
    night drive: asphalt ~0.2, shoulder ~0.37, paint 0.5..1), where Otsu falls between asphalt and
    shoulder; the robust floor treats paint as what it is, a bright outlier of the road surface
    (aiMotive: 0.50). Without paint in view it still keeps only the road's outliers, which the
    radius outlier removal then thins out.
    """
    med = float(np.median(values))
    sigma = 1.4826 * float(np.median(np.abs(values - med)))
    return float(np.clip(max(otsu_threshold(values), med + mad_k * sigma), 0.0, 1.0))


def radius_outliers(xyz: np.ndarray, radius: float, min_neighbors: int, workers: int = 1) -> np.ndarray:
    """Mask of points with at least `min_neighbors` other points within `radius` (scipy cKDTree).

    Points that share a grid cell of edge radius / sqrt(3) with `min_neighbors` others have them
    within `radius` (the cell's diagonal); two such grids, offset by half a cell, settle ~98 % of
    an accumulated cloud of dense paint without a query. The rest get a k-nearest query with an
    upper bound ("are there k neighbours", 5x faster than ball counts here) on `workers` threads;
    with more than one worker the tree is built in a thread while the cells are counted.
    """
    if len(xyz) == 0:
        return np.zeros(0, dtype=bool)
    if min_neighbors <= 0:
        return np.ones(len(xyz), dtype=bool)
    cell = radius / np.sqrt(3.0) * (1.0 - 1e-9)

    def dense() -> np.ndarray:
        return _dense_cells(xyz, cell, min_neighbors + 1, 0.0) | _dense_cells(xyz, cell, min_neighbors + 1, 0.5)

    tree = None
    if workers > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(1) as ex:
            building = ex.submit(cKDTree, xyz, balanced_tree=False, compact_nodes=False)
            keep = dense()
            tree = building.result()
    else:
        keep = dense()
    rest = np.flatnonzero(~keep)
    if len(rest):
        tree = tree if tree is not None else cKDTree(xyz, balanced_tree=False, compact_nodes=False)
        dist, _ = tree.query(xyz.take(rest, axis=0), k=[min_neighbors + 1], distance_upper_bound=radius,
                             workers=workers)
        keep[rest] = np.isfinite(dist[:, 0])
    return keep


def _dense_cells(xyz: np.ndarray, cell: float, count: int, offset: float) -> np.ndarray:
    """Mask of points in grid cells (edge `cell`, origin shifted by `offset` cells) holding at least `count` points.

    Column by column: numpy loops over rows of 3 (broadcasts, reductions along a row) cost 5-10x more.
    """
    i, j, k = (np.floor((xyz[:, c] - xyz[:, c].min()) * (1.0 / cell) + offset).astype(np.int64) for c in range(3))
    nj, nk = int(j.max()) + 1, int(k.max()) + 1
    if float(i.max() + 1) * nj * nk < 2.0**62:
        _, inv, cnt = np.unique((i * nj + j) * nk + k, return_inverse=True, return_counts=True)
    else:
        _, inv, cnt = np.unique(np.column_stack([i, j, k]), axis=0, return_inverse=True, return_counts=True)
    return cnt[inv.reshape(-1)] >= count


# --- moving objects ---------------------------------------------------------------------------


@dataclass
class _Grid:
    """The cloud's points sorted by xy cell: `order` (point indices), `keys` (their cell keys, sorted),
    `key` (every point's cell key) and `row` (key step of one cell in x)."""

    order: np.ndarray
    keys: np.ndarray
    key: np.ndarray
    row: int

    def near(self, points: np.ndarray) -> np.ndarray:
        """Indices of the points in the cells of `points` and their 8 neighbours (cells wrap at the
        grid's edge in y, which only adds points)."""
        step = np.array([-1, 0, 1])
        offsets = (step[:, None] * self.row + step[None, :]).ravel()
        want = np.unique(np.unique(self.key[points])[:, None] + offsets[None, :])
        lo, hi = np.searchsorted(self.keys, want, "left"), np.searchsorted(self.keys, want, "right")
        count = hi - lo
        pos = np.repeat(lo - np.cumsum(count) + count, count) + np.arange(int(count.sum()))
        return self.order[pos]


def _transient(xyz: np.ndarray, scan: np.ndarray, voxel: float, max_scans: int) -> tuple[np.ndarray, _Grid]:
    """`transient_mask` and the grid it sorted."""
    i = np.floor(xyz[:, 0] * (1.0 / voxel)).astype(np.int64)
    j = np.floor(xyz[:, 1] * (1.0 / voxel)).astype(np.int64)
    i -= i.min()
    j -= j.min()
    row = int(j.max()) + 3
    key = i * row + j + 1
    order = np.argsort(key, kind="stable")
    k, s = key[order], scan[order]
    if len(s) > 1 and np.any(np.diff(s) < 0):
        sub = np.lexsort((s, k))
        order, k, s = order[sub], k[sub], s[sub]
    new_cell = np.empty(len(k), dtype=bool)
    new_cell[0] = True
    np.not_equal(k[1:], k[:-1], out=new_cell[1:])
    new_scan = new_cell.copy()
    new_scan[1:] |= s[1:] != s[:-1]
    cell = np.cumsum(new_cell) - 1
    scans = np.bincount(cell, weights=new_scan)
    out = np.empty(len(k), dtype=bool)
    out[order] = scans[cell] <= max_scans
    return out, _Grid(order, k, key, row)


def transient_mask(xyz: np.ndarray, scan: np.ndarray, voxel: float, max_scans: int) -> np.ndarray:
    """Mask of points whose xy cell (edge `voxel`) holds points of at most `max_scans` distinct scans.

    One stable sort by cell: within a cell the points stay in input order, so with the cloud in
    recording order the scan changes between neighbours count the distinct scans.
    """
    if len(xyz) == 0:
        return np.zeros(0, dtype=bool)
    return _transient(xyz, scan, voxel, max_scans)[0]


def time_quantum(time: np.ndarray, scan: np.ndarray) -> float:
    """0 when the points carry their own times; the median scan interval when every point of a scan
    carries the scan's time (the motion within a sweep is then unresolved)."""
    if len(time) == 0:
        return 0.0
    if np.all(scan[1:] >= scan[:-1]):
        s, t = scan, time
    else:
        order = np.argsort(scan, kind="stable")
        s, t = scan[order], time[order]
    first = np.flatnonzero(np.r_[True, s[1:] != s[:-1]])
    if np.any(np.maximum.reduceat(t, first) > np.minimum.reduceat(t, first)):
        return 0.0
    return float(np.median(np.diff(t[first]))) if len(first) > 1 else 0.0


_Motion = tuple[float, np.ndarray]  # reference time, (degree + 1, 2) polynomial in t - reference


def _motion_fit(p: np.ndarray, t: np.ndarray, degree: int = 1) -> _Motion:
    """Least-squares polynomial motion p(t) (degree 1: constant velocity) about the mean time."""
    tm = float(t.mean())
    coef = np.linalg.lstsq(np.vander(t - tm, degree + 1, increasing=True), p, rcond=None)[0]
    return tm, coef


def _motion_residuals(p: np.ndarray, t: np.ndarray, model: _Motion
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets of the points from the model's position at their time, along and across its motion
    there, and its speed there."""
    tm, coef = model
    dt = t - tm
    res = p - np.vander(dt, len(coef), increasing=True) @ coef
    vel = np.broadcast_to(coef[1], res.shape) + (2.0 * dt[:, None] * coef[2] if len(coef) > 2 else 0.0)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    u = vel / np.maximum(speed, 1e-9)[:, None]
    return res[:, 0] * u[:, 0] + res[:, 1] * u[:, 1], res[:, 1] * u[:, 0] - res[:, 0] * u[:, 1], speed


def moving_object_mask(xyz: np.ndarray, time: np.ndarray, scan: np.ndarray, cfg: ExtractionConfig
                       ) -> tuple[np.ndarray, int]:
    """Mask of accumulated marking points that belong to moving objects, and the number of trails.

    Paint is static: as the sensor approaches, every spot of it is seen again and again. A
    vehicle is somewhere else at every instant: its points (the low, bright rear of a car driving
    with the ego, 0.15-0.5 m above the road where a far ground plane rose with it; licence plates
    and reflectors at night) leave a trail whose every spot only one or two scans saw, and whose
    position advances with time.
    1. Transient points: their `moving_voxel_m` cell holds points of at most `moving_max_scans`
       scans (`transient_mask`). Only these can ever be removed, so paint that is re-observed
       stays whatever else happens.
    2. Blobs: transient points within `moving_link_m` (xy) and `moving_pair_s` of each other,
       linked. A blob that spans `moving_min_scans` scans (an object a forward sensor hits all
       through its sweep) is a seed candidate, and so are three blobs one after the other that
       move like one object (`_blob_triples`: an object a spinning sensor hits in a few ms per
       revolution jumps from scan to scan).
    3. Seeds: a candidate whose constant-velocity fit in space-time (positions against per-point
       times, trimmed at 3 sigma) moves at `moving_min_speed_mps` or more over
       `moving_min_travel_m` or more, with an RMS along the motion of at most `moving_seed_rms_m`,
       over `moving_min_scans` scans. A rear face is thin along its motion (simple_highway: 0.04
       m at 30 m/s); static paint seen through a detection window (near range of a forward
       sensor, the first scan's near edge, the last scan's far edge) scatters by the window's
       depth (0.4-1.6 m measured), and far sparse paint has no common velocity at all.
    4. Tracking (`_track`, `_fill`): a seed grows forward and backward in time by the transient
       points within `moving_gate_m` along and `moving_half_width_m` across its motion of where
       the motion refitted on its newest `moving_fit_window_s` puts it at their time, until none
       joins for `moving_max_gap_s`: the trail is followed through curves and detection gaps.
    5. Veto: one ring of a spinning sensor meets a painted line at a spot that moves along it with
       the ego, seen once per spot like a trail (aiMotive: 13 points on the far carriageway's
       line, 0.025 m RMS across their motion, 69 % of them beside points of 2 other scans). A
       trail narrower than `moving_min_width_m` RMS across its motion (a line 0.1-0.3 m wide:
       0.03-0.09 m; a vehicle's face or licence plate: 0.14-0.6 m measured), or of which
       `moving_on_paint_share` or more of the points lie on re-observed paint
       (`_on_paint_share`; vehicles: 21 % at most, measured), stays. A vehicle drives between
       the lines.
    Without per-point times (`time_quantum` > 0) a vehicle's points spread along the motion by
    the distance it drives during a sweep: both tolerances widen accordingly, and paint seen
    through a forward window shallower than ~2 m may then pass for a trail. Objects slower than
    `moving_voxel_m` per scan (10 m/s at 10 Hz) leave cells that three or more scans saw and are
    only partly removed; slower than `moving_min_speed_mps` not at all. Deterministic (no random
    choice); one sort of the cloud (0.1 s per million points), the rest works on the transient
    points.
    """
    out = np.zeros(len(xyz), dtype=bool)
    if not cfg.moving_filter or len(xyz) < cfg.moving_min_scans:
        return out, 0
    transient, grid = _transient(xyz, scan, cfg.moving_voxel_m, cfg.moving_max_scans)
    cand = np.flatnonzero(transient)
    if len(cand) < cfg.moving_min_scans:
        return out, 0
    quantum = time_quantum(time, scan)
    cand = cand[np.argsort(time[cand], kind="stable")]
    cxy, ct, cs = _xy_at(xyz, cand), time[cand] - float(time.min()), scan[cand]
    comp, n_comp = _blobs(cxy, ct, cfg)
    by_comp = np.lexsort((cs, comp))
    cc, cx = comp[by_comp], cs[by_comp]
    first = np.r_[True, (cc[1:] != cc[:-1]) | (cx[1:] != cx[:-1])]
    scans_per_comp = np.bincount(cc, weights=first, minlength=n_comp)
    bounds = np.searchsorted(cc, np.arange(n_comp + 1))
    size = np.diff(bounds)
    centre = np.column_stack([np.bincount(comp, cxy[:, c], n_comp) for c in (0, 1)]) / size[:, None]
    mean_t = np.bincount(comp, ct, n_comp) / size
    groups = [np.array([c]) for c in np.flatnonzero(scans_per_comp >= cfg.moving_min_scans)]
    groups += list(_blob_triples(centre, mean_t, size, cfg, quantum))
    owner = np.zeros(len(cand), dtype=np.int32)  # 0 free, k > 0 trail k, -1 a vetoed trail
    trails = 0
    for group in groups:
        idx = np.sort(np.concatenate([by_comp[bounds[c]:bounds[c + 1]] for c in group]))
        if owner[idx].any():
            continue
        seed = _seed(cxy[idx], ct[idx], cs[idx], cfg, quantum)
        if seed is None:
            continue
        label = trails + 1
        members = idx[seed]
        owner[members] = label
        for sign in (1.0, -1.0):
            members = _track(members, cxy, ct, owner, label, sign, cfg, quantum)
        _fill(members, cxy, ct, owner, label, cfg, quantum)
        trail = np.flatnonzero(owner == label)
        if (_trail_width(trail, cxy, ct, cfg) < cfg.moving_min_width_m
                or _on_paint_share(cand[trail], grid, xyz, scan, cfg) >= cfg.moving_on_paint_share):
            owner[trail] = -1
        else:
            trails += 1
    out[cand[owner > 0]] = True
    return out, trails


def _blobs(xy: np.ndarray, t: np.ndarray, cfg: ExtractionConfig) -> tuple[np.ndarray, int]:
    """Component labels of the points linked within `moving_link_m` (xy) and `moving_pair_s`: one
    tree query in space-time (time scaled to the link), then the exact test."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    scale = cfg.moving_link_m / cfg.moving_pair_s
    pairs = cKDTree(np.column_stack([xy, t * scale])).query_pairs(cfg.moving_link_m * np.sqrt(2.0),
                                                                  output_type="ndarray")
    d = xy[pairs[:, 0]] - xy[pairs[:, 1]]
    pairs = pairs[(np.hypot(d[:, 0], d[:, 1]) <= cfg.moving_link_m)
                  & (np.abs(t[pairs[:, 0]] - t[pairs[:, 1]]) <= cfg.moving_pair_s)]
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(xy),) * 2)
    n, comp = connected_components(graph, directed=False)
    return comp, int(n)


def _on_paint_share(points: np.ndarray, grid: _Grid, xyz: np.ndarray, scan: np.ndarray,
                    cfg: ExtractionConfig) -> float:
    """Share of a trail's `points` that lie on re-observed paint: other points (not of the trail) of
    at least `moving_paint_min_scans` scans within `moving_paint_radius_m` (< the grid's cell).
    A following car crossing the same spots adds one scan; a painted line, seen again and again,
    more."""
    near = grid.near(points)
    near = near[~np.isin(near, points)]
    if len(near) < cfg.moving_paint_min_scans:
        return 0.0
    k = min(16, len(near))
    dist, nb = cKDTree(_xy_at(xyz, near)).query(_xy_at(xyz, points), k=k,
                                                 distance_upper_bound=cfg.moving_paint_radius_m)
    found = np.isfinite(dist.reshape(len(points), k))
    scans = np.where(found, scan[near[np.minimum(nb.reshape(len(points), k), len(near) - 1)]], -1)
    scans = np.sort(scans, axis=1)
    new = scans >= 0
    new[:, 1:] &= scans[:, 1:] != scans[:, :-1]
    return float(np.mean(new.sum(axis=1) >= cfg.moving_paint_min_scans))


def _trail_width(trail: np.ndarray, xy: np.ndarray, t: np.ndarray, cfg: ExtractionConfig) -> float:
    """RMS offset of a trail's points across its motion (refitted on every half fit window, like `_fill`)."""
    half = 0.5 * cfg.moving_fit_window_s
    tt = t[trail]
    across = np.zeros(len(trail))
    for a in np.arange(float(tt.min()), float(tt.max()) + 1e-9, half):
        here = (tt >= a) & (tt <= a + half)
        near = np.abs(tt - (a + 0.5 * half)) <= half
        if not here.any() or np.ptp(tt[near]) <= 0.0:
            continue
        curved = near.sum() >= 6 and np.ptp(tt[near]) >= half
        model = _motion_fit(xy[trail[near]], tt[near], 2 if curved else 1)
        across[here] = _motion_residuals(xy[trail[here]], tt[here], model)[1]
    return float(np.sqrt(np.mean(across**2)))


def _blob_triples(centre: np.ndarray, mean_t: np.ndarray, size: np.ndarray, cfg: ExtractionConfig,
                  quantum: float) -> np.ndarray:
    """(k, 3) ids of blobs A, B, C, later in this order, each within `moving_pair_s` of the one
    before, moving from A to B at a speed between `moving_min_speed_mps` and
    `moving_max_speed_mps`, and C where that velocity puts B at C's time (`moving_gate_m` along,
    `moving_half_width_m` across). Pairs come from one tree query in space-time (time scaled by the
    largest speed); blobs of one point are left out.
    """
    ok = np.flatnonzero(size >= 2)
    empty = np.zeros((0, 3), dtype=np.int64)
    if len(ok) < 3:
        return empty
    vmax, dt_max = cfg.moving_max_speed_mps, cfg.moving_pair_s
    st = np.column_stack([centre[ok], mean_t[ok] * vmax])
    pr = cKDTree(st).query_pairs(vmax * dt_max * np.sqrt(2.0), output_type="ndarray")
    if len(pr) == 0:
        return empty
    a, b = ok[pr[:, 0]], ok[pr[:, 1]]
    swap = mean_t[a] > mean_t[b]
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    dt = mean_t[b] - mean_t[a]
    speed = np.hypot(*(centre[b] - centre[a]).T) / np.maximum(dt, 1e-9)
    sel = (dt > 0) & (dt <= dt_max) & (speed >= cfg.moving_min_speed_mps) & (speed <= vmax)
    a, b = a[sel], b[sel]
    order = np.lexsort((b, a))
    a, b = a[order], b[order]
    lo, hi = np.searchsorted(a, b, "left"), np.searchsorted(a, b, "right")
    count = hi - lo
    if count.sum() == 0:
        return empty
    first = np.repeat(np.arange(len(a)), count)
    second = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count) + np.repeat(lo, count)
    ta, tb, tc = a[first], b[first], b[second]
    v = (centre[tb] - centre[ta]) / (mean_t[tb] - mean_t[ta])[:, None]
    err = centre[tc] - centre[tb] - v * (mean_t[tc] - mean_t[tb])[:, None]
    sp = np.hypot(v[:, 0], v[:, 1])
    along = (err[:, 0] * v[:, 0] + err[:, 1] * v[:, 1]) / sp
    across = (err[:, 1] * v[:, 0] - err[:, 0] * v[:, 1]) / sp
    fit = (np.abs(along) <= cfg.moving_gate_m + 0.5 * sp * quantum)
    fit &= np.abs(across) <= cfg.moving_half_width_m
    return np.column_stack([ta[fit], tb[fit], tc[fit]])


def _seed(p: np.ndarray, t: np.ndarray, s: np.ndarray, cfg: ExtractionConfig, quantum: float
          ) -> np.ndarray | None:
    """Mask of the points of a candidate that move like one object (see `moving_object_mask`), or None."""
    keep = np.ones(len(p), dtype=bool)
    along = np.zeros(len(p))
    for _ in range(3):
        model = _motion_fit(p[keep], t[keep])
        along = _motion_residuals(p, t, model)[0]
        keep = np.abs(along) <= max(3.0 * float(np.sqrt(np.mean(along[keep] ** 2))), 0.1)
        if keep.sum() < cfg.moving_min_scans:
            return None
    speed = float(np.hypot(*model[1][1]))
    rms = float(np.sqrt(np.mean(along[keep] ** 2)))
    if (speed < cfg.moving_min_speed_mps or speed * float(np.ptp(t[keep])) < cfg.moving_min_travel_m
            or rms > cfg.moving_seed_rms_m + speed * quantum / np.sqrt(12.0)
            or len(np.unique(s[keep])) < cfg.moving_min_scans):
        return None
    return keep


def _gated(xy: np.ndarray, t: np.ndarray, model: _Motion, cfg: ExtractionConfig, quantum: float
           ) -> np.ndarray:
    """Mask of the points within `moving_gate_m` along and `moving_half_width_m` across the motion of
    where the model puts the object at their time."""
    along, across, speed = _motion_residuals(xy, t, model)
    return (np.abs(along) <= cfg.moving_gate_m + 0.5 * speed * quantum) & (
        np.abs(across) <= cfg.moving_half_width_m)


def _track(members: np.ndarray, xy: np.ndarray, t: np.ndarray, owner: np.ndarray, label: int,
           sign: float, cfg: ExtractionConfig, quantum: float) -> np.ndarray:
    """Grow a trail in time (`sign` +1 forward, -1 backward) by the free points that its motion
    predicts (`t` sorted), `moving_step_s` at a time from the next such point, refitting the motion
    after each step (quadratic once the recent points span half the fit window: curves, U-turns);
    gives them `label` in `owner` and returns all members."""
    while True:
        end = float(t[members].max() if sign > 0 else t[members].min())
        recent = members[np.abs(t[members] - end) <= cfg.moving_fit_window_s]
        if np.ptp(t[recent]) <= 0.0:
            recent = members
        curved = len(recent) >= 6 and np.ptp(t[recent]) >= 0.5 * cfg.moving_fit_window_s
        model = _motion_fit(xy[recent], t[recent], 2 if curved else 1)
        if sign > 0:
            lo, hi = np.searchsorted(t, end, "right"), np.searchsorted(t, end + cfg.moving_max_gap_s, "right")
        else:
            lo, hi = np.searchsorted(t, end - cfg.moving_max_gap_s, "left"), np.searchsorted(t, end, "left")
        window = np.arange(lo, hi)
        window = window[owner[window] == 0]
        if len(window) == 0:
            return members
        join = window[_gated(xy[window], t[window], model, cfg, quantum)]
        if len(join) == 0:
            return members
        near = t[join[0]] if sign > 0 else t[join[-1]]
        join = join[np.abs(t[join] - near) <= cfg.moving_step_s]
        owner[join] = label
        members = np.concatenate([members, join])


def _fill(members: np.ndarray, xy: np.ndarray, t: np.ndarray, owner: np.ndarray, label: int,
          cfg: ExtractionConfig, quantum: float) -> None:
    """Give `label` to the free points within a trail's time span that its motion, refitted centred on
    them (half a fit window either side, quadratic where the trail spans that), predicts: points
    that a trimmed seed fit or an extrapolating step left out."""
    half = 0.5 * cfg.moving_fit_window_s
    mt = t[members]
    t0, t1 = float(mt.min()), float(mt.max())
    for a in np.arange(t0, t1 + 1e-9, half):
        lo, hi = np.searchsorted(t, a, "left"), np.searchsorted(t, min(a + half, t1), "right")
        window = np.arange(lo, hi)
        window = window[owner[window] == 0]
        if len(window) == 0:
            continue
        near = members[np.abs(mt - (a + 0.5 * half)) <= half]
        if len(near) < 2 or np.ptp(t[near]) <= 0.0:
            continue
        curved = len(near) >= 6 and np.ptp(t[near]) >= half
        model = _motion_fit(xy[near], t[near], 2 if curved else 1)
        owner[window[_gated(xy[window], t[window], model, cfg, quantum)]] = label


def ground_heights(
    pts: np.ndarray, r: np.ndarray, plane: tuple[np.ndarray, float], cfg: ExtractionConfig
) -> np.ndarray:
    """Height of every point above the local ground: piecewise planes over range rings.

    Within `ransac_range_m` the scan's plane. Beyond it `ground_rings` rings, each twice as wide as
    the one before (40-80 m, 80-160 m, 160 m and more with the defaults), get their own plane: a
    least-squares refit, twice, of the ring's points within `ransac_distance_m` of the plane
    before it, starting from the points within `ground_ring_window_m` of it; a refit that tilts by
    more than `ransac_max_tilt_deg` from the plane before it, or rests on fewer than 30 points,
    keeps that plane. One plane to 200 m misses crests, sags and banked curves by decimetres, so
    far paint fell out of the road band and far embankments fell in.
    """
    n, d = plane
    h = pts @ n + d
    lo = cfg.ransac_range_m
    far = np.flatnonzero(r >= lo) if cfg.ground_rings else np.zeros(0, dtype=np.int64)
    if len(far) == 0:
        return h
    cos_tilt = np.cos(np.radians(cfg.ransac_max_tilt_deg))
    fp, fr, fh = pts.take(far, axis=0), r[far], h[far]
    for k in range(cfg.ground_rings):
        beyond = fr >= lo
        if not beyond.any():
            break
        ring = beyond if k == cfg.ground_rings - 1 else beyond & (fr < 2.0 * lo)
        q = np.compress(ring & (np.abs(fh) < cfg.ground_ring_window_m), fp, axis=0)
        tol = cfg.ground_ring_window_m
        for _ in range(2):
            inl = np.compress(np.abs(q @ n + d) < tol, q, axis=0)
            if len(inl) < 30:
                break
            c, cand = _plane_fit(inl)
            if cand @ n < cos_tilt:
                break
            n, d = cand, float(-cand @ c)
            tol = cfg.ransac_distance_m
        fh[beyond] = np.compress(beyond, fp, axis=0) @ n + d
        lo *= 2.0
    h[far] = fh
    return h


_CELL_BITS = 16
_BAND_M = 10.0
_BAND_QUANTILE = 0.25
_LEVELS = 256


def cell_samples(xy: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of at most one point per `cell_m` grid cell: a density-capped sample of the surface.

    Cells are hashed (Fibonacci hashing of the packed cell index) into a table of 2^16 slots: O(n),
    no sort. Cells that share a slot give it one sample between them, which only thins the sample
    (by ~5 % at the 5-8k occupied cells of a scan's road band). Indices come in point order.
    """
    i, j = (np.floor(xy[:, c] * (1.0 / cell_m)).astype(np.int64) for c in (0, 1))
    key = ((i << 32) + (j & 0xFFFFFFFF)).view(np.uint64)
    slot = ((key * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - _CELL_BITS)).astype(np.int64)
    table = np.empty(1 << _CELL_BITS, dtype=np.int32)
    order = np.arange(len(xy), dtype=np.int32)
    table[slot] = order
    return np.flatnonzero(table.take(slot) == order)


def _preselect(intensity: np.ndarray, r: np.ndarray, min_contrast: float) -> np.ndarray:
    """Points at least `min_contrast` brighter than the lower quartile of their 10 m range band.

    Only these are judged by the local test (speed). Paint can be lost here only where the road
    around it is darker than three quarters of the road at that range (the local test compares
    with the median around the point, which then lies below the band's lower quartile).
    Quartiles come from a 256-level histogram per band (one bincount, no sort).
    """
    band = np.minimum((r * (1.0 / _BAND_M)).astype(np.int64), 63)
    level = np.minimum((intensity * _LEVELS).astype(np.int64), _LEVELS - 1)
    hist = np.bincount(band * _LEVELS + level, minlength=64 * _LEVELS).reshape(64, _LEVELS)
    cum = np.cumsum(hist, axis=1)
    floor = (np.argmax(cum >= _BAND_QUANTILE * cum[:, -1:], axis=1) / _LEVELS)
    return intensity >= floor[band] + min_contrast


def _xy_at(xyz: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Contiguous (n, 2) x, y of the points `idx`, gathered by column (a take on the strided xy view
    first copies the whole view)."""
    out = np.empty((len(idx), 2))
    out[:, 0] = xyz[:, 0].take(idx)
    out[:, 1] = xyz[:, 1].take(idx)
    return out


def local_paint_mask(
    xyz: np.ndarray, intensity: np.ndarray, height: np.ndarray, r: np.ndarray, cfg: ExtractionConfig
) -> tuple[np.ndarray, float | None]:
    """Mask of paint among one scan's road-band points, and the median local threshold it passed.

    Paint is a bright outlier of the road surface around it: a point is paint when its intensity
    is at least max(`local_contrast_k` robust sigmas, `local_min_contrast`) above the median of
    its `local_neighbors` nearest surface samples (one per `local_cell_m` cell, xy distance) and
    their heights above the ground spread by at most `local_max_roughness_m` (robust sigma). The
    reference is local, so intensity falling with range, lasers of one sensor calibrated
    differently (Pandar64) and worn or wet asphalt need no per-sensor model; a bright, rough
    shoulder (grass, gravel: 0.3..0.5 on the aiMotive drive, brighter than its faint dashes) is
    not paint because its surroundings are as bright and not flat. A point whose samples reach
    farther than `local_max_radius_m` has no road around it to compare with (far range, where
    dark asphalt no longer returns and only paint does): it is judged by the fixed
    `reflectivity_threshold` (paper: 50 %), as is every point of a scan too sparse to sample.
    """
    k = cfg.local_neighbors
    fixed = intensity >= cfg.reflectivity_threshold
    reps = cell_samples(xyz[:, :2], cfg.local_cell_m)
    if len(reps) < k:
        return fixed, None
    out = np.zeros(len(xyz), dtype=bool)
    idx = np.flatnonzero(_preselect(intensity, r, cfg.local_min_contrast) | fixed)
    if len(idx) == 0:
        return out, None
    tree = cKDTree(_xy_at(xyz, reps), balanced_tree=False, compact_nodes=False)
    dist, nn = tree.query(_xy_at(xyz, idx), k=k, distance_upper_bound=cfg.local_max_radius_m)
    judged = np.isfinite(dist[:, -1])
    out[idx[~judged][intensity[idx[~judged]] >= cfg.reflectivity_threshold]] = True
    idx, nn = idx[judged], reps.take(np.compress(judged, nn, axis=0))
    around = np.sort(np.stack([intensity.take(nn), height.take(nn)]), axis=2)
    lo, hi = (k - 1) // 2, k // 2
    med = 0.5 * (around[:, :, lo] + around[:, :, hi])
    dev = np.sort(np.abs(around - med[:, :, None]), axis=2)
    spread = 1.4826 * 0.5 * (dev[:, :, lo] + dev[:, :, hi])
    thr = med[0] + np.maximum(cfg.local_contrast_k * spread[0], cfg.local_min_contrast)
    ok = (intensity[idx] >= thr) & (spread[1] <= cfg.local_max_roughness_m)
    out[idx[ok]] = True
    if not ok.any():
        return out, None
    passed = np.sort(thr[ok])
    return out, float(0.5 * (passed[(len(passed) - 1) // 2] + passed[len(passed) // 2]))


@dataclass
class ScanMarks:
    """One scan after the per-scan filters (vehicle frame): what accumulation and odometry need.

    `final` is False while a per-drive threshold is still unknown: the points are then the whole
    road band and `calib` the intensities that will set the threshold. With `pose` (the vehicle
    pose at the stamp) `xyz` is already in the world frame (GNSS placement in the worker).
    """

    index: int
    stamp: float
    t_max: float | None
    plane: tuple[np.ndarray, float]
    fell_back: bool
    band_points: int
    xyz: np.ndarray
    intensity: np.ndarray
    times: np.ndarray | None
    final: bool = True
    calib: np.ndarray | None = None
    local_threshold: float | None = None
    odo_xyz: np.ndarray | None = None
    odo_times: np.ndarray | None = None
    pose: np.ndarray | None = None


def _row_major(xyz: np.ndarray) -> np.ndarray:
    """(N, 3) points in C order; a column-major input (the drive reader's) is copied column by column.

    numpy's own layout copy loops over rows of 3 (0.11 ms for 15k points; by columns 0.015 ms).
    """
    if xyz.flags.c_contiguous:
        return xyz
    out = np.empty(xyz.shape)
    for c in range(xyz.shape[1]):
        out[:, c] = xyz[:, c]
    return out


def filter_scan(scan: Scan, cfg: ExtractionConfig, mount_z: float, max_range: float,
                threshold: float | None, odometry: bool = False) -> ScanMarks:
    """The per-scan stage: crop, ground plane, road band, marking selection (module docstring).

    Pure and seeded by (seed, scan index): scans can be filtered in any order or process.
    `threshold` is the fixed or per-drive threshold (None: not known yet; unused by 'local').
    `odometry` also returns the scan's points above the ground for LiDAR odometry.
    """
    xyz = _row_major(scan.xyz)
    x, y = xyz[:, 0], xyz[:, 1]
    r2 = x * x + y * y
    keep = (r2 < max_range * max_range) & (xyz[:, 2] < mount_z - cfg.below_sensor_margin_m)
    if cfg.lateral_crop_m is not None:
        keep &= np.abs(y) <= cfg.lateral_crop_m
    idx = np.flatnonzero(keep)
    pts = xyz.take(idx, axis=0)
    r = np.sqrt(r2[idx])
    rng = np.random.default_rng([cfg.seed, scan.index])
    plane = fit_ground_plane(np.compress(r < cfg.ransac_range_m, pts, axis=0), cfg, rng, cfg.ground_prior_m)
    fell_back = plane is None
    if plane is None:
        plane = (np.array([0.0, 0.0, 1.0]), 0.0)
    n, d = plane
    h = ground_heights(pts, r, plane, cfg)
    band = (h <= cfg.ground_margin_m) & (h >= -cfg.ground_below_m)
    sel = idx[band]
    inten = scan.intensity[sel]
    out = ScanMarks(index=scan.index, stamp=scan.stamp, t_max=None if scan.times is None else float(scan.times.max()),
                    plane=plane, fell_back=fell_back, band_points=len(sel), xyz=xyz.take(sel, axis=0), intensity=inten,
                    times=None if scan.times is None else scan.times[sel])
    if not cfg.auto_threshold or (cfg.auto_method == "drive" and threshold is not None):
        mark = inten >= (cfg.reflectivity_threshold if not cfg.auto_threshold else threshold)
    elif cfg.auto_method == "local":
        mark, out.local_threshold = local_paint_mask(out.xyz, inten, h[band], r[band], cfg)
    else:
        mark = None
        out.final = False
        out.calib = inten[r[band] < cfg.auto_threshold_range_m]
    if mark is not None:
        out.xyz, out.intensity = np.compress(mark, out.xyz, axis=0), inten[mark]
        out.times = None if out.times is None else out.times[mark]
    if odometry:
        hall = xyz @ n + d
        rr = np.sqrt(r2)
        o = (hall > cfg.odometry_min_height_m) & (rr < cfg.odometry_max_range_m) & (rr > 2.0)
        out.odo_xyz = np.compress(o, xyz, axis=0)
        out.odo_times = None if scan.times is None else scan.times[o]
    return out


class GnssPlacer:
    """Each point at its own time in the world frame from the GNSS trajectory (motion compensation).

    Rotation by SLERP, translation linear, both between the two poses around the time. Pure, so
    pool workers place their scans themselves (fork: the trajectory is inherited, never pickled);
    `check` is the parent's, on the points a scan finally keeps.
    """

    def __init__(self, traj: Trajectory, cfg: ExtractionConfig, where: str = "poses") -> None:
        if len(traj) < 2 or not np.all(np.diff(traj.times) > 0):
            raise InputError(where, "the poses need at least 2 entries with strictly increasing times")
        self.traj = traj
        self.tol = cfg.pose_time_tolerance_s
        self.rot = Rotation.from_matrix(traj.poses[:, :3, :3])
        self.step = (self.rot[:-1].inv() * self.rot[1:]).as_rotvec()
        self.dt = np.diff(traj.times)

    def check(self, stamp: float, times: np.ndarray | None, where: str) -> None:
        """InputError when the stamp or a point time lies outside the poses (beyond the tolerance)."""
        t0, t1 = self.traj.times[0], self.traj.times[-1]
        lo = hi = stamp
        if times is not None and len(times):
            lo, hi = min(lo, float(times.min())), max(hi, float(times.max()))
        if lo < t0 - self.tol or hi > t1 + self.tol:
            raise InputError(where, f"scan time {lo:.3f}..{hi:.3f} s is outside the poses' "
                             f"{t0:.3f}..{t1:.3f} s: the poses do not cover the scans")

    def place(self, stamp: float, xyz: np.ndarray, times: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The points in the world frame and the vehicle pose (4 x 4) at the stamp; times are clipped to the poses.

        Works on the few poses around the scan. SLERP as scipy's `Slerp` does it (R_i composed
        with the interval's rotation vector scaled by the time fraction), but the two rotations
        are applied to each point in turn: composing a few hundred rotations costs scipy 1.15 ten
        times more than applying them.
        """
        times_all = self.traj.times
        t = np.full(len(xyz) + 1, stamp) if times is None else np.concatenate([[stamp], times])
        np.clip(t, times_all[0], times_all[-1], out=t)
        lo = min(max(int(np.searchsorted(times_all, t.min(), "right")) - 1, 0), len(times_all) - 2)
        hi = min(int(np.searchsorted(times_all, t.max(), "left")) + 2, len(times_all))
        tw, pw = times_all[lo:hi], self.traj.positions[lo:hi]
        pos = np.column_stack([np.interp(t, tw, pw[:, j]) for j in range(3)])
        i = lo + np.clip(np.searchsorted(tw, t, "right") - 1, 0, len(tw) - 2)
        delta = Rotation.from_rotvec(self.step[i] * ((t - times_all[i]) / self.dt[i])[:, None])
        T = np.eye(4)
        T[:3, :3] = (self.rot[int(i[0])] * delta[0]).as_matrix()
        T[:3, 3] = pos[0]
        if not len(xyz):
            return xyz.reshape(0, 3), T
        return self.rot[i[1:]].apply(delta[1:].apply(xyz)) + pos[1:], T


class _PoseSource:
    """World placement: GNSS trajectory interpolation, or LiDAR odometry."""

    def __init__(self, dataset: Dataset, cfg: ExtractionConfig, mode: str) -> None:
        self.cfg = cfg
        self.mode = mode
        self.name = str(dataset.path)
        self.odo = None
        self.gnss: GnssPlacer | None = None
        if mode == "gnss":
            traj = dataset.poses()
            assert traj is not None
            self.gnss = GnssPlacer(traj, cfg, self.name)
        else:
            from lidar2xodr.odometry import LidarOdometry

            self.odo = LidarOdometry(cfg)
        self.fed = 0

    def feed(self, marks: ScanMarks) -> int:
        """Give the scan to the odometry (its points above the ground); returns how many scans have poses."""
        self.fed += 1
        if self.odo is None:
            return self.fed
        assert marks.odo_xyz is not None
        return self.odo.add(marks.stamp, marks.odo_xyz, marks.odo_times)

    def finish(self) -> int:
        return self.odo.finish() if self.odo is not None else self.fed

    def place(self, k: int, m: ScanMarks, xyz: np.ndarray, times: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The points in the world frame (each at its own time) and the vehicle pose at the scan stamp.

        Points the filter already placed (`m.pose`, GNSS) are only checked against the poses' span.
        """
        if self.odo is not None:
            return self.odo.to_world(k, xyz, times), self.odo.poses[k]
        assert self.gnss is not None
        self.gnss.check(m.stamp, times, f"{self.name} scan {m.index}")
        if m.pose is not None:
            return xyz, m.pose
        return self.gnss.place(m.stamp, xyz, times)

    def trajectory(self) -> Trajectory:
        return self.odo.trajectory if self.odo is not None else self.gnss.traj  # type: ignore[union-attr]


def _mode(dataset: Dataset, cfg: ExtractionConfig) -> str:
    has = dataset.poses() is not None
    if cfg.odometry == "gnss" and not has:
        raise InputError(dataset.path, "--odometry gnss but the drive has no poses (use auto or lidar)")
    if cfg.odometry == "lidar" or not has:
        return "lidar"
    return "gnss"


def worker_count(cfg: ExtractionConfig) -> int:
    """`workers` as a number: 'auto' = the CPUs this process may use (affinity), at most 8."""
    if cfg.workers != "auto":
        return max(1, int(cfg.workers))
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, 8))


_Result = tuple[int, float | None, ReadStats, object]
_BATCH = 8


@dataclass
class _Job:
    """Everything filtering a scan needs besides the scan; pool workers inherit it once (fork)."""

    dataset: Dataset
    cfg: ExtractionConfig
    mount_z: float
    max_range: float
    odometry: bool
    placer: GnssPlacer | None

    def filter(self, scan: Scan, threshold: float | None) -> ScanMarks:
        """`filter_scan`, then, with GNSS poses, the marking points placed in the world frame."""
        m = filter_scan(scan, self.cfg, self.mount_z, self.max_range, threshold, self.odometry)
        if self.placer is not None:
            m.xyz, m.pose = self.placer.place(m.stamp, m.xyz, m.times)
        return m

    def read_filter(self, k: int, threshold: float | None) -> _Result:
        """Read scan k and filter it, for `iter_scans`; an InputError comes back as its (where, problem)."""
        assert isinstance(self.dataset, ScanFileDataset)
        try:
            scan, stats = self.dataset.read_scan(k)
            if scan is None:
                return k, None, stats, None
            return k, scan.stamp, stats, self.filter(scan, threshold)
        except InputError as exc:
            return k, None, ReadStats(), (exc.where, exc.problem)


def _read_batch(job: _Job, ks: range, threshold: float | None) -> list[_Result]:
    return [job.read_filter(k, threshold) for k in ks]


def _filter_one(job: _Job, scan: Scan, threshold: float | None) -> ScanMarks:
    return job.filter(scan, threshold)


def _filtered(dataset: Dataset, cfg: ExtractionConfig, state: dict, odometry: bool,
              placer: GnssPlacer | None) -> Iterator[ScanMarks]:
    """`_Job.filter` over the drive, in recording order; with `workers` > 1 or a Dask scheduler in parallel.

    In parallel (`scheduler.task_runner`: a fork pool, or Dask) each worker reads, filters and
    places whole scans (`ScanFileDataset.read_scan`), `_BATCH` consecutive scans per task, so only
    the few marking points travel between processes, and few messages; the parent reads the first
    readable scan itself, since it fixes the reader's intensity scale (and an estimated mount) that
    the workers receive with the job. At most 2 tasks per worker are in flight (memory stays flat
    on long drives) and results are taken in recording order, so the output is the same bytes as
    with one process. `state` holds the threshold known when a scan is handed out (a per-drive
    threshold may still be unknown). Readers of one stream (rosbag) are read in the parent and
    filtered in parallel.
    """
    from lidar2xodr.scheduler import task_runner

    mount_z = float(dataset.sensor.mount[2, 3])
    max_range = cfg.max_range_m if cfg.max_range_m is not None else dataset.sensor.max_range_m
    job = _Job(dataset, cfg, mount_z, max_range, odometry, placer)
    workers = min(worker_count(cfg), max(1, len(dataset)))
    if workers <= 1 and cfg.scheduler is None:
        for scan in dataset:
            yield job.filter(scan, state["threshold"])
        return
    in_flight = 2 * max(workers, 1)
    if not (isinstance(dataset, ScanFileDataset) and dataset.random_access):
        window: deque = deque()
        with task_runner(job, workers, cfg.scheduler) as submit:
            for scan in dataset:
                window.append(submit(_filter_one, scan, state["threshold"]))
                if len(window) >= in_flight:
                    yield window.popleft().result()
            while window:
                yield window.popleft().result()
        return

    def checked(res: _Result) -> _Result:
        if isinstance(res[3], tuple):
            raise InputError(*res[3])
        return res

    def results() -> Iterator[_Result]:
        k, n = 0, len(dataset)
        while k < n:
            res = checked(job.read_filter(k, state["threshold"]))
            k += 1
            yield res
            if res[1] is not None:
                break
        futures: deque = deque()
        with task_runner(job, workers, cfg.scheduler) as submit:
            while k < n or futures:
                while k < n and len(futures) < in_flight:
                    futures.append(submit(_read_batch, range(k, min(k + _BATCH, n)), state["threshold"]))
                    k += _BATCH
                for res in futures.popleft().result():
                    yield checked(res)

    yield from dataset.iter_scans(results())


def extract_markings(
    dataset: Dataset,
    cfg: ExtractionConfig,
    progress: Callable[[int], None] | None = None,
    report: ExtractionReport | None = None,
) -> MarkingCloud:
    """Marking points of the whole drive in one world frame (see the module docstring).

    `progress` is called after every scan with the number of recording scans it advanced by
    (skipped, unreadable scans included, so the calls add up to `len(dataset)` at most);
    `report`, when given, is filled with counts for the summary line.
    """
    rep = report if report is not None else ExtractionReport()
    wall0 = _time.perf_counter()
    rep.scans_total = len(dataset)
    mode = _mode(dataset, cfg)
    rep.odometry = mode
    poses = _PoseSource(dataset, cfg, mode)
    local = cfg.auto_threshold and cfg.auto_method == "local"
    state: dict = {"threshold": None if cfg.auto_threshold else cfg.reflectivity_threshold}
    rep.threshold = cfg.reflectivity_threshold
    rep.threshold_auto = local
    pending: deque[ScanMarks] = deque()
    calib: list[np.ndarray] = []
    local_thr: list[float] = []
    out_xyz: list[np.ndarray] = []
    out_int: list[np.ndarray] = []
    out_scan: list[np.ndarray] = []
    out_time: list[np.ndarray] = []
    plane_rows: list[np.ndarray] = []
    last_time = -np.inf
    flushed = 0
    reported = 0
    stamp_first = stamp_last = None

    def flush(ready: int) -> None:
        nonlocal flushed
        threshold = state["threshold"]
        while pending and (local or threshold is not None) and flushed < ready:
            m = pending.popleft()
            xyz, inten, times = m.xyz, m.intensity, m.times
            if not m.final:
                keep = inten >= threshold
                xyz, inten, times = xyz[keep], inten[keep], None if times is None else times[keep]
            world, T = poses.place(flushed, m, xyz, times)
            out_xyz.append(world)
            out_int.append(inten)
            out_scan.append(np.full(len(world), m.index, dtype=np.int32))
            out_time.append(np.full(len(world), m.stamp) if times is None else times)
            n, d = m.plane
            foot = np.array([0.0, 0.0, -d / n[2]])
            plane_rows.append(np.concatenate([[m.stamp], T[:3, :3] @ foot + T[:3, 3], T[:3, :3] @ n]))
            flushed += 1

    def set_threshold() -> None:
        values = np.concatenate(calib) if calib else np.zeros(0)
        if len(values) >= 100:
            state["threshold"] = auto_threshold(values, cfg.auto_threshold_mad_k)
            rep.threshold_auto = True
        else:
            state["threshold"] = cfg.reflectivity_threshold
        rep.threshold = state["threshold"]
        calib.clear()

    for m in _filtered(dataset, cfg, state, mode == "lidar", poses.gnss):
        if len(dataset.stats.bad_scans) > cfg.max_bad_scan_share * rep.scans_total:
            _too_many_bad(dataset, cfg)
        rep.ground_fallbacks += int(m.fell_back)
        rep.band_points += m.band_points
        if m.t_max is not None:
            assert m.times is not None
            fresh = m.times > last_time
            if not fresh.all():
                m.xyz, m.intensity, m.times = m.xyz[fresh], m.intensity[fresh], m.times[fresh]
            last_time = max(last_time, m.t_max)
        if m.calib is not None:
            calib.append(m.calib)
        if m.local_threshold is not None:
            local_thr.append(m.local_threshold)
        pending.append(m)
        stamp_first = m.stamp if stamp_first is None else stamp_first
        stamp_last = m.stamp
        ready = poses.feed(m)
        m.odo_xyz = m.odo_times = None
        rep.scans_used += 1
        if state["threshold"] is None and not local and rep.scans_used >= cfg.auto_threshold_scans:
            set_threshold()
        flush(ready)
        if progress is not None and m.index + 1 > reported:
            progress(m.index + 1 - reported)
            reported = m.index + 1
    if len(dataset.stats.bad_scans) > cfg.max_bad_scan_share * rep.scans_total:
        _too_many_bad(dataset, cfg)
    if rep.scans_used == 0:
        empty = dataset.stats.empty_scans
        raise InputError(dataset.path, f"every one of the {empty} scans is empty" if empty and empty == len(dataset)
                         else "no readable scan")
    if state["threshold"] is None and not local:
        set_threshold()
    if local and local_thr:
        rep.threshold = float(np.median(local_thr))
    flush(poses.finish())
    rep.bad_scans = list(dataset.stats.bad_scans)
    rep.empty_scans = dataset.stats.empty_scans
    rep.points_read = dataset.stats.points_read
    rep.dropped_points = dataset.stats.dropped_points
    rep.start_speed_mps = poses.odo.start_speed if poses.odo is not None else None
    if rep.start_speed_mps is not None and rep.start_speed_mps < 0.5:
        rep.warnings.append("LiDAR odometry found the scene static at the start (the vehicle stood still, or only "
                            "traffic and featureless rails were in view): check the drive length")

    xyz = np.concatenate(out_xyz) if out_xyz else np.zeros((0, 3))
    inten = np.concatenate(out_int).astype(np.float32) if out_int else np.zeros(0, np.float32)
    scan_idx = np.concatenate(out_scan) if out_scan else np.zeros(0, np.int32)
    ptime = np.concatenate(out_time) if out_time else np.zeros(0)
    rep.marking_points_raw = len(xyz)
    moving, rep.moving_trails = moving_object_mask(xyz, ptime, scan_idx, cfg)
    rep.moving_removed = int(moving.sum())
    if rep.moving_removed:
        stay = np.flatnonzero(~moving)
        keep = np.zeros(len(xyz), dtype=bool)
        keep[stay[radius_outliers(xyz.take(stay, axis=0), cfg.outlier_radius_m, cfg.outlier_min_neighbors,
                                  worker_count(cfg))]] = True
    else:
        keep = radius_outliers(xyz, cfg.outlier_radius_m, cfg.outlier_min_neighbors, worker_count(cfg))
    rep.outliers_removed = int(len(keep) - keep.sum()) - rep.moving_removed
    rep.marking_points = int(keep.sum())
    if rep.marking_points == 0:
        raise InputError(dataset.path, f"no lane-marking points found in {rep.scans_used} scans "
                         f"(threshold {rep.threshold:.2f}; {rep.band_points} road points)")
    planes = np.array(plane_rows).reshape(-1, 7)
    traj = poses.trajectory()
    rep.drive_length_m = _length(traj, stamp_first, stamp_last)
    rep.duration_s = float(stamp_last - stamp_first) if stamp_first is not None else 0.0
    rep.wall_s = _time.perf_counter() - wall0
    origin = dataset.origin if mode == "gnss" else GeoOrigin()
    return MarkingCloud(
        xyz=np.compress(keep, xyz, axis=0), intensity=inten[keep], scan_index=scan_idx[keep], time=ptime[keep],
        planes=GroundPlanes(times=planes[:, 0], points_world=planes[:, 1:4], normals_world=planes[:, 4:7]),
        trajectory=traj, origin=origin,
    )


def _length(traj: Trajectory, t0: float | None, t1: float | None) -> float:
    if t0 is None or t1 is None or len(traj) < 2:
        return 0.0
    sel = (traj.times >= t0 - 1e-9) & (traj.times <= t1 + 1e-9)
    pos = traj.positions[sel]
    return float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()) if len(pos) > 1 else 0.0


def _too_many_bad(dataset: Dataset, cfg: ExtractionConfig) -> None:
    bad = dataset.stats.bad_scans
    name, why = bad[0]
    raise InputError(dataset.path, f"{len(bad)} of {len(dataset)} scans unreadable (more than "
                     f"max_bad_scan_share={cfg.max_bad_scan_share:g}); first: {name}: {why}")
