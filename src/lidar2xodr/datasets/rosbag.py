"""ROS 1 bags (.bag, or a folder of split .bag files) and ROS 2 bags (sqlite3 or MCAP storage) via rosbags.

Decisions:
- Scans come from the one `sensor_msgs/PointCloud2` topic (x, y, z, intensity fields; a time
  field `t`/`time`/`timestamp`/`offset_time` is optional). Several PointCloud2 topics without
  `topic=` is an InputError listing them.
- Poses: `nav_msgs/Odometry`, else `geometry_msgs/PoseStamped`, else `sensor_msgs/NavSatFix`
  (several topics of the chosen kind without `pose_topic=` is an InputError). Odometry and pose
  messages are taken as poses of the vehicle frame in a local world frame. NavSatFix positions
  are projected into a local tmerc frame (see `poses.py`); they carry no orientation, so yaw is
  the direction of travel (roll and pitch zero) and fixes with status < 0 are dropped.
- The cloud's frame is the sensor frame. The mount is the chain of static transforms
  (`tf2_msgs/TFMessage` on a `*tf_static` topic) from the cloud's `frame_id` up to
  `base_footprint` / `base_link` (taken as the vehicle frame on the road, as Autoware places
  base_link), or to the top of the static tree. Without one the mount is estimated from the first
  scan's ground plane, and the lever arm between sensor and pose frame is ignored; the estimate
  from one scan is off by ~1 deg in pitch on the simulator's drives, which tilts far returns by
  metres and cost 96 % of the marking points there (with the transform: as many as from PCDs).
- Per-point times within 1 s of the header stamp are absolute; times with |median| < 1 s (after
  the unit guess) are offsets added to it. The scan stamp follows `base` (last point time, else
  the header stamp).
- A bare ROS 2 `.mcap` file (no metadata.yaml beside it, as the simulator writes) is read through
  a metadata.yaml generated from the file's own summary in a temporary folder; the bag's
  `custom_data` comes from the `rosbag2` metadata record that rosbag2 writers embed in the file.
- Intensity scale: the bag's custom data `lidar2xodr.intensity_scale` (written by the simulator:
  the Livox convention puts 100 % diffuse reflectivity at 150 of 255), else `intensity_scale=`,
  else detected from the first scan (`base.detect_intensity_scale`).
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lidar2xodr.data import GeoOrigin, SensorInfo, Trajectory
from lidar2xodr.datasets.base import RawScan, ScanFileDataset, check_trajectory
from lidar2xodr.datasets.pointfiles import from_structured
from lidar2xodr.datasets.poses import geodetic_to_local, poses_from_xyzrpy
from lidar2xodr.errors import InputError, one_line

CLOUD = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
FIX = "sensor_msgs/msg/NavSatFix"
TF = "tf2_msgs/msg/TFMessage"
VEHICLE_FRAMES = ("base_footprint", "base_link")
INTENSITY_SCALE_KEY = "lidar2xodr.intensity_scale"
_PF_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def is_rosbag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".bag", ".mcap", ".db3")
    return (path / "metadata.yaml").is_file() or any(path.glob("*.bag"))


MCAP_MAGIC = b"\x89MCAP0\r\n"


def check_mcap_records(mcap: Path) -> None:
    """InputError unless the MCAP file's top-level records (opcode, u64 length) tile the file.

    rosbags reads a record with the length it states, so a lying length (random bytes, a flipped
    bit) makes it allocate up to 2^64 bytes before it finds the file short.
    """
    import struct

    try:
        size = mcap.stat().st_size
        with mcap.open("rb") as fh:
            if fh.read(8) != MCAP_MAGIC:
                raise InputError(mcap, "not an MCAP file (no MCAP magic)")
            pos = 8
            while pos + 9 <= size - 8:
                fh.seek(pos)
                op, length = struct.unpack("<BQ", fh.read(9))
                if length > size - pos - 9:
                    raise InputError(mcap, f"MCAP record 0x{op:02x} at byte {pos} states {length} bytes, "
                                     f"{size - pos - 9} are left")
                pos += 9 + length
                if op == 0x02:  # footer
                    break
    except OSError as exc:
        raise InputError(mcap, f"cannot read: {exc.strerror or exc}") from None


ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"


def check_bag_records(bag: Path) -> None:
    """InputError unless a ROS 1 bag's records (u32 header length, header, u32 data length, data)
    tile the file: rosbags reads each with the length it states (up to 4 GiB per read)."""
    import struct

    try:
        size = bag.stat().st_size
        with bag.open("rb") as fh:
            if fh.read(len(ROSBAG1_MAGIC)) != ROSBAG1_MAGIC:
                raise InputError(bag, "not a ROS 1 bag (no '#ROSBAG V2.0' line)")
            pos = len(ROSBAG1_MAGIC)
            while pos < size:
                fh.seek(pos)
                top = fh.read(4)
                (n_head,) = struct.unpack("<I", top.ljust(4, b"\xff"))
                if len(top) < 4 or n_head > size - pos - 8:
                    raise InputError(bag, f"ROS bag record at byte {pos} states a {n_head}-byte header, "
                                     f"{size - pos - 4} bytes are left")
                fh.seek(pos + 4 + n_head)
                (n_data,) = struct.unpack("<I", fh.read(4))
                if n_data > size - pos - 8 - n_head:
                    raise InputError(bag, f"ROS bag record at byte {pos} states {n_data} bytes of data, "
                                     f"{size - pos - 8 - n_head} are left")
                pos += 8 + n_head + n_data
    except OSError as exc:
        raise InputError(bag, f"cannot read: {exc.strerror or exc}") from None


def _mcap_custom_data(mcap: Path) -> dict[str, str] | None:
    """`custom_data` of the rosbag2 metadata record an MCAP file embeds (via its summary's metadata
    index); None when there is none. Every offset and length is checked against the file size."""
    import struct

    import yaml

    size = mcap.stat().st_size
    with mcap.open("rb") as fh:
        if size < 8 + 29 + 8:
            return None
        fh.seek(size - 8 - 29)
        op, length, summary, _ = struct.unpack("<BQQQ", fh.read(25))
        if op != 0x02 or length != 20 or not 8 <= summary <= size:
            return None
        fh.seek(summary)
        block = fh.read(size - 37 - summary)
        pos, index = 0, None
        while pos + 9 <= len(block):
            op, length = struct.unpack_from("<BQ", block, pos)
            if op == 0x0D and length >= 20:
                offset, rec_len = struct.unpack_from("<QQ", block, pos + 9)
                (n,) = struct.unpack_from("<I", block, pos + 25)
                if block[pos + 29:pos + 29 + n] == b"rosbag2":
                    index = (offset, rec_len)
            pos += 9 + length
        if index is None or not 8 <= index[0] and index[0] + index[1] <= size:
            return None
        fh.seek(index[0])
        rec = fh.read(index[1])
    try:
        (n,) = struct.unpack_from("<I", rec, 9)
        pos = 13 + n + 4
        fields = {}
        while pos < len(rec):
            (kn,) = struct.unpack_from("<I", rec, pos)
            key = rec[pos + 4:pos + 4 + kn].decode()
            (vn,) = struct.unpack_from("<I", rec, pos + 4 + kn)
            fields[key] = rec[pos + 8 + kn:pos + 8 + kn + vn].decode()
            pos += 8 + kn + vn
        meta = yaml.safe_load(fields.get("serialized_metadata", "")) or {}
        custom = meta.get("rosbag2_bagfile_information", meta).get("custom_data")  # rosbags embeds the inner map
    except (struct.error, UnicodeDecodeError, yaml.YAMLError, AttributeError):
        return None
    return {str(k): str(v) for k, v in custom.items()} if isinstance(custom, dict) else None


def _mcap_metadata(mcap: Path) -> dict[str, Any]:
    """rosbag2 metadata for a bare ROS 2 MCAP file, from its summary (channels, per-chunk counts)."""
    from rosbags.rosbag2.storage_mcap import MCAPFile

    check_mcap_records(mcap)
    f = MCAPFile(mcap)
    try:
        f.open()
        if not f.channels:
            f.meta_scan()
    except Exception as exc:  # rosbags raises ReaderError, AssertionError, struct errors
        raise InputError(mcap, f"cannot read MCAP: {one_line(exc)}") from None
    finally:
        if f.bio is not None:
            f.close()
    counts: dict[int, int] = {}
    for chunk in f.chunks:
        for cid, n in chunk.channel_count.items():
            counts[cid] = counts.get(cid, 0) + n
    topics = [
        {"message_count": counts.get(cid, 0),
         "topic_metadata": {"name": ch.topic, "type": ch.schema, "serialization_format": ch.message_encoding,
                            "offered_qos_profiles": "", "type_description_hash": ""}}
        for cid, ch in sorted(f.channels.items())
    ]
    total = sum(counts.values())
    return {"rosbag2_bagfile_information": {
        "version": 8, "storage_identifier": "mcap", "relative_file_paths": [mcap.name],
        "duration": {"nanoseconds": 0}, "starting_time": {"nanoseconds_since_epoch": 0},
        "message_count": total, "topics_with_message_count": topics,
        "compression_format": "", "compression_mode": "", "custom_data": _mcap_custom_data(mcap), "ros_distro": "",
        "files": [{"path": mcap.name, "starting_time": {"nanoseconds_since_epoch": 0},
                   "duration": {"nanoseconds": 0}, "message_count": total}],
    }}


def _bag_paths(path: Path, scratch: Path) -> list[Path]:
    """What AnyReader opens; a bare .mcap gets a generated metadata.yaml in `scratch`."""
    if path.is_file() and path.suffix == ".bag":
        check_bag_records(path)
        return [path]
    if path.is_file():
        if (path.parent / "metadata.yaml").is_file():
            return [path.parent]
        if path.suffix != ".mcap":
            raise InputError(path, "a rosbag2 storage file needs the metadata.yaml beside it")
        import yaml

        (scratch / path.name).symlink_to(path.resolve())
        (scratch / "metadata.yaml").write_text(yaml.safe_dump(_mcap_metadata(path)), encoding="utf-8")
        return [scratch]
    if (path / "metadata.yaml").is_file():
        return [path]
    bags = sorted(path.glob("*.bag"))
    for bag in bags:
        check_bag_records(bag)
    if bags:
        return bags
    raise InputError(path, "no ROS bag found (a .bag file, a folder of .bag files, a rosbag2 folder or .mcap)")


def stamp_seconds(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def cloud_array(msg: Any) -> np.ndarray:
    """The points of a PointCloud2 as a structured numpy array (padding and row_step honoured).

    The layout the header states (fields inside `point_step`, rows of `row_step` bytes, `height`
    rows) is checked against the data before anything is allocated: a lying height or row step
    would otherwise loop over billions of empty rows.
    """
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _PF_TYPES or f.count != 1:
            continue
        names.append(f.name)
        formats.append(order + _PF_TYPES[f.datatype])
        offsets.append(f.offset)
    ends = [o + np.dtype(t).itemsize for o, t in zip(offsets, formats, strict=True)]
    if len(set(names)) != len(names):
        raise ValueError(f"repeated field names {names}")
    raw = np.asarray(msg.data, dtype=np.uint8)
    n_row = msg.width * msg.point_step
    if msg.width and msg.height and (max(ends, default=0) > msg.point_step or msg.row_step < n_row):
        raise ValueError(f"fields end at byte {max(ends, default=0)} of a {msg.point_step}-byte point, "
                         f"rows of {msg.width} points need {n_row} bytes, row_step is {msg.row_step}")
    n = msg.width * msg.height
    if n and raw.size < (msg.height - 1) * msg.row_step + n_row:
        raise ValueError(f"data has {raw.size} bytes, header promises {msg.height} rows of {msg.row_step}")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": max(msg.point_step, 1)})
    if n == 0:
        return np.zeros(0, dtype=dtype)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(msg.height, n_row), strides=(msg.row_step, 1))
    return np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dtype, count=n)


def _choose(topics: dict[str, Any], msgtype: str, wanted: str | None, what: str, where: Path) -> str | None:
    found = sorted(t for t, info in topics.items() if info.msgtype == msgtype)
    if wanted is not None:
        return wanted if wanted in found else None
    if len(found) > 1:
        raise InputError(where, f"several {what} topics {found}: choose one with --topic/--pose-topic")
    return found[0] if found else None


def _yaw_from_track(xy: np.ndarray) -> np.ndarray:
    """Heading of travel at each fix (central differences); held where the vehicle stands still."""
    d = np.gradient(xy, axis=0)
    moving = np.hypot(d[:, 0], d[:, 1]) > 0.05
    yaw = np.arctan2(d[:, 1], d[:, 0])
    if not moving.any():
        return np.zeros(len(xy))
    idx = np.where(moving, np.arange(len(xy)), -1)
    idx = np.maximum.accumulate(idx)
    first = int(np.argmax(moving))
    idx[idx < 0] = first
    return np.unwrap(yaw[idx])


class RosbagDataset(ScanFileDataset):
    """Reader of PointCloud2 scans and pose topics from ROS 1/2 bags."""

    estimate_mount = True

    def __init__(self, path: Path, topic: str | None = None, pose_topic: str | None = None,
                 intensity_scale: float | None = None, max_range_m: float = 200.0) -> None:
        from rosbags.highlevel import AnyReader

        super().__init__()
        self.path = path
        self._scratch = tempfile.TemporaryDirectory(prefix="lidar2xodr-bag-")
        self._paths = _bag_paths(path, Path(self._scratch.name))
        self._AnyReader = AnyReader
        try:
            with AnyReader(self._paths) as reader:
                topics = reader.topics
                self.topic = _choose(topics, CLOUD, topic, "PointCloud2", path)
                if self.topic is None:
                    have = sorted(t for t, i in topics.items() if i.msgtype == CLOUD)
                    raise InputError(path, f"no PointCloud2 topic {topic or ''} (PointCloud2 topics: {have})")
                self.count = int(topics[self.topic].msgcount)
                self._load_poses(reader, topics, pose_topic)
                mount = self._static_mount(reader, topics)
                custom = getattr(reader.readers[0], "custom_data", None) or {}
        except InputError:
            raise
        except Exception as exc:  # AnyReaderError, and the struct, decoder and value errors of rosbags
            raise InputError(path, f"cannot open bag: {one_line(exc)}") from None
        if self.count == 0:
            raise InputError(path, f"topic {self.topic} has no messages")
        self.items = range(self.count)
        self.sensor = SensorInfo(name=self.topic, max_range_m=max_range_m)
        if mount is not None:
            self.sensor.mount = mount
            self.estimate_mount = False
        if intensity_scale is None and INTENSITY_SCALE_KEY in custom:
            try:
                intensity_scale = float(custom[INTENSITY_SCALE_KEY])
            except ValueError:
                intensity_scale = None
            if intensity_scale is None or not (np.isfinite(intensity_scale) and intensity_scale > 0):
                raise InputError(path, f"custom data {INTENSITY_SCALE_KEY} {custom[INTENSITY_SCALE_KEY]!r} "
                                 "is not a positive number")
        if intensity_scale is not None:
            self.intensity_scale = self.sensor.intensity_scale = float(intensity_scale)

    def _name(self, k: int) -> str:
        return f"{self.path}:{self.topic}#{k}"

    def _load_poses(self, reader: Any, topics: dict[str, Any], pose_topic: str | None) -> None:
        self.origin = GeoOrigin()
        for msgtype, what in ((ODOMETRY, "Odometry"), (POSE, "PoseStamped"), (FIX, "NavSatFix")):
            chosen = _choose(topics, msgtype, pose_topic, what, self.path)
            if chosen is None:
                continue
            conns = [c for c in reader.connections if c.topic == chosen]
            rows = []
            for conn, _, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                t = stamp_seconds(msg.header)
                if msgtype == FIX:
                    if msg.status.status >= 0:
                        rows.append((t, msg.latitude, msg.longitude, msg.altitude))
                    continue
                pose = msg.pose.pose if msgtype == ODOMETRY else msg.pose
                p, q = pose.position, pose.orientation
                rows.append((t, p.x, p.y, p.z, q.x, q.y, q.z, q.w))
            if not rows:
                raise InputError(self.path, f"pose topic {chosen} has no usable message")
            data = np.array(rows, dtype=np.float64)
            where = f"{self.path}:{chosen}"
            check_trajectory(data[:, 0], where)
            if msgtype == FIX:
                xyz, self.origin = geodetic_to_local(data[:, 1], data[:, 2], data[:, 3], where)
                rpy = np.column_stack([np.zeros(len(xyz)), np.zeros(len(xyz)), _yaw_from_track(xyz[:, :2])])
                poses = poses_from_xyzrpy(xyz, rpy)
            else:
                from scipy.spatial.transform import Rotation

                quat = data[:, 4:8]
                if not np.all(np.linalg.norm(quat, axis=1) > 0.5):
                    raise InputError(where, "pose orientations are not unit quaternions")
                poses = np.tile(np.eye(4), (len(data), 1, 1))
                poses[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
                poses[:, :3, 3] = data[:, 1:4]
            self._trajectory = Trajectory(times=data[:, 0], poses=poses)
            return
        if pose_topic is not None:
            raise InputError(self.path, f"pose topic {pose_topic} not found (Odometry, PoseStamped or NavSatFix)")

    def poses(self) -> Trajectory | None:
        return self._trajectory

    def _static_mount(self, reader: Any, topics: dict[str, Any]) -> np.ndarray | None:
        """T_vehicle_sensor from the bag's static transforms (module doc); None without them."""
        from scipy.spatial.transform import Rotation

        tf_topics = {t for t, info in topics.items() if info.msgtype == TF and t.endswith("tf_static")}
        if not tf_topics:
            return None
        clouds = [c for c in reader.connections if c.topic == self.topic]
        first = next(iter(reader.messages(connections=clouds)), None)
        if first is None:
            return None
        frame = reader.deserialize(first[2], first[0].msgtype).header.frame_id.lstrip("/")
        parents: dict[str, tuple[str, np.ndarray]] = {}
        where = f"{self.path}:{'/'.join(sorted(tf_topics))}"
        for conn, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic in tf_topics]):
            for tr in reader.deserialize(raw, conn.msgtype).transforms:
                p, q = tr.transform.translation, tr.transform.rotation
                quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
                xyz = np.array([p.x, p.y, p.z], dtype=np.float64)
                if not (np.isfinite(xyz).all() and np.isfinite(quat).all() and abs(np.linalg.norm(quat) - 1) < 1e-3):
                    raise InputError(where, f"transform {tr.header.frame_id} -> {tr.child_frame_id} is not a "
                                     "finite rigid transform with a unit quaternion")
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = Rotation.from_quat(quat).as_matrix(), xyz
                parents[tr.child_frame_id.lstrip("/")] = (tr.header.frame_id.lstrip("/"), T)
        mount, f, seen = np.eye(4), frame, set()
        while f in parents and f not in seen and f not in VEHICLE_FRAMES:
            seen.add(f)
            f, T = parents[f]
            mount = T @ mount
        return mount if seen else None

    def _messages(self, reader: Any, conns: list[Any]) -> Iterator[tuple[Any, bytes | None]]:
        """(connection, raw message) of the scan topic; after a broken record the rest count as bad.

        A bag cannot be read past a record it cannot parse, so the messages the index promised
        beyond it are listed as unreadable (one entry each, for the share check) and end the read.
        """
        it = reader.messages(connections=conns)
        k = 0
        while True:
            try:
                conn, _, rawdata = next(it)
            except StopIteration:
                return
            except Exception as exc:  # rosbags raises struct, decompression and value errors
                for j in range(k, max(self.count, k + 1)):
                    self._bad(self._name(j), f"cannot read the bag from message {k} on: {one_line(exc)}")
                    yield None, None
                return
            k += 1
            yield conn, rawdata

    def _raw_scans(self) -> Iterator[tuple[int, RawScan | None]]:
        with self._AnyReader(self._paths) as reader:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for k, (conn, rawdata) in enumerate(self._messages(reader, conns)):
                if rawdata is None:
                    yield k, None
                    continue
                try:
                    msg = reader.deserialize(rawdata, conn.msgtype)
                    arr = cloud_array(msg)
                except Exception as exc:  # rosbags raises several kinds on a broken message
                    self._bad(self._name(k), f"cannot decode PointCloud2: {one_line(exc)}")
                    yield k, None
                    continue
                raw = from_structured(arr, self._name(k))
                if raw.intensity is None:
                    raise InputError(self._name(k), "PointCloud2 has no intensity field; lane markings are "
                                     "found by their reflectivity")
                raw.stamp = stamp_seconds(msg.header)
                if raw.times is not None:
                    med = float(np.nanmedian(raw.times))
                    if abs(med - raw.stamp) > 1.0 and abs(med) < 1.0:
                        raw.times = raw.times + raw.stamp
                yield k, raw
