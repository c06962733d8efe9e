"""The whole method as one pipeline: extract -> markings -> lanes -> OpenDRIVE (-> OpenSCENARIO).

`BuildPipeline.run()` streams the drive through each stage with a progress bar, times every
stage, checks the written map and only then moves it into place: a map that fails `check` is
written only with `allow_invalid` (nothing half-written either way). Every output of a build
(map, scenario, intermediates, report) is staged (`fileio.staged_outputs`) and moved into place
only when all of them succeeded: a build that fails writes none of them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from lidar2xodr.config import Config
from lidar2xodr.data import GroundPlanes, LaneModel, MarkingCloud, RoadNetwork
from lidar2xodr.errors import InputError
from lidar2xodr.fileio import (
    atomic_dir,
    check_output_dir,
    check_output_file,
    prepare_outputs,
    staged,
    staged_outputs,
)


@dataclass
class BuildResult:
    """What a build produced and how long each stage took."""

    map_path: Path
    scenario_path: Path | None = None
    report_path: Path | None = None
    timings: dict[str, float] = field(default_factory=dict)
    check: dict[str, Any] = field(default_factory=dict)
    summary: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def progress_bar(console: Console) -> Progress:
    """A bar per stage on a terminal; gone when done, and none at all in a pipe or log file."""
    return Progress(
        TextColumn("[bold blue]{task.description:<12}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
        disable=not console.is_terminal,
    )


class BuildPipeline:
    """Runs `build`: a drive in, a checked OpenDRIVE map (and optionally an OpenSCENARIO) out."""

    def __init__(
        self,
        drive: Path | list[Path],
        out: Path,
        config: Config | None = None,
        data_format: str | None = None,
        report_dir: Path | None = None,
        scenario: Path | None = None,
        keep_intermediate: Path | None = None,
        allow_invalid: bool = False,
        reference: Path | None = None,
        console: Console | None = None,
        topic: str | None = None,
        pose_topic: str | None = None,
        intensity_scale: float | None = None,
        lanelet2: Path | None = None,
        geojson: Path | None = None,
    ) -> None:
        self.drives = [Path(d) for d in drive] if isinstance(drive, list | tuple) else [Path(drive)]
        self.drive = self.drives[0]  # the drive whose traffic gives lane directions and the scenario
        self.fusion: Any = None  # FusionReport when several drives are fused
        self.out = Path(out)
        self.config = config or Config()
        self.data_format = data_format
        self.report_dir = report_dir
        self.scenario = scenario
        self.keep = keep_intermediate
        self.allow_invalid = allow_invalid
        self.reference = reference
        self.lanelet2 = lanelet2
        self.geojson = geojson
        self.console = console or Console(stderr=True)
        self.reader_options = dict(topic=topic, pose_topic=pose_topic, intensity_scale=intensity_scale)
        self.timings: dict[str, float] = {}
        self._tracks: Any = None  # the drive's object tracks, loaded once for lane directions and the scenario

    @contextmanager
    def _stage(self, name: str, spinner: bool = True) -> Iterator[None]:
        """Time a stage; on a terminal, show it as a (transient) spinner while it runs."""
        t0 = time.perf_counter()
        if spinner:
            with progress_bar(self.console) as bar:
                bar.add_task(name, total=None)
                yield
        else:
            yield
        self.timings[name] = time.perf_counter() - t0

    def extract(self) -> MarkingCloud:
        """The drive's marking cloud; with several drives, each one's, aligned and fused (fusion.py)."""
        from lidar2xodr.datasets import open_dataset
        from lidar2xodr.extraction import ExtractionReport, extract_markings

        datasets = [open_dataset(d, self.data_format, **self.reader_options) for d in self.drives]
        clouds, modes = [], []
        with self._stage("extract", spinner=False), progress_bar(self.console) as bar:
            for k, (drive, dataset) in enumerate(zip(self.drives, datasets, strict=True)):
                label = "extract" if len(self.drives) == 1 else f"extract {k + 1}/{len(self.drives)}"
                task = bar.add_task(label, total=len(dataset))
                rep = ExtractionReport()
                cloud = extract_markings(dataset, self.config.extraction, report=rep,
                                         progress=lambda n=1, t=task: bar.advance(t, n))
                if len(cloud.xyz) == 0 and len(self.drives) == 1:
                    raise InputError(drive, "no lane markings found in the drive (nothing bright on the ground)")
                clouds.append(cloud)
                modes.append(rep.odometry)
        if len(clouds) == 1:
            return clouds[0]
        from lidar2xodr.fusion import fuse

        with self._stage("fuse"):
            cloud, self.fusion = fuse(clouds, [str(d) for d in self.drives], modes, self.config.fusion)
        return cloud

    def _ego(self, cloud: MarkingCloud) -> Any:
        """The trajectory of the drive whose objects are used (the first), in the map's frame; None if left out."""
        return cloud.trajectory if self.fusion is None else self.fusion.trajectories[0]

    def lanes(self, cloud: MarkingCloud) -> tuple[LaneModel, RoadNetwork]:
        """The measured carriageway and, where it splits or merges, the roads joined by junctions.

        The drive's object tracks (lane directions, the scenario) are read and smoothed in a process
        of their own meanwhile (`scheduler.in_background`): the markings and lanes stages run on one
        core, and the tracks' smoothing splines take as long again on a busy road."""
        from lidar2xodr.branches import build_network
        from lidar2xodr.lanes import build_road_model
        from lidar2xodr.markings import find_candidates

        with self._tracks_beside(cloud) as tracks:
            with self._stage("markings"):
                candidates = find_candidates(cloud.xyz, self.config.markings)
            with self._stage("lanes"):
                model = build_road_model(cloud, candidates, self.config.lanes, markings_cfg=self.config.markings)
                model.warnings.extend(self._traffic_directions(model, cloud, tracks))
                network = build_network(cloud, model, self.config.lanes, self.config.markings, where=str(self.drive))
        return model, network

    @contextmanager
    def _tracks_beside(self, cloud: MarkingCloud) -> Iterator[Callable[[], Any] | None]:
        """`result()` of `tracks.load_tracks` for the lane directions, started in the background now;
        None where the lane directions do not use them (their option off, the first drive left out).
        The markings and lanes stages keep one core; the tracks are smoothed on the others (one on
        a 2-core machine: on the 50 km corridor the two stages took 64 s beside one process, 76 s
        beside a pool of two)."""
        from functools import partial

        from lidar2xodr.extraction import worker_count
        from lidar2xodr.scheduler import in_background
        from lidar2xodr.tracks import load_tracks

        ego = self._ego(cloud)
        if not self.config.lanes.traffic_directions or ego is None:
            yield None
            return
        workers = max(worker_count(self.config.extraction) - 1, 1)
        with in_background(partial(load_tracks, cfg=self.config, workers=workers), self.drive, ego) as result:
            yield result

    def _traffic_directions(self, model: LaneModel, cloud: MarkingCloud,
                            tracks: Callable[[], Any] | None) -> list[str]:
        """Dividers from the recorded traffic's directions (lane_directions.py); no object list, no change."""
        from lidar2xodr.lane_directions import apply_traffic_directions

        if not self.config.lanes.traffic_directions:
            return []
        ego = self._ego(cloud)
        if ego is None or tracks is None:
            return [f"the object list of {self.drive} was not used for lane directions: the drive was left out"]
        try:
            self._tracks = tracks()
        except InputError as exc:
            if exc.problem.startswith(("no object tracks found", "unknown track format")):
                return []
            return [f"the object list was not used for lane directions: {exc}"]
        return apply_traffic_directions(model, self._tracks.tracks, ego, self.config.lanes)

    def run(self) -> BuildResult:
        """The whole build; its outputs appear together at the end, or none of them."""
        prepare_outputs([self.out, self.scenario, self.lanelet2, self.geojson],
                        [(self.report_dir, "report"), (self.keep, "intermediate")])
        with staged_outputs():
            return self._run()

    def _run(self) -> BuildResult:
        cloud = self.extract()
        model, network = self.lanes(cloud)
        summary, verdict = write_checked_map(
            network, cloud.planes, self.config, self.out, self.allow_invalid, where=self.drive, timings=self.timings,
            stage=self._stage,
        )
        if self.keep:
            self._keep(cloud, network)
        result = BuildResult(map_path=self.out, timings=self.timings, check=verdict, warnings=list(network.warnings))
        if self.fusion is not None:
            result.warnings[:0] = self.fusion.warnings
        result.summary = {
            "length_m": float(model.s[-1] - model.s[0]) if len(model.s) else 0.0,
            "boundaries": len(model.boundaries),
            "sections": [len(sec.boundary_ids) - 1 for sec in model.sections],
            "roads": [
                {"length_m": round(float(r.s[-1] - r.s[0]), 1),
                 "lanes": [len(sc.boundary_ids) - 1 for sc in r.sections]}
                for r in network.roads
            ],
            "junction_links": len(network.links),
            "marking_points": int(len(cloud.xyz)),
            "scans": int(len(cloud.planes.times)),
            "export": summary.__dict__ if hasattr(summary, "__dict__") else str(summary),
        }
        ego = self._ego(cloud)
        if ego is not None and len(ego) >= 2:
            from lidar2xodr.evaluation import path_on_map

            result.summary["drive_on_map"] = path_on_map(staged(self.out), ego.positions, self.config.evaluation)
        if self.fusion is not None:
            result.summary["fusion"] = [d.__dict__ for d in self.fusion.drives]
            result.summary["fusion_lines"] = [d.line() for d in self.fusion.drives]
        result.warnings.extend(self._interchange(result.summary))
        scenario_info = None
        if self.scenario:
            with self._stage("scenario"):
                scenario_info = self._scenario(cloud)
            result.scenario_path = self.scenario
            result.summary["scenario"] = {
                "entities": len(scenario_info["summary"].entities),
                "manoeuvres": [f"{m.kind} {m.actor} at {m.time_s:.1f} s" for m in scenario_info["summary"].manoeuvres],
                "warnings": scenario_info["summary"].warnings,
            }
        metrics = None
        if self.reference:
            from lidar2xodr.evaluation import compare_maps

            with self._stage("compare"):
                metrics = compare_maps(staged(self.out), self.reference, self.config.evaluation)
            result.summary["metrics"] = metrics
        if self.report_dir:
            from lidar2xodr.report import write_report

            with self._stage("report"):
                result.report_path = write_report(self.report_dir, cloud=cloud, model=model, map_path=staged(self.out),
                                                  check=verdict, timings=self.timings, summary=result.summary,
                                                  scenario=scenario_info, metrics=metrics,
                                                  reference=self.reference, warnings=result.warnings,
                                                  config=self.config, final_path=self.out)
        return result

    def _interchange(self, summary: dict[str, Any]) -> list[str]:
        """Lanelet2 and GeoJSON copies of the written map (--lanelet2, --geojson); their warnings."""
        warnings: list[str] = []
        if self.lanelet2:
            from lidar2xodr.export_lanelet2 import export_lanelet2

            with self._stage("lanelet2"):
                ll = export_lanelet2(staged(self.out), self.lanelet2, self.config.interchange)
            summary["lanelet2"] = {"path": str(ll.path), "lanelets": ll.lanelets, "joined_ends": ll.joined_ends}
            warnings += ll.warnings
        if self.geojson:
            from lidar2xodr.export_geojson import export_geojson

            with self._stage("geojson"):
                gj = export_geojson(staged(self.out), self.geojson, self.config.interchange)
            summary["geojson"] = {"path": str(gj.path), "lanes": gj.lanes, "boundaries": gj.boundaries}
            warnings += gj.warnings
        return warnings

    def _scenario(self, cloud: MarkingCloud) -> dict[str, Any]:
        """Write the OpenSCENARIO on the map just written; return its summary and the tracks for the report."""
        from lidar2xodr.export_scenario import export_scenario
        from lidar2xodr.tracks import load_tracks

        assert self.scenario is not None
        ego = self._ego(cloud)
        if ego is None:
            raise InputError(self.drive, "--scenario: the scenario is of the first drive, which was left out")
        tracks = self._tracks if self._tracks is not None else load_tracks(self.drive, ego)
        summary = export_scenario(ego, tracks, self.out, self.scenario, self.config)
        return {"path": self.scenario, "summary": summary, "tracks": tracks, "ego": ego}

    def _keep(self, cloud: MarkingCloud, network: RoadNetwork) -> None:
        from lidar2xodr.branches import save_network
        from lidar2xodr.markings_io import save_markings

        assert self.keep is not None
        with atomic_dir(self.keep, kind="intermediate") as tmp:
            save_markings(cloud, tmp / "markings.ply")
            save_network(network, tmp / "lanes.json")


def write_checked_map(
    model: LaneModel | RoadNetwork,
    planes: GroundPlanes | None,
    config: Config,
    out: Path,
    allow_invalid: bool = False,
    where: str | Path = "lane model",
    timings: dict[str, float] | None = None,
    stage: Any = None,
) -> tuple[Any, dict[str, Any]]:
    """Export to a temporary file, run `check` on it, and move it into place only if it passes.

    A map that fails the checks is written only with `allow_invalid`; otherwise nothing is
    written and the error names `where` the model came from. Inside a build the map stays staged
    until the build's other outputs are done. Returns (export summary, verdict).
    """
    from lidar2xodr import export_opendrive as exporter
    from lidar2xodr.check import check_file

    timings = timings if timings is not None else {}
    out = check_output_file(out)
    with staged_outputs():
        t0 = time.perf_counter()
        if isinstance(model, RoadNetwork) and (len(model.roads) > 1 or model.links):
            summary = exporter.export_network(model, planes, config.export, out)
        else:
            single = model.roads[0] if isinstance(model, RoadNetwork) else model
            summary = exporter.export_opendrive(single, planes, config.export, out)
        t1 = time.perf_counter()
        with stage("check") if stage is not None else _no_stage():
            verdict = check_file(staged(out), cfg=config.check)
        verdict["file"] = str(out)
        timings.update(export=t1 - t0, check=time.perf_counter() - t1)
        if not verdict["ok"] and not allow_invalid:
            raise InputError(
                where,
                f"the generated map fails the checks: {'; '.join(verdict['reasons'])} ({_verdict_line(verdict)}); "
                "nothing written (use --allow-invalid to write it anyway)",
            )
    return summary, verdict


@contextmanager
def _no_stage() -> Iterator[None]:
    yield


def _reader_state(rd: dict[str, Any]) -> str:
    """'FAILED to read it' only on an error (or a failing exit); a reader that only warns still reads the map.

    netconvert warns about a lane that grows from zero width without a predecessor (an exit lane),
    and does so on the shared reference maps themselves: a warning, not a failed read.
    """
    if rd.get("errors") or rd.get("returncode") not in (None, 0):
        return "FAILED to read it"
    return "reads it with warnings" if rd.get("warnings") else "reads it"


def _verdict_line(verdict: dict[str, Any]) -> str:
    asam = verdict.get("asam", {})
    cont = verdict.get("continuity", {})
    line = (
        f"ASAM errors {asam.get('errors', '?')}, largest leap {cont.get('max_leap_m', float('nan')):.4f} m, "
        f"largest kink {cont.get('max_kink_rad', float('nan')):.4f} rad"
    )
    for name, rd in verdict.get("readers", {}).items():
        reader = rd.get("reader", name)
        if not rd.get("available"):
            line += f"; {reader}: not available"
            continue
        line += f"; {reader}: {_reader_state(rd)}, {len(rd.get('warnings', []))} warning(s), " \
                f"{len(rd.get('errors', []))} error(s)"
    return line


def print_summary(result: BuildResult, console: Console) -> None:
    """The end-of-build summary: length, lanes, time per stage, checks."""
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=escape(f"built {result.map_path}"), show_header=False)
    s = result.summary
    table.add_row("length", f"{s.get('length_m', 0.0):.0f} m")
    on_map = s.get("drive_on_map")
    if on_map:
        table.add_row("drive on the map", f"{100 * on_map['share']:.0f} % of its {on_map['path_m']:.0f} m path "
                      "(on a built lane of its direction)")
    table.add_row("lanes per section", ", ".join(str(n) for n in s.get("sections", [])))
    table.add_row("marking points / scans", f"{s.get('marking_points', 0):,} / {s.get('scans', 0):,}")
    for k, line in enumerate(s.get("fusion_lines", [])):
        table.add_row(f"drive {k + 1}", escape(line))
    for stage, sec in result.timings.items():
        table.add_row(f"time {stage}", f"{sec:.2f} s")
    # the verdict is the ASAM checker's and continuity's; each reader says for itself whether it read the map
    table.add_row("check", ("valid map: " if result.check.get("ok") else "INVALID map: ") + _verdict_line(result.check))
    metrics = s.get("metrics")
    if metrics:
        table.add_row("boundaries RMSE / mean / sigma",
                      "{rmse_m:.3f} / {mean_m:.3f} / {std_m:.3f} m".format(**metrics["boundaries"]))
        table.add_row("centre line RMSE", "{rmse_m:.3f} m".format(**metrics["centerline"]))
        table.add_row("lane count agreement", f"{metrics['lane_count_agreement']:.3f}")
        lw = metrics["lane_width"]
        table.add_row("lane width bias / sigma",
                      "no matched lanes" if lw.get("bias_m") is None else f"{lw['bias_m']:+.3f} / {lw['std_m']:.3f} m")
    for w in result.warnings:
        table.add_row("warning", escape(w))
    for w in result.check.get("lane_widths", {}).get("warnings", []):
        table.add_row("warning", escape(f"map: {w}"))
    if result.scenario_path:
        table.add_row("scenario", escape(str(result.scenario_path)))
    if result.report_path:
        table.add_row("report", escape(str(result.report_path)))
    console.print(table)


def run_demo(out_dir: Path, opts: Any, console: Console, out: Console) -> BuildResult:
    """`make demo`: simulate a drive (`opts`: SimOptions) on the project's own road, build, check, compare."""
    from lidar2xodr.demo_road import write_demo_road
    from lidar2xodr.fileio import marker_name
    from lidar2xodr.simulation import simulate

    out_dir = check_output_dir(out_dir, "demo")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / marker_name("demo")).write_text(
        "# written by lidar2xodr (demo); a re-run replaces these and no others\n"
        "demo_road.xodr\ndrive\nmap.xodr\nmap.xosc\nreport\n", encoding="utf-8")
    truth = write_demo_road(out_dir / "demo_road.xodr")
    drive = out_dir / "drive"
    console.print(f"[bold]1/2[/] simulating a {opts.length_m:.0f} m drive on {truth}")
    simulate(truth, drive, opts, console=console)
    console.print(f"[bold]2/2[/] building the map from {drive}")
    result = BuildPipeline(
        drive, out_dir / "map.xodr", report_dir=out_dir / "report", scenario=out_dir / "map.xosc",
        reference=truth, console=console,
    ).run()
    print_summary(result, out)
    out.print(f"open the report: {result.report_path}")
    return result
