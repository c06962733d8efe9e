"""The HTML of the report page: the verdict block, zoom links, plot containers and the raw numbers table.

One self-contained file: plotly.js is inlined once, pictures are data URIs, nothing is fetched.
A link or button with `data-zoom="x,y,span"` zooms the main map there; `index.html#map=ID` opens
the page zoomed to the close-up ID (e.g. `#map=junction-3`; `#map=junction`: the first junction).
A script error is shown on the page (`#js-error`), not only in the browser's console.
"""

from __future__ import annotations

import base64
import html
import json
from typing import Any

import plotly.io as pio

from lidar2xodr.report.verdict import ABSENT, FAIL, PASS, WARN, Verdict

STATUS_TEXT = {PASS: "passed", WARN: "warnings", FAIL: "failed", ABSENT: "not available"}
BADGE_TEXT = {PASS: "Passes every check", WARN: "Passes the checks, with warnings", FAIL: "Fails the checks",
              ABSENT: "Not checked"}
PLOT_CONFIG = {"scrollZoom": True, "displaylogo": False, "responsive": True,
               "modeBarButtonsToRemove": ["select2d", "lasso2d", "autoScale2d"]}

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;margin:0;color:#1d232b;background:#fafbfc}
main{padding:12px 18px;max-width:2000px;margin:auto}
.top{display:flex;gap:18px;align-items:flex-start}
.verdict{flex:0 0 430px;font-size:14px;line-height:1.35}
.mapbox{flex:1 1 auto;min-width:0;background:white;border:1px solid #dde2e8;border-radius:6px;padding:4px}
@media (max-width:1100px){.top{flex-direction:column}.verdict{flex-basis:auto}}
h1{font-size:17px;margin:4px 0 6px;word-break:break-all}
h2{font-size:16px;margin:22px 0 8px}
.badge{display:inline-block;padding:3px 10px;border-radius:12px;font-weight:600;color:white;font-size:13px}
.badge.pass{background:#2e7d32}.badge.warn{background:#b26a00}.badge.fail{background:#c62828}
.badge.absent{background:#6b7785}
.facts{margin:6px 0}.facts div{margin:2px 0}.facts b{display:inline-block;min-width:76px}
table.checks,table.metrics{border-collapse:collapse;width:100%;margin:4px 0 8px;font-size:13px}
table.checks td,table.metrics td,table.metrics th{border-top:1px solid #e3e7ec;padding:2px 4px;vertical-align:top}
table.metrics th{text-align:left;font-weight:500;color:#4a5561;white-space:nowrap}
.st{font-weight:600;white-space:nowrap}.st.pass{color:#2e7d32}.st.warn{color:#b26a00}.st.fail{color:#c62828}
.st.absent{color:#6b7785}
details.msgs summary{cursor:pointer;color:#4a5561;font-size:12px}
details.msgs div{font-family:ui-monospace,monospace;font-size:11px;white-space:pre-wrap;color:#4a5561}
ul.problems{margin:4px 0;padding-left:18px;font-size:13px}ul.problems li{margin:3px 0}
a.zoom,button.zoom{color:#1565c0;background:none;border:none;padding:0;cursor:pointer;font:inherit;
text-decoration:underline dotted}
.closeups{display:grid;grid-template-columns:repeat(auto-fill,minmax(420px,1fr));gap:12px}
.closeup{background:white;border:1px solid #dde2e8;border-radius:6px;padding:6px}
.closeup h3{font-size:13px;margin:2px 4px 4px;font-weight:600}
#js-error{background:#fdecea;color:#8a1c1c;padding:8px 12px;border-radius:6px;margin:8px 0}
details.raw>summary,details.stages>summary{cursor:pointer;font-size:16px;font-weight:600;margin:22px 0 8px}
table.raw{border-collapse:collapse;font-size:12px;margin:6px 0 14px}
table.raw td,table.raw th{border:1px solid #e0e4ea;padding:2px 6px;text-align:left;vertical-align:top}
table.raw th{font-weight:500;font-family:ui-monospace,monospace}
img{max-width:100%}.note{color:#4a5561;font-size:13px}
"""

HEAD_JS = """
window.addEventListener('error', function (e) {
  var box = document.getElementById('js-error');
  if (box) { box.hidden = false; box.textContent = 'The interactive plots could not be drawn: ' + e.message; }
});
"""

PAGE_JS = """
function zoomTo(x, y, span, scroll) {
  var el = document.getElementById('map');
  if (!el || !window.Plotly) return;
  var aspect = el.clientHeight / Math.max(el.clientWidth, 1);
  Plotly.relayout(el, {'xaxis.range': [x - span / 2, x + span / 2],
                       'yaxis.range': [y - span * aspect / 2, y + span * aspect / 2]});
  if (scroll) el.scrollIntoView({behavior: 'smooth', block: 'center'});
}
function zoomFromHash() {
  var m = /^#map=(.+)$/.exec(window.location.hash);
  var id = m && decodeURIComponent(m[1]);
  var el = id && (document.getElementById(id) || document.querySelector('[id^="' + CSS.escape(id) + '-"][data-zoom]'));
  if (el && el.dataset.zoom) { var z = el.dataset.zoom.split(',').map(Number); zoomTo(z[0], z[1], z[2], false); }
}
document.addEventListener('click', function (e) {
  var b = e.target.closest('[data-zoom]');
  if (!b || b.classList.contains('closeup')) return;
  e.preventDefault();
  var z = b.dataset.zoom.split(',').map(Number);
  zoomTo(z[0], z[1], z[2], true);
});
window.addEventListener('hashchange', zoomFromHash);
window.addEventListener('load', zoomFromHash);
"""


def esc(text: Any) -> str:
    return html.escape(str(text), quote=True)


def zoom_attr(x: float, y: float, span: float) -> str:
    return f'data-zoom="{x:.2f},{y:.2f},{span:.1f}"'


def zoom_link(label: str, x: float, y: float, span: float) -> str:
    return f'<button class="zoom" {zoom_attr(x, y, span)} title="zoom the map here">{esc(label)}</button>'


def plot_div(fig: dict[str, Any], div_id: str, post_script: str | None = None) -> str:
    """A plotly figure as a <div> and its script (plotly.js is inlined once by the page)."""
    return pio.to_html(fig, include_plotlyjs=False, full_html=False, div_id=div_id, config=PLOT_CONFIG,
                       post_script=post_script, validate=False)


def verdict_html(v: Verdict, stretch_links: list[str], junction_links: list[str], problem_links: list[list[str]]
                 ) -> str:
    """The verdict block: badge, map name, what was built, the checks, the metrics, the warnings."""
    parts = [f'<span class="badge {v.status}">{esc(BADGE_TEXT[v.status])}</span>',
             f"<h1>{esc(v.map_name)}</h1>", '<div class="facts">',
             f"<div><b>Built</b> {esc(v.built_line())}</div>"]
    parts.append("<div><b>Lanes</b> " + "; ".join(stretch_links) + "</div>")
    if junction_links:
        parts.append("<div><b>Junctions</b> " + "; ".join(junction_links) + "</div>")
    parts.append("</div>")
    if v.checks:
        rows = []
        for c in v.checks:
            msgs = ""
            if c.lines:
                body = "\n".join(esc(line) for line in c.lines[:30])
                more = f"\n... {len(c.lines) - 30} more (raw numbers)" if len(c.lines) > 30 else ""
                msgs = f'<details class="msgs"><summary>{len(c.lines)} message(s)</summary><div>{body}{more}</div>' \
                       "</details>"
            rows.append(f'<tr><td>{esc(c.name)}</td><td class="st {c.status}">{STATUS_TEXT[c.status]}</td>'
                        f"<td>{esc(c.detail)}{msgs}</td></tr>")
        parts.append(f'<table class="checks">{"".join(rows)}</table>')
    else:
        parts.append('<p class="note">The map was not checked.</p>')
    if v.metrics:
        rows = "".join(f"<tr><th>{esc(k)}</th><td>{esc(val)}</td></tr>" for k, val in v.metrics)
        parts.append(f'<div><b>Against the reference</b></div><table class="metrics">{rows}</table>')
    if v.problems:
        items = []
        for p, links in zip(v.problems, problem_links, strict=True):
            where = f" ({', '.join(links)})" if links else ""
            items.append(f"<li>{esc(p.text)}{where}</li>")
        parts.append(f'<div><b>What went wrong</b></div><ul class="problems">{"".join(items)}</ul>')
    else:
        parts.append("<div><b>What went wrong</b> nothing the build noticed</div>")
    return '<section class="verdict" id="verdict">' + "".join(parts) + "</section>"


def image(png: bytes, caption: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<figure><img src="data:image/png;base64,{data}" alt="{esc(caption)}"><figcaption class="note">' \
           f"{esc(caption)}</figcaption></figure>"


def raw_numbers_html(groups: dict[str, dict[str, Any]]) -> str:
    """Every number once, grouped, in one collapsed block."""
    body = []
    for title, data in groups.items():
        if not data:
            continue
        rows = "".join(f"<tr><th>{esc(k)}</th><td>{_value(v)}</td></tr>" for k, v in _flatten(data).items())
        body.append(f"<h3>{esc(title)}</h3><table class='raw'>{rows}</table>")
    return '<details class="raw" id="raw"><summary>Raw numbers</summary>' + "".join(body) + \
        '<p class="note">All of them as JSON: summary.json next to this page.</p></details>'


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            flat.update(_flatten(v, f"{prefix}{k}."))
        else:
            flat[f"{prefix}{k}"] = v
    return flat


def _value(v: Any) -> str:
    if isinstance(v, float):
        return esc(f"{v:.6g}")
    if isinstance(v, list) and (len(v) > 12 or any(isinstance(x, dict | list) for x in v)):
        text = json.dumps(v, indent=1, default=str)
        return f"<details><summary>{len(v)} item(s)</summary><pre>{esc(text)}</pre></details>"
    if isinstance(v, list | dict):
        return esc(json.dumps(v, default=str))
    return esc(v)
