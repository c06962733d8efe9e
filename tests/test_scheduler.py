"""The per-scan work on Dask (`--scheduler`): the same bytes as one process, and clear errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_extraction import make_drive, write_drive

from lidar2xodr.config import ExtractionConfig
from lidar2xodr.datasets import open_dataset
from lidar2xodr.extraction import extract_markings

CLI = [sys.executable, "-m", "lidar2xodr.cli"]
SIDE = (".ply", ".origin.json", ".planes.csv", ".trajectory.csv")


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    return write_drive(make_drive(n_scans=24, n_ground=4000, seed=7), tmp_path_factory.mktemp("dask") / "d")


def _extract(drive: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, "extract", str(drive), "-o", str(out), *extra], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "COLUMNS": "200"})


def test_extract_on_a_local_dask_cluster_writes_the_same_bytes_as_one_process(drive: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "one.yaml"
    cfg.write_text("extraction:\n  workers: 1\n")
    one = _extract(drive, tmp_path / "one.ply", "--config", str(cfg))
    two = _extract(drive, tmp_path / "dask.ply", "--scheduler", "local")
    assert one.returncode == 0 and two.returncode == 0, one.stderr + two.stderr
    assert two.stderr.strip() == "", two.stderr  # no Dask log lines in the user's terminal
    for ext in SIDE:
        assert (tmp_path / f"dask{ext}").read_bytes() == (tmp_path / f"one{ext}").read_bytes(), ext
    assert (tmp_path / "one.ply").stat().st_size > 10_000


def test_an_existing_cluster_by_its_address_gives_the_same_cloud(drive: Path) -> None:
    from distributed import LocalCluster

    one = extract_markings(open_dataset(drive), ExtractionConfig(workers=1))
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        cfg = ExtractionConfig(workers=2, scheduler=cluster.scheduler_address)
        assert cfg.scheduler.startswith("tcp://")
        far = extract_markings(open_dataset(drive), cfg)
    assert len(one.xyz) > 300
    assert np.array_equal(one.xyz, far.xyz) and np.array_equal(one.time, far.time)
    assert np.array_equal(one.intensity, far.intensity) and np.array_equal(one.scan_index, far.scan_index)


@pytest.mark.parametrize(("value", "message"), [
    ("foo", "--scheduler: scheduler must be 'local' or a Dask address such as tcp://host:8786, not 'foo'"),
    ("tcp://127.0.0.1:9", "tcp://127.0.0.1:9: cannot reach the Dask scheduler"),
])
def test_a_bad_scheduler_is_one_line_and_nothing_is_written(drive: Path, tmp_path: Path, value: str,
                                                            message: str) -> None:
    proc = _extract(drive, tmp_path / "m.ply", "--scheduler", value)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr and list(tmp_path.iterdir()) == []


def test_a_scheduler_in_the_configuration_is_validated(tmp_path: Path) -> None:
    from lidar2xodr.config import Config
    from lidar2xodr.errors import InputError

    cfg = tmp_path / "c.yaml"
    cfg.write_text("extraction:\n  scheduler: localhost\n")
    with pytest.raises(InputError, match="scheduler must be 'local' or a Dask address"):
        Config.load(cfg)
    cfg.write_text("extraction:\n  scheduler: tls://10.0.0.1:8786\n")
    assert Config.load(cfg).extraction.scheduler == "tls://10.0.0.1:8786"
