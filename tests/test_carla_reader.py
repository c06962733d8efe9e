"""CARLA's own OpenDRIVE parser as a reader of `check`: loads, waypoints, a walk along every lane, topology."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.quality.carla_reader import map_road_pairs, run_carla
from lidar2xodr.quality.readers import run_in_subprocess

pytest.importorskip("carla", reason="CARLA's Python package (PyPI carla) not installed")

HEADER = '<?xml version="1.0"?><OpenDRIVE><header revMajor="1" revMinor="8" name="t" version="1" date="2024-01-01"/>'
SUCC = '<link><successor elementType="road" elementId="2" contactPoint="start"/></link>'
PRED = '<link><predecessor elementType="road" elementId="1" contactPoint="end"/></link>'


def _road(rid: int, x0: float, link: str, lane_link: str) -> str:
    return (f'<road id="{rid}" length="100" junction="-1" rule="RHT">{link}<planView><geometry s="0" x="{x0}" y="0" '
            'hdg="0" length="100"><line/></geometry></planView><lanes><laneSection s="0"><center><lane id="0" '
            f'type="none"/></center><right><lane id="-1" type="driving">{lane_link}<width sOffset="0" a="3.5" b="0" '
            'c="0" d="0"/></lane></right></laneSection></lanes></road>')


def _two_roads(tmp_path: Path, name: str, succ: str = SUCC, x2: float = 100.0, to_lane: int = -1) -> Path:
    """Road 1 then road 2 (100 m each), linked both ways, lane -1 into lane -1."""
    text = (HEADER + _road(1, 0.0, succ, f'<link><successor id="{to_lane}"/></link>')
            + _road(2, x2, PRED, f'<link><predecessor id="{to_lane}"/></link>') + "</OpenDRIVE>")
    path = tmp_path / f"{name}.xodr"
    path.write_text(text)
    return path


def _carla(path: Path) -> dict:
    return run_carla(path, OpenDriveMap.load(path))


def test_linked_roads_pass(tmp_path: Path) -> None:
    res = _carla(_two_roads(tmp_path, "good"))
    assert res["ok"] and res["loads"], res
    assert res["driving_lanes"] == res["lanes_walked"] == 2 and res["road_pairs"] == 1
    assert res["road_pairs_missing"] == res["road_pairs_extra"] == 0
    assert res["max_centre_dev_m"] < 1e-6  # CARLA's mirrored y taken into account: lane -1 lies at y = -1.75


def test_a_successor_naming_a_missing_road_breaks_the_walk_and_the_topology(tmp_path: Path) -> None:
    res = _carla(_two_roads(tmp_path, "broken", succ=SUCC.replace('"2"', '"9"')))
    assert not res["ok"] and res["road_pairs_missing"] == 1
    assert "road 1 lane -1: no waypoint beyond s=100.00, where the map links the lane on" in res["errors"]
    assert "roads 1 and 2: the map links their driving lanes, CARLA's topology does not join them" in res["errors"]


def test_a_link_across_a_gap_is_a_jump(tmp_path: Path) -> None:
    res = _carla(_two_roads(tmp_path, "gap", x2=150.0))
    assert not res["ok"]
    [msg] = res["errors"]
    assert msg.startswith("road 1 lane -1: wp.next() jumps 51.00 m at s=100.00"), msg


def test_a_crash_of_the_parser_is_its_finding_not_ours(tmp_path: Path) -> None:
    """CARLA 0.9.16 segfaults on a lane link to a lane that does not exist: run in a child, it is reported."""
    path = _two_roads(tmp_path, "crash", to_lane=-3)
    res = run_in_subprocess("carla", path)
    assert res["available"] and not res["ok"] and res["version"] == "0.9.16"
    assert res["errors"] and res["errors"][0].startswith("CARLA crashed on the map (signal"), res["errors"]


def test_map_pairs_follow_driving_lanes_only(tmp_path: Path) -> None:
    path = _two_roads(tmp_path, "pairs")
    assert map_road_pairs(OpenDriveMap.load(path)) == {frozenset(("1", "2"))}
    shoulder = tmp_path / "shoulder.xodr"
    shoulder.write_text(path.read_text().replace('type="driving"', 'type="shoulder"'))
    assert map_road_pairs(OpenDriveMap.load(shoulder)) == set()


def test_absent_carla_is_a_note(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "carla", None)
    res = run_carla(_two_roads(tmp_path, "absent"), None)
    assert res == {"available": False, "note": res["note"]} and "carla" in res["note"]


def test_left_hand_traffic_walks_the_left_lanes_along_s(tmp_path: Path) -> None:
    """rule="LHT": lane 1 drives along the reference line, so its walk starts at s = 0 and goes on into road 2."""
    path = _two_roads(tmp_path, "lht", to_lane=1)
    text = path.read_text().replace('rule="RHT"', 'rule="LHT"').replace('<right><lane id="-1"', '<left><lane id="1"')
    path.write_text(text.replace("</lane></right>", "</lane></left>"))
    res = _carla(path)
    assert res["ok"] and res["lanes_walked"] == res["driving_lanes"] == 2 and res["road_pairs"] == 1, res
    broken = tmp_path / "lht_broken.xodr"
    broken.write_text(path.read_text().replace('elementId="2" contactPoint="start"', 'elementId="9"'))
    assert "road 1 lane 1: no waypoint beyond s=100.00, where the map links the lane on" in _carla(broken)["errors"]
