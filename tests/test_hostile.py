"""A hostile user's battery over every command (issue #17): configs, outputs, environment, signals.

Every case asserts the README's promise: the exit code, one message line on stderr that names the
user's file, no traceback, no output left behind and nothing of the user's changed (the test's
folder is hashed before and after). Commands run in-process (typer's CliRunner) except where
signals and processes matter. Readers' own hostile inputs live in the readers' tests.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import lidar2xodr
from lidar2xodr.cli import app
from lidar2xodr.demo_road import write_demo_road

runner = CliRunner(mix_stderr=False)
SRC = Path(lidar2xodr.__file__).resolve().parents[1]  # the subprocesses run the code under test


# --------------------------------------------------------------------------------------------
# harness


def snapshot(root: Path) -> dict[str, str]:
    """Every entry under `root` with the hash of its bytes (folders as '<dir>')."""
    snap = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_dir():
            snap[rel] = "<dir>"
        elif p.is_file():
            snap[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:  # a device or pipe (reading a pipe would block): its type
            snap[rel] = f"<special {p.lstat().st_mode:o}>"
    return snap


def hostile(args: list[object], root: Path, code: int = 2, names: object = None) -> str:
    """Run the CLI in-process; assert the promise of a failed command; return its one message line."""
    before = snapshot(root)
    res = runner.invoke(app, [str(a) for a in args])
    output = res.stdout + res.stderr
    assert res.exit_code == code, output
    assert "Traceback" not in output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    if names is not None:
        assert str(names) in lines[0], lines[0]
    assert ".lidar2xodr-" not in lines[0] and "lidar2xodr-qc-" not in lines[0], lines[0]
    assert snapshot(root) == before
    return lines[0]


@pytest.fixture(scope="module")
def assets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A valid map, a broken map, a tiny simulated drive (200 m) and its map; never written by the tests."""
    from lidar2xodr.simulation import SimOptions, simulate

    root = tmp_path_factory.mktemp("assets")
    truth = write_demo_road(root / "truth.xodr")
    broken = root / "broken.xodr"
    broken.write_text("<OpenDRIVE><road")
    drive = root / "drive"
    simulate(truth, drive, SimOptions(length_m=200.0, seed=1, traffic="mid"))
    return {"map": truth, "broken": broken, "drive": drive, "root": root}


# --------------------------------------------------------------------------------------------
# configurations: refused at load, one line naming the file and the field (item 9)

BAD_CONFIGS = {
    "negative_radius": ("markings:\n  search_radius_m: -1\n", "markings.search_radius_m"),
    "nan": ("markings:\n  search_radius_m: .nan\n", "markings.search_radius_m"),
    "inf": ("extraction:\n  outlier_radius_m: .inf\n", "extraction.outlier_radius_m"),
    "negative_workers": ("extraction:\n  workers: -3\n", "extraction.workers"),
    "zero_workers": ("extraction:\n  workers: 0\n", "extraction.workers"),
    "word_workers": ("extraction:\n  workers: many\n", "extraction.workers"),
    "fraction_above_1": ("extraction:\n  reflectivity_threshold: 1.5\n", "extraction.reflectivity_threshold"),
    "negative_share": ("lanes:\n  traffic_share: -0.1\n", "lanes.traffic_share"),
    "negative_seed": ("extraction:\n  seed: -1\n", "extraction.seed"),
    "zero_piece": ("export:\n  piece_length_m: 0\n", "export.piece_length_m"),
    "minor_9": ("export:\n  opendrive_minor: 9\n", "export.opendrive_minor"),
    "negative_ego_width": ("scenario:\n  ego_dims_m: [4.9, -1, 1.5]\n", "scenario.ego_dims_m"),
    "widths_swapped": ("lanes:\n  min_lane_width_m: 6\n", "lanes"),
    "odometry_word": ("extraction:\n  odometry: gps\n", "extraction.odometry"),
    "unknown_field": ("markings:\n  no_such_field: 1\n", "markings.no_such_field"),
    "unknown_section": ("paint:\n  colour: white\n", "paint"),
    "string_for_float": ("markings:\n  gamma: half\n", "markings.gamma"),
    "angle_over_180": ("markings:\n  max_turn_deg: 270\n", "markings.max_turn_deg"),
    "top_level_list": ("- extraction\n- markings\n", "mapping"),
    "yaml_markup": ("extraction:\n  workers: [/data/run1\n", "[/data/run1"),
    "yaml_multiline": ("extraction:\n\tworkers: 2\n", "cannot read configuration"),
    "section_not_mapping": ("markings: 3\n", "markings"),
}


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
def test_bad_config_is_one_line(case: str, tmp_path: Path) -> None:
    text, field = BAD_CONFIGS[case]
    cfg = tmp_path / "my config.yaml"
    cfg.write_text(text)
    line = hostile(["config", "--show", "-c", cfg], tmp_path, names=cfg)
    assert field in line


@pytest.mark.parametrize(("options", "said"), [
    (["--intensity-scale", "0"], "positive"),
    (["--intensity-scale", "-255"], "positive"),
    (["--intensity-scale", "nan"], "positive"),
    (["--topic", "/points"], "--topic does not apply"),
    (["--pose-topic", "/odom"], "--pose-topic does not apply"),
    (["--intensity-scale", "255"], "--intensity-scale does not apply"),
])
@pytest.mark.parametrize("command", ["build", "extract"])
def test_reader_options_that_would_be_ignored_or_mean_nothing_are_refused(
        command: str, options: list[str], said: str, tmp_path: Path, assets: dict[str, Path]) -> None:
    """Our own drive format states its intensity scale and has no topics: an option for it is a mistake."""
    out = tmp_path / "out"
    target = {"build": out / "m.xodr", "extract": out / "m.ply"}[command]
    line = hostile([command, assets["drive"], "-o", target, *options], tmp_path, names=assets["drive"])
    assert said in line


@pytest.mark.parametrize("command", ["build", "extract", "lanes", "export", "scenario", "compare"])
def test_bad_config_is_refused_by_every_command(command: str, tmp_path: Path, assets: dict[str, Path]) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("markings:\n  search_radius_m: .nan\n")
    out = tmp_path / "out"
    args = {
        "build": ["build", assets["drive"], "-o", out / "m.xodr"],
        "extract": ["extract", assets["drive"], "-o", out / "m.ply"],
        "lanes": ["lanes", tmp_path / "m.ply", "-o", out / "lanes.json"],
        "export": ["export", tmp_path / "lanes.json", "-o", out / "m.xodr"],
        "scenario": ["scenario", assets["drive"], "--map", assets["map"], "-o", out / "s.xosc"],
        "compare": ["compare", assets["map"], assets["map"]],
    }[command]
    line = hostile([*args, "-c", cfg], tmp_path, names=cfg)
    assert "markings.search_radius_m" in line


@pytest.mark.parametrize("name", ["missing.yaml", "folder", "binary.yaml"])
def test_unreadable_config(name: str, tmp_path: Path) -> None:
    (tmp_path / "folder").mkdir()
    (tmp_path / "binary.yaml").write_bytes(bytes(range(256)) * 4)
    hostile(["config", "--show", "-c", tmp_path / name], tmp_path, names=tmp_path / name)


# --------------------------------------------------------------------------------------------
# outputs in the wrong place: a folder as a file, a file as a folder (items 1, 3)


def _output_cases(a: dict[str, Path], t: Path) -> dict[str, tuple[list[object], Path]]:
    folder, userdir, userfile = t / "taken.xodr", t / "mine", t / "notes.txt"
    return {
        "build -o folder": (["build", a["drive"], "-o", folder], folder),
        "extract -o folder": (["extract", a["drive"], "-o", folder], folder),
        "lanes -o folder": (["lanes", t / "m.ply", "-o", folder], folder),
        "export -o folder": (["export", t / "lanes.json", "-o", folder], folder),
        "scenario -o folder": (["scenario", a["drive"], "--map", a["map"], "-o", folder], folder),
        "compare --json folder": (["compare", a["map"], a["map"], "--json", folder], folder),
        "check --json folder": (["check", a["map"], "--json", folder], folder),
        "build --scenario folder": (["build", a["drive"], "-o", t / "m.xodr", "--scenario", folder], folder),
        "build -o below a file": (["build", a["drive"], "-o", userfile / "m.xodr"], userfile / "m.xodr"),
        "build --report user folder": (["build", a["drive"], "-o", t / "m.xodr", "--report", userdir], userdir),
        "build --report file": (["build", a["drive"], "-o", t / "m.xodr", "--report", userfile], userfile),
        "build --keep-intermediate file": (["build", a["drive"], "-o", t / "m.xodr", "--keep-intermediate",
                                            userfile], userfile),
        "build --keep-intermediate user folder": (["build", a["drive"], "-o", t / "m.xodr",
                                                   "--keep-intermediate", userdir], userdir),
        "lanes --report user folder": (["lanes", t / "m.ply", "-o", t / "l.json", "--report", userdir], userdir),
        "simulate into user folder": (["simulate", a["map"], userdir], userdir),
        "simulate onto a file": (["simulate", a["map"], userfile], userfile),
        "demo into user folder": (["demo", "-o", userdir], userdir),
    }


OUTPUT_CASES = list(_output_cases({"drive": Path(), "map": Path()}, Path()))


@pytest.mark.parametrize("case", OUTPUT_CASES)
def test_output_in_the_wrong_place(case: str, tmp_path: Path, assets: dict[str, Path]) -> None:
    (tmp_path / "taken.xodr").mkdir()
    (tmp_path / "taken.xodr" / "inside.txt").write_text("the user's")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("the user's")
    (tmp_path / "notes.txt").write_text("the user's")
    args, named = _output_cases(assets, tmp_path)[case]
    hostile(args, tmp_path, names=named)


# --------------------------------------------------------------------------------------------
# missing and broken inputs of every command; messages keep [brackets] (items 2, 3)


def _input_cases(a: dict[str, Path], t: Path) -> dict[str, tuple[list[object], Path]]:
    nope, junk = t / "nope", t / "run[left] [time].bin"
    return {
        "build missing drive": (["build", nope, "-o", t / "o" / "m.xodr"], nope),
        "extract missing drive": (["extract", nope, "-o", t / "o" / "m.ply"], nope),
        "lanes missing cloud": (["lanes", nope / "m.ply", "-o", t / "o" / "l.json"], nope / "m.ply"),
        "lanes junk cloud": (["lanes", junk.with_suffix(".ply"), "-o", t / "o" / "l.json"], junk.with_suffix(".ply")),
        "export missing model": (["export", nope / "l.json", "-o", t / "o" / "m.xodr"], nope / "l.json"),
        "export junk model": (["export", junk.with_suffix(".json"), "-o", t / "o" / "m.xodr"],
                              junk.with_suffix(".json")),
        "scenario missing map": (["scenario", a["drive"], "--map", nope / "m.xodr", "-o", t / "o" / "s.xosc"],
                                 nope / "m.xodr"),
        "scenario broken map": (["scenario", a["drive"], "--map", junk.with_suffix(".xodr"), "-o",
                                 t / "o" / "s.xosc"], junk.with_suffix(".xodr")),
        "simulate missing map": (["simulate", nope / "m.xodr", t / "o"], nope / "m.xodr"),
        "simulate broken map": (["simulate", junk.with_suffix(".xodr"), t / "o"], junk.with_suffix(".xodr")),
        "simulate negative length": (["simulate", a["map"], t / "o", "--length-m", "-5"], "--length-m"),
        "simulate nan speed": (["simulate", a["map"], t / "o", "--speed-kmh", "nan"], "--speed-kmh"),
        "check missing": (["check", nope / "m.xodr"], nope / "m.xodr"),
        "check unknown suffix": (["check", t / "notes.txt"], t / "notes.txt"),
        "compare missing": (["compare", nope / "a.xodr", a["map"]], nope / "a.xodr"),
        "compare broken with brackets": (["compare", a["map"], junk.with_suffix(".xodr")],
                                         junk.with_suffix(".xodr")),
        "compare folder as map": (["compare", t, a["map"]], t),
    }


INPUT_CASES = list(_input_cases({"drive": Path(), "map": Path()}, Path()))


@pytest.mark.parametrize("case", INPUT_CASES)
def test_bad_input_of_every_command(case: str, tmp_path: Path, assets: dict[str, Path]) -> None:
    junk = tmp_path / "run[left] [time].bin"
    for suffix in (".ply", ".json", ".xodr"):
        junk.with_suffix(suffix).write_bytes(b"\x00garbage [/data/run1] \xff" * 7)
    (tmp_path / "empty.xodr").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("the user's")
    args, named = _input_cases(assets, tmp_path)[case]
    hostile(args, tmp_path, names=named)


@pytest.mark.parametrize("content", [b"", b"\x00garbage [/data/run1] \xff"])
def test_check_of_a_broken_file_is_a_failed_verdict(content: bytes, tmp_path: Path) -> None:
    """`check` judges the file: an empty or broken map is a verdict with errors (exit 1), not a crash."""
    bad = tmp_path / "run[left].xodr"
    bad.write_bytes(content)
    before = snapshot(tmp_path)
    res = runner.invoke(app, ["check", str(bad)])
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.output and "run[left].xodr" in res.stdout
    assert snapshot(tmp_path) == before


def test_markup_in_a_message_is_printed_verbatim(tmp_path: Path) -> None:
    """`[/data/run1]` once crashed the printer (rich markup); `[time]` and `run[left]` were eaten."""
    folder = tmp_path / "[/data/run1]"
    folder.mkdir(parents=True)
    cfg = folder / "run[left].yaml"
    cfg.write_text("markings: [time\n")
    line = hostile(["config", "--show", "-c", cfg], tmp_path)
    assert "[/data/run1]/run[left].yaml" in line and "[time" in line


# --------------------------------------------------------------------------------------------
# the user's environment: full disk, read-only, /proc (item 8) -> exit 2 naming the user's path


@contextlib.contextmanager
def tmpfs(where: Path, options: str) -> Iterator[Path]:
    where.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", options, "none", str(where)],
                                           capture_output=True).returncode != 0:
        pytest.skip("needs root and tmpfs mounts (the monkeypatched case below runs everywhere)")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def test_full_disk_is_exit_2(tmp_path: Path, assets: dict[str, Path]) -> None:
    with tmpfs(tmp_path / "small", "size=64k") as disk:
        with contextlib.suppress(OSError), open(disk / "filler", "wb") as fh:
            while True:
                fh.write(b"\0" * 4096)
                fh.flush()
        target = disk / "metrics.json"
        line = hostile(["compare", assets["map"], assets["map"], "--json", target], tmp_path, names=target)
        assert "no space left" in line


def test_read_only_target_is_exit_2(tmp_path: Path, assets: dict[str, Path]) -> None:
    with tmpfs(tmp_path / "ro", "ro,size=64k") as ro:
        target = ro / "metrics.json"
        line = hostile(["compare", assets["map"], assets["map"], "--json", target], tmp_path, names=target)
        assert "read-only" in line


def test_immutable_target_is_exit_2(tmp_path: Path, assets: dict[str, Path]) -> None:
    target = tmp_path / "metrics.json"
    target.write_text("the user's")
    if subprocess.run(["chattr", "+i", str(target)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not available here (needs root and a file system with attributes)")
    try:
        line = hostile(["compare", assets["map"], assets["map"], "--json", target], tmp_path, names=target)
        assert "permission denied" in line
    finally:
        subprocess.run(["chattr", "-i", str(target)], check=False)


def test_output_on_procfs_is_exit_2(tmp_path: Path, assets: dict[str, Path]) -> None:
    hostile(["compare", assets["map"], assets["map"], "--json", "/proc/metrics.json"], tmp_path,
            names="/proc/metrics.json")


def test_disk_full_while_writing_names_the_users_file(tmp_path: Path, assets: dict[str, Path],
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Without root: ENOSPC raised by the write itself; the message names the target, not the temp file."""
    def full(self: Path, *_args: object, **_kwargs: object) -> int:
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(pathlib.Path, "write_text", full)
    target = tmp_path / "metrics.json"
    line = hostile(["compare", assets["map"], assets["map"], "--json", target], tmp_path, names=target)
    assert "no space left" in line


def test_environment_oserror_from_a_stage_is_exit_2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An OSError of the environment escaping a stage is the user's (exit 2), not a bug (exit 3)."""
    import lidar2xodr.evaluation

    def denied(*_args: object, **_kwargs: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "a.xodr"))

    monkeypatch.setattr(lidar2xodr.evaluation, "compare_maps", denied)
    hostile(["compare", tmp_path / "a.xodr", tmp_path / "b.xodr"], tmp_path, names=tmp_path / "a.xodr")


# --------------------------------------------------------------------------------------------
# a failed build writes none of its outputs; a report only replaces its own files (items 1, 7)


def test_build_with_a_bad_object_list_writes_no_map(tmp_path: Path, assets: dict[str, Path]) -> None:
    drive = tmp_path / "drive"
    shutil.copytree(assets["drive"], drive)
    (drive / "objects.csv").write_text("time,id,class,x\n0.0,1,car,[oops]\n")
    out = tmp_path / "out"
    hostile(["build", drive, "-o", out / "map.xodr", "--scenario", out / "map.xosc", "--report", out / "rep",
             "--keep-intermediate", out / "keep"], tmp_path, names=drive / "objects.csv")


def test_build_with_an_unwritable_scenario_writes_no_map(tmp_path: Path, assets: dict[str, Path]) -> None:
    with tmpfs(tmp_path / "ro", "ro,size=64k") as ro:
        out = tmp_path / "out"
        hostile(["build", assets["drive"], "-o", out / "map.xodr", "--scenario", ro / "map.xosc"], tmp_path,
                names=ro / "map.xosc")


def test_rebuilding_a_report_keeps_the_users_files(tmp_path: Path, assets: dict[str, Path]) -> None:
    out, rep = tmp_path / "out", tmp_path / "out" / "report"
    res = runner.invoke(app, ["build", str(assets["drive"]), "-o", str(out / "map.xodr"), "--report", str(rep)])
    assert res.exit_code == 0, res.output
    assert (rep / ".lidar2xodr-report").is_file() and (rep / "index.html").is_file()
    (rep / "my notes.txt").write_text("the user's")
    (rep / "index.html").write_text("stale")
    res = runner.invoke(app, ["build", str(assets["drive"]), "-o", str(out / "map.xodr"), "--report", str(rep)])
    assert res.exit_code == 0, res.output
    assert (rep / "my notes.txt").read_text() == "the user's"
    assert (rep / "index.html").read_text() != "stale"
    assert sorted(p.name for p in out.iterdir()) == ["map.xodr", "report"]


def test_no_progress_bar_in_a_piped_log(tmp_path: Path, assets: dict[str, Path]) -> None:
    """A build that finds nothing: the one error line, not the progress bar's last state before it."""
    cfg = tmp_path / "dark.yaml"
    cfg.write_text("extraction:\n  auto_threshold: false\n  reflectivity_threshold: 1.0\n")
    line = hostile(["build", assets["drive"], "-o", tmp_path / "out" / "m.xodr", "-c", cfg], tmp_path,
                   names=assets["drive"])
    assert "no lane-marking points" in line


def test_numpy_warnings_become_one_line(tmp_path: Path, assets: dict[str, Path],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import lidar2xodr.evaluation

    real = lidar2xodr.evaluation.compare_maps

    def noisy(*args: object, **kwargs: object) -> object:
        with np.errstate(all="warn"):
            for _ in range(5):
                np.divide(np.zeros(3), np.zeros(3))
                np.log(np.zeros(2))
        return real(*args, **kwargs)

    monkeypatch.setattr(lidar2xodr.evaluation, "compare_maps", noisy)
    res = runner.invoke(app, ["compare", str(assets["map"]), str(assets["map"])])
    assert res.exit_code == 0
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("warning:") and ".py" not in lines[0], lines


# --------------------------------------------------------------------------------------------
# kills: SIGTERM like Ctrl-C, children die with us, a dead run's leftovers are cleaned (item 6)


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def _descendants(pid: int) -> set[int]:
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            with contextlib.suppress(OSError):
                kids = {int(k) for k in (task / "children").read_text().split()}
                todo.extend(kids - found)
                found |= kids
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(") ")[-1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _wait(cond: object, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():  # type: ignore[operator]
            return True
        time.sleep(0.05)
    return False


def _is_sleeper(pid: int) -> bool:
    """The stand-in checker (`sleep 601`), matched by its whole argv: "601" alone also occurs in PIDs
    and paths on other children's command lines (an extraction pool worker taken for the checker)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[:2] == [b"sleep", b"601"]
    except OSError:
        return False


def _as_in_a_terminal() -> None:
    """Ctrl-C as a terminal delivers it: a suite started in the background (`cmd &` in a script) runs
    with SIGINT ignored, which its children inherit, and a build that ignores SIGINT rightly goes on."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _build_until_checker(assets: dict[str, Path], out: Path,
                         tmpdir: Path | None = None) -> tuple[subprocess.Popen[str], set[int]]:
    """Start `build` in a subprocess and wait until the map checker (a child process) runs.

    The checker is a stand-in that sleeps (601 s), so the build is still in it when the signal comes.
    `tmpdir` is the build's system temporary folder (TMPDIR)."""
    venv = out.parent / "slow-qc"
    (venv / "bin").mkdir(parents=True, exist_ok=True)
    (venv / "bin" / "python").write_text("#!/bin/sh\nexec sleep 601\n")
    (venv / "bin" / "python").chmod(0o755)
    env = {**_env(), "LIDAR2XODR_QC_VENV": str(venv), **({"TMPDIR": str(tmpdir)} if tmpdir else {})}
    proc = subprocess.Popen([sys.executable, "-m", "lidar2xodr.cli", "build", str(assets["drive"]), "-o",
                             str(out / "map.xodr")], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_as_in_a_terminal)
    found = _wait(lambda: any(_is_sleeper(k) for k in _descendants(proc.pid)), 60)
    if not found:
        proc.kill()
        pytest.fail(f"the build never started its checker: {proc.communicate()}")
    return proc, _descendants(proc.pid)


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_sigterm_and_sigint_leave_nothing(sig: int, code: int, tmp_path: Path, assets: dict[str, Path]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "map.xodr").write_text("the map of an earlier build")
    proc, children = _build_until_checker(assets, out)
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == code, err
    assert "Traceback" not in err and len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
    assert _wait(lambda: not any(_alive(k) for k in children), 10), "a child outlived the build"
    assert [p.name for p in out.iterdir()] == ["map.xodr"]
    assert (out / "map.xodr").read_text() == "the map of an earlier build"


_CTRL_C_IN_C_CODE = """
import ctypes, sys
from lidar2xodr import check, cli

def check_file(*args, **kwargs):
    run = ctypes.pythonapi.PyRun_StringFlags
    run.restype = ctypes.py_object
    run.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object, ctypes.c_void_p]
    run(b"import os, signal\\nos.kill(os.getpid(), signal.SIGINT)\\nwhile True: pass\\n", 257, {}, {}, None)

check.check_file = check_file
sys.argv = ["lidar2xodr", "check", sys.argv[1]]
cli.run()
"""


def test_ctrl_c_inside_c_code_that_runs_python_still_exits_130(tmp_path: Path, assets: dict[str, Path]) -> None:
    """A KeyboardInterrupt that comes out of `PyRun_String` (lxml and Boost.Python run Python that way) makes
    CPython kill its own process with SIGINT at exit, whatever exit code was asked for: a CI run of the
    SIGINT test above saw -2 instead of 130 (the signal landed while lxml was busy)."""
    (tmp_path / "ctrl_c_in_c_code.py").write_text(_CTRL_C_IN_C_CODE)
    env = _env()
    env["PYTHONPATH"] = f"{tmp_path}{os.pathsep}{env['PYTHONPATH']}"
    proc = subprocess.run([sys.executable, "-m", "ctrl_c_in_c_code", str(assets["map"])], env=env,
                          capture_output=True, text=True, timeout=60, preexec_fn=_as_in_a_terminal)
    assert proc.returncode == 130, proc.stderr
    assert [ln for ln in proc.stderr.splitlines() if ln.strip()] == ["interrupted nothing written"], proc.stderr


def test_sigterm_to_the_whole_group_during_extraction_is_one_clean_exit(tmp_path: Path,
                                                                        assets: dict[str, Path]) -> None:
    """`timeout` and container stops signal every process: the extraction workers leave it to the build."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("extraction:\n  workers: 2\n")
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "lidar2xodr.cli", "build", str(assets["drive"]), "-o",
                             str(out / "map.xodr"), "-c", str(cfg)], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        if not _wait(lambda: len(_descendants(proc.pid)) >= 2, 60):
            pytest.fail(f"the build never started its workers: {proc.communicate(timeout=60)}")
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
    assert not out.exists() or list(out.iterdir()) == []


def test_sigterm_during_a_slow_checker_ends_it_at_once(tmp_path: Path, assets: dict[str, Path]) -> None:
    """The checker runs in a thread of ours; a SIGTERM to `check` must not wait for it (up to 900 s) but kill it."""
    venv = tmp_path / "slow-qc"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").write_text("#!/bin/sh\nexec sleep 601\n")
    (venv / "bin" / "python").chmod(0o755)
    proc = subprocess.Popen([sys.executable, "-m", "lidar2xodr.cli", "check", str(assets["map"])],
                            env={**_env(), "LIDAR2XODR_QC_VENV": str(venv)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)

    def sleeper() -> set[int]:
        return {k for k in _descendants(proc.pid) if _is_sleeper(k)}

    try:
        if not _wait(lambda: bool(sleeper()), 60):
            pytest.fail(f"check never started its checker: {proc.communicate(timeout=60)}")
        slow = sleeper()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "Traceback" not in err and len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
    assert _wait(lambda: not any(_alive(k) for k in slow), 10), "the checker outlived check"


def test_a_sigterm_that_surfaces_as_another_error_is_still_a_clean_143() -> None:
    """CI: the SIGTERM hit `check` while a C extension was being imported, which reported
    "ImportError: initialization failed", and the command said "internal error" with exit 3."""
    import typer

    from lidar2xodr.cli import _clean_errors
    from lidar2xodr.lifetime import Terminated

    def command() -> None:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        except Terminated:
            raise ImportError("initialization failed") from None

    with pytest.raises(typer.Exit) as stop:
        _clean_errors(command)()
    assert stop.value.exit_code == 143


def test_a_sigterm_lost_in_a_finaliser_still_ends_the_wait_for_a_child(monkeypatch: pytest.MonkeyPatch) -> None:
    """CI: the SIGTERM landed in a finaliser ("Exception ignored in ... Terminated"), its raise was lost, and
    `check` went on waiting for its checker thread (600 s). The signal itself must end the wait."""
    from concurrent.futures import ThreadPoolExecutor

    import typer

    from lidar2xodr import lifetime
    from lidar2xodr.cli import _clean_errors

    unraisable: list[object] = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)

    class SignalledWhenCollected:
        def __del__(self) -> None:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100_000):  # the handler runs in here, where Python can only print what it raises
                pass

    def command() -> object:
        with ThreadPoolExecutor(max_workers=1) as pool:
            job = pool.submit(lifetime.run_child, ["sleep", "601"], timeout=900)
            try:
                assert _wait(lambda: bool(lifetime._CHILDREN), 30), "the child never started"
                SignalledWhenCollected()
                return job.result(timeout=20)
            finally:
                lifetime.kill_children()

    started = time.monotonic()
    with pytest.raises(typer.Exit) as stop:
        _clean_errors(command)()
    assert stop.value.exit_code == 143
    assert time.monotonic() - started < 15
    assert unraisable == [], "the lost interrupt was printed"


def test_a_child_started_after_the_interrupt_is_killed_at_once() -> None:
    """A thread that runs two children in a row must not start the second one unkilled after the
    interrupt killed the first (netconvert `--version`, then the conversion: CI waited 30 s for it)."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from lidar2xodr import lifetime

    first_killed = threading.Event()

    def two_children() -> list[int]:
        codes = [lifetime.run_child(["sleep", "20"], timeout=60).returncode]
        first_killed.set()
        return [*codes, lifetime.run_child(["sleep", "20"], timeout=60).returncode]

    with ThreadPoolExecutor(max_workers=1) as pool:
        job = pool.submit(two_children)
        with pytest.raises(KeyboardInterrupt), lifetime.children_killed_on_exit(pool):
            assert _wait(lambda: bool(lifetime._CHILDREN), 30), "the first child never started"
            raise KeyboardInterrupt
        assert first_killed.is_set()
    assert job.result() == [-signal.SIGKILL, -signal.SIGKILL]
    assert not lifetime._STOPPING[0]


def test_sigkill_takes_the_checker_along_and_the_next_run_cleans_up(tmp_path: Path, assets: dict[str, Path],
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The killed build's and the next run's system temporary folder is the test's own: any other
    lidar2xodr run on the machine (a sweep beside the tests) cleans the shared one's leftovers of dead
    runs too, and took this one's before the test looked (a CI run beside a sweep failed so)."""
    import tempfile

    private = tmp_path / "tmp"
    private.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    out = tmp_path / "out"
    out.mkdir()
    (out / "map.xodr").write_text("the map of an earlier build")
    proc, children = _build_until_checker(assets, out, tmpdir=private)
    pid = proc.pid
    proc.kill()
    proc.communicate(timeout=30)
    assert _wait(lambda: not any(_alive(k) for k in children), 10), "the checker outlived a SIGKILL"
    assert (out / "map.xodr").read_text() == "the map of an earlier build"
    leftovers = [p.name for p in out.iterdir() if p.name != "map.xodr"]
    assert leftovers and all(name.startswith(f".lidar2xodr-{pid}-") for name in leftovers)
    qc = list(Path(tempfile.gettempdir()).glob(f"lidar2xodr-qc-{pid}-*"))
    assert qc, "the killed run left no checker folder to clean (was the checker running?)"
    res = runner.invoke(app, ["compare", str(assets["map"]), str(assets["map"]), "--json", str(out / "m.json")])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == ["m.json", "map.xodr"]
    assert not any(p.exists() for p in qc)


@pytest.mark.parametrize("kind", ["pool worker", "subprocess"])
def test_children_die_with_a_killed_parent(kind: str, tmp_path: Path) -> None:
    """The extraction's pool (`scheduler.task_runner`) and our subprocesses' launcher tie them to the parent."""
    script = textwrap.dedent(f"""
        import os, subprocess, sys, time
        from lidar2xodr.lifetime import dying_with_us
        from lidar2xodr.scheduler import task_runner
        def pid(job):
            return os.getpid()
        if {kind!r} == "pool worker":
            with task_runner(None, 2, None) as submit:
                print(submit(pid).result(), flush=True)
                time.sleep(60)
        else:
            child = subprocess.Popen(dying_with_us(["sleep", "60"]))
            print(child.pid, flush=True)
        time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], env=_env(), stdout=subprocess.PIPE, text=True)
    child = None
    try:
        assert proc.stdout is not None
        child = int(proc.stdout.readline())
        assert _alive(child)
        proc.kill()
        proc.wait(timeout=10)
        assert _wait(lambda: not _alive(child), 10), f"the {kind} outlived its parent"
    finally:
        proc.kill()
        if child is not None:
            with contextlib.suppress(OSError):
                os.kill(child, signal.SIGKILL)


_SPAWN_BESIDE_BLAS = """
import threading, time
import numpy as np
from lidar2xodr.lifetime import run_child

done = []
def spawn():
    while not done:
        run_child(["true"], timeout=60)
threads = [threading.Thread(target=spawn) for _ in range(4)]
for t in threads:
    t.start()
a = np.random.default_rng(0).random((200, 200))
end = time.monotonic() + 3
while time.monotonic() < end:
    np.linalg.svd(a)
done.append(1)
for t in threads:
    t.join()
print("finished")
"""


def test_children_started_from_threads_do_not_hang_a_blas_call() -> None:
    """`check` starts its readers from threads while the main thread measures the map with numpy.

    With a fork (a `preexec_fn`), OpenBLAS's at-fork handler stopped its thread pool under the main
    thread's BLAS call, which never returned: a CI build hung there and ignored SIGTERM."""
    try:
        proc = subprocess.run([sys.executable, "-c", _SPAWN_BESIDE_BLAS], env=_env(), capture_output=True, text=True,
                              timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("a BLAS call hung while threads started children")
    assert proc.stdout.strip() == "finished", proc.stderr


def test_stale_temp_of_a_live_process_is_kept(tmp_path: Path, assets: dict[str, Path]) -> None:
    """Only a dead run's leftovers go: a concurrent run's temporary files stay."""
    live = tmp_path / f".lidar2xodr-{os.getppid()}-map.xodr.abc"
    dead_pid = 2**22 + 12345
    dead = tmp_path / f".lidar2xodr-{dead_pid}-map.xodr.abc"
    live.mkdir()
    dead.mkdir()
    res = runner.invoke(app, ["compare", str(assets["map"]), str(assets["map"]), "--json", str(tmp_path / "m.json")])
    assert res.exit_code == 0
    assert live.exists() and not dead.exists()


@pytest.mark.parametrize("extra", [["--scenario", "{out}/map.xodr"], ["--lanelet2", "{out}/map.xodr"],
                                   ["--report", "{out}/rep", "--keep-intermediate", "{out}/rep"],
                                   ["--report", "{out}"]])
def test_two_outputs_on_one_path_are_refused_before_any_work(extra: list[str], tmp_path: Path,
                                                             assets: dict[str, Path]) -> None:
    """One path for two outputs would let one overwrite the other (and exit 0): exit 2, nothing written."""
    out = tmp_path / "out"
    out.mkdir()
    line = hostile(["build", assets["drive"], "-o", out / "map.xodr", *[a.format(out=out) for a in extra]], tmp_path)
    assert "two outputs" in line or "inside the" in line, line


def test_demo_with_an_impossible_length_is_a_usage_error_and_writes_nothing(tmp_path: Path) -> None:
    line = hostile(["demo", "--length-m", "0", "-o", tmp_path / "demo"], tmp_path, names="--length-m")
    assert "internal error" not in line and not (tmp_path / "demo").exists()


def test_check_uses_the_check_section_of_the_config(tmp_path: Path, assets: dict[str, Path]) -> None:
    """`check --config`: a 'narrow lane' limit above the demo road's 3.5 m lanes makes every lane narrow."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("check:\n  narrow_lane_m: 5.0\n  zero_width_m: 0.05\n")
    plain, strict = tmp_path / "plain.json", tmp_path / "strict.json"
    assert runner.invoke(app, ["check", str(assets["map"]), "--json", str(plain)]).exit_code == 0
    assert runner.invoke(app, ["check", str(assets["map"]), "--json", str(strict), "-c", str(cfg)]).exit_code == 0
    assert json.loads(plain.read_text())["lane_widths"]["narrow"] == []
    assert json.loads(strict.read_text())["lane_widths"]["narrow"]


def test_a_users_folder_named_like_ours_is_never_cleaned(tmp_path: Path, assets: dict[str, Path]) -> None:
    """Only hidden names of ours count beside the outputs: `lidar2xodr-999999-runs/` is the user's."""
    users = tmp_path / f"lidar2xodr-{2**22 + 12345}-my-runs"
    users.mkdir()
    (users / "notes.txt").write_text("mine")
    res = runner.invoke(app, ["compare", str(assets["map"]), str(assets["map"]), "--json", str(tmp_path / "m.json")])
    assert res.exit_code == 0
    assert (users / "notes.txt").read_text() == "mine"


def test_a_report_from_before_markers_is_updated_file_by_file(tmp_path: Path) -> None:
    """An unmarked report of ours (older version) is ours: only our files are replaced, none is deleted."""
    from lidar2xodr.fileio import atomic_dir

    rep = tmp_path / "report"
    rep.mkdir()
    (rep / "index.html").write_text("<!doctype html><html><head><title>lidar2xodr report</title></head></html>")
    (rep / "old_picture.png").write_bytes(b"png")
    with atomic_dir(rep) as tmp:
        (tmp / "index.html").write_text("new")
    assert (rep / "index.html").read_text() == "new" and (rep / "old_picture.png").read_bytes() == b"png"
    assert (rep / ".lidar2xodr-report").is_file()


# --------------------------------------------------------------------------------------------
# each item through commands and options that 6649d36 (the code the issue was filed on) already had,
# so that these fail there on the behaviour itself, not on a new command (`config --show`) or helper


@pytest.mark.parametrize("case", ["yaml_markup", "yaml_multiline", "negative_radius", "nan", "negative_workers"])
def test_bad_config_given_to_compare_is_one_line(case: str, tmp_path: Path, assets: dict[str, Path]) -> None:
    """Items 3, 9, 11: `[/data/run1]` in a YAML error crashed the printer; a tab gave a multi-line error;
    `search_radius_m: -1`, `.nan` and `workers: -3` were accepted."""
    text, field = BAD_CONFIGS[case]
    cfg = tmp_path / "my config.yaml"
    cfg.write_text(text)
    line = hostile(["compare", assets["map"], assets["map"], "-c", cfg], tmp_path, names=cfg)
    assert field in line


def test_markup_in_a_config_path_and_its_error_is_printed_verbatim(tmp_path: Path, assets: dict[str, Path]) -> None:
    """Item 3 through `compare -c`: the folder `[/data/run1]`, the file `run[left].yaml`, the YAML text `[time`."""
    folder = tmp_path / "[/data/run1]"
    folder.mkdir(parents=True)
    cfg = folder / "run[left].yaml"
    cfg.write_text("markings: [time\n")
    line = hostile(["compare", assets["map"], assets["map"], "-c", cfg], tmp_path)
    assert "[/data/run1]/run[left].yaml" in line and "[time" in line


def _negative_width_map(path: Path, minor: int) -> Path:
    """One straight 200 m road; lane -2 narrows by 0.05 m/m from s = 120 and is -0.5 m wide at its end."""
    path.write_text(
        f'<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header revMajor="1" revMinor="{minor}" name="t" '
        'version="1" date="2024-01-01T00:00:00"/><road id="1" length="200.0" junction="-1" rule="RHT">'
        '<planView><geometry s="0" x="0" y="0" hdg="0" length="200.0"><line/></geometry></planView>'
        '<lanes><laneSection s="0"><center><lane id="0" type="none" level="false"/></center><right>'
        '<lane id="-1" type="driving" level="false"><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane>'
        '<lane id="-2" type="driving" level="false"><width sOffset="0" a="3.5" b="0" c="0" d="0"/>'
        '<width sOffset="120" a="3.5" b="-0.05" c="0" d="0"/></lane></right></laneSection></lanes></road>'
        "</OpenDRIVE>\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("minor", [6, 8])
def test_negative_lane_width_is_refused_by_simulate_and_an_error_of_check(minor: int, tmp_path: Path) -> None:
    """Item 9: a map with a negative lane width passed `simulate` and `check` (1.6 and 1.8 headers)."""
    from lidar2xodr.check import find_qc_venv
    from lidar2xodr.errors import InputError

    bad = _negative_width_map(tmp_path / "neg.xodr", minor)
    line = hostile(["simulate", bad, tmp_path / "drive"], tmp_path, names=bad)
    assert "road 1 lane -2" in line and "-0.500" in line
    try:
        find_qc_venv()
    except InputError as exc:
        pytest.skip(f"ASAM checker environment missing: {exc}")
    verdict = tmp_path / "verdict.json"
    res = runner.invoke(app, ["check", str(bad), "--json", str(verdict)])
    assert res.exit_code == 1, res.output
    result = json.loads(verdict.read_text())
    assert result["ok"] is False and any("negative lane width" in r for r in result["reasons"]), result["reasons"]


@pytest.mark.parametrize("case", ["bad objects.csv", "--keep-intermediate onto a file"])
def test_a_failed_build_leaves_no_map(case: str, tmp_path: Path, assets: dict[str, Path]) -> None:
    """Item 10 alone (no line counting): the build fails with exit 2 and no map.xodr appears."""
    drive, out = tmp_path / "drive", tmp_path / "out"
    shutil.copytree(assets["drive"], drive)
    extra: list[str] = []
    if case == "bad objects.csv":
        (drive / "objects.csv").write_text("time,id,class,x\n0.0,1,car,[oops]\n")
        extra = ["--scenario", str(out / "map.xosc")]
    else:
        (tmp_path / "keep").write_text("the user's")
        extra = ["--keep-intermediate", str(tmp_path / "keep")]
    res = runner.invoke(app, ["build", str(drive), "-o", str(out / "map.xodr"), *extra])
    assert res.exit_code == 2, res.stdout + res.stderr
    assert not (out / "map.xodr").exists() and not (out / "map.xosc").exists()
    assert case == "bad objects.csv" or (tmp_path / "keep").read_text() == "the user's"


def test_sigkill_of_the_build_during_extraction_takes_the_workers_along(tmp_path: Path,
                                                                         assets: dict[str, Path]) -> None:
    """Item 6: killing the main process (SIGKILL, no clean-up of ours runs) left the extraction's workers running."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("extraction:\n  workers: 2\n")
    proc = subprocess.Popen([sys.executable, "-m", "lidar2xodr.cli", "build", str(assets["drive"]), "-o",
                             str(tmp_path / "out" / "map.xodr"), "-c", str(cfg)], env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        if not _wait(lambda: len(_descendants(proc.pid)) >= 2, 60):
            pytest.fail("the build never started its workers")
        workers = _descendants(proc.pid)
        proc.kill()
        proc.wait(timeout=10)
        assert _wait(lambda: not any(_alive(k) for k in workers), 10), "a worker outlived the killed build"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


def test_a_sigkilled_builds_leftovers_are_cleaned_by_the_next_run(tmp_path: Path, assets: dict[str, Path]) -> None:
    """Item 6 without our temp-name format: whatever a build killed during the map check leaves beside the
    map and in the temporary folder (its own TMPDIR here) is gone after the next run that writes there."""
    tmp, out = tmp_path / "tmp", tmp_path / "out"
    tmp.mkdir()
    out.mkdir()
    (out / "map.xodr").write_text("the map of an earlier build")
    env = {**_env(), "TMPDIR": str(tmp)}
    proc = subprocess.Popen([sys.executable, "-m", "lidar2xodr.cli", "build", str(assets["drive"]), "-o",
                             str(out / "map.xodr")], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        if not _wait(lambda: any("qc" in Path(f"/proc/{k}/cmdline").read_text(errors="ignore")
                                 for k in _descendants(proc.pid) if Path(f"/proc/{k}/cmdline").exists()), 60):
            pytest.fail("the build never started its checker")
        proc.kill()
        proc.wait(timeout=10)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert (out / "map.xodr").read_text() == "the map of an earlier build"
    left = [p for p in [*out.iterdir(), *tmp.iterdir()] if p != out / "map.xodr"]
    assert left, "the killed build left nothing (was the checker running?)"
    rerun = subprocess.run([sys.executable, "-m", "lidar2xodr.cli", "compare", str(assets["map"]), str(assets["map"]),
                            "--json", str(out / "m.json")], env=env, capture_output=True, text=True, timeout=120)
    assert rerun.returncode == 0, rerun.stderr
    assert sorted(p.name for p in out.iterdir()) == ["m.json", "map.xodr"]
    assert not any(p.exists() for p in left), left


@pytest.mark.parametrize("where", ["procfs", "read-only"])
def test_build_onto_procfs_or_a_read_only_folder_is_exit_2(where: str, tmp_path: Path,
                                                          assets: dict[str, Path]) -> None:
    """Item 8 through `build` (its temporary folder beside the map was an internal error, exit 3)."""
    if where == "procfs":
        target = Path("/proc/m.xodr")
        hostile(["build", assets["drive"], "-o", target], tmp_path, names=target)
        return
    with tmpfs(tmp_path / "ro", "ro,size=64k") as ro:
        target = ro / "m.xodr"
        line = hostile(["build", assets["drive"], "-o", target], tmp_path, names=target)
        assert "read-only" in line


@pytest.mark.parametrize("kind", ["device", "pipe"])
def test_an_output_onto_a_device_or_pipe_is_refused_and_left_as_it_is(kind: str, tmp_path: Path,
                                                                      assets: dict[str, Path]) -> None:
    """`--json /dev/null` as root replaced the null device with a regular file (the rename of an atomic
    write); a device, pipe or socket as an output file is exit 2 and stays what it was."""
    import stat

    target = tmp_path / f"out-{kind}"
    if kind == "pipe":
        os.mkfifo(target)
    else:
        try:
            os.mknod(target, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # a second /dev/null
        except PermissionError:
            pytest.skip("making a device node needs root")
    hostile(["compare", assets["map"], assets["map"], "--json", target], tmp_path, names=target)
    mode = target.lstat().st_mode
    assert stat.S_ISFIFO(mode) if kind == "pipe" else stat.S_ISCHR(mode)


def test_what_a_library_prints_while_a_sigterm_unwinds_it_is_not_shown(capsys: pytest.CaptureFixture[str]) -> None:
    """CI: the SIGTERM hit `check` while scipy was executing generated code; scipy's decorator printed
    "Error in generated code:" and the function's source before re-raising, so the user saw four lines
    instead of one. What is written to stderr after the signal is dropped; the command's own line stays."""
    import typer

    from lidar2xodr.cli import _clean_errors

    def command() -> None:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        except BaseException:
            print("Error in generated code:", file=sys.stderr)
            print("def convex_hull_plot_2d(hull, ax):", file=sys.stderr)
            raise

    with pytest.raises(typer.Exit) as stop:
        _clean_errors(command)()
    assert stop.value.exit_code == 143
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "terminated" in err[0], err
    print("after the command", file=sys.stderr)
    assert "after the command" in capsys.readouterr().err
