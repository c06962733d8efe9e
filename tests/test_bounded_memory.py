"""Stages that work in blocks so their memory does not grow with the drive give the same result as in one block.

DBSCAN is compared with scikit-learn's; the line fits, the frame projection and the cross-sections'
column sort with themselves run as one block (the block sizes patched up and down).
"""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.cluster import DBSCAN
from synth_markings import arc, make_road, straight

from lidar2xodr import markings
from lidar2xodr.config import Config, LanesConfig, MarkingsConfig
from lidar2xodr.dbscan import dbscan
from lidar2xodr.lanes import build_road_model, frame, structure


@pytest.mark.parametrize("seed", range(12))
def test_dbscan_gives_scikit_learns_labels(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 2500))
    centres = rng.random((int(rng.integers(1, 15)), 3)) * 15
    pts = centres[rng.integers(0, len(centres), n)] + rng.normal(0, rng.uniform(0.2, 1.2), (n, 3))
    weights = rng.integers(1, 5, n).astype(float) if seed % 2 else None
    eps, min_samples = float(rng.uniform(0.3, 0.9)), int(rng.integers(2, 9))
    ref = DBSCAN(eps=eps, min_samples=min_samples, algorithm="kd_tree").fit(pts, sample_weight=weights).labels_
    got = dbscan(pts, eps, min_samples, weights, block=int(rng.integers(1, 300)))
    assert len(set(ref)) > 2
    assert np.array_equal(got, ref)


def test_dbscan_border_point_joins_the_cluster_scikit_learn_reaches_first() -> None:
    """A point within eps of two clusters' core points but not core itself: the cluster with the lower
    first core point takes it (scikit-learn's expansion order), whichever block it is in."""
    left = np.column_stack([np.linspace(-3.0, -1.0, 9), np.zeros(9), np.zeros(9)])
    right = np.column_stack([np.linspace(1.0, 3.0, 9), np.zeros(9), np.zeros(9)])
    pts = np.vstack([right, [[0.0, 0.0, 0.0]], left])
    ref = DBSCAN(eps=1.05, min_samples=4).fit(pts).labels_
    for block in (1, 4, 10, 100):
        got = dbscan(pts, 1.05, 4, block=block)
        assert np.array_equal(got, ref)
    assert got[9] == got[0] != got[10]


def test_dbscan_of_nothing_and_of_noise() -> None:
    assert dbscan(np.zeros((0, 3)), 0.5, 3).shape == (0,)
    far = np.arange(30, dtype=float)[:, None] * np.array([[10.0, 0.0, 0.0]])
    assert np.all(dbscan(far, 0.5, 2) == -1)


def _cloud():
    return make_road([straight(250.0), arc(300.0, 900.0)], lane_widths=(3.75, 3.75), exit_lane=(280.0, 450.0, 60.0),
                     seed=3).cloud


def test_clusters_fitted_in_blocks_are_those_of_one_block(monkeypatch: pytest.MonkeyPatch) -> None:
    xyz = _cloud().xyz
    cfg = MarkingsConfig()
    monkeypatch.setattr(markings, "_BLOCK_POINTS", 10**9)
    whole = markings.cluster_markings(xyz, cfg)
    monkeypatch.setattr(markings, "_BLOCK_POINTS", 500)
    blocks = markings.cluster_markings(xyz, cfg)
    assert len(whole.sizes) > 50
    for name in ("labels", "centers", "directions", "lengths", "widths", "sizes"):
        assert np.array_equal(getattr(blocks, name), getattr(whole, name)), name


def test_block_draws_are_the_draws_of_one_generator() -> None:
    seq = np.random.default_rng(7)
    first, second = seq.random((20, 4)), seq.random((20, 4))
    assert np.array_equal(markings._uniforms(7, 3 * 4, (5, 4)), first[3:8])
    assert np.array_equal(markings._uniforms(7, 80 + 17 * 4, (3, 4)), second[17:20])


def test_lanes_in_blocks_are_those_of_one_block(monkeypatch: pytest.MonkeyPatch) -> None:
    """The frame's projection and the cross-sections' column sort, in small blocks: the same road model."""
    cloud = _cloud()
    cfg = Config()
    cands = markings.find_candidates(cloud.xyz, cfg.markings)

    def model() -> list[np.ndarray]:
        m = build_road_model(cloud, cands, LanesConfig(), markings_cfg=cfg.markings)
        return [m.s, m.reference, *[b.t for b in m.boundaries]]

    monkeypatch.setattr(frame, "_PROJECT_BLOCK", 10**9)
    monkeypatch.setattr(structure, "_SORT_CELLS", 10**12)
    whole = model()
    monkeypatch.setattr(frame, "_PROJECT_BLOCK", 333)
    monkeypatch.setattr(structure, "_SORT_CELLS", 97)
    blocks = model()
    assert len(whole) > 4
    assert len(blocks) == len(whole)
    for a, b in zip(blocks, whole, strict=True):
        assert np.array_equal(a, b, equal_nan=True)
