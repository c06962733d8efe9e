"""Hostile input for every reader (issue #17): each case ends in one line naming the user's file.

A broken scan file is skipped and counted (`stats.bad_scans` names it with a one-line reason); a
broken drive-level file (poses, meta, bag, calibration) is an InputError naming it. A few cases
go through `lidar2xodr extract` in a subprocess, bounded in time and memory, and check exit 2,
one error line and nothing written. Files are made in the test; shared data is only copied.
"""

from __future__ import annotations

import os
import random
import resource
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import SHARED_DATA
from test_datasets import CLOUD, _cloud_msg, _fix_msg, _write_ros2, _write_scan, ground_scan, save_pcd
from test_extraction import make_drive, write_drive

from lidar2xodr.datasets import open_dataset
from lidar2xodr.errors import InputError

MEMORY_LIMIT = 3 << 30  # address space of a CLI subprocess: the interpreter and its libraries need ~1.5 GB


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def run_cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "lidar2xodr.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, preexec_fn=_limit_memory)


def assert_one_line_error(proc: subprocess.CompletedProcess, names: str, out: Path) -> None:
    """Exit 2, one error line naming `names`, no traceback, no per-scan chatter, nothing written."""
    text = proc.stdout + proc.stderr
    assert proc.returncode == 2, text
    errors = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and names in errors[0], text
    assert "Traceback" not in text and "skipping scan" not in text, text
    assert not out.exists() and not list(out.parent.glob(out.stem + "*")), list(out.parent.iterdir())


def one_line(exc: BaseException, name: str | Path) -> str:
    msg = str(exc)
    assert "\n" not in msg and str(name) in msg, msg
    return msg


def _folder_with(tmp: Path, name: str, data: bytes, good: int = 1) -> tuple[Path, Path]:
    """A folder of `good` readable scans of the same type plus the hostile file `name` first."""
    folder = tmp / "scans"
    folder.mkdir()
    bad = folder / name
    bad.write_bytes(data)
    for k in range(good):
        _write_scan(folder / f"{k + 1:06d}{bad.suffix}", ground_scan(k + 1, t0=100.0 + 0.1 * (k + 1)))
    return folder, bad


def assert_skipped(folder: Path, bad: Path, good: int = 1) -> str:
    """The hostile file is skipped and counted with a one-line reason; the good scans still read."""
    ds = open_dataset(folder)
    scans = list(ds)
    assert len(scans) == good
    assert [n for n, _ in ds.stats.bad_scans] == [str(bad)]
    reason = ds.stats.bad_scans[0][1]
    assert reason and "\n" not in reason
    return reason


# --- LAS / LAZ -------------------------------------------------------------------------------------


def _las_bytes(n: int = 500, version: str = "1.2", fmt: int = 1, seed: int = 0) -> bytes:
    import laspy

    s = ground_scan(seed, n=n)
    hdr = laspy.LasHeader(point_format=fmt, version=version)
    hdr.scales, hdr.offsets = np.array([0.001] * 3), np.zeros(3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = s["xyz"][:, 0], s["xyz"][:, 1], s["xyz"][:, 2]
    las.intensity = np.round(s["intensity"] * 255).astype(np.uint16)
    las.gps_time = s["t"]
    import io

    buf = io.BytesIO()
    las.write(buf)
    return buf.getvalue()


def test_random_las_files_end_quickly_with_one_line(tmp_path: Path) -> None:
    """Issue #17 item 2: 604-byte files of LASF + random bytes made laspy spin and eat memory."""
    folder = tmp_path / "lasd"
    folder.mkdir()
    for i in range(3):
        rnd = random.Random(i + 3)
        (folder / f"{i:03d}.las").write_bytes(b"LASF" + bytes(rnd.getrandbits(8) for _ in range(600)))
    out = tmp_path / "m.ply"
    proc = run_cli("extract", str(folder), "-o", str(out), timeout=60)
    assert_one_line_error(proc, str(folder), out)
    assert "3 of 3 scans unreadable" in proc.stderr + proc.stdout


@pytest.mark.parametrize(
    ("field", "fmt", "value", "reason"),
    [
        ("n_vlr", "<I", 0xFFFFFFF0, "VLRs stated"),  # a valid version with a random VLR count
        ("vlr_length", "<H", 0xFFFF, "VLRs run past"),
        ("points", "<I", 2_000_000_000, "truncated LAS"),
        ("offset", "<I", 10**9, "do not fit"),
        ("record", "<H", 3, "not valid"),
    ],
)
def test_las_header_lies_are_caught_before_laspy(tmp_path: Path, field: str, fmt: str, value: int,
                                                 reason: str) -> None:
    data = bytearray(_las_bytes(version="1.2"))
    at = {"n_vlr": 100, "points": 107, "offset": 96, "record": 105}
    if field == "vlr_length":  # add a VLR header at the start of the VLR block that claims 64 KiB
        head_size, offset = struct.unpack_from("<HI", data, 94)
        vlr = bytearray(54)
        struct.pack_into("<H", vlr, 20, 0xFFFF)
        data[head_size:head_size] = vlr
        struct.pack_into("<I", data, 96, offset + 54)
        struct.pack_into("<I", data, 100, 1)
    else:
        struct.pack_into(fmt, data, at[field], value)
    folder, bad = _folder_with(tmp_path, "000000.las", bytes(data))
    assert reason in assert_skipped(folder, bad)


def test_las_14_evlr_count_beyond_the_file(tmp_path: Path) -> None:
    data = bytearray(_las_bytes(version="1.4", fmt=6))
    struct.pack_into("<QI", data, 235, len(data) - 10, 1_000_000)
    folder, bad = _folder_with(tmp_path, "000000.las", bytes(data))
    assert "EVLR" in assert_skipped(folder, bad)


def test_laz_truncated_in_the_middle_is_skipped(tmp_path: Path) -> None:
    import laspy

    las = laspy.read(__import__("io").BytesIO(_las_bytes(n=3000)))
    las.write(tmp_path / "full.laz", laz_backend=laspy.LazBackend.Lazrs)
    data = (tmp_path / "full.laz").read_bytes()
    folder = tmp_path / "scans"
    folder.mkdir()
    bad = folder / "000000.laz"
    bad.write_bytes(data[: len(data) // 2])
    las.write(folder / "000001.laz", laz_backend=laspy.LazBackend.Lazrs)
    assert "LAZ" in assert_skipped(folder, bad)  # the chunk table check or lazrs itself


# --- PCD -----------------------------------------------------------------------------------------


def _pcd_header(points: int, data: str = "binary", width: int | None = None) -> bytes:
    return (f"VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
            f"WIDTH {points if width is None else width}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {points}\nDATA {data}\n").encode()


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (_pcd_header(10**9) + bytes(64), "truncated PCD"),
        (_pcd_header(10**6, "binary_compressed") + struct.pack("<II", 16, 16 * 10**6) + bytes(16),
         "cannot hold"),
        (_pcd_header(4, width=40) + bytes(64), "is not POINTS"),
        (_pcd_header(4).replace(b"DATA binary\n", b""), "no DATA line"),
        (_pcd_header(4).replace(b"SIZE 4 4 4 4", b"SIZE 4 4 4"), "3 SIZE"),
        (b"", "no DATA line"),
    ],
    ids=["points-lie", "lzf-size-lie", "width-lie", "no-data-line", "size-count-mismatch", "empty"],
)
def test_pcd_header_lies_are_caught(tmp_path: Path, data: bytes, reason: str) -> None:
    folder, bad = _folder_with(tmp_path, "000000.pcd", data)
    assert reason in assert_skipped(folder, bad)


def test_pcd_without_xyz_names_the_file(tmp_path: Path) -> None:
    from pypcd4 import Encoding, PointCloud

    s = ground_scan(0)
    path = tmp_path / "000000.pcd"
    PointCloud.from_points([s["xyz"][:, 0], s["xyz"][:, 1], s["xyz"][:, 2], s["intensity"]],
                           ("a", "b", "c", "intensity"), [np.float32] * 4).save(path, encoding=Encoding.BINARY)
    with pytest.raises(InputError, match="no x, y, z fields") as err:
        list(open_dataset(tmp_path))
    one_line(err.value, path)


def test_all_nan_scans_are_one_input_error(tmp_path: Path) -> None:
    for k in range(3):
        s = ground_scan(k, t0=100 + 0.1 * k)
        s["xyz"][:] = np.nan
        save_pcd(tmp_path / f"{k:06d}.pcd", s)
    out = tmp_path / "out" / "m.ply"
    out.parent.mkdir()
    proc = run_cli("extract", str(tmp_path), "-o", str(out))
    assert_one_line_error(proc, str(tmp_path), out)


# --- PLY, KITTI .bin, .npy -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("header", "reason"),
    [
        (b"ply\nformat binary_little_endian 1.0\nelement vertex -5\nproperty float x\nend_header\n", "count"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex abc\nproperty float x\nend_header\n", "count"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float x\nend_header\n1 2\n3 4\n",
         "twice"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header", "end_header"),
    ],
    ids=["negative-count", "text-count", "repeated-property", "no-newline-after-header"],
)
def test_ply_header_lies_are_caught(tmp_path: Path, header: bytes, reason: str) -> None:
    folder, bad = _folder_with(tmp_path, "000000.ply", header + bytes(12))
    assert reason in assert_skipped(folder, bad)


def test_kitti_bin_with_a_stray_byte_is_skipped(tmp_path: Path) -> None:
    """17 bytes used to read as one point (the check counted floats, not bytes)."""
    folder, bad = _folder_with(tmp_path, "000000.bin", np.zeros(4, "<f4").tobytes() + b"\x00")
    assert "multiple of 16" in assert_skipped(folder, bad)


def test_npy_header_promising_more_than_the_file(tmp_path: Path) -> None:
    import io

    from numpy.lib import format as npy

    buf = io.BytesIO()
    npy.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (10**10, 4)})
    folder, bad = _folder_with(tmp_path, "000000.npy", buf.getvalue() + bytes(64))
    assert "more than the file" in assert_skipped(folder, bad)


# --- permissions, links, directories ---------------------------------------------------------------


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_unreadable_scan_is_skipped_and_named(tmp_path: Path) -> None:
    folder, bad = _folder_with(tmp_path, "000000.pcd", b"")
    save_pcd(bad, ground_scan(0))
    bad.chmod(0)
    try:
        assert "Permission denied" in assert_skipped(folder, bad)
    finally:
        bad.chmod(0o644)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_unreadable_poses_csv_is_an_input_error(tmp_path: Path) -> None:
    save_pcd(tmp_path / "0.pcd", ground_scan(0))
    poses = tmp_path / "poses.csv"
    poses.write_text("time,x,y,z,yaw\n1,0,0,0,0\n2,1,0,0,0\n")
    poses.chmod(0)
    try:
        with pytest.raises(InputError, match="Permission denied") as err:
            open_dataset(tmp_path)
        one_line(err.value, poses)
    finally:
        poses.chmod(0o644)


def test_poses_csv_symlink_loop_is_an_input_error(tmp_path: Path) -> None:
    save_pcd(tmp_path / "0.pcd", ground_scan(0))
    (tmp_path / "poses.csv").symlink_to(tmp_path / "poses.csv")
    with pytest.raises(InputError) as err:
        open_dataset(tmp_path)
    one_line(err.value, tmp_path / "poses.csv")


def test_drive_path_symlink_loop_is_an_input_error(tmp_path: Path) -> None:
    loop = tmp_path / "drive"
    loop.symlink_to(loop)
    out = tmp_path / "m.ply"
    assert_one_line_error(run_cli("extract", str(loop), "-o", str(out)), str(loop), out)


def test_scan_symlink_loop_is_counted_not_ignored(tmp_path: Path) -> None:
    """A scan that cannot be opened used to vanish from the drive without a word."""
    folder, bad = _folder_with(tmp_path, "000000.pcd", b"")
    bad.unlink()
    bad.symlink_to(bad)
    for k in range(1, 3):
        save_pcd(folder / f"{k:06d}.pcd", ground_scan(k, t0=100 + 0.1 * k))
    assert "symbolic links" in assert_skipped(folder, bad, good=2)


def test_poses_csv_that_is_a_folder(tmp_path: Path) -> None:
    save_pcd(tmp_path / "0.pcd", ground_scan(0))
    (tmp_path / "poses.csv").mkdir()
    with pytest.raises(InputError, match="Is a directory") as err:
        open_dataset(tmp_path)
    one_line(err.value, tmp_path / "poses.csv")


# --- poses ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("time,x,y,z,roll,pitch\n1,0,0,0,0,0\n2,1,0,0,0,0\n", r"missing column\(s\) yaw"),  # item 4
        ("time,lat,lon,roll,pitch,yaw\n1,48,9,0,0,0\n2,48.001,9,0,0,0\n", r"missing column\(s\) alt"),
        ("time,lat,lon,alt,yaw\n1,200,9,0,0\n2,200.001,9,0,0\n", "latitude 200.0"),  # item 8
        ("time,x,y,z,yaw,lat,lon,alt\n1,0,0,0,0,200,9,0\n2,1,0,0,0,200,9,0\n", "latitude 200.0"),
        ("time,lat,lon,alt,yaw\n1,48,400,0,0\n2,48.001,400,0,0\n", "longitude 400.0"),
        ("time,x,y,z,yaw\n1,0,0,0,nan\n2,1,0,0,0\n", "non-finite"),
        ("time,x,y,z,yaw\n1,0,0,0,0\n1,1,0,0,0\n", "not increasing"),
        ("time,x,y,z,yaw\n1,0,0,0,0\ninf,1,0,0,0\n", "not all finite"),
    ],
    ids=["no-yaw", "geodetic-no-alt", "latitude-200", "origin-latitude-200", "longitude-400", "nan-yaw",
         "repeated-time", "inf-time"],
)
def test_bad_folder_poses_are_one_input_error(tmp_path: Path, text: str, reason: str) -> None:
    save_pcd(tmp_path / "0.pcd", ground_scan(0))
    (tmp_path / "poses.csv").write_text(text)
    with pytest.raises(InputError, match=reason) as err:
        ds = open_dataset(tmp_path)
        ds.poses()
    one_line(err.value, tmp_path / "poses.csv")


def test_drive_poses_without_yaw_and_origin_latitude_200(tmp_path: Path) -> None:
    drive = make_drive(n_scans=2, n_ground=500, seed=1)
    folder = write_drive(drive, tmp_path / "d")
    poses = folder / "poses.csv"
    rows = poses.read_text().splitlines()
    cut = [",".join(r.split(",")[:6]) for r in rows]  # drop yaw, lat, lon, alt
    poses.write_text("\n".join(cut) + "\n")
    with pytest.raises(InputError, match=r"missing column\(s\) yaw") as err:
        open_dataset(folder)
    one_line(err.value, poses)
    meta = yaml.safe_load((folder / "meta.yaml").read_text())
    meta["origin"] = {"lat": 200.0, "lon": 9.0, "alt": 0.0, "proj": None}
    (folder / "meta.yaml").write_text(yaml.safe_dump(meta))
    poses.write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError, match="latitude 200.0") as err:
        open_dataset(folder)
    one_line(err.value, folder / "meta.yaml")


def test_kitti_poses_that_do_not_match_the_scans(tmp_path: Path) -> None:
    for k in range(3):
        np.column_stack([ground_scan(k)["xyz"], np.full(3200, 0.5)]).astype("<f4").tofile(tmp_path / f"{k}.bin")
    np.savetxt(tmp_path / "poses.txt", np.tile(np.eye(4)[:3].reshape(-1), (5, 1)))
    with pytest.raises(InputError, match="5 poses for 3 scans") as err:
        open_dataset(tmp_path)
    one_line(err.value, tmp_path / "poses.txt")


def test_scan_times_going_backwards_name_the_scan(tmp_path: Path) -> None:
    for k, t0 in enumerate((100.0, 100.1, 99.0)):
        save_pcd(tmp_path / f"{k:06d}.pcd", ground_scan(k, t0=t0))
    with pytest.raises(InputError, match="before the previous scan") as err:
        list(open_dataset(tmp_path))
    one_line(err.value, tmp_path / "000002.pcd")


# --- ROS bags -------------------------------------------------------------------------------------


def _bag(tmp: Path, clouds: list, poses: list | None = None) -> Path:
    _write_ros2(tmp / "b", "MCAP", clouds, poses or [])
    bare = tmp / "drive.mcap"
    next((tmp / "b").glob("*.mcap")).rename(bare)
    shutil.rmtree(tmp / "b")
    return bare


def test_pointcloud2_with_lying_height_and_row_step(tmp_path: Path) -> None:
    """height 2^31 with row_step 0 passed the size check and looped over two billion rows."""
    def lying(ts):
        msg = _cloud_msg(ts, ground_scan(0, n=10), 50.1)
        msg.height, msg.row_step = 2**31, 0
        return msg

    good = [("/p", CLOUD, 50.2 + 0.1 * k, lambda ts, k=k: _cloud_msg(ts, ground_scan(k, t0=50.1 + 0.1 * k),
                                                                       50.2 + 0.1 * k)) for k in range(1, 3)]
    bare = _bag(tmp_path, [("/p", CLOUD, 50.1, lying), *good])
    out = tmp_path / "m.ply"
    proc = run_cli("extract", str(bare), "-o", str(out), timeout=60)
    # one bad scan of three is over the default share: one line naming the bag message
    assert_one_line_error(proc, f"{bare}:/p#0", out)


def test_navsatfix_latitude_200_is_an_input_error(tmp_path: Path) -> None:
    clouds = [("/p", CLOUD, 50.1, lambda ts: _cloud_msg(ts, ground_scan(0, t0=50.0), 50.1))]
    fixes = [("/fix", "sensor_msgs/msg/NavSatFix", 50.0 + 0.1 * i, lambda ts, i=i: _fix_msg(ts, 50 + 0.1 * i, 200.0))
             for i in range(3)]
    bare = _bag(tmp_path, clouds, fixes)
    with pytest.raises(InputError, match="latitude 200.0") as err:
        open_dataset(bare)
    one_line(err.value, bare)


@pytest.mark.parametrize("cut", ["half", "head", "random"])
def test_broken_mcap_is_one_line(tmp_path: Path, cut: str) -> None:
    clouds = [("/p", CLOUD, 50.1 + 0.1 * k, lambda ts, k=k: _cloud_msg(ts, ground_scan(k, t0=50 + 0.1 * k),
                                                                         50.1 + 0.1 * k)) for k in range(3)]
    bare = _bag(tmp_path, clouds)
    data = bare.read_bytes()
    rnd = random.Random(1)
    bare.write_bytes({"half": data[: len(data) // 2], "head": data[:40],
                      "random": data[:8] + bytes(rnd.getrandbits(8) for _ in range(4000))}[cut])
    out = tmp_path / "m.ply"
    assert_one_line_error(run_cli("extract", str(bare), "-o", str(out), timeout=60), str(bare), out)


# --- objects.csv ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("time,id,class,y,z\n1,a,car,0,0\n", r"missing column\(s\) x"),
        ("time,id,class,x,y\nnan,a,car,0,0\n", "column time is not finite"),
    ],
    ids=["no-x", "nan-time"],
)
def test_bad_objects_csv(tmp_path: Path, text: str, reason: str) -> None:
    from lidar2xodr.tracks import load_tracks

    (tmp_path / "objects.csv").write_text(text)
    with pytest.raises(InputError, match=reason) as err:
        load_tracks(tmp_path, None)
    one_line(err.value, tmp_path / "objects.csv")


# --- noise: one line per problem (item 11) --------------------------------------------------------


def test_corrupt_scans_give_one_summary_line_not_one_per_scan(small_synthetic_drive: Path, tmp_path: Path) -> None:
    drive = tmp_path / "d"
    shutil.copytree(small_synthetic_drive, drive)
    scans = sorted((drive / "scans").glob("*.pcd"))
    scans[1].write_bytes(b"garbage")
    s = ground_scan(0)
    s["xyz"][:] = np.nan
    save_pcd(scans[3], s)
    out = tmp_path / "m.ply"
    proc = run_cli("extract", str(drive), "-o", str(out))
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text
    lines = [ln for ln in text.splitlines() if ln.startswith("skip")]
    assert lines == [f"skipped 2 of {len(scans)} scans in {drive}: 1 unreadable (first: scans/{scans[1].name}: "
                     "PCD header has no DATA line), 1 empty"], text


def test_too_many_corrupt_scans_give_one_error_line(small_synthetic_drive: Path, tmp_path: Path) -> None:
    drive = tmp_path / "d"
    shutil.copytree(small_synthetic_drive, drive)
    for p in sorted((drive / "scans").glob("*.pcd"))[1:]:
        p.write_bytes(b"garbage")
    out = tmp_path / "m.ply"
    assert_one_line_error(run_cli("extract", str(drive), "-o", str(out)), str(drive), out)


def test_latitude_200_in_the_drive_poses_is_exit_2(small_synthetic_drive: Path, tmp_path: Path) -> None:
    """Issue #17 item 8: a latitude of 200 is bad input, exit 2 naming the file (it was not looked at)."""
    drive = tmp_path / "d"
    shutil.copytree(small_synthetic_drive, drive)
    poses = drive / "poses.csv"
    rows = poses.read_text().splitlines()
    poses.write_text("\n".join([rows[0]] + [r.rsplit(",", 3)[0] + ",200.0,9.0,300.0" for r in rows[1:]]) + "\n")
    out = tmp_path / "m.ply"
    assert_one_line_error(run_cli("extract", str(drive), "-o", str(out)), str(poses), out)


@pytest.fixture(scope="module")
def small_synthetic_drive(tmp_path_factory) -> Path:
    return write_drive(make_drive(n_scans=12, n_ground=3000, seed=4), tmp_path_factory.mktemp("syn") / "d")


# --- the real aiMotive sample with one corrupt frame (item 7) --------------------------------------


@pytest.fixture
def aimotive_with_corrupt_middle_frame(tmp_path: Path) -> tuple[Path, Path, int]:
    """A copy of the shared sample whose middle frame has 4 KiB of random bytes in its LAZ data."""
    sample = SHARED_DATA / "lidar" / "aimotive_highway_sample"
    if not sample.is_dir():
        pytest.skip(f"aiMotive sample not found at {sample} (set LIDAR2XODR_SHARED_DATA)")
    drive = tmp_path / "aim"
    shutil.copytree(sample, drive)
    frames = sorted((drive / "dynamic" / "raw-revolutions").glob("*.laz"))
    bad = frames[len(frames) // 2]
    bad.chmod(0o644)
    data = bytearray(bad.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 4096] = bytes(random.Random(0).getrandbits(8) for _ in range(4096))
    bad.write_bytes(bytes(data))
    return drive, bad, len(frames)


def test_aimotive_corrupt_frame_is_skipped_and_counted(aimotive_with_corrupt_middle_frame) -> None:
    drive, bad, n = aimotive_with_corrupt_middle_frame
    ds = open_dataset(drive)
    assert sum(1 for _ in ds) == n - 1
    assert [name for name, _ in ds.stats.bad_scans] == [str(bad)]
    assert ds.stats.summary(n, drive) == (f"skipped 1 of {n} scans in {drive}: 1 unreadable (first: "
                                          f"dynamic/raw-revolutions/{bad.name}: {ds.stats.bad_scans[0][1]})")


@pytest.mark.slow
def test_aimotive_sample_with_a_corrupt_middle_frame_still_builds(aimotive_with_corrupt_middle_frame,
                                                                  tmp_path: Path) -> None:
    drive, bad, n = aimotive_with_corrupt_middle_frame
    out = tmp_path / "aim.xodr"
    proc = run_cli("build", str(drive), "-o", str(out), timeout=400)
    text = proc.stdout + proc.stderr
    assert f"skipped 1 of {n} scans in {drive}: 1 unreadable (first: dynamic/raw-revolutions/{bad.name}: " \
           "cannot decode LAS/LAZ" in text
    assert "skipping scan" not in text
    assert proc.returncode == 0, text
    from lidar2xodr.opendrive import OpenDriveMap

    net = OpenDriveMap.load(out)
    assert net.roads and sum(r.length for r in net.roads.values()) > 100.0


def test_a_drive_simulated_with_rosbag_builds_from_its_mcap(tmp_path: Path) -> None:
    """Item 7: the MCAP that `simulate --rosbag` writes beside the PCDs builds a map (it gave a tenth of
    the marking points without the mount and the intensity scale, and the build ended in exit 2)."""
    from lidar2xodr.demo_road import write_demo_road
    from lidar2xodr.opendrive import OpenDriveMap
    from lidar2xodr.simulation import SimOptions, simulate

    truth = write_demo_road(tmp_path / "truth.xodr")
    drive = tmp_path / "drive"
    simulate(truth, drive, SimOptions(length_m=200.0, seed=1, traffic="none", rosbag=True))
    out = tmp_path / "from-mcap.xodr"
    proc = run_cli("build", str(drive / "drive.mcap"), "-o", str(out), timeout=300)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text
    net = OpenDriveMap.load(out)
    assert net.roads and sum(r.length for r in net.roads.values()) > 100.0, text
