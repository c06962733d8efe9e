"""The scenario picture of the report: every participant and the ego on the generated lanes (matplotlib, Agg).

Kilometres of road are unreadable at world scale, so the picture is straightened into the road's
own frame (station s along, offset t across, stretched), where lane changes and cut-ins show.
"""

from __future__ import annotations

from pathlib import Path
from typing import IO, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_participants(map_path: Path, scenario: dict[str, Any], path: Path | IO[bytes]) -> None:
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
