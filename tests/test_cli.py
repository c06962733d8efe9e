"""The command line's conventions: usage errors, choices, help texts, `config --show` (issue #15 item 6)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from lidar2xodr.cli import Format, Sensor, Traffic, app
from lidar2xodr.config import Config

runner = CliRunner(mix_stderr=False)
COMMANDS = ("build", "extract", "lanes", "export", "scenario", "simulate", "compare", "check", "demo", "config",
            "export-lanelet2", "export-geojson")

# each command with missing or wrong arguments, and the word its usage error must name
USAGE_ERRORS = [
    (["build"], "DRIVE"),
    (["build", "drive"], "--output"),
    (["build", "drive", "-o", "m.xodr", "--odometry", "gps"], "--odometry"),
    (["build", "drive", "-o", "m.xodr", "--format", "zip"], "--format"),
    (["build", "drive", "-o", "m.xodr", "--bogus"], "--bogus"),
    (["extract"], "DRIVE"),
    (["extract", "drive"], "--output"),
    (["extract", "drive", "-o", "m.ply", "--intensity-scale", "lots"], "--intensity-scale"),
    (["lanes"], "MARKINGS"),
    (["lanes", "m.ply"], "--output"),
    (["export"], "LANES_JSON"),
    (["export", "lanes.json"], "--output"),
    (["scenario"], "DRIVE"),
    (["scenario", "drive", "-o", "s.xosc"], "--map"),
    (["scenario", "drive", "--map", "m.xodr"], "--output"),
    (["simulate"], "MAP.xodr"),
    (["simulate", "m.xodr"], "OUT_DIR"),
    (["simulate", "m.xodr", "out", "--sensor", "velodyne"], "--sensor"),
    (["simulate", "m.xodr", "out", "--traffic", "jam"], "--traffic"),
    (["simulate", "m.xodr", "out", "--seed", "x"], "--seed"),
    (["compare"], "GENERATED"),
    (["compare", "a.xodr"], "REFERENCE"),
    (["check"], "PATH"),
    (["check", "a.xodr", "b.xodr"], "b.xodr"),
    (["demo", "--length-m", "long"], "--length-m"),
    (["demo", "extra"], "extra"),
    (["config"], "--show"),
    (["export-lanelet2"], "MAP.xodr"),
    (["export-lanelet2", "m.xodr"], "--output"),
    (["export-geojson"], "MAP.xodr"),
    (["export-geojson", "m.xodr"], "--output"),
    (["nonsense"], "nonsense"),
]


@pytest.mark.parametrize(("args", "named"), USAGE_ERRORS, ids=[" ".join(a) for a, _ in USAGE_ERRORS])
def test_usage_error_is_clean_exit_2(args: list[str], named: str, tmp_path: Path,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.stderr and res.exception is None or isinstance(res.exception, SystemExit)
    assert "Usage:" in res.stderr and named in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_bare_command_prints_the_help() -> None:
    res = runner.invoke(app, [])
    assert "Usage:" in res.stdout + res.stderr
    for cmd in COMMANDS:
        assert cmd in res.stdout + res.stderr
    assert "Error" not in res.stdout + res.stderr


@pytest.mark.parametrize("cmd", COMMANDS)
def test_help_has_an_example_and_no_none_default(cmd: str) -> None:
    res = runner.invoke(app, [cmd, "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0
    assert "[default: None]" not in res.stdout
    assert f"Example: lidar2xodr {cmd}" in res.stdout
    assert "--out " not in res.stdout  # one spelling: --output / -o


def test_choices_are_listed_in_help() -> None:
    build = runner.invoke(app, ["build", "--help"], env={"COLUMNS": "200"}).stdout
    assert "auto|gnss|lidar" in build and "drive|aimotive|kitti_raw|rosbag|folder" in build
    assert "--topic" in build and "--pose-topic" in build
    sim = runner.invoke(app, ["simulate", "--help"], env={"COLUMNS": "200"}).stdout
    assert "livox-horizon|pandar64" in sim and "none|low|mid|high" in sim


def test_choice_enums_match_the_code() -> None:
    """The CLI's hard-coded choices (kept import-free for a fast --help) are the readers' and the simulator's."""
    from lidar2xodr.datasets import FORMATS
    from lidar2xodr.simulation import SimOptions

    assert tuple(f.value for f in Format) == FORMATS
    for sensor in Sensor:
        SimOptions(sensor=sensor.value)
    for traffic in Traffic:
        SimOptions(traffic=traffic.value)
    with pytest.raises(ValueError):
        SimOptions(sensor="velodyne")


def test_config_show_dumps_the_effective_configuration(tmp_path: Path) -> None:
    res = runner.invoke(app, ["config", "--show"])
    assert res.exit_code == 0
    assert yaml.safe_load(res.stdout) == Config().model_dump(mode="json")
    mine = tmp_path / "my.yaml"
    mine.write_text("markings:\n  search_radius_m: 2.5\nextraction:\n  workers: 2\n")
    res = runner.invoke(app, ["config", "--show", "-c", str(mine)])
    shown = yaml.safe_load(res.stdout)
    assert shown["markings"]["search_radius_m"] == 2.5 and shown["extraction"]["workers"] == 2
    assert Config.model_validate(shown) == Config.load(mine)


def test_every_option_is_spelled_once() -> None:
    """`--output/-o` is the one spelling of a command's main output; `--out` is gone everywhere."""
    for cmd in COMMANDS:
        text = runner.invoke(app, [cmd, "--help"], env={"COLUMNS": "200"}).stdout
        assert not re.search(r"--out\b(?!put)", text), cmd
