"""One simulated drive, step by step: plan the route, drive ego and traffic, build the world, cast
every scan, write the drive directory (see writer.py for its layout)."""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from lidar2xodr.angles import wrap_angle
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import atomic_dir
from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.simulation import T0, SimOptions, SimSummary, _stream
from lidar2xodr.simulation import writer as W
from lidar2xodr.simulation.gnss import pose_errors
from lidar2xodr.simulation.lidar import Lidar
from lidar2xodr.simulation.poses import PoseTrack, TrafficPoses, ego_track, traffic_poses
from lidar2xodr.simulation.preview import PreviewCollector, Region, render, render_tiles, tile_regions
from lidar2xodr.simulation.route import RoadGraph, Route, build_route, longest_chain
from lidar2xodr.simulation.scene import build_world
from lidar2xodr.simulation.sensors import PRESETS, SensorPreset
from lidar2xodr.simulation.traffic import DT, Agents, TrafficSim

POSE_RATE_HZ = 100.0
TRAFFIC_MARGIN_M = 1200.0
"""Route built beyond the drive's end so traffic ahead has somewhere to be."""
END_MARGIN_M = 30.0
"""A one-pass drive on a route that ends in nothing stops this far before the end."""


@dataclass
class Plan:
    odr: OpenDriveMap
    preset: SensorPreset
    route: Route
    closed: bool
    chain_len: float
    length: float


def plan(map_path: Path, opts: SimOptions) -> Plan:
    """The route and the drive length (one pass by default, laps when --length-m asks for more)."""
    where = str(map_path)
    odr = OpenDriveMap.load(map_path)
    odr.require_nonnegative_widths()
    graph = RoadGraph(odr)
    nodes = longest_chain(graph, opts.start_road, where)
    closed = nodes[0] in graph.successors(nodes[-1]) and len(nodes) > 1
    chain_len = sum(odr.roads[r].length for r, _ in nodes)
    length = float(opts.length_m) if opts.length_m else chain_len
    if length < 5.0:
        raise InputError(where, f"the route is only {length:.1f} m long: too short for a drive")
    one_pass = length <= chain_len + 0.5
    if one_pass and not closed and chain_len > 2 * END_MARGIN_M:
        # a front-mounted sensor sees little but the end of the map in its last metres: stop before
        length = min(length, chain_len - END_MARGIN_M)
    route = build_route(odr, nodes, closed, chain_len if one_pass else length + TRAFFIC_MARGIN_M, where)
    return Plan(odr, PRESETS[opts.sensor], route, closed, chain_len, min(length, route.length - 0.5))


def run(map_path: Path, out_dir: Path, opts: SimOptions, console: Console | None) -> SimSummary:
    p = plan(map_path, opts)
    preset = p.preset
    agents = TrafficSim(p.route, opts.traffic, opts.speed_kmh, _stream(opts.seed, 1)).run(p.length)
    ego = ego_track(p.route, agents, T0, _stream(opts.seed, 2))
    traffic = traffic_poses(p.route, agents, int(round(preset.period / DT)))
    duration = float(agents.times[-1])
    n_scans = int(math.floor(duration / preset.period + 1e-9))
    if n_scans < 1:
        raise InputError(map_path, "the drive is shorter than one scan")
    world = build_world(p.odr, _roads_in_view(p.odr, ego.pos, preset.max_range_m + 60.0), opts.seed, opts.roadside)
    lidar = Lidar(preset, world, ego, traffic, agents, T0, _stream(opts.seed, 3))
    geo = W.Geo(p.odr.geo_reference)
    close_k = _closeup_index(ego, traffic)
    regions = [Region.at(ego, close_k, 1, f"close-up at t = {close_k / ego.hz:.1f} s: all points below sensor "
                         "height, reflectivity")]
    tiles = tile_regions(ego) if opts.preview else []
    with atomic_dir(out_dir, kind="drive") as tmp:
        (tmp / "scans").mkdir()
        (tmp / "truth").mkdir()
        col = PreviewCollector(preset.mount_xyz[2], preset.intensity_scale, n_scans * preset.rays_per_scan,
                               regions + tiles)
        bag = W.BagWriter(tmp, geo.ok, (preset.mount_xyz, preset.mount_rpy), preset.intensity_scale) \
            if opts.rosbag else None
        points, seen = _scans(tmp, lidar, traffic, agents, n_scans, col, bag, _stream(opts.seed, 5), console)
        outages = _poses(tmp, ego, geo, opts, bag)
        W.copy_map(map_path, tmp / "truth" / "map.xodr")
        W.write_json(tmp / "truth" / "route.json", _route_json(p.route, agents, ego, outages, p.length, duration,
                                                               preset.period, n_scans, gnss_bias(opts)))
        W.write_yaml(tmp / "meta.yaml", _meta(preset, geo, opts, map_path))
        title = (f"{map_path.name}: {p.length / 1000:.2f} km, {duration:.0f} s, {opts.sensor}, traffic "
                 f"{opts.traffic}, seed {opts.seed} (points below sensor height, reflectivity)")
        render(tmp / "preview.png", col, ego, title)
        if tiles:
            render_tiles(tmp / "preview", tiles)
    legs = p.route.legs
    passes = int(math.ceil(p.length / max(p.chain_len, 1e-9))) if p.closed else \
        1 + sum(leg.kind == "turn" for leg in legs if leg.u0 < p.length)
    return SimSummary(
        out_dir=out_dir, scans=n_scans, points=points, length_m=round(p.length, 1), duration_s=round(duration, 2),
        mean_speed_kmh=round(3.6 * p.length / max(duration, 1e-9), 1), roads=[r for r, _ in p.route.nodes],
        passes=passes, vehicles=len(seen), lane_changes=len(agents.lane_changes), gnss_outages=outages,
        preview=out_dir / "preview.png",
    )


def _scans(tmp: Path, lidar: Lidar, traffic: TrafficPoses, agents: Agents, n_scans: int, col: PreviewCollector,
           bag: W.BagWriter | None, obj_rng: np.random.Generator, console: Console | None) -> tuple[int, set[int]]:
    """Cast and write every scan; stream objects.csv and truth/objects.csv alongside."""
    period = lidar.p.period
    total = 0
    seen: set[int] = set()
    # Tiny matrix products on 100k rays: OpenBLAS threads only fight Embree's for the cores.
    with threadpool_limits(1, "blas"), _progress(console) as progress, \
            open(tmp / "objects.csv", "w", encoding="utf-8", newline="\n") as f_obj, \
            open(tmp / "truth" / "objects.csv", "w", encoding="utf-8", newline="\n") as f_truth:
        f_obj.write(W.OBJECT_HEADER + "\n")
        f_truth.write(W.OBJECT_HEADER + "\n")
        task = progress.add_task("simulating scans", total=n_scans) if progress else None
        for n in range(n_scans):
            scan = lidar.scan(n)
            W.write_pcd(tmp / "scans" / f"{n:06d}.pcd", scan)
            col.add(scan)
            total += len(scan.t)
            hits = np.bincount(scan.vehicle[scan.vehicle >= 0], minlength=len(agents.cls))
            reported, truth = _objects(traffic, agents, n, T0 + (n + 0.5) * period, hits, obj_rng, seen)
            f_obj.write(W.object_lines(reported))
            f_truth.write(W.object_lines(truth))
            if bag is not None:
                bag.scan(T0 + n * period, scan)
            if progress is not None and task is not None:
                progress.advance(task)
    return total, seen


def _poses(tmp: Path, ego: PoseTrack, geo: W.Geo, opts: SimOptions, bag: W.BagWriter | None
           ) -> list[tuple[float, float]]:
    """poses.csv (GNSS-measured), truth/poses.csv and the bag's pose topics; returns the outages."""
    idx = np.arange(0, len(ego.pos), int(round(ego.hz / POSE_RATE_HZ)))
    t = ego.times[idx]
    err, outages = pose_errors(t, opts.gnss_noise_m, opts.gnss_outage, _stream(opts.seed, 4))
    err[:, :2] += gnss_bias(opts)
    true_xyz, true_rpy = ego.pos[idx], W.rpy(ego.rot[idx])
    meas_xyz, meas_rpy = true_xyz + err[:, :3], true_rpy + err[:, 3:]
    (tmp / "poses.csv").write_text(W.poses_csv(t, meas_xyz, meas_rpy, geo), encoding="utf-8")
    (tmp / "truth" / "poses.csv").write_text(W.poses_csv(t, true_xyz, true_rpy, geo), encoding="utf-8")
    if bag is not None:
        q = W.quaternions(_rot_from_rpy(meas_rpy))
        ll = geo.latlon(meas_xyz) if geo.ok else None
        for j, tj in enumerate(t):
            lla = (float(ll[0][j]), float(ll[1][j]), float(ll[2][j])) if ll is not None else None
            bag.pose(float(tj), meas_xyz[j], q[j], lla, max(opts.gnss_noise_m, 0.01))
        bag.close()
    return outages


def gnss_bias(opts: SimOptions) -> np.ndarray:
    """The drive's constant horizontal GNSS offset (x, y): `gnss_bias_m` long, its direction drawn from the seed.

    A stream of its own, so a drive without a bias is the same bytes as before the option existed.
    """
    if opts.gnss_bias_m <= 0:
        return np.zeros(2)
    angle = float(_stream(opts.seed, 6).uniform(0.0, 2.0 * np.pi))
    return opts.gnss_bias_m * np.array([np.cos(angle), np.sin(angle)])


def _progress(console: Console | None):
    if console is None:
        return contextlib.nullcontext(None)
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=console, transient=False)


def _roads_in_view(odr: OpenDriveMap, ego_pos: np.ndarray, radius: float) -> list[str]:
    """Roads with any part within `radius` of the ego path (what the sensor can possibly see)."""
    tree = cKDTree(ego_pos[:: 50, :2])
    out = []
    for rid, road in odr.roads.items():
        s = np.linspace(0.0, road.length, max(2, int(road.length / 10.0) + 1))
        p = road.to_world(s, 0.0)[:, :2]
        d, _ = tree.query(p, k=1)
        if np.min(d) < radius + 30.0:
            out.append(rid)
    return out


def _objects(traffic: TrafficPoses, agents: Agents, n: int, t_mid: float, hits: np.ndarray, rng: np.random.Generator,
             seen: set[int]) -> tuple[list[tuple], list[tuple]]:
    """Rows of the objects a perception system reports in scan n (>= 3 returns, noisy) and of all true ones."""
    if n + 1 >= len(traffic.start):
        return [], []
    now = traffic.step(n)
    cols = traffic.agent[now]
    yaw = traffic.yaw[now]
    vel = traffic.velocity[now]
    centre = traffic.centre[now] + vel * (t_mid - T0 - 0.1 * n)
    if n + 2 < len(traffic.start):
        nxt = traffic.step(n + 1)
        j, q = np.nonzero(cols[:, None] == traffic.agent[nxt][None, :])
        centre[j] = 0.5 * (traffic.centre[now][j] + traffic.centre[nxt][q])
    truth, reported = [], []
    for j, c in enumerate(cols):
        c = int(c)
        ln, wd, ht = agents.size[c]
        cls = agents.cls[c]
        x, y, z = centre[j]
        truth.append((t_mid, c, cls, x, y, z, wrap_angle(yaw[j]), ln, wd, ht, vel[j, 0], vel[j, 1]))
        if hits[c] >= 3:
            seen.add(c)
            e = rng.normal(0.0, 1.0, 9)
            reported.append((t_mid, c, cls, x + 0.08 * e[0], y + 0.08 * e[1], z + 0.05 * e[2],
                             wrap_angle(yaw[j] + 0.02 * e[3]), ln + 0.05 * e[4], wd + 0.05 * e[5], ht + 0.05 * e[6],
                             vel[j, 0] + 0.2 * e[7], vel[j, 1] + 0.2 * e[8]))
    return reported, truth


def _rot_from_rpy(a: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("ZYX", a[:, ::-1]).as_matrix()


def _closeup_index(ego: PoseTrack, traffic: TrafficPoses) -> int:
    """Pose index for the preview close-up: at speed, where most traffic is just ahead (occlusions)."""
    n = len(traffic.start) - 1
    best, best_k = 0, len(ego.pos) // 2
    speed = np.gradient(ego.u) * ego.hz
    for s in range(0, n, max(1, n // 200)):
        sl = traffic.step(s)
        k = min(int(round(s * 0.1 * ego.hz)), len(ego.pos) - 1)
        if sl.stop == sl.start or speed[k] < 15.0 or not 0.1 * n <= s <= 0.9 * n:
            continue
        d = traffic.centre[sl] - ego.pos[k]
        fwd = d @ ego.rot[k][:, 0]
        lat = d @ ego.rot[k][:, 1]
        count = int(((fwd > 8) & (fwd < 60) & (np.abs(lat) < 12)).sum())
        if count > best:
            best, best_k = count, k
    return best_k


def _route_json(route, agents, ego, outages, length: float, duration: float, period: float, n_scans: int,
                bias: np.ndarray) -> dict:
    legs = []
    for leg in route.legs:
        if leg.u0 >= length:
            break
        item = {"kind": leg.kind, "pass": leg.lap, "u_start": round(leg.u0, 3), "u_end": round(min(leg.u1, length), 3)}
        if leg.kind == "road":
            item.update(road=leg.road, direction="+" if leg.direction > 0 else "-", s_start=round(leg.s0, 3),
                        s_end=round(leg.s_at(np.array([min(leg.u1, length)]))[0], 3), against_traffic=leg.wrong_way)
        else:
            item.update(road=leg.road, s=round(leg.s0, 3))
        legs.append(item)
    lanes: list[dict] = []
    for n in range(n_scans):
        t = (n + 0.5) * period
        k = min(int(round(t * ego.hz)), len(ego.pos) - 1)
        road, lane = route.lane_at(float(ego.u[k]), float(ego.lam[k]))
        if lanes and lanes[-1]["road"] == road and lanes[-1]["lane"] == lane:
            lanes[-1]["t_end"] = round(T0 + t, 3)
        else:
            lanes.append({"t_start": round(T0 + t, 3), "t_end": round(T0 + t, 3), "road": road, "lane": lane})
    changes = [{**c, "t_start": round(T0 + c["t_start"], 3), "t_end": round(T0 + c["t_end"], 3)}
               for c in agents.lane_changes]
    for c in changes:
        c.pop("from_track", None)
        c.pop("to_track", None)
    return {
        "format": "lidar2xodr-route",
        "version": 1,
        "map": "map.xodr",
        "time_origin": T0,
        "length_m": round(length, 3),
        "duration_s": round(duration, 3),
        "closed": route.closed,
        "chain": [{"road": r, "direction": "+" if d > 0 else "-"} for r, d in route.nodes],
        "chain_length_m": round(route.chain_length, 3),
        "legs": legs,
        "ego_lanes": lanes,
        "lane_changes": changes,
        "gnss_outages": [[round(a, 3), round(b, 3)] for a, b in outages],
        **({"gnss_bias_m": [round(float(v), 4) for v in bias]} if np.any(bias) else {}),
    }


def _meta(preset, geo, opts: SimOptions, map_path: Path) -> dict:
    x, y, z = preset.mount_xyz
    roll, pitch, yaw = preset.mount_rpy
    return {
        "format": "lidar2xodr-drive",
        "version": 1,
        "sensor": {
            "name": preset.name,
            "mount": {"x": x, "y": y, "z": z, "roll": roll, "pitch": round(pitch, 6), "yaw": yaw},
            "max_range_m": preset.max_range_m,
            "intensity_scale": preset.intensity_scale,
            "rate_hz": preset.rate_hz,
        },
        "origin": geo.origin(),
        "offset": [0.0, 0.0, 0.0],
        "scans": {"dir": "scans", "format": "pcd"},
        "poses": {"file": "poses.csv", "rate_hz": POSE_RATE_HZ, "angles": "rad, R = Rz(yaw) Ry(pitch) Rx(roll)"},
        "seed": opts.seed,
        "options": {**opts.model_dump(mode="json"), "map": map_path.name},
        "simulator": {"time_origin": T0},
    }
