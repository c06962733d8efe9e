"""Sweep: simulate -> build -> check -> compare on EVERY shared map (issue #6: "every map built from
simulated drives of the shared maps ... loads without warnings").

Run with `.venv/bin/python bench/sweep.py [--length-m 1000] [--out DIR]` (`make sweep`). Each map
gets a drive of `--length-m` (default 1 km, seed 1) along the simulator's default route; the row says
whether a map was built (or the one-line error `build` gave), what `check` said (ASAM errors and
warnings, largest leap and kink, SUMO netconvert and pyxodr) and the accuracy against the map.
Targets are not applied here: many shared maps are test roads outside the motorway scope (an 80 m
road of double lines, a town); the table shows what happens on them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from run import SHARED, bench_map, print_reader_messages, print_table  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "bench-out" / "sweep")
    ap.add_argument("--length-m", type=float, default=1000.0)
    ap.add_argument("--maps", nargs="*", default=None, help="map file stems (default: all)")
    args = ap.parse_args()
    maps = sorted((SHARED / "maps").glob("*/*.xodr"))
    if not maps:
        print(f"shared maps not found at {SHARED}: nothing to sweep")
        return
    rows = []
    for path in maps:
        if args.maps and path.stem not in args.maps:
            continue
        row = bench_map(path.stem, path, args.out, args.length_m, 0.95)
        row["folder"] = path.parent.name
        print(json.dumps(row), flush=True)
        rows.append(row)
    (args.out / "sweep.json").write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=2))
    cols = ["folder", "map", "asam_errors", "asam_warnings", "leap_m", "kink_rad", "sumo_warnings", "sumo_errors",
            "pyxodr_ok", "boundaries_rmse", "centerline_rmse", "lane_count", "elevation_rmse", "error"]
    print_table(rows, cols)
    print_reader_messages(rows)

if __name__ == "__main__":
    main()
