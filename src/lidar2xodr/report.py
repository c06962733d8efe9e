"""The build report: one HTML page with a bird's-eye picture of every stage and the numbers.

Users look before they read: the page shows the accumulated markings, the candidate lines and
boundaries found from them, the map drawn back from the written .xodr (so what you see is what
a simulator reads), the check verdict, the timing of each stage and, when a truth is known,
the comparison metrics.
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lidar2xodr.data import LaneModel, MarkingCloud  # noqa: E402
from lidar2xodr.fileio import atomic_dir  # noqa: E402

MAX_POINTS = 400_000


def _figure(extent: np.ndarray) -> tuple[plt.Figure, plt.Axes]:
    span = np.ptp(extent, axis=0) + 1.0
    aspect = float(np.clip(span[1] / span[0], 0.25, 1.5))
    fig, ax = plt.subplots(figsize=(14, max(4.0, 14 * aspect)), dpi=110)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.2)
    return fig, ax


def plot_markings(cloud: MarkingCloud, path: Path) -> None:
    """The accumulated marking cloud, coloured by reflectivity, with the trajectory used."""
    xyz = cloud.xyz
    if len(xyz) > MAX_POINTS:
        xyz_idx = np.random.default_rng(0).choice(len(xyz), MAX_POINTS, replace=False)
        xyz, inten = xyz[xyz_idx], cloud.intensity[xyz_idx]
    else:
        inten = cloud.intensity
    fig, ax = _figure(xyz[:, :2] if len(xyz) else np.zeros((1, 2)))
    sc = ax.scatter(xyz[:, 0], xyz[:, 1], c=inten, s=0.3, cmap="viridis", vmin=0, vmax=1, linewidths=0)
    if len(cloud.trajectory):
        p = cloud.trajectory.positions
        ax.plot(p[:, 0], p[:, 1], "-", color="tab:red", lw=0.8, label="trajectory (placement only)")
        ax.legend(loc="best")
    fig.colorbar(sc, ax=ax, label="reflectivity", shrink=0.6)
    ax.set_title(f"Accumulated markings: {len(cloud.xyz):,} points")
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def plot_map(map_path: Path, path: Path, title: str, overlay: dict[str, np.ndarray] | None = None) -> None:
    """The map as a simulator reads it: lane borders and reference line from the written file."""
    from lidar2xodr.opendrive import OpenDriveMap

    odr = OpenDriveMap.load(map_path)
    sections = odr.sample(1.0)
    pts = np.concatenate([sec.xyz[:, :2] for sec in sections]) if sections else np.zeros((1, 2))
    fig, ax = _figure(pts)
    for sec in sections:
        ax.plot(sec.xyz[:, 0], sec.xyz[:, 1], "-", color="tab:purple", lw=1.0)
        for lane_id, xyz in sec.border_xyz.items():
            kind = sec.lane_types.get(lane_id, "")
            color = "black" if kind in ("driving", "entry", "exit", "onRamp", "offRamp") else "0.6"
            ax.plot(xyz[:, 0], xyz[:, 1], "-", color=color, lw=0.6)
    for name, line in (overlay or {}).items():
        ax.plot(line[:, 0], line[:, 1], "-", lw=0.8, label=name)
    ax.plot([], [], "-", color="tab:purple", label="reference line")
    ax.plot([], [], "-", color="black", label="driving-lane borders")
    ax.legend(loc="best")
    ax.set_title(title)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def plot_participants(map_path: Path, scenario: dict[str, Any], path: Path) -> None:
    """Every participant's path and the ego's on the generated lanes, straightened into road coordinates.

    Station s along the reference line horizontally, lateral offset t vertically (stretched), so
    lane changes, cut-ins and lanes that open or close are visible along a kilometres-long drive.
    """
    from scipy.spatial import cKDTree

    from lidar2xodr.opendrive import OpenDriveMap

    odr = OpenDriveMap.load(map_path)
    sections = odr.sample(1.0)
    ref = np.concatenate([sec.xyz[:, :2] for sec in sections])
    s_all = np.concatenate([sec.s for sec in sections])  # a built map is one road
    hdg = np.concatenate([sec.hdg for sec in sections])
    tree = cKDTree(ref)

    def to_st(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dist, idx = tree.query(xy[:, :2])
        d = xy[:, :2] - ref[idx]
        t = -d[:, 0] * np.sin(hdg[idx]) + d[:, 1] * np.cos(hdg[idx])
        s = s_all[idx] + d[:, 0] * np.cos(hdg[idx]) + d[:, 1] * np.sin(hdg[idx])
        return np.where(dist < 30.0, s, np.nan), np.where(dist < 30.0, t, np.nan)

    fig, ax = plt.subplots(figsize=(16, 6), dpi=110)
    for sec in sections:
        for lane_id, t in sec.border_t.items():
            driving = sec.lane_types.get(lane_id, "") == "driving" or lane_id == 0
            ax.plot(sec.s, t, "-", color="black" if driving else "0.7", lw=0.6)
    cmap = plt.get_cmap("tab20")
    for k, track in enumerate(scenario["tracks"].tracks):
        s, t = to_st(track.xyz)
        ax.plot(s, t, "-", lw=1.2, color=cmap(k % 20))
        if np.isfinite(s).any():
            i = int(np.nanargmin(s))
            ax.annotate(f"{track.category} {track.id}", (s[i], t[i]), fontsize=7, color=cmap(k % 20))
    s, t = to_st(scenario["ego"].positions)
    ax.plot(s, t, "-", lw=2.0, color="tab:red", label="ego")
    for m in scenario["summary"].manoeuvres:
        xy = np.array([_position_at(scenario, m.actor, m.time_s)])
        ms, mt = to_st(xy)
        ax.plot(ms, mt, "v", color="tab:red")
        ax.annotate(f"{m.kind} {m.actor}", (ms[0], mt[0]), fontsize=7, color="tab:red", rotation=30)
    ax.set_xlabel("s along the reference line [m]")
    ax.set_ylabel("t, left of the reference line [m]")
    ax.legend(loc="upper right")
    ax.grid(alpha=0.2)
    ax.set_title(f"{len(scenario['tracks'].tracks)} participants and the ego on the generated lanes (road frame)")
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def _position_at(scenario: dict[str, Any], actor: str, t: float) -> tuple[float, float]:
    ego = scenario["ego"]
    track = next((tr for tr in scenario["tracks"].tracks if str(tr.id) in actor), None)
    times, xyz = (track.times, track.xyz) if track is not None else (ego.times, ego.positions)
    t_abs = t + scenario["summary"].time_offset_s
    return float(np.interp(t_abs, times, xyz[:, 0])), float(np.interp(t_abs, times, xyz[:, 1]))


def _table(rows: dict[str, Any]) -> str:
    body = "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>" for k, v in rows.items()
    )
    return f"<table>{body}</table>"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict | list):
        return json.dumps(v, default=str)
    return str(v)


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(_flatten(v, key + "."))
        elif not isinstance(v, list) or len(v) < 20:
            flat[key] = v
    return flat


def write_report(
    out_dir: Path,
    cloud: MarkingCloud,
    model: LaneModel,
    map_path: Path,
    check: dict[str, Any],
    timings: dict[str, float],
    summary: dict[str, Any],
    scenario: dict[str, Any] | None = None,
    metrics: dict[str, Any] | None = None,
) -> Path:
    """Write `out_dir/index.html` with its pictures, atomically (the folder appears whole)."""
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        figures: list[tuple[str, str]] = []
        plot_markings(cloud, tmp / "1_markings.png")
        figures.append(("1_markings.png", "Stage 1: accumulated lane-marking points"))
        try:
            from lidar2xodr.lanes_report import plot_lane_model

            plot_lane_model(cloud, model, tmp / "2_lanes.png")
            figures.append(("2_lanes.png", "Stages 2-3: clusters, candidate lines by superline, boundaries, reference"))
        except ImportError:
            pass
        overlay = {"trajectory": cloud.trajectory.positions} if len(cloud.trajectory) else None
        plot_map(map_path, tmp / "3_map.png", f"Stage 4: the written map ({map_path.name})", overlay)
        figures.append(("3_map.png", "Stage 4: the map drawn back from the written OpenDRIVE file"))
        if scenario:
            plot_participants(map_path, scenario, tmp / "4_scenario.png")
            figures.append(("4_scenario.png", "Scenario: the ego and every participant on the generated lanes"))
        parts = [
            "<!doctype html><html><head><meta charset='utf-8'><title>lidar2xodr report</title>",
            "<style>body{font-family:sans-serif;max-width:1400px;margin:auto}img{max-width:100%}"
            "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;"
            "text-align:left}</style></head><body>",
            f"<h1>lidar2xodr report: {html.escape(map_path.name)}</h1>",
            "<h2>Summary</h2>",
            _table(_flatten(summary)),
            "<h2>Time per stage [s]</h2>",
            _table({k: round(v, 2) for k, v in timings.items()}),
            "<h2>Map check</h2>",
            _table(_flatten(check)),
        ]
        if metrics:
            parts += ["<h2>Comparison with the reference map</h2>", _table(_flatten(metrics))]
        if model.warnings:
            items = "".join(f"<li>{html.escape(w)}</li>" for w in model.warnings)
            parts += [f"<h2>Warnings</h2><ul>{items}</ul>"]
        if scenario:
            summ = scenario["summary"]
            items = "".join(
                f"<li>{html.escape(f'{m.kind}: {m.actor} at {m.time_s:.1f} s')}</li>" for m in summ.manoeuvres
            ) or "<li>none detected</li>"
            parts += [
                f"<h2>Scenario {html.escape(str(scenario['path']))}</h2>",
                f"<p>{len(summ.entities)} entities, {summ.duration_s:.1f} s.</p>",
                f"<h3>Manoeuvres relative to the generated lanes</h3><ul>{items}</ul>",
            ]
        for name, caption in figures:
            parts += [f"<h2>{html.escape(caption)}</h2><img src='{name}' alt='{html.escape(caption)}'>"]
        parts.append("</body></html>")
        (tmp / "index.html").write_text("\n".join(parts), encoding="utf-8")
        (tmp / "summary.json").write_text(
            json.dumps({"summary": summary, "timings": timings, "check": check, "metrics": metrics},
                       indent=2, default=str, sort_keys=True),
            encoding="utf-8",
        )
    return out_dir / "index.html"
