"""One scan: every ray cast from the sensor pose at its own time against the world and the traffic.

The static world is an Embree scene per 200 m window of the ego's travel; traffic vehicles are
oriented boxes intersected analytically per ray, each at its position at that ray's time, so a
rolling-shutter scan of moving cars is exact. Points come out in the sensor frame at each ray's
time (no motion compensation), like a real sensor's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar2xodr.simulation import reflectivity as R
from lidar2xodr.simulation.poses import PoseTrack, TrafficPoses
from lidar2xodr.simulation.scene import StaticWorld, WindowScene
from lidar2xodr.simulation.sensors import SensorPreset
from lidar2xodr.simulation.traffic import Agents

WINDOW_M = 200.0


@dataclass
class ScanOut:
    """The returned points of one scan."""

    xyz: np.ndarray  # (M, 3) float32, sensor frame
    intensity: np.ndarray  # (M,) float32, sensor's raw scale
    t: np.ndarray  # (M,) float64, absolute
    material: np.ndarray  # (M,) uint8 (ground truth label, not written)
    vehicle: np.ndarray  # (M,) int32 agent column hit, -1 for the static world
    local: np.ndarray  # (M, 3) float32, true position of the point relative to `origin`
    origin: np.ndarray  # (3,) float64
    height: np.ndarray  # (M,) float32, height above the vehicle frame's origin (vehicle z)

    @property
    def world(self) -> np.ndarray:
        """(M, 3) float64 true world positions."""
        return self.local.astype(np.float64) + self.origin


class Lidar:
    """Casts the scans of one drive."""

    def __init__(self, preset: SensorPreset, world: StaticWorld, ego: PoseTrack, traffic: TrafficPoses,
                 agents: Agents, t_start: float, rng: np.random.Generator) -> None:
        self.p = preset
        self.world = world
        self.ego = ego
        self.traffic = traffic
        self.agents = agents
        self.t_start = t_start
        self.rng = rng
        mount = preset.mount_matrix()
        self.mount_rot = mount[:3, :3]
        self.mount_pos = mount[:3, 3]
        self._window_key: int | None = None
        self._window: WindowScene | None = None

    def scene_for(self, u: float) -> WindowScene:
        key = int(u // WINDOW_M)
        if key != self._window_key:
            lo, hi = key * WINDOW_M - 20.0, (key + 1) * WINDOW_M + 20.0
            m = (self.ego.u >= lo) & (self.ego.u <= hi)
            xy = self.ego.pos[m, :2][:: max(1, int(m.sum() // 20))]
            if len(xy) == 0:
                xy = self.ego.pos[[int(np.argmin(np.abs(self.ego.u - u)))], :2]
            self._window = self.world.window(xy, self.p.max_range_m + 5.0)
            self._window_key = key
        assert self._window is not None
        return self._window

    def scan(self, n: int) -> ScanOut:
        p = self.p
        t0 = self.t_start + n * p.period
        dirs_s, times = p.rays(t0, self.t_start)
        (p0, p1), (r0, r1) = self.ego.at(np.array([t0, t0 + p.period]))
        k, _ = self.ego.slot(np.array([t0 + 0.5 * p.period]))
        scene = self.scene_for(float(self.ego.u[k[0]]))
        # Poses move little within a scan: interpolate linearly between its start and end.
        w = ((times - t0) / p.period).astype(np.float32)[:, None]
        o0 = p0 + r0 @ self.mount_pos - scene.origin
        o1 = p1 + r1 @ self.mount_pos - scene.origin
        origins = o0.astype(np.float32) + w * (o1 - o0).astype(np.float32)
        a = np.ascontiguousarray((r0 @ self.mount_rot).T, dtype=np.float32)  # F-ordered would be 20x slower
        b = np.ascontiguousarray(((r1 - r0) @ self.mount_rot).T, dtype=np.float32)
        dirs = dirs_s @ a + w * (dirs_s @ b)
        rng_hit, mat, base, cos_inc = scene.cast(origins, dirs)
        vehicle = np.full(len(times), -1, dtype=np.int32)
        self._traffic(n, w[:, 0], origins, dirs, scene.origin, rng_hit, mat, base, cos_inc, vehicle)
        ret = R.returns(rng_hit, mat, base, cos_inc, p.detection_range, p.min_range_m, p.range_sigma_m, self.rng)
        i = ret.index
        r = ret.rng_m.astype(np.float32)[:, None]
        local = origins[i] + dirs[i] * r
        wi = w[i]
        ground = (p0 - scene.origin).astype(np.float32) + wi * (p1 - p0).astype(np.float32)
        up = r0[:, 2].astype(np.float32) + wi * (r1[:, 2] - r0[:, 2]).astype(np.float32)
        height = np.einsum("ij,ij->i", local - ground, up)
        return ScanOut(dirs_s[i] * r, R.to_raw(ret.reflectivity, p.intensity_scale), times[i], mat[i], vehicle[i],
                       local, scene.origin, height)

    def _traffic(self, n: int, w: np.ndarray, origins: np.ndarray, dirs: np.ndarray, shift: np.ndarray,
                 rng_hit: np.ndarray, mat: np.ndarray, base: np.ndarray, cos_inc: np.ndarray,
                 vehicle: np.ndarray) -> None:
        """Intersect the rays with the traffic boxes, each box moving linearly through the scan."""
        tp, ag = self.traffic, self.agents
        if n + 1 >= len(tp.start):
            return
        now = tp.step(n)
        if now.stop == now.start:
            return
        cols = tp.agent[now]
        c0 = tp.centre[now] - shift
        yaw = tp.yaw[now]
        c1 = c0 + tp.velocity[now] * self.p.period
        if n + 2 < len(tp.start):
            nxt = tp.step(n + 1)
            nxt_cols = tp.agent[nxt]
            j, q = np.nonzero(cols[:, None] == nxt_cols[None, :])
            c1[j] = tp.centre[nxt][q] - shift
        size = ag.size[cols]
        clear = ag.clearance[cols]
        half = np.column_stack([0.5 * size[:, 0], 0.5 * size[:, 1], 0.5 * (size[:, 2] - clear)])
        mid = 0.5 * (origins[0] + origins[-1]).astype(np.float64)
        span = float(np.linalg.norm(origins[-1] - origins[0]))
        vec = 0.5 * (c0 + c1) - mid
        dist = np.linalg.norm(vec, axis=1)
        radius = np.linalg.norm(half, axis=1) + np.linalg.norm(c1 - c0, axis=1) + span + 0.2
        unit = vec / np.maximum(dist, 1e-9)[:, None]
        ang = np.arcsin(np.minimum(1.0, radius / np.maximum(dist, 1e-9)))
        cos_lim = np.where(dist <= radius, -2.0, np.cos(ang))
        # keep boxes within range whose angular disc meets the cone of this scan's rays
        axis = dirs.mean(axis=0).astype(np.float64)
        norm = float(np.linalg.norm(axis))
        if norm > 0.3:
            axis /= norm
            spread = np.arccos(np.clip(float(np.min(dirs @ axis.astype(np.float32))), -1.0, 1.0))
            view = np.arccos(np.clip(unit @ axis, -1.0, 1.0)) <= spread + ang
        else:
            view = np.ones(len(unit), dtype=bool)
        near = np.flatnonzero((dist - radius < self.p.max_range_m) & (view | (dist <= radius)))
        if len(near) == 0:
            return
        inside = (dirs @ unit[near].T.astype(np.float32)) > cos_lim[near].astype(np.float32)[None, :]
        for col, j in enumerate(near):
            cand = np.flatnonzero(inside[:, col])
            if dist[j] <= radius[j] and len(cand):
                # close by, the cone test passes every ray: keep those that meet the moving bounding sphere
                rel = (c0[j] - origins[cand]).astype(np.float32) + w[cand, None] * (c1[j] - c0[j]).astype(np.float32)
                tca = np.einsum("ij,ij->i", rel, dirs[cand])
                miss2 = np.einsum("ij,ij->i", rel, rel) - tca * tca
                rb = float(np.linalg.norm(half[j])) + 0.1
                cand = cand[(miss2 < rb * rb) & (tca > -rb)]
            if len(cand) == 0:
                continue
            ww = w[cand, None].astype(np.float64)  # box motion and slab test in float64
            centre = c0[j] + ww * (c1[j] - c0[j])
            cy, sy = np.cos(yaw[j]), np.sin(yaw[j])
            rel = origins[cand] - centre
            o = np.column_stack([cy * rel[:, 0] + sy * rel[:, 1], -sy * rel[:, 0] + cy * rel[:, 1], rel[:, 2]])
            d = dirs[cand].astype(np.float64)
            dl = np.column_stack([cy * d[:, 0] + sy * d[:, 1], -sy * d[:, 0] + cy * d[:, 1], d[:, 2]])
            t_hit, axis = _slab(o, dl, half[j])
            better = t_hit < rng_hit[cand]
            if not better.any():
                continue
            idx = cand[better]
            th, ax = t_hit[better], axis[better]
            rng_hit[idx] = th
            vehicle[idx] = cols[j]
            cos_inc[idx] = np.abs(dl[better][np.arange(len(idx)), ax])
            local = o[better] + dl[better] * th[:, None]
            ground = -half[j, 2] - clear[j]
            plate = (ax == 0) & (np.abs(local[:, 1]) < 0.26) & (local[:, 2] > ground + 0.45) & (
                local[:, 2] < ground + 0.56)
            mat[idx] = np.where(plate, R.PLATE, R.VEHICLE)
            base[idx] = np.where(plate, 2.0, ag.rho[cols[j]])


def _slab(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry distance into an axis-aligned box centred at 0 (inf = miss) and the entry face's axis."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
    lo = np.fmin(t1, t2)
    hi = np.fmax(t1, t2)
    axis = np.argmax(lo, axis=1)
    t_near = lo[np.arange(len(o)), axis]
    t_far = hi.min(axis=1)
    hit = (t_near <= t_far) & (t_near > 0)
    return np.where(hit, t_near, np.inf), axis
