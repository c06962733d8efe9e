"""LiDAR odometry: synthetic drive with posts (exact truth), and the real aiMotive motorway sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_extraction import DASH_LEN, DASH_PERIOD, SOLID_Y, T0, ListDataset, aimotive_cloud, fit_edge_line, make_drive

from lidar2xodr.config import ExtractionConfig
from lidar2xodr.data import Trajectory
from lidar2xodr.extraction import ExtractionReport, extract_markings
from lidar2xodr.odometry import LidarOdometry, align_to_truth, deskew, se3_exp, se3_log, trajectory_errors


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


def _arc(n: int = 600, radius: float = 800.0, speed: float = 25.0) -> Trajectory:
    """True poses along a left-hand arc at 10 Hz, flat."""
    t = 100.0 + 0.1 * np.arange(n)
    yaw = speed * (t - t[0]) / radius
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, :3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    poses[:, 0, 3] = 300.0 + radius * np.sin(yaw)
    poses[:, 1, 3] = -50.0 + radius * (1.0 - np.cos(yaw))
    return Trajectory(times=t, poses=poses)


def _in_first_frame(truth: Trajectory, scale: float = 1.0, yaw_drift_deg: float = 0.0, climb_m: float = 0.0
                    ) -> Trajectory:
    """The truth as odometry would give it (world = first vehicle frame), with a scale, heading and height error."""
    first = np.linalg.inv(truth.poses[0])
    poses = first[None] @ truth.poses
    poses[:, :3, 3] *= scale
    f = np.linspace(0.0, 1.0, len(poses))
    poses[:, :3, :3] = Rotation.from_euler("z", np.radians(yaw_drift_deg) * f).as_matrix() @ poses[:, :3, :3]
    poses[:, 2, 3] += climb_m * f
    return Trajectory(times=truth.times.copy(), poses=poses)


def test_trajectory_errors_are_zero_for_the_truth_in_another_frame() -> None:
    truth = _arc()
    e = trajectory_errors(_in_first_frame(truth), truth)
    assert e["travelled_m"] == pytest.approx(25.0 * 59.9, rel=1e-3)
    assert abs(e["length_error_pct"]) < 1e-9 and e["aligned_max_m"] < 1e-6 and e["segment_max_m"] < 1e-6
    assert abs(e["heading_end_deg"]) < 1e-9 and abs(e["height_end_m"]) < 1e-9


def test_trajectory_errors_measure_scale_heading_and_height_drift() -> None:
    truth = _arc()
    e = trajectory_errors(_in_first_frame(truth, scale=1.01), truth)
    assert e["length_error_pct"] == pytest.approx(1.0, abs=1e-6)
    assert e["segment_mean_m"] == pytest.approx(1.0, abs=0.05)  # 1 % of every 100 m
    assert e["aligned_end_m"] > 5.0  # 15 m too long: no rigid fit hides a scale error
    e = trajectory_errors(_in_first_frame(truth, yaw_drift_deg=0.5, climb_m=-2.0), truth)
    assert e["heading_end_deg"] == pytest.approx(0.5, abs=1e-6)
    assert e["height_end_m"] == pytest.approx(-2.0, abs=1e-6)
    assert e["segment_max_m"] == pytest.approx(100.0 * np.sin(np.radians(0.5)), rel=0.05)  # facing 0.5 deg off
    rot, shift = align_to_truth(_in_first_frame(truth), truth)
    assert np.allclose(_in_first_frame(truth).positions[:, :2] @ rot.T + shift, truth.positions[:, :2], atol=1e-6)


def _traffic_scene(n: int, ego: float = 25.0, truck: float = 19.0) -> list[tuple[float, np.ndarray]]:
    """Forward-sensor scans (vehicle frame): poles beside the road, and a truck in the next lane ahead."""
    rng = np.random.default_rng(7)
    pole_x = np.arange(-20.0, 400.0, 7.0) + rng.uniform(-1.0, 1.0, 60)
    pole_y = np.where(np.arange(60) % 2 == 0, 9.0, -9.5)
    out = []
    for k in range(n):
        t = 0.1 * k
        px = np.repeat(pole_x - ego * t, 25)
        ang = rng.uniform(0.0, 2.0 * np.pi, len(px))
        poles = np.column_stack([px + 0.1 * np.cos(ang), np.repeat(pole_y, 25) + 0.1 * np.sin(ang),
                                 rng.uniform(0.4, 2.5, len(px))])
        rear = 20.0 + (truck - ego) * t
        side = np.column_stack([rng.uniform(rear, rear + 12.0, 3000), np.full(3000, -2.3), rng.uniform(0.5, 4.0, 3000)])
        back = np.column_stack([np.full(1000, rear), rng.uniform(-4.7, -2.3, 1000), rng.uniform(0.5, 4.0, 1000)])
        pts = np.vstack([poles, side, back])
        ahead = (pts[:, 0] > 2.0) & (np.abs(np.arctan2(pts[:, 1], pts[:, 0])) < np.radians(41.0))
        out.append((1000.0 + t, pts[ahead]))
    return out


def test_start_speed_is_the_static_worlds_not_the_trucks_ahead() -> None:
    """A truck fills much of a forward sensor's view; its speed relative to ours (6 m/s) must not win."""
    odo = LidarOdometry(ExtractionConfig())
    for stamp, pts in _traffic_scene(8):
        odo.add(stamp, pts, None)
    assert odo.start_speed == pytest.approx(25.0, abs=0.5)
    assert odo.max_range_m == ExtractionConfig().odometry_max_range_m  # a forward sensor: the long range


def test_a_sensor_that_sees_all_around_registers_within_the_short_range() -> None:
    rng = np.random.default_rng(1)
    az = rng.uniform(-np.pi, np.pi, 5000)
    r = rng.uniform(5.0, 150.0, 5000)
    ring = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(0.5, 3.0, 5000)])
    odo = LidarOdometry(ExtractionConfig())
    odo.add(1000.0, ring, None)
    odo.finish()
    assert odo.max_range_m == ExtractionConfig().odometry_surround_range_m


def test_simulated_motorway_drive_gives_the_true_distance(tmp_path: Path) -> None:
    """150 m of the demo road in the simulator (default Livox, mid traffic, ~6 s): the odometry
    travels the true distance within 1 %, ends within 0.5 m of the truth after the rigid fit, and
    turns and climbs with it. Without the roadside scenery (only rails and traffic beside the road)
    this drive gave -81 %: ICP found almost no forward motion."""
    from lidar2xodr.datasets import open_dataset
    from lidar2xodr.datasets.poses import read_pose_csv
    from lidar2xodr.demo_road import write_demo_road
    from lidar2xodr.simulation import SimOptions, simulate

    simulate(write_demo_road(tmp_path / "road.xodr"), tmp_path / "drive",
             SimOptions(length_m=150.0, seed=0, roadside=True))
    rep = ExtractionReport()
    cloud = extract_markings(open_dataset(tmp_path / "drive"), ExtractionConfig(odometry="lidar"), report=rep)
    truth, _ = read_pose_csv(tmp_path / "drive" / "truth" / "poses.csv")
    e = trajectory_errors(cloud.trajectory, truth)
    assert rep.odometry == "lidar" and e["travelled_m"] > 140.0
    assert abs(e["length_error_pct"]) < 1.0
    assert e["aligned_end_m"] < 0.5 and e["segment_max_m"] < 0.5
    assert abs(e["heading_end_deg"]) < 0.3 and abs(e["height_end_m"]) < 0.5
