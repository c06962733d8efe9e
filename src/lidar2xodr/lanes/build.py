"""The lanes stage: candidates and marking points -> LaneModel (`build_lane_model`)."""

from __future__ import annotations

import numpy as np

from lidar2xodr.config import LanesConfig, MarkingsConfig
from lidar2xodr.data import Boundary, Candidate, LaneModel, MarkingCloud
from lidar2xodr.errors import InputError
from lidar2xodr.lanes.dividers import _divided_left, _ego_offsets, _ego_track, _mark_dividers
from lidar2xodr.lanes.frame import (
    _LINE_EXT_M,
    _LINE_FRAME_GAIN,
    Frame,
    _first_frame,
    _line_frame,
    _parallel_length,
    _Points,
    _stations,
)
from lidar2xodr.lanes.labels import (
    _fork_curves,
    _hold_ends,
    _label_by_candidates,
    _label_by_distance,
    _labelling_curves,
)
from lidar2xodr.lanes.lookups import candidate_segments, global_lookup, lane_step, relative_lookups, split_candidates
from lidar2xodr.lanes.marks import _mark_pattern, marking_widths, section_marks
from lidar2xodr.lanes.sections import _sections
from lidar2xodr.lanes.smoothing import _lam, _runs, _whittaker
from lidar2xodr.lanes.structure import _lane_structure, _Structure
from lidar2xodr.lanes.tapers import _add_tapers, _Taper, _taper_lanes, _travel_sign, _type_by_width, _type_tapers
from lidar2xodr.lanes.tracks import _continuations, _crossing_points, _Fit, _fit_boundaries, _Lines, _observed


def build_lane_model(
    cloud: MarkingCloud, candidates: list[Candidate], cfg: LanesConfig, where: str = "marking cloud",
    line_axis_only: bool = False,
) -> LaneModel:
    """Paper Alg. 2 and beyond: superlines, boundaries t(s), sections and the reference line.

    `line_axis_only`: built along the longest line's axis alone (`_line_frame`; `build_road_model`'s
    rescue of a road that explains less than half of that line)."""
    xyz = np.asarray(cloud.xyz, dtype=np.float64)
    if len(xyz) == 0:
        raise InputError(where, "no marking points: nothing to build lanes from")
    if not candidates:
        raise InputError(where, "no candidate lines were found in the markings")
    step = cfg.station_step_m
    pieces, owner = split_candidates(candidates, cfg)
    segs = candidate_segments(pieces)
    lookups = relative_lookups(segs, cfg)
    w_lane = lane_step(lookups, cfg)
    if w_lane is None:
        raise NoLanesError(
            where,
            "found no two parallel marking lines "
            f"{cfg.min_lane_width_m:g}-{cfg.max_lane_width_m:g} m apart: a single line "
            "(or none) cannot give lanes",
        )
    superline = global_lookup(len(pieces), lookups, w_lane, cfg)
    frame = _first_frame(segs, lookups, cfg)
    along_line = _line_frame(pieces, cfg)
    frames = [frame]
    if line_axis_only:
        frames = [] if along_line is None else [along_line]
    elif along_line is not None:
        if (along_line.length >= 0.9 * frame.length
                and _parallel_length(along_line, segs, cfg) > _LINE_FRAME_GAIN * _parallel_length(frame, segs, cfg)):
            frames.insert(0, along_line)
        else:
            frames.append(along_line)
    for frame in frames:
        try:
            return _build_on_frame(cloud, candidates, cfg, where, xyz, pieces, owner, superline, frame, step, w_lane)
        except _NoRoad:
            continue
    raise NoLanesError(where, "no stretch of road has two marking lines a lane apart")


_LINE_SPAN_SHARE = 0.5
"""A road that explains less than this share of the longest marking line's span, after the rebuild along
the drive, was built on a failed axis (its cross-sections' middles bent by clutter or by a far line seen
on one stretch only): the road is built again along the line's own axis and that is kept where it
explains `min_section_length_m` more road. Measured on the aiMotive sample with one middle frame
unreadable and road-based odometry: the first axis built 63 m of the line's 149 m, the line axis 144 m.
A road explaining half the line or more is kept: on single roads the first axis builds 80-90 % of the
line's span, and the line axis, built there too, added less accurate ends (BENCHMARKS: "Second road axis
kept where it builds more road"). After the rebuild along the drive, not before: that rebuild holds more
of a drive through streets than the line axis does (ParametricCubicCurveComplexRoad s2: 194 m against
177 m)."""


def _road_m(model: LaneModel) -> float:
    """Metres of road a lane model explains."""
    return float(model.s[-1] - model.s[0]) if len(model.s) else 0.0


class NoLanesError(InputError):
    """No two marking lines lie a lane apart (`min_lane_width_m`-`max_lane_width_m`) anywhere."""


def build_road_model(
    cloud: MarkingCloud, candidates: list[Candidate], cfg: LanesConfig, where: str = "marking cloud",
    markings_cfg: MarkingsConfig | None = None,
) -> LaneModel:
    """`build_lane_model` of the drive's own road; where no two lines lie a lane apart, once more with
    lanes from `narrow_lane_width_m` on, with a warning: a map of the lanes the markings show (a test
    track, a catalogue of marks with 2 m lanes) rather than none. Branch roads do not take this
    fallback: a ramp's one line and the clutter beside it would make a lane. With `markings_cfg`
    (the drive's build), a road under almost none of the drive is built again along it
    (`along_drive.build_along_drive`, candidates found in each stretch's markings)."""
    model = _road_model(cloud, candidates, cfg, where)
    if markings_cfg is not None:
        from lidar2xodr.lanes.along_drive import build_along_drive
        from lidar2xodr.markings import find_candidates

        model = build_along_drive(cloud, model, lambda sub: _road_model(sub, find_candidates(sub.xyz, markings_cfg),
                                                                         cfg, where))
    return _along_longest_line(model, cloud, candidates, cfg, where)


def _along_longest_line(model: LaneModel, cloud: MarkingCloud, candidates: list[Candidate], cfg: LanesConfig,
                        where: str) -> LaneModel:
    """`model`, or the road built along the longest line's axis where `model` explains less than
    `_LINE_SPAN_SHARE` of that line's span and the line's road explains `min_section_length_m` more."""
    along_line = _line_frame(split_candidates(candidates, cfg)[0], cfg) if candidates else None
    if along_line is None or _road_m(model) >= _LINE_SPAN_SHARE * (along_line.length - 2.0 * _LINE_EXT_M):
        return model
    try:
        rescued = build_lane_model(cloud, candidates, cfg, where, line_axis_only=True)
    except InputError:
        return model
    return rescued if _road_m(rescued) > _road_m(model) + cfg.min_section_length_m else model


def _road_model(cloud: MarkingCloud, candidates: list[Candidate], cfg: LanesConfig, where: str) -> LaneModel:
    """`build_lane_model`, with the narrow-lane fallback of `build_road_model`."""
    try:
        return build_lane_model(cloud, candidates, cfg, where)
    except NoLanesError as exc:
        if cfg.narrow_lane_width_m >= cfg.min_lane_width_m:
            raise
        narrow = cfg.model_copy(update={"min_lane_width_m": cfg.narrow_lane_width_m})
        try:
            model = build_lane_model(cloud, candidates, narrow, where)
        except NoLanesError:
            raise exc from None
    model.warnings.insert(0, f"no two marking lines lie {cfg.min_lane_width_m:g}-{cfg.max_lane_width_m:g} m apart "
                             f"(a lane); built with lanes from {cfg.narrow_lane_width_m:g} m, narrower than "
                             "motorway lanes")
    return model


class _NoRoad(Exception):
    """No station of a frame has two kept lines: the road axis may be poor (`build_lane_model` tries the next)."""


def _build_on_frame(cloud: MarkingCloud, candidates: list[Candidate], cfg: LanesConfig, where: str, xyz: np.ndarray,
                    pieces: list[Candidate], owner: np.ndarray, superline: np.ndarray, frame: Frame, step: float,
                    w_lane: float) -> LaneModel:
    """`build_lane_model` along one road axis; `_NoRoad` when no stretch has two lines a lane apart on it."""
    warnings: list[str] = []
    label = _label_by_candidates(xyz[:, :2], pieces, superline, cfg)
    n_sl = int(superline.max()) + 1
    ego = cloud.trajectory.positions[:, :2] if len(cloud.trajectory) else None
    lam = _lam(cfg.boundary_smoothing_m, step)
    lam_shift = _lam(cfg.shift_smoothing_m, step) if cfg.shift_smoothing_m > 0 else None
    structure = fit = None
    if _travel_sign(frame, ego, cfg.max_normal_length_m) < 0:
        frame = Frame(frame.xy[::-1], step)
    travel = _travel_sign(frame, ego, cfg.max_normal_length_m)
    tapers: list[_Taper] = []
    taper_notes: list[str] = []
    off = np.zeros(len(xyz), dtype=bool)  # points of taper lines found: refitted without them (they bend the edge)
    double = (cfg.double_line_max_spacing_m, max(int(round(cfg.double_line_block_m / step)), 1))
    for it in range(3):
        k_pt, t_pt, inside, s_pt = _stations(frame, xyz[:, :2])
        t_ego = _ego_offsets(frame, ego)
        for _ in range(3):
            use = np.where(off, -1, label)
            fit = structure = None  # the last pass's arrays are freed before the next are made
            lines = _fit_boundaries(k_pt, t_pt, use, inside, n_sl, len(frame.s), lam, int(round(20.0 / step)),
                                    cfg.same_line_tolerance_m, double, cfg.end_dash_drift, lam_shift)
            root = _joins(lines, int(round(cfg.line_join_gap_m / step)), cfg.same_line_tolerance_m,
                          int(round(10.0 / step)))
            if np.any(root != np.arange(n_sl)):
                label = np.where(label >= 0, root[np.maximum(label, 0)], -1)
                use = np.where(off, -1, label)
                superline = root[superline]
                lines = _fit_boundaries(k_pt, t_pt, use, inside, n_sl, len(frame.s), lam, int(round(20.0 / step)),
                                        cfg.same_line_tolerance_m, double, cfg.end_dash_drift, lam_shift)
            crossing = _crossing_points(lines, use, k_pt, t_pt, cfg.assign_distance_m)
            counts = lines.finite_counts()
            short = counts * step < cfg.min_section_length_m
            n_short = int(np.sum(short & (counts > 0)))
            active = np.flatnonzero(~short & (counts > 0))
            fit = _Fit(lines.dense(active), lines.support, active)
            del lines
            solid = np.array(
                [_mark_pattern(s_pt[(use == b) & inside], cfg)[0] == "solid" for b in active], dtype=bool
            )
            seen = _observed(k_pt[inside], t_pt[inside], ~crossing[inside], len(frame.s))
            sub = _lane_structure(fit.t, fit.support[active], solid, t_ego, step, w_lane, cfg, seen, frame)
            structure = _Structure(sub.on.copy(), sub.t.copy(), active, n_sl)
            if not np.any(structure.on.sum(axis=0) >= 2):
                raise _NoRoad
            tapers, taper_notes = _taper_lanes(_Points(k_pt, t_pt, s_pt, inside, use, xyz[:, 2]), structure,
                                               -travel, step, cfg)
            found = np.zeros(len(label), dtype=bool)
            for taper in tapers:
                found[taper.points] = True
            if not np.any(found & ~off):
                break
            off |= found
            # the edge bent towards a taper's line had left its own paint unlabelled: label again
            curves = _hold_ends(_labelling_curves(sub.t, fit.t, cfg.same_line_tolerance_m),
                                int(round(100.0 / step)), cfg.same_line_tolerance_m)
            nearest = _label_by_distance(k_pt, t_pt, inside, curves, cfg)
            label = np.where(nearest >= 0, active[np.maximum(nearest, 0)], -1)
        curves = _labelling_curves(sub.t, fit.t, cfg.same_line_tolerance_m)
        curves = _hold_ends(curves, int(round(100.0 / step)), cfg.same_line_tolerance_m)
        curves = _fork_curves(curves, sub.on, cfg.min_lane_width_m)
        nearest = _label_by_distance(k_pt, t_pt, inside, curves, cfg)
        label = np.where(nearest >= 0, active[np.maximum(nearest, 0)], -1)
        if it < 2:
            frame = _recentre(frame, structure, cfg)
    assert structure is not None and fit is not None
    if n_short:
        warnings.append(
            f"ignored {n_short} marking pieces shorter than {cfg.min_section_length_m:g} m "
            "(stray returns, blobs, arrows)"
        )
    del sub, curves, nearest, use, found, crossing, seen  # (lines, stations) and per-point arrays not used below
    pts = _Points(k_pt, t_pt, s_pt, inside, np.where(off, -1, label), xyz[:, 2])
    _add_tapers(fit, structure, pts.label, tapers)
    warnings.extend(taper_notes)
    model, new_id = _assemble(cloud, pieces, superline, frame, fit, structure, pts, warnings, cfg)
    solid_rows = np.zeros(len(fit.support), dtype=bool)
    solid_rows[active] = solid
    first = int(np.argmin(np.linalg.norm(frame.xy - model.reference[0, :2], axis=1)))
    assert np.array_equal(structure.rows, fit.rows)
    divided = _divided_left(fit.t, structure.on, solid_rows[fit.rows])[first : first + len(model.s)]
    _mark_dividers(model, _ego_track(frame, ego, model), cfg, divided)
    _type_tapers(model, tapers, new_id, travel)
    _type_by_width(model, travel, cfg)
    from lidar2xodr.unpainted_lanes import type_implied_lanes

    type_implied_lanes(model)
    counts = [len(sec.boundary_ids) - 1 for sec in model.sections]
    if len(set(counts)) > 1:
        model.warnings.append(
            "lane count changes along the road: "
            + ", ".join(f"{n} from s {sec.s_start:.0f} m" for n, sec in zip(counts, model.sections, strict=True))
        )
    longest: dict[int, tuple[int, int]] = {}
    for piece, i in zip(pieces, owner, strict=True):
        if i not in longest or len(piece.centers) > longest[i][0]:
            longest[i] = (len(piece.centers), piece.superline)
    for i, c in enumerate(candidates):
        c.superline = longest[i][1]
    model.candidates = candidates
    return model


def _joins(lines: _Lines, gap_max: int, tol: float, probe: int) -> np.ndarray:
    """`_continuations` of the fitted lines, on the lines longer than `probe` stations only (the only
    ones that can join)."""
    rows = np.flatnonzero(lines.finite_counts() > probe)
    root = np.arange(len(lines.t))
    root[rows] = rows[_continuations(lines.dense(rows), gap_max, tol, probe)]
    return root


def _centre_offsets(structure: _Structure, cfg: LanesConfig, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Offset of the road centre at each station (NaN-free, smoothed) and where it is measured."""
    rows = np.flatnonzero(structure.on.any(axis=1))
    on, t = structure.on[rows], structure.t[rows]
    valid = on.sum(axis=0) >= 2
    top = np.max(np.where(on, t, -np.inf), axis=0, initial=-np.inf)
    bottom = np.min(np.where(on, t, np.inf), axis=0, initial=np.inf)
    centre = np.where(valid, 0.5 * (np.where(valid, top, 0.0) + np.where(valid, bottom, 0.0)), 0.0)
    w = valid.astype(np.float64)
    if w.sum() == 0:
        return np.zeros(len(centre)), valid
    lam = _lam(cfg.reference_smoothing_m, step)
    sm = _whittaker(centre, w, lam)
    return sm, valid


def _recentre(frame: Frame, structure: _Structure, cfg: LanesConfig) -> Frame:
    """The road centre as the next frame (trimmed to where the road is measured)."""
    centre, valid = _centre_offsets(structure, cfg, frame.s[1] - frame.s[0])
    idx = np.flatnonzero(valid)
    margin = int(round(20.0 / (frame.s[1] - frame.s[0])))
    a, b = max(idx[0] - margin, 0), min(idx[-1] + margin + 1, len(frame.s))
    return Frame(frame.point(centre)[a:b], frame.s[1] - frame.s[0])


def _reference_z(
    k: np.ndarray, t: np.ndarray, z: np.ndarray, use: np.ndarray, m: int, step: float
) -> np.ndarray:
    """Height of the road at t = 0: a plane across the road per 5 m window, smoothed along s.

    A window whose points do not lie on both sides of t = 0 (the drive's ends, a single line seen)
    gives its mean height at 5 % weight instead of a plane extrapolated to the centre: at the end of
    a 1 km straight_3000m drive such extrapolations ramped the road up 2.2 m in its last 15 m.
    """
    k, t, z = k[use], t[use], z[use]
    if len(z) == 0:
        return np.zeros(m)
    win = max(int(round(5.0 / step)), 1)
    g = k // win
    n = m // win + 1
    s1 = np.bincount(g, minlength=n).astype(np.float64)
    st, stt = np.bincount(g, t, n), np.bincount(g, t * t, n)
    sz, stz = np.bincount(g, z, n), np.bincount(g, t * z, n)
    den = s1 * stt - st**2
    spread_ok = den > 1e-6 * np.maximum(s1, 1) ** 2
    t_lo, t_hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(t_lo, g, t)
    np.maximum.at(t_hi, g, t)
    straddle = (t_lo < -1.0) & (t_hi > 1.0)
    plane = spread_ok & straddle
    a = np.where(plane, (sz * stt - st * stz) / np.where(plane, den, 1.0), sz / np.maximum(s1, 1))
    w = np.where(s1 > 0, np.where(plane, 1.0, 0.05), 0.0)
    centres = (np.arange(n) + 0.5) * win
    zz = _whittaker(np.where(w > 0, a, 0.0), w, _lam(50.0, win * step))
    return np.interp(np.arange(m), centres, zz)


def _assemble(
    cloud: MarkingCloud,
    candidates: list[Candidate],
    superline: np.ndarray,
    frame: Frame,
    fit: _Fit,
    structure: _Structure,
    pts: _Points,
    warnings: list[str],
    cfg: LanesConfig,
) -> tuple[LaneModel, np.ndarray]:
    """Trim to the measured road, number boundaries left to right, classify them, write the model.

    Also returns the boundary id of every row (-1 for rows not used)."""
    label, k_pt, t_pt, inside, s_pt = pts.label, pts.k, pts.t, pts.inside, pts.s
    step = frame.s[1] - frame.s[0]
    on, t = structure.on, structure.t
    valid = on.sum(axis=0) >= 2
    idx = np.flatnonzero(valid)
    a, b = int(idx[0]), int(idx[-1]) + 1
    s = frame.s[a:b] - frame.s[a]
    on, t = on[:, a:b], t[:, a:b]
    used_at = np.flatnonzero(on.any(axis=1))
    med = np.array([np.nanmedian(t[i]) for i in used_at])
    ordered_at = used_at[np.argsort(-med, kind="stable")]
    used, ordered = structure.rows[used_at], structure.rows[ordered_at]
    painted = inside & np.isin(label, ordered)
    by_row = np.argsort(label[painted], kind="stable")
    row_labels, row_starts = np.unique(label[painted][by_row], return_index=True)
    row_pts = dict(zip(row_labels.tolist(), np.split(s_pt[painted][by_row], row_starts[1:]), strict=True)) \
        if len(row_labels) else {}
    patterns = [_mark_pattern(row_pts.get(int(old), np.zeros(0)), cfg) for old in ordered]
    residuals = []
    for old in ordered:
        sel = (label == old) & inside
        resid = t_pt[sel] - fit.t[fit.row_of(old), k_pt[sel]]
        residuals.append(resid[np.isfinite(resid)])
    widths = marking_widths(residuals)
    rows = [
        Boundary(id=-1, t=np.where(on[at], t[at], np.nan), mark_type=kind,
                 mark_width=round(width, 3) if width is not None else 0.15, dash_length=dash, gap_length=gap)
        for at, width, (kind, dash, gap) in zip(ordered_at, widths, patterns, strict=True)
    ]
    rows_on, rows_t = on[ordered_at], t[ordered_at]
    if cfg.unpainted_lanes:
        from lidar2xodr.unpainted_lanes import implied_edges  # it uses this module's helpers
        broken = np.array([kind == "broken" and dash is not None and gap is not None
                           for kind, dash, gap in patterns], dtype=bool)
        solid = np.array([kind == "solid" for kind, _, _ in patterns], dtype=bool)
        extra_on, extra_t = implied_edges(rows_on, rows_t, broken, solid, step, cfg)
        if len(extra_on):
            rows_on, rows_t = np.vstack([rows_on, extra_on]), np.vstack([rows_t, extra_t])
            rows += [Boundary(id=-1, t=row, mark_type="none", mark_width=0.0) for row in extra_t]
            warnings.append(
                f"{len(extra_on)} lane(s) beyond a broken outermost line built without a seen outer edge "
                "(a broken line has a lane on both sides; width from its neighbour)"
            )
    final = np.argsort(-np.array([np.nanmedian(r.t) for r in rows]), kind="stable")
    rows_on, rows_t = rows_on[final], rows_t[final]
    boundaries = [rows[i] for i in final]
    for i, bnd in enumerate(boundaries):
        bnd.id = i
    position = np.argsort(final, kind="stable")
    new_id = np.full(structure.n, -1, dtype=np.int64)
    new_id[ordered] = position[: len(ordered)]
    z_ref = _reference_z(k_pt, t_pt, pts.z, inside & (label >= 0) & np.isin(label, used), len(frame.s), step)
    reference = np.column_stack([frame.xy[a:b], z_ref[a:b]])
    sections, on_new, t_new = _sections(rows_on, rows_t, s, cfg.min_section_length_m)
    for i, bnd in enumerate(boundaries):
        bnd.t = t_new[i]
    row_s = {int(position[k]): np.sort(row_pts[int(old)]) for k, old in enumerate(ordered) if int(old) in row_pts}
    section_marks(sections, boundaries, row_s, float(frame.s[a]), cfg)
    for i, c in enumerate(candidates):
        c.superline = int(new_id[superline[i]]) if superline[i] < len(new_id) else -1
    warnings.extend(_unused_notes(fit.t[:, a:b], on_new, {int(fit.row_of(old)): int(new_id[old]) for old in ordered},
                                  s))
    model = LaneModel(
        s=s,
        reference=reference,
        boundaries=boundaries,
        sections=sections,
        candidates=candidates,
        origin=cloud.origin,
        warnings=warnings,
    )
    return model, new_id


def _unused_notes(t_fit: np.ndarray, on: np.ndarray, row: dict[int, int], s: np.ndarray) -> list[str]:
    """One warning per measured line (row: its boundary id) for the stretches where it is not a lane boundary."""
    notes = []
    for x in range(len(t_fit)):
        used = on[row[x]] if x in row else np.zeros(len(s), dtype=bool)
        unused = np.isfinite(t_fit[x]) & ~used
        spans = [(a, b) for a, b in _runs(unused) if s[b - 1] - s[a] >= 1.0]
        if not spans:
            continue
        where = ", ".join(f"{s[a]:.0f}-{s[b - 1]:.0f}" for a, b in spans[:3]) + (
            " ..." if len(spans) > 3 else ""
        )
        t_med = float(np.nanmedian(t_fit[x][unused]))
        name = f"boundary {row[x]}" if x in row else "a marking line"
        notes.append(
            f"{name} ({t_med:+.1f} m from the reference) ignored on s {where} m: off the carriageway, "
            "a duplicate, or no stable lane beside it"
        )
    return notes
