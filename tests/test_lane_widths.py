"""Lane widths a map must not have (negative: an error) or should not have (slivers, long zero-width lanes)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from lidar2xodr.check import check_file, find_qc_venv
from lidar2xodr.cli import app
from lidar2xodr.errors import InputError


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
