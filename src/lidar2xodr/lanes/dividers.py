"""Directions on a paint-only two-way road: the divider from where the ego drove, opposite lanes kept or dropped."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import LaneModel, LaneSection
from lidar2xodr.lanes.frame import Frame


def _ego_offsets(frame: Frame, ego: np.ndarray | None) -> np.ndarray | None:
    """The ego's offset at every station (NaN beyond its samples), from the samples that travel the way
    it first travelled on the frame: a drive that turns round passes the stations twice, on a divided
    road once on each carriageway, and one curve through both passes would jump between them."""
    if ego is None or len(ego) < 2:
        return None
    s, t, inside = frame.project(ego)
    ds = np.gradient(s)
    moving = inside & (np.abs(ds) > 1e-3)
    if moving.sum() >= 2:
        inside = moving & (np.sign(ds) == np.sign(ds[np.flatnonzero(moving)[0]]))
    if inside.sum() < 2:
        return None
    order = np.argsort(s[inside])
    return np.interp(frame.s, s[inside][order], t[inside][order], left=np.nan, right=np.nan)


@dataclass
class _EgoTrack:
    """Trajectory samples on the model's stations: index, offset, and +1/-1 travelling along/against s."""

    k: np.ndarray
    t: np.ndarray
    direction: np.ndarray


def _ego_track(frame: Frame, ego: np.ndarray | None, model: LaneModel) -> _EgoTrack | None:
    """The trajectory on the model's stations (the model starts at a station of `frame`).

    Only samples heading within 14 degrees of the road axis are kept (a lane change takes a few):
    a U-turn at the end of the drive (or a stop) has no travel direction along the road, so it
    cannot tell a divider's side.
    """
    if ego is None or len(ego) < 3:
        return None
    s_e, t_e, inside = frame.project(ego)
    ds = np.gradient(s_e)
    moving = (np.abs(ds) > 1e-3) & (np.abs(np.gradient(t_e)) < 0.25 * np.abs(ds))
    step = float(frame.s[1] - frame.s[0])
    first = int(np.argmin(np.linalg.norm(frame.xy - model.reference[0, :2], axis=1)))
    k = np.rint(s_e / step).astype(np.int64) - first
    keep = inside & moving
    return _EgoTrack(k[keep], t_e[keep], np.sign(ds[keep]).astype(np.int64))


def _divided_left(t_fit: np.ndarray, on: np.ndarray, solid: np.ndarray, on_rows: np.ndarray | None = None
                  ) -> np.ndarray:
    """Stations where another carriageway lies left of the kept one beyond a median: the nearest
    measured line left of the leftmost kept line is solid (its left edge line) and has a line beyond it.
    `on`: where each kept line is kept, for the rows `on_rows` of `t_fit` (default all rows). Only rows
    with a kept or a fitted station are looked at: most of a long drive's (lines, stations) array is empty."""
    m = t_fit.shape[1]
    if on_rows is None:
        on_rows = np.arange(len(on))
    held = on.any(axis=1)
    on_rows, on = on_rows[held], on[held]
    rows = np.flatnonzero(np.isfinite(t_fit).any(axis=1))
    on_at = np.zeros((len(rows), m), dtype=bool)
    pos = np.minimum(np.searchsorted(rows, on_rows), max(len(rows) - 1, 0))
    hit = (rows[pos] == on_rows) if len(rows) else np.zeros(len(on_rows), dtype=bool)
    on_at[pos[hit]] = on[hit]
    with np.errstate(invalid="ignore"):
        top = np.max(np.where(on, t_fit[on_rows], -np.inf), axis=0, initial=-np.inf)
        beyond = ~on_at & np.isfinite(t_fit[rows]) & (t_fit[rows] > top[None, :] + 0.5)
    count = beyond.sum(axis=0)
    if len(rows) == 0:
        return np.zeros(m, dtype=bool)
    nearest = rows[np.argmin(np.where(beyond, t_fit[rows], np.inf), axis=0)]
    return (count >= 2) & solid[nearest]


def _mark_dividers(model: LaneModel, ego: _EgoTrack | None, cfg: LanesConfig,
                   divided: np.ndarray | None = None) -> None:
    """Set `LaneSection.divider_id` where a painted line separates the two directions.

    Evidence (right-hand traffic), none of it from the trajectory's shape connecting markings, and
    only from trajectory samples on the carriageway (within 1 m of its outermost lines: beyond a
    median the ego drives another carriageway): the line is solid, has lanes on both sides over
    sections of at least `divider_min_length_m` together, and every trajectory sample beside it
    lies on the side of its own travel direction (right of it while moving along s, left while
    moving against s), over at least
    `divider_min_length_m` of stations, up to `divider_max_wrong_side_m` of stations (projection
    noise where a U-turn ends the drive): the ego never crossed it. A broken (or other non-solid)
    centre line qualifies only when the ego drove both ways beside it, each over
    `divider_min_length_m` (along s right of it, against s left of it): a one-way carriageway is
    never driven against s; a solid candidate wins over broken ones, and several broken ones alone
    (every line between the two tracks qualifies) are ambiguous, so none is set. A solid line inside one
    carriageway (an exit lane's, a lane drop's) is short, or crossed, or has the ego on its wrong
    side, so it is no divider. A road shorter than `divider_min_length_m` cannot show that
    much line: there `divider_short_share` of its length stands in for it, and every line (solid
    too) needs the decisive evidence, the ego driving both ways beside it (along s right of it,
    against s left of it) each over that share; a solid no-lane-change line between lanes of one
    direction (near a junction) is never driven against s, so it cannot qualify. Without a
    trajectory no divider is set (the side cannot be known); where several lines qualify,
    the one nearest the ego bounds its carriageway. Sections where the
    line is the outermost one (the opposite lanes not seen) keep no divider. A line beside which
    another carriageway lies left of this one beyond a median over more than half its stations
    (`divided`, from `_divided_left`) is no divider whatever the ego did: under right-hand traffic
    that carriageway is the opposite direction, so this one is one-way (a drive that turned round
    on it drove it the wrong way).
    """
    if ego is None or not model.sections or len(ego.k) == 0:
        return
    by_id = {b.id: b for b in model.boundaries}
    step = float(model.s[1] - model.s[0]) if len(model.s) > 1 else 1.0
    inner: dict[int, list[int]] = {}
    for j, sec in enumerate(model.sections):
        for bid in sec.boundary_ids[1:-1]:
            inner.setdefault(bid, []).append(j)
    ok = np.flatnonzero((ego.k >= 0) & (ego.k < len(model.s)))
    # only samples on this carriageway: beyond a median the ego drives another one
    ts = np.array([b.t for b in model.boundaries])
    with np.errstate(invalid="ignore"):
        top, bottom = np.nanmax(ts, axis=0), np.nanmin(ts, axis=0)
    ok = ok[(ego.t[ok] <= top[ego.k[ok]] + 1.0) & (ego.t[ok] >= bottom[ego.k[ok]] - 1.0)]
    k, t_e, direction = ego.k[ok], ego.t[ok], ego.direction[ok]
    road = float(model.s[-1] - model.s[0])
    short = road < cfg.divider_min_length_m
    need = cfg.divider_short_share * road if short else cfg.divider_min_length_m
    closeness: dict[int, float] = {}
    along: dict[int, bool] = {}
    for bid, secs in inner.items():
        length = sum(model.sections[j].s_end - model.sections[j].s_start for j in secs)
        if length < need:
            continue
        if divided is not None and float(np.mean(divided[np.isfinite(by_id[bid].t)])) > 0.5:
            continue
        t_b = by_id[bid].t[k]
        beside = np.isfinite(t_b)
        if not beside.any():
            continue
        right_side = t_e[beside] < t_b[beside]
        consistent = np.where(direction[beside] > 0, right_side, ~right_side)
        covered = _covered_m(k[beside], step)
        wrong = len(np.unique(k[beside][~consistent])) * step
        both = [_covered_m(k[beside][consistent & (direction[beside] == sign)], step) for sign in (1, -1)]
        if (short or by_id[bid].mark_type != "solid") and min(both) < need:
            continue
        if wrong <= cfg.divider_max_wrong_side_m and covered >= need:
            closeness[bid] = float(np.median(np.abs(t_e[beside] - t_b[beside])))
            along[bid] = bool(np.median(direction[beside]) > 0)
    for j, sec in enumerate(model.sections):
        found = [bid for bid in closeness if j in inner[bid]]
        solid = [bid for bid in found if by_id[bid].mark_type == "solid"]
        if solid or len(found) > 1:
            found = solid
        sec.divider_id = min(found, key=lambda b: (closeness[b], b)) if found else None
    _drop_partial_opposite(model, along)


def _covered_m(k: np.ndarray, step: float, max_gap_m: float = 5.0) -> float:
    """Length of road the samples at stations k cover: the stations between neighbouring samples up
    to `max_gap_m` apart count (poses a few metres apart cover the road between them)."""
    u = np.unique(k)
    if len(u) == 0:
        return 0.0
    cap = max(int(round(max_gap_m / step)), 1)
    return float(np.sum(np.minimum(np.diff(u), cap)) + 1) * step


def _drop_partial_opposite(model: LaneModel, along: dict[int, bool]) -> None:
    """Keep the opposite carriageway only where it was seen whole.

    A carriageway is complete when its outermost line is a solid edge line. In every section whose
    outermost line beyond the divider (the side the ego does not drive) is not solid, the opposite
    lanes are left out: the divider becomes the leftmost boundary (lane 0 stays on it) and only the
    ego's direction is exported there, with a warning. A wrong lane count is worse than a missing
    carriageway. Only done when the ego drives along s (the opposite lanes are left of the
    divider); against s the section is left as it is, because a one-way export runs along s.
    """
    by_id = {b.id: b for b in model.boundaries}
    cut_at: list[str] = []
    for sec in model.sections:
        d = sec.divider_id
        if d is None or not along.get(d, False) or by_id[sec.boundary_ids[0]].mark_type == "solid":
            continue
        cut_at.append(f"{sec.s_start:.0f}-{sec.s_end:.0f}")
        sec.boundary_ids = sec.boundary_ids[sec.boundary_ids.index(d) :]
        sec.divider_id = None
        sec.marks = {i: m for i, m in (sec.marks or {}).items() if i in sec.boundary_ids} or None
    if not cut_at:
        return
    merged: list[LaneSection] = []
    for sec in model.sections:
        prev = merged[-1] if merged else None
        if prev and prev.boundary_ids == sec.boundary_ids and prev.divider_id == sec.divider_id \
                and prev.marks == sec.marks:
            prev.s_end = sec.s_end
        else:
            merged.append(sec)
    model.sections = merged
    model.warnings.append(
        "the opposite carriageway was seen only partly on s " + ", ".join(cut_at) + " m (its outermost "
        "line is not a solid edge line): only the ego's direction is exported there"
    )
