"""The verdict of a build: what was built, how good it is, and what went wrong, in a few lines.

Everything about the map is read back from the written OpenDRIVE (what a simulator gets), not from
the pipeline's intermediate model: lengths, roads, junctions, and the lanes per stretch, where a
lane counts once it is `lane_count_min_width_m` wide (the same rule as `compare`, so a taper that
opens a lane is not a lane yet). The check verdict is given per part and per reader: a reader that
failed, warned or was not installed says so, it is never shown as passed. Warnings keep their text;
the stretches of road they name (`s 120 m`, `s 0-315, 457-977 m`, in the measured carriageway's
stations) become places the map can zoom to.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidar2xodr.evaluation import DRIVING_TYPES
from lidar2xodr.opendrive import OpenDriveMap

PASS, WARN, FAIL, ABSENT = "pass", "warn", "fail", "absent"
_VERSION = re.compile(r"\d+(?:\.\d+)+")
KM_UNITS_FROM_M = 2000.0  # roads at least this long give their stretches in km, shorter ones in m
_STATIONS = re.compile(r"\bs (\d+(?:\.\d+)?(?:-\d+(?:\.\d+)?)?(?:, \d+(?:\.\d+)?(?:-\d+(?:\.\d+)?)?)*) m\b")


@dataclass
class Stretch:
    """A stretch of one road with a constant number of lanes (right: along s, left: against it)."""

    road: str
    s0: float
    s1: float
    right: int
    left: int
    kinds: tuple[str, ...] = ()  # lane types other than "driving" among the counted lanes
    road_length: float = 0.0

    def text(self) -> str:
        return f"{_stretch(self.s0, self.s1, self.road_length)}: {self.lanes_text()}"

    def lanes_text(self) -> str:
        lanes = f"{self.right} lane{'s' * (self.right != 1)}"
        if self.left:
            lanes += f" + {self.left} opposite"
        if self.kinds:
            lanes += f" ({', '.join(self.kinds)})"
        return lanes


@dataclass
class JunctionInfo:
    """A junction, where it lies and which roads meet there."""

    id: str
    xy: tuple[float, float]
    roads: list[str]
    connecting: int

    def text(self) -> str:
        via = f" via {self.connecting} connecting road{'s' * (self.connecting != 1)}" if self.connecting else ""
        return f"junction {self.id}: roads {', '.join(self.roads)}{via}"


@dataclass
class CheckRow:
    """One part of the check: its status (pass, warn, fail, absent) and a one-line detail."""

    name: str
    status: str
    detail: str
    lines: list[str] = field(default_factory=list)  # the reader's own messages, verbatim


@dataclass
class Problem:
    """A warning and the stretches of road it names, as (s0, s1) in the measured carriageway's stations."""

    text: str
    stretches: list[tuple[float, float]] = field(default_factory=list)
    points: list[tuple[float, float]] = field(default_factory=list)  # world x, y where it is


@dataclass
class Verdict:
    """The first thing the report says."""

    map_name: str
    length_m: float
    roads: list[str]
    road_lengths: dict[str, float]
    stretches: list[Stretch]
    junctions: list[JunctionInfo]
    checks: list[CheckRow]
    check_ok: bool | None
    metrics: list[tuple[str, str]]
    problems: list[Problem]

    @property
    def status(self) -> str:
        """fail: the map fails the checks; warn: it passes, but a reader or the build complains; absent: not
        checked; else pass."""
        if self.check_ok is None:
            return ABSENT
        if self.check_ok is False or any(c.status == FAIL and c.name in ("ASAM checker", "continuity")
                                         for c in self.checks):
            return FAIL
        if any(c.status in (FAIL, WARN) for c in self.checks) or self.problems:
            return WARN
        return PASS

    def built_line(self) -> str:
        """'2.97 km of road: 1 road, no junction; 0-1.59 km: 3 lanes, ...'."""
        n = len(self.roads)
        junctions = f"{len(self.junctions)} junction{'s' * (len(self.junctions) != 1)}" if self.junctions \
            else "no junction"
        return f"{_km(self.length_m)} km of road: {n} road{'s' * (n != 1)}, {junctions}"

    def lanes_lines(self) -> list[str]:
        """Lanes per stretch, one line per road ('road 1: 0-1.59 km: 3 lanes, 1.59-2.08 km: 4 lanes (entry)')."""
        out = []
        for road in self.roads:
            parts = [st.text() for st in self.stretches if st.road == road]
            head = f"road {road} ({_km(self.road_lengths[road])} km): " if len(self.roads) > 1 else ""
            out.append(head + (", ".join(parts) if parts else "no driving lane"))
        return out

    def headline(self) -> str:
        """The whole verdict in one line of plain text: built, checks, metrics, warnings."""
        checks = ", ".join(f"{c.name} {_STATUS_WORD[c.status]}" for c in self.checks) or "not checked"
        parts = [self.built_line(), f"checks: {checks}"]
        parts += [f"{k} {v.split(' (')[0]}" for k, v in self.metrics[:3]]
        if self.problems:
            parts.append(f"{len(self.problems)} warning{'s' * (len(self.problems) != 1)}")
        return " · ".join(parts)


_STATUS_WORD = {PASS: "passed", WARN: "warnings", FAIL: "FAILED", ABSENT: "not available"}


def _km(m: float) -> str:
    return f"{m / 1000.0:.2f}"


def _stretch(s0: float, s1: float, road_length: float) -> str:
    """'0.00-1.59 km' on roads of a few km, '0-41 m' on shorter ones (where 0.01 km hides a taper)."""
    if road_length >= KM_UNITS_FROM_M:
        return f"{_km(s0)}-{_km(s1)} km"
    return f"{s0:.0f}-{s1:.0f} m"


def lane_stretches(odr: OpenDriveMap, min_width: float, step: float) -> list[Stretch]:
    """Stretches of constant lane count on every road outside junctions, in road order and s."""
    out: list[Stretch] = []
    for sec in odr.sample(step):
        road = odr.roads[sec.road_id]
        if road.junction not in ("", "-1"):
            continue
        counts: dict[int, np.ndarray] = {}
        kinds: list[set[str]] = [set() for _ in sec.s]
        for side in (-1, 1):
            n = np.zeros(len(sec.s), dtype=int)
            for lid in (i for i in sec.lane_ids if i * side > 0):
                kind = sec.lane_types[lid]
                if kind.lower() not in DRIVING_TYPES:
                    continue
                wide = np.abs(sec.border_t[lid] - sec.border_t[lid - side]) >= min_width
                n += wide
                if kind != "driving":
                    for k in np.flatnonzero(wide):
                        kinds[k].add(kind)
            counts[side] = n
        for k, s in enumerate(sec.s):
            key = (int(counts[-1][k]), int(counts[1][k]), tuple(sorted(kinds[k])))
            last = out[-1] if out and out[-1].road == sec.road_id else None
            if last is not None and (last.right, last.left, last.kinds) == key:
                last.s1 = float(s)
            else:
                if last is not None:
                    last.s1 = float(s)
                out.append(Stretch(sec.road_id, float(s), float(s), *key, road_length=float(road.length)))
    return _merge_single_steps(out, step)


def _merge_single_steps(stretches: list[Stretch], step: float) -> list[Stretch]:
    """Stretches no longer than one sampling step (where two lane sections meet) join the one before."""
    out: list[Stretch] = []
    for st in stretches:
        if out and out[-1].road == st.road and (st.s1 - st.s0 <= step + 1e-9 or (
                (out[-1].right, out[-1].left, out[-1].kinds) == (st.right, st.left, st.kinds))):
            out[-1].s1 = st.s1
        elif out and out[-1].road == st.road and out[-1].s1 - out[-1].s0 <= step + 1e-9:
            out[-1] = Stretch(st.road, out[-1].s0, st.s1, st.right, st.left, st.kinds, st.road_length)
        else:
            out.append(st)
    return out


def junction_infos(odr: OpenDriveMap) -> list[JunctionInfo]:
    """Every junction with the roads that touch it (connecting roads counted, not listed)."""
    out = []
    for jid, junction in odr.junctions.items():
        ends: list[np.ndarray] = []
        roads: list[str] = []
        connecting = 0
        for road in odr.roads.values():
            if road.junction == jid:
                connecting += 1
                x, y, _ = road.reference(np.array([0.5 * road.length]))
                ends.append(np.array([x[0], y[0]]))
                continue
            for link, s in ((road.predecessor, 0.0), (road.successor, road.length)):
                if link is not None and link.element_type == "junction" and link.element_id == jid:
                    x, y, _ = road.reference(np.array([s]))
                    ends.append(np.array([x[0], y[0]]))
                    roads.append(road.id)
        roads += [c.incoming_road for c in junction.connections
                  if c.incoming_road in odr.roads and odr.roads[c.incoming_road].junction in ("", "-1")]
        xy = np.mean(ends, axis=0) if ends else np.zeros(2)
        out.append(JunctionInfo(jid, (float(xy[0]), float(xy[1])), sorted(set(roads), key=_natural), connecting))
    return out


def _natural(text: str) -> tuple[int, str]:
    return (int(text), "") if text.isdigit() else (1 << 30, text)


def check_rows(check: dict[str, Any]) -> list[CheckRow]:
    """ASAM checker, continuity and every reader, each with its own status."""
    rows: list[CheckRow] = []
    if not check:
        return rows
    asam = check.get("asam")
    if asam:
        status = FAIL if asam.get("errors") else WARN if asam.get("warnings") else PASS
        detail = f"{asam.get('errors', 0)} error(s), {asam.get('warnings', 0)} warning(s)"
        if asam.get("checkers_failed"):
            detail += f", {asam['checkers_failed']} checker(s) crashed (not evaluated)"
        if asam.get("checkers_skipped_for_version"):
            detail += f", {asam['checkers_skipped_for_version']} rule(s) skipped for the file's version"
        rows.append(CheckRow("ASAM checker", status, detail, _asam_lines(asam.get("issues", []))))
    cont = check.get("continuity")
    if cont is not None:
        if "error" in cont:
            rows.append(CheckRow("continuity", FAIL, f"geometry unreadable: {cont['error']}"))
        else:
            leap, kink = cont.get("max_leap_m", 0.0), cont.get("max_kink_rad", 0.0)
            bad = leap > cont.get("leap_limit_m", np.inf) or kink > cont.get("kink_limit_rad", np.inf)
            detail = f"largest leap {leap:.2g} m, kink {kink:.2g} rad"
            if cont.get("max_junction_gap_m"):
                detail += f", lane border gap across junctions {cont['max_junction_gap_m']:.3f} m"
            rows.append(CheckRow("continuity", FAIL if bad else PASS, detail))
    for key, rd in sorted(check.get("readers", {}).items()):
        rows.append(_reader_row(key, rd))
    return rows


def _asam_lines(issues: list[dict[str, Any]], limit: int = 8) -> list[str]:
    groups: dict[tuple[str, str], int] = {}
    for issue in issues:
        if issue.get("level") in ("error", "warning", "internal"):
            key = (issue["level"], issue.get("message", ""))
            groups[key] = groups.get(key, 0) + 1
    order = {"error": 0, "internal": 1, "warning": 2}
    keys = sorted(groups, key=lambda k: (order[k[0]], -groups[k], k[1]))
    return [f"{lvl}: {msg}" + (f" ({groups[(lvl, msg)]} places)" if groups[(lvl, msg)] > 1 else "")
            for lvl, msg in keys[:limit]]


def _reader_row(key: str, rd: dict[str, Any]) -> CheckRow:
    name = rd.get("reader", key)
    if not rd.get("available", True):
        return CheckRow(name, ABSENT, rd.get("note", "not installed: not checked"))
    errors, warnings = list(rd.get("errors", [])), list(rd.get("warnings", []))
    number = _VERSION.search(str(rd.get("version", "")))
    version = f" {number.group(0)}" if number else ""
    status = FAIL if errors else WARN if warnings else FAIL if rd.get("ok") is False else PASS
    detail = f"{len(errors)} error(s), {len(warnings)} warning(s)"
    facts = [f"{k.replace('_', ' ')} {rd[k]}" for k in ("roads", "junctions", "edges", "lanes", "connections",
                                                         "waypoints") if isinstance(rd.get(k), int)]
    if facts:
        detail += "; read " + ", ".join(facts)
    if isinstance(rd.get("max_reference_dev_m"), float):
        detail += f"; reference within {rd['max_reference_dev_m']:.2g} m of ours"
    return CheckRow(name + version, status, detail, errors + warnings)


def metric_rows(metrics: dict[str, Any] | None) -> list[tuple[str, str]]:
    """The comparison with the reference, most telling first."""
    if not metrics:
        return []
    rows: list[tuple[str, str]] = []
    b, c = metrics.get("boundaries", {}), metrics.get("centerline", {})
    if b:
        rows.append(("boundaries RMSE", f"{b['rmse_m']:.3f} m (p95 {b['p95_m']:.3f}, max {b['max_m']:.3f} m)"))
    if c:
        rows.append(("centre line RMSE", f"{c['rmse_m']:.3f} m (p95 {c['p95_m']:.3f}, max {c['max_m']:.3f} m)"))
    if "lane_count_agreement" in metrics:
        rows.append(("lane count agreement", f"{100.0 * metrics['lane_count_agreement']:.1f} %"))
    graph = metrics.get("lane_graph")
    if isinstance(graph, dict):
        rows.append(("lane graph agreement", _graph_text(graph)))
    elif isinstance(graph, int | float):
        rows.append(("lane graph agreement", f"{100.0 * graph:.1f} %"))
    lw = metrics.get("lane_width", {})
    if lw:
        rows.append(("lane width bias / sigma", "no matched lanes" if lw.get("bias_m") is None
                     else f"{lw['bias_m']:+.3f} / {lw['std_m']:.3f} m"))
    if "coverage" in metrics:
        rows.append(("coverage of the reference", f"{100.0 * metrics['coverage']:.1f} %"))
    el = metrics.get("elevation", {})
    if el.get("eval_length_m"):
        rows.append(("elevation RMSE", f"{el['rmse_m']:.3f} m"))
    return rows


def _graph_text(graph: dict[str, Any]) -> str:
    if isinstance(graph.get("agreement"), int | float):
        text = f"{100.0 * graph['agreement']:.1f} %"
        if isinstance(graph.get("breaks"), int):
            text += f" ({graph['breaks']} break{'s' * (graph['breaks'] != 1)}"
            text += f", {graph['wrong_m']:.0f} m wrong)" if isinstance(graph.get("wrong_m"), int | float) else ")"
        return text
    scalars = [f"{k.replace('_', ' ')} {v:.3g}" if isinstance(v, float) else f"{k.replace('_', ' ')} {v}"
               for k, v in graph.items() if isinstance(v, int | float | str)]
    return ", ".join(scalars[:6]) or "see the raw numbers"


def problems(warnings: list[str]) -> list[Problem]:
    """Each warning once, with the stretches of road its text names."""
    out: list[Problem] = []
    seen: set[str] = set()
    for text in warnings:
        if text in seen:
            continue
        seen.add(text)
        stretches = []
        for match in _STATIONS.finditer(text):
            for part in match.group(1).split(", "):
                a, _, b = part.partition("-")
                stretches.append((float(a), float(b or a)))
        out.append(Problem(text, stretches))
    return out


def make_verdict(map_name: str, odr: OpenDriveMap, check: dict[str, Any], metrics: dict[str, Any] | None,
                 warnings: list[str], min_width: float, step: float) -> Verdict:
    """The verdict of a written map, its check result, the comparison (or None) and the build's warnings."""
    roads = sorted((r.id for r in odr.roads.values() if r.junction in ("", "-1")), key=_natural)
    lengths = {r.id: float(r.length) for r in odr.roads.values()}
    rows = check_rows(check)
    return Verdict(
        map_name=map_name,
        length_m=float(sum(lengths.values())),
        roads=roads,
        road_lengths=lengths,
        stretches=lane_stretches(odr, min_width, step),
        junctions=junction_infos(odr),
        checks=rows,
        check_ok=check.get("ok") if check else None,
        metrics=metric_rows(metrics),
        problems=problems(check_problems(check, rows) + list(warnings)) + graph_problems(metrics),
    )


def graph_problems(metrics: dict[str, Any] | None) -> list[Problem]:
    """Each place where the generated lanes stop routing a reference lane (`compare`'s lane graph breaks)."""
    graph = (metrics or {}).get("lane_graph")
    if not isinstance(graph, dict):
        return []
    return [Problem(f"lane graph break: the generated lanes do not route reference road "
                    f"{b.get('reference_road', '?')} lane {b.get('reference_lane', '?')} on from here",
                    points=[(float(b["x"]), float(b["y"]))])
            for b in graph.get("breaks_at", []) if isinstance(b, dict) and "x" in b and "y" in b]


def check_problems(check: dict[str, Any], rows: list[CheckRow]) -> list[str]:
    """What the checks found wrong, in words: why the map fails them, each reader that failed, and the
    lanes of a width no lane has (`check`'s `lane_widths` warnings: zero-width, narrow, wide)."""
    out = [f"the map fails its checks: {reason}" for reason in check.get("reasons", [])] if check else []
    for row in rows:
        if row.status == FAIL and row.name not in ("ASAM checker", "continuity"):
            first = f": {row.lines[0]}" if row.lines else ""
            out.append(f"{row.name} failed to read the map{first}")
    if check:
        out += [f"map: {w}" for w in check.get("lane_widths", {}).get("warnings", [])]
    return out
