"""DBSCAN in blocks: scikit-learn's labels, in working memory that does not grow with the drive.

scikit-learn's `DBSCAN.fit` holds every point's whole neighbourhood at once (on a 50 km drive's
voxel centroids, most of the markings stage's peak memory). Here the neighbourhoods are found
for one block of points at a time against one KD-tree of all points:

1. every point's weighted neighbour count (itself included) decides whether it is a core point;
2. core points within `eps` of each other are joined (union-find over the block's pairs, each
   cluster named by its lowest core index);
3. a border point (not core, a core point within `eps`) joins the neighbouring cluster with the
   lowest name: the one scikit-learn's expansion, which starts clusters in point order and never
   relabels a point, reaches it from first.

So the labels are scikit-learn's, numbered in the same order (its clusters are found in order of
their lowest core index too); `tests/test_dbscan.py` compares them.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

BLOCK_POINTS = 1 << 14  # points whose neighbourhoods are held at once


def dbscan(points: np.ndarray, eps: float, min_samples: float, weights: np.ndarray | None = None,
           block: int = BLOCK_POINTS) -> np.ndarray:
    """Labels 0..C-1 (-1 = noise): scikit-learn's
    `DBSCAN(eps=eps, min_samples=min_samples).fit(points, sample_weight=weights).labels_`."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    tree = cKDTree(points)
    count = np.zeros(n)
    for a, i, j in _pairs(points, tree, eps, block):
        count[a:a + block] += np.bincount(i, w[j], minlength=min(block, n - a))
    core = count >= min_samples
    parent = np.arange(n)
    border_i, border_j = [], []
    for a, i, j in _pairs(points, tree, eps, block):
        gi = i + a
        both = core[gi] & core[j]
        _union(parent, gi[both], j[both])
        edge = ~core[gi] & core[j]
        border_i.append(gi[edge])
        border_j.append(j[edge])
    root = _roots(parent, np.arange(n))
    name = np.where(core, root, n)
    bi, bj = np.concatenate(border_i), np.concatenate(border_j)
    np.minimum.at(name, bi, root[bj])
    labels = np.full(n, -1, dtype=np.int64)
    kept = name < n
    _, rank = np.unique(name[kept], return_inverse=True)
    labels[kept] = rank
    return labels


def _pairs(points: np.ndarray, tree: cKDTree, eps: float, block: int) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """(first index of the block, block-local i, global j) of every pair within eps, one block at a time."""
    for a in range(0, len(points), block):
        m = cKDTree(points[a:a + block]).sparse_distance_matrix(tree, eps, output_type="ndarray")
        yield a, m["i"], m["j"]


def _roots(parent: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The root of every x (pointer jumping); compresses the paths it walked."""
    r = parent[x]
    while True:
        rr = parent[r]
        if np.array_equal(rr, r):
            parent[x] = r
            return r
        r = rr


def _union(parent: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """Join the trees of every pair (a, b); each merged tree's root is its lowest root."""
    ra, rb = _roots(parent, a), _roots(parent, b)
    diff = ra != rb
    if not diff.any():
        return
    ra, rb = ra[diff], rb[diff]
    nodes, inv = np.unique(np.concatenate([ra, rb]), return_inverse=True)
    k = len(ra)
    graph = coo_matrix((np.ones(k, dtype=np.int8), (inv[:k], inv[k:])), shape=(len(nodes), len(nodes)))
    _, comp = connected_components(graph, directed=False)
    lowest = np.full(comp.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(lowest, comp, nodes)
    parent[nodes] = lowest[comp]
