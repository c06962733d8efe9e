"""Roadside scenery of the simulator (simulation/roadside.py): beside the road on both sides, seeded,
off by default, and clear of other roads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from test_simulation import _lane, tiny_map

from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.simulation import reflectivity as R
from lidar2xodr.simulation.roadside import TERRAIN_GAP_M, icosphere
from lidar2xodr.simulation.scene import StaticWorld, build_world

LEFT_EDGE, RIGHT_EDGE = 1.0, -9.5  # tiny_map: a 1 m border lane left, 3.5 + 3.5 + 2.5 m right


def _world(path: Path, seed: int = 3, roadside: bool = True) -> StaticWorld:
    odr = OpenDriveMap.load(path)
    return build_world(odr, list(odr.roads), seed, roadside)


def _tri(world: StaticWorld, *materials: int) -> np.ndarray:
    return world.tri[np.isin(world.material, materials)].astype(np.float64) + world.origin


def test_icosphere_is_a_closed_unit_sphere() -> None:
    v, f = icosphere()
    assert v.shape == (42, 3) and f.shape == (80, 3)
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert np.all(count == 2)  # every edge between two faces: no holes
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(np.einsum("ij,ij->i", normal, v[f].mean(axis=1)) > 0)  # all faces wound outwards


def test_scenery_lines_both_sides_beyond_the_verges(tmp_path: Path) -> None:
    xodr = tiny_map(tmp_path / "tiny.xodr", 1000.0)
    world = _world(xodr)
    plants = _tri(world, R.FOLIAGE, R.WOOD).reshape(-1, 3)
    y = plants[:, 1]
    assert np.all((y > LEFT_EDGE + 5.0) | (y < RIGHT_EDGE - 5.0)), "a plant on or next to the road"
    for side in (y > LEFT_EDGE, y < RIGHT_EDGE):
        x = plants[side, 0]
        assert np.histogram(x, bins=10, range=(0.0, 1000.0))[0].min() > 0, "a 100 m stretch without plants"
    assert plants[:, 2].max() > 8.0  # trees, not only bushes
    grass = _tri(world, R.GRASS).reshape(-1, 3)
    far = np.abs(grass[:, 1] - (LEFT_EDGE + RIGHT_EDGE) / 2) > 30.0
    assert far.any() and grass[far, 2].max() > 1.0 and grass[far, 2].min() < -1.5  # cuttings and embankments
    bare = _world(xodr, roadside=False)
    assert not np.isin(bare.material, [R.FOLIAGE, R.WOOD]).any()
    assert len(bare.tri) < len(world.tri)


def test_scenery_follows_the_seed(tmp_path: Path) -> None:
    xodr = tiny_map(tmp_path / "tiny.xodr", 600.0)
    a, b, c = _world(xodr, 3), _world(xodr, 3), _world(xodr, 4)
    assert np.array_equal(a.tri, b.tri) and np.array_equal(a.base, b.base)
    assert a.tri.shape != c.tri.shape or not np.array_equal(a.tri, c.tri)


def _two_roads(path: Path, gap: float = 40.0) -> Path:
    """Two straight one-way roads along +x, the second `gap` metres left of the first."""
    lanes = (f'<lanes><laneSection s="0"><left>{_lane(1, "border", 1.0, None)}</left><center><lane id="0" '
             f'type="none" level="false"/></center><right>{_lane(-1, "driving", 3.5, "broken")}'
             f'{_lane(-2, "driving", 3.5, "solid")}{_lane(-3, "shoulder", 2.5, None)}</right></laneSection></lanes>')
    roads = "".join(
        f'<road name="r{k}" length="800" id="{k}" junction="-1"><link/><planView><geometry s="0" x="0" y="{y}" '
        f'hdg="0" length="800"><line/></geometry></planView>{lanes}</road>' for k, y in ((1, 0.0), (2, gap)))
    path.write_text(f'<?xml version="1.0" encoding="UTF-8"?><OpenDRIVE><header revMajor="1" revMinor="7" '
                    f'name="two"/>{roads}</OpenDRIVE>', encoding="utf-8")
    return path


def test_scenery_keeps_clear_of_another_road(tmp_path: Path) -> None:
    """Nothing stands on the other road; between the roads the terrain stays level (ramps stay in sight)."""
    gap = 40.0
    world = _world(_two_roads(tmp_path / "two.xodr", gap))
    paved = [(RIGHT_EDGE, LEFT_EDGE), (gap + RIGHT_EDGE, gap + LEFT_EDGE)]
    plants = _tri(world, R.FOLIAGE, R.WOOD).reshape(-1, 3)
    grass = _tri(world, R.GRASS)
    raised = grass[grass[:, :, 2].max(axis=1) > 0.0].reshape(-1, 3)  # terrain above road level (not the verges)
    for lo, hi in paved:
        assert not np.any((plants[:, 1] > lo - 6.0) & (plants[:, 1] < hi + 6.0))
        assert not np.any((raised[:, 1] > lo - TERRAIN_GAP_M) & (raised[:, 1] < hi + TERRAIN_GAP_M))
    between = (grass[:, :, 1].min(axis=1) > LEFT_EDGE) & (grass[:, :, 1].max(axis=1) < gap + RIGHT_EDGE)
    assert between.any() and grass[between, :, 2].max() < 0.5
    outside = grass[:, :, 1].max(axis=1) < RIGHT_EDGE - 20.0
    assert grass[outside, :, 2].max() > 1.0  # beyond, the terrain does rise
