"""The report's interactive map (plotly, SVG, no WebGL): the written map at lane level and what it came from.

Lane areas are filled by lane type, lane borders drawn thin, road marks as written (solid marks as
lines, broken ones as their dashes at the written length and gap, so zooming in shows them as
painted), the reference line, junctions and lane-count changes marked, the marking cloud as light
points (one per `cloud_cell_m` cell, at most `max_cloud_points`), the drive's path, and the
reference map in another colour when given, and (off until clicked in the legend) the lanes stage's
candidate lines. Everything is sampled from the written OpenDRIVE with
the project's reader, every `map_step_m`. A close-up is the same layers clipped to a window.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidar2xodr.config import ReportConfig
from lidar2xodr.data import LaneModel, MarkingCloud
from lidar2xodr.opendrive import OpenDriveMap, Road
from lidar2xodr.report.verdict import Verdict

LANE_COLOURS = {
    "driving": "#c7d3e3", "entry": "#f6c37b", "onramp": "#f6c37b", "exit": "#f3a3a0", "offramp": "#f3a3a0",
    "shoulder": "#d3e8c8", "stop": "#d3e8c8", "border": "#e4e4e4", "restricted": "#e8d4ef", "median": "#d9ccb8",
    "biking": "#cfe7ef", "sidewalk": "#ececec", "parking": "#e9e4c9",
}
_OTHER_LANE = "#dedede"
_MARK_COLOURS = {"yellow": "#c99a00", "blue": "#2a5bd7", "red": "#c0392b", "green": "#2e8b57"}
_MARK_DARK = "#222222"
_DEFAULT_DASH = (3.0, 9.0)
_REFERENCE_COLOUR = "#e4572e"
COMPACT_LIMIT_M = 65536.0  # coordinates below this are sent as float32 (resolution under 4 mm)


@dataclass
class Layer:
    """One trace: polylines (line), polygons (fill) or points, with their style."""

    name: str
    kind: str  # line | fill | points
    parts: list[np.ndarray]  # (n, 2) each; fills: (n, 4), inner and outer border at the same stations
    colour: str
    width: float = 1.0
    size: float = 3.0
    opacity: float = 1.0
    hover: list[str] | None = None
    legend: bool = True
    visible: bool | str = True
    group: str = ""
    _flat: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def flat(self) -> tuple[np.ndarray, np.ndarray]:
        """All parts stacked, and the part each row belongs to (computed once, for every close-up)."""
        if self._flat is None:
            rows = np.concatenate(self.parts) if self.parts else np.zeros((0, 2))
            self._flat = (rows, np.repeat(np.arange(len(self.parts)), [len(p) for p in self.parts]))
        return self._flat


@dataclass
class Place:
    """A close-up: a junction or a lane-count change, with the window that shows it."""

    id: str
    title: str
    x: float
    y: float
    span: float
    kind: str  # junction | lanes


@dataclass
class MapLayers:
    """Everything the map draws, in drawing order, and the places worth a close-up."""

    layers: list[Layer] = field(default_factory=list)
    places: list[Place] = field(default_factory=list)


def _lane_colour(kind: str) -> str:
    return LANE_COLOURS.get(kind.lower(), _OTHER_LANE)


def written_map_layers(odr: OpenDriveMap, cfg: ReportConfig) -> list[Layer]:
    """Lane areas by type, lane borders, road marks, the reference line and lane labels of a map."""
    fills: dict[str, list[np.ndarray]] = {}
    borders: list[np.ndarray] = []
    reference: list[np.ndarray] = []
    hover_xy: list[np.ndarray] = []
    hover: list[str] = []
    every = max(1, round(cfg.lane_hover_step_m / cfg.map_step_m))
    for sec in odr.sample(cfg.map_step_m):
        reference.append(sec.xyz[:, :2])
        for lid in sec.lane_ids:
            borders.append(sec.border_xyz[lid][:, :2])
            if lid == 0:
                continue
            inner_id = lid - (1 if lid > 0 else -1)
            inner, outer = sec.border_xyz[inner_id][:, :2], sec.border_xyz[lid][:, :2]
            width = np.abs(sec.border_t[lid] - sec.border_t[inner_id])
            if not np.nanmax(width, initial=0.0) > 1e-3:
                continue
            kind = sec.lane_types[lid]
            fills.setdefault(kind, []).append(np.hstack([inner, outer]))
            idx = np.arange(every // 2, len(sec.s), every)
            idx = idx[width[idx] > 1e-3]
            hover_xy.append(0.5 * (inner[idx] + outer[idx]))
            hover += [f"road {sec.road_id}, lane {lid} ({kind})<br>s {sec.s[i]:.0f} m, width {width[i]:.2f} m"
                      for i in idx]
    layers = [Layer(f"{kind} lane", "fill", parts, _lane_colour(kind), group="lanes")
              for kind, parts in sorted(fills.items(), key=lambda kv: (kv[0] != "driving", kv[0]))]
    layers.append(Layer("lane borders", "line", borders, "#8a94a3", width=0.6, group="lanes"))
    layers += road_mark_layers(odr, cfg.map_step_m)
    layers.append(Layer("reference line", "line", reference, "#a22cc2", width=1.0, visible="legendonly"))
    if hover_xy:
        layers.append(Layer("lanes (hover)", "points", [np.concatenate(hover_xy)], "#000000", size=8,
                            opacity=0.0, hover=hover, legend=False))
    return layers


def road_mark_layers(odr: OpenDriveMap, step: float) -> list[Layer]:
    """Solid marks as lines and broken marks as their dashes, one layer per kind and colour."""
    parts: dict[tuple[str, str], list[np.ndarray]] = {}
    widths: dict[tuple[str, str], float] = {}
    for road in odr.roads.values():
        for ls in road.lane_sections:
            for lid, lane in ls.lanes.items():
                for k, mark in enumerate(lane.road_marks):
                    kind = mark.type.lower()
                    if kind in ("none", ""):
                        continue
                    s_a = ls.s + mark.s_offset
                    s_b = ls.s + lane.road_marks[k + 1].s_offset if k + 1 < len(lane.road_marks) else ls.s_end
                    if s_b - s_a <= 1e-6:
                        continue
                    broken = "broken" in kind
                    key = ("broken" if broken else "solid", mark.color.lower())
                    pieces = _dashes(road, lid, s_a, s_b, mark) if broken else _solid(road, lid, s_a, s_b, step)
                    parts.setdefault(key, []).extend(pieces)
                    widths[key] = max(widths.get(key, 0.0), mark.width)
    return [Layer(f"road mark, {kind}" + ("" if colour in ("white", "standard") else f" ({colour})"), "line",
                  parts[(kind, colour)], _MARK_COLOURS.get(colour, _MARK_DARK),
                  width=2.4 if widths[(kind, colour)] >= 0.25 else 1.5, group="marks")
            for kind, colour in sorted(parts)]


def _solid(road: Road, lane_id: int, s_a: float, s_b: float, step: float) -> list[np.ndarray]:
    s = np.linspace(s_a, s_b - 1e-6, max(2, int(np.ceil((s_b - s_a) / step)) + 1))
    return [road.to_world(s, road.border_t(s, lane_id))[:, :2]]


def _dashes(road: Road, lane_id: int, s_a: float, s_b: float, mark: Any) -> list[np.ndarray]:
    """Every dash of a broken mark as a two-point line, at the written dash length and gap."""
    line = mark.lines[0] if mark.lines and mark.lines[0].space > 0 else None
    length, space = (line.length, line.space) if line is not None else _DEFAULT_DASH
    start = s_a + (line.s_offset if line is not None else 0.0)
    begin = np.arange(start, s_b - 1e-6, length + space)
    if begin.size == 0:
        return []
    end = np.minimum(begin + length, s_b - 1e-6)
    s = np.column_stack([begin, end]).ravel()
    xy = road.to_world(s, road.border_t(s, lane_id))[:, :2]
    return list(xy.reshape(-1, 2, 2))


def reference_layer(ref: OpenDriveMap, around: np.ndarray, cfg: ReportConfig) -> Layer:
    """The reference map's lane borders within `reference_margin_m` of the box `around` ((2, 2): min, max)."""
    lo, hi = around[0] - cfg.reference_margin_m, around[1] + cfg.reference_margin_m
    parts = []
    for sec in ref.sample(cfg.map_step_m):
        for lid in sec.lane_ids:
            xy = sec.border_xyz[lid][:, :2]
            parts += _runs(xy, np.all((xy >= lo) & (xy <= hi), axis=1))
    return Layer("reference map (lane borders)", "line", parts, _REFERENCE_COLOUR, width=1.2, group="reference")


def cloud_layer(cloud: MarkingCloud, cfg: ReportConfig) -> Layer | None:
    """The marking points, one per cell, evenly thinned to `max_cloud_points` (deterministic)."""
    xy = np.asarray(cloud.xyz, dtype=np.float64)[:, :2]
    if len(xy) == 0 or cfg.max_cloud_points == 0:
        return None
    cell = np.floor((xy - xy.min(axis=0)) / cfg.cloud_cell_m).astype(np.int64)
    key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
    _, first = np.unique(key, return_index=True)
    first.sort()
    if len(first) > cfg.max_cloud_points:
        first = first[np.linspace(0, len(first) - 1, cfg.max_cloud_points).astype(np.int64)]
    name = f"marking points ({len(first):,} of {len(xy):,})"
    return Layer(name, "points", [xy[first]], "#7fa7d4", size=2.5, opacity=0.55, group="cloud")


def candidate_layers(model: LaneModel) -> list[Layer]:
    """The lanes stage's candidate lines (chained cluster centres): kept in a superline or ignored; off at first."""
    kept = [np.asarray(c.centers, dtype=np.float64)[:, :2] for c in model.candidates if c.superline >= 0]
    ignored = [np.asarray(c.centers, dtype=np.float64)[:, :2] for c in model.candidates if c.superline < 0]
    out = []
    for name, parts, colour in (("candidate lines, kept", kept, "#2ca02c"), ("candidate lines, ignored", ignored,
                                                                             "#9a9a9a")):
        if parts:
            out.append(Layer(name, "line", parts, colour, width=1.0, visible="legendonly", group="candidates"))
    return out


def path_layer(cloud: MarkingCloud, max_points: int = 4000) -> Layer | None:
    """The drive's path (the poses the scans were placed with), off until clicked in the legend."""
    if not len(cloud.trajectory):
        return None
    p = np.asarray(cloud.trajectory.positions, dtype=np.float64)[:, :2]
    p = p[np.unique(np.linspace(0, len(p) - 1, min(len(p), max_points)).astype(np.int64))]
    return Layer("drive path", "line", [p], "#d62728", width=1.0, visible="legendonly")


def places(verdict: Verdict, odr: OpenDriveMap, cfg: ReportConfig) -> list[Place]:
    """A close-up of every junction and of every lane-count change inside a road."""
    out = [Place(f"junction-{j.id}", j.text(), j.xy[0], j.xy[1], cfg.closeup_m, "junction")
           for j in verdict.junctions]
    for a, b in zip(verdict.stretches, verdict.stretches[1:], strict=False):
        if a.road != b.road:
            continue
        road = odr.roads[a.road]
        x, y = _carriageway_centre(road, b.s0)
        title = f"road {a.road} at s {b.s0:.0f} m: {a.lanes_text()} to {b.lanes_text()}"
        out.append(Place(f"lanes-{len(out) + 1}", title, x, y, cfg.closeup_m, "lanes"))
    return out


def _carriageway_centre(road: Road, s: float) -> tuple[float, float]:
    ls = road.lane_sections[int(road.section_index(s)[0])]
    t = [float(road.border_t(s, lid)[0]) for lid in ls.lanes]
    t = [v for v in t if np.isfinite(v)] or [0.0]
    xy = road.to_world(np.array([s]), np.array([0.5 * (min(t) + max(t))]))[0]
    return float(xy[0]), float(xy[1])


def place_layers(found: list[Place]) -> list[Layer]:
    """Markers with labels for the junctions and the lane-count changes."""
    out = []
    for kind, name, colour in (("junction", "junction", "#6a3d9a"), ("lanes", "lane count changes", "#1f78b4")):
        sel = [p for p in found if p.kind == kind]
        if sel:
            out.append(Layer(name, "points", [np.array([[p.x, p.y] for p in sel])], colour, size=11,
                             hover=[p.title for p in sel]))
    return out


def _runs(xy: np.ndarray, inside: np.ndarray, part: np.ndarray | None = None) -> list[np.ndarray]:
    """The runs of consecutive rows (of one part) that are inside, each with one row beyond either end."""
    same = np.ones(max(len(xy) - 1, 0), bool) if part is None else part[1:] == part[:-1]
    keep = inside | (np.r_[inside[1:], False] & np.r_[same, False]) | (np.r_[False, inside[:-1]] & np.r_[False, same])
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return []
    cut = (np.diff(idx) > 1) | ~same[idx[:-1]]
    return [xy[run] for run in np.split(idx, np.flatnonzero(cut) + 1) if run.size > 1]


def _clip(layer: Layer, box: tuple[float, float, float, float] | None) -> list[np.ndarray]:
    """The layer's parts within `box` (points: those inside; lines and fills: the runs inside)."""
    if box is None:
        return layer.parts
    rows, part = layer.flat()
    x0, x1, y0, y1 = box
    inside = np.zeros(len(rows), bool)
    for c in range(0, rows.shape[1], 2):
        inside |= (rows[:, c] >= x0) & (rows[:, c] <= x1) & (rows[:, c + 1] >= y0) & (rows[:, c + 1] <= y1)
    if layer.kind == "points":
        return [rows[inside]] if inside.any() else []
    return _runs(rows, inside, part)


def _joined(layer: Layer, box: tuple[float, float, float, float] | None) -> tuple[np.ndarray, np.ndarray]:
    """x and y of the layer clipped to `box`, NaN between parts (fills closed as polygons), to the cm."""
    kind = layer.kind
    parts = _clip(layer, box)
    if kind == "fill":
        parts = [np.vstack([p[:, :2], p[::-1, 2:], p[:1, :2]]) for p in parts]
    if not parts:
        return np.zeros(0), np.zeros(0)
    gap = np.full((1, 2), np.nan)
    xy = np.concatenate(parts) if kind == "points" else np.concatenate([q for p in parts for q in (p, gap)][:-1])
    xy = np.round(xy, 2)
    if np.nanmax(np.abs(xy), initial=0.0) < COMPACT_LIMIT_M:
        xy = xy.astype(np.float32)
    return xy[:, 0], xy[:, 1]


def typed(values: np.ndarray) -> dict[str, str]:
    """A numeric array as plotly.js's typed-array spec (base64 of little-endian float32/float64 bytes)."""
    arr = np.ascontiguousarray(values)
    dtype = "f4" if arr.dtype == np.float32 else "f8"
    arr = arr.astype("<" + dtype, copy=False)
    spec = {"dtype": dtype, "bdata": base64.b64encode(arr.tobytes()).decode("ascii")}
    if arr.ndim > 1:
        spec["shape"] = ", ".join(str(n) for n in arr.shape)
    return spec


def figure(layers: list[Layer], height: int, window: tuple[float, float, float, float] | None = None,
           legend: bool = True) -> dict[str, Any]:
    """A plotly figure (as the dict plotly.js reads) of the layers at equal x, y scales, clipped to `window`.

    Built as plain data rather than graph objects: validating thousands of properties per close-up
    costs more than drawing them.
    """
    margin = 0.25 * (window[1] - window[0]) if window is not None else 0.0
    clip = None if window is None else (window[0] - margin, window[1] + margin, window[2] - margin,
                                        window[3] + margin)
    data: list[dict[str, Any]] = []
    for layer in layers:
        x, y = _joined(layer, clip)
        if window is not None and x.size == 0:
            continue
        trace: dict[str, Any] = {"type": "scatter", "x": typed(x), "y": typed(y), "name": layer.name,
                                 "showlegend": legend and layer.legend, "visible": layer.visible,
                                 "legendgroup": layer.group or layer.name, "hoverinfo": "skip"}
        if layer.kind == "fill":
            trace.update(mode="lines", fill="toself", fillcolor=layer.colour, line={"width": 0, "color": layer.colour})
        elif layer.kind == "line":
            trace.update(mode="lines", line={"width": layer.width, "color": layer.colour})
        else:
            trace.update(mode="markers", marker={"size": layer.size, "color": layer.colour, "opacity": layer.opacity,
                                                 "line": {"width": 0}})
            if layer.hover:
                trace.update(hovertext=layer.hover, hoverinfo="text")
        data.append(trace)
    axis: dict[str, Any] = {"showgrid": True, "gridcolor": "#eeeeee", "zeroline": False, "ticksuffix": " m",
                            "showline": True, "linecolor": "#bbbbbb", "mirror": True}
    layout: dict[str, Any] = {
        "height": height, "margin": {"l": 60, "r": 10, "t": 10, "b": 40}, "plot_bgcolor": "white",
        "paper_bgcolor": "white", "hovermode": "closest", "dragmode": "pan",
        "font": {"family": "sans-serif", "size": 12}, "showlegend": legend,
        "legend": {"orientation": "h", "yanchor": "bottom", "y": 1.0, "x": 0.0, "bgcolor": "rgba(255,255,255,0.8)"},
        "xaxis": dict(axis), "yaxis": {**axis, "scaleanchor": "x", "scaleratio": 1.0},
    }
    if window is not None:
        layout["xaxis"]["range"] = [window[0], window[1]]
        layout["yaxis"]["range"] = [window[2], window[3]]
    return {"data": data, "layout": layout}


def window(place: Place, aspect: float) -> tuple[float, float, float, float]:
    """x0, x1, y0, y1 of a place's window for a plot `aspect` = height / width."""
    half_x, half_y = 0.5 * place.span, 0.5 * place.span * aspect
    return place.x - half_x, place.x + half_x, place.y - half_y, place.y + half_y
