"""Work run beside the build's one-core stages (`scheduler.in_background`): its value or its error
comes back as if it had been called in place, and a build that stops early leaves no process behind."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from lidar2xodr.errors import InputError
from lidar2xodr.scheduler import in_background


def _value(n: int, scale: float) -> dict[str, np.ndarray]:
    return {"x": np.arange(n) * scale, "pid": np.array([os.getpid()])}


def _bad_input(where: str) -> None:
    raise InputError(where, "no object tracks found")


def _bug() -> None:
    raise ValueError("a bug")


def _killed() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _wait_forever(pid_file: Path) -> None:
    pid_file.write_text(str(os.getpid()))
    time.sleep(120)


def test_the_value_comes_back_from_another_process() -> None:
    with in_background(_value, 200_000, 0.5) as result:
        got = result()
    assert np.array_equal(got["x"], np.arange(200_000) * 0.5)
    assert int(got["pid"][0]) != os.getpid()


def test_an_input_error_keeps_its_file_and_problem() -> None:
    with in_background(_bad_input, "drive/objects.csv") as result, pytest.raises(InputError) as exc:
        result()
    assert exc.value.where == "drive/objects.csv" and exc.value.problem == "no object tracks found"


def test_a_bug_or_a_killed_process_is_an_error_that_names_it() -> None:
    with in_background(_bug) as result, pytest.raises(RuntimeError, match="ValueError: a bug"):
        result()
    with in_background(_killed) as result, pytest.raises(RuntimeError, match="without a result"):
        result()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split()[2] != "Z"


def test_leaving_without_the_result_stops_the_process(tmp_path: Path) -> None:
    pid_file = tmp_path / "pid"
    with pytest.raises(KeyError), in_background(_wait_forever, pid_file):
        for _ in range(200):
            if pid_file.exists() and pid_file.read_text():
                break
            time.sleep(0.05)
        pid = int(pid_file.read_text())
        assert _alive(pid)
        raise KeyError("the stage failed")
    assert not _alive(pid)
