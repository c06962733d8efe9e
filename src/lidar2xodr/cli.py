"""The `lidar2xodr` command line: one thin typer command per pipeline stage.

Commands import their stage lazily so `--help` stays fast. Exit codes (the README's promise):
0 done; 1 `check` found errors in the file; 2 bad input, bad usage or an unusable environment
(a full disk, a read-only target): one line on stderr naming the user's file, never a traceback;
3 a bug of ours: one line naming the exception (LIDAR2XODR_DEBUG=1 shows the traceback);
130 interrupted (Ctrl-C), 143 terminated (SIGTERM). Whatever the exit code, a command that does
not end with 0 (or 1) writes none of its outputs and changes no file that was there before.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import functools
import json
import os
import sys
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from lidar2xodr import __version__
from lidar2xodr.errors import InputError, OutputError, one_line
from lidar2xodr.fileio import os_problem, prepare_outputs, staged_outputs

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

# errors of the user's environment, not of lidar2xodr: exit code 2 like bad input
_ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EPERM, errno.EDQUOT, errno.EISDIR,
                       errno.ENOTDIR, errno.ENAMETOOLONG, errno.EFBIG, errno.EIO, errno.ENOENT, errno.EEXIST,
                       errno.ENOTEMPTY, errno.EXDEV, errno.EMFILE, errno.ENFILE}


class Odometry(str, enum.Enum):
    """Where the scans' poses come from."""

    auto = "auto"
    gnss = "gnss"
    lidar = "lidar"


class Format(str, enum.Enum):
    """The recording formats of `datasets.FORMATS` (a test keeps the two the same)."""

    drive = "drive"
    aimotive = "aimotive"
    kitti_raw = "kitti_raw"
    rosbag = "rosbag"
    folder = "folder"


class Sensor(str, enum.Enum):
    """The simulator's sensor presets."""

    livox_horizon = "livox-horizon"
    pandar64 = "pandar64"


class Traffic(str, enum.Enum):
    """The simulator's traffic densities."""

    none = "none"
    low = "low"
    mid = "mid"
    high = "high"


def _opt(default: Any, *names: str, **kwargs: Any) -> Any:
    """A typer option that shows no "[default: None]" (defaults worth showing are in the help text)."""
    return typer.Option(default, *names, show_default=False, **kwargs)


def _arg(**kwargs: Any) -> Any:
    """A required typer argument."""
    return typer.Argument(..., show_default=False, **kwargs)


def _say(prefix: str, text: object) -> None:
    """One line on stderr; the text is escaped, so `[/data/run1]` is printed, not parsed as markup."""
    console.print(f"{prefix} {escape(one_line(text))}".rstrip(), highlight=False, soft_wrap=True)


def warn(text: object) -> None:
    _say("[yellow]warning:[/]", text)


@contextlib.contextmanager
def _warnings_as_one_line() -> Iterator[None]:
    """Python warnings (numpy's "invalid value encountered", with source paths) become one summary line."""
    seen: dict[str, int] = {}

    def collect(message: Warning | str, category: type[Warning], *_args: Any, **_kwargs: Any) -> None:
        key = f"{category.__name__}: {one_line(message)}"
        seen[key] = seen.get(key, 0) + 1

    with warnings.catch_warnings():
        warnings.showwarning = collect
        try:
            yield
        finally:
            if seen:
                first = next(iter(seen))
                more = f" and {len(seen) - 1} other kind(s)" if len(seen) > 1 else ""
                warn(f"{sum(seen.values())} library warning(s) ({first}{more}); they did not stop the run")


@contextlib.contextmanager
def _busy(what: str) -> Iterator[None]:
    """A transient spinner for a stage without a count, on a terminal only (nothing in a pipe or log)."""
    if not console.is_terminal:
        yield
        return
    with console.status(escape(what)):
        yield


def _environment_problem(exc: OSError) -> str:
    where = exc.filename if exc.filename is not None else "output"
    return f"{where}: {os_problem(exc)}"


def _clean_errors(fn: F) -> F:
    """Turn expected failures into one line and exit code 2; SIGTERM and Ctrl-C into 143 and 130."""
    from lidar2xodr.lifetime import Terminated, raise_if_signalled, terminate_as_interrupt, terminated

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with terminate_as_interrupt(), _warnings_as_one_line():
                result = fn(*args, **kwargs)
                raise_if_signalled()  # a signal whose raise was lost (in a finaliser) still ends the command as one
                return result
        except (InputError, OutputError) as exc:
            _say("[bold red]error:[/]", exc)
            raise typer.Exit(2) from None
        except Terminated:
            _say("[bold red]terminated[/]", "(SIGTERM); nothing written")
            raise typer.Exit(143) from None
        except KeyboardInterrupt:
            _say("[bold red]interrupted[/]", "nothing written")
            raise typer.Exit(130) from None
        except (typer.Exit, typer.Abort, typer.BadParameter):
            raise
        except Exception as exc:
            if terminated():  # the SIGTERM's Terminated, turned into another error by the code it interrupted
                _say("[bold red]terminated[/]", "(SIGTERM); nothing written")
                raise typer.Exit(143) from None
            if os.environ.get("LIDAR2XODR_DEBUG"):
                raise
            if isinstance(exc, OSError) and exc.errno in _ENVIRONMENT_ERRNOS:
                _say("[bold red]error:[/]", _environment_problem(exc))
                raise typer.Exit(2) from None
            _say("[bold red]internal error:[/]", f"{type(exc).__name__}: {exc} (a bug in lidar2xodr, please "
                 "report it; LIDAR2XODR_DEBUG=1 shows the traceback)")
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


ConfigOpt = _opt(None, "--config", "-c", help="YAML configuration (see README).")
SchedulerOpt = _opt(None, "--scheduler", help="Run the per-scan work on Dask: 'local' (a LocalCluster) or a "
                    "scheduler address such as tcp://host:8786 (default: a process pool here).")


def _with_scheduler(cfg: Any, scheduler: str) -> Any:
    """The extraction configuration with `--scheduler`, validated like the configuration file's."""
    from lidar2xodr.scheduler import valid_scheduler

    try:
        valid_scheduler(scheduler)
    except ValueError as exc:
        raise InputError("--scheduler", str(exc)) from None
    return cfg.model_copy(update={"scheduler": scheduler})


@app.command(epilog="Example: lidar2xodr compare map.xodr truth.xodr --json metrics.json")
@_clean_errors
def compare(
    generated: Path = _arg(help="The generated .xodr."),
    reference: Path = _arg(help="The reference .xodr (ground truth)."),
    json_out: Path | None = _opt(None, "--json", help="Write the metrics as JSON."),
    config: Path | None = ConfigOpt,
    align: bool = typer.Option(False, "--align", help="First move the generated map rigidly (2D) onto the reference "
                               "(its markings' registration, within fusion.search_radius_m): the shape without a "
                               "GNSS bias."),
    trajectory: Path | None = _opt(None, "--trajectory", help="The drive's path in the reference's frame (CSV with "
                                   "x and y columns, e.g. a simulated drive's truth/poses.csv): also report the "
                                   "share of the driven road that was built."),
) -> None:
    """The paper's lateral distance between two maps: RMSE, mean, sigma, lane count, widths, coverage."""
    from lidar2xodr.config import Config
    from lidar2xodr.evaluation import compare_maps, load_trajectory, print_metrics

    prepare_outputs([json_out])
    full = Config.load(config)
    path = None if trajectory is None else load_trajectory(trajectory)
    with _busy(f"comparing {generated} with {reference}"):
        metrics = compare_maps(generated, reference, full.evaluation, full.fusion if align else None, path)
    if json_out:
        write_json(json_out, metrics)
    print_metrics(metrics, out)


@app.command(epilog="Example: lidar2xodr check map.xodr --json verdict.json")
@_clean_errors
def check(
    path: Path = _arg(help="An .xodr map or an .xosc scenario."),
    json_out: Path | None = _opt(None, "--json", help="Write the verdict as JSON."),
    config: Path | None = ConfigOpt,
) -> None:
    """ASAM quality checker plus our continuity checks. Exit code 1 when the file has errors."""
    from lidar2xodr.check import check_file, print_check
    from lidar2xodr.config import Config

    prepare_outputs([json_out])
    cfg = Config.load(config).check
    with _busy(f"checking {path}"):
        result = check_file(path, cfg=cfg)
    if json_out:
        write_json(json_out, result)
    print_check(result, out)
    if not result["ok"]:
        raise typer.Exit(1)


@app.command(epilog="Example: lidar2xodr build drive/ -o map.xodr --report report/ --scenario map.xosc")
@_clean_errors
def build(
    drive: list[Path] = _arg(metavar="DRIVE...", help="One or more drives (drive directory, scan folder, KITTI, "
                             "bag/MCAP, aiMotive) or folders of drives: several are aligned by their markings and "
                             "fused into one map."),
    output: Path = _opt(..., "--output", "-o", help="The OpenDRIVE map to write."),
    report: Path | None = _opt(None, "--report", help="Write an HTML report with pictures here."),
    odometry: Odometry | None = _opt(None, "--odometry", help="Pose source (default: from config, auto)."),
    data_format: Format | None = _opt(None, "--format", help="Force the reader (default: detected)."),
    scenario: Path | None = _opt(None, "--scenario", help="Also write the OpenSCENARIO here."),
    keep_intermediate: Path | None = _opt(
        None, "--keep-intermediate", help="Keep markings.ply and lanes.json in this (new or empty) folder."
    ),
    allow_invalid: bool = typer.Option(False, "--allow-invalid", help="Write the map even if it fails check."),
    reference: Path | None = _opt(None, "--reference", help="A reference .xodr (ground truth): compare with it "
                                  "and draw it in the report."),
    config: Path | None = ConfigOpt,
    topic: str | None = _opt(None, "--topic", help="PointCloud2 topic of a bag (when it has several)."),
    pose_topic: str | None = _opt(None, "--pose-topic", help="Pose topic of a bag (when it has several)."),
    intensity_scale: float | None = _opt(None, "--intensity-scale",
                                         help="Raw intensity that means 100 % (folders, bags)."),
    lanelet2: Path | None = _opt(None, "--lanelet2", help="Also write the map as Lanelet2 (.osm)."),
    geojson: Path | None = _opt(None, "--geojson", help="Also write the map as GeoJSON (WGS84)."),
    scheduler: str | None = SchedulerOpt,
    anchor: int | None = _opt(None, "--anchor", help="With several drives: the one (1 = first) whose GNSS places "
                              "the map, e.g. an RTK drive (default: the mean of all drives' GNSS)."),
) -> None:
    """The whole pipeline: extract markings, build lanes, export a checked OpenDRIVE map."""
    from lidar2xodr.config import Config
    from lidar2xodr.pipeline import BuildPipeline

    cfg = Config.load(config)
    if odometry:
        cfg = cfg.model_copy(update={"extraction": cfg.extraction.model_copy(update={"odometry": odometry.value})})
    if scheduler is not None:
        cfg = cfg.model_copy(update={"extraction": _with_scheduler(cfg.extraction, scheduler)})
    if reference is not None and not reference.is_file():
        raise InputError(reference, "reference map not found")
    if data_format is None:
        from lidar2xodr.datasets import drives_in

        drive = drives_in(drive)
    if anchor is not None:
        if not 1 <= anchor <= len(drive):
            raise InputError("--anchor", f"must name one of the {len(drive)} drive(s) given, 1 to {len(drive)} "
                                         f"(got {anchor})")
        cfg = cfg.model_copy(update={"fusion": cfg.fusion.model_copy(update={"anchor": anchor})})
    result = BuildPipeline(
        drive, output, cfg, data_format=data_format.value if data_format else None, report_dir=report,
        scenario=scenario, keep_intermediate=keep_intermediate, allow_invalid=allow_invalid, reference=reference,
        console=console, topic=topic, pose_topic=pose_topic, intensity_scale=intensity_scale,
        lanelet2=lanelet2, geojson=geojson,
    ).run()
    from lidar2xodr.pipeline import print_summary

    print_summary(result, out)


@app.command(epilog="Example: lidar2xodr demo -o demo-out --length-m 1000")
@_clean_errors
def demo(
    out_dir: Path = typer.Option(Path("demo-out"), "--output", "-o", help="Where the demo writes everything (a "
                                 "new or empty folder, or an earlier demo's)."),
    length_m: float = typer.Option(3000.0, "--length-m", help="Length of the simulated drive."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random choice."),
) -> None:
    """Simulate a drive on the project's own demo road, build the map, check it, compare with the truth."""
    from lidar2xodr.pipeline import run_demo

    run_demo(out_dir, _sim_options(length_m=length_m, seed=seed), console=console, out=out)


def _sim_options(**raw: Any) -> Any:
    """The simulator's options from command-line values; a value out of range names its option (exit 2)."""
    from pydantic import ValidationError

    from lidar2xodr.simulation import SimOptions

    try:
        return SimOptions(**raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        name = "--" + str(err["loc"][0]).replace("_", "-")
        raise InputError(name, f"{err['msg']} (got {err.get('input')!r})") from None


@app.command(epilog="Example: lidar2xodr scenario drive/ --map map.xodr -o drive.xosc")
@_clean_errors
def scenario(
    drive: Path = _arg(help="Drive folder or track file: objects.csv, detections, aiMotive, A9 CSV."),
    map_path: Path = _opt(..., "--map", help="The OpenDRIVE map to place the traffic on."),
    out_path: Path = _opt(..., "--output", "-o", help="The OpenSCENARIO file to write (.xosc)."),
    ego_path: Path | None = _opt(None, "--ego", help="Ego poses when the drive has none: poses.csv "
                                          "layout or the extraction's *.trajectory.csv (LiDAR odometry)."),
    json_out: Path | None = _opt(None, "--json", help="Write the summary as JSON."),
    config: Path | None = ConfigOpt,
) -> None:
    """OpenSCENARIO of the recorded traffic on a map, with cut-ins, cut-outs and lane changes."""
    from lidar2xodr.config import Config
    from lidar2xodr.export_scenario import export_scenario, print_summary
    from lidar2xodr.opendrive import OpenDriveMap
    from lidar2xodr.tracks import load_tracks, read_poses_csv

    prepare_outputs([out_path, json_out])
    cfg = Config.load(config)
    ego = read_poses_csv(ego_path) if ego_path else None
    geo = OpenDriveMap.load(map_path).geo_reference
    tracks = load_tracks(drive, ego, cfg=cfg, geo_reference=geo)
    ego = ego if ego is not None else tracks.ego
    if ego is None:
        raise InputError(drive, "no ego trajectory: the drive has no poses.csv; pass --ego POSES.csv")
    with staged_outputs(), _busy(f"writing {out_path}"):
        summary = export_scenario(ego, tracks, map_path, out_path, cfg)
        if json_out:
            write_json(json_out, summary.to_dict())
    print_summary(summary, out, console)


@app.command(epilog="Example: lidar2xodr simulate map.xodr drive/ --length-m 2000 --traffic high --seed 1")
@_clean_errors
def simulate(
    map_path: Path = _arg(metavar="MAP.xodr", help="The OpenDRIVE map to drive on."),
    out_dir: Path = _arg(metavar="OUT_DIR", help="The drive directory to write."),
    start_road: str | None = _opt(None, "--start-road", help="First road (default: longest chain)."),
    speed_kmh: float = typer.Option(110.0, "--speed-kmh", help="Mean desired ego speed."),
    length_m: float | None = _opt(None, "--length-m", help="Drive length (default: one pass)."),
    sensor: Sensor = typer.Option(Sensor.livox_horizon, "--sensor", help="The simulated sensor."),
    traffic: Traffic = typer.Option(Traffic.mid, "--traffic", help="Density of the other road users."),
    gnss_noise_m: float = typer.Option(0.05, "--gnss-noise-m", help="GNSS sigma per horizontal axis (m)."),
    gnss_outage: bool = typer.Option(False, "--gnss-outage", help="Add GNSS outages with INS drift."),
    gnss_bias_m: float = typer.Option(0.0, "--gnss-bias-m", help="A constant GNSS offset of this length (m) for "
                                      "the whole drive, in a direction drawn from the seed."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random choice."),
    rosbag: bool = typer.Option(False, "--rosbag", help="Also write drive.mcap (ROS 2)."),
    preview: bool = typer.Option(False, "--preview", help="Also write a close-up per 200 m under preview/."),
    roadside: bool = typer.Option(False, "--roadside", help="Terrain, trees, signs, noise barriers beside the "
                                  "road (needed by --odometry lidar)."),
) -> None:
    """Turn any OpenDRIVE map into a simulated LiDAR test drive with ground truth."""
    from lidar2xodr.simulation import simulate as run_simulation

    prepare_outputs([], [(out_dir, "drive")])
    opts = _sim_options(start_road=start_road, speed_kmh=speed_kmh, length_m=length_m, sensor=sensor.value,
                        traffic=traffic.value, gnss_noise_m=gnss_noise_m, gnss_outage=gnss_outage,
                        gnss_bias_m=gnss_bias_m, seed=seed,
                        rosbag=rosbag, preview=preview, roadside=roadside)
    s = run_simulation(map_path, out_dir, opts, console=console)
    out.print(f"wrote {s.out_dir}: {s.scans} scans, {s.points:,} points, {s.length_m / 1000:.2f} km in "
              f"{s.duration_s:.0f} s ({s.mean_speed_kmh:.0f} km/h), {s.passes} pass(es) over roads "
              f"{', '.join(s.roads[:8])}{' ...' if len(s.roads) > 8 else ''}; {s.vehicles} vehicles seen, "
              f"{s.lane_changes} ego lane changes", markup=False, highlight=False)
    out.print(f"preview: {s.preview}", markup=False, highlight=False)



@app.command(epilog="Example: lidar2xodr extract drive/ -o markings.ply")
@_clean_errors
def extract(
    drive: Path = _arg(metavar="DRIVE", help="Recorded drive: drive dir, scan folder, KITTI raw, "
                                 "ROS bag / MCAP, aiMotive sequence."),
    output: Path = _opt(..., "--output", "-o", help="The marking cloud to write (.ply + sidecars)."),
    format: Format | None = _opt(None, "--format", help="Force the reader (default: detected)."),
    odometry: Odometry | None = _opt(None, "--odometry", help="Pose source (default: from config, auto)."),
    topic: str | None = _opt(None, "--topic", help="PointCloud2 topic of a bag."),
    pose_topic: str | None = _opt(None, "--pose-topic", help="Pose topic of a bag."),
    intensity_scale: float | None = _opt(None, "--intensity-scale",
                                                    help="Raw intensity that means 100 % (folders, bags)."),
    config: Path | None = ConfigOpt,
    scheduler: str | None = SchedulerOpt,
) -> None:
    """Lane-marking points of every scan, accumulated in one world frame (paper Sec. III-B)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from lidar2xodr.config import Config
    from lidar2xodr.datasets import open_dataset
    from lidar2xodr.extraction import ExtractionReport, extract_markings
    from lidar2xodr.markings_io import save_markings

    prepare_outputs([output])
    cfg = Config.load(config).extraction
    if odometry is not None:
        cfg = cfg.model_copy(update={"odometry": odometry.value})
    if scheduler is not None:
        cfg = _with_scheduler(cfg, scheduler)
    dataset = open_dataset(drive, format.value if format else None, topic=topic, pose_topic=pose_topic,
                           intensity_scale=intensity_scale)
    rep = ExtractionReport()
    with Progress(TextColumn("extract"), BarColumn(), MofNCompleteColumn(), TextColumn("scans"),
                  TimeRemainingColumn(), console=console, transient=True, disable=not console.is_terminal) as bar:
        task = bar.add_task("extract", total=len(dataset))
        cloud = extract_markings(dataset, cfg, progress=lambda n: bar.advance(task, n), report=rep)
    with staged_outputs():  # the cloud and its three sidecars appear together
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
              f"{rtf:.2f}x real time", markup=False, highlight=False)
    for warning in rep.warnings:
        warn(warning)


@app.command(epilog="Example: lidar2xodr lanes markings.ply -o lanes.json --report pictures/")
@_clean_errors
def lanes(
    markings: Path = _arg(help="The marking cloud (markings.ply with its sidecars, from extract)."),
    output: Path = _opt(..., "--output", "-o", help="The lane model to write (lanes.json)."),
    report: Path | None = _opt(None, "--report", help="Write bird's-eye pictures (PNG) into this folder."),
    config: Path | None = ConfigOpt,
) -> None:
    """Lanes from markings alone (paper Alg. 1 and 2): candidates, superlines, boundaries, sections."""
    from lidar2xodr.branches import build_network, save_network
    from lidar2xodr.config import Config
    from lidar2xodr.fileio import atomic_dir
    from lidar2xodr.lanes import build_road_model
    from lidar2xodr.markings import find_candidates
    from lidar2xodr.markings_io import load_markings

    prepare_outputs([output], [(report, "report")])
    cfg = Config.load(config)
    cloud = load_markings(markings)
    if len(cloud.xyz) == 0:
        raise InputError(markings, "the marking cloud is empty")
    with _busy(f"lanes from {markings}"):
        candidates = find_candidates(cloud.xyz, cfg.markings)
        model = build_road_model(cloud, candidates, cfg.lanes, where=str(markings), markings_cfg=cfg.markings)
        network = build_network(cloud, model, cfg.lanes, cfg.markings, where=str(markings))
    pictures: list[Path] = []
    with staged_outputs():
        save_network(network, output)
        if report is not None:
            from lidar2xodr.lanes_report import write_lanes_report

            with atomic_dir(report, kind="report") as tmp:
                pictures = [report / Path(p).relative_to(tmp) for p in write_lanes_report(cloud, model, tmp)]
    counts = ", ".join(f"{len(sec.boundary_ids) - 1} from {sec.s_start:.0f} m" for sec in model.sections)
    out.print(f"wrote {output}: {model.s[-1]:.0f} m of road, {len(candidates)} candidates, "
              f"{len(model.boundaries)} boundaries, lanes {counts}; {len(network.roads)} road(s) after "
              f"junctions", highlight=False, markup=False)
    for path in pictures:
        out.print(f"wrote {path}", highlight=False, markup=False)
    for warning in network.warnings:
        warn(warning)


@app.command(epilog="Example: lidar2xodr export lanes.json -o map.xodr --markings markings.ply")
@_clean_errors
def export(
    lanes_json: Path = _arg(help="The lane model (lanes.json, from `lanes` or --keep-intermediate)."),
    output: Path = _opt(..., "--output", "-o", help="The OpenDRIVE map to write."),
    markings: Path | None = _opt(
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

    prepare_outputs([output])
    cfg = Config.load(config)
    model = load_network(lanes_json)
    planes = load_markings(markings).planes if markings else None
    with _busy(f"exporting and checking {output}"):
        summary, verdict = write_checked_map(model, planes, cfg, output, allow_invalid, where=lanes_json)
    out.print(f"wrote {output}: {summary.length_m:.0f} m, {summary.pieces} paramPoly3 pieces, "
              f"{summary.lane_sections} lane sections; check: {_verdict_line(verdict)}", highlight=False, markup=False)


@app.command(name="config", epilog="Example: lidar2xodr config --show -c my.yaml > effective.yaml")
@_clean_errors
def config_cmd(
    show: bool = typer.Option(False, "--show", help="Print the effective configuration as YAML."),
    config: Path | None = ConfigOpt,
) -> None:
    """The configuration: the defaults with the --config file applied, as YAML (every field of the README)."""
    import yaml

    from lidar2xodr.config import Config

    if not show:
        raise typer.BadParameter("nothing to do: pass --show", param_hint="--show")
    cfg = Config.load(config)
    out.print(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False), end="", markup=False,
              highlight=False)


@app.command("export-lanelet2", epilog="Example: lidar2xodr export-lanelet2 map.xodr -o map.osm")
@_clean_errors
def export_lanelet2(
    map_path: Path = _arg(metavar="MAP.xodr", help="The OpenDRIVE map to convert."),
    output: Path = _opt(..., "--output", "-o", help="The Lanelet2 map to write (.osm)."),
    config: Path | None = ConfigOpt,
) -> None:
    """Lanelet2 (.osm) for Autoware: lanelets with shared, mark-tagged bounds, routable like the lane links."""
    from lidar2xodr.config import Config
    from lidar2xodr.export_lanelet2 import export_lanelet2 as run_export

    prepare_outputs([output])
    s = run_export(map_path, output, Config.load(config).interchange)
    out.print(f"wrote {output}: {s.lanelets} lanelets, {s.linestrings} linestrings, {s.points:,} points, "
              f"{s.joined_ends} linked lane ends joined; projector origin {s.origin_lat:.7f} N "
              f"{s.origin_lon:.7f} E", highlight=False, markup=False)
    for warning in s.warnings:
        warn(warning)


@app.command("export-geojson", epilog="Example: lidar2xodr export-geojson map.xodr -o map.geojson")
@_clean_errors
def export_geojson(
    map_path: Path = _arg(metavar="MAP.xodr", help="The OpenDRIVE map to convert."),
    output: Path = _opt(..., "--output", "-o", help="The GeoJSON file to write (WGS84)."),
    config: Path | None = ConfigOpt,
) -> None:
    """GeoJSON (RFC 7946, WGS84) of the lanes, lane borders and reference lines, for GIS tools."""
    from lidar2xodr.config import Config
    from lidar2xodr.export_geojson import export_geojson as run_export

    prepare_outputs([output])
    s = run_export(map_path, output, Config.load(config).interchange)
    out.print(f"wrote {output}: {s.reference_lines} reference lines, {s.lanes} lanes, {s.boundaries} lane "
              f"borders", highlight=False, markup=False)
    for warning in s.warnings:
        warn(warning)


def run() -> None:
    """The `lidar2xodr` command (console script and `python -m lidar2xodr.cli`).

    An interrupted command (exit code 130 or 143) ends with `os._exit` once its streams are flushed: a
    KeyboardInterrupt that came out of C code running Python (`PyRun_String`; lxml and Boost.Python do)
    makes CPython kill its own process with SIGINT at exit, whatever code was asked for (a CI run saw
    -2 instead of 130). Everything that needs cleaning up was cleaned up before the exit code was chosen.
    """
    try:
        app()
    except SystemExit as exc:
        if exc.code in (130, 143):
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(Exception):
                    stream.flush()
            os._exit(exc.code)
        raise


if __name__ == "__main__":  # pragma: no cover
    run()
