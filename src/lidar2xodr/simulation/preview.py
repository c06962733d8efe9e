"""Bird's-eye pictures of the accumulated scans (true poses), coloured by reflectivity.

Only points below the sensor's mounting height are drawn (what the extraction keeps), so
bridges and sign gantries vanish while dashes, solid lines and the gaps that vehicles leave
behind them show. preview.png holds the whole drive and a 150 m close-up in the ego's frame;
--preview adds one close-up per 200 m of the drive under preview/.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import PowerNorm  # noqa: E402

from lidar2xodr.simulation.lidar import ScanOut  # noqa: E402
from lidar2xodr.simulation.poses import PoseTrack  # noqa: E402

MAX_POINTS = 4_000_000
NEAR_M = 80.0
TILE_EVERY_M = 200.0
MAX_TILES = 100


class PreviewCollector:
    """Keeps a decimated share of the points below sensor height within NEAR_M of the sensor."""

    def __init__(self, mount_z: float, intensity_scale: float, expected_points: int) -> None:
        self.mount_z = mount_z
        self.scale = intensity_scale
        self.stride = max(1, math.ceil(expected_points * 0.5 / MAX_POINTS))
        self.origin: np.ndarray | None = None
        self.xy: list[np.ndarray] = []
        self.z: list[np.ndarray] = []
        self.val: list[np.ndarray] = []

    def add(self, scan: ScanOut) -> None:
        keep = (scan.height < self.mount_z) & (np.hypot(scan.xyz[:, 0], scan.xyz[:, 1]) < NEAR_M)
        idx = np.flatnonzero(keep)[:: self.stride]
        world = scan.world[idx]
        if self.origin is None:
            self.origin = scan.origin[:2].copy()
        self.xy.append((world[:, :2] - self.origin).astype(np.float32))
        self.z.append(world[:, 2].astype(np.float32))
        self.val.append(np.minimum(scan.intensity[idx] / self.scale, 1.2).astype(np.float32))

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """World xy and reflectivity (1.0 = 100 %) of the kept points."""
        if not self.xy or self.origin is None:
            return np.zeros((0, 2)), np.zeros(0, np.float32)
        return np.concatenate(self.xy).astype(np.float64) + self.origin, np.concatenate(self.val)

    def heights(self) -> np.ndarray:
        """World z of the kept points."""
        return np.concatenate(self.z) if self.z else np.zeros(0, np.float32)


def _raster(xy: np.ndarray, val: np.ndarray, x0: float, y0: float, px: float, w: int, h: int) -> np.ndarray:
    img = np.full((h, w), -1.0, dtype=np.float32)
    ix = np.floor((xy[:, 0] - x0) / px).astype(np.int64)
    iy = np.floor((xy[:, 1] - y0) / px).astype(np.int64)
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    np.maximum.at(img, (iy[ok], ix[ok]), val[ok])
    return np.ma.masked_less(img, 0.0)


def _local(xy: np.ndarray, origin: np.ndarray, rot: np.ndarray) -> np.ndarray:
    fwd = rot[:2, 0] / np.linalg.norm(rot[:2, 0])
    left = np.array([-fwd[1], fwd[0]])
    d = xy - origin[:2]
    return np.column_stack([d @ fwd, d @ left])


def _closeup(ax, xy: np.ndarray, val: np.ndarray, ego: PoseTrack, k: int, title: str) -> None:
    local = _local(xy, ego.pos[k], ego.rot[k])
    sel = (local[:, 0] > -25) & (local[:, 0] < 125) & (np.abs(local[:, 1]) < 25)
    img = _raster(local[sel], val[sel], -25.0, -25.0, 0.1, 1500, 500)
    ax.set_facecolor("black")
    ax.imshow(img, origin="lower", extent=(-25, 125, -25, 25), cmap="inferno", norm=PowerNorm(0.5, 0.0, 1.0),
              interpolation="nearest")
    ax.plot([0], [0], marker=">", color="cyan", markersize=8)
    ax.set_xlabel("metres ahead of the ego (x forward)")
    ax.set_ylabel("metres left")
    ax.set_title(title, fontsize=9)


def render(path: Path, col: PreviewCollector, ego: PoseTrack, title: str, closeup_k: int) -> None:
    """preview.png: the whole drive on top, one close-up below."""
    xy, val = col.points()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(12, 10), gridspec_kw={"height_ratios": [1.3, 1.0]})
    fig.patch.set_facecolor("white")
    if len(xy):
        lo, hi = xy.min(axis=0) - 5.0, xy.max(axis=0) + 5.0
        span = float(max(hi - lo))
        px = max(0.1, span / 1800.0)
        w, h = int(math.ceil((hi[0] - lo[0]) / px)), int(math.ceil((hi[1] - lo[1]) / px))
        img = _raster(xy, val, lo[0], lo[1], px, max(w, 1), max(h, 1))
        top.set_facecolor("black")
        top.imshow(img, origin="lower", extent=(lo[0], lo[0] + w * px, lo[1], lo[1] + h * px), cmap="inferno",
                   norm=PowerNorm(0.5, 0.0, 1.0), interpolation="nearest")
    top.plot(ego.pos[:, 0], ego.pos[:, 1], color="cyan", linewidth=0.4, alpha=0.6)
    top.set_aspect("equal")
    top.set_title(title, fontsize=10)
    top.set_xlabel("map x (m)")
    top.set_ylabel("map y (m)")
    _closeup(bottom, xy, val, ego, closeup_k, f"close-up at t = {closeup_k / ego.hz:.1f} s (reflectivity, "
             "points below sensor height)")
    fig.tight_layout()
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)


def render_tiles(folder: Path, col: PreviewCollector, ego: PoseTrack) -> list[Path]:
    """One close-up per TILE_EVERY_M of ego travel (at most MAX_TILES, evenly spread)."""
    folder.mkdir(parents=True, exist_ok=True)
    xy, val = col.points()
    total = float(ego.u[-1] - ego.u[0])
    marks = np.arange(0.0, total, TILE_EVERY_M)
    if len(marks) > MAX_TILES:
        marks = marks[np.linspace(0, len(marks) - 1, MAX_TILES).astype(int)]
    out = []
    for j, m in enumerate(marks):
        k = int(np.searchsorted(ego.u, ego.u[0] + m))
        k = min(k, len(ego.u) - 1)
        fig, ax = plt.subplots(figsize=(12, 4.6))
        _closeup(ax, xy, val, ego, k, f"u = {m:.0f} m, t = {k / ego.hz:.1f} s")
        fig.tight_layout()
        p = folder / f"{j:03d}.png"
        fig.savefig(p, dpi=110, metadata={"Software": None})
        plt.close(fig)
        out.append(p)
    return out
