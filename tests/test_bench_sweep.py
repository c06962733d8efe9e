"""bench/sweep.py's summary and bench/corridors.py's maps (no sweep is run here)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import corridors  # noqa: E402
import sweep  # noqa: E402

from lidar2xodr.evaluation import DRIVING_TYPES  # noqa: E402
from lidar2xodr.lane_graph import build_lane_graph  # noqa: E402
from lidar2xodr.opendrive import OpenDriveMap  # noqa: E402


def _row(name: str, seed: int = 1, **kw: object) -> dict:
    row = {"map": name, "seed": seed, "asam_errors": 0, "leap_m": 0.0, "kink_rad": 0.0, "boundaries_rmse": 0.05,
           "centerline_rmse": 0.05, "lane_count": 1.0, "lane_graph": 1.0, "lane_graph_breaks": 0}
    row.update(kw)
    return row


def test_summary_counts_targets_failures_and_worst_cases() -> None:
    rows = [_row("a"), _row("b", boundaries_rmse=0.6), _row("c", lane_graph=0.9, lane_graph_breaks=2),
            _row("d", asam_errors=3), {"map": "e", "seed": 2, "error": "build: no road"}, _row("f", kink_rad=0.01)]
    s = sweep.summarise(rows)
    assert s["cases"] == 6 and s["built"] == 5
    assert s["valid_maps"] == 3  # a, b, c; d has ASAM errors, e was not built, f kinks
    assert s["meeting_targets"] == 1 and s["share_meeting_targets"] == pytest.approx(1 / 6)
    assert s["above_0_5_m"] == ["b s1"] and not s["done"]
    causes = {f["map"]: f["cause"] for f in s["failures"]}
    assert set(causes) == {"b", "c", "d", "e", "f"}
    assert causes["e"] == "build: no road" and causes["d"] == "3 ASAM error(s)"
    assert "lane_graph 0.900 below 0.98" in causes["c"] and "2 lane-graph break(s)" in causes["c"]
    assert "boundaries_rmse 0.600 above 0.1" in causes["b"] and "heading kink" in causes["f"]
    assert s["worst"]["boundaries_rmse"][0] == {"map": "b", "seed": 1, "boundaries_rmse": 0.6}
    assert s["worst"]["lane_graph"][0]["map"] == "c"
    assert s["medians"]["boundaries_rmse"] == pytest.approx(0.05)
    wrong_way = _row("w", boundaries_rmse=16.0, lane_graph=0.0, lane_graph_unheld_m=995.0, lane_graph_eval_m=1000.0)
    assert "wrong-way" in sweep.failure_cause(wrong_way)
    assert "wrong-way" not in sweep.failure_cause({**wrong_way, "lane_graph_unheld_m": 900.0})
    text = sweep.format_summary(s)
    assert "1/6 = 17 %" in text and "done when met: no" in text


def test_summary_done_when_every_case_meets_the_targets() -> None:
    rows = [_row(f"m{i}", seed) for i in range(10) for seed in (1, 2)]
    rows[0]["lane_graph"] = 0.97  # 1 of 20 misses: 95 % still meets the targets
    s = sweep.summarise(rows)
    assert s["share_meeting_targets"] == pytest.approx(0.95) and s["done"]
    rows[1]["lane_count"] = 0.5
    assert not sweep.summarise(rows)["done"]


def test_cases_of_a_quick_run_are_fixed(tmp_path: Path) -> None:
    args = argparse.Namespace(quick=True, maps=None, length_m=None, corridors=20, out=tmp_path)
    todo = sweep.cases(args)
    corr = [c for c in todo if c["kind"] == "corridor"]
    assert [c["map"] for c in corr] == ["corridor_001", "corridor_002"]
    assert all(c["seed"] == 1 and c["length_m"] == sweep.QUICK_LENGTH_M for c in todo)
    full = sweep.cases(argparse.Namespace(quick=False, maps=None, length_m=None, corridors=3, out=tmp_path))
    corr = [c for c in full if c["kind"] == "corridor"]
    assert len(corr) == 6 and {c["length_m"] for c in corr} == {sweep.CORRIDOR_LENGTH_M}
    assert len({sweep.case_id(c) for c in full}) == len(full)


def test_a_stored_row_is_reused_only_for_the_same_commit_and_arguments(tmp_path: Path) -> None:
    case = {"kind": "shared", "map": "x", "xodr": str(tmp_path / "absent.xodr"), "seed": 1, "length_m": 1000.0}
    key = {"commit": "abc", "case": case}
    sweep._store(tmp_path / "rows" / f"{sweep.case_id(case)}.json", key, {"map": "x", "seed": 1, "stored": True})
    assert sweep.run_case(case, tmp_path, "abc", force=False)["stored"]
    rerun = sweep.run_case(case, tmp_path, "def", force=False)  # another commit: run (the map is absent)
    assert "stored" not in rerun and "error" in rerun


def test_corridor_is_reproducible_and_a_valid_network(tmp_path: Path) -> None:
    pytest.importorskip("roadgen")
    a, b = tmp_path / "a.xodr", tmp_path / "b.xodr"
    spec = corridors.write_corridor(3, a, length_m=2500.0)
    corridors.write_corridor(3, b, length_m=2500.0)
    assert a.read_bytes() == b.read_bytes()
    assert 2 <= spec.lanes <= 4 and all(700.0 <= abs(c["radius_m"]) <= 5000.0 for c in spec.curves)
    assert len(spec.ramps) + len(spec.dropped_ramps) >= 1
    odr = OpenDriveMap.load(a)
    assert odr.junctions, "slip roads join the carriageways through junctions"
    widths = [float(np.nanmax(lane.width(np.linspace(0.0, ls.s_end - ls.s, 50))))
              for road in odr.roads.values() for ls in road.lane_sections for lane in ls.lanes.values() if lane.id]
    assert max(widths) < 10.0, "no lane extrapolated from a width record that starts late"
    graph = build_lane_graph(odr, DRIVING_TYPES)
    driving = [r for r in odr.roads.values() if r.junction == "-1"
               and any(ls.lanes[i].type == "driving" for ls in r.lane_sections for i in ls.lanes)]
    assert len(driving) >= 3 and sum(len(s) for s in graph.succ) > 0
    other = corridors.write_corridor(4, tmp_path / "c.xodr", length_m=2500.0)
    assert other.curves != spec.curves


def test_changes_against_an_earlier_sweep_list_worse_cases_first(tmp_path: Path) -> None:
    todo = [{"map": m, "seed": 1, "length_m": 1000.0} for m in ("a", "b", "c", "d")]
    old = tmp_path / "old" / "rows"
    before = [_row("a"), _row("b"), _row("c", lane_count=0.5), _row("d")]
    for case, row in zip(todo, before, strict=True):
        sweep._store(old / f"{sweep.case_id(case)}.json", {"commit": "x"}, row)
    now = [_row("a", boundaries_rmse=0.051), _row("b", lane_graph=0.9), _row("c", lane_count=1.0),
           {"map": "d", "seed": 1, "error": "build: no road"}]
    items = sweep.changes(now, old.parent, todo, tmp_path / "new")
    assert [x["case"] for x in items] == ["b-s1-1000m", "d-s1-1000m", "c-s1-1000m"], "within tolerance: a"
    assert items[0]["worse"] == ["lane_graph 1.000 -> 0.900"] and items[2]["better"] == ["lane_count 0.500 -> 1.000"]
    assert items[1]["worse"] == ["built -> build: no road"]
    assert "3 (2 with a metric worse)" in sweep.format_changes(items)


def _straight(path: Path, *pieces: tuple[float, float, float, float], marks: list[str] | None = None) -> Path:
    """A one-way road of two 3.5 m lanes along +x, as (x start, length, shift, shift per metre) pieces;
    `marks`: the outer road mark of lanes -1 and -2 on each piece, in turn (none: no road marks)."""
    def mark(i: int, k: int) -> str:
        return "" if marks is None else f'<roadMark sOffset="0" type="{marks[2 * i + k - 1]}" width="0.15"/>'

    roads = "".join(
        f'<road id="{i + 1}" length="{n}" junction="-1" rule="RHT"><planView><geometry s="0" x="{x0}" y="0" hdg="0" '
        f'length="{n}"><line/></geometry></planView><lanes><laneOffset s="0" a="{dt}" b="{slope}" c="0" d="0"/>'
        '<laneSection s="0"><center><lane id="0" type="none" level="false"/></center><right>'
        + "".join(f'<lane id="-{k}" type="driving" level="false"><width sOffset="0" a="3.5" b="0" c="0" d="0"/>'
                  f"{mark(i, k)}</lane>" for k in (1, 2))
        + "</right></laneSection></lanes></road>"
        for i, (x0, n, dt, slope) in enumerate(pieces)
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header revMajor="1" revMinor="8" name="t" '
                    f'version="1"/>{roads}</OpenDRIVE>\n', encoding="utf-8")
    return path


@pytest.mark.parametrize(("common_shift", "worse"), [(0.0, False), (0.1, True)])
def test_more_road_is_judged_on_the_common_stretch(tmp_path: Path, common_shift: float, worse: bool) -> None:
    """A map that builds more road is worse only if it is worse where the earlier map also built road."""
    case = {"map": "m", "seed": 1, "length_m": 300.0, "xodr": str(_straight(tmp_path / "ref.xodr", (0, 300, 0, 0)))}
    cid = sweep.case_id(case)
    _straight(tmp_path / "old" / "cases" / cid / "map.xodr", (0, 150, 0, 0))
    # the added road drifts off the truth from where the earlier map ended (0.2 m at its end)
    _straight(tmp_path / "new" / "cases" / cid / "map.xodr", (0, 150, common_shift, 0),
              (150, 150, common_shift, 0.2 / 150))
    sweep._store(tmp_path / "old" / "rows" / f"{cid}.json", {"commit": "x"}, _row("m", boundaries_rmse=0.0,
                                                                                   driven=0.5))
    now = [_row("m", boundaries_rmse=0.07, driven=1.0)]
    common = sweep.common_rmse(tmp_path / "new" / "cases" / cid / "map.xodr",
                               tmp_path / "old" / "cases" / cid / "map.xodr", Path(case["xodr"]))
    assert common["boundaries_rmse"] == pytest.approx((0.0, common_shift), abs=0.01), "the seam's samples only"
    (item,) = sweep.changes(now, tmp_path / "old", [case], tmp_path / "new")
    assert "driven 0.500 -> 1.000" in item["better"]
    listed = item["worse"] if worse else item["better"]
    assert any(x.startswith("boundaries_rmse 0.000 -> 0.070 over more road; on the common stretch 0.000 -> ")
               for x in listed)


@pytest.mark.parametrize(("common_mark", "worse"), [("broken", False), ("solid", True)])
def test_road_marks_over_more_matched_line_are_judged_on_the_samples_both_match(
        tmp_path: Path, common_mark: str, worse: bool) -> None:
    """The new map's second half lies on the truth (the earlier one's lay 1.5 m off) with a wrongly typed
    line: its agreement falls over the added length, and is worse only if it falls where both match."""
    case = {"map": "m", "seed": 1, "length_m": 300.0,
            "xodr": str(_straight(tmp_path / "ref.xodr", (0, 300, 0, 0), marks=["broken", "solid"]))}
    cid = sweep.case_id(case)
    _straight(tmp_path / "old" / "cases" / cid / "map.xodr", (0, 150, 0, 0), (150, 150, 1.5, 0),
              marks=["broken", "solid", "broken", "solid"])
    _straight(tmp_path / "new" / "cases" / cid / "map.xodr", (0, 150, 0, 0), (150, 150, 0, 0),
              marks=[common_mark, "solid", "solid", "solid"])
    old_marks, new_marks, old_m, new_m = sweep.common_marks(tmp_path / "new" / "cases" / cid / "map.xodr",
                                                            tmp_path / "old" / "cases" / cid / "map.xodr",
                                                            Path(case["xodr"]))
    assert new_m > old_m and old_marks == pytest.approx(1.0)
    sweep._store(tmp_path / "old" / "rows" / f"{cid}.json", {"commit": "x"}, _row("m", road_marks=1.0))
    (item,) = sweep.changes([_row("m", road_marks=0.8)], tmp_path / "old", [case], tmp_path / "new")
    listed = item["worse"] if worse else item["better"]
    assert len(listed) == 1 and listed[0].startswith("road_marks 1.000 -> 0.800 over more matched line")


def test_maps_of_different_road_are_judged_by_the_driven_share(tmp_path: Path) -> None:
    """An earlier map of a street beside the drive and a new map of the driven road share no road:
    their RMSEs are of different road, so the driven share decides; a lane count is still compared."""
    case = {"map": "m", "seed": 1, "length_m": 300.0, "xodr": str(_straight(tmp_path / "ref.xodr", (0, 300, 0, 0)))}
    cid = sweep.case_id(case)
    _straight(tmp_path / "old" / "cases" / cid / "map.xodr", (0, 100, 0, 0))
    _straight(tmp_path / "new" / "cases" / cid / "map.xodr", (150, 150, 0.1, 0))
    sweep._store(tmp_path / "old" / "rows" / f"{cid}.json", {"commit": "x"},
                 _row("m", boundaries_rmse=0.0, driven=0.33))
    (item,) = sweep.changes([_row("m", boundaries_rmse=0.1, driven=0.5, lane_count=0.9)], tmp_path / "old", [case],
                            tmp_path / "new")
    assert "boundaries_rmse 0.000 -> 0.100 over more road; the two maps share no road (the driven share decides)" \
        in item["better"]
    assert item["worse"] == ["lane_count 1.000 -> 0.900"]


def test_drives_are_reused_only_from_finished_cases(tmp_path: Path) -> None:
    case = {"map": "a", "seed": 1, "length_m": 1000.0}
    first, second = tmp_path / "one", tmp_path / "two"
    for folder in (first, second):
        (folder / "cases" / sweep.case_id(case) / "drive").mkdir(parents=True)
        (folder / "cases" / sweep.case_id(case) / "drive" / "meta.yaml").write_text("format: lidar2xodr-drive\n")
    assert sweep.reused_drive(case, [first, second]) is None, "no row: the drive may be half simulated"
    sweep._store(second / "rows" / f"{sweep.case_id(case)}.json", {"commit": "x"}, _row("a"))
    assert sweep.reused_drive(case, [first, second]) == second / "cases" / sweep.case_id(case) / "drive"
