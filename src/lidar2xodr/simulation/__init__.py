"""The drive simulator: any OpenDRIVE map becomes a LiDAR test drive with ground truth.

`simulate(map_path, out_dir, opts)` plans a route, drives the ego and traffic along it, casts every
LiDAR ray from the sensor pose at its own time, and writes the drive directory (see writer.py).
Same map, options and seed give the same bytes: every random choice draws from a generator
seeded with (seed, purpose), and times count from a fixed origin (T0), never the wall clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from rich.console import Console

from lidar2xodr.errors import OutputError

T0 = 1_700_000_000.0
"""Absolute time of the drive start (s, Unix epoch, 2023-11-14T22:13:20Z): fixed so outputs repeat."""


class SimOptions(BaseModel):
    """Options of one simulated drive (the `simulate` command's flags)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    start_road: str | None = Field(None, description="first road of the route; default: the longest chain")
    speed_kmh: float = Field(110.0, gt=5.0, le=250.0, description="mean desired ego speed")
    length_m: float | None = Field(None, gt=0.0, le=2_000_000.0,
                                   description="drive length; default one pass over the route")
    sensor: Literal["livox-horizon", "pandar64"] = "livox-horizon"
    traffic: Literal["none", "low", "mid", "high"] = "mid"
    gnss_noise_m: float = Field(0.05, ge=0.0, le=20.0, description="per-axis horizontal GNSS sigma")
    gnss_outage: bool = False
    gnss_bias_m: float = Field(0.0, ge=0.0, le=20.0, description="constant horizontal GNSS offset of this length for "
                               "the whole drive, its direction drawn from the seed (GNSS without corrections: a "
                               "metre or two, different every day); listed in truth/route.json")
    seed: int = 0
    rosbag: bool = False
    preview: bool = False
    roadside: bool = Field(False, description="terrain, vegetation, signs and noise barriers beside the road "
                           "(roadside.py): what LiDAR odometry needs to find the forward motion")


@dataclass
class SimSummary:
    out_dir: Path
    scans: int
    points: int
    length_m: float
    duration_s: float
    mean_speed_kmh: float
    roads: list[str]
    passes: int
    vehicles: int
    lane_changes: int
    gnss_outages: list[tuple[float, float]] = field(default_factory=list)
    preview: Path | None = None


def _stream(seed: int, purpose: int) -> np.random.Generator:
    return np.random.default_rng([seed & 0xFFFFFFFF, purpose])


def _check_target(out_dir: Path) -> None:
    """Refuse to replace anything that is not an earlier drive directory."""
    if out_dir.is_symlink() or (out_dir.exists() and not out_dir.is_dir()):
        raise OutputError(out_dir, "exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        meta = out_dir / "meta.yaml"
        if not (meta.is_file() and "format: lidar2xodr-drive" in meta.read_text(encoding="utf-8", errors="replace")):
            raise OutputError(out_dir, "exists and is not a drive directory; refusing to replace it")


def simulate(map_path: str | Path, out_dir: str | Path, opts: SimOptions | None = None,
             console: Console | None = None) -> SimSummary:
    """Simulate a drive on `map_path` and write the drive directory `out_dir` atomically.

    Bad input raises InputError, an unwritable or foreign `out_dir` OutputError; nothing is left
    behind either way. `console` gets a progress bar over the scans.
    """
    from lidar2xodr.simulation.drive import run

    opts = opts or SimOptions()
    map_path, out_dir = Path(map_path), Path(out_dir)
    _check_target(out_dir)
    return run(map_path, out_dir, opts, console)
