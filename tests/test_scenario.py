"""OpenSCENARIO of the recorded traffic: readers, association, replay accuracy, manoeuvres, ASAM checker."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from lxml import etree
from scenariogeneration import xodr
from typer.testing import CliRunner

from lidar2xodr.cli import app
from lidar2xodr.config import ScenarioConfig
from lidar2xodr.data import Trajectory
from lidar2xodr.errors import InputError
from lidar2xodr.export_scenario import export_scenario, thin_vertices
from lidar2xodr.tracks import associate, load_tracks

LANE_W = 3.5
GRADE = 0.02  # elevation slope of the synthetic map
T = np.round(np.arange(0.0, 12.0, 0.1), 3)
EGO_Y = -LANE_W / 2  # lane -1


def _write_map(path: Path, start: tuple[float, float, float] = (0.0, 0.0, 0.0), length: float = 800.0,
               lanes: int = 2, geo: str | None = None, grade: float = GRADE,
               geometry: xodr.ParamPoly3 | None = None) -> Path:
    road = xodr.create_road(geometry or xodr.Line(length), id=1, left_lanes=0, right_lanes=lanes, lane_width=LANE_W)
    road.planview.set_start_point(*start)
    road.add_elevation(0.0, 0.0, grade, 0.0, 0.0)
    odr = xodr.OpenDrive("test", revMinor="7", geo_reference=geo)
    odr.add_road(road)
    odr.adjust_roads_and_lanes()
    odr.write_xml(str(path))
    return path


@pytest.fixture
def straight_map(tmp_path: Path) -> Path:
    return _write_map(tmp_path / "maps" / "straight.xodr", start=(-100.0, 0.0, 0.0))


def _smoothstep(t: np.ndarray, t0: float, t1: float) -> np.ndarray:
    u = np.clip((t - t0) / (t1 - t0), 0, 1)
    return 0.5 - 0.5 * np.cos(np.pi * u)


def _truth() -> dict[str, dict]:
    """Ego in lane -1 at 25 m/s; car_1 cuts in from lane -2 between 5 s and 8 s 20-40 m ahead; a truck
    keeps lane -2; a van appears at 3 s far ahead in lane -1."""
    ya = -1.5 * LANE_W + LANE_W * _smoothstep(T, 5.0, 8.0)
    t3 = T[T >= 3.0]
    return {
        "ego": {"t": T, "x": 50 + 25 * T, "y": np.full_like(T, EGO_Y)},
        "1": {"t": T, "x": 70 + 27 * T, "y": ya, "cls": "car", "dims": (4.5, 1.8, 1.5)},
        "2": {"t": T, "x": 120 + 22 * T, "y": np.full_like(T, -1.5 * LANE_W), "cls": "truck", "dims": (12.0, 2.5, 3.8)},
        "3": {"t": t3, "x": 200 + 24 * (t3 - 3), "y": np.full_like(t3, EGO_Y), "cls": "van", "dims": (5.2, 2.0, 2.2)},
    }


def _write_drive(folder: Path, truth: dict[str, dict], noise: float = 0.0, seed: int = 0) -> Path:
    """The project's drive layout: poses.csv (ego) and objects.csv (world frame, box centres)."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    ego = truth["ego"]
    with (folder / "poses.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time", "x", "y", "z", "roll", "pitch", "yaw", "lat", "lon", "alt"])
        for t, x, y in zip(ego["t"], ego["x"], ego["y"], strict=True):
            w.writerow([t, x, y, 0.0, 0.0, 0.0, 0.0, 48.0, 9.0, 0.0])
    with (folder / "objects.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time", "id", "class", "x", "y", "z", "yaw", "length", "width", "height", "vx", "vy"])
        for oid, o in truth.items():
            if oid == "ego":
                continue
            yaw = np.arctan2(np.gradient(o["y"], o["t"]), np.gradient(o["x"], o["t"]))
            nx, ny = rng.normal(0, noise, (2, len(o["t"])))
            for k in range(len(o["t"])):
                w.writerow([o["t"][k], oid, o["cls"], o["x"][k] + nx[k], o["y"][k] + ny[k], o["dims"][2] / 2,
                            yaw[k], *o["dims"], "", ""])
    return folder


def _replay(xosc: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Polyline vertices (time, xyz) per entity, read back from the written file."""
    root = etree.parse(str(xosc)).getroot()
    out = {}
    for traj in root.iter("Trajectory"):
        verts = traj.findall("./Shape/Polyline/Vertex")
        t = np.array([float(v.get("time")) for v in verts])
        xyz = np.array([[float(v.find("Position/WorldPosition").get(k)) for k in "xyz"] for v in verts])
        out[traj.get("name").removesuffix("_recorded")] = (t, xyz)
    return out


def _asam_errors(path: Path) -> int:
    check = pytest.importorskip("lidar2xodr.check")
    try:
        result = check.check_file(path)
    except InputError as exc:
        if "environment not found" in exc.problem:
            pytest.skip(f"ASAM checker not installed: {exc}")
        raise
    assert result["asam"]["checkers_completed"] > 0
    return int(result["asam"]["errors"])


def _export(drive: Path, map_path: Path, out: Path, cfg: ScenarioConfig | None = None, **kw):
    tracks = load_tracks(drive, None, cfg=cfg, **kw)
    return tracks, export_scenario(tracks.ego, tracks, map_path, out, cfg)


# --------------------------------------------------------------------------------------------
# the synthetic drive: accuracy, manoeuvres, structure


def test_synthetic_drive_replays_within_tolerance_and_detects_cut_in(tmp_path: Path, straight_map: Path) -> None:
    truth = _truth()
    drive = _write_drive(tmp_path / "drive", truth, noise=0.08)
    out = tmp_path / "out" / "drive.xosc"
    tracks, summary = _export(drive, straight_map, out)
    assert len(tracks.tracks) == 3 and tracks.dropped == 0
    replay = _replay(out)
    assert set(replay) == set(summary.entities)
    for name, tid in summary.entities.items():
        t, xyz = replay[name]
        o = truth[tid]
        sim_t = o["t"] - summary.time_offset_s
        err = np.hypot(np.interp(sim_t, t, xyz[:, 0]) - o["x"], np.interp(sim_t, t, xyz[:, 1]) - o["y"])
        assert err.max() < (0.1 if tid == "ego" else 0.3), (name, err.max())
        # z on the road surface of the map (elevation grade; the map starts at x = -100)
        z_road = GRADE * (np.interp(sim_t, t, xyz[:, 0]) + 100.0)
        assert np.abs(np.interp(sim_t, t, xyz[:, 2]) - z_road).max() < 0.02
        assert len(t) < len(o["t"])  # vertices were thinned
    kinds = [(m.kind, m.actor) for m in summary.manoeuvres]
    assert kinds == [("cut_in", "car_1")]
    cut = summary.manoeuvres[0]
    assert (cut.from_lane, cut.to_lane, cut.direction) == (-2, -1, "left")
    assert 5.0 < cut.time_s < 8.0 and 0 < cut.distance_m <= 50
    assert _asam_errors(out) == 0


def test_late_and_early_entities_are_added_and_removed(tmp_path: Path, straight_map: Path) -> None:
    truth = _truth()
    end = truth["2"]["t"] <= 6.0  # the truck leaves the sensor's view at 6 s
    truth["2"] = {**truth["2"], "t": truth["2"]["t"][end], "x": truth["2"]["x"][end], "y": truth["2"]["y"][end]}
    drive = _write_drive(tmp_path / "drive", truth)
    out = tmp_path / "drive.xosc"
    _, summary = _export(drive, straight_map, out)
    assert summary.late_entities == ["van_3"] and summary.removed_entities == ["truck_2"]
    root = etree.parse(str(out)).getroot()
    init_refs = {p.get("entityRef") for p in root.find("Storyboard/Init/Actions").iter("Private")}
    assert init_refs == {"Ego", "car_1", "truck_2"}
    add = root.find(".//EntityAction[@entityRef='van_3']/AddEntityAction/Position/WorldPosition")
    assert float(add.get("x")) == pytest.approx(200.0, abs=0.05)
    appear = root.find(".//Event[@name='van_3_appear']//SimulationTimeCondition")
    assert float(appear.get("value")) == pytest.approx(3.0)
    assert root.find(".//EntityAction[@entityRef='truck_2']/DeleteEntityAction") is not None
    leave = root.find(".//Event[@name='truck_2_leave']//SimulationTimeCondition")
    assert float(leave.get("value")) == pytest.approx(6.0)
    stop = root.find("Storyboard/StopTrigger//SimulationTimeCondition")
    assert float(stop.get("value")) == pytest.approx(T[-1])
    assert root.find("RoadNetwork/LogicFile").get("filepath") == "maps/straight.xodr"
    timing = root.find(".//FollowTrajectoryAction/TimeReference/Timing")
    assert timing.get("domainAbsoluteRelative") == "absolute"
    assert _asam_errors(out) == 0


def test_output_is_byte_reproducible(tmp_path: Path, straight_map: Path) -> None:
    drive = _write_drive(tmp_path / "drive", _truth(), noise=0.05, seed=3)
    _export(drive, straight_map, tmp_path / "a.xosc")
    _export(drive, straight_map, tmp_path / "b.xosc")
    assert (tmp_path / "a.xosc").read_bytes() == (tmp_path / "b.xosc").read_bytes()


def test_ego_lane_change_and_cut_out(tmp_path: Path, straight_map: Path) -> None:
    truth = _truth()
    ego = truth["ego"]
    ego["y"] = EGO_Y - LANE_W * _smoothstep(T, 7.0, 9.5)  # ego moves right at 7-9.5 s
    # 30 m ahead, leaves the ego lane to the right at 2-4.5 s
    lead = {"t": T, "x": 80 + 25 * T, "y": EGO_Y - LANE_W * _smoothstep(T, 2.0, 4.5), "cls": "car",
            "dims": (4.5, 1.8, 1.5)}
    truth = {"ego": ego, "9": lead}
    drive = _write_drive(tmp_path / "drive", truth)
    _, summary = _export(drive, straight_map, tmp_path / "x.xosc")
    got = [(m.kind, m.actor, m.from_lane, m.to_lane, m.direction) for m in summary.manoeuvres]
    assert got == [("cut_out", "car_9", -1, -2, "right"), ("ego_lane_change", "Ego", -1, -2, "right")]


def test_thin_vertices_bounds_replay_error() -> None:
    t = np.linspace(0, 10, 201)
    xyz = np.stack([20 * t, 3 * np.sin(t), np.zeros_like(t)], axis=1)
    yaw = np.arctan2(3 * np.cos(t), 20)
    keep = thin_vertices(t, xyz, yaw, 0.05, 0.02)
    assert 2 < len(keep) < 100 and keep[0] == 0 and keep[-1] == 200
    rep = np.stack([np.interp(t, t[keep], xyz[keep, k]) for k in range(3)], axis=1)
    assert np.linalg.norm(rep - xyz, axis=1).max() <= 0.05 + 1e-12
    assert np.abs(np.interp(t, t[keep], yaw[keep]) - yaw).max() <= 0.02 + 1e-12


# --------------------------------------------------------------------------------------------
# detections without ids, vehicle frame, bad input


def test_association_of_vehicle_frame_detections_without_ids(tmp_path: Path, straight_map: Path) -> None:
    """Two cars 3.5 m apart (adjacent lanes) passing the ego, shuffled rows, noise and one spike."""
    rng = np.random.default_rng(1)
    t = np.round(np.arange(0, 6, 0.1), 3)
    ego = Trajectory(times=t, poses=np.tile(np.eye(4), (len(t), 1, 1)))
    ego.poses[:, 0, 3] = 30 * t
    ego.poses[:, 1, 3] = EGO_Y
    cars = {"A": (10 + 2 * t, np.zeros_like(t)), "B": (-20 + 4 * t, np.full_like(t, -LANE_W))}
    rows = []
    for name, (x, y) in cars.items():
        for k in range(len(t)):
            rows.append({"time": float(t[k]), "x": float(x[k] + rng.normal(0, 0.05)),
                         "y": float(y[k] + rng.normal(0, 0.05)), "class": "car", "truth": name})
    rows[17]["x"] += 6.0  # a spike on car A
    order = rng.permutation(len(rows))
    det = [{k: v for k, v in rows[i].items() if k != "truth"} for i in order]
    path = tmp_path / "dets.json"
    path.write_text(json.dumps({"frame": "vehicle", "detections": det}))
    ts = load_tracks(path, ego)
    assert len(ts.tracks) == 2
    assert ts.counts["dropped_short"] == 1  # the spike is outside every gate: a 1-sample track, dropped
    assert ts.counts["associated_detections"] == len(rows)
    for tr in ts.tracks:
        # each track is one car: world y constant within noise, x follows that car
        start_x = tr.xyz[0, 0] - 30 * tr.times[0]
        name = "A" if abs(start_x - 10) < 2 else "B"
        x, y = cars[name]
        assert np.abs(tr.xyz[:, 0] - (30 * tr.times + np.interp(tr.times, t, x))).max() < 0.3
        assert np.abs(tr.xyz[:, 1] - (EGO_Y + np.interp(tr.times, t, y))).max() < 0.3
    summary = export_scenario(ego, ts, straight_map, tmp_path / "a.xosc")
    assert len(summary.entities) == 3


def test_associate_keeps_crossing_free_tracks_apart() -> None:
    t = np.repeat(np.arange(10) * 0.1, 2)
    xy = np.stack([np.where(np.arange(20) % 2, 0.0, 3.5) + 0 * t, 25 * t], axis=1)
    labels = associate(t, xy, gate_m=3.0, max_gap_s=1.0, init_vel=np.tile([0.0, 25.0], (20, 1)))
    assert len(set(labels[::2])) == 1 and len(set(labels[1::2])) == 1 and labels[0] != labels[1]


def test_bad_input_is_counted_and_the_file_stays_valid(tmp_path: Path, straight_map: Path) -> None:
    truth = _truth()
    drive = _write_drive(tmp_path / "drive", truth)
    with (drive / "objects.csv").open() as fh:
        lines = fh.read().splitlines()
    header, body = lines[0], lines[1:]
    body[10], body[11] = body[11], body[10]  # out of order
    body = [line.replace(",4.5,1.8,1.5,", ",0,0,0,") for line in body]  # zero size for car 1
    body = [line.replace(",van,", ",hovercraft,") for line in body]  # unknown class
    body += [f"{t:.1f},77,car,{1000 + 25 * t},400,0.75,0,4.5,1.8,1.5,," for t in T]  # far off the map
    body += [f"{t:.1f},88,car,{90 + 25 * t},-1.75,0.75,0,4.5,1.8,1.5,," for t in T[:3]]  # too short
    spike = body[40].split(",")
    body[40] = ",".join([*spike[:3], str(float(spike[3]) + 5.0), *spike[4:]])  # one jump of 5 m
    (drive / "objects.csv").write_text("\n".join([header, *body]) + "\n")
    out = tmp_path / "bad.xosc"
    tracks, summary = _export(drive, straight_map, out)
    assert tracks.counts["out_of_order"] == 1
    assert tracks.counts["zero_size_tracks"] == 1 and tracks.counts["dropped_short"] == 1
    assert tracks.counts["spikes_removed"] == 1
    assert tracks.counts["unknown_class_samples"] == len(truth["3"]["t"])
    assert summary.counts["off_map_tracks"] == 1 and summary.counts["off_map_samples"] == len(T)
    text = " | ".join(summary.warnings)
    for word in ("out of time order", "zero or missing size", "too short", "'hovercraft'", "outside the map", "spike"):
        assert word in text
    cars = {t.id: t for t in tracks.tracks}
    assert cars["1"].dims.tolist() == [4.6, 1.9, 1.5] and cars["3"].category == "car"
    assert _asam_errors(out) == 0


@pytest.mark.parametrize(
    ("name", "content", "problem"),
    [
        ("empty.csv", "time,id,x,y\n", "no detections"),
        ("nox.csv", "time,id,y\n0,1,2\n", "missing column(s) x"),
        ("text.csv", "time,id,x,y\n0,1,abc,2\n", "row 2: column x: 'abc' is not a number"),
        ("bad.json", "{not json", "cannot read JSON"),
        ("frame.csv", "time,x,y,frame\n0,1,2,moon\n", "unknown frame 'moon'"),
        ("veh.csv", "time,x,y,frame\n0,1,2,vehicle\n", "no ego trajectory"),
    ],
)
def test_unreadable_input_raises_input_error(tmp_path: Path, name: str, content: str, problem: str) -> None:
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputError) as exc:
        load_tracks(path, None)
    assert problem in exc.value.problem and exc.value.where == str(path)


def test_cli_scenario_command(tmp_path: Path, straight_map: Path) -> None:
    drive = _write_drive(tmp_path / "drive", _truth())
    out, js = tmp_path / "cli.xosc", tmp_path / "cli.json"
    runner = CliRunner()
    res = runner.invoke(app, ["scenario", str(drive), "--map", str(straight_map), "-o", str(out), "--json", str(js)])
    assert res.exit_code == 0, res.output
    assert out.is_file() and "cut_in" in res.output
    assert json.loads(js.read_text())["manoeuvres"][0]["kind"] == "cut_in"
    res = runner.invoke(app, ["scenario", str(tmp_path / "none"), "--map", str(straight_map), "-o", str(out)])
    assert res.exit_code == 2 and "not found" in res.output


# --------------------------------------------------------------------------------------------
# real recordings (third-party data)


def _aimotive_ego(folder: Path, speed: float) -> Trajectory:
    """Constant-velocity ego along x (the sample has no poses; ~25 m/s on this motorway)."""
    stamps = sorted(float(json.loads(f.read_text())["Timestamp"]) * 1e-9 for f in folder.glob("frame_*.json"))
    t = np.array(stamps)
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, 0, 3] = speed * (t - t[0])
    return Trajectory(times=t, poses=poses)


def test_aimotive_boxes(tmp_path: Path, shared_data: Path) -> None:
    drive = shared_data / "lidar" / "aimotive_highway_sample"
    ego = _aimotive_ego(drive / "dynamic" / "box" / "3d_body", 25.0)
    ts = load_tracks(drive, ego)
    cats = {t.id: t.category for t in ts.tracks}
    assert cats == {"0": "car", "1": "van", "2": "car", "3": "van", "4": "car", "5": "truck", "6": "car", "7": "car"}
    truck = next(t for t in ts.tracks if t.id == "5")
    assert truck.dims[0] == pytest.approx(16.7, abs=0.2)
    # two through lanes plus the exit lane; the ego drives in the left lane (y = 0)
    map_path = _write_map(tmp_path / "hu.xodr", start=(-200.0, LANE_W / 2, 0.0), length=600.0, lanes=3, grade=0.0)
    out = tmp_path / "aimotive.xosc"
    summary = export_scenario(ego, ts, map_path, out)
    assert "truck_5" in summary.removed_entities  # leaves the view before the end
    assert summary.counts["off_map_tracks"] == 0
    assert _asam_errors(out) == 0


def test_a9_drive(tmp_path: Path, shared_data: Path) -> None:
    csv_path = shared_data / "scenarios" / "a9" / "trajectories_file.csv"
    local = load_tracks(csv_path, None)
    assert local.ego is not None and local.origin is not None and local.origin.proj
    assert any("differs from the GNSS course" in w for w in local.warnings)
    # a 3-lane carriageway along the ego path, with the ego in the middle lane, in the tracks' frame
    p, yaw = local.ego.positions[:, :2], np.arctan2(local.ego.poses[:, 1, 0], local.ego.poses[:, 0, 0])
    left = p + 1.5 * LANE_W * np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
    h0 = float(yaw[0])
    rel = (left - left[0]) @ np.array([[math.cos(h0), -math.sin(h0)], [math.sin(h0), math.cos(h0)]])
    u = np.linspace(0, 1, len(rel))
    cu, cv = np.polyfit(u, rel[:, 0], 3)[::-1], np.polyfit(u, rel[:, 1], 3)[::-1]
    pp = np.linspace(0, 1, 2001)
    length = float(np.sum(np.hypot(np.diff(np.polyval(cu[::-1], pp)), np.diff(np.polyval(cv[::-1], pp)))))
    geom = xodr.ParamPoly3(*cu, *cv, prange="normalized", length=length)
    map_path = _write_map(tmp_path / "a9.xodr", start=(float(left[0, 0]), float(left[0, 1]), h0), lanes=3,
                          geo=local.origin.proj, grade=0.0, geometry=geom)
    ts = load_tracks(csv_path, None, geo_reference=local.origin.proj)
    assert np.allclose(ts.ego.positions, local.ego.positions)
    assert {t.id for t in ts.tracks} == {"1", "3", "5", "6", "7"}
    assert ts.counts["dropped_short"] >= 2  # slots 2 and 4 hold 1 and 4 samples
    lead = next(t for t in ts.tracks if t.id == "1")
    assert 22 < float(np.median(lead.speed)) < 40  # ~100-140 km/h on the motorway
    out = tmp_path / "a9.xosc"
    summary = export_scenario(ts.ego, ts, map_path, out)
    assert summary.counts["ego_off_map_samples"] == 0
    assert summary.duration_s == pytest.approx(10.2)
    assert _asam_errors(out) == 0


def test_border_hugging_vehicle_makes_no_lane_change(tmp_path: Path, straight_map: Path) -> None:
    """A car driving on the lane line with 0.2 m lateral jitter flickers between lanes: hysteresis."""
    truth = _truth()
    rng = np.random.default_rng(5)
    truth = {"ego": truth["ego"], "4": {"t": T, "x": 150 + 25 * T, "y": -LANE_W + rng.normal(0, 0.2, len(T)),
                                       "cls": "car", "dims": (4.5, 1.8, 1.5)}}
    drive = _write_drive(tmp_path / "drive", truth)
    _, summary = _export(drive, straight_map, tmp_path / "x.xosc")
    assert summary.manoeuvres == []


def test_frames_json_categories_and_osc_1_3(tmp_path: Path, straight_map: Path) -> None:
    t = np.round(np.arange(0, 4, 0.1), 3)
    kinds = {"p1": ("person", -8.0, 1.4), "m1": ("motorcycle", -1.75, 30.0), "b1": ("cyclist", -5.25, 6.0),
             "x1": ("ufo", -5.25, 20.0)}
    frames = [{"time": float(tk), "objects": [
        {"track_id": k, "type": c, "x": 60 + v * tk, "y": y, "z": 0.0, "l": 0, "w": 0, "h": 0}
        for k, (c, y, v) in kinds.items()]} for tk in t]
    path = tmp_path / "frames.json"
    path.write_text(json.dumps({"frame": "world", "frames": frames}))
    ego = Trajectory(times=t, poses=np.tile(np.eye(4), (len(t), 1, 1)))
    ego.poses[:, 0, 3], ego.poses[:, 1, 3] = 25 * t, EGO_Y
    cfg = ScenarioConfig(osc_minor_version=3)
    ts = load_tracks(path, ego, cfg=cfg)
    assert {tr.id: tr.category for tr in ts.tracks} == {"p1": "pedestrian", "m1": "motorbike", "b1": "bicycle",
                                                         "x1": "car"}
    assert ts.counts["zero_size_tracks"] == 4 and ts.counts["unknown_class_samples"] == len(t)
    out = tmp_path / "cats.xosc"
    export_scenario(ego, ts, straight_map, out, cfg)
    root = etree.parse(str(out)).getroot()
    assert root.find("FileHeader").get("revMinor") == "3"
    assert root.find(".//ScenarioObject[@name='pedestrian_p1']/Pedestrian") is not None
    assert root.find(".//ScenarioObject[@name='motorbike_m1']/Vehicle").get("vehicleCategory") == "motorbike"
    assert _asam_errors(out) == 0


def test_ego_from_trajectory_csv_and_clock_mismatch(tmp_path: Path, straight_map: Path) -> None:
    """Vehicle-frame detections placed with the extraction's quaternion trajectory (CLI --ego)."""
    t = np.round(np.arange(100.0, 104.0, 0.1), 3)
    yaw = 0.05
    traj = tmp_path / "markings.trajectory.csv"
    qz, qw = math.sin(yaw / 2), math.cos(yaw / 2)
    traj.write_text("time,x,y,z,qx,qy,qz,qw\n" + "".join(
        f"{tk},{25 * (tk - 100) * math.cos(yaw)},{EGO_Y + 25 * (tk - 100) * math.sin(yaw)},0,0,0,{qz},{qw}\n"
        for tk in t))
    dets = tmp_path / "dets.csv"
    dets.write_text("time,id,class,x,y,frame\n" + "".join(f"{tk},7,car,20,0,vehicle\n" for tk in t))
    out = tmp_path / "ego.xosc"
    res = CliRunner().invoke(app, ["scenario", str(dets), "--map", str(straight_map), "-o", str(out),
                                   "--ego", str(traj)])
    assert res.exit_code == 0, res.output
    t_rep, xyz = _replay(out)["car_7"]
    # 20 m ahead of the ego along its heading
    assert xyz[0, 0] == pytest.approx(20 * math.cos(yaw), abs=0.01)
    assert xyz[0, 1] == pytest.approx(EGO_Y + 20 * math.sin(yaw), abs=0.01)
    late = tmp_path / "late.csv"
    late.write_text("time,id,x,y,frame\n" + "".join(f"{tk + 1000},7,20,0,vehicle\n" for tk in t))
    res = CliRunner().invoke(app, ["scenario", str(late), "--map", str(straight_map), "-o", str(out),
                                   "--ego", str(traj)])
    assert res.exit_code == 2 and "share a clock" in res.output


@pytest.mark.parametrize("name", ["asam/Ex_Line-Spiral-Arc_elevation_and_superelevation.xodr",
                                  "esmini/straight_500_superelevation_elevation_curve.xodr"])
def test_map_index_on_curved_superelevated_roads(shared_data: Path, name: str) -> None:
    """Lane and surface height of lane centres computed by the OpenDRIVE reader are found again."""
    from lidar2xodr.export_scenario import MapIndex
    from lidar2xodr.opendrive import OpenDriveMap

    odr = OpenDriveMap.load(shared_data / "maps" / name)
    index = MapIndex(odr, 0.5, 0.5)
    rng = np.random.default_rng(2)
    checked = 0
    for road in odr.roads.values():
        s = np.sort(rng.uniform(0.5, road.length - 0.5, 60))
        sec = road.section_index(s)
        for lid in {i for ls in road.lane_sections for i in ls.lanes if i != 0}:
            inner = road.border_t(s, lid - 1 if lid > 0 else lid + 1) if abs(lid) > 1 else road.border_t(s, 0)
            outer = road.border_t(s, lid)
            ok = np.isfinite(inner) & np.isfinite(outer) & (np.abs(outer - inner) > 1.0)
            ok &= np.array([lid in road.lane_sections[k].lanes for k in sec])
            if not ok.any():
                continue
            p = road.to_world(s[ok], 0.5 * (inner[ok] + outer[ok]))
            got = index.locate(p[:, :2])
            assert got.on_map.all()
            same_road = got.road_id == road.id
            assert same_road.mean() > 0.9
            assert (got.lane_id[same_road] == lid).all(), (road.id, lid)
            assert np.abs(got.z[same_road] - p[same_road, 2]).max() < 0.03
            checked += int(same_road.sum())
    assert checked > 100


def test_tracks_smoothed_on_worker_processes_are_the_same_bytes() -> None:
    """The GCV smoothing of every track runs on a process pool when there are enough tracks: each
    track alone, taken back in order, so one worker or two give the same arrays."""
    from lidar2xodr.tracks import _PARALLEL_TRACKS, _smooth_all

    rng = np.random.default_rng(4)
    items = []
    for k in range(_PARALLEL_TRACKS + 2):
        t = np.sort(rng.uniform(0.0, 10.0, 60 + k))
        xyz = np.stack([25.0 * t, 0.3 * np.sin(t), np.full(len(t), np.nan if k == 1 else 0.5)], axis=1)
        items.append((t, xyz + rng.normal(0.0, 0.05, xyz.shape)))
    serial = _smooth_all(items, 1)
    pooled = _smooth_all(items, 2)
    assert len(pooled) == len(items)
    for (s_xyz, s_vel), (p_xyz, p_vel) in zip(serial, pooled, strict=True):
        assert s_xyz.tobytes() == p_xyz.tobytes() and s_vel.tobytes() == p_vel.tobytes()
    assert not np.allclose(serial[0][0][:, 0], items[0][1][:, 0]), "the tracks were smoothed"


def test_the_tracks_are_smoothed_on_as_many_processes_as_asked(tmp_path: Path, monkeypatch) -> None:
    """`load_tracks(workers=...)` overrides the configuration's count (the build smooths the tracks
    beside its lanes stage on the cores that stage leaves); the tracks are the same either way."""
    import lidar2xodr.tracks as tracks_mod
    from lidar2xodr.config import Config

    drive = _write_drive(tmp_path / "d", _truth(), noise=0.05, seed=3)
    cfg = Config.model_validate({"extraction": {"workers": 2}})
    asked: list[int] = []
    smooth_all = tracks_mod._smooth_all

    def counted(items: list, workers: int) -> list:
        asked.append(workers)
        return smooth_all(items, workers)

    monkeypatch.setattr(tracks_mod, "_smooth_all", counted)
    default = load_tracks(drive, None, cfg=cfg)
    one = load_tracks(drive, None, cfg=cfg, workers=1)
    assert asked == [2, 1]
    assert [t.xyz.tobytes() for t in default.tracks] == [t.xyz.tobytes() for t in one.tracks]
