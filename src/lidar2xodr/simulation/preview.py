"""Bird's-eye pictures of the accumulated scans (true poses), coloured by reflectivity.

Only points below the sensor's mounting height are drawn (what the extraction keeps), so
bridges and sign gantries vanish while dashes, solid lines and the gaps that vehicles leave
behind them show. preview.png holds the whole drive (decimated; long, straight drives are cut
into stacked strips along their main direction) and a full-density 150 m x 50 m close-up in the
ego's frame where most traffic is just ahead; --preview adds one close-up per 200 m of the
drive under preview/ (every second point).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
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
BOX = (-25.0, 125.0, -25.0, 25.0)  # close-up extent in the ego frame: x0, x1, y0, y1
_NORM = PowerNorm(0.5, 0.0, 1.0)


@dataclass
class Region:
    """A close-up: points within BOX of the ego frame at pose index k, kept in that frame."""

    k: int
    origin: np.ndarray
    fwd: np.ndarray
    stride: int = 1
    title: str = ""
    xy: list[np.ndarray] = field(default_factory=list)
    val: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def at(cls, ego: PoseTrack, k: int, stride: int, title: str) -> Region:
        f = ego.rot[k][:2, 0]
        return cls(k, ego.pos[k, :2].copy(), f / np.linalg.norm(f), stride, title)

    def local(self, xy: np.ndarray) -> np.ndarray:
        d = xy - self.origin
        return np.column_stack([d @ self.fwd, d @ np.array([-self.fwd[1], self.fwd[0]])])


class PreviewCollector:
    """Keeps points below sensor height within NEAR_M of the sensor: decimated for the overview,
    all (or every stride-th) inside the close-up regions."""

    def __init__(self, mount_z: float, intensity_scale: float, expected_points: int,
                 regions: list[Region] | None = None) -> None:
        self.mount_z = mount_z
        self.scale = intensity_scale
        self.stride = max(1, math.ceil(expected_points * 0.5 / MAX_POINTS))
        self.regions = regions or []
        self._centres = np.array([r.origin + r.fwd * 50.0 for r in self.regions]).reshape(-1, 2)
        self.origin: np.ndarray | None = None
        self.xy: list[np.ndarray] = []
        self.z: list[np.ndarray] = []
        self.val: list[np.ndarray] = []

    def add(self, scan: ScanOut) -> None:
        keep = (scan.height < self.mount_z) & (np.hypot(scan.xyz[:, 0], scan.xyz[:, 1]) < NEAR_M)
        sel = np.flatnonzero(keep)
        if len(sel) == 0:
            return
        world = scan.world[sel]
        val = np.minimum(scan.intensity[sel] / self.scale, 1.2).astype(np.float32)
        if self.origin is None:
            self.origin = scan.origin[:2].copy()
        dec = slice(None, None, self.stride)
        self.xy.append((world[dec, :2] - self.origin).astype(np.float32))
        self.z.append(world[dec, 2].astype(np.float32))
        self.val.append(val[dec])
        if len(self.regions):
            near = np.flatnonzero(np.hypot(*(self._centres - world[0, :2]).T) < 200.0)
            for j in near:
                reg = self.regions[j]
                loc = reg.local(world[:: reg.stride, :2])
                x0, x1, y0, y1 = BOX
                m = (loc[:, 0] > x0) & (loc[:, 0] < x1) & (loc[:, 1] > y0) & (loc[:, 1] < y1)
                reg.xy.append(loc[m].astype(np.float32))
                reg.val.append(val[:: reg.stride][m])

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """World xy and reflectivity (1.0 = 100 %) of the decimated overview points."""
        if not self.xy or self.origin is None:
            return np.zeros((0, 2)), np.zeros(0, np.float32)
        return np.concatenate(self.xy).astype(np.float64) + self.origin, np.concatenate(self.val)

    def heights(self) -> np.ndarray:
        """World z of the decimated overview points."""
        return np.concatenate(self.z) if self.z else np.zeros(0, np.float32)


def _raster(xy: np.ndarray, val: np.ndarray, x0: float, y0: float, px: float, w: int, h: int) -> np.ndarray:
    img = np.full((h, w), -1.0, dtype=np.float32)
    ix = np.floor((xy[:, 0] - x0) / px).astype(np.int64)
    iy = np.floor((xy[:, 1] - y0) / px).astype(np.int64)
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    np.maximum.at(img, (iy[ok], ix[ok]), val[ok])
    return np.ma.masked_less(img, 0.0)


def _closeup(ax, reg: Region) -> None:
    x0, x1, y0, y1 = BOX
    xy = np.concatenate(reg.xy) if reg.xy else np.zeros((0, 2), np.float32)
    val = np.concatenate(reg.val) if reg.val else np.zeros(0, np.float32)
    img = _raster(xy, val, x0, y0, 0.1, int(round((x1 - x0) / 0.1)), int(round((y1 - y0) / 0.1)))
    ax.set_facecolor("black")
    ax.imshow(img, origin="lower", extent=BOX, cmap="inferno", norm=_NORM, interpolation="nearest")
    ax.plot([0], [0], marker=">", color="cyan", markersize=8)
    ax.set_xlabel("metres ahead of the ego (x forward)")
    ax.set_ylabel("metres left")
    ax.set_title(reg.title, fontsize=9)


def _overview(fig, spec, xy: np.ndarray, val: np.ndarray, path_xy: np.ndarray, title: str) -> None:
    """The whole drive; elongated drives as stacked strips along their principal direction."""
    c = path_xy.mean(axis=0)
    _, _, vt = np.linalg.svd(path_xy[:: max(1, len(path_xy) // 2000)] - c, full_matrices=False)
    e1, e2 = vt[0], np.array([-vt[0][1], vt[0][0]])
    a, b = (xy - c) @ e1, (xy - c) @ e2
    pa, pb = (path_xy - c) @ e1, (path_xy - c) @ e2
    span_a = float(np.ptp(pa)) + 40.0
    span_b = float(max(np.ptp(pb), np.ptp(b) if len(b) else 0.0)) + 40.0
    strips = int(np.clip(round(math.sqrt(span_a / (12.0 * span_b))), 1, 8)) if span_a > 6 * span_b else 1
    if strips == 1:
        ax = fig.add_subplot(spec)
        if len(xy):
            lo, hi = xy.min(axis=0) - 5.0, xy.max(axis=0) + 5.0
            px = max(0.1, float(max(hi - lo)) / 1800.0)
            w, h = int(math.ceil((hi[0] - lo[0]) / px)), int(math.ceil((hi[1] - lo[1]) / px))
            ax.set_facecolor("black")
            ax.imshow(_raster(xy, val, lo[0], lo[1], px, max(w, 1), max(h, 1)), origin="lower",
                      extent=(lo[0], lo[0] + w * px, lo[1], lo[1] + h * px), cmap="inferno", norm=_NORM,
                      interpolation="nearest")
        ax.plot(path_xy[:, 0], path_xy[:, 1], color="cyan", linewidth=0.4, alpha=0.6)
        ax.set_aspect("equal")
        ax.set_xlabel("map x (m)")
        ax.set_ylabel("map y (m)")
        ax.set_title(title, fontsize=10)
        return
    sub = spec.subgridspec(strips, 1, hspace=0.6)
    a0 = float(pa.min()) - 20.0
    length = span_a / strips
    b0 = float(min(pb.min(), b.min() if len(b) else pb.min())) - 20.0
    b1 = float(max(pb.max(), b.max() if len(b) else pb.max())) + 20.0
    for k in range(strips):
        ax = fig.add_subplot(sub[k])
        lo = a0 + k * length
        m = (a >= lo) & (a < lo + length)
        px = max(0.1, length / 1800.0)
        w, h = int(math.ceil(length / px)), max(1, int(math.ceil((b1 - b0) / px)))
        ax.set_facecolor("black")
        ax.imshow(_raster(np.column_stack([a[m], b[m]]), val[m], lo, b0, px, w, h), origin="lower",
                  extent=(lo, lo + w * px, b0, b0 + h * px), cmap="inferno", norm=_NORM, interpolation="nearest",
                  aspect="equal")
        ax.set_yticks([])
        ax.tick_params(labelsize=7)
        if k == 0:
            ax.set_title(title + f"\n(drive cut into {strips} strips along its main direction, metres)", fontsize=10)


def render(path: Path, col: PreviewCollector, ego: PoseTrack, title: str) -> None:
    """preview.png: the whole drive on top, the first close-up region below."""
    xy, val = col.points()
    fig = plt.figure(figsize=(12, 10))
    grid = fig.add_gridspec(2, 1, height_ratios=[1.3, 1.0])
    _overview(fig, grid[0], xy, val, ego.pos[:, :2], title)
    if col.regions:
        _closeup(fig.add_subplot(grid[1]), col.regions[0])
    fig.tight_layout()
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)


def tile_regions(ego: PoseTrack) -> list[Region]:
    """One close-up per TILE_EVERY_M of ego travel (at most MAX_TILES, evenly spread), every 2nd point."""
    total = float(ego.u[-1] - ego.u[0])
    marks = np.arange(0.0, total, TILE_EVERY_M)
    if len(marks) > MAX_TILES:
        marks = marks[np.linspace(0, len(marks) - 1, MAX_TILES).astype(int)]
    out = []
    for m in marks:
        k = min(int(np.searchsorted(ego.u, ego.u[0] + m)), len(ego.u) - 1)
        out.append(Region.at(ego, k, 2, f"u = {m:.0f} m, t = {k / ego.hz:.1f} s (every 2nd point)"))
    return out


def render_tiles(folder: Path, regions: list[Region]) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for j, reg in enumerate(regions):
        fig, ax = plt.subplots(figsize=(12, 4.6))
        _closeup(ax, reg)
        fig.tight_layout()
        p = folder / f"{j:03d}.png"
        fig.savefig(p, dpi=110, metadata={"Software": None})
        plt.close(fig)
        out.append(p)
    return out
