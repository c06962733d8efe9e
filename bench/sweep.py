"""Generalisation sweep (issue #13): simulate -> build -> check -> compare on maps nobody tuned to.

`make sweep` = `python bench/sweep.py`: every shared map at drive seeds 1, 2, 3 (1 km along the
simulator's default route) and `--corridors` (20) random roadgen motorway corridors
(bench/corridors.py; corridor k drawn from seed k) at drive seeds 1 and 2 (3 km). Each case is
`bench/run.py`'s `bench_map`, exactly as a shared map in `make bench`. Prints one table (map, seed,
built or the one-line error, ASAM errors, leap, kink, boundaries and centre RMSE, lane count,
lane-graph agreement and breaks, the share of the driven road
built: `compare --trajectory`) and a summary: medians, worst cases, failures with their cause,
and the issue #13 done-when check (the share of cases with boundaries <= 0.10 m, centre <= 0.15 m,
lane count >= 0.98 and lane graph >= 0.98; every map valid; none above 0.5 m boundaries RMSE).

`make sweep-quick` = `--quick`: a FIXED mixed subset (QUICK_MAPS: single roads, a crest with
superelevation, an exit, a merge, the ASAM entry/exit junction map, a 2+1 road; seed 1) plus
corridors 1 and 2 at seed 1, all 1 km drives.

Resumable: every case writes OUT/rows/<case>.json with the commit (`-dirty` when src/ or bench/
has uncommitted changes) and its arguments; a case whose row exists for the same commit and
arguments is not run again (`--force` runs it anyway). `--jobs N` runs N cases at once (each case
is one process at a time; the 2-core machine takes `--jobs 2`). Corridor maps are written to
OUT/corridors/ (never committed).

Time per case (simulate + build + check + compare), measured on the shared 2-core machine with
other work beside it (load average 15-20): a 1 km drive on a shared map 106-181 s, a 1 km drive
on a corridor 128-137 s, a 3 km corridor drive: see BENCHMARKS.md "Generalisation sweep". The
quick run (8 cases) took 19 min there; the full sweep (24 shared maps x 3 + 20 corridors x 2 = 112
cases, corridors at 3 km) is ~4-6 h there at --jobs 1, so it is for a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from run import REPO, SHARED, bench_map, print_reader_messages, print_table  # noqa: E402

from lidar2xodr.config import Config  # noqa: E402

SHARED_SEEDS = (1, 2, 3)
CORRIDOR_SEEDS = (1, 2)
SHARED_LENGTH_M = 1000.0
CORRIDOR_LENGTH_M = 3000.0
QUICK_MAPS = ("AB_RQ31_R2000", "crest-curve", "highway_exit", "highway_merge", "Ex_Entry_Exit", "two_plus_one")
QUICK_CORRIDORS = (1, 2)
QUICK_LENGTH_M = 1000.0

# issue #13 "done when"
BOUNDARIES_MAX_M = 0.10
CENTRE_MAX_M = 0.15
LANE_COUNT_MIN = 0.98
LANE_GRAPH_MIN = 0.98
SHARE_MIN = 0.95
BOUNDARIES_NEVER_M = 0.5
UNHELD_ALL = 0.99
"""A case whose reference lanes lie this much outside every built lane of their direction is told apart."""
LEAP_MAX_M = 1e-3
KINK_MAX_RAD = 1e-3

TABLE_COLS = ["map", "seed", "built", "asam_errors", "leap_m", "kink_rad", "boundaries_rmse", "centerline_rmse",
              "lane_count", "lane_graph", "lane_graph_breaks", "road_marks", "driven"]


def commit_id() -> str:
    """HEAD, with -dirty when src/ or bench/ differ from it (results then belong to no commit)."""
    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short=12", "HEAD") or "unknown"
    return head + ("-dirty" if git("status", "--porcelain", "src", "bench") else "")


def cases(args: argparse.Namespace) -> list[dict]:
    """Every case of this run: kind, map name, map file (corridors: to be written), seed, drive length."""
    out: list[dict] = []
    maps = sorted((SHARED / "maps").glob("*/*.xodr"))
    if args.quick:
        maps = [p for p in maps if p.stem in QUICK_MAPS]
    for path in maps:
        if args.maps and path.stem not in args.maps:
            continue
        for seed in (SHARED_SEEDS[:1] if args.quick else SHARED_SEEDS):
            out.append({"kind": "shared", "map": path.stem, "xodr": str(path), "seed": seed,
                        "length_m": args.length_m or (QUICK_LENGTH_M if args.quick else SHARED_LENGTH_M)})
    ids = QUICK_CORRIDORS if args.quick else range(1, args.corridors + 1)
    for k in ids:
        name = f"corridor_{k:03d}"
        if args.maps and name not in args.maps:
            continue
        for seed in (CORRIDOR_SEEDS[:1] if args.quick else CORRIDOR_SEEDS):
            out.append({"kind": "corridor", "map": name, "corridor": k, "seed": seed,
                        "xodr": str(args.out / "corridors" / f"{name}.xodr"),
                        "length_m": args.length_m or (QUICK_LENGTH_M if args.quick else CORRIDOR_LENGTH_M)})
    return out


def case_id(case: dict) -> str:
    return f"{case['map']}-s{case['seed']}-{case['length_m']:g}m"


_CORRIDOR_LOCK = threading.Lock()


def reused_drive(case: dict, drives_from: list[Path]) -> Path | None:
    """The drive of this case in an earlier sweep's output, when that case finished there (its row exists)."""
    for folder in drives_from:
        drive = folder / "cases" / case_id(case) / "drive"
        done = (folder / "rows" / f"{case_id(case)}.json").exists()
        if done and (drive / "meta.yaml").exists():
            return drive
    return None


def run_case(case: dict, out: Path, commit: str, force: bool, drives_from: list[Path] | None = None) -> dict:
    """One case, or its stored row when it already ran for this commit and these arguments."""
    row_path = out / "rows" / f"{case_id(case)}.json"
    key = {"commit": commit, "case": {k: v for k, v in case.items()}}
    if row_path.exists() and not force:
        old = json.loads(row_path.read_text())
        if old.get("key") == key:
            return old["row"]
    t0 = time.perf_counter()
    with _CORRIDOR_LOCK:  # both seeds of a corridor share its map: with --jobs 2 they raced to write it
        if case["kind"] == "corridor" and not Path(case["xodr"]).exists():
            from corridors import write_corridor

            try:
                write_corridor(case["corridor"], Path(case["xodr"]))
            except Exception as exc:  # noqa: BLE001 - a corridor roadgen refuses is a row, not a crash
                row = {"map": case["map"], "seed": case["seed"], "error": f"corridor: {exc}".splitlines()[0][:200]}
                _store(row_path, key, row)
                return row
    row = bench_map(case["map"], Path(case["xodr"]), out / "cases", case["length_m"], LANE_COUNT_MIN,
                    seed=case["seed"], case=case_id(case), drive=reused_drive(case, drives_from or []))
    row.update(kind=case["kind"], case_s=round(time.perf_counter() - t0, 1))
    _store(row_path, key, row)
    return row


def _store(path: Path, key: dict, row: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"key": key, "row": row}, indent=1, default=str))
    tmp.replace(path)


def valid_map(row: dict) -> bool:
    """Built, 0 ASAM errors, leap <= 1 mm, kink <= 1 mrad."""
    return ("error" not in row and "check_error" not in row and row.get("asam_errors") == 0
            and (row.get("leap_m") or 0.0) <= LEAP_MAX_M and (row.get("kink_rad") or 0.0) <= KINK_MAX_RAD)


def meets_targets(row: dict) -> bool:
    """A valid map with boundaries, centre, lane count and lane graph all within issue #13's targets."""
    def num(k: str, bad: float) -> float:
        v = row.get(k)
        return bad if v is None else float(v)
    return (valid_map(row) and num("boundaries_rmse", 1e9) <= BOUNDARIES_MAX_M
            and num("centerline_rmse", 1e9) <= CENTRE_MAX_M and num("lane_count", -1.0) >= LANE_COUNT_MIN
            and num("lane_graph", -1.0) >= LANE_GRAPH_MIN)


def failure_cause(row: dict) -> str | None:
    """One line saying why a case misses the targets (None when it meets them)."""
    if "error" in row:
        return str(row["error"])
    if "check_error" in row:
        return "check: " + str(row["check_error"])
    if row.get("asam_errors"):
        return f"{row['asam_errors']} ASAM error(s)"
    if (row.get("leap_m") or 0.0) > LEAP_MAX_M:
        return f"geometry leap {row['leap_m']:.4f} m"
    if (row.get("kink_rad") or 0.0) > KINK_MAX_RAD:
        return f"heading kink {row['kink_rad']:.4f} rad"
    misses = []
    limits = (("boundaries_rmse", BOUNDARIES_MAX_M, "above"), ("centerline_rmse", CENTRE_MAX_M, "above"),
              ("lane_count", LANE_COUNT_MIN, "below"), ("lane_graph", LANE_GRAPH_MIN, "below"))
    for key, limit, worse in limits:
        v = row.get(key)
        if v is None or (v > limit if worse == "above" else v < limit):
            misses.append(f"{key} {'n/a' if v is None else f'{v:.3f}'} {worse} {limit:g}")
    if misses and row.get("lane_graph_breaks"):
        misses.append(f"{row['lane_graph_breaks']} lane-graph break(s)")
    unheld, evaluated = row.get("lane_graph_unheld_m"), row.get("lane_graph_eval_m")
    if misses and unheld is not None and evaluated and unheld >= UNHELD_ALL * evaluated:
        misses.append("no built lane of the reference's travel direction lies under its lanes "
                      "(wrong-way or misplaced lanes)")
    return "; ".join(misses) or None


def summarise(rows: list[dict]) -> dict:
    """Medians, worst cases, failures and the issue #13 done-when check over all rows."""
    built = [r for r in rows if "error" not in r and r.get("boundaries_rmse") is not None]

    def median(key: str) -> float | None:
        vals = [float(r[key]) for r in built if r.get(key) is not None]
        return statistics.median(vals) if vals else None

    def worst(key: str, high: bool) -> list[dict]:
        have = [r for r in built if r.get(key) is not None]
        have.sort(key=lambda r: (-float(r[key]) if high else float(r[key]), r["map"], r["seed"]))
        return [{"map": r["map"], "seed": r["seed"], key: r[key]} for r in have[:3]]

    n = len(rows)
    meeting = sum(meets_targets(r) for r in rows)
    valid = sum(valid_map(r) for r in rows)
    above = [f"{r['map']} s{r['seed']}" for r in rows
             if r.get("boundaries_rmse") is not None and r["boundaries_rmse"] > BOUNDARIES_NEVER_M]
    failures = [{"map": r["map"], "seed": r["seed"], "cause": failure_cause(r)} for r in rows if not meets_targets(r)]
    share = meeting / n if n else 0.0
    return {
        "cases": n,
        "built": len(built),
        "valid_maps": valid,
        "medians": {k: median(k) for k in ("boundaries_rmse", "centerline_rmse", "lane_count", "lane_graph",
                                           "road_marks", "driven")},
        "worst": {"boundaries_rmse": worst("boundaries_rmse", True), "centerline_rmse": worst("centerline_rmse", True),
                  "lane_count": worst("lane_count", False), "lane_graph": worst("lane_graph", False),
                  "road_marks": worst("road_marks", False), "driven": worst("driven", False)},
        "meeting_targets": meeting,
        "share_meeting_targets": share,
        "above_0_5_m": above,
        "failures": failures,
        "done": bool(n and valid == n and share >= SHARE_MIN and not above),
    }


def format_summary(s: dict) -> str:
    def f(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f}"
    lines = [f"cases {s['cases']}, built {s['built']}, valid maps (0 ASAM errors, leap <= 1 mm, kink <= 1 mrad) "
             f"{s['valid_maps']}",
             "medians: " + ", ".join(f"{k} {f(v)}" for k, v in s["medians"].items())]
    for key, worst in s["worst"].items():
        lines.append(f"worst {key}: " + ", ".join(f"{w['map']} s{w['seed']} {f(w[key])}" for w in worst))
    lines.append(f"issue #13 targets (boundaries <= {BOUNDARIES_MAX_M} m, centre <= {CENTRE_MAX_M} m, lane count >= "
                 f"{LANE_COUNT_MIN}, lane graph >= {LANE_GRAPH_MIN}): {s['meeting_targets']}/{s['cases']} = "
                 f"{100 * s['share_meeting_targets']:.0f} % (needs >= {100 * SHARE_MIN:.0f} %)")
    lines.append(f"cases above {BOUNDARIES_NEVER_M} m boundaries RMSE: {len(s['above_0_5_m'])} "
                 + (f"({', '.join(s['above_0_5_m'])})" if s["above_0_5_m"] else ""))
    lines.append("done when met: " + ("yes" if s["done"] else "no"))
    if s["failures"]:
        lines.append("failures:")
        lines += [f"  {x['map']} s{x['seed']}: {x['cause']}" for x in s["failures"]]
    return "\n".join(lines)


CHANGE_KEYS = (("boundaries_rmse", 1), ("centerline_rmse", 1), ("lane_count", -1), ("lane_graph", -1),
               ("road_marks", -1), ("driven", -1))
"""Compared metrics and which way is worse (+1: a rise, -1: a fall)."""
CHANGE_TOL = {"boundaries_rmse": 0.002, "centerline_rmse": 0.002, "lane_count": 0.002, "lane_graph": 0.002,
              "road_marks": 0.002, "driven": 0.002}
LIKE_FOR_LIKE = ("boundaries_rmse", "centerline_rmse")
"""RMSEs that are also compared on the common stretch where a case's driven share rose (`common_rmse`)."""


def _sampled(reference: Path, *paths: Path) -> tuple[Any, float, Any, list[Any]]:
    """`compare`'s settings, heading tolerance [rad], and the sampled carriageways of the reference and of
    each map (in the reference's frame)."""
    from lidar2xodr import evaluation as ev

    cfg = Config().evaluation
    ref_map = ev._load(reference)
    maps = []
    for path in paths:
        m = ev._load(path)
        maps.append(ev.carriageways(m, cfg.sample_step_m, ev._frame_transform(m, ref_map, path)[0]))
    return cfg, math.radians(cfg.heading_tolerance_deg), ev.carriageways(ref_map, cfg.sample_step_m), maps


def common_rmse(new: Path, old: Path, reference: Path, near_m: float = 1.0) -> dict[str, tuple[float, float]]:
    """Boundaries and centre RMSE of the old and the new map on the road both built.

    A sample of one map counts when the other map has a line of the same kind (boundary, centre) and
    travel direction within `near_m` of it; each map's counted samples are measured against the
    reference as `compare` does (rule 1). Returns {key: (old RMSE, new RMSE)}; NaN where nothing is common.
    """
    from lidar2xodr import evaluation as ev

    cfg, tol, ref, maps = _sampled(reference, old, new)
    out: dict[str, list[float]] = {"boundaries_rmse": [], "centerline_rmse": []}
    for a, b in ((maps[0], maps[1]), (maps[1], maps[0])):
        for key, lines_a, lines_b, ref_lines, w in (
                ("boundaries_rmse", a.boundaries, b.boundaries, ref.boundaries, a.boundaries.weight),
                ("centerline_rmse", a.centre, b.centre, ref.centre, a.centre.weight)):
            if len(lines_a.xy) == 0 or len(lines_b.xy) == 0:
                out[key].append(float("nan"))
                continue
            d_other, _, past = ev.nearest(lines_b, lines_a.xy, lines_a.hdg, tol)
            common = (d_other <= near_m) & ~past
            d_ref, _, _ = ev.nearest(ref_lines, lines_a.xy[common], lines_a.hdg[common], tol)
            wc = w[common]
            out[key].append(math.sqrt(float(np.sum(wc * d_ref**2) / wc.sum())) if wc.sum() > 0 else float("nan"))
    return {k: (v[0], v[1]) for k, v in out.items()}


def common_marks(new: Path, old: Path, reference: Path) -> tuple[float, float, float, float]:
    """Road-mark agreement (`compare`'s rule 10) of the old and the new map on the reference boundary
    samples that both maps match, and each map's whole matched length: (old, new, old m, new m).

    A map whose lines lie nearer the truth matches more of the reference's lines, and the added
    length carries its own marks: its agreement is then an average over other road, like an RMSE
    over more road (`common_rmse`)."""
    from lidar2xodr import evaluation as ev

    cfg, tol, ref, maps = _sampled(reference, old, new)
    per_map = []
    for gen in maps:
        q = gen.boundary_query
        if not q.any() or len(ref.boundaries.xy) == 0:
            per_map.append((np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool),
                            np.zeros(0)))
            continue
        d, v, _ = ev.nearest(ref.boundaries, gen.boundaries.xy[q], gen.boundaries.hdg[q], tol)
        matched = (d <= cfg.mark_match_m) & (ref.boundary_gap[v] >= cfg.mark_match_m)
        per_map.append((v, matched, gen.boundary_mark[q] == ref.boundary_mark[v], gen.boundaries.weight[q]))
    both = np.intersect1d(per_map[0][0][per_map[0][1]], per_map[1][0][per_map[1][1]])
    out = []
    for v, matched, agree, w in per_map:
        sel = matched & np.isin(v, both)
        out.append(float(np.sum(w[sel & agree]) / np.sum(w[sel])) if np.sum(w[sel]) > 0 else float("nan"))
    return out[0], out[1], float(np.sum(per_map[0][3][per_map[0][1]])), float(np.sum(per_map[1][3][per_map[1][1]]))


def changes(rows: list[dict], before: Path, todo: list[dict], out: Path) -> list[dict]:
    """Per case, the metrics that moved beyond CHANGE_TOL against an earlier sweep's rows (same case ids).

    Where the driven share rose, a rise of an RMSE in LIKE_FOR_LIKE is measured again on the road both
    maps built (`common_rmse`): it is worse only when it is worse there; otherwise it is listed with both
    numbers as accuracy on the added road, not a regression (the added road still counts in the RMSE
    and in the targets). Two maps that share no road at all (the earlier one built a stretch the new
    one does not, or a street beside the drive) are different road: the driven share decides. Likewise
    a fall of the road-mark agreement where the new map matches more of the reference's lines is
    measured again on the samples both maps match (`common_marks`)."""
    items = []
    for case, row in zip(todo, rows, strict=True):
        path = before / "rows" / f"{case_id(case)}.json"
        if not path.exists():
            continue
        old = json.loads(path.read_text())["row"]
        item = {"case": case_id(case), "worse": [], "better": []}
        if ("error" in old) != ("error" in row):
            (item["worse"] if "error" in row else item["better"]).append(
                f"built -> {row['error']}" if "error" in row else f"{old['error']} -> built")
        more_road = (old.get("driven") is not None and row.get("driven") is not None
                     and row["driven"] - old["driven"] > CHANGE_TOL["driven"])
        common = marks = None
        for key, sign in CHANGE_KEYS:
            a, b = old.get(key), row.get(key)
            if a is None or b is None or abs(b - a) <= CHANGE_TOL[key]:
                continue
            text = f"{key} {a:.3f} -> {b:.3f}"
            worse = sign * (b - a) > 0
            if worse and more_road and key in LIKE_FOR_LIKE:
                maps = (before / "cases" / case_id(case) / "map.xodr", out / "cases" / case_id(case) / "map.xodr")
                if common is None and all(p.exists() for p in maps):
                    common = common_rmse(maps[1], maps[0], Path(case["xodr"]))
                if common is not None:
                    c_old, c_new = common[key]
                    if math.isnan(c_old) and math.isnan(c_new):
                        text += " over more road; the two maps share no road (the driven share decides)"
                        worse = False
                    else:
                        text += f" over more road; on the common stretch {c_old:.3f} -> {c_new:.3f}"
                        worse = not (c_new - c_old <= CHANGE_TOL[key])
            if worse and key == "road_marks":
                maps = (before / "cases" / case_id(case) / "map.xodr", out / "cases" / case_id(case) / "map.xodr")
                if marks is None and all(p.exists() for p in maps):
                    marks = common_marks(maps[1], maps[0], Path(case["xodr"]))
                if marks is not None and marks[3] > marks[2] and not math.isnan(marks[0] + marks[1]):
                    text += (f" over more matched line ({marks[2]:.0f} -> {marks[3]:.0f} m); on the samples both match "
                             f"{marks[0]:.3f} -> {marks[1]:.3f}")
                    worse = marks[0] - marks[1] > CHANGE_TOL[key]
            (item["worse"] if worse else item["better"]).append(text)
        if item["worse"] or item["better"]:
            items.append(item)
    return sorted(items, key=lambda x: (not x["worse"], x["case"]))


def format_changes(items: list[dict]) -> str:
    worse = sum(bool(x["worse"]) for x in items)
    lines = [f"changed cases against the earlier sweep: {len(items)} ({worse} with a metric worse)"]
    for x in items:
        lines.append(f"  {x['case']}: " + "; ".join([f"WORSE {w}" for w in x["worse"]] + x["better"]))
    return "\n".join(lines)


def table_rows(rows: list[dict]) -> list[dict]:
    out = []
    for r in rows:
        t = dict(r)
        t["built"] = "yes" if "error" not in r else str(r["error"])[:80]
        out.append(t)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description="issue #13 generalisation sweep")
    ap.add_argument("--out", type=Path, default=REPO / "bench-out" / "sweep")
    ap.add_argument("--quick", action="store_true", help="the fixed ~20 min subset (make sweep-quick)")
    ap.add_argument("--length-m", type=float, default=None,
                    help=f"drive length (default {SHARED_LENGTH_M:g} m shared, {CORRIDOR_LENGTH_M:g} m corridors)")
    ap.add_argument("--corridors", type=int, default=20, help="random corridors 1..N")
    ap.add_argument("--maps", nargs="*", default=None, help="only these map stems / corridor_NNN names")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at once")
    ap.add_argument("--force", action="store_true", help="run cases again even when their row exists")
    ap.add_argument("--drives-from", type=Path, default=None,
                    help="build the drives an earlier sweep (its --out) simulated instead of simulating again, "
                         "for each case it finished (this --out's own finished drives are always reused; the "
                         "simulator gives the same drive for the same map, seed and length: only for changes "
                         "outside simulation/)")
    ap.add_argument("--reverse", action="store_true",
                    help="run the cases last first (two sweeps of two commits, each --drives-from the other, meet in "
                         "the middle and simulate every drive once)")
    ap.add_argument("--against", type=Path, default=None,
                    help="an earlier sweep's --out: list every case whose numbers changed, worse ones first")
    args = ap.parse_args()
    if not (SHARED / "maps").is_dir():
        print(f"shared maps not found at {SHARED}: only corridors are swept")
    todo = cases(args)
    commit = commit_id()
    print(f"{len(todo)} cases, commit {commit}, {args.jobs} job(s), rows in {args.out / 'rows'}", flush=True)

    def one(case: dict) -> dict:
        reuse = [args.out] + ([args.drives_from] if args.drives_from else [])
        row = run_case(case, args.out, commit, args.force, reuse)
        print(json.dumps({k: row.get(k) for k in ["map", "seed", "case_s", *TABLE_COLS[2:], "error"] if k in row},
                         default=str), flush=True)
        return row

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        rows = list(pool.map(one, todo[::-1] if args.reverse else todo))
    if args.reverse:
        rows = rows[::-1]
    summary = summarise(rows)
    (args.out / "sweep.json").write_text(json.dumps({"command": " ".join(sys.argv), "commit": commit, "rows": rows,
                                                     "summary": summary}, indent=1, default=str))
    print_table(table_rows(rows), TABLE_COLS)
    # what check's readers said (issue #6), verbatim below
    print_table(rows, ["map", "seed", "asam_warnings", "sumo_warnings", "sumo_errors", "pyxodr_ok", "check_error"])
    print_reader_messages(rows)
    print()
    print(format_summary(summary))
    if args.against is not None:
        print()
        print(format_changes(changes(rows, args.against, todo, args.out)))


if __name__ == "__main__":
    main()
