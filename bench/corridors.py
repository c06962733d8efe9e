"""Random motorway corridors for the generalisation sweep (issue #13): maps nobody tuned the tool to.

Corridor k is drawn from `numpy.random.default_rng(k)` and written with PyPI `roadgen` 0.41.2
(`Map.add_corridor`, `Corridor.add_ramp`, `Map.export_opendrive`), so it is reproducible but chosen
by no one. What is drawn:

- alignment: straights of 200-800 m and curves of radius 700 m-5 km (log-uniform, either hand),
  each entered and left by a clothoid of length R/9-R/3 (at most 300 m); `ALIGNMENT_POINT_M`
  spaced centre-line points are handed to roadgen, which fits its own alignment through them;
- vertical: a height knot every 600-1200 m, changing by at most `MAX_GRADE` of the distance, so
  there are crests and sags (roadgen rounds them with its standard's vertical curves);
- cross-section: 2-4 lanes each way (roadgen's motorway standard: 3.5 m lanes, shoulders, median);
- events: 2-6 per 5 km (scaled to the corridor length) exits and entries on either carriageway,
  `MIN_RAMP_SPACING_M` apart on one carriageway, none in the first `CLEAR_START_M` or last
  `CLEAR_END_M`. roadgen 0.41.2's corridor has no lane drop, so lane drops are not drawn; the
  acceleration and deceleration lanes of the slip roads are the lane-count events.

roadgen quirk handled here: a lane that starts inside a lane section (an acceleration lane behind an
entry junction) gets its first <width> at an sOffset > 0; OpenDRIVE leaves the width before it
undefined and the project's reader extrapolates the cubic (200 m wide lanes). `_fix_widths` adds a
constant record from sOffset 0 at the first record's start width, and puts each road's children
in schema order (roadgen 0.41.2 writes <elevationProfile> before <planView>, an ASAM schema error
in the truth map). A ramp roadgen refuses (a slip
road too steep for its standard, say) is dropped, last drawn first, and said so in the manifest.

Use: `python bench/corridors.py OUT_DIR --count 3` writes corridor_000.xodr ... and a manifest.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from lxml import etree

CORRIDOR_LENGTH_M = 4500.0
"""Long enough for a 3 km drive from the simulator's start with slip roads to spare."""
ALIGNMENT_POINT_M = 25.0
MAX_GRADE = 0.015
"""Below roadgen's 2 % motorway limit at 120 km/h, so its vertical curves fit between knots."""
MIN_RAMP_SPACING_M = 800.0
"""Deceleration lane, taper and slip road of one ramp clear of the next on the same carriageway."""
CLEAR_START_M = 400.0
CLEAR_END_M = 400.0
RAMP_REACH_M = (250.0, 350.0)
"""A slip road's open end lies this far along the carriageway from its nose ..."""
RAMP_OFFSET_M = (60.0, 90.0)
"""... and this far out to the side."""
DESIGN_SPEED_KMH = 110.0
"""roadgen's standard at this speed allows the 700 m minimum radius drawn here."""


@dataclass
class CorridorSpec:
    """What was drawn for one corridor (written to the manifest)."""

    seed: int
    lanes: int
    length_m: float
    curves: list[dict[str, float]] = field(default_factory=list)
    profile: list[tuple[float, float]] = field(default_factory=list)
    ramps: list[dict[str, object]] = field(default_factory=list)
    dropped_ramps: list[dict[str, object]] = field(default_factory=list)


def _alignment(rng: np.random.Generator, length: float) -> tuple[np.ndarray, np.ndarray, list[dict[str, float]]]:
    """Centre line (1 m stations) of straights, clothoids and arcs: xy (n, 2), heading (n,)."""
    kappa: list[np.ndarray] = []
    curves: list[dict[str, float]] = []
    total = 0.0
    while total < length:
        straight = rng.uniform(200.0, 800.0)
        radius = math.exp(rng.uniform(math.log(700.0), math.log(5000.0))) * rng.choice([-1.0, 1.0])
        spiral = min(abs(radius) / rng.uniform(3.0, 9.0), 300.0)
        arc = rng.uniform(150.0, 700.0)
        k = 1.0 / radius
        kappa += [np.zeros(round(straight)), np.linspace(0.0, k, round(spiral), endpoint=False),
                  np.full(round(arc), k), np.linspace(k, 0.0, round(spiral), endpoint=False)]
        curves.append({"radius_m": round(radius, 1), "clothoid_m": round(spiral, 1), "arc_m": round(arc, 1)})
        total += straight + 2 * spiral + arc
    k = np.concatenate(kappa)[: int(length) + 1]
    heading = np.concatenate([[0.0], np.cumsum(k[:-1])])
    xy = np.stack([np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]))]),
                   np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]))])], axis=1)
    return xy, heading, curves


def _profile(rng: np.random.Generator, length: float) -> list[tuple[float, float]]:
    knots = [(0.0, 0.0)]
    while knots[-1][0] < length:
        gap = rng.uniform(600.0, 1200.0)
        s = min(knots[-1][0] + gap, length)
        dz = rng.uniform(-1.0, 1.0) * MAX_GRADE * (s - knots[-1][0])
        knots.append((round(s, 1), round(knots[-1][1] + dz, 2)))
    return knots


def _ramps(rng: np.random.Generator, length: float) -> list[dict[str, object]]:
    count = int(round(rng.uniform(2.0, 6.0) * length / 5000.0))
    ramps: list[dict[str, object]] = []
    for _ in range(50 * count):
        if len(ramps) == count:
            break
        at = rng.uniform(CLEAR_START_M, length - CLEAR_END_M)
        side = str(rng.choice(["right", "left"]))
        if any(r["side"] == side and abs(float(r["at"]) - at) < MIN_RAMP_SPACING_M for r in ramps):
            continue
        on = bool(rng.random() < 0.5)
        ramps.append({"at": round(at, 1), "side": side, "on": on, "reach_m": round(rng.uniform(*RAMP_REACH_M), 1),
                      "offset_m": round(rng.uniform(*RAMP_OFFSET_M), 1)})
    ramps.sort(key=lambda r: float(r["at"]))
    for i, r in enumerate(ramps):
        r["name"] = f"{'on' if r['on'] else 'off'}{i}"
    return ramps


def _ramp_end(ramp: dict[str, object], xy: np.ndarray, heading: np.ndarray,
              profile: list[tuple[float, float]]) -> tuple[float, float, float]:
    """Open end of a slip road: downstream of an exit, upstream of an entry, in the carriageway's
    travel direction (the left carriageway travels against the stations), out to its right."""
    downstream = 1.0 if ramp["side"] == "right" else -1.0
    ahead = float(ramp["reach_m"]) * downstream * (1.0 if not ramp["on"] else -1.0)
    i = int(np.clip(round(float(ramp["at"]) + ahead), 0, len(xy) - 1))
    lateral = -float(ramp["offset_m"]) * downstream
    z = float(np.interp(i, [p[0] for p in profile], [p[1] for p in profile]))
    return (float(xy[i, 0] - lateral * math.sin(heading[i])), float(xy[i, 1] + lateral * math.cos(heading[i])), z)


_ROAD_CHILDREN = ("link", "type", "planView", "elevationProfile", "lateralProfile", "lanes", "objects", "signals",
                  "surface", "railroad")
"""Schema order of a <road>'s children (OpenDRIVE 1.6-1.8 XSD)."""


def _fix_xodr(path: Path) -> int:
    """Give every lane whose first <width> starts after sOffset 0 a constant record from 0, and put
    each road's children in schema order (roadgen writes <elevationProfile> first): see the top."""
    tree = etree.parse(str(path))
    for road in tree.getroot().iter("road"):
        kids = list(road)
        rank = {tag: i for i, tag in enumerate(_ROAD_CHILDREN)}
        for kid in kids:
            road.remove(kid)
        for kid in sorted(kids, key=lambda k: rank.get(k.tag, len(rank)) if isinstance(k.tag, str) else len(rank)):
            road.append(kid)
    fixed = 0
    for lane in tree.getroot().iter("lane"):
        widths = lane.findall("width")
        if widths and float(widths[0].get("sOffset", "0")) > 0.0:
            first = widths[0]
            rec = etree.Element("width", sOffset="0", a=first.get("a", "0"), b="0", c="0", d="0")
            first.addprevious(rec)
            fixed += 1
    tree.write(str(path), xml_declaration=True, encoding="UTF-8")
    return fixed


def write_corridor(seed: int, path: Path, length_m: float = CORRIDOR_LENGTH_M) -> CorridorSpec:
    """Draw corridor `seed` and write it as OpenDRIVE to `path` (written via a temporary file)."""
    import roadgen

    rng = np.random.default_rng(seed)
    xy, heading, curves = _alignment(rng, length_m)
    profile = _profile(rng, length_m)
    spec = CorridorSpec(seed=seed, lanes=int(rng.integers(2, 5)), length_m=length_m, curves=curves, profile=profile,
                        ramps=_ramps(rng, length_m))
    points = [(float(x), float(y), 0.0) for x, y in xy[:: int(ALIGNMENT_POINT_M)]]
    tmp = path.with_name(path.name + ".tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    ramps = list(spec.ramps)
    while True:
        rmap = roadgen.Map(name=f"corridor_{seed:03d}")
        corridor = rmap.add_corridor("m", points, design_speed=DESIGN_SPEED_KMH, lanes=spec.lanes, profile=profile)
        for r in ramps:
            corridor.add_ramp(str(r["name"]), float(r["at"]), _ramp_end(r, xy, heading, profile),
                              side=str(r["side"]), on=bool(r["on"]))
        try:
            rmap.add_plan(corridor.plan())
            rmap.export_opendrive(str(tmp), trace=False)
            break
        except ValueError as exc:
            if not ramps:
                raise
            dropped = ramps.pop()
            spec.dropped_ramps.append({**dropped, "why": str(exc).splitlines()[-1].strip()[:200]})
    spec.ramps = ramps
    _fix_xodr(tmp)
    tmp.replace(path)
    return spec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--count", type=int, default=1)
    ap.add_argument("--first", type=int, default=0)
    args = ap.parse_args()
    specs = [asdict(write_corridor(k, args.out / f"corridor_{k:03d}.xodr"))
             for k in range(args.first, args.first + args.count)]
    (args.out / "corridors.json").write_text(json.dumps(specs, indent=1))
    for s in specs:
        print(f"corridor {s['seed']}: {s['lanes']} lanes each way, {len(s['ramps'])} ramps "
              f"({len(s['dropped_ramps'])} dropped), {len(s['curves'])} curves")


if __name__ == "__main__":
    main()
