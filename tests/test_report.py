"""The build report: its verdict on small hand-written maps, and the page as headless Chromium draws it."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from lidar2xodr.data import Boundary, GroundPlanes, LaneModel, LaneSection, MarkingCloud, Trajectory
from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.report import write_report
from lidar2xodr.report.verdict import ABSENT, FAIL, PASS, WARN, make_verdict, problems

LANE = 3.5
TAPER_M = 100.0  # the entry lane opens from 0 to LANE over this length


def _lane(lid: int, kind: str, a: float, b: float, mark: str, link: str = "") -> str:
    return (f'<lane id="{lid}" type="{kind}" level="false">{link}<width sOffset="0" a="{a}" b="{b}" c="0" d="0"/>'
            f'<roadMark sOffset="0" type="{mark}" weight="standard" color="white" width="0.15"/></lane>')


def _road(rid: str, x0: float, length: float, sections: str, junction: str = "-1", link: str = "") -> str:
    return (f'<road id="{rid}" name="" length="{length}" junction="{junction}" rule="RHT"><link>{link}</link>'
            f'<planView><geometry s="0" x="{x0}" y="0" hdg="0" length="{length}"><line/></geometry></planView>'
            f"<lanes>{sections}</lanes></road>")


def _section(s: float, lanes: str) -> str:
    centre = '<center><lane id="0" type="none" level="false"><roadMark sOffset="0" type="solid" ' \
             'weight="standard" color="white" width="0.15"/></lane></center>'
    return f'<laneSection s="{s}">{centre}<right>{lanes}</right></laneSection>'


def _two_lanes() -> str:
    return _lane(-1, "driving", LANE, 0, "broken") + _lane(-2, "driving", LANE, 0, "solid")


def _xodr(roads: str, junctions: str = "") -> str:
    return ('<?xml version="1.0" encoding="UTF-8"?><OpenDRIVE><header revMajor="1" revMinor="8" name="t" '
            f'date="2026-01-01T00:00:00"/>{roads}{junctions}</OpenDRIVE>')


def entry_map(path: Path) -> Path:
    """One 600 m road: 2 lanes, then from s 300 m an entry lane opening over TAPER_M."""
    sec1 = _lane(-1, "driving", LANE, 0, "broken") + _lane(-2, "driving", LANE, 0, "broken") + \
        _lane(-3, "entry", 0.0, LANE / TAPER_M, "solid")
    path.write_text(_xodr(_road("1", 0.0, 600.0, _section(0.0, _two_lanes()) + _section(300.0, sec1))))
    return path


def junction_map(path: Path) -> Path:
    """Road 1 (300 m) -> classic junction 10 (connecting road 11, 20 m) -> road 2 (300 m), two lanes throughout."""
    connecting = "".join(_lane(lid, "driving", LANE, 0, mark, f'<link><predecessor id="{lid}"/><successor '
                                 f'id="{lid}"/></link>') for lid, mark in ((-1, "broken"), (-2, "solid")))
    roads = (_road("1", 0.0, 300.0, _section(0.0, _two_lanes()), link='<successor elementType="junction" '
                   'elementId="10"/>')
             + _road("11", 300.0, 20.0, _section(0.0, connecting), junction="10",
                     link='<predecessor elementType="road" elementId="1" contactPoint="end"/><successor '
                          'elementType="road" elementId="2" contactPoint="start"/>')
             + _road("2", 320.0, 300.0, _section(0.0, _two_lanes()), link='<predecessor elementType="junction" '
                     'elementId="10"/>'))
    junction = ('<junction id="10" name=""><connection id="0" incomingRoad="1" connectingRoad="11" '
                'contactPoint="start"><laneLink from="-1" to="-1"/><laneLink from="-2" to="-2"/></connection>'
                "</junction>")
    path.write_text(_xodr(roads, junction))
    return path


def _reader(name: str, ok: bool, errors: list[str] | None = None) -> dict:
    return {"available": True, "reader": name, "version": f"Eclipse {name} 1.28.0", "ok": ok, "errors": errors or [],
            "warnings": []}


def _check(ok: bool = True, sumo_errors: list[str] | None = None) -> dict:
    return {
        "file": "/somewhere/.lidar2xodr-abc123/map.xodr", "ok": ok, "reasons": [] if ok else ["1 ASAM error(s)"],
        "asam": {"errors": 0 if ok else 1, "warnings": 0, "checkers_failed": 0, "checkers_skipped_for_version": 0,
                 "issues": [] if ok else [{"level": "error", "rule": "r", "message": "lane width negative"}]},
        "continuity": {"max_leap_m": 0.0, "max_kink_rad": 0.0, "leap_limit_m": 0.001, "kink_limit_rad": 0.001,
                       "max_junction_gap_m": 0.0},
        "readers": {
            "netconvert": _reader("SUMO netconvert", not sumo_errors, sumo_errors),
            "pyxodr": _reader("pyxodr", True),
            "carla": {"available": False, "note": "carla not installed: not checked"},
        },
    }


METRICS = {
    "boundaries": {"rmse_m": 0.0731, "p95_m": 0.12, "max_m": 0.2, "mean_m": 0.06, "std_m": 0.04, "eval_length_m": 9.0},
    "centerline": {"rmse_m": 0.0754, "p95_m": 0.13, "max_m": 0.18, "mean_m": 0.06, "std_m": 0.04, "eval_length_m": 3.0},
    "lane_count_agreement": 0.9998, "coverage": 1.0, "lane_width": {"bias_m": -0.002, "std_m": 0.01, "pairs": 9},
    "lane_graph": {"agreement": 0.75, "breaks": 1, "wrong_m": 150.0,
                   "breaks_at": [{"x": 350.0, "y": -5.0, "reference_road": "1", "reference_lane": -3}]},
}


def test_the_verdict_says_what_was_built_lane_by_lane(tmp_path: Path) -> None:
    odr = OpenDriveMap.load(entry_map(tmp_path / "entry.xodr"))
    v = make_verdict("out/map.xodr", odr, _check(), None, [], min_width=1.75, step=2.0)
    assert v.built_line() == "0.60 km of road: 1 road, no junction"
    assert [(st.right, st.kinds) for st in v.stretches] == [(2, ()), (3, ("entry",))]
    opens = 300.0 + TAPER_M * 1.75 / LANE  # the entry lane counts once it is half a lane wide
    assert abs(v.stretches[0].s1 - opens) <= 2.0 and v.stretches[1].s1 == 600.0
    assert v.lanes_lines() == [f"0-{v.stretches[0].s1:.0f} m: 2 lanes, {v.stretches[0].s1:.0f}-600 m: 3 lanes (entry)"]
    assert v.junctions == []


def test_the_verdict_names_the_junction_and_its_roads(tmp_path: Path) -> None:
    odr = OpenDriveMap.load(junction_map(tmp_path / "junction.xodr"))
    v = make_verdict("j.xodr", odr, _check(), None, [], min_width=1.75, step=2.0)
    assert v.roads == ["1", "2"] and v.built_line() == "0.62 km of road: 2 roads, 1 junction"
    (j,) = v.junctions
    assert (j.id, j.roads, j.connecting) == ("10", ["1", "2"], 1)
    assert abs(j.xy[0] - 310.0) < 1.0 and abs(j.xy[1]) < 1e-6


def test_a_failed_or_missing_reader_is_never_shown_as_passed(tmp_path: Path) -> None:
    odr = OpenDriveMap.load(entry_map(tmp_path / "entry.xodr"))
    v = make_verdict("m.xodr", odr, _check(sumo_errors=["Error: No edges loaded."]), None, [], 1.75, 2.0)
    status = {c.name.split(" ")[0]: c.status for c in v.checks}
    assert status == {"ASAM": PASS, "continuity": PASS, "SUMO": FAIL, "pyxodr": PASS, "carla": ABSENT}
    assert v.status == WARN, "the map passes its checks, but a reader failed"
    assert [p.text for p in v.problems] == ["SUMO netconvert 1.28.0 failed to read the map: Error: No edges loaded."]
    assert "SUMO netconvert 1.28.0 FAILED" in v.headline() and "carla not available" in v.headline()
    failed = make_verdict("m.xodr", odr, _check(ok=False), None, [], 1.75, 2.0)
    assert failed.status == FAIL and failed.problems[0].text == "the map fails its checks: 1 ASAM error(s)"
    assert make_verdict("m.xodr", odr, _check(), None, [], 1.75, 2.0).status == PASS
    assert make_verdict("m.xodr", odr, {}, None, [], 1.75, 2.0).status == ABSENT, "not checked is not passed"


def test_a_lane_of_a_width_no_lane_has_is_a_problem_of_the_map(tmp_path: Path) -> None:
    """`check` warns about zero-width, narrow and wide lanes; the verdict lists them and is not a pass."""
    odr = OpenDriveMap.load(entry_map(tmp_path / "entry.xodr"))
    wide = "road 1 lane -2: wider than 5.0 m over 87.0 m (s 12.0-99.0, up to 7.00 m): two lanes as one, or a border"
    check = {**_check(), "lane_widths": {"negative": [], "zero_width": [], "narrow": [], "wide": [{}],
                                          "warnings": [wide]}}
    v = make_verdict("m.xodr", odr, check, None, [], 1.75, 2.0)
    assert [p.text for p in v.problems] == [f"map: {wide}"]
    assert v.status == WARN


def test_metrics_come_most_telling_first_with_the_lane_graph(tmp_path: Path) -> None:
    odr = OpenDriveMap.load(entry_map(tmp_path / "entry.xodr"))
    rows = dict(make_verdict("m.xodr", odr, _check(), METRICS, [], 1.75, 2.0).metrics)
    assert rows["boundaries RMSE"].startswith("0.073 m") and rows["centre line RMSE"].startswith("0.075 m")
    assert rows["lane count agreement"] == "100.0 %"
    assert rows["lane graph agreement"] == "75.0 % (1 break, 150 m wrong)"
    (brk,) = make_verdict("m.xodr", odr, _check(), METRICS, [], 1.75, 2.0).problems
    assert brk.points == [(350.0, -5.0)] and "reference road 1 lane -3" in brk.text


def test_warnings_keep_the_stretches_of_road_they_name() -> None:
    found = problems(["boundary 0 ignored on s 0-315, 457-977 m: off the carriageway",
                      "lane count changes along the road: 3 from s 0 m, 4 from s 1588 m",
                      "a warning without a place", "a warning without a place"])
    assert [p.stretches for p in found] == [[(0.0, 315.0), (457.0, 977.0)], [(0.0, 0.0), (1588.0, 1588.0)], []]


def _model_and_cloud(length: float = 600.0) -> tuple[LaneModel, MarkingCloud]:
    """A lane model along x and a marking cloud on its three lines (dashes on the middle one)."""
    s = np.arange(0.0, length + 1e-9, 1.0)
    ref = np.column_stack([s, np.full_like(s, -LANE), np.zeros_like(s)])
    model = LaneModel(s=s, reference=ref, boundaries=[Boundary(i, np.full(len(s), LANE * (1 - i))) for i in range(3)],
                      sections=[LaneSection(0.0, length, [0, 1, 2])], warnings=["a warning on s 100-200 m"])
    x = np.arange(0.0, length, 0.1)
    lines = [np.column_stack([x, np.full_like(x, y), np.zeros_like(x)]) for y in (0.0, -LANE, -2 * LANE)]
    lines[1] = lines[1][(lines[1][:, 0] % 12.0) < 3.0]
    xyz = np.concatenate(lines)
    times = np.linspace(0.0, 30.0, 31)
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    poses[:, 0, 3] = times * 20.0
    poses[:, 1, 3] = -1.5 * LANE
    planes = GroundPlanes(times=times, normals_world=np.tile([0.0, 0.0, 1.0], (len(times), 1)),
                          points_world=poses[:, :3, 3].copy())
    cloud = MarkingCloud(xyz=xyz, intensity=np.ones(len(xyz), np.float32), scan_index=np.zeros(len(xyz), np.int32),
                         time=np.zeros(len(xyz)), planes=planes, trajectory=Trajectory(times, poses))
    return model, cloud


def _write(tmp_path: Path, name: str, map_path: Path, **kwargs: object) -> Path:
    model, cloud = _model_and_cloud()
    summary = {"length_m": 600.0, "metrics": METRICS}
    return write_report(tmp_path / name, cloud, model, map_path, _check(sumo_errors=["Error: No edges loaded."]),
                        {"extract": 1.0}, summary, metrics=METRICS, **kwargs)


def test_the_page_names_the_users_map_shows_each_number_once_and_is_reproducible(tmp_path: Path) -> None:
    map_path = entry_map(tmp_path / "entry.xodr")
    staged = tmp_path / ".lidar2xodr-stage" / "entry.xodr"  # where a build writes it before moving it into place
    staged.parent.mkdir()
    shutil.copy(map_path, staged)
    page = _write(tmp_path, "report", staged, reference=map_path, final_path=map_path)
    text = page.read_text(encoding="utf-8")
    assert ".lidar2xodr-" not in text, "the temporary folders the map was written and checked in are not its name"
    assert f"<h1>{map_path}</h1>" in text
    assert text.index('id="verdict"') < text.index('id="map"') < text.index('id="raw"')
    assert text.count("<th>boundaries.rmse_m</th>") == 1, "the metrics appear once, in the raw numbers"
    assert ">failed<" in text and ">not available<" in text and "SUMO netconvert 1.28.0 FAILED" in text
    assert text.count('class="closeup"') == 1, "one close-up: the lane-count change"
    assert 'id="along-road"' in text and "https://" not in text.split("<main>")[1]
    again = _write(tmp_path, "again", staged, reference=map_path, final_path=map_path)
    assert again.read_bytes() == page.read_bytes()


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("headless Chromium not installed (Debian package chromium): the page is not rendered")
    return exe


def _render(exe: str, page: Path) -> tuple[str, str]:
    """The DOM after the scripts ran (10 s of virtual time) and the browser's log."""
    cmd = [exe, "--headless", "--disable-gpu", "--no-first-run", "--enable-logging=stderr", "--v=0",
           "--virtual-time-budget=10000", "--dump-dom", page.resolve().as_uri()]
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        cmd.insert(1, "--no-sandbox")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout, proc.stderr


@pytest.mark.parametrize("make", [entry_map, junction_map])
def test_headless_chromium_draws_the_map_without_errors(tmp_path: Path, make: object) -> None:
    exe = _chromium()
    map_path = make(tmp_path / "map.xodr")  # type: ignore[operator]
    dom, log = _render(exe, _write(tmp_path, "report", map_path, reference=map_path))
    console = [ln for ln in log.splitlines() if "CONSOLE" in ln]
    assert not [ln for ln in console if re.search(r"error|uncaught|exception", ln, re.I)], console
    assert re.search(r'<div id="js-error" hidden="?"?>', dom), "the page reported a script error"
    plots = dom.count("js-plotly-plot")
    assert plots >= 3, f"map, close-up and error plot drawn, found {plots}"
    main = dom[dom.index('id="map"'):dom.index('class="note"', dom.index('id="map"'))]
    assert "main-svg" in main and main.count("scatterlayer") >= 1
    assert len(re.findall(r'class="trace scatter', main)) >= 5, "lanes, borders, marks, points and markers"


def test_a_map_that_cannot_be_read_back_still_gets_its_verdict(tmp_path: Path) -> None:
    broken = tmp_path / "broken.xodr"
    broken.write_text("<OpenDRIVE><road id='1' length='x'/></OpenDRIVE>")
    text = _write(tmp_path, "report", broken, reference=entry_map(tmp_path / "truth.xodr")).read_text(encoding="utf-8")
    assert "the written map cannot be read back, so it is not drawn" in text and 'id="raw"' in text


def test_build_with_a_missing_reference_stops_before_building(tmp_path: Path) -> None:
    import sys

    missing = tmp_path / "truth.xodr"
    cmd = [sys.executable, "-m", "lidar2xodr.cli", "build", str(tmp_path), "-o", str(tmp_path / "m.xodr"),
           "--reference", str(missing)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2 and "reference map not found" in proc.stderr and str(missing) in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "m.xodr").exists()
