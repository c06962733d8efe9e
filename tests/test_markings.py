"""Alg. 1: clusters, slicing, centres and directions, SearchMark and Combine on synthetic markings."""

from __future__ import annotations

import numpy as np
import pytest
from synth_markings import arc, make_road, polyline_distance, straight

from lidar2xodr import markings
from lidar2xodr.config import MarkingsConfig
from lidar2xodr.errors import InputError
from lidar2xodr.markings import Clusters, cluster_markings, combine, find_candidates, search_mark

CFG = MarkingsConfig()


def _paint(
    rng: np.random.Generator,
    s0: float,
    s1: float,
    y: float,
    width: float,
    density: float = 300.0,
    x0: float = 5.0,
) -> np.ndarray:
    """Points of a straight painted stripe along x (from x0 + s0 to x0 + s1) at lateral y."""
    n = rng.poisson(density * width * (s1 - s0))
    xs = rng.uniform(x0 + s0, x0 + s1, n)
    ys = y + rng.uniform(-width / 2, width / 2, n)
    return np.column_stack([xs, ys, rng.normal(0.0, 0.02, n)])


def _dashed(
    rng: np.random.Generator,
    length: float,
    y: float,
    gaps: tuple[tuple[float, float], ...] = (),
    dash: float = 6.0,
    gap: float = 12.0,
) -> tuple[np.ndarray, int]:
    parts, n_dash = [], 0
    for a in np.arange(0.0, length, dash + gap):
        if any(g0 <= a + dash and a <= g1 for g0, g1 in gaps):
            continue
        parts.append(_paint(rng, a, a + dash, y, 0.15))
        n_dash += 1
    return np.vstack(parts), n_dash


def test_dash_centre_direction_and_length() -> None:
    rng = np.random.default_rng(0)
    ang = np.radians(30.0)
    local = _paint(rng, 0.0, 6.0, 0.0, 0.15, x0=-3.0)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    xy = local[:, :2] @ rot.T + np.array([-50.0, -20.0])
    cl = cluster_markings(np.column_stack([xy, local[:, 2]]), CFG)
    assert len(cl) == 1
    assert np.allclose(cl.centers[0, :2], [-50.0, -20.0], atol=0.05)
    assert cl.lengths[0] == pytest.approx(6.0, abs=0.1)
    # direction is the dash's axis, turned to point away from the world origin
    assert abs(abs(cl.directions[0] @ rot[:, 0]) - 1.0) < 1e-3
    assert cl.directions[0] @ cl.centers[0, :2] > 0


def test_stray_points_do_not_move_the_centre() -> None:
    rng = np.random.default_rng(1)
    dash = _paint(rng, 0.0, 6.0, 0.0, 0.15)
    stray = np.array([[5.0 + 3.0, 0.5, 0.0], [5.0 + 3.2, 0.55, 0.0]])
    cl = cluster_markings(np.vstack([dash, stray]), CFG)
    assert len(cl) == 1
    assert abs(cl.centers[0, 1]) < 0.03


def test_long_solid_lines_are_sliced_along_the_curve() -> None:
    road = make_road(
        [arc(150.0, 100.0)], lane_widths=(3.5,), ego_lane=0, occlusions=0, spurious=0, blobs=0, seed=2
    )
    cl = cluster_markings(road.cloud.xyz, CFG)
    # two solid edges of 150 m on a 100 m radius: about 25 slices each, all about 6 m long
    assert 44 <= len(cl) <= 56
    inner = cl.lengths > 1.0
    assert np.all(np.abs(cl.lengths[inner] - 6.0) < 1.0)


def test_chaining_a_dashed_line_across_an_occlusion() -> None:
    rng = np.random.default_rng(3)
    # the occlusion hides two dashes: 54 m between centres, beyond SearchMark (27 m), within Combine (63 m)
    pts, n_dash = _dashed(rng, 600.0, 0.0, gaps=((200.0, 225.0),))
    cands = find_candidates(pts, CFG)
    assert len(cands) == 1
    c = cands[0]
    assert len(c.centers) == n_dash
    assert np.all(np.diff(c.centers[:, 0]) > 0), "centres are ordered along the line from the origin"
    assert np.all(c.directions[:, 0] > 0.99)


def test_parallel_lines_with_blobs_between_stay_apart() -> None:
    rng = np.random.default_rng(4)
    left, _ = _dashed(rng, 400.0, 1.75)
    right, _ = _dashed(rng, 400.0, -1.75, gaps=((100.0, 130.0),))
    blobs = [
        np.column_stack([rng.uniform(-1, 1, 40) + x, rng.uniform(-0.5, 0.5, 40) + y, np.zeros(40)])
        for x, y in ((60.0, 0.0), (120.0, -0.6), (130.0, 0.4), (250.0, -0.2))
    ]
    cands = find_candidates(np.vstack([left, right, *blobs]), CFG)
    for c in cands:
        ys = c.centers[:, 1]
        on_left = np.abs(ys - 1.75) < 0.5
        on_right = np.abs(ys + 1.75) < 0.5
        assert not (on_left.any() and on_right.any()), "a candidate mixes both lines"
    long = [c for c in cands if len(c.centers) > 5]
    assert len(long) == 2


def test_candidates_are_deterministic() -> None:
    road = make_road([straight(300.0)], lane_widths=(3.75, 3.75), seed=5)
    a = find_candidates(road.cloud.xyz, CFG)
    b = find_candidates(road.cloud.xyz.copy(), CFG)
    assert len(a) == len(b)
    for ca, cb in zip(a, b, strict=True):
        assert ca.id == cb.id
        assert np.array_equal(ca.centers, cb.centers)
        assert np.array_equal(ca.cluster_ids, cb.cluster_ids)


def test_road_lines_become_one_candidate_each() -> None:
    road = make_road(
        [straight(200.0), arc(400.0, 2000.0)],
        lane_widths=(3.75, 3.75, 3.75),
        occlusions=4,
        spurious=100,
        blobs=10,
        seed=6,
    )
    cands = find_candidates(road.cloud.xyz, CFG)
    long = [c for c in cands if len(c.centers) >= 10]
    assert len(long) == 4
    for c in long:
        # (almost) every centre of a candidate lies on one truth line; absorbed blobs may sit beside it
        d = np.array([polyline_distance(c.centers[:, :2], road.line_xy(line, road.s)) for line in road.lines])
        best = np.argmin(np.median(d, axis=1))
        assert np.sum(d[best] >= 0.3) <= max(2, 0.05 * len(c.centers))
        assert np.all(d[best] < 1.75)


def test_bad_points_are_input_errors() -> None:
    with pytest.raises(InputError, match="shape"):
        find_candidates(np.zeros((10, 2)), CFG)
    bad = np.zeros((10, 3))
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        find_candidates(bad, CFG)
    assert find_candidates(np.zeros((0, 3)), CFG) == []


def _clusters(centers: list[tuple[float, float]], angles_deg: list[float], lengths: list[float]) -> Clusters:
    """Hand-made clusters (centres at z = 0) for SearchMark and Combine on exact geometry."""
    ang = np.radians(np.asarray(angles_deg))
    n = len(centers)
    return Clusters(
        labels=np.zeros(0, dtype=np.int64),
        centers=np.column_stack([np.asarray(centers, dtype=np.float64), np.zeros(n)]),
        directions=np.column_stack([np.cos(ang), np.sin(ang)]),
        lengths=np.asarray(lengths, dtype=np.float64),
        widths=np.full(n, 0.15),
        sizes=np.full(n, 50),
    )


def test_search_does_not_step_onto_the_next_lane_line() -> None:
    """Three dashes along y = 0, the last one turned by 9 degrees (Eq. 1 turns the search by 4.5),
    then the neighbouring line 3 m to the left: the ball at 18 m lands 1.6 m from its first dash,
    but that dash lies 3 m beside the line extrapolated from the chain, so the chain must stop."""
    cl = _clusters(
        [(10.0, 0.0), (28.0, 0.0), (46.0, 0.0), (64.0, 3.0), (82.0, 3.0), (100.0, 3.0)],
        [0.0, 0.0, 9.0, 0.0, 0.0, 0.0],
        [6.0] * 6,
    )
    line_of = np.array([0, 0, 0, 1, 1, 1])
    for gate, crosses in ((CFG.max_lateral_offset_m, False), (100.0, True)):
        cfg = CFG.model_copy(update={"max_lateral_offset_m": gate})
        chains = combine(search_mark(cl, cfg), cl, cfg)
        assert any(len(set(line_of[c])) > 1 for c in chains) is crosses
    chains = combine(search_mark(cl, CFG), cl, CFG)
    assert sorted(sorted(c.tolist()) for c in chains) == [[0, 1, 2], [3, 4, 5]]


def test_chain_is_cut_at_a_hop_across_the_road_and_loses_off_line_blobs() -> None:
    """A chain along y = 0 with a blob 1.7 m beside it and a final hop across the road (75 deg)."""
    cl = _clusters(
        [(10.0, 0.0), (28.0, 0.0), (37.0, 1.7), (46.0, 0.0), (64.0, 0.0), (67.0, 11.0), (68.0, 16.0)],
        [0.0, 0.0, 40.0, 0.0, 0.0, 80.0, 80.0],
        [6.0, 6.0, 0.3, 6.0, 6.0, 0.3, 0.3],
    )
    chains = combine([np.arange(7)], cl, CFG)
    assert sorted(sorted(c.tolist()) for c in chains) == [[0, 1, 3, 4], [2], [5], [6]]


def test_chain_ends_are_computed_once_per_chain(monkeypatch: pytest.MonkeyPatch) -> None:
    """Combine's linking rounds reuse the ends of chains they did not change: the same candidates as
    computing every chain's ends again in every round, with fewer extrapolations."""
    road = make_road([straight(200.0), arc(300.0, 1500.0)], lane_widths=(3.75, 3.75), occlusions=8, seed=9)
    calls = []
    original = markings._chain_ends

    def counted(*args: object) -> list:
        calls.append(1)
        return original(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(markings, "_chain_ends", counted)
    cached = find_candidates(road.cloud.xyz, CFG)
    n_cached = len(calls)
    terminals = markings._terminals
    monkeypatch.setattr(markings, "_terminals",
                        lambda chains, clusters, cfg, ends=None: terminals(chains, clusters, cfg))
    calls.clear()
    fresh = find_candidates(road.cloud.xyz, CFG)
    assert n_cached < len(calls)
    assert len(cached) == len(fresh) > 2
    for a, b in zip(cached, fresh, strict=True):
        assert np.array_equal(a.centers, b.centers)
        assert np.array_equal(a.cluster_ids, b.cluster_ids)
