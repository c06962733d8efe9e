"""End to end: simulate a drive on the demo road, build the map, check it and compare with the truth.

Accuracy targets live in `make bench`; this test guards the wiring and catches gross regressions
(a lane too many, a map metres off, an invalid file) with generous bounds.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lidar2xodr.config import Config
from lidar2xodr.demo_road import write_demo_road
from lidar2xodr.errors import InputError
from lidar2xodr.pipeline import BuildPipeline


@pytest.fixture(scope="module")
def demo_drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from lidar2xodr.simulation import SimOptions, simulate

    root = tmp_path_factory.mktemp("e2e")
    truth = write_demo_road(root / "truth.xodr")
    drive = root / "drive"
    simulate(truth, drive, SimOptions(length_m=700.0, seed=3, traffic="mid"))
    return truth, drive


def test_build_check_compare(demo_drive: tuple[Path, Path], tmp_path: Path) -> None:
    truth, drive = demo_drive
    out = tmp_path / "map.xodr"
    result = BuildPipeline(drive, out, report_dir=tmp_path / "report", reference=truth,
                           scenario=tmp_path / "map.xosc").run()
    assert out.exists() and result.check["ok"]
    assert result.check["continuity"]["max_leap_m"] <= 1e-3
    assert result.check["continuity"]["max_kink_rad"] <= 1e-3
    metrics = result.summary["metrics"]
    assert metrics["boundaries"]["eval_length_m"] > 500
    assert metrics["boundaries"]["rmse_m"] < 0.3
    assert metrics["centerline"]["rmse_m"] < 0.3
    assert metrics["lane_count_agreement"] > 0.9
    assert abs(metrics["lane_width"]["bias_m"]) < 0.15
    on_map = result.summary["drive_on_map"]
    assert 650.0 < on_map["path_m"] < 720.0 and on_map["share"] > 0.8, "the drive's own path lies on the map"
    html = (tmp_path / "report" / "index.html").read_text()
    assert f"<h1>{out}</h1>" in html, "the report names the map where it was written"
    assert 'id="map"' in html and 'id="along-road"' in html and 'id="raw"' in html
    assert (tmp_path / "report" / "summary.json").is_file()
    assert (tmp_path / "map.xosc").exists()


def test_two_drives_are_fused_onto_the_anchor_and_the_biased_one_reported(demo_drive: tuple[Path, Path],
                                                                          tmp_path: Path) -> None:
    """`build DRIVE1 DRIVE2 --anchor 1`: the second drive's 1.2 m GNSS bias is found from the markings
    and taken out, so the fused map is where drive 1 puts it and its lines are not doubled."""
    from typer.testing import CliRunner

    from lidar2xodr.cli import app
    from lidar2xodr.simulation import SimOptions, simulate

    truth, drive = demo_drive
    biased = tmp_path / "biased"
    simulate(truth, biased, SimOptions(length_m=700.0, seed=5, traffic="low", gnss_bias_m=1.2))
    bias = np.array(json.loads((biased / "truth" / "route.json").read_text())["gnss_bias_m"])
    out = tmp_path / "fused.xodr"
    res = CliRunner().invoke(app, ["build", str(drive), str(biased), "-o", str(out), "--anchor", "1",
                                   "--reference", str(truth)])
    assert res.exit_code == 0, res.output
    assert "drive 2" in res.output and "offset" in res.output
    single = tmp_path / "single.xodr"
    alone = BuildPipeline(drive, single, reference=truth).run().summary["metrics"]["boundaries"]["rmse_m"]
    pipe = BuildPipeline([drive, biased], tmp_path / "again.xodr", reference=truth,
                         config=Config(fusion={"anchor": 1}))
    result = pipe.run()
    first, second = result.summary["fusion"]
    assert (first["dx_m"], first["dy_m"]) == (0.0, 0.0)
    # the bias is in the biased drive's poses; across the road the markings fix it to centimetres
    assert np.hypot(second["dx_m"] + bias[0], second["dy_m"] + bias[1]) < 0.3, (second, bias)
    fused = result.summary["metrics"]["boundaries"]["rmse_m"]
    assert fused < alone + 0.05, f"fusing made the map worse: {fused:.3f} m against {alone:.3f} m alone"
    assert (tmp_path / "again.xodr").read_bytes() == out.read_bytes()


def test_build_into_a_new_folder(demo_drive: tuple[Path, Path], tmp_path: Path) -> None:
    _, drive = demo_drive
    out = tmp_path / "new" / "deeper" / "map.xodr"
    BuildPipeline(drive, out).run()
    assert out.exists() and [p.name for p in out.parent.iterdir()] == ["map.xodr"]


def test_same_drive_same_bytes(demo_drive: tuple[Path, Path], tmp_path: Path) -> None:
    _, drive = demo_drive
    a, b = tmp_path / "a.xodr", tmp_path / "b.xodr"
    BuildPipeline(drive, a).run()
    BuildPipeline(drive, b).run()
    assert a.read_bytes() == b.read_bytes()


def test_no_markings_is_a_clear_error_and_writes_nothing(demo_drive: tuple[Path, Path], tmp_path: Path) -> None:
    """A threshold nothing passes leaves no markings: one clear error, no map, no temp files."""
    _, drive = demo_drive
    base = Config.model_validate({"extraction": {"auto_threshold": False}})
    # above the valid range on purpose (model_copy skips validation): no point of any drive passes
    cfg = base.model_copy(update={"extraction": base.extraction.model_copy(update={"reflectivity_threshold": 1.01})})
    out = tmp_path / "out" / "map.xodr"
    out.parent.mkdir()
    with pytest.raises(InputError):
        BuildPipeline(drive, out, cfg).run()
    assert list(out.parent.iterdir()) == []


def test_cli_build_bad_drive_one_line(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = subprocess.run([sys.executable, "-m", "lidar2xodr.cli", "build", str(empty), "-o", str(tmp_path / "m.xodr")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "empty" in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "m.xodr").exists()


def test_cli_compare_json_keys(demo_drive: tuple[Path, Path], tmp_path: Path) -> None:
    truth, _ = demo_drive
    out = tmp_path / "m.json"
    cmd = [sys.executable, "-m", "lidar2xodr.cli", "compare", str(truth), str(truth), "--json", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    m = json.loads(out.read_text())
    for group in ("boundaries", "centerline"):
        for key in ("rmse_m", "mean_m", "std_m", "eval_length_m"):
            assert np.isfinite(m[group][key])
        assert m[group]["rmse_m"] == 0.0
    assert m["lane_count_agreement"] == 1.0 and m["coverage"] == pytest.approx(1.0, abs=0.01)
    assert m["lane_width"]["bias_m"] == 0.0


def test_stages_rerun_from_intermediates_give_the_same_map(demo_drive: tuple[Path, Path], tmp_path: Path) -> None:
    """--keep-intermediate keeps markings.ply and lanes.json; `lanes` and `export` re-run the later stages."""
    _, drive = demo_drive
    keep = tmp_path / "int"
    BuildPipeline(drive, tmp_path / "built.xodr", keep_intermediate=keep).run()
    cli = [sys.executable, "-m", "lidar2xodr.cli"]
    subprocess.run([*cli, "lanes", str(keep / "markings.ply"), "-o", str(tmp_path / "lanes.json")], check=True,
                   capture_output=True)
    proc = subprocess.run([*cli, "export", str(tmp_path / "lanes.json"), "-o", str(tmp_path / "rerun.xodr"),
                           "--markings", str(keep / "markings.ply")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "rerun.xodr").read_bytes() == (tmp_path / "built.xodr").read_bytes()


def test_the_summary_says_failed_only_when_a_reader_could_not_read_the_map() -> None:
    """A reader that only warns (netconvert on an exit lane growing from zero width) still reads the map."""
    from lidar2xodr.pipeline import _verdict_line

    base = {"asam": {"errors": 0}, "continuity": {"max_leap_m": 0.0, "max_kink_rad": 0.0}}
    warn = {"available": True, "reader": "SUMO netconvert", "ok": False, "returncode": 0, "errors": [],
            "warnings": ["Warning: Lane '-1#1_0' is not connected from any incoming edge at junction '1#1'."]}
    clean = {"available": True, "reader": "pyxodr", "ok": True, "warnings": [], "errors": []}
    broken = {"available": True, "reader": "CARLA", "ok": False, "warnings": [],
              "errors": ["CARLA crashed on the map (signal 6)"]}
    failed_exit = {**warn, "reader": "netconvert", "warnings": [], "returncode": 1}
    line = _verdict_line({**base, "readers": {"n": warn, "p": clean, "c": broken, "x": failed_exit}})
    assert "SUMO netconvert: reads it with warnings, 1 warning(s), 0 error(s)" in line
    assert "pyxodr: reads it, 0 warning(s), 0 error(s)" in line
    assert "CARLA: FAILED to read it, 0 warning(s), 1 error(s)" in line
    assert "netconvert: FAILED to read it" in line


def test_a_map_failing_the_checks_is_refused_with_the_reason(demo_drive: tuple[Path, Path], tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """The error names what failed (here a negative lane width), not only the parts that passed."""
    import lidar2xodr.check

    reason = "1 negative lane width record(s), first: road 2 lane -1 -0.012 m at s=40.00"
    real = lidar2xodr.check.check_file

    def failing(*args: object, **kwargs: object) -> dict:
        return {**real(*args, **kwargs), "ok": False, "reasons": [reason]}

    monkeypatch.setattr(lidar2xodr.check, "check_file", failing)
    _, drive = demo_drive
    out = tmp_path / "map.xodr"
    with pytest.raises(InputError, match="fails the checks: 1 negative lane width record.*ASAM errors 0") as err:
        BuildPipeline(drive, out).run()
    assert "nothing written" in str(err.value) and not out.exists()
