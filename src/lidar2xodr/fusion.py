"""Several drives into one marking cloud: each drive aligned to the drives before it by its markings.

The paper notes that markings of several drives can be accumulated; with GNSS that is off by a
metre or more (no correction service) plain accumulation doubles every line. So, in drive order:

1. Frame: every drive's cloud is brought into the first kept drive's local frame through its
   geodetic origin (pyproj). Drives without a geodetic origin share the frame only when none has
   one (a simulated map without geoReference) and all were placed with poses; a drive placed by
   LiDAR odometry has no prior and is left out with a warning.
2. Alignment (the GNSS is the prior): a grid search of horizontal offsets within
   `search_radius_m`, coarse then fine, scores how many of the drive's marking points (voxel
   sampled) lie within `inlier_m` of the markings fused so far; this finds the right line where a
   local method would snap to a neighbour one lane width away. Point-to-point ICP against all
   fused points (`max_correspondence_m`) then refines offset and heading. Across the road the
   lines fix the offset to centimetres; along it only dash ends and curves do (decimetres on a
   straight road); the height offset is the median
   height difference of the matched points.
3. A drive that shares fewer than `min_overlap_points` marking points with the fused ones (within
   the search radius), or whose best alignment matches fewer than `min_inlier_share` of them, is
   left out with a warning naming it: a drive of another road, or markings that cannot be aligned.

4. Placement: the drives agree with each other after alignment, but which one's GNSS is right
   cannot be told from the markings. With `anchor` (a drive recorded with RTK corrections, say)
   the fused cloud sits where that drive's GNSS puts it; without, at the mean of the drives' own
   GNSS placements (least squares for independent biases: N drives with biases of sigma b leave
   b / sqrt(N)). Each drive's reported offset is the correction from its GNSS to that placement.

The fused cloud concatenates the aligned points, planes and trajectories (scan indices and the
trajectory's times continue after the drive before, so both stay increasing; the first drive's
times are its own). `FusionReport` lists each drive's estimated offset for the build's summary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from lidar2xodr.config import FusionConfig
from lidar2xodr.data import GeoOrigin, GroundPlanes, MarkingCloud, Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.georeference import origin_proj


@dataclass
class DriveOffset:
    """How one drive was placed: the offset added to its GNSS placement, or why it was left out."""

    drive: str
    dx_m: float = 0.0
    dy_m: float = 0.0
    dz_m: float = 0.0
    yaw_deg: float = 0.0
    inlier_share: float = 1.0
    points: int = 0
    left_out: str | None = None

    def line(self) -> str:
        if self.left_out:
            return f"{self.drive}: left out ({self.left_out})"
        return (f"{self.drive}: offset x {self.dx_m:+.2f} m, y {self.dy_m:+.2f} m, z {self.dz_m:+.2f} m, yaw "
                f"{self.yaw_deg:+.3f} deg; {self.inlier_share:.0%} of its {self.points:,} marking points matched")


@dataclass
class FusionReport:
    drives: list[DriveOffset] = field(default_factory=list)
    trajectories: list[Trajectory | None] = field(default_factory=list)  # per drive, in the fused frame

    @property
    def warnings(self) -> list[str]:
        return [f"drive {d.line()}" for d in self.drives if d.left_out]


def _reproject(cloud: MarkingCloud, target: GeoOrigin) -> MarkingCloud:
    """The cloud in the local frame of `target` (same geodetic placement, other origin)."""
    from lidar2xodr.georeference import ToWgs84

    src, dst = origin_proj(cloud.origin), origin_proj(target)
    if src is None or dst is None or src == dst:
        return cloud
    a, b = ToWgs84(src, "fusion"), ToWgs84(dst, "fusion")

    def move(xyz: np.ndarray) -> np.ndarray:
        if len(xyz) == 0:
            return xyz
        lon, lat = a.lonlat(xyz[:, 0], xyz[:, 1])
        x, y = b.local(lon, lat)
        return np.column_stack([x, y, xyz[:, 2] + (cloud.origin.alt - target.alt)])

    poses = cloud.trajectory.poses.copy()
    poses[:, :3, 3] = move(poses[:, :3, 3])
    planes = GroundPlanes(cloud.planes.times, cloud.planes.normals_world, move(cloud.planes.points_world))
    return MarkingCloud(move(cloud.xyz), cloud.intensity, cloud.scan_index, cloud.time, planes,
                        Trajectory(cloud.trajectory.times, poses), target)


def _voxel(xy: np.ndarray, size: float) -> np.ndarray:
    """One point per occupied cell (the first), in a fixed order: deterministic sampling."""
    _, first = np.unique(np.floor(xy / size).astype(np.int64), axis=0, return_index=True)
    return xy[np.sort(first)]


def _grid_search(tree: cKDTree, pts: np.ndarray, centre: np.ndarray, radius: float, step: float,
                 tol: float) -> tuple[np.ndarray, int]:
    """The offset on a grid around `centre` that puts most points within `tol` of the tree's points."""
    ticks = np.arange(-radius, radius + 1e-9, step)
    best, best_n = centre, -1
    for dx in ticks:
        for dy in ticks:
            off = centre + np.array([dx, dy])
            d, _ = tree.query(pts + off, distance_upper_bound=tol)
            n = int(np.count_nonzero(np.isfinite(d)))
            if n > best_n:
                best, best_n = off, n
    return best, best_n


def _rigid_2d(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray]:
    """Least-squares rotation angle and shift that move `src` onto `dst` (paired 2D points, Kabsch)."""
    a, b = src - src.mean(axis=0), dst - dst.mean(axis=0)
    h = a.T @ b
    yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return yaw, dst.mean(axis=0) - src.mean(axis=0) @ rot.T


def _icp(tree: cKDTree, ref: np.ndarray, pts: np.ndarray, yaw: float, shift: np.ndarray, max_dist: float,
         iterations: int = 100, tol: float = 1e-4) -> tuple[float, np.ndarray]:
    """Point-to-point ICP in 2D from (`yaw`, `shift`): pairs within `max_dist`, Kabsch, until the step is below `tol`.

    Written out rather than Open3D's, whose multi-threaded reductions gave other last digits on
    every run (a build must give the same bytes for the same drives).
    """
    for _ in range(iterations):
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        moved = pts @ rot.T + shift
        d, j = tree.query(moved, distance_upper_bound=max_dist)
        hit = np.isfinite(d)
        if np.count_nonzero(hit) < 3:
            break
        dyaw, dshift = _rigid_2d(moved[hit], ref[j[hit]])
        step = np.array([[math.cos(dyaw), -math.sin(dyaw)], [math.sin(dyaw), math.cos(dyaw)]])
        yaw, shift = yaw + dyaw, shift @ step.T + dshift
        if abs(dyaw) * 100.0 + float(np.hypot(*dshift)) < tol:
            break
    return yaw, shift


def align(fused: np.ndarray, drive: np.ndarray, cfg: FusionConfig) -> tuple[np.ndarray, float, int]:
    """Rigid 2D+z transform (4x4) that puts `drive`'s marking points on `fused`'s, its inlier share and overlap.

    Returns the identity and share 0 when the drives share fewer than `min_overlap_points` points.
    """
    ref_xy, mov_xy = _voxel(fused[:, :2], cfg.voxel_m), _voxel(drive[:, :2], cfg.voxel_m)
    tree = cKDTree(ref_xy)
    near, _ = tree.query(mov_xy, distance_upper_bound=cfg.search_radius_m)
    overlap = mov_xy[np.isfinite(near)]
    if len(overlap) < cfg.min_overlap_points:
        return np.eye(4), 0.0, len(overlap)
    sample = overlap[:: max(1, len(overlap) // cfg.max_search_points)]
    coarse, _ = _grid_search(tree, sample, np.zeros(2), cfg.search_radius_m, cfg.coarse_step_m,
                             max(cfg.coarse_step_m * 0.6, cfg.inlier_m))
    fine, _ = _grid_search(tree, sample, coarse, cfg.coarse_step_m, cfg.fine_step_m, cfg.inlier_m)
    dense = cKDTree(fused[:, :2])
    finest, _ = _grid_search(dense, sample, fine, cfg.fine_step_m, cfg.fine_step_m / 5, cfg.fine_step_m / 2)
    yaw, shift = _icp(dense, fused[:, :2], overlap, 0.0, finest, cfg.max_correspondence_m)
    out = np.eye(4)
    out[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    out[:2, 3] = shift
    moved = drive[:, :2] @ out[:2, :2].T + out[:2, 3]
    d, j = dense.query(moved, distance_upper_bound=cfg.inlier_m)
    hit = np.isfinite(d)
    share = float(np.count_nonzero(hit)) / max(len(drive), 1)
    if hit.any():
        out[2, 3] = float(np.median(fused[j[hit], 2] - drive[hit, 2]))
    return out, share, len(overlap)


def _apply(cloud: MarkingCloud, t: np.ndarray) -> MarkingCloud:
    def move(xyz: np.ndarray) -> np.ndarray:
        return xyz @ t[:3, :3].T + t[:3, 3] if len(xyz) else xyz

    poses = np.einsum("ij,njk->nik", t, cloud.trajectory.poses) if len(cloud.trajectory) else cloud.trajectory.poses
    normals = np.asarray(cloud.planes.normals_world).reshape(-1, 3) @ t[:3, :3].T
    planes = GroundPlanes(cloud.planes.times, normals, move(cloud.planes.points_world))
    return MarkingCloud(move(cloud.xyz), cloud.intensity, cloud.scan_index, cloud.time, planes,
                        Trajectory(cloud.trajectory.times, poses), cloud.origin)


def _concat(clouds: list[MarkingCloud]) -> MarkingCloud:
    """One cloud; scan indices and trajectory times continue after the drive before."""
    scan_off, t_off, last_t = 0, 0.0, -np.inf
    xyz, inten, scan, time, pt, pn, pp, tt, tp = [], [], [], [], [], [], [], [], []
    for c in clouds:
        xyz.append(c.xyz)
        inten.append(c.intensity)
        scan.append(np.asarray(c.scan_index, dtype=np.int64) + scan_off)
        time.append(c.time)
        pt.append(c.planes.times)
        pn.append(c.planes.normals_world)
        pp.append(c.planes.points_world)
        if len(c.trajectory):
            t_off = 0.0 if last_t == -np.inf else max(0.0, last_t + 1.0 - float(c.trajectory.times[0]))
            tt.append(c.trajectory.times + t_off)
            tp.append(c.trajectory.poses)
            last_t = float(tt[-1][-1])
        scan_off = int(scan[-1].max()) + 1 if len(scan[-1]) else scan_off
    planes = GroundPlanes(np.concatenate(pt), np.concatenate(pn).reshape(-1, 3), np.concatenate(pp).reshape(-1, 3))
    traj = Trajectory(np.concatenate(tt), np.concatenate(tp)) if tt else clouds[0].trajectory
    return MarkingCloud(np.concatenate(xyz), np.concatenate(inten), np.concatenate(scan).astype(np.int32),
                        np.concatenate(time), planes, traj, clouds[0].origin)


def fuse(clouds: list[MarkingCloud], names: list[str], modes: list[str], cfg: FusionConfig
         ) -> tuple[MarkingCloud, FusionReport]:
    """The drives' markings in one cloud, each drive aligned to those fused before it (module docstring)."""
    rep = FusionReport()
    any_geo = any(origin_proj(c.origin) for c in clouds)
    kept: list[MarkingCloud] = []
    for cloud, name, mode in zip(clouds, names, modes, strict=True):
        entry = DriveOffset(name, points=len(cloud.xyz))
        rep.drives.append(entry)
        if len(cloud.xyz) == 0:
            entry.left_out = "no lane markings found in the drive (nothing bright on the ground)"
            continue
        if mode == "lidar":
            entry.left_out = "placed by LiDAR odometry: no GNSS prior to align it by"
            continue
        if any_geo and origin_proj(cloud.origin) is None:
            entry.left_out = "its poses have no geodetic origin, the other drives' do"
            continue
        if not kept:
            kept.append(cloud)
            continue
        cloud = _reproject(cloud, kept[0].origin)
        fused = np.concatenate([c.xyz for c in kept])
        t, share, overlap = align(fused, cloud.xyz, cfg)
        if overlap < cfg.min_overlap_points:
            entry.left_out = (f"only {overlap} of its marking points lie within {cfg.search_radius_m:g} m of the "
                              "drives before: no overlap (another road?)")
            continue
        if share < cfg.min_inlier_share:
            entry.left_out = (f"its markings could not be aligned: {share:.0%} matched, at least "
                              f"{cfg.min_inlier_share:.0%} needed")
            continue
        entry.dx_m, entry.dy_m, entry.dz_m = (float(v) for v in t[:3, 3])
        entry.yaw_deg = math.degrees(math.atan2(t[1, 0], t[0, 0]))
        entry.inlier_share = share
        kept.append(_apply(cloud, t))
    if not kept:
        raise InputError(names[0], "no drive can be fused: " + "; ".join(d.line() for d in rep.drives))
    placed = [d for d in rep.drives if not d.left_out]
    if cfg.anchor is not None:
        if cfg.anchor > len(rep.drives):
            raise InputError(names[-1], f"fusion.anchor is drive {cfg.anchor}, but only {len(rep.drives)} were given")
        anchor = rep.drives[cfg.anchor - 1]
        if anchor.left_out:
            raise InputError(anchor.drive, f"the anchor drive (fusion.anchor {cfg.anchor}) was left out: "
                                           f"{anchor.left_out}")
        placed_by = [anchor]
    else:
        placed_by = placed
    mean = np.array([np.mean([getattr(d, k) for d in placed_by]) for k in ("dx_m", "dy_m", "dz_m")])
    for d in placed:
        d.dx_m, d.dy_m, d.dz_m = d.dx_m - mean[0], d.dy_m - mean[1], d.dz_m - mean[2]
    shift = np.eye(4)
    shift[:3, 3] = -mean
    kept = [_apply(c, shift) for c in kept]
    placed_clouds = iter(kept)
    rep.trajectories = [None if d.left_out else next(placed_clouds).trajectory for d in rep.drives]
    return _concat(kept), rep
