"""Readers of every recording format, auto-detection, and every kind of bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from pypcd4 import Encoding, PointCloud
from scipy.spatial.transform import Rotation
from test_extraction import make_drive, write_drive

from lidar2xodr.datasets import detect_format, open_dataset
from lidar2xodr.datasets.base import detect_intensity_scale, time_unit
from lidar2xodr.errors import InputError

SENSOR_HEIGHT = 1.9


def ground_scan(seed: int, n: int = 3000, t0: float = 100.0, height: float = SENSOR_HEIGHT) -> dict:
    """Sensor-frame points of flat ground `height` below a level sensor, plus a post; times over 0.1 s."""
    rng = np.random.default_rng(seed)
    r, az = rng.uniform(3, 30, n), rng.uniform(-np.pi, np.pi, n)
    xyz = np.column_stack([r * np.cos(az), r * np.sin(az), np.full(n, -height)])
    post = np.column_stack([np.full(200, 8.0), np.full(200, 3.0), rng.uniform(-height, 1.0, 200)])
    xyz = np.vstack([xyz, post])
    t = t0 + np.sort(rng.uniform(0, 0.1, len(xyz)))
    return {"xyz": xyz, "intensity": rng.uniform(0, 1, len(xyz)), "t": t}


def save_pcd(path: Path, s: dict, scale: float = 1.0, with_intensity: bool = True, with_t: bool = True) -> None:
    cols, names, types = [s["xyz"][:, 0], s["xyz"][:, 1], s["xyz"][:, 2]], ["x", "y", "z"], [np.float32] * 3
    if with_intensity:
        cols.append(s["intensity"] * scale)
        names.append("intensity")
        types.append(np.float32)
    if with_t:
        cols.append(s["t"])
        names.append("t")
        types.append(np.float64)
    PointCloud.from_points(cols, names, types).save(path, encoding=Encoding.BINARY)


def scans_of(ds) -> list:
    return list(ds)


# --- helpers ----------------------------------------------------------------------------------


def test_intensity_scale_and_time_unit_guesses() -> None:
    assert detect_intensity_scale(np.array([0, 200], dtype=np.uint8)) == 255
    assert detect_intensity_scale(np.array([0, 254], dtype=np.uint16)) == 255
    assert detect_intensity_scale(np.array([0, 4000], dtype=np.uint16)) == 65535
    assert detect_intensity_scale(np.array([0.0, 0.7])) == 1.0
    assert detect_intensity_scale(np.array([0.0, 87.0])) == 100.0
    assert detect_intensity_scale(np.array([0.0, 180.0], dtype=np.float32)) == 255.0
    assert time_unit(0.1) == 1.0 and time_unit(100.0) == 1e-3 and time_unit(1e5) == 1e-6 and time_unit(1e8) == 1e-9


# --- the drive directory ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_drive():
    return make_drive(n_scans=3, n_ground=800, seed=11)


def test_drive_dir_scans_are_in_the_vehicle_frame(small_drive, tmp_path: Path) -> None:
    folder = write_drive(small_drive, tmp_path / "d", scale=150.0)
    assert detect_format(folder) == "drive"
    ds = open_dataset(folder)
    assert len(ds) == 3 and ds.sensor.name == "synthetic" and ds.sensor.intensity_scale == 150.0
    assert np.allclose(ds.sensor.mount, small_drive.mount, atol=1e-9)
    scans = scans_of(ds)
    for scan, truth in zip(scans, small_drive.scans, strict=True):
        expected = truth["world"] - small_drive.pose(truth["t"])
        assert np.allclose(scan.xyz, expected, atol=2e-5)  # float32 in the PCD
        assert np.allclose(scan.intensity, truth["intensity"], atol=1e-6)
        assert np.array_equal(scan.times, truth["t"]) and scan.stamp == truth["t"].max()
    traj = ds.poses()
    assert traj is not None and np.allclose(traj.positions[:, 0], small_drive.speed * (traj.times - 1000.0), atol=1e-5)
    assert ds.origin.lat == 48.7 and ds.origin.proj.startswith("+proj=tmerc")


def _meta(folder: Path) -> dict:
    return yaml.safe_load((folder / "meta.yaml").read_text())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m.update(version=2), "unsupported version 2"),
        (lambda m: m["sensor"]["mount"].pop("z"), "sensor.mount.z: expected a number"),
        (lambda m: m["sensor"].update(intensity_scale=-1), "intensity_scale must be positive"),
        (lambda m: m["scans"].update(dir="nope"), "scan folder missing"),
        (lambda m: m.update(origin=[1, 2]), "'origin' must be a mapping"),
    ],
)
def test_drive_meta_errors_name_the_file(small_drive, tmp_path: Path, change, message: str) -> None:
    folder = write_drive(small_drive, tmp_path / "d")
    meta = _meta(folder)
    change(meta)
    (folder / "meta.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(InputError, match=message) as err:
        open_dataset(folder, "drive")
    assert "meta.yaml" in str(err.value) or "nope" in str(err.value)


def test_scan_without_intensity_is_an_input_error(small_drive, tmp_path: Path) -> None:
    folder = write_drive(small_drive, tmp_path / "d")
    s = small_drive.scans[1]
    save_pcd(folder / "scans" / "000001.pcd", s, with_intensity=False)
    with pytest.raises(InputError, match=r"000001\.pcd: scan has no intensity field"):
        scans_of(open_dataset(folder))


def test_scans_out_of_time_order(small_drive, tmp_path: Path) -> None:
    folder = write_drive(small_drive, tmp_path / "d")
    a, b = folder / "scans" / "000001.pcd", folder / "scans" / "000002.pcd"
    data = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(data)
    with pytest.raises(InputError, match=r"000002\.pcd: scan time .* is before the previous scan"):
        scans_of(open_dataset(folder))


def test_corrupt_empty_and_nan_scans_are_skipped_and_counted(small_drive, tmp_path: Path) -> None:
    folder = write_drive(small_drive, tmp_path / "d")
    (folder / "scans" / "000001.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4")
    s = dict(small_drive.scans[2])
    s["xyz"] = s["xyz"].copy()
    s["xyz"][:, 2] = np.inf
    save_pcd(folder / "scans" / "000002.pcd", s)
    ds = open_dataset(folder)
    scans = scans_of(ds)
    assert [sc.index for sc in scans] == [0]
    assert [Path(n).name for n, _ in ds.stats.bad_scans] == ["000001.pcd"]
    assert ds.stats.empty_scans == 1  # all-inf: no return anywhere, an empty scan rather than a broken file
    assert ds.stats.dropped_points == len(s["xyz"])


def test_scan_with_zero_points_is_skipped_not_a_crash(small_drive, tmp_path: Path) -> None:
    """A sensor can deliver an empty frame (the simulator did at a U-turn off its terrain); pypcd4
    reads such a PCD as a (0, n_fields) array, which once crashed the drive reader's transform."""
    folder = write_drive(small_drive, tmp_path / "d")
    empty = {"xyz": np.zeros((0, 3)), "intensity": np.zeros(0), "t": np.zeros(0)}
    save_pcd(folder / "scans" / "000001.pcd", empty)
    ds = open_dataset(folder)
    assert [sc.index for sc in scans_of(ds)] == [0, 2]
    assert not ds.stats.bad_scans and ds.stats.empty_scans == 1
    scan, stats = ds.read_scan(1)
    assert scan is None and stats.empty_scans == 1
    one = {"xyz": np.array([[5.0, 0.0, -1.8]]), "intensity": np.array([0.3]), "t": np.array([100.05])}
    save_pcd(folder / "scans" / "000001.pcd", one)  # one return: its time alone cannot stamp the scan
    ds = open_dataset(folder)
    assert [sc.index for sc in scans_of(ds)] == [0, 2] and ds.stats.empty_scans == 1


def test_nonexistent_and_empty_inputs(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        open_dataset(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no scans found"):
        open_dataset(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(InputError, match="single file is not a drive"):
        open_dataset(tmp_path / "notes.txt")
    with pytest.raises(InputError, match="unknown format 'xyz'"):
        open_dataset(tmp_path / "empty", "xyz")
    with pytest.raises(InputError, match="no scan files found"):
        open_dataset(tmp_path / "empty", "folder")


def test_a_folder_of_drives_names_its_drives_and_a_drive_twice_is_refused(small_drive, tmp_path: Path) -> None:
    from lidar2xodr.datasets import drives_in

    fleet = tmp_path / "fleet"
    b, a = write_drive(small_drive, fleet / "tuesday"), write_drive(small_drive, fleet / "monday")
    (fleet / "notes").mkdir()
    (fleet / ".cache").mkdir()
    assert drives_in([fleet]) == [a, b]
    assert drives_in([b, a]) == [b, a]
    with pytest.raises(InputError, match="given twice") as err:
        drives_in([fleet, a])
    assert str(err.value).startswith(str(a))
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no scans found") as err:
        drives_in([tmp_path / "empty"])
    assert "folder of drives" not in str(err.value)
    with pytest.raises(InputError, match="no scans found.*nor is any of its folders a drive"):
        drives_in([tmp_path])  # holds fleet/ and empty/, neither a drive
    with pytest.raises(InputError, match="no such file"):
        drives_in([tmp_path / "missing"])


# --- folders of scan files --------------------------------------------------------------------


def _write_scan(path: Path, s: dict) -> None:
    xyz, inten = s["xyz"], s["intensity"]
    suffix = path.suffix
    if suffix == ".pcd":
        save_pcd(path, s, scale=255.0)
    elif suffix in (".las", ".laz"):
        import laspy

        hdr = laspy.LasHeader(point_format=1, version="1.2")
        hdr.scales = np.array([0.001, 0.001, 0.001])
        hdr.offsets = np.zeros(3)
        las = laspy.LasData(hdr)
        las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        las.intensity = np.round(inten * 255).astype(np.uint16)
        las.gps_time = s["t"]
        las.write(path)
    elif suffix == ".ply":
        from lidar2xodr.markings_io import ply_bytes

        arr = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u1"), ("t", "f8")])
        arr["x"], arr["y"], arr["z"] = xyz.T
        arr["intensity"] = np.round(inten * 255)
        arr["t"] = s["t"]
        path.write_bytes(ply_bytes(arr))
    elif suffix == ".bin":
        np.column_stack([xyz, inten]).astype("<f4").tofile(path)
    elif suffix == ".npy":
        np.save(path, np.column_stack([xyz, inten * 100.0, s["t"]]))


@pytest.mark.parametrize(("suffix", "scale", "has_times"),
                         [(".pcd", 255.0, True), (".las", 255.0, True), (".laz", 255.0, True), (".ply", 255.0, True),
                          (".bin", 1.0, False), (".npy", 100.0, True)])
def test_folder_of_scans(tmp_path: Path, suffix: str, scale: float, has_times: bool) -> None:
    scans = [ground_scan(k, t0=100.0 + 0.1 * k) for k in range(3)]
    for k, s in enumerate(scans):
        _write_scan(tmp_path / f"scan_{k}{suffix}", s)
    (tmp_path / "README.md").write_text("not a scan")
    assert detect_format(tmp_path) == "folder"
    ds = open_dataset(tmp_path)
    out = scans_of(ds)
    assert len(out) == 3 and ds.sensor.intensity_scale == scale
    assert ds.sensor.mount[2, 3] == pytest.approx(SENSOR_HEIGHT, abs=0.01)  # estimated from the ground
    ground = out[0].xyz[: len(scans[0]["xyz"]) - 200]
    assert np.abs(ground[:, 2]).max() < 0.01  # the vehicle frame has its origin on the road
    assert np.allclose(out[0].intensity, scans[0]["intensity"], atol=0.003)
    if has_times:
        assert np.allclose(out[1].times, scans[1]["t"], atol=1e-6)
    else:
        assert out[1].times is None and out[1].stamp == 1.0


def test_folder_poses_csv_local_and_geodetic(tmp_path: Path) -> None:
    for k in range(3):
        save_pcd(tmp_path / f"{k:03d}.pcd", ground_scan(k, t0=100.0 + 0.1 * k))
    rows = ["time,x,y,z,roll,pitch,yaw"] + [f"{100 + 0.05 * i:.2f},{2.0 * i},0,0,0,0,0.1" for i in range(10)]
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    ds = open_dataset(tmp_path)
    traj = ds.poses()
    assert traj is not None and len(traj) == 10
    # sensor poses in, vehicle poses out: the vehicle origin lies SENSOR_HEIGHT below the sensor
    assert traj.positions[0, 2] == pytest.approx(-SENSOR_HEIGHT, abs=0.01)
    assert Rotation.from_matrix(traj.poses[3, :3, :3]).as_euler("ZYX")[0] == pytest.approx(0.1, abs=1e-3)

    rows = ["t,lat,lon,alt,roll,pitch,yaw"] + [f"{100 + 0.05 * i:.2f},{48.0 + 1e-4 * i:.6f},9.0,300,0,0,1.5708"
                                               for i in range(10)]
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    ds = open_dataset(tmp_path)
    traj = ds.poses()
    assert ds.origin.lat == 48.0 and ds.origin.lon == 9.0 and "+proj=tmerc" in ds.origin.proj
    north = traj.positions[-1] - traj.positions[0]
    assert north[1] == pytest.approx(9 * 11.12, rel=0.01) and abs(north[0]) < 0.01


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("time,x,y,z,yaw\n1,0,0,0,0\n0.5,1,0,0,0\n", "not increasing"),
        ("stamp_ns,x,y,z,yaw\n1,0,0,0,0\n2,1,0,0,0\n", r"missing column\(s\) time \(required"),
        ("time,a,b,yaw\n1,0,0,0\n2,1,0,0\n", r"missing column\(s\) x, y, z"),
        ("time,x,y,z\n1,0,0,0\n2,1,0,0\n", r"missing column\(s\) yaw"),
        ("time,lat,lon,yaw\n1,48,9,0\n2,48.1,9,0\n", r"missing column\(s\) alt"),
        ("time,x,y,z,yaw\n1,0,0,0,0\n2,abc,0,0,0\n", "row 3, column 'x': not a number"),
        ("time,x,y,z,yaw\n", "needs a header and at least 2 rows"),
    ],
)
def test_bad_pose_files(tmp_path: Path, text: str, message: str) -> None:
    save_pcd(tmp_path / "0.pcd", ground_scan(0))
    (tmp_path / "poses.csv").write_text(text)
    with pytest.raises(InputError, match=message) as err:
        open_dataset(tmp_path)
    assert "poses.csv" in str(err.value)


def test_kitti_poses_and_time_file(tmp_path: Path) -> None:
    for k in range(3):
        np.column_stack([ground_scan(k)["xyz"], np.full(3200, 0.5)]).astype("<f4").tofile(tmp_path / f"{k:06d}.bin")
    poses = np.tile(np.eye(4)[:3].reshape(-1), (3, 1))
    poses[:, 3] = [0.0, 1.0, 2.0]
    np.savetxt(tmp_path / "poses.txt", poses)
    (tmp_path / "times.txt").write_text("0.0\n0.1\n0.2\n")
    ds = open_dataset(tmp_path)
    scans = scans_of(ds)
    assert [s.stamp for s in scans] == [0.0, 0.1, 0.2]
    traj = ds.poses()
    assert np.allclose(traj.times, [0.0, 0.1, 0.2]) and np.allclose(traj.positions[:, 0], [0.0, 1.0, 2.0])
    np.savetxt(tmp_path / "poses.txt", poses[:2])
    with pytest.raises(InputError, match="2 poses for 3 scans"):
        open_dataset(tmp_path)


def test_time_file_with_offset_point_times(tmp_path: Path) -> None:
    for k in range(2):
        s = ground_scan(k, t0=0.0)
        _write_scan(tmp_path / f"{k}.npy", s)
    (tmp_path / "timestamps.txt").write_text("2011-09-26 13:02:25.500000000\n2011-09-26 13:02:25.600000000\n")
    out = scans_of(open_dataset(tmp_path))
    day = 13 * 3600 + 2 * 60 + 25.5
    assert out[0].times.min() == pytest.approx(day, abs=0.01)
    assert out[1].times.min() == pytest.approx(day + 0.1, abs=0.01)


# --- KITTI raw --------------------------------------------------------------------------------


def test_kitti_raw_drive(tmp_path: Path) -> None:
    date = tmp_path / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    (drive / "oxts" / "data").mkdir(parents=True)
    (date / "calib_imu_to_velo.txt").write_text("calib_time: x\nR: 1 0 0 0 1 0 0 0 1\nT: -0.81 0.32 -0.80\n")
    stamps = [f"2011-09-26 13:02:25.{k}00000000" for k in range(3)]
    for k in range(3):
        s = ground_scan(k, height=1.73)
        np.column_stack([s["xyz"], s["intensity"]]).astype("<f4").tofile(
            drive / "velodyne_points" / "data" / f"{k:010d}.bin")
        oxts = [49.0 + 1e-5 * k, 8.4, 110.0, 0.0, 0.0, 0.0] + [0.0] * 24
        (drive / "oxts" / "data" / f"{k:010d}.txt").write_text(" ".join(map(str, oxts)) + "\n")
    (drive / "velodyne_points" / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    (drive / "oxts" / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    assert detect_format(drive) == "kitti_raw"
    ds = open_dataset(drive)
    assert np.allclose(ds.sensor.mount[:3, 3], [0.81, -0.32, 1.73])
    scans = scans_of(ds)
    assert np.abs(scans[0].xyz[:3000, 2]).max() < 0.01
    assert scans[1].stamp - scans[0].stamp == pytest.approx(0.1, abs=1e-6)
    traj = ds.poses()
    assert traj is not None and ds.origin.lat == 49.0
    assert traj.positions[2, 1] - traj.positions[0, 1] == pytest.approx(2 * 1.112, rel=0.01)
    assert traj.positions[0, 2] == pytest.approx(-0.93, abs=1e-6)  # IMU 0.93 m above the road


# --- ROS bags ---------------------------------------------------------------------------------


def _cloud_msg(ts, s: dict, stamp: float, fields: tuple = ("x", "y", "z", "intensity", "t"), ros1: bool = False,
               relative_time: bool = False):
    T = ts.types
    pf = T["sensor_msgs/msg/PointField"]
    dt = {"x": "<f4", "y": "<f4", "z": "<f4", "intensity": "<f4", "t": "<f8", "time": "<f4"}
    names = [f for f in fields if not (f == "t" and relative_time)] + (["time"] if relative_time else [])
    rec = np.zeros(len(s["xyz"]), dtype=[(n, dt[n]) for n in names])
    for i, c in enumerate("xyz"):
        if c in rec.dtype.names:
            rec[c] = s["xyz"][:, i]
    if "intensity" in names:
        rec["intensity"] = s["intensity"] * 255.0
    if "t" in names:
        rec["t"] = s["t"]
    if "time" in names:
        rec["time"] = s["t"] - stamp
    code = {"<f4": 7, "<f8": 8}
    pfs = [pf(n, rec.dtype.fields[n][1], code[rec.dtype[n].str], 1) for n in names]
    sec = int(stamp)
    time = T["builtin_interfaces/msg/Time"](sec, int(round((stamp - sec) * 1e9)))
    header = T["std_msgs/msg/Header"](0, time, "lidar") if ros1 else T["std_msgs/msg/Header"](time, "lidar")
    return T["sensor_msgs/msg/PointCloud2"](header, 1, len(rec), pfs, False, rec.itemsize, rec.nbytes,
                                            rec.view(np.uint8).reshape(-1), True)


def _header(ts, t: float, ros1: bool = False):
    T = ts.types
    sec = int(t)
    time = T["builtin_interfaces/msg/Time"](sec, int(round((t - sec) * 1e9)))
    return T["std_msgs/msg/Header"](0, time, "map") if ros1 else T["std_msgs/msg/Header"](time, "map")


def _pose_msg(ts, t: float, x: float, ros1: bool = False):
    T, g = ts.types, "geometry_msgs/msg/"
    pose = T[g + "Pose"](T[g + "Point"](x, 0.0, 0.0), T[g + "Quaternion"](0.0, 0.0, 0.0, 1.0))
    return T[g + "PoseStamped"](_header(ts, t, ros1), pose)


def _odom_msg(ts, t: float, x: float):
    T, g = ts.types, "geometry_msgs/msg/"
    pose = T[g + "Pose"](T[g + "Point"](x, 0.0, 0.0), T[g + "Quaternion"](0.0, 0.0, 0.0, 1.0))
    twist = T[g + "Twist"](T[g + "Vector3"](0.0, 0.0, 0.0), T[g + "Vector3"](0.0, 0.0, 0.0))
    return T["nav_msgs/msg/Odometry"](_header(ts, t), "base_link", T[g + "PoseWithCovariance"](pose, np.zeros(36)),
                                      T[g + "TwistWithCovariance"](twist, np.zeros(36)))


def _fix_msg(ts, t: float, lat: float):
    T = ts.types
    st = T["sensor_msgs/msg/NavSatStatus"](0, 1)
    return T["sensor_msgs/msg/NavSatFix"](_header(ts, t), st, lat, 9.0, 300.0, np.zeros(9), 0)


def _write_ros2(path: Path, plugin: str, clouds: list[tuple], poses: list[tuple]) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=8, storage_plugin=getattr(StoragePlugin, plugin)) as w:
        conns = {}
        for topic, msgtype, _, _ in clouds + poses:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
        for topic, msgtype, t, make in sorted(clouds + poses, key=lambda r: r[2]):
            w.write(conns[topic], int(t * 1e9), ts.serialize_cdr(make(ts), msgtype))


CLOUD = "sensor_msgs/msg/PointCloud2"


def test_ros2_sqlite_bag_with_odometry(tmp_path: Path) -> None:
    scans = [ground_scan(k, t0=50.0 + 0.1 * k) for k in range(3)]
    clouds = [("/points", CLOUD, 50.1 + 0.1 * k, lambda ts, s=s, k=k: _cloud_msg(ts, s, 50.1 + 0.1 * k))
              for k, s in enumerate(scans)]
    poses = [("/odom", "nav_msgs/msg/Odometry", 49.9 + 0.05 * i, lambda ts, i=i: _odom_msg(ts, 49.9 + 0.05 * i, i))
             for i in range(12)]
    _write_ros2(tmp_path / "bag", "SQLITE3", clouds, poses)
    assert detect_format(tmp_path / "bag") == "rosbag"
    ds = open_dataset(tmp_path / "bag")
    out = scans_of(ds)
    assert len(out) == 3 and np.allclose(out[2].times, scans[2]["t"])
    assert ds.sensor.mount[2, 3] == pytest.approx(SENSOR_HEIGHT, abs=0.01)
    assert np.allclose(out[0].intensity, scans[0]["intensity"], atol=1e-6)  # floats up to 255 -> scale 255
    traj = ds.poses()
    assert len(traj) == 12 and np.allclose(traj.positions[:, 0], np.arange(12))


def test_bare_mcap_with_navsatfix_and_two_cloud_topics(tmp_path: Path) -> None:
    scans = [ground_scan(k, t0=50.0 + 0.1 * k) for k in range(2)]
    clouds = [(topic, CLOUD, 50.1 + 0.1 * k, lambda ts, s=s, k=k: _cloud_msg(ts, s, 50.1 + 0.1 * k))
              for k, s in enumerate(scans) for topic in ("/front", "/rear")]
    fixes = [("/fix", "sensor_msgs/msg/NavSatFix", 50.0 + 0.1 * i,
              lambda ts, i=i: _fix_msg(ts, 50 + 0.1 * i, 48 + 1e-5 * i)) for i in range(5)]
    _write_ros2(tmp_path / "b", "MCAP", clouds, fixes)
    bare = tmp_path / "drive.mcap"
    next((tmp_path / "b").glob("*.mcap")).rename(bare)
    assert detect_format(bare) == "rosbag"
    with pytest.raises(InputError, match=r"several PointCloud2 topics \['/front', '/rear'\]"):
        open_dataset(bare)
    ds = open_dataset(bare, topic="/rear")
    assert len(ds) == 2 and len(scans_of(ds)) == 2
    traj = ds.poses()
    yaw = Rotation.from_matrix(traj.poses[:, :3, :3]).as_euler("ZYX")[:, 0]
    assert np.allclose(yaw, np.pi / 2, atol=1e-3)  # driving north: heading from the track
    assert ds.origin.lat == 48.0


def test_ros1_bag_with_relative_point_times_and_pose_stamped(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    scans = [ground_scan(k, t0=50.0 + 0.1 * k) for k in range(2)]
    with Writer(tmp_path / "d.bag") as w:
        c = w.add_connection("/velodyne_points", CLOUD, typestore=ts)
        p = w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        for i in range(6):
            w.write(p, int((50.0 + 0.05 * i) * 1e9), ts.serialize_ros1(_pose_msg(ts, 50.0 + 0.05 * i, i, True),
                                                                         "geometry_msgs/msg/PoseStamped"))
        for k, s in enumerate(scans):
            stamp = 50.0 + 0.1 * k
            msg = _cloud_msg(ts, s, stamp, ros1=True, relative_time=True)
            w.write(c, int(stamp * 1e9), ts.serialize_ros1(msg, CLOUD))
    ds = open_dataset(tmp_path / "d.bag")
    out = scans_of(ds)
    assert np.allclose(out[1].times, scans[1]["t"], atol=1e-5)  # offsets from the header stamp
    assert len(ds.poses()) == 6


def test_bag_cloud_without_intensity(tmp_path: Path) -> None:
    s = ground_scan(0, t0=50.0)
    _write_ros2(tmp_path / "bag", "SQLITE3",
                [("/p", CLOUD, 50.1, lambda ts: _cloud_msg(ts, s, 50.1, fields=("x", "y", "z", "t")))], [])
    with pytest.raises(InputError, match=r"/p#0: PointCloud2 has no intensity field"):
        scans_of(open_dataset(tmp_path / "bag"))


# --- aiMotive ---------------------------------------------------------------------------------


def _aimotive(folder: Path, n: int = 2) -> None:
    import laspy

    (folder / "dynamic" / "raw-revolutions").mkdir(parents=True)
    (folder / "sensor" / "calibration").mkdir(parents=True)
    mount = np.eye(4)
    mount[:3, 3] = [1.16, 0.0, 1.68]
    calib = {"M_LIDAR_M": {"sensor_type": "lidar", "RT_body_from_sensor": mount.tolist(),
                           "custom_vars": {"product_name": "Hesai Pandar64"}},
             "F_CAM": {"sensor_type": "camera", "RT_body_from_sensor": np.eye(4).tolist()}}
    (folder / "sensor" / "calibration" / "calibration.json").write_text(json.dumps(calib))
    for k in range(n):
        s = ground_scan(k, height=0.0)
        hdr = laspy.LasHeader(point_format=1, version="1.2")
        hdr.scales = np.array([0.001] * 3)
        hdr.offsets = np.zeros(3)
        las = laspy.LasData(hdr)
        las.x, las.y, las.z = s["xyz"].T
        las.intensity = np.round(s["intensity"] * 254).astype(np.uint16)
        las.gps_time = np.round((4833.0 + 0.0667 * k + (s["t"] - s["t"][0])) * 1e9)
        las.write(folder / "dynamic" / "raw-revolutions" / f"frame_{33643 + k:07d}.laz")


def test_aimotive_layout(tmp_path: Path) -> None:
    _aimotive(tmp_path / "seq")
    assert detect_format(tmp_path / "seq") == "aimotive"
    ds = open_dataset(tmp_path / "seq")
    assert ds.sensor.name == "Hesai Pandar64" and ds.sensor.mount[2, 3] == 1.68 and ds.poses() is None
    scans = scans_of(ds)
    assert np.abs(scans[0].xyz[:3000, 2]).max() < 1e-3  # body frame kept: no mount transform applied
    assert scans[1].times.min() == pytest.approx(4833.0667, abs=1e-6)
    assert scans[0].intensity.max() <= 254 / 255 + 1e-6
    (tmp_path / "seq" / "sensor" / "calibration" / "calibration.json").write_text("{}")
    with pytest.raises(InputError, match="calibration.json: expected one entry with sensor_type 'lidar'"):
        open_dataset(tmp_path / "seq")


def test_real_aimotive_sample(shared_data: Path) -> None:
    ds = open_dataset(shared_data / "lidar" / "aimotive_highway_sample")
    assert len(ds) == 50 and ds.sensor.name == "Hesai Pandar64"
    assert ds.sensor.mount[2, 3] == pytest.approx(1.68, abs=0.01)
    first = next(iter(ds))
    assert len(first.xyz) > 100_000 and 0.0 <= first.intensity.min() and first.intensity.max() <= 1.0
    assert 0.09 < first.times.max() - first.times.min() < 0.11  # one 10 Hz revolution, in seconds
    near = np.linalg.norm(first.xyz[:, :2], axis=1) < 15
    assert abs(np.median(first.xyz[near & (first.xyz[:, 2] < 0.5), 2])) < 0.15  # origin on the ground


def test_simulated_drive_gives_the_same_markings_from_its_mcap_as_from_its_pcds(tmp_path: Path) -> None:
    """Issue #17 item 7: without the mount (/tf_static) and the Livox intensity scale (bag custom data)
    the MCAP gave 370 marking points against 12,942 from the PCDs of this drive."""
    from test_simulation import tiny_map

    from lidar2xodr.config import Config
    from lidar2xodr.extraction import extract_markings
    from lidar2xodr.simulation import SimOptions, simulate

    xodr = tiny_map(tmp_path / "tiny.xodr", 1000.0)
    simulate(xodr, tmp_path / "drive", SimOptions(length_m=200.0, traffic="none", seed=3, rosbag=True))
    pcd = open_dataset(tmp_path / "drive")
    bag = open_dataset(tmp_path / "drive" / "drive.mcap")
    assert bag.sensor.intensity_scale == pcd.sensor.intensity_scale == 150.0
    assert np.allclose(bag.sensor.mount, pcd.sensor.mount, atol=1e-6)
    counts = [len(extract_markings(ds, Config().extraction).xyz) for ds in (pcd, bag)]
    assert counts[0] > 5000 and abs(counts[1] - counts[0]) <= 0.01 * counts[0], counts


def test_build_refuses_an_anchor_that_names_no_given_drive(small_drive, tmp_path: Path) -> None:
    import subprocess
    import sys

    drive = write_drive(small_drive, tmp_path / "d")
    out = tmp_path / "m.xodr"
    proc = subprocess.run([sys.executable, "-m", "lidar2xodr.cli", "build", str(drive), "-o", str(out), "--anchor",
                           "2"], capture_output=True, text=True, timeout=120, check=False)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "--anchor" in lines[0] and "1 to 1 (got 2)" in lines[0], \
        proc.stderr
    assert not out.exists() and "Traceback" not in proc.stderr
