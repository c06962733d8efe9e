"""Lane widths a map must not have (negative: an error) or should not have (slivers, long zero-width lanes)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from lidar2xodr.check import check_file, find_qc_venv
from lidar2xodr.cli import app
from lidar2xodr.config import CheckConfig
from lidar2xodr.errors import InputError
from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.quality.lane_widths import lane_widths


def _map(tmp_path: Path, widths: str, minor: int = 8, length: float = 200.0, name: str = "m.xodr") -> Path:
    """One straight two-lane road (right lanes -1 at 3.5 m and -2 with the given width records)."""
    xml = (f'<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header revMajor="1" revMinor="{minor}" name="t" '
           'version="1" date="2024-01-01T00:00:00"/><road id="1" length="{length}" junction="-1" rule="RHT">'
           f'<planView><geometry s="0" x="0" y="0" hdg="0" length="{length}"><line/></geometry></planView>'
           '<lanes><laneSection s="0"><center><lane id="0" type="none" level="false"/></center><right>'
           '<lane id="-1" type="driving" level="false"><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane>'
           f'<lane id="-2" type="driving" level="false">{widths}</lane></right></laneSection></lanes></road>'
           "</OpenDRIVE>\n").replace("{length}", str(length))
    path = tmp_path / name
    path.write_text(xml, encoding="utf-8")
    return path


NEGATIVE = '<width sOffset="0" a="3.5" b="0" c="0" d="0"/><width sOffset="120" a="3.5" b="-0.05" c="0" d="0"/>'


@pytest.fixture()
def _checker() -> None:
    try:
        find_qc_venv()
    except InputError as exc:
        pytest.skip(f"ASAM checker environment missing: {exc}")


@pytest.mark.usefixtures("_checker")
@pytest.mark.parametrize("minor", [6, 8])
def test_check_fails_a_negative_lane_width(tmp_path: Path, minor: int) -> None:
    """3.5 - 0.05 ds from s = 120 reaches 0 at s = 190 and -0.5 m at the road's end (s = 200)."""
    res = check_file(_map(tmp_path, NEGATIVE, minor), readers=False)
    [neg] = res["lane_widths"]["negative"]
    assert (neg["road"], neg["lane"], neg["s"]) == ("1", -2, 200.0) and neg["width"] == pytest.approx(-0.5)
    assert res["ok"] is False
    assert any("negative lane width" in r and "road 1 lane -2" in r for r in res["reasons"]), res["reasons"]
    fine = check_file(_map(tmp_path, NEGATIVE.replace("-0.05", "-0.025"), minor, name="ok.xodr"), readers=False)
    assert fine["lane_widths"]["negative"] == [] and fine["ok"], fine["reasons"]


def test_simulate_refuses_a_negative_lane_width_in_one_line(tmp_path: Path) -> None:
    path = _map(tmp_path, NEGATIVE)
    out = tmp_path / "drive"
    res = CliRunner().invoke(app, ["simulate", str(path), str(out)])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    assert f"{path} road 1 lane -2" in " ".join(lines) and "lane width -0.500 m < 0 at s=200.00" in lines[0]
    assert not out.exists()


def _findings(tmp_path: Path, widths: str, lane_type: str = "driving", cfg: CheckConfig | None = None) -> dict:
    path = _map(tmp_path, widths)
    if lane_type != "driving":
        path.write_text(path.read_text().replace('<lane id="-2" type="driving"', f'<lane id="-2" type="{lane_type}"'))
    return lane_widths(OpenDriveMap.load(path), cfg)


def _w(s_offset: float, a: float, b: float = 0.0) -> str:
    return f'<width sOffset="{s_offset}" a="{a}" b="{b}" c="0" d="0"/>'


def test_a_sliver_lane_is_warned_about_and_a_shoulder_is_not(tmp_path: Path) -> None:
    res = _findings(tmp_path, _w(0, 0.5))
    assert res["zero_width"] == [] and res["negative"] == []
    [sliver] = res["narrow"]
    assert (sliver["road"], sliver["lane"], sliver["s_start"], sliver["s_end"]) == ("1", -2, 0.0, 200.0)
    assert sliver["min_width_m"] == 0.5
    assert res["warnings"] == ["road 1 lane -2: narrower than 1.0 m over 200.0 m, not a taper "
                               "(s 0.0-200.0, down to 0.50 m)"]
    assert _findings(tmp_path, _w(0, 0.5), lane_type="shoulder")["warnings"] == []
    assert _findings(tmp_path, _w(0, 0.5), cfg=CheckConfig(narrow_lane_m=0.4))["warnings"] == []


def test_a_taper_is_no_sliver_unless_it_stays_narrow_beyond_its_first_60_m(tmp_path: Path) -> None:
    # opens from 0 to 3.5 m over the first 60 m: its narrow metres are the taper
    assert _findings(tmp_path, _w(0, 0.0, 3.5 / 60) + _w(60, 3.5))["warnings"] == []
    # closes to 0 over the last 60 m: the same at the section's end
    assert _findings(tmp_path, _w(0, 3.5) + _w(140, 3.5, -3.5 / 60))["warnings"] == []
    # opens at 1 cm per metre: narrow (>= 0.05 m, < 1 m) from s = 5 to 100, of which 60-100 is no taper
    [slow] = _findings(tmp_path, _w(0, 0.0, 0.01))["narrow"]
    assert slow["s_start"] == 60.5 and slow["s_end"] == 99.5 and slow["length_m"] == 39.0


def test_a_zero_width_lane_kept_over_a_long_stretch_is_warned_about(tmp_path: Path) -> None:
    """Width 0 for 150 m, then it opens over 50 m (as a lane folded into the section before for SUMO)."""
    res = _findings(tmp_path, _w(0, 0.0) + _w(150, 0.0, 3.5 / 50))
    [zero] = res["zero_width"]
    assert (zero["s_start"], zero["s_end"], zero["min_width_m"]) == (0.0, 150.5, 0.0)
    assert res["narrow"] == []  # its opening is 14 m below 1 m: short, and a taper
    assert res["warnings"] == ["road 1 lane -2: zero width (< 0.05 m) over 150.5 m (s 0.0-150.5)"]
    # 25 m of zero width is not "long"
    assert _findings(tmp_path, _w(0, 0.0) + _w(25, 0.0, 3.5 / 50) + _w(75, 3.5))["warnings"] == []


@pytest.mark.usefixtures("_checker")
def test_check_reports_width_warnings_without_failing(tmp_path: Path) -> None:
    res = check_file(_map(tmp_path, _w(0, 0.5)), readers=False)
    assert res["ok"] is True and len(res["lane_widths"]["narrow"]) == 1
    assert res["lane_widths"]["warnings"][0].startswith("road 1 lane -2: narrower than 1.0 m")


def test_a_lane_wider_than_any_lane_is_warned_about(tmp_path: Path) -> None:
    """A border that leaves the road: the lane widens from 3.5 m at 0.05 m per metre, over 5 m from s = 30."""
    res = _findings(tmp_path, _w(0, 3.5, 0.05))
    [wide] = res["wide"]
    assert (wide["road"], wide["lane"], wide["s_start"], wide["s_end"]) == ("1", -2, 30.5, 200.0)
    assert wide["max_width_m"] == pytest.approx(13.5)
    assert res["warnings"] == ["road 1 lane -2: wider than 5.0 m over 169.5 m (s 30.5-200.0, up to 13.50 m): two "
                               "lanes as one, or a border that left the road"]
    # a 4.5 m lane is a lane; 25 m over 5 m (widening to 6 m at the end) is not long
    assert _findings(tmp_path, _w(0, 4.5))["warnings"] == []
    assert _findings(tmp_path, _w(0, 3.5) + _w(175, 5.0, 0.04))["wide"] == []
    assert _findings(tmp_path, _w(0, 7.0), lane_type="shoulder")["warnings"] == []
    assert _findings(tmp_path, _w(0, 7.0), cfg=CheckConfig(wide_lane_m=8.0))["warnings"] == []
