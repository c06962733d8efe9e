"""`lidar2xodr check`: what a simulator user needs to know before loading a map or a scenario.

Three parts:

* `asam`: the official ASAM quality checker (asam-qc-opendrive for .xodr, asam-qc-openscenarioxml for
  .xosc) run as a subprocess from its own virtual environment (it pins numpy<2). The environment is
  `$LIDAR2XODR_QC_VENV` or `<project root>/.venv-qc` (project root = the parent of src/). Issue levels
  follow the ASAM result format: 1 = error, 2 = warning, 3 = information. Checkers the tool skips
  (e.g. every rule newer than the file's OpenDRIVE version: `checkers_skipped_for_version`) are
  counted and pointed out, not hidden, and checkers that
  crash are listed as issues of level "internal" without failing the verdict (the rule was not
  evaluated, the file is not proven wrong).
* `continuity` (.xodr only; the ASAM checker does not test it): per road, the largest position leap (m)
  and heading kink (rad) between the end of each plan-view geometry and the start of the next, and for
  every paramPoly3 the difference between its declared length and the arc length of the curve it
  describes (integrated numerically; for pRange=normalized the declared length is the only arc-length
  information a reader has, so a mismatch distorts every s coordinate on that piece). Also the largest
  gap between the borders of lanes linked across a junction (`max_junction_gap_m`): for every laneLink
  the two borders of its `from` lane at the incoming road's end that touches the junction against those
  of its `to` lane at the connecting (linked) road's contact point, in 3D (reported, not judged:
  overlap zones of real maps may be wide on purpose).

* `readers` (.xodr; `readers=False` skips them): independent readers load the map as a user
  would (quality/readers.py). `netconvert`: SUMO's converter with its default options (the
  PyPI eclipse-sumo of the lock unless SUMO_HOME says otherwise), every "Warning:"/"Error:" line
  verbatim and the edges/lanes/connections it built; absent netconvert gives
  {"available": False, "note": ...}. `pyxodr`: the map loaded and
  everything evaluated (references, lane borders, successors, junction roads); Python warnings and
  printed lines are warnings, exceptions errors; `max_reference_dev_m` is how far its reference
  points lie from ours. `carla`: CARLA's own parser (PyPI carla, offline), the map loaded, a
  waypoint on every driving lane, a `wp.next()` walk along every lane through sections and links,
  and its topology against the map's road links (quality/carla_reader.py). `lanelet2`: the map
  exported to Lanelet2 and loaded back, `checkValidity` clean, every lane link in travel direction
  a `following` of lanelet2's routing graph (lanelet2_reader.py). pyxodr, CARLA and lanelet2 run
  in child processes: a reader that crashes (CARLA segfaults on a lane link to a missing lane) is
  an error of that reader, never of `check`. Reported, never part of the verdict: a reader's
  limits are not the file's fault (SUMO 1.28 warns about a lane that appears at a section change
  on a two-way road, which the standard requires to be unlinked).

* `lane_widths` (.xodr, quality/lane_widths.py): `negative` lists every lane width record whose
  cubic drops below 0 on its range (road, section, lane, s and the width there; an error);
  `zero_width` and `narrow` the stretches of driving lanes kept at width ~0 or narrower than 1 m
  (outside their tapers) for more than 30 m, `wide` those wider than 5 m for more than 30 m (warnings;
  the numbers are `CheckConfig`'s).

Verdict: `ok` is False when the ASAM checker reports at least one error, when the project's
OpenDRIVE reader cannot evaluate the geometry (`continuity.error`), a lane width record is
negative somewhere, or a leap exceeds
`LEAP_LIMIT_M` (1 mm) or a kink exceeds `KINK_LIMIT_RAD` (1 mrad), the limits issue #6 sets for
built maps. Why so strict: readers that snap to the next piece make lane borders jump by many times
the gap (a 1.4 cm gap moved borders by 30-81 cm), and a 1 mrad kink still shifts a border 11 m from
the reference line by 1.1 cm. Our own maps meet them by construction (~1e-13); of the shared
third-party maps only Town04 (1.5 mm) and the maliput test road (8.6 mrad) do not. Warnings and
paramPoly3 length mismatches are reported but do not fail the verdict.
"""

from __future__ import annotations

import math
import os
import subprocess
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from lxml import etree
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from lidar2xodr.angles import wrap_angle
from lidar2xodr.config import CheckConfig
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import temp_dir
from lidar2xodr.lifetime import children_killed_on_exit, run_child
from lidar2xodr.quality.lane_widths import lane_widths
from lidar2xodr.quality.readers import (
    find_netconvert,
    polyline_distance,
    run_in_subprocess,
    run_netconvert,
    run_pyxodr,
)

__all__ = ["check_file", "continuity", "find_netconvert", "find_qc_venv", "junction_gaps", "polyline_distance",
           "print_check", "run_asam_checker", "run_netconvert", "run_pyxodr"]

LEAP_LIMIT_M = 0.001
KINK_LIMIT_RAD = 0.001
QC_ENV_VAR = "LIDAR2XODR_QC_VENV"
QC_TIMEOUT_S = 900
ARC_STEP_M = 0.05
_LEVELS = {1: "error", 2: "warning", 3: "information"}
_CHECKERS = {".xodr": ("qc_opendrive", "xodrBundle"), ".xosc": ("qc_openscenario", "xoscBundle")}


def find_qc_venv() -> Path:
    """The virtual environment holding the ASAM checkers; InputError with a one-line fix when absent."""
    env = os.environ.get(QC_ENV_VAR)
    venv = Path(env) if env else Path(__file__).resolve().parents[2] / ".venv-qc"
    if not (venv / "bin" / "python").exists():
        raise InputError(venv, "ASAM quality checker environment not found; run `make setup` "
                         f"(or point {QC_ENV_VAR} at a venv with asam-qc-opendrive)")
    return venv


def _write_config(cfg: Path, input_file: Path, bundle: str, result: Path) -> None:
    root = etree.Element("Config")
    etree.SubElement(root, "Param", name="InputFile", value=str(input_file))
    bundle_el = etree.SubElement(root, "CheckerBundle", application=bundle)
    etree.SubElement(bundle_el, "Param", name="resultFile", value=str(result))
    cfg.write_bytes(etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True))


def _issue_message(issue: etree._Element) -> dict[str, Any]:
    level = int(issue.get("level", "1"))
    text = issue.get("description", "")
    row = None
    xpath = None
    for loc in issue.iter("Locations"):
        desc = loc.get("description", "")
        if desc and desc != text:
            text = f"{text}: {desc}" if text and not text.startswith("Issue flagging") else desc
        fl = loc.find("FileLocation")
        if row is None and fl is not None and fl.get("row") is not None:
            row = int(fl.get("row"))
        xl = loc.find("XMLLocation")
        if xpath is None and xl is not None:
            xpath = xl.get("xpath")
    out: dict[str, Any] = {"level": _LEVELS.get(level, str(level)), "rule": issue.get("ruleUID", ""),
                           "message": text}
    if row is not None:
        out["row"] = row
    if xpath is not None:
        out["xpath"] = xpath
    return out


def parse_result(xqar: Path) -> dict[str, Any]:
    """Counts and messages from an ASAM result file (.xqar)."""
    try:
        root = etree.parse(str(xqar)).getroot()
    except (OSError, etree.XMLSyntaxError) as exc:
        raise InputError(xqar, f"unreadable ASAM checker result: {exc}") from None
    issues: list[dict[str, Any]] = []
    status = {"completed": 0, "skipped": 0, "error": 0}
    skipped_for_version = 0
    for checker in root.iter("Checker"):
        st = checker.get("status", "")
        status[st] = status.get(st, 0) + 1
        skipped_for_version += st == "skipped" and checker.get("summary", "").startswith("Version")
        if st == "error":
            issues.append({"level": "internal", "rule": checker.get("checkerId", ""),
                           "message": f"checker crashed: {checker.get('summary', '')}"})
        for issue in checker.iter("Issue"):
            msg = _issue_message(issue)
            msg["checker"] = checker.get("checkerId", "")
            issues.append(msg)
    counts = {name: sum(i["level"] == name for i in issues) for name in ("error", "warning", "information")}
    return {
        "errors": counts["error"],
        "warnings": counts["warning"],
        "information": counts["information"],
        "checkers_completed": status["completed"],
        "checkers_skipped": status["skipped"],
        "checkers_failed": status["error"],
        "checkers_skipped_for_version": skipped_for_version,
        "issues": issues,
    }


def run_asam_checker(path: Path, venv: Path | None = None) -> dict[str, Any]:
    """Run the ASAM checker bundle matching the file's suffix and return its parsed result."""
    module, bundle = _CHECKERS[path.suffix.lower()]
    venv = venv or find_qc_venv()
    with temp_dir(kind="qc") as tmp:
        cfg, result = Path(tmp) / "config.xml", Path(tmp) / "result.xqar"
        checked, namespace = _plain_copy(path, Path(tmp)) if module == "qc_opendrive" else (path, None)
        _write_config(cfg, checked.resolve(), bundle, result)
        try:
            proc = run_child([str(venv / "bin" / "python"), "-m", module, "-c", str(cfg)], cwd=tmp,
                             timeout=QC_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise InputError(path, f"the ASAM checker did not finish within {QC_TIMEOUT_S} s") from None
        except OSError as exc:
            raise InputError(venv, f"cannot start the ASAM checker: {exc}") from None
        if not result.exists():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            raise InputError(path, f"the ASAM checker ({module}) failed: {tail[0]}")
        out = parse_result(result)
    out["checker"] = module
    if namespace:
        out["note"] = f"the root's namespace {namespace} was removed for the checker (its schemas declare none)"
    return out


def _plain_copy(path: Path, tmp: Path) -> tuple[Path, str | None]:
    """The map as the ASAM checker can validate it: a copy without an OpenDRIVE namespace, when it has one.

    The checker's schemas have no target namespace, so it rejects `<OpenDRIVE xmlns=...>` outright;
    the copy keeps every line where it was, so the issues' row numbers still point into the user's file.
    """
    from lidar2xodr.opendrive import OPENDRIVE_NAMESPACES, strip_namespace

    try:
        _, root = next(etree.iterparse(str(path), events=("start",)))
        namespace = etree.QName(root).namespace
    except (etree.XMLSyntaxError, OSError, StopIteration):
        return path, None
    if namespace not in OPENDRIVE_NAMESPACES:
        return path, None
    tree = etree.parse(str(path), etree.XMLParser(huge_tree=True))
    strip_namespace(tree.getroot())
    plain = tmp / path.name
    tree.write(str(plain), xml_declaration=True, encoding=tree.docinfo.encoding or "UTF-8")
    return plain, namespace


def _arc_length(geom: Any) -> float:
    """Arc length of the curve a geometry traces over ds in [0, length] (Richardson-refined polyline)."""
    n = max(16, math.ceil(geom.length / ARC_STEP_M))
    n += n % 2

    def polyline(m: int) -> float:
        ds = np.linspace(0.0, geom.length, m + 1)
        x, y, _ = geom.eval(ds)
        return float(np.hypot(np.diff(x), np.diff(y)).sum())

    fine, coarse = polyline(n), polyline(n // 2)
    return (4.0 * fine - coarse) / 3.0


def _contact_s(road: Any, junction_id: str, contact: str | None) -> float | None:
    """Station of the road end that touches the junction (the contact point when given)."""
    if contact in ("start", "end"):
        return 0.0 if contact == "start" else float(road.length)
    for link, s in ((road.successor, float(road.length)), (road.predecessor, 0.0)):
        if link is not None and link.element_type == "junction" and link.element_id == junction_id:
            return s
    return None


def _lane_border_points(road: Any, s: float, lane_id: int) -> np.ndarray:
    """World points (2, 3) of the inner and outer border of a lane at station s (NaN when it is absent)."""
    inner = lane_id - (1 if lane_id > 0 else -1)
    t = np.array([road.border_t(s, inner)[0], road.border_t(s, lane_id)[0]])
    if not np.all(np.isfinite(t)):
        return np.full((2, 3), np.nan)
    return road.to_world(np.array([s, s]), t)


def _gap(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance of two lanes' (inner, outer) border points, matched as they are or swapped."""
    return float(min(np.linalg.norm(a - b, axis=1).max(), np.linalg.norm(a - b[::-1], axis=1).max()))


def _linked_lanes(odr: Any) -> list[tuple[str, str, Any, float, int, Any, float, int]]:
    """(junction, connection, road, s, lane, other road, s, lane) of every lane link that crosses a junction.

    From each connection's laneLinks (incoming road end -> connecting road at the contact point), and
    from the lane links of every connecting road into the road it leads to or comes from (its other
    end, where no connection element names the lanes).
    """
    out = []
    for jid, junction in odr.junctions.items():
        for conn in junction.connections:
            inc, other = odr.roads.get(conn.incoming_road), odr.roads.get(conn.connecting_road)
            if inc is None or other is None or not conn.lane_links:
                continue
            s_in, s_out = _contact_s(inc, jid, None), _contact_s(other, jid, conn.contact_point)
            if s_in is not None and s_out is not None:
                out += [(jid, conn.id, inc, s_in, a, other, s_out, b) for a, b in conn.lane_links]
    for road in odr.roads.values():
        if road.junction in ("", "-1") or not road.lane_sections:
            continue
        for link, s_own, section, kind in ((road.predecessor, 0.0, road.lane_sections[0], "predecessor"),
                                           (road.successor, float(road.length), road.lane_sections[-1], "successor")):
            other = odr.roads.get(link.element_id) if link is not None and link.element_type == "road" else None
            if other is None or other.junction == road.junction:
                continue
            s_other = float(other.length) if link.contact_point == "end" else 0.0
            for lane in section.lanes.values():
                target = getattr(lane, kind)
                if lane.id != 0 and target is not None:
                    out.append((road.junction, f"road {road.id} {kind}", road, s_own, lane.id, other, s_other, target))
    return out


def junction_gaps(odr: Any) -> dict[str, Any]:
    """Largest distance between the borders of lanes linked across junctions, and where it is.

    Inner and outer borders are matched as they are or swapped, whichever fits (roads may meet
    head to head). Links naming missing roads or lanes are skipped.
    """
    worst: dict[str, Any] | None = None
    count = 0
    for jid, conn_id, road_a, s_a, lane_a, road_b, s_b, lane_b in _linked_lanes(odr):
        a = _lane_border_points(road_a, s_a, lane_a)
        b = _lane_border_points(road_b, s_b, lane_b)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            continue
        gap = _gap(a, b)
        count += 1
        if worst is None or gap > worst["value"]:
            worst = {"junction": jid, "connection": conn_id, "from": lane_a, "to": lane_b, "value": gap}
    return {"max_junction_gap_m": worst["value"] if worst else 0.0, "worst": worst, "lane_links": count}


def continuity(odr: Any) -> dict[str, Any]:
    """Largest geometry-to-geometry leap and kink, and paramPoly3 length errors, over all roads."""
    worst: dict[str, dict[str, Any]] = {}
    over: list[str] = []

    def note(key: str, value: float, road: str, index: int, s: float) -> None:
        if key not in worst or value > worst[key]["value"]:
            worst[key] = {"road": road, "geometry": index, "s": round(float(s), 4), "value": float(value)}

    for road_id, road in odr.roads.items():
        geoms = list(road.geometries)
        road_bad = False
        for i, geom in enumerate(geoms):
            if str(geom.kind).lower() == "parampoly3" and geom.length > 0:
                err = abs(_arc_length(geom) - geom.length)
                note("length", err, road_id, i, geom.s)
                note("length_rel", err / geom.length, road_id, i, geom.s)
            if i + 1 == len(geoms):
                continue
            nxt = geoms[i + 1]
            ex, ey, eh = (float(v[0]) for v in geom.eval(geom.length))
            sx, sy, sh = (float(v[0]) for v in nxt.eval(0.0))
            leap = math.hypot(sx - ex, sy - ey)
            kink = abs(wrap_angle(sh - eh))
            note("leap", leap, road_id, i, nxt.s)
            note("kink", kink, road_id, i, nxt.s)
            road_bad |= leap > LEAP_LIMIT_M or kink > KINK_LIMIT_RAD
        if road_bad:
            over.append(road_id)
    top = {k: v["value"] for k, v in worst.items()}
    gaps = junction_gaps(odr)
    if gaps["worst"] is not None:
        worst["junction_gap"] = gaps["worst"]
    return {
        "max_leap_m": top.get("leap", 0.0),
        "max_kink_rad": top.get("kink", 0.0),
        "max_length_error_m": top.get("length", 0.0),
        "max_length_error_rel": top.get("length_rel", 0.0),
        "max_junction_gap_m": gaps["max_junction_gap_m"],
        "worst": {k: worst[k] for k in sorted(worst)},
        "roads_over_limit": over,
        "leap_limit_m": LEAP_LIMIT_M,
        "kink_limit_rad": KINK_LIMIT_RAD,
    }


def check_file(path: Path, readers: bool = True, cfg: CheckConfig | None = None) -> dict[str, Any]:
    """Check an .xodr (ASAM + continuity + independent readers) or an .xosc (ASAM); the result always holds `ok`.

    The ASAM checker and the readers are child processes started together; the continuity check
    runs here meanwhile, so the whole check takes about as long as its slowest part.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _CHECKERS:
        raise InputError(path, "expected an OpenDRIVE (.xodr) or OpenSCENARIO (.xosc) file")
    if not path.is_file():
        raise InputError(path, "file not found")
    venv = find_qc_venv()
    result: dict[str, Any] = {"file": str(path), "kind": suffix[1:]}
    reasons = []
    with ThreadPoolExecutor(max_workers=5) as pool, children_killed_on_exit(pool):
        asam = pool.submit(run_asam_checker, path, venv)
        jobs: dict[str, Future] = {}
        if suffix == ".xodr" and readers:
            jobs = {"netconvert": pool.submit(run_netconvert, path),
                    "pyxodr": pool.submit(run_in_subprocess, "pyxodr", path),
                    "carla": pool.submit(run_in_subprocess, "carla", path),
                    "lanelet2": pool.submit(run_in_subprocess, "lanelet2", path)}
        if suffix == ".xodr":
            from lidar2xodr.opendrive import OpenDriveMap

            try:
                odr = OpenDriveMap.load(path)
                result["continuity"] = continuity(odr)
                result["lane_widths"] = lane_widths(odr, cfg)
            except InputError as exc:
                result["continuity"] = {"error": str(exc)}
                reasons.append(f"unreadable geometry: {exc.problem}")
        result["asam"] = asam.result()
        if jobs:
            result["readers"] = {name: job.result() for name, job in jobs.items()}
    if result["asam"]["errors"]:
        reasons.insert(0, f"{result['asam']['errors']} ASAM error(s)")
    cont = result.get("continuity", {})
    if cont.get("max_leap_m", 0.0) > LEAP_LIMIT_M:
        reasons.append(f"geometry leap {cont['max_leap_m']:.4f} m > {LEAP_LIMIT_M} m")
    if cont.get("max_kink_rad", 0.0) > KINK_LIMIT_RAD:
        reasons.append(f"heading kink {cont['max_kink_rad']:.4f} rad > {KINK_LIMIT_RAD} rad")
    negative = result.get("lane_widths", {}).get("negative", [])
    if negative:
        w = negative[0]
        reasons.append(f"{len(negative)} negative lane width record(s), first: road {w['road']} lane {w['lane']} "
                       f"{w['width']:.3f} m at s={w['s']:.2f}")
    result["reasons"] = reasons
    result["ok"] = not reasons
    return result



def print_check(result: dict[str, Any], console: Console, max_issues: int = 20) -> None:
    """A short human-readable verdict: counts, continuity, the first issues."""
    asam = result["asam"]
    table = Table(title=escape(f"check {result['file']}"), show_header=True)
    table.add_column("item")
    table.add_column("value", justify="right")
    table.add_row(f"ASAM errors ({asam['checker']})", str(asam["errors"]))
    table.add_row("ASAM warnings", str(asam["warnings"]))
    table.add_row("ASAM checkers completed / skipped / crashed",
                  f"{asam['checkers_completed']} / {asam['checkers_skipped']} / {asam['checkers_failed']}")
    cont = result.get("continuity", {})
    if "error" in cont:
        table.add_row("geometry", "unreadable")
    elif cont:
        table.add_row("largest geometry leap (m)", f"{cont['max_leap_m']:.4f}")
        table.add_row("largest heading kink (rad)", f"{cont['max_kink_rad']:.4f}")
        table.add_row("largest paramPoly3 length error (m)", f"{cont['max_length_error_m']:.4f}")
        if "junction_gap" in cont.get("worst", {}):
            table.add_row("largest lane border gap across a junction (m)", f"{cont['max_junction_gap_m']:.4f}")
    widths = result.get("lane_widths", {})
    if widths:
        table.add_row("negative lane width records", str(len(widths["negative"])))
        table.add_row("zero-width / narrow / wide driving lane stretches",
                      f"{len(widths['zero_width'])} / {len(widths['narrow'])} / {len(widths.get('wide', []))}")
    for rd in result.get("readers", {}).values():
        if not rd["available"]:
            table.add_row("reader", rd["note"])
            continue
        text = f"{len(rd['warnings'])} warning(s), {len(rd['errors'])} error(s)"
        if "max_reference_dev_m" in rd:
            text += f", reference within {rd['max_reference_dev_m']:.4f} m of ours"
        if "lanes_walked" in rd:
            text += f", {rd['lanes_walked']} of {rd['driving_lanes']} driving lanes walked"
        table.add_row(f"{rd['reader']} {rd['version']}", text)
    console.print(table)
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for issue in asam["issues"]:
        groups.setdefault((issue["level"], issue["message"]), []).append(issue)
    order = {"error": 0, "internal": 1, "warning": 2, "information": 3}
    keys = sorted(groups, key=lambda k: (order.get(k[0], 9), -len(groups[k])))
    for level, message in keys[:max_issues]:
        first = groups[(level, message)][0]
        where = f"row {first['row']}" if "row" in first else first.get("xpath", "")
        more = len(groups[(level, message)]) - 1
        where += f" and {more} more place(s)" if more else ""
        console.print(f"  {level}: {message}" + (f" ({where})" if where else ""), highlight=False, soft_wrap=True,
                      markup=False)
    if len(keys) > max_issues:
        console.print(f"  ... {len(keys) - max_issues} more kind(s) of issue (see --json)")
    for line in widths.get("warnings", [])[:max_issues]:
        console.print(f"  lane width warning: {line}", highlight=False, soft_wrap=True, markup=False)
    for rd in result.get("readers", {}).values():
        for line in (rd.get("errors", []) + rd.get("warnings", []))[:max_issues]:
            console.print(f"  {rd['reader']}: {line}", highlight=False, soft_wrap=True, markup=False)
    if asam["checkers_skipped_for_version"]:
        console.print(f"  note: {asam['checkers_skipped_for_version']} ASAM rule(s) were skipped because the file's "
                      "version predates them (OpenDRIVE >= 1.7 / OpenSCENARIO >= 1.2 gets them all)", highlight=False)
    verdict = "[bold green]OK[/]" if result["ok"] else "[bold red]NOT OK[/]: " + escape("; ".join(result["reasons"]))
    console.print(verdict)
