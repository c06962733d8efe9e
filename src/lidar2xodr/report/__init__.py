"""The build report: one self-contained HTML page that answers "what was built, and how good is it".

In reading order: the verdict (what was built, the check per reader, the metrics against the
reference, the warnings with the stretch of road they name) beside an interactive map of the
written OpenDRIVE that zooms to lane level; close-ups of every junction and lane-count change; the
error along the road when a reference is given; the scenario; and last, once, the raw numbers. (The
lanes stage's own pictures come from `lidar2xodr lanes --report`; here its candidate lines are a
layer of the map, which costs no time.) No internet needed: plotly.js is inlined, pictures are embedded.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
from plotly.offline import get_plotlyjs

from lidar2xodr.config import Config
from lidar2xodr.data import LaneModel, MarkingCloud
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import atomic_dir
from lidar2xodr.opendrive import OpenDriveMap
from lidar2xodr.report import mapview, page
from lidar2xodr.report.verdict import Verdict, make_verdict

MAP_HEIGHT_PX = 760
CLOSEUP_HEIGHT_PX = 330
CLOSEUP_ASPECT = 0.75


def write_report(
    out_dir: Path,
    cloud: MarkingCloud,
    model: LaneModel,
    map_path: Path,
    check: dict[str, Any],
    timings: dict[str, float],
    summary: dict[str, Any],
    scenario: dict[str, Any] | None = None,
    metrics: dict[str, Any] | None = None,
    reference: Path | None = None,
    warnings: list[str] | None = None,
    config: Config | None = None,
    final_path: Path | None = None,
) -> Path:
    """Write `out_dir/index.html` and `summary.json`, atomically (the folder appears whole).

    `map_path` is the written map to read back; `final_path` is where the user asked for it, the
    name the page shows (default: `map_path`; a build that stages its outputs passes both).
    `warnings` are the build's (default: the lane model's); `reference` draws the reference map in
    and plots the error along the road.
    """
    cfg = config or Config()
    map_path = Path(map_path)
    shown = Path(final_path) if final_path is not None else map_path
    warnings = list(model.warnings if warnings is None else warnings)
    try:
        odr = OpenDriveMap.load(map_path)
    except InputError as exc:  # written with --allow-invalid: the verdict and the numbers still help
        odr = OpenDriveMap(map_path, (1, 8), None, {}, {})
        warnings.insert(0, f"the written map cannot be read back, so it is not drawn: {exc.problem}")
    check = {**check, "file": str(shown)} if check else {}
    verdict = make_verdict(str(shown), odr, check, metrics, warnings, cfg.evaluation.lane_count_min_width_m,
                           cfg.report.map_step_m)
    ref_odr = OpenDriveMap.load(reference) if reference else None
    html_text = _page(verdict, odr, ref_odr, cloud, model, map_path, reference, scenario, cfg,
                      _raw_groups(summary, timings, check, metrics))
    with atomic_dir(Path(out_dir)) as tmp:
        (tmp / "index.html").write_text(html_text, encoding="utf-8")
        (tmp / "summary.json").write_text(
            json.dumps({"summary": {k: v for k, v in summary.items() if k != "metrics"}, "timings": timings,
                        "check": check, "metrics": metrics}, indent=2, default=str, sort_keys=True),
            encoding="utf-8",
        )
    return Path(out_dir) / "index.html"


def _raw_groups(summary: dict[str, Any], timings: dict[str, float], check: dict[str, Any],
                metrics: dict[str, Any] | None) -> dict[str, dict[str, Any]]:
    return {
        "build": {k: v for k, v in summary.items() if k != "metrics"},
        "time per stage [s]": {k: round(v, 3) for k, v in timings.items()},
        "check": check,
        "comparison with the reference": metrics or {},
    }


def _page(verdict: Verdict, odr: OpenDriveMap, ref_odr: OpenDriveMap | None, cloud: MarkingCloud,
          model: LaneModel, map_path: Path, reference: Path | None, scenario: dict[str, Any] | None,
          cfg: Config, raw: dict[str, dict[str, Any]]) -> str:
    rc = cfg.report
    layers = mapview.written_map_layers(odr, rc)
    extent = _extent(layers)
    below_borders = next((k for k, layer in enumerate(layers) if layer.kind != "fill"), len(layers))
    under = [mapview.cloud_layer(cloud, rc), mapview.reference_layer(ref_odr, extent, rc) if ref_odr else None]
    layers[below_borders:below_borders] = [layer for layer in under if layer is not None]
    layers += mapview.candidate_layers(model)
    path = mapview.path_layer(cloud)
    if path is not None:
        layers.append(path)
    found = mapview.places(verdict, odr, rc)
    layers += mapview.place_layers(found)
    sections = [
        '<div class="top">',
        page.verdict_html(verdict, _stretch_links(verdict, odr, rc.closeup_m), _junction_links(verdict, found),
                          _problem_links(verdict, model, rc.closeup_m)),
        '<div class="mapbox">', page.plot_div(mapview.figure(layers, MAP_HEIGHT_PX), "map"),
        '<div class="note">Scroll to zoom, drag to pan, double-click for the whole map; click a legend entry to '
        "hide or show it. Lane borders, marks and lanes are read back from the written file.</div>",
        "</div></div>",
    ]
    sections.append(_closeups_html(layers, found, rc.max_closeups))
    if reference is not None and odr.roads:
        sections.append(_along_road_html(map_path, reference, cfg))
    if scenario:
        sections.append(_scenario_html(scenario, map_path))
    sections.append(page.raw_numbers_html(raw))
    return "\n".join([
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>lidar2xodr report: {page.esc(Path(verdict.map_name).name)}</title>",
        f'<meta name="description" content="{page.esc(verdict.headline())}">',
        f"<style>{page.CSS}</style><script>{page.HEAD_JS}</script>",
        f"<script>{get_plotlyjs()}</script><script>{page.PAGE_JS}</script></head><body><main>",
        '<div id="js-error" hidden></div>',
        "<noscript><p class='note'>The map and plots need JavaScript; the verdict and the numbers do not.</p>"
        "</noscript>",
        *sections,
        "</main></body></html>",
    ])


def _extent(layers: list[mapview.Layer]) -> np.ndarray:
    pts = [p for layer in layers if layer.kind == "line" for p in layer.parts]
    if not pts:
        return np.zeros((2, 2))
    xy = np.concatenate(pts)
    return np.stack([np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)])


def _box_zoom(xy: np.ndarray, span_min: float) -> tuple[float, float, float]:
    """Centre and span of a window that shows all of `xy` (at least `span_min` wide)."""
    lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
    centre = 0.5 * (lo + hi)
    return float(centre[0]), float(centre[1]), float(max(span_min, 1.15 * float(np.max(hi - lo))))


def _stretch_links(verdict: Verdict, odr: OpenDriveMap, span_min: float) -> list[str]:
    links = []
    for line_road, line in zip(verdict.roads, verdict.lanes_lines(), strict=True):
        road = odr.roads[line_road]
        texts = [st for st in verdict.stretches if st.road == line_road]
        head = line.split(": ", 1)[0] + ": " if len(verdict.roads) > 1 else ""
        items = []
        for st in texts:
            s = np.linspace(st.s0, st.s1, 40)
            x, y, _ = road.reference(s)
            items.append(page.zoom_link(st.text(), *_box_zoom(np.column_stack([x, y]), span_min)))
        links.append(page.esc(head) + (", ".join(items) if items else "no driving lane"))
    return links


def _junction_links(verdict: Verdict, found: list[mapview.Place]) -> list[str]:
    by_id = {p.id: p for p in found}
    out = []
    for j in verdict.junctions:
        p = by_id[f"junction-{j.id}"]
        out.append(page.zoom_link(j.text(), p.x, p.y, p.span))
    return out


def _problem_links(verdict: Verdict, model: LaneModel, span_min: float) -> list[list[str]]:
    """Zoom links for the stretches each warning names (stations of the measured carriageway)."""
    s = np.asarray(model.s, dtype=np.float64)
    ref = np.asarray(model.reference, dtype=np.float64)
    out = []
    for p in verdict.problems:
        links = []
        if len(s) >= 2:
            for s0, s1 in p.stretches:
                q = np.linspace(s0, s1, 40)
                xy = np.column_stack([np.interp(q, s, ref[:, 0]), np.interp(q, s, ref[:, 1])])
                label = f"s {s0:.0f} m" if s1 == s0 else f"s {s0:.0f}-{s1:.0f} m"
                links.append(page.zoom_link(label, *_box_zoom(xy, span_min)))
        links += [page.zoom_link("show", x, y, span_min) for x, y in p.points]
        out.append(links)
    return out


def _closeups_html(layers: list[mapview.Layer], found: list[mapview.Place], max_closeups: int) -> str:
    if not found:
        return ('<h2>Close-ups</h2><p class="note">No junction and no change of the lane count: the map has one '
                "lane layout throughout.</p>")
    cells = []
    for k, p in enumerate(found):
        attr = page.zoom_attr(p.x, p.y, p.span)
        button = f'<button class="zoom" {attr}>zoom the main map here</button>'
        if k < max_closeups:
            fig = mapview.figure(layers, CLOSEUP_HEIGHT_PX, mapview.window(p, CLOSEUP_ASPECT), legend=False)
            plot = page.plot_div(fig, f"closeup-{p.id}")
        else:
            plot = '<p class="note">(not drawn: more close-ups than report.max_closeups)</p>'
        cells.append(f'<div class="closeup" id="{p.id}" {attr}><h3>{page.esc(p.title)}</h3>{plot}{button}</div>')
    return '<h2>Close-ups: every junction and lane-count change</h2><div class="closeups">' + "".join(cells) + "</div>"


def _along_road_html(map_path: Path, reference: Path, cfg: Config) -> str:
    from lidar2xodr.report.along_road import error_profiles, profile_figure

    profiles = error_profiles(map_path, reference, cfg.evaluation, cfg.report.map_step_m)
    if not profiles:
        return ""
    click = ("document.getElementById('{plot_id}').on('plotly_click', function (d) {"
             f" var c = d.points[0].customdata; if (c) zoomTo(c[0], c[1], {cfg.report.closeup_m:.1f}, true); }});")
    return (f"<h2>Error along the road, against {page.esc(reference)}</h2>"
            '<p class="note">The distance of the generated carriageway centre line to the reference one (what '
            "the centre line RMSE sums up) and the lane count of both maps; click a point to see it on the map."
            "</p>" + page.plot_div(profile_figure(profiles), "along-road", click))


def _scenario_html(scenario: dict[str, Any], map_path: Path) -> str:
    from lidar2xodr.report.stages import plot_participants

    summ = scenario["summary"]
    items = "".join(f"<li>{page.esc(f'{m.kind}: {m.actor} at {m.time_s:.1f} s')}</li>" for m in summ.manoeuvres) \
        or "<li>none detected</li>"
    warns = "".join(f"<li>{page.esc(w)}</li>" for w in summ.warnings)
    png = io.BytesIO()
    plot_participants(map_path, scenario, png)
    return (f"<h2>Scenario {page.esc(scenario['path'])}</h2><p>{len(summ.entities)} entities, "
            f"{summ.duration_s:.1f} s.</p><details class='msgs'><summary>{len(summ.manoeuvres)} manoeuvre(s) "
            f"relative to the generated lanes</summary><ul>{items}</ul></details>"
            + (f"<details class='msgs'><summary>{len(summ.warnings)} warning(s)</summary><ul>{warns}</ul></details>"
               if warns else "")
            + page.image(png.getvalue(), "The ego and every participant on the generated lanes (road frame)"))
