"""`check`: the real ASAM checkers plus our geometry continuity verdict."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from rich.console import Console
from typer.testing import CliRunner

from lidar2xodr.check import (
    KINK_LIMIT_RAD,
    LEAP_LIMIT_M,
    check_file,
    find_qc_venv,
    print_check,
    run_netconvert,
    run_pyxodr,
)
from lidar2xodr.cli import app
from lidar2xodr.errors import InputError
from lidar2xodr.quality import readers

HEADER = '<header revMajor="1" revMinor="8" name="t" version="1" date="2024-01-01T00:00:00"/>'
LANES = """<lanes><laneSection s="0"><center><lane id="0" type="none" level="false"/></center>
<right><lane id="-1" type="driving" level="false"><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></right>
</laneSection></lanes>"""


def _map(tmp_path: Path, geometries: str, length: float, name: str = "m.xodr") -> Path:
    """A one-road OpenDRIVE 1.8 map with the given <geometry> records and one right driving lane."""
    xml = (f'<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE>{HEADER}'
           f'<road id="1" length="{length}" junction="-1" rule="RHT"><planView>{geometries}</planView>'
           f"{LANES}</road></OpenDRIVE>\n")
    path = tmp_path / name
    path.write_text(xml, encoding="utf-8")
    return path


def _line(s: float, x: float, y: float, hdg: float, length: float) -> str:
    return f'<geometry s="{s}" x="{x}" y="{y}" hdg="{hdg}" length="{length}"><line/></geometry>'


def _ppoly(s: float, x: float, length: float, b_u: float) -> str:
    return (f'<geometry s="{s}" x="{x}" y="0" hdg="0" length="{length}"><paramPoly3 aU="0" bU="{b_u}" cU="0" '
            'dU="0" aV="0" bV="0" cV="0" dV="0" pRange="normalized"/></geometry>')


@pytest.fixture(scope="module", autouse=True)
def _needs_checker() -> None:
    try:
        find_qc_venv()
    except InputError as exc:
        pytest.skip(f"ASAM checker environment missing: {exc}")


def test_real_highway_map_is_clean(shared_data: Path) -> None:
    res = check_file(shared_data / "maps" / "asam" / "Ex_Entry_Exit.xodr")
    assert res["asam"]["checker"] == "qc_opendrive"
    assert res["asam"]["errors"] == 0
    assert res["asam"]["warnings"] > 0  # the real checker flags its redundant elevation records
    assert res["asam"]["warnings"] == sum(i["level"] == "warning" for i in res["asam"]["issues"])
    assert res["asam"]["checkers_completed"] > 15  # OpenDRIVE 1.8: the rules are really applied
    assert res["continuity"]["max_leap_m"] < 1e-3 and res["continuity"]["max_kink_rad"] < 1e-3
    assert res["ok"] is True


def test_schema_error_of_a_real_map_fails(shared_data: Path) -> None:
    res = check_file(shared_data / "maps" / "maliput" / "ParametricCubicCurveComplexRoad.xodr")
    assert res["asam"]["errors"] >= 1
    assert any("rule" in i["message"] and i["level"] == "error" for i in res["asam"]["issues"])
    assert res["ok"] is False


def test_five_centimetre_leap_fails(tmp_path: Path) -> None:
    path = _map(tmp_path, _line(0, 0, 0, 0, 50) + _line(50, 50, 0.05, 0, 50), 100)
    res = check_file(path)
    assert res["asam"]["errors"] == 0  # schema-valid: only our continuity check sees the gap
    assert res["continuity"]["max_leap_m"] == pytest.approx(0.05, abs=1e-9)
    assert res["continuity"]["max_kink_rad"] == pytest.approx(0.0, abs=1e-12)
    assert res["continuity"]["roads_over_limit"] == ["1"]
    assert res["continuity"]["worst"]["leap"]["s"] == 50.0
    assert res["ok"] is False and any("leap" in r for r in res["reasons"])


def test_heading_kink_fails_and_tiny_one_passes(tmp_path: Path) -> None:
    kinked = _map(tmp_path, _line(0, 0, 0, 0, 50) + _line(50, 50, 0, 0.02, 50), 100, "k.xodr")
    res = check_file(kinked)
    assert res["continuity"]["max_kink_rad"] == pytest.approx(0.02, abs=1e-9)
    assert res["ok"] is False
    fine = _map(tmp_path, _line(0, 0, 0, 0, 50) + _line(50, 50, 0.0004, 0.0005, 50), 100, "f.xodr")
    res = check_file(fine)
    assert res["continuity"]["max_leap_m"] == pytest.approx(0.0004, abs=1e-9)
    assert res["continuity"]["max_kink_rad"] == pytest.approx(0.0005, abs=1e-9)
    assert 0.0004 < LEAP_LIMIT_M <= 0.001 and 0.0005 < KINK_LIMIT_RAD <= 0.001
    assert res["ok"] is True


def test_parampoly3_length_mismatch_is_measured(tmp_path: Path) -> None:
    # The curve is 100 m long (u = 100 p) but declares 101 m; the second piece is consistent.
    path = _map(tmp_path, _ppoly(0, 0, 101, 100) + _ppoly(101, 100, 40, 40), 141)
    cont = check_file(path)["continuity"]
    assert cont["max_length_error_m"] == pytest.approx(1.0, abs=1e-6)
    assert cont["max_length_error_rel"] == pytest.approx(1.0 / 101, abs=1e-8)
    assert cont["worst"]["length"]["geometry"] == 0
    assert cont["max_leap_m"] == pytest.approx(0.0, abs=1e-9)


def test_valid_scenario(shared_data: Path) -> None:
    res = check_file(shared_data / "scenarios" / "asam" / "CutIn.xosc")
    assert res["kind"] == "xosc" and "continuity" not in res
    assert res["asam"]["checker"] == "qc_openscenario"
    assert res["asam"]["checkers_completed"] >= 5
    assert res["asam"]["checkers_skipped_for_version"] > 0  # OpenSCENARIO 1.0 predates most rules
    assert res["asam"]["errors"] == 0 and res["ok"] is True


def test_cli_writes_json_and_exits_1_when_not_ok(tmp_path: Path) -> None:
    path = _map(tmp_path, _line(0, 0, 0, 0, 50) + _line(50, 50, 0.05, 0, 50), 100)
    out = tmp_path / "verdict.json"
    res = CliRunner().invoke(app, ["check", str(path), "--json", str(out)])
    assert res.exit_code == 1, res.output
    data = json.loads(out.read_text())
    assert data["ok"] is False and data["continuity"]["max_leap_m"] == pytest.approx(0.05)
    assert {"errors", "warnings", "issues"} <= set(data["asam"])


def test_unreadable_map_is_reported_not_raised(tmp_path: Path) -> None:
    path = tmp_path / "broken.xodr"
    path.write_text(f'<OpenDRIVE>{HEADER}<road id="1" length="10" junction="-1"><planView/></road></OpenDRIVE>')
    res = check_file(path)
    assert res["ok"] is False and "error" in res["continuity"] and res["asam"]["errors"] > 0


def test_bad_input_and_missing_checker(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(InputError, match="expected an OpenDRIVE"):
        check_file(tmp_path / "map.txt")
    with pytest.raises(InputError, match="not found"):
        check_file(tmp_path / "absent.xodr")
    path = _map(tmp_path, _line(0, 0, 0, 0, 10), 10)
    monkeypatch.setenv("LIDAR2XODR_QC_VENV", str(tmp_path / "no-venv"))
    with pytest.raises(InputError, match="make setup"):
        check_file(path)
    res = CliRunner().invoke(app, ["check", str(path)])
    assert res.exit_code == 2 and "make setup" in res.output and "Traceback" not in res.output


def _steep_map(tmp_path: Path) -> Path:
    """One straight road climbing 50 %: valid OpenDRIVE, but SUMO warns about the grade."""
    path = _map(tmp_path, _line(0, 0, 0, 0, 100), 100, "steep.xodr")
    text = path.read_text().replace("<lanes>", '<elevationProfile><elevation s="0" a="0" b="0.5" c="0" d="0"/>'
                                    "</elevationProfile><lanes>")
    path.write_text(text)
    return path


def test_reader_warnings_are_reported_verbatim_not_judged(tmp_path: Path) -> None:
    res = check_file(_steep_map(tmp_path))
    assert res["ok"] is True and res["asam"]["errors"] == 0  # the readers never fail the verdict
    sumo, pyx, carla = res["readers"]["netconvert"], res["readers"]["pyxodr"], res["readers"]["carla"]
    assert pyx["available"] and pyx["ok"] and pyx["roads"] == 1 and pyx["max_reference_dev_m"] < 1e-3
    assert not carla["available"] or (carla["ok"] and carla["lanes_walked"] == 1), carla
    if not sumo["available"]:
        pytest.skip(sumo["note"])
    assert sumo["returncode"] == 0 and not sumo["errors"] and not sumo["ok"]
    assert any(ln.startswith("Warning: Edge") and "has a grade of 50.00%" in ln for ln in sumo["warnings"]), sumo
    assert sumo["edges"] == 1 and sumo["lanes"] == 1


def test_absent_readers_are_skipped_with_a_note(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _map(tmp_path, _line(0, 0, 0, 0, 50), 50)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("SUMO_HOME", raising=False)
    monkeypatch.setattr(readers, "_pypi_sumo_home", lambda: None)
    monkeypatch.setitem(sys.modules, "pyxodr.road_objects.network", None)
    sumo, pyx = run_netconvert(path), run_pyxodr(path)
    assert sumo == {"available": False, "note": sumo["note"]} and "netconvert not installed" in sumo["note"]
    assert pyx["available"] is False and "pyxodr" in pyx["note"]
    console = Console(record=True, width=200)
    print_check({"file": str(path), "asam": {"checker": "qc_opendrive", "errors": 0, "warnings": 0, "issues": [],
                                             "checkers_completed": 1, "checkers_skipped": 0, "checkers_failed": 0,
                                             "checkers_skipped_for_version": 0},
                 "readers": {"netconvert": sumo, "pyxodr": pyx}, "ok": True, "reasons": []}, console)
    assert "netconvert not installed" in console.export_text()


def test_pyxodr_failure_is_an_error_of_the_reader(tmp_path: Path) -> None:
    """A junction naming a road that does not exist: pyxodr cannot find the outgoing road."""
    path = _map(tmp_path, _line(0, 0, 0, 0, 50), 50)
    text = path.read_text().replace("</OpenDRIVE>", '<junction id="7" name="j"><connection id="0" incomingRoad="1" '
                                    'connectingRoad="99" contactPoint="start"/></junction></OpenDRIVE>')
    path.write_text(text)
    pyx = run_pyxodr(path)
    assert pyx["available"] and not pyx["ok"]
    assert pyx["errors"] and "99" in pyx["errors"][0], pyx


def _fake_sumo(home: Path, with_data: bool) -> Path:
    """A SUMO_HOME whose bin/netconvert is a script that reports a version and writes nothing."""
    exe = home / "bin" / "netconvert"
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\necho 'Eclipse SUMO netconvert Version 0.0-fake'\n")
    exe.chmod(0o755)
    if with_data:
        types = home / "data" / "typemap" / "opendriveNetconvert.typ.xml"
        types.parent.mkdir(parents=True)
        types.write_text("<types/>")
    return exe


def test_netconvert_comes_from_the_locked_pypi_package_unless_sumo_home_says_otherwise(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A fresh machine: no SUMO_HOME, nothing on PATH; the eclipse-sumo wheel brings netconvert and its data."""
    monkeypatch.delenv("SUMO_HOME", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    found = readers.find_netconvert()
    if found is None:
        pytest.skip("PyPI eclipse-sumo not installed")
    assert found.source == "PyPI eclipse-sumo" and found.exe.is_file()
    assert (found.sumo_home / "data" / "typemap" / "opendriveNetconvert.typ.xml").is_file()
    res = run_netconvert(_map(tmp_path, _line(0, 0, 0, 0, 50), 50))
    assert res["version"].startswith("1.28") and res["ok"] and res["edges"] == 1, res
    # an explicit SUMO_HOME wins; one that does not exist is named and not used
    _fake_sumo(tmp_path / "sumo", with_data=True)
    monkeypatch.setenv("SUMO_HOME", str(tmp_path / "sumo"))
    assert readers.find_netconvert().exe == tmp_path / "sumo" / "bin" / "netconvert"
    monkeypatch.setenv("SUMO_HOME", str(tmp_path / "absent"))
    found = readers.find_netconvert()
    assert found.source == "PyPI eclipse-sumo" and "absent does not exist" in found.note


def test_netconvert_without_sumo_data_is_an_error_naming_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """What a fresh machine with Debian's sumo but no sumo-tools met: named instead of a types-file failure."""
    _fake_sumo(tmp_path / "sumo", with_data=False)
    monkeypatch.setenv("SUMO_HOME", str(tmp_path / "sumo"))
    res = run_netconvert(_map(tmp_path, _line(0, 0, 0, 0, 50), 50))
    assert res["available"] and not res["ok"] and res["version"] == "0.0"
    types = "data/typemap/opendriveNetconvert.typ.xml"
    assert res["errors"] == [f"SUMO's data is missing: no {types} in {tmp_path / 'sumo'}"]


@pytest.mark.parametrize("namespace", ["http://www.opendrive.org",
                                       "http://code.asam.net/simulation/standard/opendrive_schema"])
def test_namespaced_map_checks_like_the_plain_one(tmp_path: Path, namespace: str) -> None:
    """The ASAM checker's schemas have no namespace: it gets a plain copy, its rows still point into the file."""
    plain = _map(tmp_path, _line(0, 0, 0, 0, 50) + _line(50, 50, 0.05, 0, 50), 100)
    spaced = tmp_path / "spaced.xodr"
    spaced.write_text(plain.read_text().replace("<OpenDRIVE>", f'<OpenDRIVE xmlns="{namespace}">'))
    a, b = check_file(plain, readers=False), check_file(spaced, readers=False)
    assert namespace in b["asam"]["note"] and "note" not in a["asam"]
    assert b["asam"]["errors"] == a["asam"]["errors"] == 0 and b["reasons"] == a["reasons"]
    assert b["continuity"] == a["continuity"] and b["ok"] is a["ok"] is False
