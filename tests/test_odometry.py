"""LiDAR odometry: synthetic drive with posts (exact truth), and the real aiMotive motorway sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_extraction import DASH_LEN, DASH_PERIOD, SOLID_Y, T0, ListDataset, aimotive_cloud, fit_edge_line, make_drive

from lidar2xodr.config import ExtractionConfig
from lidar2xodr.extraction import ExtractionReport, extract_markings
from lidar2xodr.odometry import deskew, se3_exp, se3_log


class NoPoses(ListDataset):
    def poses(self) -> None:  # type: ignore[override]
        return None


def test_se3_helpers_and_deskew() -> None:
    xi = np.array([1.0, -2.0, 0.5, 0.01, -0.02, 0.3])
    assert np.allclose(se3_log(se3_exp(xi)), xi)
    pts = np.array([[10.0, 0.0, 0.0], [0.0, 5.0, 1.0]])
    twist = np.array([20.0, 0, 0, 0, 0, 0])
    out = deskew(pts, np.array([0.05, -0.05]), twist)
    assert np.allclose(out, [[11.0, 0.0, 0.0], [-1.0, 5.0, 1.0]])
    assert deskew(pts, None, twist) is pts


@pytest.fixture(scope="module")
def lidar_run() -> tuple:
    drive = make_drive(n_scans=20, speed=25.0, n_ground=6000, posts=True, seed=3)
    rep = ExtractionReport()
    cloud = extract_markings(NoPoses(drive, with_times=True), ExtractionConfig(), report=rep)  # type: ignore[arg-type]
    return drive, cloud, rep


def test_lidar_odometry_recovers_the_synthetic_motion(lidar_run: tuple) -> None:
    drive, cloud, rep = lidar_run
    assert rep.odometry == "lidar"
    assert rep.start_speed_mps == pytest.approx(25.0, abs=0.5)
    t = cloud.trajectory.times
    expected = drive.speed * (t - t[0])
    pos = cloud.trajectory.positions
    assert np.max(np.abs(pos[:, 0] - expected)) < 0.15  # < 0.3 % of the 47 m driven
    assert np.max(np.abs(pos[:, 1])) < 0.15
    assert np.max(np.abs(pos[:, 2])) < 0.3  # height rests on posts only: weakly constrained
    assert cloud.origin.lat is None  # the world is the first vehicle frame, not geodetic


def test_markings_from_lidar_odometry_are_sharp(lidar_run: tuple) -> None:
    drive, cloud, _ = lidar_run
    x0 = drive.speed * (cloud.trajectory.times[0] - T0)  # world frame = vehicle frame of the first scan
    y = cloud.xyz[:, 1]
    solid = np.min(np.abs(y[:, None] - np.array(SOLID_Y)[None]), axis=1) < 0.3
    assert solid.sum() > 200
    assert np.percentile(np.min(np.abs(y[solid, None] - np.array(SOLID_Y)[None]), axis=1), 95) < 0.15
    dash = np.abs(y) < 0.3
    phase = np.mod(cloud.xyz[dash, 0] + x0, DASH_PERIOD)
    assert np.mean((phase > -0.2) & (phase < DASH_LEN + 0.2)) > 0.95


def test_lidar_odometry_is_deterministic(lidar_run: tuple) -> None:
    drive, cloud, _ = lidar_run
    again = extract_markings(NoPoses(drive, with_times=True), ExtractionConfig())  # type: ignore[arg-type]
    assert np.array_equal(again.trajectory.poses, cloud.trajectory.poses)
    assert np.array_equal(again.xyz, cloud.xyz)


@pytest.mark.slow
def test_aimotive_motorway_edge_line_is_straight(shared_data: Path) -> None:
    """Real drive without poses: 50 Pandar64 revolutions at ~30 m/s, accumulated with LiDAR odometry.

    The solid left edge line, accumulated over all 50 scans, must lie within 0.10 m of a smooth
    line along its whole length: a wrong speed doubles dashes, a yaw error bends or fans the line.
    """
    cloud, rep = aimotive_cloud(shared_data / "lidar" / "aimotive_highway_sample")
    assert rep.odometry == "lidar" and rep.scans_used == 50
    assert 25.0 < rep.start_speed_mps < 35.0
    assert rep.drive_length_m > 60.0
    speeds = np.linalg.norm(np.diff(cloud.trajectory.positions, axis=0), axis=1) / np.diff(cloud.trajectory.times)
    assert speeds.std() < 1.0  # a motorway drive at steady speed, no jumps
    fit = fit_edge_line(cloud.xyz, cloud.intensity)
    assert 1.0 < fit["y0"] < 2.5  # the solid line left of the ego lane
    assert fit["hi"] - fit["lo"] > 100.0 and fit["bins"] >= 20
    assert fit["rms"] < 0.10
    assert fit["max_bin"] < 0.10


def test_featureless_scene_warns() -> None:
    """Only the road and a car driving along: nothing fixes the forward motion, and the report says so."""
    drive = make_drive(n_scans=6, speed=25.0, n_ground=4000, posts=False, seed=5)
    rep = ExtractionReport()
    extract_markings(NoPoses(drive, with_times=True), ExtractionConfig(), report=rep)  # type: ignore[arg-type]
    assert rep.start_speed_mps is not None and rep.start_speed_mps < 0.5
    assert any("static" in w for w in rep.warnings)
