"""The drive's road built along stretches of the drive when the markings' road axis misses it (`lanes.along_drive`)."""

from __future__ import annotations

import numpy as np
import pytest

from lidar2xodr.data import Boundary, GroundPlanes, LaneModel, LaneSection, MarkingCloud, Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.lanes.along_drive import build_along_drive, held_length


def _road(x0: float, x1: float, y: float) -> LaneModel:
    """A straight two-lane road along x at height y (boundaries at y + 3.5, y, y - 3.5)."""
    s = np.arange(0.0, x1 - x0 + 1e-9, 1.0)
    ref = np.stack([x0 + s, np.full_like(s, y), np.zeros_like(s)], axis=1)
    bounds = [Boundary(0, np.full_like(s, 3.5)), Boundary(1, np.zeros_like(s), "broken"),
              Boundary(2, np.full_like(s, -3.5))]
    return LaneModel(s=s, reference=ref, boundaries=bounds, sections=[LaneSection(0.0, float(s[-1]), [0, 1, 2])])


def _cloud(length: float = 1000.0) -> MarkingCloud:
    """A drive along x at y = -1.75 (the right lane of a road at y = 0) and markings beside it and far off."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, length / 25.0, 0.1)
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, 0, 3], poses[:, 1, 3] = 25.0 * t, -1.75
    x = rng.uniform(0.0, length, 6000)
    near = np.stack([x[:3000], rng.choice([3.5, 0.0, -3.5], 3000), np.zeros(3000)], axis=1)
    far = np.stack([x[3000:], 200.0 + rng.choice([3.5, 0.0, -3.5], 3000), np.zeros(3000)], axis=1)
    xyz = np.vstack([near, far])
    n = len(xyz)
    planes = GroundPlanes(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    return MarkingCloud(xyz=xyz, intensity=np.ones(n, np.float32), scan_index=np.zeros(n, np.int32),
                        time=np.zeros(n), planes=planes, trajectory=Trajectory(t, poses))


def test_held_length_counts_the_path_on_the_carriageway() -> None:
    road = _road(0.0, 100.0, 0.0)
    along = np.stack([np.arange(-20.0, 150.0, 1.0), np.full(170, 1.0)], axis=1)
    assert held_length(road, along) == pytest.approx(101.0, abs=2.0)
    beside = np.stack([np.arange(0.0, 100.0, 1.0), np.full(100, 5.0)], axis=1)
    assert held_length(road, beside) == 0.0


def test_a_road_under_none_of_the_drive_is_built_again_along_it() -> None:
    """The road found from all markings lies 200 m off the drive (a town's streets threaded into one
    axis): the road is built again from the markings along stretches of the drive, and the one that
    holds most of the drive is kept, with a warning naming the stretch. Each stretch's build sees only
    markings near the drive, and its own part of the trajectory."""
    cloud = _cloud()
    seen: list[tuple[float, float]] = []

    def build(sub: MarkingCloud) -> LaneModel:
        assert np.all(np.abs(sub.xyz[:, 1]) <= 30.0)
        x = sub.trajectory.positions[:, 0]
        seen.append((float(x.min()), float(x.max())))
        if x.min() > 600.0:
            raise InputError("marking cloud", "no stretch of road has two marking lines a lane apart")
        return _road(float(x.min()), float(x.max()), 0.0)

    model = build_along_drive(cloud, _road(0.0, 1000.0, 200.0), build)
    assert len(seen) >= 5 and all(b - a <= 300.0 + 1e-6 for a, b in seen)
    assert model.reference[0, 1] == 0.0 and model.s[-1] == pytest.approx(300.0, abs=3.0)
    assert "lies under 0 m" in model.warnings[0] and "stretch 0-300 m" in model.warnings[0]


def test_a_road_under_the_drive_is_kept_as_built() -> None:
    cloud = _cloud()

    def build(sub: MarkingCloud) -> LaneModel:
        raise AssertionError("a road under the drive is not built again")

    road = _road(0.0, 1000.0, 0.0)
    assert build_along_drive(cloud, road, build) is road


def test_lanes_command_and_build_look_along_the_drive(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`lidar2xodr lanes` and `build`'s lanes stage both pass their road through `build_along_drive`
    (so `lanes` + `export` give the map `build` gives)."""
    import sys

    from typer.testing import CliRunner

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from synth_markings import make_road, straight

    import lidar2xodr.lanes.along_drive as along
    from lidar2xodr.cli import app
    from lidar2xodr.markings_io import save_markings
    from lidar2xodr.pipeline import BuildPipeline

    calls: list[int] = []

    def spy(cloud: MarkingCloud, model: LaneModel, build: object) -> LaneModel:
        calls.append(len(cloud.xyz))
        return model

    monkeypatch.setattr(along, "build_along_drive", spy)
    road = make_road([straight(300.0)], lane_widths=(3.5, 3.5), seed=2)
    save_markings(road.cloud, tmp_path / "m.ply")
    result = CliRunner().invoke(app, ["lanes", str(tmp_path / "m.ply"), "-o", str(tmp_path / "lanes.json")])
    assert result.exit_code == 0, result.output
    BuildPipeline(tmp_path / "no-drive", tmp_path / "map.xodr").lanes(road.cloud)
    assert len(calls) == 2 and calls[0] == calls[1] == len(road.cloud.xyz)
