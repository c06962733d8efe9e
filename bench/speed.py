"""Speed of the whole `build` (issue #14), and the extraction and clustering side by side with Open3D.

Run with `make bench-speed` (= `.venv/bin/python bench/speed.py --out bench-out/speed`). For every
drive length (`--loop-km`, the project's demo road driven round and round; `--corridor-km`, one
distinct roadgen corridor with slip roads, bench/corridors.py) it simulates a drive with the
default sensor, runs `lidar2xodr build DRIVE -o MAP.xodr` as a user would (default options, check
included, no report) and records the wall time, the real-time factor (drive duration / wall time),
the largest resident memory of any process of the build, and the build's own stage times (its
summary's `time <stage>` rows). With two loop lengths it gives the time ratio and the scaling
exponent log(t2 / t1) / log(L2 / L1) (1 = linear).

Side by side (`--open3d-km`, a drive of the demo road of that length): our extraction (`lidar2xodr
extract`, every worker it uses) and DBSCAN (`markings._dbscan`, before slicing) against the same
steps written plainly with Open3D's own functions on the same scans and poses: per scan a crop to
the sensor's range, `segment_plane` (our RANSAC distance and iteration count), the points within
the ground margin above the plane and at or above the reflectivity threshold, placed in the world
with the drive's poses; then `remove_radius_outlier` (our radius and neighbour count) and
`cluster_dbscan` (our eps and minimum points) on the whole cloud. Both marking clouds' point
counts and cluster counts are reported beside the times, so the ratio is read as one of equal work:
ours does more per scan (moving-object and local-paint filters) and clusters voxel centroids.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
from run import CLI  # noqa: E402

_WRAPPER = (
    "import resource, subprocess, sys, time\n"
    "t0 = time.perf_counter()\n"
    "p = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
    "wall = time.perf_counter() - t0\n"
    "peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss\n"
    "sys.stdout.write(p.stdout + p.stderr + f'\\n@@ {p.returncode} {wall} {peak}\\n')\n"
)


def measured(cmd: list[str]) -> tuple[int, float, float, str]:
    """Exit code, wall seconds, largest resident memory of any descendant [MB] and the output of `cmd`."""
    proc = subprocess.run([sys.executable, "-c", _WRAPPER, *cmd], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "200"})
    out = proc.stdout
    m = re.search(r"@@ (-?\d+) ([0-9.]+) (\d+)\s*$", out)
    if m is None:
        return 1, math.nan, math.nan, out + proc.stderr
    return int(m.group(1)), float(m.group(2)), int(m.group(3)) / 1024.0, out[: m.start()]


def stage_times(log: str) -> dict[str, float]:
    """The build summary's `time <stage>  X s` rows."""
    return {m.group(1): float(m.group(2)) for m in re.finditer(r"time (\w+)\s*│\s*([0-9.]+) s", log)}


def drive_duration(drive: Path) -> float:
    lines = (drive / "poses.csv").read_text().splitlines()[1:]
    return float(lines[-1].split(",")[0]) - float(lines[0].split(",")[0])


def simulate(xodr: Path, drive: Path, length_m: float) -> None:
    if (drive / "poses.csv").exists():
        return
    proc = subprocess.run(CLI + ["simulate", str(xodr), str(drive), "--length-m", str(length_m), "--seed", "0"],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"simulate {xodr} failed: {(proc.stdout + proc.stderr)[-500:]}")


def bench_build(name: str, drive: Path, out: Path) -> dict:
    xodr = out / f"{name}.xodr"
    rc, wall, peak, log = measured(CLI + ["build", str(drive), "-o", str(xodr)])
    duration = drive_duration(drive)
    row = {"drive": name, "duration_s": round(duration, 1), "build_s": round(wall, 1), "rc": rc,
           "realtime_factor": round(duration / wall, 1), "peak_rss_mb": round(peak), "stages_s": stage_times(log)}
    if rc != 0:
        row["error"] = log.strip().splitlines()[-1] if log.strip() else f"exit {rc}"
    return row


def side_by_side(drive: Path, out: Path) -> dict:
    """Our extract + clustering against Open3D's segment_plane / remove_radius_outlier / cluster_dbscan."""
    sys.path.insert(0, str(REPO / "src"))
    import numpy as np
    import open3d as o3d

    from lidar2xodr.config import Config
    from lidar2xodr.datasets import open_dataset
    from lidar2xodr.markings import _dbscan
    from lidar2xodr.markings_io import load_markings

    cfg = Config()
    ply = out / "side_by_side_markings.ply"
    rc, t_extract, _, log = measured(CLI + ["extract", str(drive), "-o", str(ply)])
    if rc != 0:
        return {"error": log.strip().splitlines()[-1]}
    ours = load_markings(ply)
    t0 = time.perf_counter()
    labels_ours = _dbscan(np.asarray(ours.xyz), cfg.markings)
    t_cluster = time.perf_counter() - t0
    n_ours = int(labels_ours.max() + 1) if len(labels_ours) else 0

    ex = cfg.extraction
    t0 = time.perf_counter()
    dataset = open_dataset(drive)
    traj = dataset.poses()
    max_range = ex.max_range_m or dataset.sensor.max_range_m
    o3d.utility.random.seed(ex.seed)
    parts = []
    for scan in dataset:
        xyz, inten = np.asarray(scan.xyz), np.asarray(scan.intensity)
        keep = np.hypot(xyz[:, 0], xyz[:, 1]) <= max_range
        xyz, inten = xyz[keep], inten[keep]
        if len(xyz) < 3:
            continue
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        plane, _ = pcd.segment_plane(ex.ransac_distance_m, 3, ex.ransac_iterations)
        normal, d = np.asarray(plane[:3]), float(plane[3])
        if normal[2] < 0:
            normal, d = -normal, -d
        height = xyz @ normal + d
        sel = (height <= ex.ground_margin_m) & (height >= -ex.ground_below_m) & (inten >= ex.reflectivity_threshold)
        k = min(int(np.searchsorted(traj.times, scan.stamp)), len(traj.times) - 1)
        pose = traj.poses[k]
        parts.append(xyz[sel] @ pose[:3, :3].T + pose[:3, 3])
    world = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(parts)))
    kept, _ = world.remove_radius_outlier(ex.outlier_min_neighbors, ex.outlier_radius_m)
    t_o3d_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    labels = np.asarray(kept.cluster_dbscan(cfg.markings.dbscan_eps_m, cfg.markings.dbscan_min_samples))
    t_o3d_cluster = time.perf_counter() - t0
    ours_s, o3d_s = t_extract + t_cluster, t_o3d_extract + t_o3d_cluster
    return {"drive_duration_s": round(drive_duration(drive), 1),
            "ours": {"extract_s": round(t_extract, 1), "cluster_s": round(t_cluster, 1), "points": len(ours.xyz),
                     "clusters": n_ours},
            "open3d": {"extract_s": round(t_o3d_extract, 1), "cluster_s": round(t_o3d_cluster, 1),
                       "points": len(kept.points), "clusters": int(labels.max() + 1) if len(labels) else 0},
            "open3d_over_ours": round(o3d_s / ours_s, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "bench-out" / "speed")
    ap.add_argument("--loop-km", type=float, nargs="*", default=[10.0, 50.0])
    ap.add_argument("--corridor-km", type=float, nargs="*", default=[50.0])
    ap.add_argument("--open3d-km", type=float, default=3.0, help="0 skips the side-by-side")
    args = ap.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(REPO / "src"))
    from corridors import write_corridor

    from lidar2xodr.demo_road import write_demo_road

    demo = write_demo_road(out / "demo_road.xodr")
    rows = []
    for km in args.loop_km:
        drive = out / f"loop_{km:g}km"
        simulate(demo, drive, km * 1000.0)
        rows.append(bench_build(f"demo road looped, {km:g} km", drive, out))
        print(json.dumps(rows[-1]), flush=True)
    for km in args.corridor_km:
        xodr = out / f"corridor_{km:g}km.xodr"
        if not xodr.exists():
            write_corridor(1, xodr, km * 1000.0)
        drive = out / f"corridor_{km:g}km"
        simulate(xodr, drive, km * 1000.0)
        rows.append(bench_build(f"roadgen corridor, {km:g} km", drive, out))
        print(json.dumps(rows[-1]), flush=True)
    result: dict = {"builds": rows}
    loops = [(km, r) for km, r in zip(args.loop_km, rows, strict=False) if r["rc"] == 0]
    if len(loops) >= 2:
        (k1, r1), (k2, r2) = loops[0], loops[1]
        ratio = r2["build_s"] / r1["build_s"]
        result["scaling"] = {"lengths_km": [k1, k2], "time_ratio": round(ratio, 2),
                             "exponent": round(math.log(ratio) / math.log(k2 / k1), 2)}
    if args.open3d_km > 0:
        drive = out / f"loop_{args.open3d_km:g}km"
        simulate(demo, drive, args.open3d_km * 1000.0)
        result["side_by_side"] = side_by_side(drive, out)
    (out / "speed.json").write_text(json.dumps(result, indent=1))
    print("| drive | duration [s] | build [s] | real-time factor | peak memory [MB] | stages [s] |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        stages = ", ".join(f"{k} {v:g}" for k, v in r["stages_s"].items())
        print(f"| {r['drive']} | {r['duration_s']} | {r['build_s']} | {r['realtime_factor']}x | {r['peak_rss_mb']} "
              f"| {stages or r.get('error', '')} |")
    if "scaling" in result:
        print("scaling:", result["scaling"])
    if "side_by_side" in result:
        print("side by side:", json.dumps(result["side_by_side"]))


if __name__ == "__main__":
    main()
