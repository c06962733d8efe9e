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
- The cloud's frame is the sensor frame; TF is not read, so the mount is estimated from the
  first scan's ground plane, and the lever arm between sensor and pose frame is ignored.
- Per-point times within 1 s of the header stamp are absolute; times with |median| < 1 s (after
  the unit guess) are offsets added to it. The scan stamp follows `base` (last point time, else
  the header stamp).
- A bare ROS 2 `.mcap` file (no metadata.yaml beside it, as the simulator writes) is read through
  a metadata.yaml generated from the file's own summary in a temporary folder.
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
from lidar2xodr.errors import InputError

CLOUD = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
FIX = "sensor_msgs/msg/NavSatFix"
_PF_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def is_rosbag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".bag", ".mcap", ".db3")
    return (path / "metadata.yaml").is_file() or any(path.glob("*.bag"))


def _mcap_metadata(mcap: Path) -> dict[str, Any]:
    """rosbag2 metadata for a bare ROS 2 MCAP file, from its summary (channels, per-chunk counts)."""
    from rosbags.rosbag2.storage_mcap import MCAPFile

    f = MCAPFile(mcap)
    try:
        f.open()
        if not f.channels:
            f.meta_scan()
    except Exception as exc:  # rosbags raises ReaderError, AssertionError, struct errors
        raise InputError(mcap, f"cannot read MCAP: {exc}") from None
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
        "compression_format": "", "compression_mode": "", "custom_data": None, "ros_distro": "",
        "files": [{"path": mcap.name, "starting_time": {"nanoseconds_since_epoch": 0},
                   "duration": {"nanoseconds": 0}, "message_count": total}],
    }}


def _bag_paths(path: Path, scratch: Path) -> list[Path]:
    """What AnyReader opens; a bare .mcap gets a generated metadata.yaml in `scratch`."""
    if path.is_file() and path.suffix == ".bag":
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
    if bags:
        return bags
    raise InputError(path, "no ROS bag found (a .bag file, a folder of .bag files, a rosbag2 folder or .mcap)")


def stamp_seconds(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def cloud_array(msg: Any) -> np.ndarray:
    """The points of a PointCloud2 as a structured numpy array (padding and row_step honoured)."""
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _PF_TYPES or f.count != 1:
            continue
        names.append(f.name)
        formats.append(order + _PF_TYPES[f.datatype])
        offsets.append(f.offset)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step})
    raw = np.asarray(msg.data, dtype=np.uint8)
    n_row = msg.width * msg.point_step
    if raw.size < msg.height * msg.row_step - (msg.row_step - n_row):
        raise ValueError(f"data has {raw.size} bytes, header promises {msg.height} rows of {msg.row_step}")
    rows = [raw[r * msg.row_step:r * msg.row_step + n_row] for r in range(msg.height)]
    buf = np.concatenate(rows) if len(rows) != 1 else rows[0]
    return np.frombuffer(buf.tobytes(), dtype=dtype, count=msg.width * msg.height)


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
        from rosbags.highlevel import AnyReader, AnyReaderError

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
        except AnyReaderError as exc:
            raise InputError(path, f"cannot open bag: {exc}") from None
        if self.count == 0:
            raise InputError(path, f"topic {self.topic} has no messages")
        self.items = range(self.count)
        self.sensor = SensorInfo(name=self.topic, max_range_m=max_range_m)
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
                xyz, self.origin = geodetic_to_local(data[:, 1], data[:, 2], data[:, 3])
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

    def _raw_scans(self) -> Iterator[tuple[int, RawScan | None]]:
        with self._AnyReader(self._paths) as reader:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for k, (conn, _, rawdata) in enumerate(reader.messages(connections=conns)):
                try:
                    msg = reader.deserialize(rawdata, conn.msgtype)
                    arr = cloud_array(msg)
                except Exception as exc:  # rosbags raises several kinds on a broken message
                    self._bad(self._name(k), f"cannot decode PointCloud2: {exc}")
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
