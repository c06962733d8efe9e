"""The drive simulator: layout, determinism, readable scans, marks on the true polygons, occlusion,
GNSS statistics, laps and bad input. Most checks run on a tiny straight map written here, where
map x = station s and map y = lateral t, so the true paint polygons are known exactly."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import yaml
from pypcd4 import PointCloud
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from lidar2xodr.cli import app
from lidar2xodr.errors import InputError, OutputError
from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.simulation import T0, SimOptions, simulate
from lidar2xodr.simulation.gnss import pose_errors
from lidar2xodr.simulation.route import RoadGraph, build_route, longest_chain, turn_shape
from lidar2xodr.simulation.sensors import LIVOX_HORIZON, PANDAR64, pandar64_elevations

GEO = "+proj=tmerc +lat_0=48.78 +lon_0=9.18 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
DASH, GAP = 6.0, 12.0


def _lane(lid: int, kind: str, width: float, mark: str | None, mark_width: float = 0.15) -> str:
    rm = f'<roadMark sOffset="0" type="{mark}" weight="standard" color="white" width="{mark_width}"/>' if mark else ""
    return f'<lane id="{lid}" type="{kind}" level="false"><width sOffset="0" a="{width}" b="0" c="0" d="0"/>{rm}</lane>'


def tiny_map(path: Path, length: float = 1000.0, two_way: bool = False, geo: bool = False,
             driving: str = "driving") -> Path:
    """A straight road along +x. Right: -1 (broken 0.15 at y=-3.5), -2 (solid 0.30 at y=-7), shoulder.
    Centre line solid 0.15 at y=0. Left: a 1 m border (one-way) or two driving lanes (two-way)."""
    if two_way:
        left = _lane(2, driving, 3.5, "solid", 0.3) + _lane(1, driving, 3.5, "broken")
    else:
        left = _lane(1, "border", 1.0, None)
    right = _lane(-1, driving, 3.5, "broken") + _lane(-2, driving, 3.5, "solid", 0.3) + _lane(-3, "shoulder", 2.5, None)
    geo_el = f"<geoReference><![CDATA[{GEO}]]></geoReference>" if geo else ""
    path.write_text(f"""<?xml version="1.0" encoding="UTF-8"?>
<OpenDRIVE><header revMajor="1" revMinor="7" name="tiny">{geo_el}</header>
<road name="tiny" length="{length}" id="1" junction="-1">
<link/><planView><geometry s="0" x="0" y="0" hdg="0" length="{length}"><line/></geometry></planView>
<elevationProfile><elevation s="0" a="0" b="0" c="0" d="0"/></elevationProfile>
<lanes><laneSection s="0"><left>{left}</left>
<center><lane id="0" type="none" level="false"><roadMark sOffset="0" type="solid" weight="standard" color="white"
 width="0.15"/></lane></center><right>{right}</right></laneSection></lanes></road></OpenDRIVE>
""", encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------------------- reading back


def read_pcd_plain(path: Path) -> np.ndarray:
    """Independent PCD reader: header by hand, binary body with numpy."""
    raw = path.read_bytes()
    header, _, body = raw.partition(b"DATA binary\n")
    fields = sizes = types = None
    for line in header.decode("ascii").splitlines():
        key, *vals = line.split()
        if key == "FIELDS":
            fields = vals
        elif key == "SIZE":
            sizes = [int(v) for v in vals]
        elif key == "TYPE":
            types = vals
    assert fields and sizes and types
    dtype = np.dtype([(f, {"F": "f", "U": "u", "I": "i"}[t] + str(s)) for f, s, t in zip(fields, sizes, types,
                                                                                    strict=True)])
    return np.frombuffer(body, dtype=dtype)


def load_poses(path: Path) -> np.ndarray:
    rows = [line.split(",") for line in path.read_text().splitlines()[1:]]
    return np.array([[float(v) for v in r[:7]] for r in rows])


class Drive:
    """A written drive with helpers that put scan points into the map frame using the TRUE poses."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.meta = yaml.safe_load((root / "meta.yaml").read_text())
        self.truth = load_poses(root / "truth" / "poses.csv")
        m = self.meta["sensor"]["mount"]
        self.mount_rot = Rotation.from_euler("ZYX", [m["yaw"], m["pitch"], m["roll"]]).as_matrix()
        self.mount_pos = np.array([m["x"], m["y"], m["z"]])
        self.scale = self.meta["sensor"]["intensity_scale"]
        self.scans = sorted((root / "scans").glob("*.pcd"))

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self.truth
        pos = np.column_stack([np.interp(t, p[:, 0], p[:, i]) for i in (1, 2, 3)])
        ang = [np.interp(t, p[:, 0], np.unwrap(p[:, i])) for i in (6, 5, 4)]
        return pos, Rotation.from_euler("ZYX", np.column_stack(ang)).as_matrix()

    def world(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """World points, reflectivity (1 = 100 %), times and sensor origins of scan k."""
        a = read_pcd_plain(self.scans[k])
        xyz = np.column_stack([a["x"], a["y"], a["z"]]).astype(np.float64)
        pos, rot = self.pose(a["t"])
        veh = xyz @ self.mount_rot.T + self.mount_pos
        origin = pos + np.einsum("nij,j->ni", rot, self.mount_pos)
        return pos + np.einsum("nij,nj->ni", rot, veh), a["intensity"] / self.scale, a["t"], origin


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Drive:
    tmp = tmp_path_factory.mktemp("sim")
    xodr = tiny_map(tmp / "tiny.xodr", 1000.0)
    simulate(xodr, tmp / "drive", SimOptions(length_m=450.0, traffic="high", seed=3, rosbag=True))
    return Drive(tmp / "drive")


# ---------------------------------------------------------------------------------------------- layout


def test_drive_directory_layout(drive: Drive) -> None:
    root = drive.root
    for rel in ("meta.yaml", "poses.csv", "objects.csv", "preview.png", "drive.mcap", "truth/map.xodr",
                "truth/poses.csv", "truth/objects.csv", "truth/route.json"):
        assert (root / rel).is_file(), rel
    meta = drive.meta
    assert meta["format"] == "lidar2xodr-drive" and meta["version"] == 1
    assert meta["sensor"]["name"] == "livox-horizon"
    assert set(meta["sensor"]["mount"]) == {"x", "y", "z", "roll", "pitch", "yaw"}
    assert meta["sensor"]["intensity_scale"] == 150.0 and meta["sensor"]["rate_hz"] == 10.0
    assert meta["origin"]["lat"] is None and meta["origin"]["lon"] is None and meta["origin"]["note"]
    assert meta["offset"] == [0.0, 0.0, 0.0]
    assert meta["scans"] == {"dir": "scans", "format": "pcd"}
    assert meta["seed"] == 3 and meta["options"]["traffic"] == "high"
    assert (root / "poses.csv").read_text().splitlines()[0] == "time,x,y,z,roll,pitch,yaw,lat,lon,alt"
    assert (root / "objects.csv").read_text().splitlines()[0] == "time,id,class,x,y,z,yaw,length,width,height,vx,vy"
    assert (root / "truth" / "map.xodr").read_bytes() == (root.parent / "tiny.xodr").read_bytes()
    # 450 m at motorway speed: one scan per 0.1 s of the drive
    duration = drive.truth[-1, 0] - drive.truth[0, 0]
    assert len(drive.scans) == int(duration / 0.1 + 1e-6)
    assert drive.truth[-1, 1] == pytest.approx(450.0, abs=1.0)  # straight road: x = distance driven
    assert not list(root.parent.glob(".drive.*")), "temporary directories left behind"
    assert min(_pcd_points(p) for p in drive.scans) > 3000, "a scan (e.g. at the map's end) came out empty"


def _pcd_points(path: Path) -> int:
    head = path.read_bytes()[:400].split(b"DATA")[0].decode()
    return int(next(line.split()[1] for line in head.splitlines() if line.startswith("POINTS")))


def test_scans_read_back_with_three_readers(drive: Drive) -> None:
    path = drive.scans[len(drive.scans) // 2]
    plain = read_pcd_plain(path)
    pc = PointCloud.from_path(path)
    assert tuple(pc.fields) == ("x", "y", "z", "intensity", "t")
    arr = pc.numpy(("x", "y", "z", "intensity", "t"))
    t_o3d = o3d.t.io.read_point_cloud(str(path))
    pos = t_o3d.point.positions.numpy()
    assert len(plain) == len(arr) == len(pos) > 5000
    np.testing.assert_array_equal(arr[:, 0], plain["x"])
    np.testing.assert_array_equal(pos[:, 2], plain["z"])
    np.testing.assert_array_equal(t_o3d.point.t.numpy()[:, 0], plain["t"])
    assert plain["t"].dtype == np.float64
    k = drive.scans.index(path)
    assert np.all((plain["t"] >= T0 + 0.1 * k) & (plain["t"] < T0 + 0.1 * (k + 1)))
    rng = np.linalg.norm(np.column_stack([plain["x"], plain["y"], plain["z"]]), axis=1)
    assert rng.max() <= LIVOX_HORIZON.max_range_m + 25.0  # + multipath ghosts
    assert np.all(plain["intensity"] == np.round(plain["intensity"])) and plain["intensity"].max() <= 255
    # sensor frame: everything lies inside the forward field of view
    az = np.degrees(np.arctan2(plain["y"], plain["x"]))
    assert np.all(np.abs(az) <= 41.0)


def test_deterministic_bytes_and_seed_matters(tmp_path: Path) -> None:
    xodr = tiny_map(tmp_path / "m.xodr", 400.0)
    digests = []
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        simulate(xodr, tmp_path / name, SimOptions(length_m=120.0, seed=seed, traffic="mid", gnss_outage=True))
        files = sorted(p for p in (tmp_path / name).rglob("*") if p.is_file())
        digests.append({str(p.relative_to(tmp_path / name)): hashlib.sha256(p.read_bytes()).hexdigest()
                        for p in files})
    assert digests[0] == digests[1]
    assert digests[0]["scans/000005.pcd"] != digests[2]["scans/000005.pcd"]
    assert digests[0]["poses.csv"] != digests[2]["poses.csv"]


# ---------------------------------------------------------------------------------------------- content


def _mark_polygons(x: np.ndarray, y: np.ndarray, tol: float) -> np.ndarray:
    centre = np.abs(y) <= 0.075 + tol
    phase = np.mod(x, DASH + GAP)
    broken = (np.abs(y + 3.5) <= 0.075 + tol) & ((phase <= DASH + tol) | (phase >= DASH + GAP - tol))
    edge = np.abs(y + 7.0) <= 0.15 + tol
    return centre | broken | edge


def test_painted_marks_are_bright_and_lie_on_the_true_polygons(drive: Drive) -> None:
    pts, refl = [], []
    for k in range(20, len(drive.scans), 7):
        w, r, _, _ = drive.world(k)
        pts.append(w)
        refl.append(r)
    w, r = np.concatenate(pts), np.concatenate(refl)
    ground = (np.abs(w[:, 2]) < 0.1) & (w[:, 1] > -8.0) & (w[:, 1] < 1.0)
    on_paint = _mark_polygons(w[:, 0], w[:, 1], 0.1)
    clear_of_paint = ~_mark_polygons(w[:, 0], w[:, 1], 0.35)
    bright = ground & (r >= 0.45)
    assert bright.sum() > 2000
    assert np.mean(on_paint[bright]) > 0.97, "bright ground points off the painted polygons"
    assert np.median(r[ground & _mark_polygons(w[:, 0], w[:, 1], -0.03)]) > 0.55
    asphalt = ground & clear_of_paint
    assert np.median(r[asphalt]) < 0.12 and np.mean(r[asphalt] >= 0.45) < 0.01
    # the broken line shows its dashes and gaps: bright points only within the 6 m dashes
    dashed = bright & (np.abs(w[:, 1] + 3.5) < 0.2)
    phase = np.mod(w[dashed, 0], DASH + GAP)
    assert np.mean((phase <= DASH + 0.15) | (phase >= DASH + GAP - 0.15)) > 0.97
    assert len(np.unique(np.floor(w[dashed, 0] / (DASH + GAP)))) >= 10


def test_structures_above_sensor_are_scanned_but_not_in_the_preview(tmp_path: Path) -> None:
    from lidar2xodr.simulation import _stream
    from lidar2xodr.simulation.lidar import Lidar
    from lidar2xodr.simulation.poses import ego_track, traffic_poses
    from lidar2xodr.simulation.preview import PreviewCollector
    from lidar2xodr.simulation.scene import build_world
    from lidar2xodr.simulation.traffic import TrafficSim

    odr = OpenDriveMap.load(tiny_map(tmp_path / "m.xodr", 1000.0))
    route = build_route(odr, [("1", 1)], False, 1000.0, "m")
    agents = TrafficSim(route, "none", 110.0, _stream(0, 1)).run(620.0)
    ego = ego_track(route, agents, T0, _stream(0, 2))
    world = build_world(odr, ["1"], seed=0)
    lidar = Lidar(LIVOX_HORIZON, world, ego, traffic_poses(route, agents, 2), agents, T0, _stream(0, 3))
    col = PreviewCollector(LIVOX_HORIZON.mount_xyz[2], LIVOX_HORIZON.intensity_scale, 10**6)
    high = 0
    retro = 0
    for n in range(0, int(agents.times[-1] / 0.1), 3):
        scan = lidar.scan(n)
        high += int((scan.world[:, 2] > 4.5).sum())
        retro += int((scan.intensity > LIVOX_HORIZON.intensity_scale).sum())
        col.add(scan)
    assert high > 100, "no bridge or gantry in view"
    assert retro > 0
    z = col.heights()
    assert len(z) > 10000 and z.max() < LIVOX_HORIZON.mount_xyz[2] + 0.2


def test_objects_match_the_scans_and_vehicles_occlude(drive: Drive) -> None:
    truth = _objects(drive.root / "truth" / "objects.csv")
    seen = _objects(drive.root / "objects.csv")
    assert len(seen) > 20 and set(seen) <= set(truth)
    for key, row in seen.items():
        assert np.hypot(row[0] - truth[key][0], row[1] - truth[key][1]) < 0.6
    on_box = behind = inside = 0
    checked = set()
    for k in range(0, len(drive.scans), 4):
        w, _, t, origin = drive.world(k)
        t_mid = T0 + 0.1 * (k + 0.5)
        boxes = [(oid, v) for (tt, oid), v in truth.items() if abs(tt - t_mid) < 1e-3]
        for oid, (x, y, z, yaw, ln, wd, ht, vx, vy) in boxes:
            centre = np.column_stack([x + vx * (t - t_mid), y + vy * (t - t_mid), np.full(len(t), z)])
            rot = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
            o = np.column_stack([(origin - centre)[:, :2] @ rot.T, (origin - centre)[:, 2]])
            seg = w - origin
            d = np.column_stack([seg[:, :2] @ rot.T, seg[:, 2]])
            p = o + d  # the point in the box frame
            hit = (np.abs(p[:, 0]) < ln / 2 + 0.3) & (np.abs(p[:, 1]) < wd / 2 + 0.3) & (np.abs(p[:, 2]) < ht / 2 + 0.3)
            on_box += int(hit.sum())
            # no return may come from behind the vehicle: its ray would cross the box's core
            half = np.array([ln / 2 - 0.3, wd / 2 - 0.3, 0.25])
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-half - o) / d, (half - o) / d
            lo, hi = np.fmin(t1, t2).max(axis=1), np.fmax(t1, t2).min(axis=1)
            behind += int(((lo <= hi) & (hi > 0) & (lo < 1.0)).sum())
            if (t_mid, oid) in seen:
                checked.add((t_mid, oid))
                inside += int(hit.sum() >= 3)
    assert on_box > 300, "no vehicle in front of the sensor"
    assert behind <= max(3, 0.01 * on_box), f"{behind} returns lie behind a vehicle ({on_box} on vehicles)"
    assert checked and inside >= 0.95 * len(checked)


def _objects(path: Path) -> dict[tuple[float, int], tuple]:
    out = {}
    for line in path.read_text().splitlines()[1:]:
        v = line.split(",")
        out[(round(float(v[0]), 3), int(v[1]))] = tuple(float(a) for a in v[3:])
    return out


def test_rosbag_holds_points_and_poses(drive: Drive) -> None:
    from rosbags.rosbag2.storage_mcap import MCAPFile

    path = drive.root / "drive.mcap"
    assert path.read_bytes()[:8] == b"\x89MCAP0\r\n"
    f = MCAPFile(path)
    f.open()
    f.meta_scan()
    topics = {c.topic: c.schema for c in f.channels.values()}
    assert topics == {"/lidar/points": "sensor_msgs/msg/PointCloud2", "/gnss/pose": "geometry_msgs/msg/PoseStamped",
                      "/tf_static": "tf2_msgs/msg/TFMessage"}
    from types import SimpleNamespace

    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    conns = [SimpleNamespace(topic=t, msgtype=m) for t, m in topics.items()]
    counts: dict[str, int] = {}
    first: dict[str, object] = {}
    for conn, _, raw in f.messages(conns):
        counts[conn.topic] = counts.get(conn.topic, 0) + 1
        first.setdefault(conn.topic, ts.deserialize_cdr(raw, conn.msgtype))
    assert counts == {"/lidar/points": len(drive.scans), "/gnss/pose": len(drive.truth), "/tf_static": 1}
    (mount,) = first["/tf_static"].transforms
    assert (mount.header.frame_id, mount.child_frame_id) == ("base_link", "lidar")
    assert mount.transform.translation.z == pytest.approx(drive.mount_pos[2])
    cloud = first["/lidar/points"]
    assert cloud.width == len(read_pcd_plain(drive.scans[0])) and cloud.point_step == 24
    meas = load_poses(drive.root / "poses.csv")
    assert first["/gnss/pose"].pose.position.x == pytest.approx(meas[0, 1], abs=1e-3)
    f.close()


# ---------------------------------------------------------------------------------------------- GNSS


def test_gnss_noise_statistics_match_the_option() -> None:
    t = np.arange(0.0, 4 * 3600.0, 0.01)
    err, outages = pose_errors(t, 0.3, False, np.random.default_rng(1))
    assert outages == []
    assert np.std(err[:, 0]) == pytest.approx(0.3, rel=0.12)
    assert np.std(err[:, 1]) == pytest.approx(0.3, rel=0.12)
    assert np.std(err[:, 2]) == pytest.approx(0.45, rel=0.12)
    assert abs(np.mean(err[:, 0])) < 0.1
    # correlated, not white: errors one second apart are alike
    lag = 100
    assert np.corrcoef(err[:-lag, 0], err[lag:, 0])[0, 1] > 0.4
    zero, _ = pose_errors(t[:1000], 0.0, False, np.random.default_rng(1))
    assert not zero.any()


def test_gnss_outage_drifts_and_recovers() -> None:
    t = np.arange(0.0, 600.0, 0.01)
    err, outages = pose_errors(t, 0.05, True, np.random.default_rng(4))
    assert len(outages) == 2
    inside = np.zeros(len(t), bool)
    for a, b in outages:
        assert 20.0 <= b - a <= 45.0 and 60.0 <= a and b <= 540.0
        inside |= (t >= a) & (t < b)
    after = np.zeros(len(t), bool)
    for _, b in outages:
        after |= (t >= b + 3.0) & (t < b + 30.0)
    assert np.max(np.hypot(err[inside, 0], err[inside, 1])) > 0.5
    assert np.max(np.hypot(err[after, 0], err[after, 1])) < 0.35


def test_written_gnss_poses_differ_from_truth_by_the_option(drive: Drive) -> None:
    meas = load_poses(drive.root / "poses.csv")
    d = meas[:, 1:3] - drive.truth[:, 1:3]
    assert np.array_equal(meas[:, 0], drive.truth[:, 0])
    # a 15 s drive sees a short stretch of the 20 s correlated part: loose bounds
    assert 0.01 < np.std(d) < 0.15 and np.abs(d).max() < 0.4


def test_a_gnss_bias_shifts_every_pose_by_one_vector_and_changes_nothing_else(tmp_path: Path) -> None:
    xodr = tiny_map(tmp_path / "m.xodr", 400.0)
    plain, biased = tmp_path / "plain", tmp_path / "biased"
    simulate(xodr, plain, SimOptions(length_m=120.0, seed=5, traffic="low"))
    simulate(xodr, biased, SimOptions(length_m=120.0, seed=5, traffic="low", gnss_bias_m=1.5))
    for rel in ("scans/000005.pcd", "truth/poses.csv", "truth/objects.csv"):
        assert (plain / rel).read_bytes() == (biased / rel).read_bytes(), rel
    d = load_poses(biased / "poses.csv")[:, 1:4] - load_poses(plain / "poses.csv")[:, 1:4]
    assert np.ptp(d, axis=0).max() < 2e-3  # one constant vector (csv rounding aside)
    assert np.linalg.norm(d[:, :2].mean(axis=0)) == pytest.approx(1.5, abs=2e-3) and abs(d[:, 2]).max() < 1e-3
    listed = json.loads((biased / "truth" / "route.json").read_text())["gnss_bias_m"]
    assert np.allclose(listed, d[:, :2].mean(axis=0), atol=2e-3)
    assert "gnss_bias_m" not in json.loads((plain / "truth" / "route.json").read_text())


# ---------------------------------------------------------------------------------------------- route and laps


def test_route_repeats_back_and_forth_on_a_one_way_road(tmp_path: Path) -> None:
    odr = OpenDriveMap.load(tiny_map(tmp_path / "m.xodr", 300.0))
    nodes = longest_chain(RoadGraph(odr), None, "m")
    assert nodes == [("1", 1)]
    route = build_route(odr, nodes, False, 1000.0, "m")
    kinds = [(leg.kind, leg.direction, leg.wrong_way) for leg in route.legs]
    assert kinds[:4] == [("road", 1, False), ("turn", 1, False), ("road", -1, True), ("turn", -1, False)]
    turn = route.legs[1].turn
    assert turn is not None
    end = turn.world(np.array([turn.length]))[0]
    # the U-turn ends in the leftmost lane (lane -1, y = -1.75) heading back
    assert end[1] == pytest.approx(-1.75, abs=0.05)
    back = route.world(np.array([route.legs[2].u0 + 1.0]), np.array([route.same.lam[int(route.legs[2].u0) + 2, 0]]))
    assert np.linalg.norm(back[0, :2] - end[:2]) < 1.5


def test_turn_shapes_are_u_turns() -> None:
    for d in (0.0, 3.5, 12.0, 20.0):
        sigma, xy = turn_shape(d)
        assert xy[0] == pytest.approx([0.0, 0.0])
        assert xy[-1] == pytest.approx([0.0, d], abs=1e-6)
        step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        assert np.allclose(step, np.diff(sigma), atol=1e-3) and step.max() < 0.11


def test_laps_on_a_two_way_road_keep_poses_continuous(tmp_path: Path) -> None:
    xodr = tiny_map(tmp_path / "m.xodr", 220.0, two_way=True, geo=True)
    s = simulate(xodr, tmp_path / "d", SimOptions(length_m=380.0, traffic="none", seed=1, rosbag=True))
    assert s.passes == 2
    poses = load_poses(tmp_path / "d" / "truth" / "poses.csv")
    assert min(_pcd_points(p) for p in (tmp_path / "d" / "scans").glob("*.pcd")) > 1000  # U-turn included
    steps = np.linalg.norm(np.diff(poses[:, 1:3], axis=0), axis=1)
    assert steps.max() < 0.5  # 100 Hz: no jumps
    yaw = np.unwrap(poses[:, 6])
    assert abs(yaw[-1] - yaw[0]) == pytest.approx(math.pi, abs=0.1)
    assert poses[-1, 2] > 0.5  # back on the other side's lanes (left of the centre line)
    route = yaml.safe_load((tmp_path / "d" / "truth" / "route.json").read_text())
    assert [leg["kind"] for leg in route["legs"]] == ["road", "turn", "road"]
    assert route["legs"][2]["against_traffic"] is False
    rows = (tmp_path / "d" / "poses.csv").read_text().splitlines()
    lat = float(rows[1].split(",")[7])
    assert lat == pytest.approx(48.78, abs=0.01)
    meta = yaml.safe_load((tmp_path / "d" / "meta.yaml").read_text())
    assert meta["origin"]["lat"] == pytest.approx(48.78, abs=1e-6) and meta["origin"]["proj"] == GEO
    from rosbags.rosbag2.storage_mcap import MCAPFile

    f = MCAPFile(tmp_path / "d" / "drive.mcap")
    f.open()
    f.meta_scan()
    assert "/gnss/fix" in {c.topic for c in f.channels.values()}
    f.close()


def test_geo_reference_conventions() -> None:
    from lidar2xodr.simulation.writer import Geo

    carla = Geo("+lat_0=4.9000000000000000e+1 +lon_0=8.0000000000000000e+0")
    assert carla.ok and "CARLA" in (carla.note or "")
    lat, lon, alt = carla.latlon(np.array([[0.0, 1000.0, 5.0], [1000.0, 0.0, 5.0]]))
    assert lat[0] == pytest.approx(49.0 + 1000.0 / 111_200.0, abs=2e-4) and lon[1] > 8.01 and alt[0] == 5.0
    # as in esmini's straight_500_superelevation_elevation_curve.xodr: PROJ refuses it with the grid
    grids = Geo("+proj=utm +lat_0=37.35 +lon_0=-122.08 +k_0=1 +x_0=0 +y_0=0 +datum=WGS84 "
                "+geoidgrids=not_installed_here.gtx +vunits=m +zone=32 +ellps=GRS80 +units=m +no_defs")
    assert grids.ok and "grid" in (grids.note or "") and grids.origin()["lon"] == pytest.approx(4.5113, abs=1e-3)
    bad = Geo("no projection at all")
    assert not bad.ok and "not understood" in (bad.note or "")
    assert Geo(None).origin()["lat"] is None


# ---------------------------------------------------------------------------------------------- sensors


def test_pandar64_pattern() -> None:
    el = pandar64_elevations()
    assert len(el) == 64 and el.max() == 15.0 and el.min() == -25.0 and len(np.unique(el)) == 64
    d, t = PANDAR64.rays(T0, T0)
    assert d.shape == (115_200, 3) and np.all(np.diff(t) >= 0) and t[-1] - t[0] < 0.1
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    assert np.histogram(az, bins=36, range=(-180, 180))[0].min() > 2000


def test_livox_pattern_is_non_repetitive_and_fills_the_field_of_view() -> None:
    def coverage(n: int) -> float:
        d = np.concatenate([LIVOX_HORIZON.rays(T0 + 0.1 * k, T0)[0] for k in range(n)])
        az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
        el = np.degrees(np.arcsin(d[:, 2]))
        assert np.abs(az).max() <= 81.7 / 2 + 1e-6 and np.abs(el).max() <= 25.1 / 2 + 1e-6
        h, _, _ = np.histogram2d(az, el, bins=(327, 100), range=((-40.85, 40.85), (-12.55, 12.55)))
        return float(np.mean(h > 0))

    one, five = coverage(1), coverage(5)
    assert 0.2 < one < five and five > 0.8
    a, _ = LIVOX_HORIZON.rays(T0, T0)
    b, _ = LIVOX_HORIZON.rays(T0 + 0.1, T0)
    assert len(a) == 24_000 and not np.allclose(a, b)


# ---------------------------------------------------------------------------------------------- bad input


def test_bad_input_is_one_clear_error_and_leaves_nothing(tmp_path: Path) -> None:
    good = tiny_map(tmp_path / "good.xodr", 300.0)
    no_lanes = tiny_map(tmp_path / "walk.xodr", 300.0, driving="sidewalk")
    short = tiny_map(tmp_path / "short.xodr", 30.0)
    cases = [
        (no_lanes, SimOptions(), InputError, "no lane of type driving"),
        (good, SimOptions(start_road="7"), InputError, "--start-road 7: no such road"),
        (short, SimOptions(length_m=500.0), InputError, "too short to turn around"),
        (good, SimOptions(length_m=1_000_000.0), InputError, "passes"),
        (tmp_path / "missing.xodr", SimOptions(), InputError, "not found"),
    ]
    for xodr, opts, exc, text in cases:
        with pytest.raises(exc, match=text):
            simulate(xodr, tmp_path / "out", opts)
        assert not (tmp_path / "out").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError):
        simulate(good, tmp_path / "file" / "drive", SimOptions(length_m=50.0))
    keep = tmp_path / "mine"
    keep.mkdir()
    (keep / "thesis.tex").write_text("precious")
    with pytest.raises(OutputError, match="not a drive directory"):
        simulate(good, keep, SimOptions(length_m=50.0))
    assert (keep / "thesis.tex").read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "good.xodr", "mine", "short.xodr", "walk.xodr"]


def test_cli_reports_bad_input_in_one_line(tmp_path: Path) -> None:
    good = tiny_map(tmp_path / "good.xodr", 300.0)
    runner = CliRunner()
    res = runner.invoke(app, ["simulate", str(good), str(tmp_path / "d"), "--start-road", "9"])
    assert res.exit_code == 2
    assert "no such road" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["simulate", str(good), str(tmp_path / "d"), "--traffic", "jam"])
    assert res.exit_code == 2 and "--traffic" in res.output


# ---------------------------------------------------------------------------------------------- shared maps


def test_simple_highway_from_the_shared_maps(shared_data: Path, tmp_path: Path) -> None:
    xodr = shared_data / "maps" / "esmini" / "simple_highway.xodr"
    s = simulate(xodr, tmp_path / "d", SimOptions(length_m=300.0, traffic="low", seed=2))
    assert s.scans > 80 and s.points > 80 * 5000
    d = Drive(tmp_path / "d")
    w, r, _, _ = d.world(len(d.scans) // 2)
    road = OpenDriveMap.load(xodr).roads["0"]
    z_road = road.elevation(np.array([w[:, 0].mean()]))[0]
    ground_bright = (np.abs(w[:, 2] - z_road) < 0.3) & (r > 0.45)
    assert ground_bright.sum() > 50


def test_one_pass_stops_before_the_end_of_the_map(tmp_path: Path) -> None:
    s = simulate(tiny_map(tmp_path / "m.xodr", 150.0), tmp_path / "d", SimOptions(traffic="none"))
    assert s.passes == 1 and s.length_m == pytest.approx(120.0, abs=0.6)
    last = sorted((tmp_path / "d" / "scans").glob("*.pcd"))[-1]
    assert _pcd_points(last) > 3000
