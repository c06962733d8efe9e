"""The `lidar2xodr` command line: one thin typer command per pipeline stage.

Commands import their stage lazily so `--help` stays fast. Bad input raises InputError, which
becomes one line on stderr and exit code 2 (never a traceback). Any other exception is a bug of
ours: it becomes one line naming the exception and exit code 3, and the traceback is shown only
with LIDAR2XODR_DEBUG=1 (outputs are written atomically, so nothing half-written is left).
"""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console

from lidar2xodr import __version__
from lidar2xodr.errors import InputError, OutputError

app = typer.Typer(
    name="lidar2xodr",
    help="LiDAR test drives to ASAM OpenDRIVE maps and OpenSCENARIO traffic, without odometry.",
    rich_markup_mode="rich",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
out = Console()

F = TypeVar("F", bound=Callable[..., Any])


def _clean_errors(fn: F) -> F:
    """Turn expected failures into one line and exit code 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (InputError, OutputError) as exc:
            console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            console.print("[bold red]interrupted[/]")
            raise typer.Exit(130) from None
        except (typer.Exit, typer.Abort, typer.BadParameter):
            raise
        except Exception as exc:
            if os.environ.get("LIDAR2XODR_DEBUG"):
                raise
            console.print(f"[bold red]internal error:[/] {type(exc).__name__}: {exc} (a bug in lidar2xodr, "
                          "please report it; LIDAR2XODR_DEBUG=1 shows the traceback)", highlight=False, soft_wrap=True)
            raise typer.Exit(3) from None

    return wrapper  # type: ignore[return-value]


def _version(value: bool) -> None:
    if value:
        out.print(f"lidar2xodr {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version."),
) -> None:
    """LiDAR test drives to ASAM OpenDRIVE maps and OpenSCENARIO traffic."""


def write_json(path: Path, data: dict[str, Any]) -> None:
    from lidar2xodr.fileio import write_text

    write_text(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


ConfigOpt = typer.Option(None, "--config", "-c", help="YAML configuration (see README).")


@app.command()
@_clean_errors
def compare(
    generated: Path = typer.Argument(..., help="The generated .xodr."),
    reference: Path = typer.Argument(..., help="The reference .xodr (ground truth)."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the metrics as JSON."),
    config: Path | None = ConfigOpt,
) -> None:
    """The paper's lateral distance between two maps: RMSE, mean, sigma, lane count, widths, coverage."""
    from lidar2xodr.config import Config
    from lidar2xodr.evaluation import compare_maps, print_metrics

    metrics = compare_maps(generated, reference, Config.load(config).evaluation)
    print_metrics(metrics, out)
    if json_out:
        write_json(json_out, metrics)


@app.command()
@_clean_errors
def check(
    path: Path = typer.Argument(..., help="An .xodr map or an .xosc scenario."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the verdict as JSON."),
) -> None:
    """ASAM quality checker plus our continuity checks. Exit code 1 when the file has errors."""
    from lidar2xodr.check import check_file, print_check

    result = check_file(path)
    if json_out:
        write_json(json_out, result)
    print_check(result, out)
    if not result["ok"]:
        raise typer.Exit(1)


@app.command()
@_clean_errors
def build(
    drive: Path = typer.Argument(..., help="A drive: drive directory, scan folder, KITTI, bag/MCAP, aiMotive."),
    output: Path = typer.Option(..., "--output", "-o", help="The OpenDRIVE map to write."),
    report: Path | None = typer.Option(None, "--report", help="Write an HTML report with pictures here."),
    odometry: str | None = typer.Option(None, "--odometry", help="gnss | lidar | auto (default auto)."),
    data_format: str | None = typer.Option(None, "--format", help="Force the reader (see README)."),
    scenario: Path | None = typer.Option(None, "--scenario", help="Also write the OpenSCENARIO here."),
    keep_intermediate: Path | None = typer.Option(
        None, "--keep-intermediate", help="Keep markings.ply and lanes.json in this folder."
    ),
    allow_invalid: bool = typer.Option(False, "--allow-invalid", help="Write the map even if it fails check."),
    reference: Path | None = typer.Option(None, "--reference", help="A reference .xodr (ground truth): compare "
                                          "with it and draw it in the report."),
    config: Path | None = ConfigOpt,
) -> None:
    """The whole pipeline: extract markings, build lanes, export a checked OpenDRIVE map."""
    from lidar2xodr.config import Config
    from lidar2xodr.pipeline import BuildPipeline

    cfg = Config.load(config)
    if odometry:
        if odometry not in ("auto", "gnss", "lidar"):
            raise InputError("--odometry", f"unknown value {odometry!r} (gnss, lidar or auto)")
        cfg = cfg.model_copy(update={"extraction": cfg.extraction.model_copy(update={"odometry": odometry})})
    if reference is not None and not reference.is_file():
        raise InputError(reference, "reference map not found")
    result = BuildPipeline(
        drive, output, cfg, data_format=data_format, report_dir=report, scenario=scenario,
        keep_intermediate=keep_intermediate, allow_invalid=allow_invalid, reference=reference, console=console,
    ).run()
    from lidar2xodr.pipeline import print_summary

    print_summary(result, out)


@app.command()
@_clean_errors
def demo(
    out_dir: Path = typer.Option(Path("demo-out"), "--out", help="Where the demo writes everything."),
    length_m: float = typer.Option(3000.0, "--length-m", help="Length of the simulated drive."),
    seed: int = typer.Option(0, "--seed"),
) -> None:
    """Simulate a drive on the project's own demo road, build the map, check it, compare with the truth."""
    from lidar2xodr.pipeline import run_demo

    run_demo(out_dir, length_m=length_m, seed=seed, console=console, out=out)


@app.command()
@_clean_errors
def scenario(
    drive: Path = typer.Argument(..., help="Drive folder or track file: objects.csv, detections, aiMotive, A9 CSV."),
    map_path: Path = typer.Option(..., "--map", help="The OpenDRIVE map to place the traffic on."),
    out_path: Path = typer.Option(..., "--out", "-o", help="The OpenSCENARIO file to write (.xosc)."),
    ego_path: Path | None = typer.Option(None, "--ego", help="Ego poses when the drive has none: poses.csv "
                                          "layout or the extraction's *.trajectory.csv (LiDAR odometry)."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the summary as JSON."),
    config: Path | None = ConfigOpt,
) -> None:
    """OpenSCENARIO of the recorded traffic on a map, with cut-ins, cut-outs and lane changes."""
    from lidar2xodr.config import Config
    from lidar2xodr.export_scenario import export_scenario, print_summary
    from lidar2xodr.opendrive import OpenDriveMap
    from lidar2xodr.tracks import load_tracks, read_poses_csv

    cfg = Config.load(config)
    ego = read_poses_csv(ego_path) if ego_path else None
    geo = OpenDriveMap.load(map_path).geo_reference
    tracks = load_tracks(drive, ego, cfg=cfg, geo_reference=geo)
    ego = ego if ego is not None else tracks.ego
    if ego is None:
        raise InputError(drive, "no ego trajectory: the drive has no poses.csv; pass --ego POSES.csv")
    summary = export_scenario(ego, tracks, map_path, out_path, cfg)
    print_summary(summary, out, console)
    if json_out:
        write_json(json_out, summary.to_dict())


@app.command()
@_clean_errors
def simulate(
    map_path: Path = typer.Argument(..., metavar="MAP.xodr", help="The OpenDRIVE map to drive on."),
    out_dir: Path = typer.Argument(..., metavar="OUT_DIR", help="The drive directory to write."),
    start_road: str | None = typer.Option(None, "--start-road", help="First road (default: longest chain)."),
    speed_kmh: float = typer.Option(110.0, "--speed-kmh", help="Mean desired ego speed."),
    length_m: float | None = typer.Option(None, "--length-m", help="Drive length (default: one pass)."),
    sensor: str = typer.Option("livox-horizon", "--sensor", help="livox-horizon | pandar64."),
    traffic: str = typer.Option("mid", "--traffic", help="none | low | mid | high."),
    gnss_noise_m: float = typer.Option(0.05, "--gnss-noise-m", help="GNSS sigma per horizontal axis (m)."),
    gnss_outage: bool = typer.Option(False, "--gnss-outage", help="Add GNSS outages with INS drift."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random choice."),
    rosbag: bool = typer.Option(False, "--rosbag", help="Also write drive.mcap (ROS 2)."),
    preview: bool = typer.Option(False, "--preview", help="Also write a close-up per 200 m under preview/."),
    roadside: bool = typer.Option(False, "--roadside", help="Terrain, trees, signs, noise barriers beside the "
                                  "road (needed by --odometry lidar)."),
) -> None:
    """Turn any OpenDRIVE map into a simulated LiDAR test drive with ground truth."""
    from pydantic import ValidationError

    from lidar2xodr.simulation import SimOptions
    from lidar2xodr.simulation import simulate as run_simulation

    raw = dict(start_road=start_road, speed_kmh=speed_kmh, length_m=length_m, sensor=sensor, traffic=traffic,
               gnss_noise_m=gnss_noise_m, gnss_outage=gnss_outage, seed=seed, rosbag=rosbag, preview=preview,
               roadside=roadside)
    try:
        opts = SimOptions(**raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        name = "--" + str(err["loc"][0]).replace("_", "-")
        raise InputError(name, f"{err['msg']} (got {err.get('input')!r})") from None
    s = run_simulation(map_path, out_dir, opts, console=console)
    out.print(f"wrote {s.out_dir}: {s.scans} scans, {s.points:,} points, {s.length_m / 1000:.2f} km in "
              f"{s.duration_s:.0f} s ({s.mean_speed_kmh:.0f} km/h), {s.passes} pass(es) over roads "
              f"{', '.join(s.roads[:8])}{' ...' if len(s.roads) > 8 else ''}; {s.vehicles} vehicles seen, "
              f"{s.lane_changes} ego lane changes")
    out.print(f"preview: {s.preview}")



@app.command()
@_clean_errors
def extract(
    drive: Path = typer.Argument(..., metavar="DRIVE", help="Recorded drive: drive dir, scan folder, KITTI raw, "
                                 "ROS bag / MCAP, aiMotive sequence."),
    output: Path = typer.Option(..., "--output", "-o", help="The marking cloud to write (.ply + sidecars)."),
    format: str | None = typer.Option(None, "--format", help="drive | aimotive | kitti_raw | rosbag | folder "
                                         "(default: detected)."),
    odometry: str | None = typer.Option(None, "--odometry", help="auto | gnss | lidar (default: from config)."),
    topic: str | None = typer.Option(None, "--topic", help="PointCloud2 topic of a bag."),
    pose_topic: str | None = typer.Option(None, "--pose-topic", help="Pose topic of a bag."),
    intensity_scale: float | None = typer.Option(None, "--intensity-scale",
                                                    help="Raw intensity that means 100 % (folders, bags)."),
    config: Path | None = ConfigOpt,
) -> None:
    """Lane-marking points of every scan, accumulated in one world frame (paper Sec. III-B)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from lidar2xodr.config import Config
    from lidar2xodr.datasets import FORMATS, open_dataset
    from lidar2xodr.extraction import ExtractionReport, extract_markings
    from lidar2xodr.markings_io import save_markings

    if format is not None and format not in FORMATS:
        raise InputError("--format", f"unknown format {format!r} (known: {', '.join(FORMATS)})")
    if odometry is not None and odometry not in ("auto", "gnss", "lidar"):
        raise InputError("--odometry", f"must be auto, gnss or lidar, got {odometry!r}")
    cfg = Config.load(config).extraction
    if odometry is not None:
        cfg = cfg.model_copy(update={"odometry": odometry})
    dataset = open_dataset(drive, format, topic=topic, pose_topic=pose_topic, intensity_scale=intensity_scale)
    rep = ExtractionReport()
    with Progress(TextColumn("extract"), BarColumn(), MofNCompleteColumn(), TextColumn("scans"),
                  TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task("extract", total=len(dataset))
        cloud = extract_markings(dataset, cfg, progress=lambda n: bar.advance(task, n), report=rep)
    save_markings(cloud, output)
    skipped = f", {len(rep.bad_scans)} skipped" if rep.bad_scans else ""
    skipped += f", {rep.empty_scans} empty" if rep.empty_scans else ""
    dropped = f", {rep.dropped_points:,} non-finite points dropped" if rep.dropped_points else ""
    speed = f" (start {rep.start_speed_mps:.1f} m/s)" if rep.start_speed_mps is not None else ""
    rtf = rep.duration_s / rep.wall_s if rep.wall_s > 0 else 0.0
    out.print(f"wrote {output}: {rep.marking_points:,} marking points from {rep.scans_used}/{rep.scans_total} scans"
              f"{skipped}{dropped}; threshold {rep.threshold:.2f} ({'auto' if rep.threshold_auto else 'fixed'}), "
              f"{rep.outliers_removed:,} outliers and {rep.moving_removed:,} points of {rep.moving_trails} moving "
              f"objects ({rep.moving_removed / max(rep.marking_points_raw, 1):.2%}) removed; "
              f"{rep.odometry} poses{speed}, {rep.drive_length_m:.0f} m "
              f"in {rep.duration_s:.1f} s; {rep.points_read / max(rep.wall_s, 1e-9):,.0f} points/s, "
              f"{rtf:.2f}x real time")
    for warning in rep.warnings:
        console.print(f"[yellow]warning:[/] {warning}", highlight=False, soft_wrap=True)


@app.command()
@_clean_errors
def lanes(
    markings: Path = typer.Argument(..., help="The marking cloud (markings.ply with its sidecars, from extract)."),
    output: Path = typer.Option(..., "--output", "-o", help="The lane model to write (lanes.json)."),
    report: Path | None = typer.Option(None, "--report", help="Write bird's-eye pictures (PNG) into this folder."),
    config: Path | None = ConfigOpt,
) -> None:
    """Lanes from markings alone (paper Alg. 1 and 2): candidates, superlines, boundaries, sections."""
    from lidar2xodr.branches import build_network, save_network
    from lidar2xodr.config import Config
    from lidar2xodr.lanes import build_lane_model
    from lidar2xodr.markings import find_candidates
    from lidar2xodr.markings_io import load_markings

    cfg = Config.load(config)
    cloud = load_markings(markings)
    if len(cloud.xyz) == 0:
        raise InputError(markings, "the marking cloud is empty")
    candidates = find_candidates(cloud.xyz, cfg.markings)
    model = build_lane_model(cloud, candidates, cfg.lanes, where=str(markings))
    network = build_network(cloud, model, cfg.lanes, cfg.markings, where=str(markings))
    save_network(network, output)
    counts = ", ".join(f"{len(sec.boundary_ids) - 1} from {sec.s_start:.0f} m" for sec in model.sections)
    out.print(f"wrote {output}: {model.s[-1]:.0f} m of road, {len(candidates)} candidates, "
              f"{len(model.boundaries)} boundaries, lanes {counts}; {len(network.roads)} road(s) after "
              f"junctions", highlight=False)
    if report is not None:
        from lidar2xodr.lanes_report import write_lanes_report

        for path in write_lanes_report(cloud, model, report):
            out.print(f"wrote {path}", highlight=False)
    for warning in network.warnings:
        console.print(f"[yellow]warning:[/] {warning}", highlight=False, soft_wrap=True)


@app.command()
@_clean_errors
def export(
    lanes_json: Path = typer.Argument(..., help="The lane model (lanes.json, from `lanes` or --keep-intermediate)."),
    output: Path = typer.Option(..., "--output", "-o", help="The OpenDRIVE map to write."),
    markings: Path | None = typer.Option(
        None, "--markings", help="markings.ply whose ground planes give the superelevation (else none)."
    ),
    allow_invalid: bool = typer.Option(False, "--allow-invalid", help="Write the map even if it fails check."),
    config: Path | None = ConfigOpt,
) -> None:
    """Stage 4 alone: OpenDRIVE from a lane model (paper Alg. 3), checked before it is written."""
    from lidar2xodr.branches import load_network
    from lidar2xodr.config import Config
    from lidar2xodr.markings_io import load_markings
    from lidar2xodr.pipeline import _verdict_line, write_checked_map

    model = load_network(lanes_json)
    planes = load_markings(markings).planes if markings else None
    summary, verdict = write_checked_map(model, planes, Config.load(config), output, allow_invalid, where=lanes_json)
    out.print(f"wrote {output}: {summary.length_m:.0f} m, {summary.pieces} paramPoly3 pieces, "
              f"{summary.lane_sections} lane sections; check: {_verdict_line(verdict)}", highlight=False)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
