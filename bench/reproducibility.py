"""The paper's reproducibility protocol (issue #16): four drives of one road, three compared against the fourth.

`python bench/reproducibility.py [--map asam/AB_RQ31_R2000.xodr] [--length-m 2000] [--out DIR]`
(`make bench-repro`). Four drives of the same shared map differ in everything the simulator
draws from the seed (traffic, ego lanes and lane changes, sensor and GNSS noise), in traffic
density, and in a constant GNSS bias of 0, 0.5, 1 and 2 m (`simulate --gnss-bias-m`, its
direction drawn from the seed). Each drive is built alone; drives 1-3 are compared with drive 4
(`compare BUILT_k BUILT_4`: the paper's lateral distance, RMSE / mean / sigma; paper: 0.24 /
0.20 / 0.13 m) and every drive with the truth. A single build cannot remove its drive's GNSS
bias, so the drive-to-drive numbers measure the bias as much as the method; `compare --align`
(the same pair after a rigid 2D registration of the two maps) measures the shape alone. Then the
four drives are fused in one build (fusion.py), placed by the mean of their GNSS and by drive 1's
(`--anchor 1`, as a drive with RTK corrections would be), each against the truth; the consensus
build is repeated on a Dask LocalCluster (`--scheduler local`) and its bytes compared. Prints two
Markdown tables; results in OUT/<map>.json. Resumable: a drive or build that exists is not redone.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from run import CLI, REPO, SHARED, print_table, run  # noqa: E402

DRIVES = (  # seed, traffic, GNSS bias (m)
    (1, "low", 0.0),
    (2, "mid", 0.5),
    (3, "high", 1.0),
    (4, "mid", 2.0),
)
PAPER = {"rmse_m": 0.24, "mean_m": 0.20, "std_m": 0.13}


def _drive(xodr: Path, base: Path, seed: int, traffic: str, bias: float, length_m: float) -> dict:
    drive, built = base / f"drive{seed}", base / f"map{seed}.xodr"
    row: dict = {"drive": seed, "traffic": traffic, "gnss_bias_m": bias}
    if not (drive / "meta.yaml").is_file():
        rc, t, log = run(CLI + ["simulate", str(xodr), str(drive), "--length-m", str(length_m), "--seed", str(seed),
                                "--traffic", traffic, "--gnss-bias-m", str(bias)])
        if rc != 0:
            return {**row, "error": "simulate: " + log.strip().splitlines()[-1]}
        row["simulate_s"] = round(t, 1)
    if not built.is_file():
        rc, t, log = run(CLI + ["build", str(drive), "-o", str(built)])
        if rc != 0:
            return {**row, "error": "build: " + log.strip().splitlines()[-1]}
        row["build_s"] = round(t, 1)
    row["map_path"] = str(built)
    return row


def _fused(base: Path, drives: list[dict], name: str, extra: list[str]) -> dict:
    built = base / f"{name}.xodr"
    row: dict = {"build": name, "options": " ".join(extra)}
    if not built.is_file():
        rc, t, log = run(CLI + ["build", *(str(base / f"drive{d['drive']}") for d in drives), "-o", str(built), *extra])
        if rc != 0:
            return {**row, "error": "build: " + log.strip().splitlines()[-1]}
        row["build_s"] = round(t, 1)
    row["map_path"] = str(built)
    return row


def _compare(generated: Path, reference: Path, out_json: Path, align: bool = False) -> dict:
    extra = ["--align"] if align else []
    rc, _, log = run(CLI + ["compare", str(generated), str(reference), "--json", str(out_json), *extra])
    if not out_json.is_file():
        return {"error": "compare: " + log.strip().splitlines()[-1]}
    m = json.loads(out_json.read_text())
    b = m["boundaries"]
    return {"rmse_m": b["rmse_m"], "mean_m": b["mean_m"], "std_m": b["std_m"], "eval_length_m": b["eval_length_m"],
            "lane_count": m["lane_count_agreement"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", default="asam/AB_RQ31_R2000.xodr", help="a map under the shared data's maps/")
    ap.add_argument("--length-m", type=float, default=2000.0)
    ap.add_argument("--out", type=Path, default=REPO / "bench-out" / "reproducibility")
    args = ap.parse_args()
    xodr = SHARED / "maps" / args.map
    if not xodr.is_file():
        sys.exit(f"{xodr}: shared map not found (set LIDAR2XODR_SHARED_DATA)")
    base = args.out / Path(args.map).stem
    base.mkdir(parents=True, exist_ok=True)
    drives = [_drive(xodr, base, seed, traffic, bias, args.length_m) for seed, traffic, bias in DRIVES]
    last = drives[-1]
    rows = []
    for d in drives:
        row = {k: d[k] for k in ("drive", "traffic", "gnss_bias_m")}
        if "error" in d:
            rows.append({**row, "error": d["error"]})
            continue
        truth = _compare(Path(d["map_path"]), xodr, base / f"truth{d['drive']}.json")
        row.update({f"truth_{k}": v for k, v in truth.items()})
        if d is not last and "error" not in last:
            pair = _compare(Path(d["map_path"]), Path(last["map_path"]), base / f"vs{last['drive']}_{d['drive']}.json")
            row.update({f"vs_drive{last['drive']}_{k}": v for k, v in pair.items()})
            pair = _compare(Path(d["map_path"]), Path(last["map_path"]),
                            base / f"vs{last['drive']}_{d['drive']}_aligned.json", align=True)
            row.update({f"aligned_{k}": v for k, v in pair.items()})
        rows.append(row)
        print(json.dumps(row), flush=True)
    fused = []
    if not any("error" in d for d in drives):
        for name, extra in (("fused_mean", []), ("fused_anchor1", ["--anchor", "1"]),
                            ("fused_mean_dask", ["--scheduler", "local"])):
            row = _fused(base, drives, name, extra)
            if "error" not in row:
                row.update({f"truth_{k}": v for k, v in _compare(Path(row["map_path"]), xodr,
                                                                   base / f"truth_{name}.json").items()})
            fused.append(row)
            print(json.dumps(row), flush=True)
        serial, dask = base / "fused_mean.xodr", base / "fused_mean_dask.xodr"
        if serial.is_file() and dask.is_file():
            fused[-1]["same_bytes_as_serial"] = serial.read_bytes() == dask.read_bytes()
    results = {"command": " ".join(sys.argv), "map": args.map, "length_m": args.length_m, "paper": PAPER,
               "drives": drives, "rows": rows, "fused": fused}
    (args.out / f"{Path(args.map).stem}.json").write_text(json.dumps(results, indent=2))
    key = f"vs_drive{last['drive']}"
    print_table(rows, ["drive", "traffic", "gnss_bias_m", "truth_rmse_m", "truth_mean_m", "truth_std_m",
                       "truth_lane_count", f"{key}_rmse_m", f"{key}_mean_m", f"{key}_std_m", "aligned_rmse_m",
                       "aligned_mean_m", "aligned_std_m", f"{key}_eval_length_m", "error"])
    print(f"\npaper (drive to drive): RMSE {PAPER['rmse_m']} m, mean {PAPER['mean_m']} m, sigma {PAPER['std_m']} m\n")
    print_table(fused, ["build", "options", "build_s", "truth_rmse_m", "truth_mean_m", "truth_std_m",
                        "truth_lane_count", "truth_eval_length_m", "same_bytes_as_serial", "error"])


if __name__ == "__main__":
    main()
