"""The locks hold every pin of pyproject.toml and requirements-qc.txt: `make lock` was run after a change."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _pins(lines: list[str]) -> dict[str, str]:
    """name -> version of every `name[extras]==version` requirement."""
    out = {}
    for line in lines:
        m = re.match(r"^\s*([A-Za-z0-9_.-]+)(\[[^\]]*\])?==([^\s;#]+)", line)
        if m:
            out[_norm(m.group(1))] = m.group(3)
    return out


@pytest.mark.parametrize(("sources", "lock"), [(["pyproject.toml"], "requirements.lock"),
                                               (["requirements-qc.txt"], "requirements-qc.lock")])
def test_lock_holds_every_pin(sources: list[str], lock: str) -> None:
    wanted: dict[str, str] = {}
    for src in sources:
        if src == "pyproject.toml":
            project = tomllib.loads((ROOT / src).read_text())["project"]
            wanted |= _pins(project["dependencies"] + project["optional-dependencies"]["dev"])
        else:
            wanted |= _pins((ROOT / src).read_text().splitlines())
    locked = _pins((ROOT / lock).read_text().splitlines())
    assert wanted, f"no pins found in {sources}"
    differ = {name: (version, locked.get(name)) for name, version in wanted.items() if locked.get(name) != version}
    assert not differ, f"{lock} is stale (run `make lock`): wanted vs locked {differ}"
    for name in ("click", "plotly", "lanelet2", "carla", "eclipse-sumo", "hypothesis", "roadgen"):
        assert lock != "requirements.lock" or name in locked, name
