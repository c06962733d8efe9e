"""Bird's-eye pictures of the lanes stage (matplotlib, Agg): what the method saw and what it built.

One overview of the whole drive in world x, y plus detail windows (200 m) in the road's own frame
(station s along, offset t across, t exaggerated) where the lane count changes, or spread along
the road when it does not. They show the marking points (subsampled), cluster centres, candidate
lines coloured by superline (grey: ignored), normals of the relative lookups (every third
segment), boundaries (solid or dashed as their marking) and the reference line. Files are
written atomically.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lidar2xodr.data import LaneModel, MarkingCloud  # noqa: E402
from lidar2xodr.fileio import atomic_path  # noqa: E402
from lidar2xodr.lanes import Frame  # noqa: E402

_MAX_POINTS = 200_000
_DETAIL_M = 200.0
_MAX_DETAILS = 6


def boundary_xy(model: LaneModel) -> dict[int, np.ndarray]:
    """World x, y of every boundary at the stations (NaN where it is absent)."""
    ref = np.asarray(model.reference, dtype=np.float64)[:, :2]
    if len(ref) < 2:
        return {}
    tan = np.gradient(ref, axis=0)
    tan /= np.maximum(np.linalg.norm(tan, axis=1), 1e-12)[:, None]
    normal = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    return {b.id: ref + normal * np.asarray(b.t, dtype=np.float64)[:, None] for b in model.boundaries}


def _colour(superline: int) -> tuple[float, float, float, float]:
    if superline < 0:
        return (0.6, 0.6, 0.6, 1.0)
    return plt.get_cmap("tab10")(superline % 10)


def _draw_overview(ax: plt.Axes, cloud: MarkingCloud, model: LaneModel) -> None:
    """The whole drive in world x, y (equal scales)."""
    xyz = np.asarray(cloud.xyz)
    if len(xyz) > _MAX_POINTS:
        xyz = xyz[np.linspace(0, len(xyz) - 1, _MAX_POINTS).astype(np.int64)]
    ax.scatter(xyz[:, 0], xyz[:, 1], s=0.05, c="#9ab", lw=0, label="marking points")
    for k, c in enumerate(model.candidates):
        ctr = np.asarray(c.centers)
        ax.plot(
            ctr[:, 0],
            ctr[:, 1],
            "-",
            color=_colour(c.superline),
            lw=0.6,
            label="candidates by superline" if k == 0 else None,
        )
    kinds = {b.id: b.mark_type for b in model.boundaries}
    for i, (bid, xy) in enumerate(sorted(boundary_xy(model).items())):
        ax.plot(
            xy[:, 0],
            xy[:, 1],
            "--" if kinds[bid] == "broken" else "-",
            color="k",
            lw=1.0,
            label="boundaries" if i == 0 else None,
        )
    ref = np.asarray(model.reference)
    if len(ref):
        ax.plot(ref[:, 0], ref[:, 1], "-", color="#a2c", lw=1.2, label="reference line")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def _draw_detail(ax: plt.Axes, cloud: MarkingCloud, model: LaneModel, frame: Frame, s0: float) -> None:
    """A window of the road in its own frame: station s along, offset t across (left up)."""
    lo, hi = s0 - _DETAIL_M / 2, s0 + _DETAIL_M / 2
    xyz = np.asarray(cloud.xyz)
    centre = frame.xy[int(np.clip(np.searchsorted(frame.s, s0), 0, len(frame.s) - 1))]
    near = np.linalg.norm(xyz[:, :2] - centre, axis=1) < _DETAIL_M
    ps, pt, ins = frame.project(xyz[near, :2])
    keep = ins & (ps >= lo) & (ps <= hi)
    ax.scatter(ps[keep], pt[keep], s=0.4, c="#9ab", lw=0, label="marking points")
    for k, c in enumerate(model.candidates):
        ctr = np.asarray(c.centers)[:, :2]
        close = np.linalg.norm(ctr - centre, axis=1) < _DETAIL_M
        if not close.any():
            continue
        cs, ct, cin = frame.project(ctr)
        sel = cin & (cs >= lo - 20) & (cs <= hi + 20)
        if not sel.any():
            continue
        col = _colour(c.superline)
        ax.plot(cs[sel], ct[sel], "-", color=col, lw=1.0, label="candidates by superline" if k == 0 else None)
        ax.plot(cs[sel], ct[sel], ".", color="#e80", ms=3, label="cluster centres" if k == 0 else None)
        for x, y in zip(cs[sel][::3], ct[sel][::3], strict=True):
            ax.plot([x, x], [y - 2.0, y + 2.0], "-", color="#d33", lw=0.4, alpha=0.6)
    s = np.asarray(model.s)
    win = (s >= lo) & (s <= hi)
    for i, b in enumerate(model.boundaries):
        ax.plot(
            s[win],
            np.asarray(b.t)[win],
            "--" if b.mark_type == "broken" else "-",
            color="k",
            lw=1.2,
            label="boundaries" if i == 0 else None,
        )
    ax.axhline(0.0, color="#a2c", lw=1.2, label="reference line")
    ax.set_xlim(lo, hi)
    ax.set_xlabel("s along the reference [m]")
    ax.set_ylabel("t, left of the reference [m]")


def _windows(model: LaneModel) -> list[float]:
    """Centres of the detail windows: the section changes, or spread along the road."""
    s = np.asarray(model.s)
    if len(s) < 2:
        return []
    changes = [sec.s_start for sec in model.sections[1:]]
    if not changes:
        n = int(min(_MAX_DETAILS, max(1, (s[-1] - s[0]) // 2000 + 1)))
        changes = list(np.linspace(s[0], s[-1], n + 2)[1:-1])
    return [float(c) for c in changes[:_MAX_DETAILS]]


def lane_model_figure(cloud: MarkingCloud, model: LaneModel) -> plt.Figure:
    """One picture: the whole drive (top) and up to three detail windows (bottom); the caller closes it."""
    details = _windows(model)[:3]
    fig = plt.figure(figsize=(14, 10 if details else 6), dpi=110)
    grid = fig.add_gridspec(2 if details else 1, max(len(details), 1))
    ax = fig.add_subplot(grid[0, :])
    _draw_overview(ax, cloud, model)
    counts = ", ".join(f"{len(sec.boundary_ids) - 1} from {sec.s_start:.0f} m" for sec in model.sections)
    ax.set_title(
        f"Lanes from markings: {len(model.candidates)} candidates, {len(model.boundaries)} boundaries, "
        f"lanes {counts}",
        fontsize=10,
    )
    ax.legend(loc="best", fontsize=7, markerscale=6)
    if details:
        frame = Frame(np.asarray(model.reference)[:, :2], float(np.median(np.diff(model.s))))
        for i, s0 in enumerate(details):
            axd = fig.add_subplot(grid[1, i])
            _draw_detail(axd, cloud, model, frame, s0)
            axd.set_title(f"around s = {s0:.0f} m", fontsize=9)
    fig.tight_layout()
    return fig


def plot_lane_model(cloud: MarkingCloud, model: LaneModel, path: str | Path) -> None:
    """`lane_model_figure` written to `path` as PNG, atomically."""
    fig = lane_model_figure(cloud, model)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_lanes_report(cloud: MarkingCloud, model: LaneModel, out_dir: str | Path) -> list[Path]:
    """`lanes.png` (overview) and `lanes_detail_<k>.png` (200 m windows) in `out_dir`; returns the paths."""
    out_dir = Path(out_dir)
    paths = [out_dir / "lanes.png"]
    plot_lane_model(cloud, model, paths[0])
    if len(model.s) < 2:
        return paths
    frame = Frame(np.asarray(model.reference)[:, :2], float(np.median(np.diff(model.s))))
    for k, s0 in enumerate(_windows(model)):
        fig, ax = plt.subplots(figsize=(14, 5), dpi=110)
        _draw_detail(ax, cloud, model, frame, s0)
        ax.set_title(f"Lanes around s = {s0:.0f} m (road frame; t exaggerated)", fontsize=10)
        ax.legend(loc="best", fontsize=7, markerscale=4)
        fig.tight_layout()
        path = out_dir / f"lanes_detail_{k}.png"
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)
        paths.append(path)
    return paths
