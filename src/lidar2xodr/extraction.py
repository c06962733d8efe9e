"""Stage 1 (paper Sec. III-B): lane-marking points from every scan, accumulated in one world frame.

Per scan, in the vehicle frame: crop to the maximum range; keep points below the sensor mount
height; fit the ground plane with a seeded, vectorised RANSAC; keep the road band from
`ground_below_m` below the plane to `ground_margin_m` (paper: 0.15 m) above it; keep bright
points (reflectivity threshold). Then move the points into the world frame: with poses, each
point at its own time (SLERP rotation, linear translation: motion compensation), else with LiDAR
odometry (`odometry.py`). Finally a radius outlier removal (paper: fewer than 4 neighbours
within 0.5 m) on the accumulated cloud.

Decisions beyond the paper:
- The ground plane is fitted to points within `ransac_range_m` (a local plane), with normals
  within `ransac_max_tilt_deg` of vehicle z; its band is applied to every point in range. A scan
  where no plane is found falls back to the road plane z = 0 of the vehicle frame (counted).
- Automatic threshold (`auto_threshold`, see `auto_threshold`): from the road-band intensities of
  the first `auto_threshold_scans` scans within `auto_threshold_range_m`: max(Otsu, median +
  `auto_threshold_mad_k` robust sigmas). With fewer than 100 such points the fixed
  `reflectivity_threshold` (paper: 50 %) is used.
- Scans whose per-point time windows overlap (aiMotive: 100 ms revolutions every 66.7 ms) carry
  the same returns twice; points not newer than the previous scan's last point are not
  accumulated again.
- Streaming: only the marking points (and, for the first scans, the ground band waiting for the
  threshold) are kept; memory does not grow with the drive beyond the marking cloud.
"""

from __future__ import annotations

import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from lidar2xodr.config import ExtractionConfig
from lidar2xodr.data import GeoOrigin, GroundPlanes, MarkingCloud, Scan, Trajectory
from lidar2xodr.datasets.base import Dataset
from lidar2xodr.errors import InputError


@dataclass
class ExtractionReport:
    """What happened, for the command's summary line and for benchmarks."""

    scans_total: int = 0
    scans_used: int = 0
    bad_scans: list[tuple[str, str]] = field(default_factory=list)
    points_read: int = 0
    dropped_points: int = 0
    ground_fallbacks: int = 0
    band_points: int = 0
    marking_points_raw: int = 0
    outliers_removed: int = 0
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
    xyz: np.ndarray, cfg: ExtractionConfig, rng: np.random.Generator
) -> tuple[np.ndarray, float] | None:
    """Seeded RANSAC plane (n, d) with n . p + d = 0, n up; all hypotheses scored at once.

    `ransac_iterations` triples are drawn together; each is scored by its inliers among
    `ransac_sample_points` random points; the best is refined twice by least squares (SVD) on its
    inliers among all points. None when fewer than 3 points or no hypothesis is level enough.
    """
    if len(xyz) < 3:
        return None
    m = min(len(xyz), cfg.ransac_sample_points)
    sample = xyz[rng.choice(len(xyz), size=m, replace=False)] if m < len(xyz) else xyz
    tri = xyz[rng.integers(0, len(xyz), size=(cfg.ransac_iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n = n / np.where(ok, norm, 1.0)[:, None]
    n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
    ok &= n[:, 2] >= np.cos(np.radians(cfg.ransac_max_tilt_deg))
    if not ok.any():
        return None
    d = -np.einsum("ij,ij->i", n, tri[:, 0])
    score = (np.abs(sample @ n.T + d) < cfg.ransac_distance_m).sum(axis=0)
    score[~ok] = -1
    best = int(np.argmax(score))
    normal, offset = n[best], float(d[best])
    for _ in range(2):
        inl = xyz[np.abs(xyz @ normal + offset) < cfg.ransac_distance_m]
        if len(inl) < 3:
            break
        c = inl.mean(axis=0)
        _, _, vt = np.linalg.svd(inl - c, full_matrices=False)
        cand = vt[2] if vt[2, 2] >= 0 else -vt[2]
        if cand[2] < np.cos(np.radians(cfg.ransac_max_tilt_deg)):
            break
        normal, offset = cand, float(-cand @ c)
    return normal, offset


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


def radius_outliers(xyz: np.ndarray, radius: float, min_neighbors: int) -> np.ndarray:
    """Mask of points with at least `min_neighbors` other points within `radius` (scipy cKDTree).

    A k-nearest query with an upper bound answers "are there k neighbours" without counting every
    neighbour in dense paint (5x faster than ball counts here).
    """
    if len(xyz) == 0:
        return np.zeros(0, dtype=bool)
    if min_neighbors <= 0:
        return np.ones(len(xyz), dtype=bool)
    dist, _ = cKDTree(xyz).query(xyz, k=[min_neighbors + 1], distance_upper_bound=radius)
    return np.isfinite(dist[:, 0])


@dataclass
class _Pending:
    """One scan's road band in the vehicle frame, waiting for the threshold and/or its pose."""

    index: int
    stamp: float
    xyz: np.ndarray
    intensity: np.ndarray
    times: np.ndarray | None
    plane: tuple[np.ndarray, float]


class _PoseSource:
    """World placement: GNSS trajectory interpolation, or LiDAR odometry."""

    def __init__(self, dataset: Dataset, cfg: ExtractionConfig, mode: str) -> None:
        self.cfg = cfg
        self.mode = mode
        self.name = str(dataset.path)
        self.odo = None
        if mode == "gnss":
            traj = dataset.poses()
            assert traj is not None
            self.traj = traj
            self.slerp = Slerp(traj.times, Rotation.from_matrix(traj.poses[:, :3, :3]))
        else:
            from lidar2xodr.odometry import LidarOdometry

            self.odo = LidarOdometry(cfg)
        self.fed = 0

    def feed(self, scan: Scan, plane: tuple[np.ndarray, float]) -> int:
        """Give the scan to the odometry (non-ground points); returns how many scans have poses."""
        self.fed += 1
        if self.odo is None:
            return self.fed
        n, d = plane
        h = scan.xyz @ n + d
        r = np.linalg.norm(scan.xyz[:, :2], axis=1)
        keep = (h > self.cfg.odometry_min_height_m) & (r < self.cfg.odometry_max_range_m) & (r > 2.0)
        return self.odo.add(scan.stamp, scan.xyz[keep], None if scan.times is None else scan.times[keep])

    def finish(self) -> int:
        return self.odo.finish() if self.odo is not None else self.fed

    def _interp(self, t: np.ndarray, where: str) -> tuple[Rotation, np.ndarray]:
        t0, t1 = self.traj.times[0], self.traj.times[-1]
        tol = self.cfg.pose_time_tolerance_s
        if t.min() < t0 - tol or t.max() > t1 + tol:
            raise InputError(where, f"scan time {t.min():.3f}..{t.max():.3f} s is outside the poses' "
                             f"{t0:.3f}..{t1:.3f} s: the poses do not cover the scans")
        t = np.clip(t, t0, t1)
        uniq, inv = np.unique(t, return_inverse=True)
        rot = self.slerp(uniq)
        pos = np.column_stack([np.interp(uniq, self.traj.times, self.traj.positions[:, j]) for j in range(3)])
        return rot[inv], pos[inv]

    def to_world(self, k: int, p: _Pending, xyz: np.ndarray, times: np.ndarray | None) -> np.ndarray:
        if self.odo is not None:
            return self.odo.to_world(k, xyz, times)
        t = np.full(len(xyz), p.stamp) if times is None else times
        if len(t) == 0:
            return xyz.reshape(0, 3)
        rot, pos = self._interp(t, f"{self.name} scan {p.index}")
        return rot.apply(xyz) + pos

    def pose_at_stamp(self, k: int, p: _Pending) -> np.ndarray:
        if self.odo is not None:
            return self.odo.poses[k]
        rot, pos = self._interp(np.array([p.stamp]), f"{self.name} scan {p.index}")
        T = np.eye(4)
        T[:3, :3] = rot.as_matrix()[0]
        T[:3, 3] = pos[0]
        return T

    def trajectory(self) -> Trajectory:
        return self.odo.trajectory if self.odo is not None else self.traj


def _mode(dataset: Dataset, cfg: ExtractionConfig) -> str:
    has = dataset.poses() is not None
    if cfg.odometry == "gnss" and not has:
        raise InputError(dataset.path, "--odometry gnss but the drive has no poses (use auto or lidar)")
    if cfg.odometry == "lidar" or not has:
        return "lidar"
    return "gnss"


def _road_band(scan: Scan, cfg: ExtractionConfig, mount_z: float, max_range: float,
               rng: np.random.Generator) -> tuple[np.ndarray, tuple[np.ndarray, float], bool]:
    """Mask of the scan's road-band points, its ground plane, and whether the plane fell back."""
    xyz = scan.xyz
    r = np.linalg.norm(xyz[:, :2], axis=1)
    below = (r < max_range) & (xyz[:, 2] < mount_z - cfg.below_sensor_margin_m)
    cand = xyz[below & (r < cfg.ransac_range_m)]
    plane = fit_ground_plane(cand, cfg, rng)
    fallback = plane is None
    if plane is None:
        plane = (np.array([0.0, 0.0, 1.0]), 0.0)
    n, d = plane
    h = xyz @ n + d
    band = below & (h <= cfg.ground_margin_m) & (h >= -cfg.ground_below_m)
    return band, plane, fallback


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
    threshold: float | None = None if cfg.auto_threshold else cfg.reflectivity_threshold
    rep.threshold = cfg.reflectivity_threshold
    pending: list[_Pending] = []
    calib: list[np.ndarray] = []
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
        while pending and threshold is not None and flushed < ready:
            p = pending.pop(0)
            keep = p.intensity >= threshold
            times = None if p.times is None else p.times[keep]
            world = poses.to_world(flushed, p, p.xyz[keep], times)
            out_xyz.append(world)
            out_int.append(p.intensity[keep])
            out_scan.append(np.full(len(world), p.index, dtype=np.int32))
            out_time.append(np.full(len(world), p.stamp) if times is None else times)
            T = poses.pose_at_stamp(flushed, p)
            n, d = p.plane
            foot = np.array([0.0, 0.0, -d / n[2]])
            plane_rows.append(np.concatenate([[p.stamp], T[:3, :3] @ foot + T[:3, 3], T[:3, :3] @ n]))
            flushed += 1

    def set_threshold() -> None:
        nonlocal threshold
        values = np.concatenate(calib) if calib else np.zeros(0)
        if len(values) >= 100:
            threshold = auto_threshold(values, cfg.auto_threshold_mad_k)
            rep.threshold_auto = True
        else:
            threshold = cfg.reflectivity_threshold
        rep.threshold = threshold
        calib.clear()

    for scan in dataset:
        n_bad = len(dataset.stats.bad_scans)
        if n_bad > cfg.max_bad_scan_share * rep.scans_total:
            _too_many_bad(dataset, cfg)
        max_range = cfg.max_range_m if cfg.max_range_m is not None else dataset.sensor.max_range_m
        rng = np.random.default_rng([cfg.seed, scan.index])
        band, plane, fell_back = _road_band(scan, cfg, float(dataset.sensor.mount[2, 3]), max_range, rng)
        rep.ground_fallbacks += int(fell_back)
        if scan.times is not None:
            band &= scan.times > last_time
            last_time = max(last_time, float(scan.times.max()))
        xyz, inten = scan.xyz[band], scan.intensity[band]
        times = None if scan.times is None else scan.times[band]
        rep.band_points += len(xyz)
        if threshold is None:
            r = np.linalg.norm(xyz[:, :2], axis=1)
            calib.append(inten[r < cfg.auto_threshold_range_m])
            keep = np.ones(len(xyz), dtype=bool)
        else:
            keep = inten >= threshold
        pending.append(_Pending(scan.index, scan.stamp, xyz[keep], inten[keep],
                                None if times is None else times[keep], plane))
        stamp_first = scan.stamp if stamp_first is None else stamp_first
        stamp_last = scan.stamp
        ready = poses.feed(scan, plane)
        rep.scans_used += 1
        if threshold is None and rep.scans_used >= cfg.auto_threshold_scans:
            set_threshold()
        flush(ready)
        if progress is not None and scan.index + 1 > reported:
            progress(scan.index + 1 - reported)
            reported = scan.index + 1
    if len(dataset.stats.bad_scans) > cfg.max_bad_scan_share * rep.scans_total:
        _too_many_bad(dataset, cfg)
    if rep.scans_used == 0:
        raise InputError(dataset.path, "no readable scan")
    if threshold is None:
        set_threshold()
    flush(poses.finish())
    rep.bad_scans = list(dataset.stats.bad_scans)
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
    keep = radius_outliers(xyz, cfg.outlier_radius_m, cfg.outlier_min_neighbors)
    rep.outliers_removed = int(len(keep) - keep.sum())
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
        xyz=xyz[keep], intensity=inten[keep], scan_index=scan_idx[keep], time=ptime[keep],
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
