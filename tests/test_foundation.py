"""Configuration, atomic output, CLI error handling and the project's own demo road."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lidar2xodr.cli import app
from lidar2xodr.config import Config
from lidar2xodr.demo_road import ADDED_LANE, LANE_WIDTH, write_demo_road
from lidar2xodr.errors import InputError, OutputError
from lidar2xodr.fileio import atomic_dir, atomic_path, staged, staged_outputs

runner = CliRunner()


def test_config_defaults_are_the_papers_values() -> None:
    cfg = Config()
    assert cfg.extraction.ground_margin_m == 0.15
    assert cfg.extraction.reflectivity_threshold == 0.5
    assert cfg.extraction.outlier_radius_m == 0.5 and cfg.extraction.outlier_min_neighbors == 4
    assert cfg.markings.slice_threshold_m == 30.0 and cfg.markings.slice_length_m == 6.0
    assert cfg.markings.gamma == 0.5
    assert (cfg.markings.search_step_m, cfg.markings.search_max_m, cfg.markings.search_radius_m) == (3.0, 27.0, 1.75)
    assert cfg.markings.combine_search_m == 63.0
    assert cfg.export.piece_length_m == 100.0 and cfg.export.look_fraction == 0.125


def test_every_config_parameter_is_read_by_the_package() -> None:
    """A parameter nobody reads is a knob that does nothing (a revert once left six odometry_ground* behind)."""
    import re

    package = Path(__file__).resolve().parents[1] / "src" / "lidar2xodr"
    code = "\n".join(p.read_text() for p in package.rglob("*.py") if p.name != "config.py")
    unread = [f"{section}.{name}" for section, field in Config.model_fields.items()
              for name in getattr(field.annotation, "model_fields", {})
              if not re.search(rf"\b{re.escape(name)}\b", code)]
    assert not unread, f"configuration parameters read nowhere: {unread}"


def test_config_load_overrides_and_rejects(tmp_path: Path) -> None:
    good = tmp_path / "c.yaml"
    good.write_text("markings:\n  search_radius_m: 2.0\n")
    assert Config.load(good).markings.search_radius_m == 2.0
    bad = tmp_path / "bad.yaml"
    bad.write_text("markings:\n  no_such_field: 1\n")
    with pytest.raises(InputError, match="no_such_field"):
        Config.load(bad)
    with pytest.raises(InputError, match="not found"):
        Config.load(tmp_path / "missing.yaml")


def test_atomic_path_leaves_nothing_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "map.xodr"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["map.xodr"]
    with atomic_path(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"


def test_atomic_dir_replaces_whole(tmp_path: Path) -> None:
    target = tmp_path / "report"
    with pytest.raises(RuntimeError), atomic_dir(target) as tmp:
        (tmp / "a.txt").write_text("x")
        raise RuntimeError("crash")
    assert not target.exists()
    with atomic_dir(target) as tmp:
        (tmp / "a.txt").write_text("x")
    assert (target / "a.txt").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_cli_version_and_help() -> None:
    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and "lidar2xodr" in res.stdout
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0
    for cmd in ("build", "compare", "check", "demo"):
        assert cmd in res.stdout


def test_cli_bad_input_is_one_line_exit_2(tmp_path: Path) -> None:
    """A missing or broken map: one line naming the file, exit code 2, no traceback."""
    broken = tmp_path / "broken.xodr"
    broken.write_text("<OpenDRIVE><road")
    for args in (["compare", str(tmp_path / "nope.xodr"), str(broken)], ["compare", str(broken), str(broken)]):
        proc = subprocess.run([sys.executable, "-m", "lidar2xodr.cli", *args], capture_output=True, text=True)
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and ".xodr" in lines[0]


def test_cli_unexpected_exception_is_one_line_exit_3(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug inside a stage still ends in one line naming the exception, not a traceback."""
    import lidar2xodr.evaluation

    def broken(*_args: object, **_kwargs: object) -> None:
        raise ValueError("matmul: size 3 is different from 15")

    monkeypatch.setattr(lidar2xodr.evaluation, "compare_maps", broken)
    monkeypatch.delenv("LIDAR2XODR_DEBUG", raising=False)
    res = runner.invoke(app, ["compare", str(tmp_path / "a.xodr"), str(tmp_path / "b.xodr")])
    assert res.exit_code == 3
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "ValueError: matmul" in lines[0] and "Traceback" not in res.output
    monkeypatch.setenv("LIDAR2XODR_DEBUG", "1")
    res = runner.invoke(app, ["compare", str(tmp_path / "a.xodr"), str(tmp_path / "b.xodr")])
    assert isinstance(res.exception, ValueError)


def test_demo_road_is_deterministic_and_as_designed(tmp_path: Path) -> None:
    from lidar2xodr.opendrive import OpenDriveMap

    a = write_demo_road(tmp_path / "a.xodr").read_bytes()
    b = write_demo_road(tmp_path / "b.xodr").read_bytes()
    assert a == b
    odr = OpenDriveMap.load(tmp_path / "a.xodr")
    (road,) = odr.roads.values()
    assert road.length == pytest.approx(3000.0)
    s = np.array([100.0, ADDED_LANE[0] + 250.0, 2900.0])
    lanes = [sum(1 for ln in road.lane_sections[i].lanes.values() if ln.type == "driving")
             for i in road.section_index(s)]
    assert lanes == [3, 4, 3]
    width = road.border_t(s, -3) - road.border_t(s, -4)
    assert width[1] == pytest.approx(LANE_WIDTH, abs=1e-6)
    assert road.superelevation(np.array([800.0]))[0] == pytest.approx(-0.025)


def test_atomic_outputs_get_normal_permissions(tmp_path: Path) -> None:
    """mkstemp makes 0600 files; outputs must be readable like any other file the user writes."""
    import os
    import stat

    mask = os.umask(0)
    os.umask(mask)
    with atomic_path(tmp_path / "m.xodr") as tmp:
        tmp.write_text("x")
    assert stat.S_IMODE((tmp_path / "m.xodr").stat().st_mode) == 0o666 & ~mask


def test_staged_outputs_are_all_or_nothing(tmp_path: Path) -> None:
    """Inside staged_outputs, outputs appear together at the end, or none of them (and no new folder)."""
    (tmp_path / "map.xodr").write_text("old")
    with pytest.raises(RuntimeError), staged_outputs():
        with atomic_path(tmp_path / "map.xodr") as tmp:
            tmp.write_text("new")
        assert (tmp_path / "map.xodr").read_text() == "old"
        assert staged(tmp_path / "map.xodr").read_text() == "new"
        assert staged(tmp_path / "map.xodr").name == "map.xodr"
        with atomic_dir(tmp_path / "new" / "report") as tmp:
            (tmp / "index.html").write_text("x")
        raise RuntimeError("the scenario failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.xodr"]
    assert (tmp_path / "map.xodr").read_text() == "old"
    with staged_outputs():
        with atomic_path(tmp_path / "map.xodr") as tmp:
            tmp.write_text("new")
        with atomic_dir(tmp_path / "report") as tmp:
            (tmp / "index.html").write_text("x")
    assert (tmp_path / "map.xodr").read_text() == "new" and (tmp_path / "report" / "index.html").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.xodr", "report"]


def test_an_output_that_is_a_link_is_written_where_it_points(tmp_path: Path) -> None:
    """`-o latest.xodr`, a link to the day's map: the map is replaced and the link stays a link (the
    atomic rename used to put a file in place of the link and leave the linked map stale); a staged
    output is found by either name."""
    maps = tmp_path / "maps"
    maps.mkdir()
    (maps / "today.xodr").write_text("old")
    link = tmp_path / "latest.xodr"
    link.symlink_to(maps / "today.xodr")
    with staged_outputs():
        with atomic_path(link) as tmp:
            tmp.write_text("new")
        assert staged(link).read_text() == "new" and staged(maps / "today.xodr").read_text() == "new"
    assert link.is_symlink() and (maps / "today.xodr").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest.xodr", "maps"]
    dangling = tmp_path / "next.xodr"
    dangling.symlink_to(maps / "tomorrow.xodr")
    with atomic_path(dangling) as tmp:
        tmp.write_text("first")
    assert dangling.is_symlink() and (maps / "tomorrow.xodr").read_text() == "first"


def test_atomic_dir_replaces_only_its_own_files(tmp_path: Path) -> None:
    rep = tmp_path / "report"
    with atomic_dir(rep) as tmp:
        (tmp / "a.png").write_text("1")
        (tmp / "b.png").write_text("1")
    (rep / "mine.txt").write_text("the user's")
    with atomic_dir(rep) as tmp:
        (tmp / "a.png").write_text("2")
    assert sorted(p.name for p in rep.iterdir()) == [".lidar2xodr-report", "a.png", "mine.txt"]
    assert (rep / "a.png").read_text() == "2" and (rep / "mine.txt").read_text() == "the user's"
    other = tmp_path / "other"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    with pytest.raises(OutputError, match="not a lidar2xodr report"), atomic_dir(other):
        pass
    assert [p.name for p in other.iterdir()] == ["thesis.tex"]
