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
from lidar2xodr.odometry import (
    GroundMap,
    LidarOdometry,
    align_to_truth,
    deskew,
    fit_to_road,
    se3_exp,
    se3_log,
    split_scan,
    trajectory_errors,
)


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
    assert np.max(np.abs(pos[:, 2])) < 0.02  # the road holds the height (posts alone: 0.3 m)
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


SENSOR = np.array([1.5, 0.0, 1.8])
FOV = np.radians(41.0)


def _road(xy: np.ndarray, grade: float, crossfall: float) -> np.ndarray:
    return grade * xy[:, 0] + crossfall * xy[:, 1]


def _forward_drive(n: int, speed: float = 25.0, seed: int = 0, noise: float = 0.02) -> list[tuple]:
    """Forward-sensor sweeps over a flat road with posts beside it: (stamp, points, times), vehicle frame.

    Stamps at the sweep's end, every point at its own time (the vehicle moves 2.5 m per sweep).
    Road returns from 4 to 45 m with Gaussian range noise along the ray; posts every ~8 m, 9 m left
    and right, 0.3-2.5 m high: the only structure, so KISS-ICP alone has little to fix its pitch.
    """
    rng = np.random.default_rng(seed)
    post_x = np.arange(-40.0, speed * 0.1 * n + 120.0, 8.0)
    post_x = post_x + rng.uniform(-1.0, 1.0, len(post_x))
    post_y = np.where(np.arange(len(post_x)) % 2 == 0, 9.0, -9.0)
    out = []
    for k in range(n):
        stamp = 1000.0 + 0.1 * (k + 1)
        t = stamp - rng.uniform(0.0, 0.1, 5000)
        az = rng.uniform(-FOV, FOV, 5000)
        el = rng.uniform(np.arctan(SENSOR[2] / 45.0), np.arctan(SENSOR[2] / 4.0), 5000)
        ray = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
        road = SENSOR + ray * (SENSOR[2] / np.sin(el) + rng.normal(0.0, noise, 5000))[:, None]
        tp = stamp - rng.uniform(0.0, 0.1, (30, len(post_x)))
        posts = np.column_stack([(post_x - speed * (tp - 1000.0)).ravel() + rng.normal(0.0, 0.03, tp.size),
                                 np.broadcast_to(post_y, tp.shape).ravel() + rng.normal(0.0, 0.03, tp.size),
                                 rng.uniform(0.3, 2.5, tp.size)])
        seen = (posts[:, 0] > 3.0) & (posts[:, 0] < 120.0) & (np.abs(np.arctan2(posts[:, 1], posts[:, 0])) < FOV)
        out.append((stamp, np.vstack([road, posts[seen]]), np.concatenate([t, tp.ravel()[seen]])))
    return out


def _run(scans: list[tuple], cfg: ExtractionConfig, pitch_bias_deg: float = 0.0) -> LidarOdometry:
    """LidarOdometry over the scans; `pitch_bias_deg` tilts every KISS-ICP result nose-down by that much
    more than it found (the steady registration bias seen on simulated motorways, made certain)."""
    odo = LidarOdometry(cfg)
    if pitch_bias_deg:
        align = odo._reg.align_points_to_map
        tilt = se3_exp(np.array([0.0, 0.0, 0.0, 0.0, np.radians(pitch_bias_deg), 0.0]))
        odo._reg.align_points_to_map = lambda *a: align(*a) @ tilt  # type: ignore[method-assign]
    for stamp, xyz, times in scans:
        odo.add(stamp, xyz, times)
    odo.finish()
    return odo


def _pitch_deg(poses: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(poses[:, :3, :3]).as_euler("ZYX")[:, 1])


@pytest.fixture(scope="module")
def forward_drive() -> list[tuple]:
    return _forward_drive(60)


def test_the_road_holds_height_and_pitch(forward_drive: list[tuple]) -> None:
    """150 m over a flat road seen by a forward sensor: height and pitch stay at the road's."""
    odo = _run(forward_drive, ExtractionConfig())
    poses = odo.trajectory.poses
    assert odo.ground_fixes == len(poses) - 1
    assert np.max(np.abs(poses[:, 2, 3])) < 0.015  # registration alone: 0.47 m
    assert np.max(np.abs(_pitch_deg(poses))) < 0.015  # registration alone: 0.72 deg
    travelled = 25.0 * (odo.trajectory.times - odo.trajectory.times[0])
    assert np.max(np.abs(poses[:, 0, 3] - travelled)) < 0.3


def test_a_registration_pitch_bias_does_not_reach_the_poses(forward_drive: list[tuple]) -> None:
    """Every registration 0.02 deg more nose-down than it found: without the road the pitch and the
    height run away, with it the bias is undone at every scan (the fit is repeated until it moves
    the pose no more: one linear step left 2 % of KISS-ICP's error, and the road map kept it)."""
    off = _run(forward_drive, ExtractionConfig(odometry_ground=False), pitch_bias_deg=0.02)
    on = _run(forward_drive, ExtractionConfig(), pitch_bias_deg=0.02)
    assert _pitch_deg(off.trajectory.poses)[-1] > 0.5 and off.trajectory.positions[-1, 2] < -0.5
    assert np.max(np.abs(_pitch_deg(on.trajectory.poses))) < 0.015
    assert np.max(np.abs(on.trajectory.positions[:, 2])) < 0.015


def _graded_road(rng: np.random.Generator, centre: np.ndarray, n: int, grade: float = 0.04,
                 crossfall: float = 0.025) -> np.ndarray:
    """Road points (world frame) ahead of `centre` on a plane with a grade and a crossfall."""
    xy = centre[:2] + np.column_stack([rng.uniform(4.0, 40.0, n), rng.uniform(-12.0, 12.0, n)])
    return np.column_stack([xy, _road(xy, grade, crossfall)])


def _pose(x: float, y: float, grade: float = 0.04, crossfall: float = 0.025, err: tuple = (0, 0, 0)) -> np.ndarray:
    """The vehicle on the graded road at (x, y), level with it, times an error (dz, roll, pitch) in its frame."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [0.0, -np.arctan(grade), np.arctan(crossfall)]).as_matrix()
    T[:3, 3] = [x, y, grade * x + crossfall * y]
    return T @ se3_exp(np.array([0.0, 0.0, err[0], err[1], err[2], 0.0]))


@pytest.mark.parametrize("offset", [0.0, 1.0e5])
def test_ground_correction_finds_height_roll_and_pitch(offset: float) -> None:
    """A scan placed 8 cm too high, 0.3 deg rolled and 0.2 deg pitched on a road with 4 % grade and
    2.5 % crossfall, the low body of a car on it: the fit brings it back to within 1 mm and 0.005 deg,
    also 100 km from the origin (moments relative to each cell's corner)."""
    rng = np.random.default_rng(4)
    start = np.array([offset, -offset, 0.0])
    gmap = GroundMap(2.0)
    gmap.update(_graded_road(rng, start - [30.0, 0.0, 0.0], 40000) + rng.normal(0.0, 0.01, (40000, 3)))
    truth = _pose(start[0], start[1])
    local = np.linalg.inv(truth) @ np.column_stack([_graded_road(rng, start, 6000), np.ones(6000)]).T
    car = np.column_stack([rng.uniform(12.0, 16.0, 800), rng.uniform(-1.0, 1.0, 800), rng.uniform(0.0, 0.15, 800)])
    scan = np.vstack([local[:3].T, car])
    err = (0.08, np.radians(0.3), np.radians(0.2))
    guess = truth @ se3_exp(np.array([0.0, 0.0, *err, 0.0]))
    fitted = fit_to_road(scan, guess, gmap, 0.1, 20)
    assert fitted is not None
    off = np.linalg.inv(truth) @ fitted
    assert abs(off[2, 3]) < 1e-3
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(off[:3, :3]).as_rotvec())) < 0.005
    assert fit_to_road(scan[:10], guess, gmap, 0.1, 20) is None  # too few shared cells


def test_chained_road_on_a_grade_does_not_drift() -> None:
    """300 scans (900 m) up a 4 % grade with a 2.5 % crossfall, each placed at the truth times the last
    scan's remaining error and corrected against the road the scans before it mapped: point-to-plane
    residuals keep the chain exact (heights per cell compared at the cells' centroids drifted 7 m
    over 700 scans on this road: a cell's centroid moves with where the points fall)."""
    rng = np.random.default_rng(2)
    gmap = GroundMap(2.0)
    err = np.eye(4)
    for k in range(300):
        truth = _pose(3.0 * k, 0.0)
        local = (np.linalg.inv(truth) @ np.column_stack([_graded_road(rng, truth[:3, 3], 3000),
                                                           np.ones(3000)]).T)[:3].T
        pose = truth @ err
        if len(gmap):
            fitted = fit_to_road(local, pose, gmap, 0.1, 20)
            assert fitted is not None
            pose = fitted
        err = np.linalg.inv(truth) @ pose
        gmap.update(local @ pose[:3, :3].T + pose[:3, 3])
        gmap.prune(pose[:3, 3], 80.0)
    assert abs(err[2, 3]) < 1e-4
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(err[:3, :3]).as_rotvec())) < 1e-3
    assert len(gmap) < 1000  # cells more than 80 m away are forgotten (900 m x 24 m of road: 5400 cells)


def test_split_scan_separates_road_and_structure() -> None:
    """A body pitched 1 deg on its springs: the road is found by the scan's own plane, not by z = 0."""
    rng = np.random.default_rng(6)
    road = np.column_stack([rng.uniform(3.0, 60.0, 4000), rng.uniform(-10.0, 10.0, 4000), np.zeros(4000)])
    posts = np.column_stack([rng.uniform(3.0, 60.0, 500), np.full(500, 9.0), rng.uniform(0.0, 2.5, 500)])
    tilt = Rotation.from_euler("y", 1.0, degrees=True).as_matrix()
    xyz = np.vstack([road, posts]) @ tilt.T
    times = np.arange(len(xyz), dtype=np.float64)
    high, t_high, low, t_low = split_scan(xyz, times, ExtractionConfig(), np.random.default_rng(0))
    height = np.concatenate([road[:, 2], posts[:, 2]])
    near = np.hypot(xyz[:, 0], xyz[:, 1]) < ExtractionConfig().odometry_ground_range_m
    assert np.array_equal(t_low.astype(int), np.flatnonzero((height < 0.15) & near))  # post feet count as road
    assert np.array_equal(t_high.astype(int), np.flatnonzero(height > 0.3))
    assert np.allclose(low, xyz[t_low.astype(int)]) and np.allclose(high, xyz[t_high.astype(int)])
    assert len(split_scan(xyz, times, ExtractionConfig(odometry_ground=False), np.random.default_rng(0))[2]) == 0
    everything = split_scan(xyz, None, ExtractionConfig(odometry_min_height_m=0.3), np.random.default_rng(0))
    assert len(everything[0]) == len(xyz) and len(everything[2]) == 0 and everything[3] is None
