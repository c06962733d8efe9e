"""Hypothesis fuzzing of every reader: random bytes and mutated valid files (issue #17).

Each case must end, within `CASE_TIMEOUT_S`, with valid data or the reader's own error (InputError;
CorruptScan for a single scan file, which the dataset then skips and counts), never another
exception. Cases run in one forked worker process whose address space is capped at its size after
the imports plus `CASE_MEMORY`: a reader that allocates what a lying header promises hits the cap,
and a MemoryError anywhere in the exception chain (even one the reader turned into InputError)
fails the case. A worker that does not answer in time is killed and the case fails as a hang.
Deterministic (derandomize) and small (max_examples), so that the file stays within ~60 s.
"""

from __future__ import annotations

import io
import multiprocessing
import os
import resource
import struct
import tempfile
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

CASE_TIMEOUT_S = 10.0
CASE_MEMORY = 512 << 20
EXAMPLES = 60

FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# --- the readers under test, as run inside the worker ----------------------------------------------


def _scan_file(suffix: str) -> Callable[[Path, bytes], str]:
    def run(tmp: Path, data: bytes) -> str:
        from lidar2xodr.datasets.pointfiles import read_scan_file

        path = tmp / f"000000{suffix}"
        path.write_bytes(data)
        raw = read_scan_file(path)
        n = len(raw.xyz)
        assert raw.xyz.shape == (n, 3)
        assert raw.intensity is None or len(raw.intensity) == n
        assert raw.times is None or len(raw.times) == n
        return f"ok {n} points"
    return run


def _mcap(tmp: Path, data: bytes) -> str:
    from lidar2xodr.datasets.rosbag import RosbagDataset

    path = tmp / "drive.mcap"
    path.write_bytes(data)
    ds = RosbagDataset(path)
    return f"ok {sum(1 for _ in ds)} scans"


def _ros1_bag(tmp: Path, data: bytes) -> str:
    from lidar2xodr.datasets.rosbag import RosbagDataset

    path = tmp / "drive.bag"
    path.write_bytes(data)
    ds = RosbagDataset(path)
    return f"ok {sum(1 for _ in ds)} scans"


def _poses_csv(tmp: Path, data: bytes) -> str:
    from lidar2xodr.datasets.poses import read_pose_csv

    path = tmp / "poses.csv"
    path.write_bytes(data)
    traj, _ = read_pose_csv(path)
    assert np.isfinite(traj.poses).all()
    return f"ok {len(traj)} poses"


def _objects_csv(tmp: Path, data: bytes) -> str:
    from lidar2xodr.tracks import load_tracks

    path = tmp / "objects.csv"
    path.write_bytes(data)
    return f"ok {len(load_tracks(path, None).tracks)} tracks"


def _meta_yaml(tmp: Path, data: bytes) -> str:
    from lidar2xodr.datasets.drive import DriveDataset

    (tmp / "meta.yaml").write_bytes(data)
    ds = DriveDataset(tmp)
    return f"ok {len(ds)} scans"


def _xodr(tmp: Path, data: bytes) -> str:
    from lidar2xodr.opendrive import OpenDriveMap

    path = tmp / "map.xodr"
    path.write_bytes(data)
    return f"ok {len(OpenDriveMap.load(path).roads)} roads"


READERS: dict[str, Callable[[Path, bytes], str]] = {
    **{s: _scan_file(f".{s}") for s in ("pcd", "las", "laz", "ply", "bin", "npy")},
    "mcap": _mcap, "bag": _ros1_bag, "poses": _poses_csv, "objects": _objects_csv, "meta": _meta_yaml, "xodr": _xodr,
}


def _memory_in_chain(exc: BaseException | None) -> bool:
    seen = 0
    while exc is not None and seen < 20:
        if isinstance(exc, MemoryError):
            return True
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return False


def _serve(conn, scan_dir: str) -> None:
    """Worker loop: cap the address space, then run (kind, bytes) cases until told to stop."""
    import lidar2xodr.datasets.drive  # noqa: F401  (imports before the cap: they are not the reader's)
    import lidar2xodr.datasets.rosbag  # noqa: F401
    import lidar2xodr.opendrive  # noqa: F401
    import lidar2xodr.tracks  # noqa: F401
    from lidar2xodr.datasets.base import CorruptScan
    from lidar2xodr.errors import InputError

    with open("/proc/self/statm") as fh:
        size = int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    resource.setrlimit(resource.RLIMIT_AS, (size + CASE_MEMORY, size + CASE_MEMORY))
    while True:
        kind, data = conn.recv()
        if kind is None:
            return
        with tempfile.TemporaryDirectory() as tmp:
            tmp_path = Path(tmp)
            if kind == "meta":
                os.symlink(scan_dir, tmp_path / "scans")
            try:
                answer = READERS[kind](tmp_path, data)
            except (InputError, CorruptScan) as exc:
                answer = "memory: " + str(exc) if _memory_in_chain(exc) else "error"
                if "\n" in str(exc):
                    answer = f"multi-line message: {exc!r}"
            except BaseException as exc:  # noqa: BLE001 - the point of the test
                answer = "memory: " if isinstance(exc, MemoryError) else "crash: "
                answer += "".join(traceback.format_exception(exc))[-3000:]
        conn.send(answer)


class Worker:
    """One forked reader process at a time; replaced after a hang."""

    def __init__(self, scan_dir: Path) -> None:
        self.scan_dir = scan_dir
        self.ctx = multiprocessing.get_context("fork")
        self._start()

    def _start(self) -> None:
        self.conn, child = self.ctx.Pipe()
        self.proc = self.ctx.Process(target=_serve, args=(child, str(self.scan_dir)), daemon=True)
        self.proc.start()

    def run(self, kind: str, data: bytes) -> str:
        if not self.proc.is_alive():
            self._start()
        self.conn.send((kind, data))
        answer = f"hang: no answer within {CASE_TIMEOUT_S} s"
        if self.conn.poll(CASE_TIMEOUT_S):
            try:
                return self.conn.recv()
            except EOFError:
                answer = "died (a library aborted the process, e.g. a failed native allocation)"
        self.proc.kill()
        self.proc.join()
        self._start()
        return f"{answer}; exit code {self.proc.exitcode}" if "died" in answer else answer

    def close(self) -> None:
        self.conn.send((None, None))
        self.proc.join(5)
        if self.proc.is_alive():
            self.proc.kill()


# --- valid seed files ------------------------------------------------------------------------------


def _scan(n: int = 64, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"xyz": rng.uniform(-20, 20, (n, 3)), "intensity": rng.uniform(0, 1, n),
            "t": 100.0 + np.sort(rng.uniform(0, 0.1, n))}


def _seed_pcd(encoding: str) -> bytes:
    from pypcd4 import Encoding, PointCloud

    s = _scan()
    pc = PointCloud.from_points([*s["xyz"].T, s["intensity"], s["t"]], ("x", "y", "z", "intensity", "t"),
                                (np.float32, np.float32, np.float32, np.float32, np.float64))
    with tempfile.TemporaryDirectory() as tmp:
        pc.save(Path(tmp) / "s.pcd", encoding=getattr(Encoding, encoding))
        return (Path(tmp) / "s.pcd").read_bytes()


def _seed_las(compressed: bool) -> bytes:
    import laspy

    s = _scan()
    hdr = laspy.LasHeader(point_format=1, version="1.2")
    hdr.scales, hdr.offsets = np.array([0.001] * 3), np.zeros(3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = s["xyz"].T
    las.intensity = np.round(s["intensity"] * 255).astype(np.uint16)
    las.gps_time = s["t"]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / ("s.laz" if compressed else "s.las")
        las.write(path, laz_backend=laspy.LazBackend.Lazrs if compressed else None)
        return path.read_bytes()


def _seed_ply() -> bytes:
    from lidar2xodr.markings_io import ply_bytes

    s = _scan()
    arr = np.empty(64, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u1"), ("t", "f8")])
    arr["x"], arr["y"], arr["z"] = s["xyz"].T
    arr["intensity"], arr["t"] = np.round(s["intensity"] * 255), s["t"]
    return ply_bytes(arr)


def _seed_npy() -> bytes:
    buf = io.BytesIO()
    s = _scan()
    np.save(buf, np.column_stack([s["xyz"], s["intensity"] * 100, s["t"]]))
    return buf.getvalue()


def _seed_mcap() -> bytes:
    from test_datasets import CLOUD, _cloud_msg, _fix_msg, _write_ros2

    clouds = [("/p", CLOUD, 50.1 + 0.1 * k,
               lambda ts, k=k: _cloud_msg(ts, {**_scan(16, k), "t": 50.0 + 0.1 * k + np.linspace(0, 0.09, 16)},
                                          50.1 + 0.1 * k)) for k in range(2)]
    fixes = [("/fix", "sensor_msgs/msg/NavSatFix", 50.0 + 0.1 * i, lambda ts, i=i: _fix_msg(ts, 50 + 0.1 * i, 48.0))
             for i in range(3)]
    with tempfile.TemporaryDirectory() as tmp:
        _write_ros2(Path(tmp) / "b", "MCAP", clouds, fixes)
        return next((Path(tmp) / "b").glob("*.mcap")).read_bytes()


def _seed_bag() -> bytes:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore
    from test_datasets import CLOUD, _cloud_msg, _pose_msg

    ts = get_typestore(Stores.ROS1_NOETIC)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "d.bag"
        with Writer(path) as w:
            c = w.add_connection("/points", CLOUD, typestore=ts)
            p = w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
            for i in range(3):
                w.write(p, int((50.0 + 0.05 * i) * 1e9),
                        ts.serialize_ros1(_pose_msg(ts, 50.0 + 0.05 * i, i, True), "geometry_msgs/msg/PoseStamped"))
            for k in range(2):
                s = {**_scan(16, k), "t": 50.0 + 0.1 * k + np.linspace(0, 0.09, 16)}
                w.write(c, int((50.1 + 0.1 * k) * 1e9),
                        ts.serialize_ros1(_cloud_msg(ts, s, 50.1 + 0.1 * k, ros1=True), CLOUD))
        return path.read_bytes()


SEED_POSES = (b"time,x,y,z,roll,pitch,yaw,lat,lon,alt\n" + b"".join(
    f"{100 + 0.1 * i:.1f},{2.0 * i},0.5,0,0,0,0.1,48.0,9.0,300\n".encode() for i in range(6)))
SEED_OBJECTS = (b"time,id,class,x,y,z,yaw,length,width,height,vx,vy\n" + b"".join(
    f"{100 + 0.1 * i:.1f},{k},car,{5.0 * k + 2.0 * i},{3.5 * k},0.8,0,4.5,1.8,1.5,20,0\n".encode()
    for i in range(12) for k in range(2)))
SEED_META = (b"format: lidar2xodr-drive\nversion: 1\nsensor:\n  name: s\n  mount: {x: 1.2, y: 0.0, z: 1.8, "
             b"roll: 0.0, pitch: 0.02, yaw: 0.0}\n  max_range_m: 100.0\n  intensity_scale: 150.0\n  rate_hz: 10\n"
             b"origin: {lat: 48.7, lon: 9.1, alt: 300.0, proj: null}\nscans: {dir: scans, format: pcd}\n")
SEED_XODR = b"""<?xml version="1.0"?>
<OpenDRIVE><header revMajor="1" revMinor="6"/>
<road id="1" length="100" junction="-1"><planView>
<geometry s="0" x="0" y="0" hdg="0" length="50"><line/></geometry>
<geometry s="50" x="50" y="0" hdg="0" length="50"><arc curvature="0.01"/></geometry></planView>
<lanes><laneSection s="0"><center><lane id="0" type="none"/></center>
<right><lane id="-1" type="driving"><width sOffset="0" a="3.5" b="0" c="0" d="0"/>
<roadMark sOffset="0" type="broken" width="0.15"/></lane></right></laneSection></lanes></road>
</OpenDRIVE>
"""


@pytest.fixture(scope="module")
def seeds() -> dict[str, bytes]:
    return {"pcd": _seed_pcd("BINARY"), "pcd_ascii": _seed_pcd("ASCII"), "pcd_lzf": _seed_pcd("BINARY_COMPRESSED"),
            "las": _seed_las(False), "laz": _seed_las(True), "ply": _seed_ply(),
            "bin": np.column_stack([_scan()["xyz"], _scan()["intensity"]]).astype("<f4").tobytes(),
            "npy": _seed_npy(), "mcap": _seed_mcap(), "bag": _seed_bag(), "poses": SEED_POSES, "objects": SEED_OBJECTS,
            "meta": SEED_META, "xodr": SEED_XODR}


@pytest.fixture(scope="module")
def worker(tmp_path_factory, seeds) -> Iterator[Worker]:
    scans = tmp_path_factory.mktemp("fuzz-scans")
    (scans / "000000.pcd").write_bytes(seeds["pcd"])
    w = Worker(scans)
    yield w
    w.close()


def check(worker: Worker, kind: str, data: bytes) -> None:
    answer = worker.run(kind, data)
    assert answer == "error" or answer.startswith("ok"), f"{kind} ({len(data)} bytes {data[:80]!r}...): {answer}"


def test_the_seeds_are_valid(worker: Worker, seeds: dict[str, bytes]) -> None:
    """Mutations start from files each reader accepts (else the fuzzing only tests the first check)."""
    for key, data in seeds.items():
        kind = key.split("_")[0]
        assert worker.run(kind, data).startswith("ok"), key


# --- strategies ------------------------------------------------------------------------------------

MAGIC = {"pcd": b"# .PCD v0.7\nVERSION 0.7\n", "las": b"LASF", "laz": b"LASF", "ply": b"ply\n",
         "npy": b"\x93NUMPY\x01\x00", "mcap": b"\x89MCAP0\r\n", "bag": b"#ROSBAG V2.0\n", "bin": b"",
         "poses": b"time,x,y,z,yaw\n",
         "objects": b"time,id,class,x,y\n", "meta": b"format: lidar2xodr-drive\nversion: 1\n",
         "xodr": b"<?xml version='1.0'?><OpenDRIVE>"}


@st.composite
def mutated(draw: st.DrawFn, data: bytes) -> bytes:
    """A valid file with a few byte flips, an inserted run, a truncation, or a number in it lying."""
    buf = bytearray(data)
    kind = draw(st.sampled_from(["flip", "truncate", "insert", "number", "int"]))
    if kind == "flip":
        for _ in range(draw(st.integers(1, 8))):
            buf[draw(st.integers(0, len(buf) - 1))] = draw(st.integers(0, 255))
    elif kind == "truncate":
        del buf[draw(st.integers(0, len(buf) - 1)):]
    elif kind == "insert":
        at = draw(st.integers(0, len(buf)))
        buf[at:at] = draw(st.binary(min_size=1, max_size=64))
    elif kind == "number":  # a number in a text header (counts, sizes, coordinates) replaced by another
        head = bytes(buf[:4096])
        spans = [(i, j) for i, j in _digit_runs(head)]
        if spans:
            i, j = draw(st.sampled_from(spans))
            value = draw(st.sampled_from([b"0", b"-1", b"4294967295", b"18446744073709551616", b"1e308",
                                          b"nan", b"-inf", b"999999999999"]))
            buf[i:j] = value
    else:  # a binary header field overwritten with a large or zero integer
        at = draw(st.integers(0, max(0, min(len(buf), 400) - 8)))
        width = draw(st.sampled_from([1, 2, 4, 8]))
        value = draw(st.sampled_from([0, 1, 2**(8 * width) - 1, 2**(8 * width - 1), 1000]))
        buf[at:at + width] = (value % 2 ** (8 * width)).to_bytes(width, "little")[: len(buf) - at]
    return bytes(buf)


def _digit_runs(head: bytes) -> list[tuple[int, int]]:
    import re

    return [(m.start(), m.end()) for m in re.finditer(rb"\d+(\.\d+)?", head)][:200]


KINDS = ["pcd", "las", "laz", "ply", "bin", "npy", "mcap", "bag", "poses", "objects", "meta", "xodr"]


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(data=st.data())
def test_random_bytes(worker: Worker, kind: str, data: st.DataObject) -> None:
    body = data.draw(st.binary(max_size=2048))
    prefix = data.draw(st.sampled_from([b"", MAGIC[kind]]))
    check(worker, kind, prefix + body)


SEED_KEYS = ["pcd", "pcd_ascii", "pcd_lzf", "las", "laz", "ply", "bin", "npy", "mcap", "bag", "poses", "objects",
             "meta", "xodr"]


@pytest.mark.parametrize("key", SEED_KEYS)
@FUZZ
@given(data=st.data())
def test_mutated_valid_files(worker: Worker, seeds: dict[str, bytes], key: str, data: st.DataObject) -> None:
    check(worker, key.split("_")[0], data.draw(mutated(seeds[key])))


def test_las_header_fields_each_lying(worker: Worker, seeds: dict[str, bytes]) -> None:
    """Every LAS/LAZ public-header field from the size fields on, set to 0 and to its maximum."""
    fields = [(94, "<H"), (96, "<I"), (100, "<I"), (104, "<B"), (105, "<H"), (107, "<I")]
    for key in ("las", "laz"):
        for at, fmt in fields:
            for value in (0, 2 ** (8 * struct.calcsize(fmt)) - 1):
                buf = bytearray(seeds[key])
                struct.pack_into(fmt, buf, at, value)
                check(worker, key, bytes(buf))
