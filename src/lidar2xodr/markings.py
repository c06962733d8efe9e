"""Candidate lines from lane-marking points (paper Alg. 1): clusters, directions, SearchMark, Combine.

Decisions the paper leaves open (parameters in `MarkingsConfig`):
- DBSCAN runs in 3D with eps = 0.6 m (dashes are 0.15-0.30 m wide and 12 m apart, lines 3.5 m
  apart, so 0.6 m bridges sparse far-away returns without joining lines) and min_samples = 5. To
  bound memory on 50 km drives it runs on point-count-weighted centroids of 0.2 m voxels
  (sample_weight = points per voxel), and the labels are mapped back to the points.
- "Longer than 30 m" is the geodesic length of the cluster (shortest path over its 1 m cells), and
  the slices are equal pieces of about 6 m along that path, so curved kilometre-long edge lines
  are sliced along the curve rather than along a straight axis.
- LineRANSAC is 2D (x, y), vectorised over all clusters with a seeded generator, and refined by a
  principal-axis fit of its inliers. Heights are used as a gate (`search_z_tolerance_m`) in every
  search, which keeps lines on bridges and below them apart.
- Directions are unified away from the world origin (paper); inside a chain every new direction is
  also turned to agree with the previous one, so roads that bend back towards the origin still
  chain. A found cluster steers the search (Eq. 1) only when it is elongated (longer than
  `min_direction_length_m` and 3x its width) and turns the search by less than `max_turn_deg`;
  otherwise the previous direction is kept. A found cluster that is neither elongated nor on the
  line (within `segment_tolerance_m`) joins the chain but the search goes on from the previous
  centre: blobs beside a line were stepping stones to the neighbouring line. The centre is the
  box centre of the RANSAC inliers in the line's own frame, so stray points attached to a dash
  do not move it.
- SearchMark takes the unvisited centre nearest to the expected point, in the first 3 m step that
  finds one; candidate ids are given in order of the first centre's distance to the origin (the
  paper's random ids would break "same input, same output").
- Combine: terminals (both ends) of all candidates are matched along an extrapolation (quadratic
  in the last 60 m when available: a 63 m search on a 2 km radius drifts by 1 m otherwise) over
  `combine_search_m`; candidates whose start or end lies on another candidate (point-to-segment)
  and whose overlapping centres all lie on it are merged into it. Both repeat until nothing
  merges; every result is ordered from its end nearer the origin (DistSort). Terminals sit on a
  chain's first and last elongated cluster; chains of blobs only are never linked, and only a
  chain holding an elongated cluster can absorb another (blobs bridged lines otherwise).
- Lateral gate (ours; the paper gates by the ball only): once a chain's bases span a search step,
  a SearchMark hit must lie within `max_lateral_offset_m` (0.8 m, a third of the minimum lane
  width) of the line extrapolated from them, and a Combine link needs each end within that of
  the other's extrapolation. One dash turned by a few degrees steered the 1.75 m ball onto the
  next lane line; the paper's 3 m steps, 27 m reach, 1.75 m ball and 63 m Combine are unchanged.
- Chains are pruned before and after Combine: a blob between two elongated clusters lying more
  than `max_lateral_offset_m` beside them leaves the chain, and the chain is cut at a step that
  deviates by more than `combine_max_angle_deg` from its smoothed direction while moving more
  than `max_lateral_offset_m` sideways (blob-to-blob hops across the road).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from lidar2xodr.config import MarkingsConfig
from lidar2xodr.data import Candidate
from lidar2xodr.dbscan import dbscan
from lidar2xodr.errors import InputError

_RANSAC_SAMPLES = 48
_MAX_CURV = 1.0 / 500.0  # curvature allowed in the Combine extrapolation (63 m on R 500 m: 4 m)
_CHUNK = 1024
_BLOCK_POINTS = 1 << 18  # marking points per block of `_line_fit`


@dataclass
class Clusters:
    """Marking clusters (after slicing): one centre, direction and length each."""

    labels: np.ndarray  # (N,) cluster per point, -1 = noise
    centers: np.ndarray  # (C, 3) bounding-box centres
    directions: np.ndarray  # (C, 2) unit line directions, unified away from the origin
    lengths: np.ndarray  # (C,) extent along the direction
    widths: np.ndarray  # (C,) extent across it
    sizes: np.ndarray  # (C,) points per cluster

    def __len__(self) -> int:
        return len(self.centers)


def find_candidates(xyz: np.ndarray, cfg: MarkingsConfig) -> list[Candidate]:
    """Paper Alg. 1: cluster the markings, chain the clusters (SearchMark) and combine the chains."""
    clusters = cluster_markings(xyz, cfg)
    chains = combine(search_mark(clusters, cfg), clusters, cfg)
    return to_candidates(chains, clusters)


# --------------------------------------------------------------------------------------------
# clusters


def cluster_markings(xyz: np.ndarray, cfg: MarkingsConfig) -> Clusters:
    """DBSCAN, slicing of long clusters, bounding-box centres and unified RANSAC directions."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError("marking cloud", f"points have shape {xyz.shape}, expected (N, 3)")
    if not np.all(np.isfinite(xyz)):
        raise InputError("marking cloud", "points contain NaN or infinite coordinates")
    labels = _dbscan(xyz, cfg) if len(xyz) else np.zeros(0, dtype=np.int64)
    labels = _slice_long(xyz, labels, cfg)
    order, starts, sizes = _groups(labels)
    pts = xyz[order]
    if len(starts) == 0:
        z = np.zeros((0, 3))
        return Clusters(labels, z, z[:, :2], z[:, 0], z[:, 0], np.zeros(0, dtype=np.int64))
    centers, directions, lengths, widths = _line_fit(pts, starts, sizes, cfg)
    flip = np.einsum("ij,ij->i", directions, centers[:, :2]) < 0
    directions[flip] *= -1.0
    return Clusters(labels, centers, directions, lengths, widths, sizes)


def _dbscan(xyz: np.ndarray, cfg: MarkingsConfig) -> np.ndarray:
    """3D DBSCAN (scikit-learn's labels, in blocks: dbscan.py) on weighted voxel centroids; labels compact
    0..C-1 in point order, -1 = noise."""
    v = cfg.dbscan_voxel_m
    cell = np.floor((xyz - xyz.min(axis=0)) / v).astype(np.int64)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    cent = np.stack([np.bincount(inverse, xyz[:, k] - xyz[0, k]) for k in range(3)], axis=1) / counts[:, None]
    vox_labels = dbscan(cent, cfg.dbscan_eps_m, cfg.dbscan_min_samples, weights=counts)
    labels = vox_labels[inverse]
    sizes = np.bincount(labels[labels >= 0]) if np.any(labels >= 0) else np.zeros(0, dtype=np.int64)
    small = sizes < cfg.min_cluster_points
    labels = np.where((labels >= 0) & ~small[np.maximum(labels, 0)], labels, -1)
    return _compact(labels)


def _compact(labels: np.ndarray) -> np.ndarray:
    """Renumber clusters 0..C-1 in the order of their first point (deterministic)."""
    valid = labels >= 0
    if not valid.any():
        return np.full(len(labels), -1, dtype=np.int64)
    uniq, first = np.unique(labels[valid], return_index=True)
    rank = np.empty(len(uniq), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(uniq))
    out = np.full(len(labels), -1, dtype=np.int64)
    out[valid] = rank[np.searchsorted(uniq, labels[valid])]
    return out


def _groups(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point order sorted by cluster (noise dropped), start offsets and sizes of clusters 0..C-1."""
    valid = np.flatnonzero(labels >= 0)
    order = valid[np.argsort(labels[valid], kind="stable")]
    sizes = np.bincount(labels[order]) if len(order) else np.zeros(0, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64) if len(sizes) else sizes
    return order, starts, sizes


def _slice_long(xyz: np.ndarray, labels: np.ndarray, cfg: MarkingsConfig) -> np.ndarray:
    """Cut clusters longer than `slice_threshold_m` into ~`slice_length_m` pieces along their path."""
    order, starts, sizes = _groups(labels)
    if len(starts) == 0:
        return labels
    pts = xyz[order, :2]
    extent = np.maximum.reduceat(pts, starts, axis=0) - np.minimum.reduceat(pts, starts, axis=0)
    long = np.flatnonzero(np.hypot(extent[:, 0], extent[:, 1]) > cfg.slice_threshold_m)
    out = labels.copy()
    next_id = len(starts)
    for c in long:
        idx = order[starts[c] : starts[c] + sizes[c]]
        part = _geodesic_slices(xyz[idx, :2], cfg.slice_threshold_m, cfg.slice_length_m)
        more = part > 0
        out[idx[more]] = next_id + part[more] - 1
        next_id += int(part.max())
    return _compact(out)


def _geodesic_slices(xy: np.ndarray, threshold: float, length: float) -> np.ndarray:
    """Slice index per point: equal pieces of about `length` along the cluster's shortest-path axis."""
    cell = np.floor(xy).astype(np.int64)
    keys, inverse = np.unique(cell, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    counts = np.bincount(inverse)
    cent = np.stack([np.bincount(inverse, xy[:, k]) for k in range(2)], axis=1) / counts[:, None]
    n = len(keys)
    pairs = cKDTree(keys.astype(np.float64)).query_pairs(1.5, output_type="ndarray")
    w = np.linalg.norm(cent[pairs[:, 0]] - cent[pairs[:, 1]], axis=1) + 1e-6
    graph = coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    ncomp, comp = connected_components(graph, directed=False)
    slice_of_cell = np.zeros(n, dtype=np.int64)
    next_slice = 0
    for k in range(ncomp):
        nodes = np.flatnonzero(comp == k)
        d0 = dijkstra(graph, directed=False, indices=nodes[0])
        far = nodes[np.argmax(d0[nodes])]
        arc = dijkstra(graph, directed=False, indices=far)[nodes]
        total = float(arc.max())
        pieces = 1 if total <= threshold else max(1, int(round(total / length)))
        piece = np.minimum((arc / max(total, 1e-9) * pieces).astype(np.int64), pieces - 1)
        slice_of_cell[nodes] = next_slice + piece
        next_slice += pieces
    return slice_of_cell[inverse]


def _line_fit(
    pts: np.ndarray, starts: np.ndarray, sizes: np.ndarray, cfg: MarkingsConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Seeded RANSAC line per cluster (vectorised over clusters), refined on its inliers.

    Returns centres, directions, lengths (inliers along the line) and widths (all points across it,
    so a blob with a thin line of inliers inside is not taken for a marking). The centre is the
    centre of the inliers' bounding box in the line's own frame (a stray bright point that DBSCAN
    attached to a dash moves an axis-aligned box by decimetres). The clusters are fitted in blocks
    of about `_BLOCK_POINTS` points with their share of the seeded draws (`_uniforms`), so the
    working memory does not grow with the drive and the result is the same as in one block.
    """
    n_c = len(starts)
    k, m = cfg.line_ransac_iterations, _RANSAC_SAMPLES
    out = [np.zeros((n_c, 3)), np.zeros((n_c, 2)), np.zeros(n_c), np.zeros(n_c)]
    ends = np.append(starts[1:], len(pts)) if n_c else starts
    a = 0
    while a < n_c:
        b = max(int(np.searchsorted(ends, starts[a] + _BLOCK_POINTS, side="right")), a + 1)
        lo, hi = int(starts[a]), int(ends[b - 1])
        draws = (_uniforms(cfg.seed, a * k, (b - a, k)), _uniforms(cfg.seed, (n_c + a) * k, (b - a, k)),
                 _uniforms(cfg.seed, 2 * n_c * k + a * m, (b - a, m)))
        fit = _line_fit_block(pts[lo:hi], starts[a:b] - lo, sizes[a:b], draws, cfg)
        for whole, part in zip(out, fit, strict=True):
            whole[a:b] = part
        a = b
    return out[0], out[1], out[2], out[3]


def _uniforms(seed: int, skip: int, shape: tuple[int, int]) -> np.ndarray:
    """Uniform draws number `skip` onwards of `default_rng(seed)` (PCG64 draws one 64-bit word per
    double), so a block's draws are those of one `random` call for all clusters: draws of all
    pair starts (clusters x k), then all pair ends, then all scored samples."""
    gen = np.random.Generator(np.random.PCG64(seed))
    gen.bit_generator.advance(skip)
    return gen.random(shape)


def _line_fit_block(
    pts: np.ndarray, starts: np.ndarray, sizes: np.ndarray, draws: tuple[np.ndarray, np.ndarray, np.ndarray],
    cfg: MarkingsConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`_line_fit` on the clusters of one block, with their uniform draws (pair starts, pair ends, scored samples)."""
    n_c = len(starts)
    label = np.repeat(np.arange(n_c), sizes)
    mean = np.stack([np.bincount(label, pts[:, k], n_c) for k in range(3)], axis=1) / sizes[:, None]
    xy = pts[:, :2] - mean[label, :2]
    pick = lambda r: starts[:, None] + np.minimum((r * sizes[:, None]).astype(np.int64), sizes[:, None] - 1)  # noqa: E731
    i1, i2, js = (pick(r) for r in draws)
    best_u = np.tile([1.0, 0.0], (n_c, 1))
    best_p = np.zeros((n_c, 2))
    thr = cfg.line_ransac_distance_m
    for a in range(0, n_c, _CHUNK):
        sl = slice(a, min(a + _CHUNK, n_c))
        p1, p2 = xy[i1[sl]], xy[i2[sl]]
        d = p2 - p1
        norm = np.linalg.norm(d, axis=2)
        u = d / np.maximum(norm, 1e-12)[..., None]
        rel = xy[js[sl]][:, None, :, :] - p1[:, :, None, :]
        dist = np.abs(u[:, :, None, 0] * rel[..., 1] - u[:, :, None, 1] * rel[..., 0])
        score = np.where(norm > 1e-6, (dist <= thr).sum(axis=2), -1)
        kb = np.argmax(score, axis=1)
        rows = np.arange(len(kb))
        best_u[sl] = np.where((score[rows, kb] >= 0)[:, None], u[rows, kb], best_u[sl])
        best_p[sl] = p1[rows, kb]
    off = xy - best_p[label]
    inl = np.abs(best_u[label, 0] * off[:, 1] - best_u[label, 1] * off[:, 0]) <= thr
    few = np.bincount(label, inl, n_c) < 3
    inl |= few[label]
    w = inl.astype(np.float64)
    sw = np.bincount(label, w, n_c)
    mx = np.bincount(label, w * xy[:, 0], n_c) / sw
    my = np.bincount(label, w * xy[:, 1], n_c) / sw
    dx, dy = xy[:, 0] - mx[label], xy[:, 1] - my[label]
    sxx = np.bincount(label, w * dx * dx, n_c)
    syy = np.bincount(label, w * dy * dy, n_c)
    sxy = np.bincount(label, w * dx * dy, n_c)
    ang = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    refined = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    dirs = np.where(((sw >= 3) & (sxx + syy > 1e-9))[:, None], refined, best_u)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    along = dx * dirs[label, 0] + dy * dirs[label, 1]
    across = dy * dirs[label, 0] - dx * dirs[label, 1]
    big = np.where(inl, 0.0, np.inf)
    lo = np.minimum.reduceat(np.stack([along + big, across + big, pts[:, 2] + big], axis=1), starts, axis=0)
    hi = np.maximum.reduceat(np.stack([along - big, across - big, pts[:, 2] - big], axis=1), starts, axis=0)
    mid = 0.5 * (lo + hi)
    normal = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
    cxy = mean[:, :2] + np.stack([mx, my], axis=1) + dirs * mid[:, :1] + normal * mid[:, 1:2]
    centers = np.column_stack([cxy, mid[:, 2]])
    widths = np.maximum.reduceat(across, starts) - np.minimum.reduceat(across, starts)
    return centers, dirs, hi[:, 0] - lo[:, 0], widths


# --------------------------------------------------------------------------------------------
# SearchMark


def search_mark(clusters: Clusters, cfg: MarkingsConfig) -> list[np.ndarray]:
    """Chain clusters into candidate lines: ordered cluster indices, one array per candidate."""
    n = len(clusters)
    if n == 0:
        return []
    centers, dirs = clusters.centers, clusters.directions
    tree = cKDTree(centers[:, :2])
    steps = np.arange(cfg.search_step_m, cfg.search_max_m + 1e-9, cfg.search_step_m)
    visited = np.zeros(n, dtype=bool)
    cos_turn = np.cos(np.radians(cfg.max_turn_deg))
    strong = _elongated(clusters, cfg)
    chains: list[np.ndarray] = []
    for start in np.argsort(np.linalg.norm(centers[:, :2], axis=1), kind="stable"):
        if visited[start]:
            continue
        visited[start] = True
        chain = [int(start)]
        bases = [int(start)]
        v_star_prev = dirs[start]
        v = dirs[start]
        while True:
            base = bases[-1]
            found, d = _next_center(tree, centers, visited, bases, v, steps, cfg)
            if found < 0:
                break
            between = _on_segment(
                tree, centers, visited, centers[base], centers[found], cfg.segment_tolerance_m
            )
            for i in [*[b for b in between if b != found], found]:
                visited[i] = True
                chain.append(int(i))
            own = dirs[found] if float(dirs[found] @ v) >= 0 else -dirs[found]
            elongated = bool(strong[found])
            rel = centers[found, :2] - centers[base, :2]
            on_line = abs(float(rel[0] * v[1] - rel[1] * v[0])) <= cfg.segment_tolerance_m
            if not (elongated or on_line):
                continue
            bases.append(int(found))
            v_star = own if elongated and float(own @ v) >= cos_turn else v
            v = cfg.gamma * v_star + (1.0 - cfg.gamma) * v_star_prev
            v /= max(float(np.linalg.norm(v)), 1e-9)
            v_star_prev = v_star
        chains.append(np.asarray(chain, dtype=np.int64))
    return chains


def _next_center(
    tree: cKDTree,
    centers: np.ndarray,
    visited: np.ndarray,
    bases: list[int],
    v: np.ndarray,
    steps: np.ndarray,
    cfg: MarkingsConfig,
) -> tuple[int, float]:
    """The unvisited centre nearest to c + v * d in the first step d that finds one (-1 if none).

    Once the chain's bases span a search step, a hit must also lie within `max_lateral_offset_m`
    of the line extrapolated from them: one dash turned by a few degrees steers the ball 3 m aside
    at 20 m, onto the neighbouring lane line.
    """
    cur = centers[bases[-1]]
    slope = 0.0
    if len(bases) >= 2:
        prev = centers[bases[-2]]
        slope = (cur[2] - prev[2]) / max(float(np.linalg.norm(cur[:2] - prev[:2])), 1e-3)
    expected = cur[:2] + steps[:, None] * v
    line = centers[bases, :2]
    gated = len(bases) >= 2 and float(np.linalg.norm(line[-1] - line[0])) >= cfg.search_step_m
    if gated:
        out, pred = _extrapolate(line, v, steps)
    for k, hits in enumerate(tree.query_ball_point(expected, cfg.search_radius_m)):
        if not hits:
            continue
        hits = np.asarray(hits)
        hits = hits[~visited[hits]]
        hits = hits[np.abs(centers[hits, 2] - cur[2] - slope * steps[k]) <= cfg.search_z_tolerance_m]
        if gated:
            rel = centers[hits, :2] - pred[k]
            hits = hits[np.abs(rel[:, 0] * out[1] - rel[:, 1] * out[0]) <= cfg.max_lateral_offset_m]
        if len(hits):
            best = hits[np.argmin(np.linalg.norm(centers[hits, :2] - expected[k], axis=1))]
            return int(best), float(steps[k])
    return -1, 0.0


def _on_segment(
    tree: cKDTree, centers: np.ndarray, visited: np.ndarray, a: np.ndarray, b: np.ndarray, tol: float
) -> list[int]:
    """Unvisited centres within `tol` of the segment a-b (strictly between), ordered from a to b."""
    ab = b[:2] - a[:2]
    length = float(np.linalg.norm(ab))
    if length < 1e-6:
        return []
    hits = np.asarray(tree.query_ball_point(0.5 * (a[:2] + b[:2]), 0.5 * length + tol), dtype=np.int64)
    hits = hits[~visited[hits]]
    if len(hits) == 0:
        return []
    rel = centers[hits, :2] - a[:2]
    along = rel @ ab / length**2
    lateral = np.abs(rel[:, 0] * ab[1] - rel[:, 1] * ab[0]) / length
    ok = (
        (along > 0) & (along < 1) & (lateral <= tol) & (np.abs(centers[hits, 2] - a[2]) <= 1.0 + 0.1 * length)
    )
    sel = hits[ok]
    return [int(i) for i in sel[np.argsort(along[ok], kind="stable")]]


# --------------------------------------------------------------------------------------------
# Combine and DistSort


@dataclass
class _Terminal:
    point: np.ndarray  # (T, 3)
    out: np.ndarray  # (T, 2) outward unit directions
    predicted: np.ndarray  # (T, D, 2) expected positions along the search
    valid: np.ndarray  # (T,) False for chains without an elongated cluster


def combine(chains: list[np.ndarray], clusters: Clusters, cfg: MarkingsConfig) -> list[np.ndarray]:
    """Merge chains end to start (search of `combine_search_m`) and chains lying on others, until stable."""
    chains = [_dist_sort(c, clusters.centers) for c in _prune_all(chains, clusters, cfg)]
    ends: dict[bytes, list] = {}
    for _ in range(20):
        linked = _link_terminals(chains, clusters, cfg, ends)
        merged = _absorb(linked, clusters, cfg)
        changed = len(merged) != len(chains)
        chains = merged
        if not changed:
            break
    chains = [_dist_sort(c, clusters.centers) for c in _prune_all(chains, clusters, cfg)]
    first = np.array([np.linalg.norm(clusters.centers[c[0], :2]) for c in chains])
    return [chains[i] for i in np.argsort(first, kind="stable")]


def _prune_all(chains: list[np.ndarray], clusters: Clusters, cfg: MarkingsConfig) -> list[np.ndarray]:
    """`_prune` on every chain; what it takes out becomes chains of its own."""
    strong = _elongated(clusters, cfg)
    out: list[np.ndarray] = []
    for chain in chains:
        out.extend(_prune(chain, clusters, strong, cfg))
    return out


def _prune(chain: np.ndarray, clusters: Clusters, strong: np.ndarray, cfg: MarkingsConfig) -> list[np.ndarray]:
    """Split a chain where it leaves its own line; the pieces in chain order, off-line blobs alone.

    A blob (not elongated) between two elongated clusters of the chain that lies more than
    `max_lateral_offset_m` beside the segment joining them is taken out. A step whose direction
    deviates by more than `combine_max_angle_deg` from the chain's smoothed direction (the
    elongated clusters' directions nearest before and after it; the chord of a chain of blobs)
    and that moves more than `max_lateral_offset_m` sideways is a hop to another line: the chain
    is cut there.
    """
    if len(chain) < 2:
        return [chain]
    xy = clusters.centers[chain, :2]
    idx = np.arange(len(chain))
    sidx = idx[strong[chain]]
    alone: list[np.ndarray] = []
    if len(sidx) >= 2:
        nxt = np.searchsorted(sidx, idx, side="right")
        inner = ~strong[chain] & (nxt > 0) & (nxt < len(sidx))
        a = sidx[np.clip(nxt - 1, 0, len(sidx) - 1)]
        b = sidx[np.clip(nxt, 0, len(sidx) - 1)]
        ab = xy[b] - xy[a]
        ln = np.maximum(np.linalg.norm(ab, axis=1), 1e-9)
        rel = xy - xy[a]
        off = inner & (np.abs(rel[:, 0] * ab[:, 1] - rel[:, 1] * ab[:, 0]) / ln > cfg.max_lateral_offset_m)
        alone = [chain[i : i + 1] for i in np.flatnonzero(off)]
        chain, xy = chain[~off], xy[~off]
        if len(chain) < 2:
            return [chain, *alone]
    seg = np.diff(xy, axis=0)
    d = _chain_dirs(chain, clusters)
    sidx = np.flatnonzero(strong[chain])
    if len(sidx):
        j = np.arange(len(seg))
        before = sidx[np.clip(np.searchsorted(sidx, j, side="right") - 1, 0, len(sidx) - 1)]
        after = sidx[np.clip(np.searchsorted(sidx, j + 1, side="left"), 0, len(sidx) - 1)]
        ref = d[before] + d[after]
    else:
        ref = np.repeat((xy[-1] - xy[0])[None], len(seg), axis=0)
    ref /= np.maximum(np.linalg.norm(ref, axis=1), 1e-9)[:, None]
    lateral = np.abs(seg[:, 0] * ref[:, 1] - seg[:, 1] * ref[:, 0])
    along = np.abs(np.einsum("ij,ij->i", seg, ref))
    cos_max = np.cos(np.radians(cfg.combine_max_angle_deg))
    hop = (lateral > cfg.max_lateral_offset_m) & (along < cos_max * np.hypot(along, lateral))
    cuts = np.flatnonzero(hop) + 1
    return [*np.split(chain, cuts), *alone]


def _dist_sort(chain: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """Order a chain from its end nearer the world origin."""
    if len(chain) > 1 and np.linalg.norm(centers[chain[-1], :2]) < np.linalg.norm(centers[chain[0], :2]):
        return chain[::-1].copy()
    return chain


def _chain_dirs(chain: np.ndarray, clusters: Clusters) -> np.ndarray:
    """Cluster directions turned to follow the chain order."""
    d = clusters.directions[chain].copy()
    if len(chain) > 1:
        xy = clusters.centers[chain, :2]
        chord = np.gradient(xy, axis=0)
        d[np.einsum("ij,ij->i", d, chord) < 0] *= -1.0
    return d


def _terminals(chains: list[np.ndarray], clusters: Clusters, cfg: MarkingsConfig,
               ends: dict[bytes, list] | None = None) -> _Terminal:
    """Head (index 2k) and tail (2k + 1) of every chain with outward directions and extrapolations.

    Terminals sit on the first and last elongated cluster: a blob at a chain's end (or a chain of
    blobs, whose terminals are marked invalid) would steer the search off the line.
    """
    dists = np.arange(cfg.search_step_m, cfg.combine_search_m + 1e-9, cfg.search_step_m)
    strong = _elongated(clusters, cfg)
    pts, outs, preds, valid = [], [], [], []
    ends = {} if ends is None else ends
    for chain in chains:
        key = chain.tobytes()
        if key not in ends:
            ends[key] = _chain_ends(chain, clusters, strong, dists)
        for point, out, pred, ok in ends[key]:
            pts.append(point)
            outs.append(out)
            preds.append(pred)
            valid.append(ok)
    return _Terminal(
        np.array(pts).reshape(-1, 3),
        np.array(outs).reshape(-1, 2),
        np.array(preds).reshape(-1, len(dists), 2),
        np.array(valid, dtype=bool),
    )


def _chain_ends(chain: np.ndarray, clusters: Clusters, strong: np.ndarray, dists: np.ndarray) -> list[tuple]:
    """(point, outward direction, extrapolation, valid) of a chain's head and tail."""
    keep = np.flatnonzero(strong[chain])
    core = chain[keep[0] : keep[-1] + 1] if len(keep) else chain
    d = _chain_dirs(core, clusters)
    out = []
    for seq, u in ((core[::-1], -d[0]), (core, d[-1])):
        o, p = _extrapolate(clusters.centers[seq, :2], u, dists)
        out.append((clusters.centers[seq[-1]], o, p, len(keep) > 0))
    return out


def _elongated(clusters: Clusters, cfg: MarkingsConfig) -> np.ndarray:
    """Clusters shaped like a piece of a line (not blobs or specks)."""
    return clusters.lengths >= np.maximum(cfg.min_direction_length_m, 3.0 * clusters.widths)


def _extrapolate(
    xy: np.ndarray, u: np.ndarray, dists: np.ndarray, span: float = 60.0
) -> tuple[np.ndarray, np.ndarray]:
    """Outward direction and expected positions beyond the last point of an ordered polyline."""
    last = xy[-1]
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    from_end = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
    use = from_end <= span
    if use.sum() >= 2 and from_end[use].max() >= 3.0:
        chord = last - xy[use][0]
        u = chord / np.linalg.norm(chord)
    n = np.array([-u[1], u[0]])
    rel = xy[use] - last
    al, lat = rel @ u, rel @ n
    slope = curv = 0.0
    if use.sum() >= 4 and -al.min() >= 20.0:
        coef = np.polyfit(al, lat, 2)
        if np.sqrt(np.mean((np.polyval(coef, al) - lat) ** 2)) < 0.3:
            curv, slope = float(np.clip(coef[0], -_MAX_CURV / 2, _MAX_CURV / 2)), float(coef[1])
    out = u + n * slope
    out /= np.linalg.norm(out)
    pred = last + dists[:, None] * u + (slope * dists + curv * dists**2)[:, None] * n
    return out, pred


class _UnionFind:
    def __init__(self, n: int) -> None:
        self.parent = np.arange(n)

    def find(self, i: int) -> int:
        root = i
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[i] != root:
            self.parent[i], i = root, self.parent[i]
        return int(root)

    def union(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.parent[max(ra, rb)] = min(ra, rb)
        return True


def _link_terminals(chains: list[np.ndarray], clusters: Clusters, cfg: MarkingsConfig,
                    ends: dict[bytes, list] | None = None) -> list[np.ndarray]:
    """Combine: join facing chain ends found along each end's extrapolation (shortest reach first)."""
    if len(chains) < 2:
        return chains
    term = _terminals(chains, clusters, cfg, ends)
    tree = cKDTree(term.point[:, :2])
    cos_max = np.cos(np.radians(cfg.combine_max_angle_deg))
    dists = np.arange(cfg.search_step_m, cfg.combine_search_m + 1e-9, cfg.search_step_m)
    proposals = []
    for a in np.flatnonzero(term.valid):
        for k, hits in enumerate(tree.query_ball_point(term.predicted[a], cfg.search_radius_m)):
            hits = np.asarray(hits, dtype=np.int64)
            hits = hits[(hits // 2 != a // 2) & term.valid[hits]]
            hits = hits[term.out[hits] @ term.out[a] <= -cos_max]
            dz = np.abs(term.point[hits, 2] - term.point[a, 2])
            hits = hits[dz <= cfg.search_z_tolerance_m + 0.1 * dists[k]]
            gap = term.point[hits, :2] - term.point[a, :2]
            gap /= np.maximum(np.linalg.norm(gap, axis=1), 1e-9)[:, None]
            hits = hits[
                (gap @ term.out[a] >= cos_max) & (np.einsum("ij,ij->i", gap, -term.out[hits]) >= cos_max)
            ]
            hits = hits[_both_on_line(term, a, hits, k, dists, cfg.max_lateral_offset_m)]
            if len(hits):
                off = np.linalg.norm(term.point[hits, :2] - term.predicted[a, k], axis=1)
                proposals.append((float(dists[k]), float(off.min()), a, int(hits[np.argmin(off)])))
                break
    partner = np.full(len(term.point), -1, dtype=np.int64)
    uf = _UnionFind(len(chains))
    for _, _, a, b in sorted(proposals):
        if partner[a] < 0 and partner[b] < 0 and uf.union(a // 2, b // 2):
            partner[a], partner[b] = b, a
    if not np.any(partner >= 0):
        return chains
    used = np.zeros(len(chains), dtype=bool)
    out: list[np.ndarray] = []
    ends = [c for c in range(len(chains)) if partner[2 * c] < 0 or partner[2 * c + 1] < 0]
    for c0 in ends + list(range(len(chains))):
        if used[c0]:
            continue
        parts, c, forward = [], c0, partner[2 * c0] < 0
        while True:
            used[c] = True
            parts.append(chains[c] if forward else chains[c][::-1])
            nxt = partner[2 * c + 1] if forward else partner[2 * c]
            if nxt < 0 or used[nxt // 2]:
                break
            c, forward = int(nxt // 2), nxt % 2 == 0
        out.append(np.concatenate(parts))
    return out


def _both_on_line(
    term: _Terminal, a: int, hits: np.ndarray, k: int, dists: np.ndarray, tol: float
) -> np.ndarray:
    """Mask of ends `hits` within `tol` beside the extrapolation of end `a` (at step k) and with `a`
    within `tol` beside each hit's own extrapolation (at the step nearest to their distance).

    Both lines must agree: an end extrapolated with a slight slope reaches the start of the
    neighbouring lane line, which, extrapolated back, passes a lane away from it.
    """
    rel = term.point[hits, :2] - term.predicted[a, k]
    ua = term.out[a]
    ok = np.abs(rel[:, 0] * ua[1] - rel[:, 1] * ua[0]) <= tol
    gap = np.linalg.norm(term.point[hits, :2] - term.point[a, :2], axis=1)
    kb = np.clip(np.rint(gap / dists[0]).astype(np.int64) - 1, 0, len(dists) - 1)
    back = term.point[a, :2] - term.predicted[hits, kb]
    ub = term.out[hits]
    return ok & (np.abs(back[:, 0] * ub[:, 1] - back[:, 1] * ub[:, 0]) <= tol)


def _absorb(chains: list[np.ndarray], clusters: Clusters, cfg: MarkingsConfig) -> list[np.ndarray]:
    """Combine: merge chains whose start or end lies on another chain's segments (point-to-segment)."""
    if len(chains) < 2:
        return chains
    tol = cfg.segment_tolerance_m
    samples, owner = _densify(chains, clusters.centers, 1.0)
    if len(samples) == 0:
        return chains
    tree = cKDTree(samples[:, :2])
    uf = _UnionFind(len(chains))
    strong = _elongated(clusters, cfg)
    result = {i: chains[i] for i in range(len(chains))}
    for b, chain in enumerate(chains):
        for end in (chain[0], chain[-1]):
            hits = np.asarray(tree.query_ball_point(clusters.centers[end, :2], tol + 0.5), dtype=np.int64)
            hits = hits[owner[hits] != b]
            if len(hits) == 0:
                continue
            a = int(
                owner[hits[np.argmin(np.linalg.norm(samples[hits, :2] - clusters.centers[end, :2], axis=1))]]
            )
            ra, rb = uf.find(a), uf.find(b)
            if ra == rb:
                continue
            merged = _merge_overlap(result[ra], result[rb], clusters, strong, cfg)
            if merged is not None:
                uf.union(ra, rb)
                keep = uf.find(ra)
                result.pop(ra if keep == rb else rb)
                result[keep] = merged
                break
    return [result[k] for k in sorted(result)]


def _densify(chains: list[np.ndarray], centers: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` along each chain's polyline, with the chain index of each."""
    pts, owner = [], []
    for i, chain in enumerate(chains):
        xyz = centers[chain]
        if len(xyz) == 1:
            pts.append(xyz)
            owner.append(np.full(1, i))
            continue
        seg = np.diff(xyz, axis=0)
        n = np.maximum(np.ceil(np.linalg.norm(seg[:, :2], axis=1) / step).astype(np.int64), 1)
        f = np.concatenate([np.arange(k) / k for k in n])
        base = np.repeat(np.arange(len(seg)), n)
        pts.append(np.vstack([xyz[base] + seg[base] * f[:, None], xyz[-1:]]))
        owner.append(np.full(len(f) + 1, i))
    return np.vstack(pts), np.concatenate(owner)


def _merge_overlap(
    a: np.ndarray, b: np.ndarray, clusters: Clusters, strong: np.ndarray, cfg: MarkingsConfig
) -> np.ndarray | None:
    """`a` and `b` as one chain when every centre of `b` beside `a` lies on it; else None.

    The longer chain is the host and must hold an elongated cluster (blobs host nothing).
    """
    if len(a) < len(b):
        a, b = b, a
    ca, cb = clusters.centers[a, :2], clusters.centers[b, :2]
    if len(a) < 2 or not strong[a].any():
        return None
    da = _chain_dirs(a, clusters)
    db = _chain_dirs(b, clusters) if len(b) > 1 else clusters.directions[b]
    seg = np.diff(ca, axis=0)
    seg_len = np.maximum(np.linalg.norm(seg, axis=1), 1e-9)
    rel = cb[:, None, :] - ca[None, :-1, :]
    f = np.clip(np.einsum("bsk,sk->bs", rel, seg) / seg_len**2, 0.0, 1.0)
    foot = ca[None, :-1, :] + f[..., None] * seg[None]
    dist = np.linalg.norm(cb[:, None, :] - foot, axis=2)
    j = np.argmin(dist, axis=1)
    lateral = dist[np.arange(len(b)), j]
    arc = np.concatenate([[0.0], np.cumsum(seg_len)])
    param = arc[j] + f[np.arange(len(b)), j] * seg_len[j]
    behind = np.einsum("ij,j->i", cb - ca[0], da[0]) < 0
    ahead = np.einsum("ij,j->i", cb - ca[-1], da[-1]) > 0
    inside = ~behind & ~ahead
    if not inside.any() or np.any(lateral[inside] > 2 * cfg.segment_tolerance_m):
        return None
    for mask, end, u in ((behind, ca[0], da[0]), (ahead, ca[-1], da[-1])):
        rel = cb[mask] - end
        if np.any(np.abs(rel[:, 0] * u[1] - rel[:, 1] * u[0]) > cfg.search_radius_m):
            return None
    cos_max = np.cos(np.radians(cfg.combine_max_angle_deg))
    seg_dir = seg[j] / seg_len[j, None]
    agree = np.einsum("ij,ij->i", db, seg_dir)
    if np.any(np.abs(agree[inside]) < cos_max):
        return None
    if len(b) > 1 and np.median(agree[inside]) < 0:
        b, param, behind, ahead, inside = b[::-1], param[::-1], behind[::-1], ahead[::-1], inside[::-1]
    idx = np.flatnonzero(inside)
    if np.any(behind[idx[-1] :]) or np.any(ahead[: idx[0] + 1]):
        return None
    key = np.where(behind, -1e12 + np.arange(len(b)), np.where(ahead, 1e12 + np.arange(len(b)), param))
    keys = np.concatenate([arc, key])
    return np.concatenate([a, b])[np.argsort(keys, kind="stable")]


def to_candidates(chains: list[np.ndarray], clusters: Clusters) -> list[Candidate]:
    """Candidate objects with ids in chain order."""
    return [
        Candidate(
            id=i,
            centers=clusters.centers[c].copy(),
            directions=_chain_dirs(c, clusters),
            cluster_ids=c.copy(),
        )
        for i, c in enumerate(chains)
    ]
