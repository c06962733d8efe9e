"""Fusion of several drives (fusion.py): offsets recovered from the markings, lines not doubled,
drives that cannot be aligned left out with their reason, the anchor drive's GNSS kept."""

from __future__ import annotations

import numpy as np
import pytest

from lidar2xodr.config import FusionConfig
from lidar2xodr.data import GeoOrigin, GroundPlanes, MarkingCloud, Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.fusion import fuse

LINES_Y = (-1.75, 1.75, 5.25)  # right edge solid, centre dashed 6 m / 12 m, left edge solid
ORIGIN = GeoOrigin(lat=48.0, lon=11.0)


def _markings(rng: np.random.Generator, length: float, shift: np.ndarray) -> np.ndarray:
    """Marking points of a straight two-lane road, as one drive's scans leave them, moved by `shift`."""
    parts = []
    for k, y in enumerate(LINES_Y):
        x = rng.uniform(0.0, length, int(length * 20))
        if k == 1:
            x = x[(x % 18.0) < 6.0]
        parts.append(np.column_stack([x, y + rng.uniform(-0.07, 0.07, len(x)), rng.normal(0.0, 0.01, len(x))]))
    return np.concatenate(parts) + shift


def _cloud(xyz: np.ndarray, origin: GeoOrigin = ORIGIN, length: float = 300.0) -> MarkingCloud:
    n_scans = 30
    order = np.argsort(xyz[:, 0], kind="stable")
    xyz = xyz[order]
    scan = np.minimum((xyz[:, 0] / length * n_scans).astype(np.int32), n_scans - 1)
    times = np.arange(n_scans, dtype=float) * 0.1
    poses = np.repeat(np.eye(4)[None], n_scans, axis=0)
    poses[:, 0, 3] = np.linspace(0.0, length, n_scans)
    planes = GroundPlanes(times, np.tile([0.0, 0.0, 1.0], (n_scans, 1)), poses[:, :3, 3].copy())
    return MarkingCloud(xyz, np.full(len(xyz), 0.8, np.float32), scan, times[scan], planes,
                        Trajectory(times, poses), origin)


def _distance_to_lines(xyz: np.ndarray) -> np.ndarray:
    return np.min(np.abs(xyz[:, 1:2] - np.asarray(LINES_Y)[None]), axis=1)


def test_a_biased_drive_is_aligned_onto_the_first_and_its_offset_reported() -> None:
    rng = np.random.default_rng(3)
    bias = np.array([1.3, -1.1, 0.2])  # GNSS without corrections; the y part is a third of a lane
    clouds = [_cloud(_markings(rng, 300.0, np.zeros(3))), _cloud(_markings(rng, 300.0, bias))]
    fused, rep = fuse(clouds, ["a", "b"], ["gnss", "gnss"], FusionConfig(anchor=1))
    a, b = rep.drives
    assert (a.dx_m, a.dy_m, a.dz_m) == (0.0, 0.0, 0.0)
    # across the road the lines fix the offset to centimetres; along it only the dash ends do (decimetres)
    assert abs(b.dx_m + bias[0]) < 0.2 and np.allclose([b.dy_m, b.dz_m], -bias[1:], atol=0.05), b.line()
    assert b.inlier_share > 0.9 and abs(b.yaw_deg) < 0.05
    second = fused.xyz[len(clouds[0].xyz):]
    assert np.percentile(_distance_to_lines(second), 99) < 0.1, "the second drive's lines are doubled"
    dashed = second[np.abs(second[:, 1] - LINES_Y[1]) < 0.2]
    assert np.percentile(dashed[:, 0] % 18.0, 99) < 6.2, "the dashes are shifted along the road"
    assert np.all(np.diff(fused.trajectory.times) > 0) and np.all(np.diff(fused.scan_index[len(clouds[0].xyz):]) >= 0)
    assert fused.scan_index[len(clouds[0].xyz):].min() > clouds[0].scan_index.max()


def test_without_an_anchor_the_map_sits_at_the_mean_of_the_drives_gnss() -> None:
    rng = np.random.default_rng(4)
    biases = [np.zeros(3), np.array([0.8, 0.6, 0.0]), np.array([-0.4, 1.2, 0.0])]
    clouds = [_cloud(_markings(rng, 300.0, b)) for b in biases]
    fused, rep = fuse(clouds, ["a", "b", "c"], ["gnss"] * 3, FusionConfig())
    mean = np.mean(biases, axis=0)
    for d, b in zip(rep.drives, biases, strict=True):
        assert abs(d.dx_m - (mean - b)[0]) < 0.2 and abs(d.dy_m - (mean - b)[1]) < 0.05, d.line()
    assert abs(np.median(fused.xyz[:, 1] - np.round((fused.xyz[:, 1] - mean[1] + 1.75) / 3.5) * 3.5 + 1.75)
               - mean[1]) < 0.05


def test_a_drive_of_another_road_and_an_odometry_drive_are_left_out_with_their_reason() -> None:
    rng = np.random.default_rng(5)
    here = _cloud(_markings(rng, 300.0, np.zeros(3)))
    elsewhere = _cloud(_markings(rng, 300.0, np.array([5000.0, 0.0, 0.0])))
    odometry = _cloud(_markings(rng, 300.0, np.zeros(3)))
    unplaced = _cloud(_markings(rng, 300.0, np.zeros(3)), origin=GeoOrigin())
    dark = _cloud(np.zeros((0, 3)))
    fused, rep = fuse([here, elsewhere, odometry, unplaced, dark], ["here", "elsewhere", "odo", "nogeo", "dark"],
                      ["gnss", "gnss", "lidar", "gnss", "gnss"], FusionConfig())
    assert len(fused.xyz) == len(here.xyz)
    assert rep.drives[0].left_out is None
    assert "no overlap" in rep.drives[1].left_out
    assert "LiDAR odometry" in rep.drives[2].left_out
    assert "no geodetic origin" in rep.drives[3].left_out
    assert "no lane markings" in rep.drives[4].left_out
    assert [w.split(":")[0] for w in rep.warnings] == ["drive elsewhere", "drive odo", "drive nogeo", "drive dark"]
    assert rep.trajectories[0] is not None and rep.trajectories[1:] == [None] * 4


def test_markings_that_do_not_match_are_left_out() -> None:
    rng = np.random.default_rng(6)
    here = _cloud(_markings(rng, 300.0, np.zeros(3)))
    noise = np.column_stack([rng.uniform(0, 300, 6000), rng.uniform(-3, 7, 6000), np.zeros(6000)])
    _, rep = fuse([here, _cloud(noise)], ["here", "noise"], ["gnss", "gnss"], FusionConfig())
    assert "could not be aligned" in rep.drives[1].left_out


def test_a_left_out_anchor_is_an_error_naming_it() -> None:
    rng = np.random.default_rng(7)
    here = _cloud(_markings(rng, 300.0, np.zeros(3)))
    odometry = _cloud(_markings(rng, 300.0, np.zeros(3)))
    with pytest.raises(InputError, match="anchor drive.*LiDAR odometry") as err:
        fuse([here, odometry], ["here", "odo"], ["gnss", "lidar"], FusionConfig(anchor=2))
    assert str(err.value).startswith("odo")


def test_no_drive_with_markings_is_an_error_listing_each() -> None:
    dark = _cloud(np.zeros((0, 3)))
    with pytest.raises(InputError, match="no drive can be fused: a: left out .no lane markings.*b: left out"):
        fuse([dark, dark], ["a", "b"], ["gnss", "gnss"], FusionConfig())


def test_the_same_drives_give_the_same_cloud() -> None:
    clouds = [_cloud(_markings(np.random.default_rng(8 + k), 300.0, np.array([0.5 * k, -0.3 * k, 0.0])))
              for k in range(3)]
    a, _ = fuse(clouds, ["a", "b", "c"], ["gnss"] * 3, FusionConfig())
    b, _ = fuse(clouds, ["a", "b", "c"], ["gnss"] * 3, FusionConfig())
    assert a.xyz.tobytes() == b.xyz.tobytes()
