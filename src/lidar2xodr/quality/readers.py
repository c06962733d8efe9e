"""Independent readers that load a map as its users would: SUMO netconvert and pyxodr (CARLA: carla_reader.py).

Each returns {"available": False, "note": ...} when the reader is not installed, else a dict with
`reader`, `version`, `warnings`, `errors` (verbatim) and `ok` (no warning, no error). Their verdicts
are reported by `check`, never part of its verdict: a reader's limits are not the file's fault.

Which netconvert: an explicit `SUMO_HOME` that exists wins (its `bin/netconvert`, else the one on
PATH, the Debian layout with the data in /usr/share/sumo); otherwise the PyPI package `eclipse-sumo`
pinned in the lock (its SUMO_HOME is the package folder, found without importing it, because its
`__init__` writes SUMO_HOME into the environment); otherwise a netconvert on PATH with
`SUMO_HOME_DEFAULT`. A SUMO_HOME naming a missing folder is reported in `note` and not used.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import io
import json
import math
import os
import re
import shutil
import subprocess
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from lxml import etree

from lidar2xodr.fileio import temp_dir
from lidar2xodr.lifetime import run_child

READER_TIMEOUT_S = 600
"""A reader that has not finished a map within this time is reported as failed (SUMO needs ~10 s for Town04)."""
PYXODR_RESOLUTION_M = 0.5
"""Sampling step of pyxodr's lines: fine enough to compare reference lines to the millimetre after projection."""
SUMO_HOME_DEFAULT = Path("/usr/share/sumo")
"""Where Debian's sumo-tools put SUMO's data, used for a netconvert found on PATH without SUMO_HOME."""
RESULT_PREFIX = "lidar2xodr-reader-result "
"""Marks the worker's JSON line among whatever a reader's C++ code prints to stdout."""
_TYPES_FILE = Path("data") / "typemap" / "opendriveNetconvert.typ.xml"


@dataclass(frozen=True)
class Netconvert:
    """A netconvert executable, the SUMO_HOME its data lives in, and how it was chosen."""

    exe: Path
    sumo_home: Path | None
    source: str
    note: str = ""

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        if self.sumo_home is not None:
            env["SUMO_HOME"] = str(self.sumo_home)
            proj = self.sumo_home / "data" / "proj"
            if proj.is_dir() and not env.get("PROJ_LIB") and not env.get("PROJ_DATA"):
                env["PROJ_DATA"] = env["PROJ_LIB"] = str(proj)
        return env


def _pypi_sumo_home() -> Path | None:
    spec = importlib.util.find_spec("sumo")
    if spec is None or spec.origin is None:
        return None
    home = Path(spec.origin).parent
    return home if (home / "bin" / "netconvert").is_file() else None


def find_netconvert() -> Netconvert | None:
    """The netconvert `check` uses (see the module docstring for the order); None when there is none."""
    note = ""
    explicit = os.environ.get("SUMO_HOME")
    if explicit:
        home = Path(explicit)
        if home.is_dir():
            exe = home / "bin" / "netconvert"
            found = str(exe) if exe.is_file() else shutil.which("netconvert")
            if found:
                return Netconvert(Path(found), home, "SUMO_HOME")
        note = f"SUMO_HOME={explicit} does not exist, not used; "
    home = _pypi_sumo_home()
    if home is not None:
        return Netconvert(home / "bin" / "netconvert", home, "PyPI eclipse-sumo", note)
    found = shutil.which("netconvert")
    if found:
        return Netconvert(Path(found), SUMO_HOME_DEFAULT if SUMO_HOME_DEFAULT.is_dir() else None, "PATH", note)
    return None


def run_netconvert(path: Path) -> dict[str, Any]:
    """SUMO netconvert reads the map as a user would (`--opendrive-files MAP`, default options).

    Every "Warning:" and "Error:" line is kept verbatim (`--aggregate-warnings -1`, so none is folded
    into a count); the built network's edges, lanes and connections show that something was read.
    """
    nc = find_netconvert()
    if nc is None:
        return {"available": False, "note": "SUMO netconvert not installed (PyPI eclipse-sumo, see the lock file): "
                                            "not checked"}
    env = nc.env()
    out: dict[str, Any] = {"available": True, "reader": "SUMO netconvert", "executable": str(nc.exe),
                           "sumo_home": str(nc.sumo_home) if nc.sumo_home else None, "source": nc.source}
    if nc.note:
        out["note"] = nc.note.rstrip("; ")
    try:
        head = run_child([str(nc.exe), "--version"], env=env, timeout=60)
        number = re.search(r"\d+\.\d+(\.\d+)?", (head.stdout.strip().splitlines() or [""])[0])
        out["version"] = number.group(0) if number else "?"
    except (OSError, subprocess.TimeoutExpired):
        out["version"] = "?"
    if nc.sumo_home is None or not (nc.sumo_home / _TYPES_FILE).is_file():
        where = nc.sumo_home or "(no SUMO_HOME)"
        return {**out, "ok": False, "returncode": None, "warnings": [],
                "errors": [f"SUMO's data is missing: no {_TYPES_FILE} in {where}"]}
    with temp_dir(kind="sumo") as tmp:
        net = Path(tmp) / "map.net.xml"
        cmd = [str(nc.exe), "--opendrive-files", str(path.resolve()), "--aggregate-warnings", "-1", "-o", str(net)]
        try:
            proc = run_child(cmd, env=env, cwd=tmp, timeout=READER_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            return {**out, "ok": False, "returncode": None, "warnings": [],
                    "errors": [f"netconvert did not finish within {READER_TIMEOUT_S} s"]}
        except OSError as exc:
            return {**out, "ok": False, "returncode": None, "warnings": [],
                    "errors": [f"cannot start netconvert: {exc}"]}
        lines = [ln.strip() for ln in (proc.stdout + "\n" + proc.stderr).splitlines()]
        out.update(returncode=proc.returncode, warnings=[ln for ln in lines if ln.startswith("Warning:")],
                   errors=[ln for ln in lines if ln.startswith("Error:")], edges=0, lanes=0, connections=0)
        if net.is_file():
            root = etree.parse(str(net)).getroot()
            edges = [e for e in root.iter("edge") if e.get("function") != "internal"]
            out.update(edges=len(edges), lanes=sum(len(e.findall("lane")) for e in edges),
                       connections=sum(not c.get("from", ":").startswith(":") for c in root.iter("connection")))
    out["ok"] = out["returncode"] == 0 and not out["warnings"] and not out["errors"]
    return out


def polyline_distance(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance of each point to a polyline (the segments beside its nearest vertex)."""
    from scipy.spatial import cKDTree

    _, i = cKDTree(poly).query(points)
    best = np.full(len(points), np.inf)
    for a, b in ((np.maximum(i - 1, 0), i), (i, np.minimum(i + 1, len(poly) - 1))):
        seg = poly[b] - poly[a]
        u = np.clip(np.sum((points - poly[a]) * seg, axis=1) / np.maximum(np.sum(seg * seg, axis=1), 1e-18), 0, 1)
        best = np.minimum(best, np.linalg.norm(points - (poly[a] + u[:, None] * seg), axis=1))
    return best


def run_pyxodr(path: Path, odr: Any | None = None) -> dict[str, Any]:
    """pyxodr (an independent Python reader) loads the map and evaluates everything a user would touch.

    Every road (connecting roads included): reference line, lane offset, heights, every lane's
    borders, centre and traffic-flow successors; every junction's incoming and outgoing roads (a
    missing road is an error). Python warnings and anything printed are kept as warnings, exceptions
    as errors. With the project's reader's `odr`, `max_reference_dev_m` is the largest distance of
    pyxodr's reference points from ours (the two readers agree on the geometry).
    """
    try:
        from pyxodr.road_objects.network import RoadNetwork
    except ImportError:
        return {"available": False, "note": "pyxodr not installed: not checked"}
    out: dict[str, Any] = {"available": True, "reader": "pyxodr", "version": importlib.metadata.version("pyxodr"),
                           "warnings": [], "errors": []}
    printed = io.StringIO()
    refs: dict[str, np.ndarray] = {}
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(printed), \
            contextlib.redirect_stderr(printed):
        warnings.simplefilter("always")
        try:
            net = RoadNetwork(str(path), resolution=PYXODR_RESOLUTION_M)
            roads = net.get_roads(include_connecting_roads=True)
            for road in roads:
                refs[str(road.id)] = np.asarray(road.reference_line)[:, :2]
                _ = road.lane_offset_line, road.z_coordinates
                for section in road.lane_sections:
                    for lane in section.lanes:
                        _ = lane.boundary_line, lane.centre_line, lane.traffic_flow_successors
            for junction in net.get_junctions():
                _ = junction.get_incoming_road_ids(), junction.get_outgoing_road_ids(net.road_ids_to_object)
            out.update(roads=len(roads), junctions=len(net.get_junctions()))
        except Exception as exc:  # any failure of the reader is its verdict on the file
            out["errors"].append(f"{type(exc).__name__}: {exc}")
    out["warnings"] += [f"{w.category.__name__}: {w.message}" for w in caught]
    out["warnings"] += [ln for ln in printed.getvalue().splitlines() if ln.strip()]
    if odr is not None and refs and not out["errors"]:
        dev = 0.0
        for rid, pts in refs.items():
            road = odr.roads.get(rid)
            if road is None or road.length <= 0:
                continue
            s = np.linspace(0.0, road.length, max(2, math.ceil(road.length / 0.05) + 1))
            x, y, _ = road.reference(s)
            dev = max(dev, float(polyline_distance(pts, np.column_stack([x, y])).max()))
        out["max_reference_dev_m"] = dev
    out["ok"] = not out["warnings"] and not out["errors"]
    return out


def run_in_subprocess(reader: str, path: Path, timeout_s: float = READER_TIMEOUT_S) -> dict[str, Any]:
    """Run a Python reader (`pyxodr`, `carla` or `lanelet2`) on the map in a child process and return its result.

    A child of its own keeps a reader that aborts or hangs (CARLA's parser calls abort() on some
    maps) from taking `check` down, lets the readers run side by side, and keeps pyxodr's printing
    and warnings out of this process. A crash is the reader's finding: an error naming the signal.
    """
    src = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH")) if p))
    cmd = [sys.executable, "-m", "lidar2xodr.quality.worker", reader, str(Path(path).resolve())]
    names = {"pyxodr": "pyxodr", "carla": "CARLA", "lanelet2": "lanelet2"}
    try:
        version = importlib.metadata.version(reader)
    except importlib.metadata.PackageNotFoundError:
        version = "?"
    try:
        proc = run_child(cmd, env=env, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"available": True, "reader": names[reader], "version": version, "ok": False, "warnings": [],
                "errors": [f"{names[reader]} did not finish within {timeout_s:.0f} s"]}
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_PREFIX):
            return json.loads(line[len(RESULT_PREFIX):])
    how = f"signal {-proc.returncode}" if proc.returncode < 0 else f"exit code {proc.returncode}"
    tail = [ln for ln in proc.stderr.strip().splitlines() if ln.strip() and not ln.startswith("WARNING:")][-1:]
    return {"available": True, "reader": names[reader], "version": version, "ok": False, "warnings": [],
            "errors": [f"{names[reader]} crashed on the map ({how})" + (f": {tail[0]}" if tail else "")]}
