"""Shared fixtures. Tests that need ../shared/data skip with a clear reason when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("LIDAR2XODR_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The third-party test material (maps, the aiMotive recording, the A9 drive)."""
    if not (SHARED_DATA / "maps").is_dir():
        pytest.skip(f"third-party test data not found at {SHARED_DATA} (set LIDAR2XODR_SHARED_DATA)")
    return SHARED_DATA


def shared_maps() -> list[Path]:
    """Every shared .xodr map (empty when the data is absent), for parametrised tests."""
    return sorted((SHARED_DATA / "maps").glob("*/*.xodr")) if SHARED_DATA.is_dir() else []
