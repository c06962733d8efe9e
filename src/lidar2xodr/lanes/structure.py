"""Cross-sections: which lines form the carriageway at every station, tapers followed to zero width."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar2xodr.config import LanesConfig
from lidar2xodr.lanes.frame import Frame
from lidar2xodr.lanes.smoothing import _groups, _runs
from lidar2xodr.lanes.tracks import _ABSENT_RUN, _Observed, _strays

_SORT_CELLS = 1 << 20  # (line, station) cells sorted at once by `_present_columns`


@dataclass
class _Structure:
    """The kept lines: only the rows of lines that can be kept (most of a long drive's fitted lines
    are short pieces that never are), each with its row in the full numbering of lines."""

    on: np.ndarray  # (R, M) boundary kept at station
    t: np.ndarray  # (R, M) offsets including taper extensions
    rows: np.ndarray | None = None  # (R,) ascending row of each in the full numbering (None: 0..R-1)
    n: int = 0  # rows in the full numbering

    def __post_init__(self) -> None:
        if self.rows is None:
            self.rows = np.arange(len(self.on))
        self.n = max(self.n, len(self.on))


def _lane_structure(
    t_fit: np.ndarray,
    support: np.ndarray,
    solid: np.ndarray,
    t_ego: np.ndarray | None,
    step: float,
    w_lane: float,
    cfg: LanesConfig,
    seen: _Observed | None = None,
    frame: Frame | None = None,
) -> _Structure:
    """Which boundaries form the carriageway at each station, with tapers followed to zero width.

    `seen` (where marking points were measured, see `_Observed`) keeps lines from being carried
    towards the drive's ends where they were seen to be absent; `frame` (the stations' axis) lets
    `_open_beside_edge` tell in the world which of two lines moves.

    Two rounds: the extensions found in the first (tapers, lines carried to the drive's ends) are
    measured lines in the second, which decides presence again from scratch, so a line dropped
    only because its neighbour had not been carried yet comes back.
    """
    rank = np.argsort(np.argsort(-support, kind="stable"), kind="stable")
    min_run = max(int(round(cfg.min_section_length_m / step)), 1)
    t = t_fit.copy()
    on = np.isfinite(t)
    for _ in range(2):
        on = np.isfinite(t)
        _drop_duplicates(t, on, rank, cfg.same_line_tolerance_m, min_run)
        for _ in range(3):
            on = _choose_carriageway(t, on, t_ego, solid, support, cfg)
            on, _ = _check_adjacency(t, on, rank, step, cfg)
            on = _clean_runs(on, min_run)
        t_ext, on = _follow_tapers(t, on, step, w_lane, cfg, seen, solid, frame)
        t = np.where(on, t_ext, t)
    return _Structure(on, np.where(on, t, np.nan))


def _drop_duplicates(t: np.ndarray, on: np.ndarray, rank: np.ndarray, tol: float, min_run: int) -> None:
    """Where two lines run closer than `tol`, keep one: the one that goes on where the other ends
    (a lane closing onto its neighbour), else the one with more support.

    Only pairs whose kept spans overlap are compared, on that overlap: presence is only ever taken
    away here, so a pair apart at the start stays apart."""
    b_n, m = t.shape
    finite = np.isfinite(t)
    lo, hi = _spans(on)
    for i in range(b_n):
        for j in np.flatnonzero(np.maximum(lo[i + 1 :], lo[i]) < np.minimum(hi[i + 1 :], hi[i])) + i + 1:
            a, e = max(lo[i], lo[j]), min(hi[i], hi[j])
            close = on[i, a:e] & on[j, a:e] & (np.abs(t[i, a:e] - t[j, a:e]) < tol)
            for c0, c1 in _runs(close):
                c0, c1 = c0 + a, c1 + a
                bi, ai = _finite_reach(finite[i], c0, c1)
                bj, aj = _finite_reach(finite[j], c0, c1)
                ends_i = (ai < min_run <= aj) or (bi < min_run <= bj)
                ends_j = (aj < min_run <= ai) or (bj < min_run <= bi)
                if ends_i != ends_j:
                    victim = i if ends_i else j
                else:
                    victim = i if rank[i] > rank[j] else j
                on[victim, c0:c1] = False


def _spans(on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[first, last + 1) of every row's True stations ((0, 0) for a row without any)."""
    anyon = on.any(axis=1)
    m = on.shape[1]
    lo = np.where(anyon, np.argmax(on, axis=1), 0)
    hi = np.where(anyon, m - np.argmax(on[:, ::-1], axis=1), 0)
    return lo, hi


def _finite_reach(finite: np.ndarray, c0: int, c1: int) -> tuple[int, int]:
    """How far a line goes on (measured) before station c0 and after station c1."""
    gaps_before = np.flatnonzero(~finite[:c0])
    gaps_after = np.flatnonzero(~finite[c1:])
    before = c0 - 1 - (gaps_before[-1] if len(gaps_before) else -1)
    after = gaps_after[0] if len(gaps_after) else len(finite) - c1
    return int(before), int(after)


def _sorted_columns(t: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per station: boundary indices ordered left to right (present first) and their offsets."""
    key = np.where(on, -t, np.inf)
    order = np.argsort(key, axis=0, kind="stable")
    return order, np.take_along_axis(np.where(on, t, np.nan), order, axis=0)


def _present_columns(t: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_sorted_columns` cut to as many places as the fullest station has present lines: the places
    below hold no line at any station (a long drive keeps ~90 rows but ~6 lines at a station).
    Sorted in blocks of stations, so the full sort of one block is all that is held at once."""
    depth = min(max(int(on.sum(axis=0).max(initial=0)), 1), len(t))
    m = t.shape[1]
    order = np.empty((depth, m), dtype=np.intp)
    ts = np.empty((depth, m))
    step = max(_SORT_CELLS // max(len(t), 1), 1)
    for a in range(0, m, step):
        o, v = _sorted_columns(t[:, a:a + step], on[:, a:a + step])
        order[:, a:a + step], ts[:, a:a + step] = o[:depth], v[:depth]
    return order, ts


def _choose_carriageway(
    t: np.ndarray,
    on: np.ndarray,
    t_ego: np.ndarray | None,
    solid: np.ndarray,
    support: np.ndarray,
    cfg: LanesConfig,
) -> np.ndarray:
    """Split into carriageways and keep the one with the ego (else the most lines, then most points).

    Splits: spacings above `carriageway_gap_m`; steady spacings above `max_lane_width_m` between
    the outermost two lines (inside, or while a taper opens, such a space holds a lane whose
    line was not seen); and a
    space between two solid lines that both have lines beyond them (the median between two
    carriageways: each edge line has its own lanes on its other side).
    """
    b_n, m = t.shape
    if b_n == 0 or m == 0:
        return np.zeros_like(on)
    order, ts = _present_columns(t, on)
    present = np.isfinite(ts)
    gap = ts[:-1] - ts[1:]
    both_solid = solid[order[:-1]] & solid[order[1:]]
    beyond = np.vstack([np.zeros((1, m), dtype=bool), present[:-2]]) & np.vstack(
        [present[2:], np.zeros((1, m), dtype=bool)]
    )
    median = both_solid & beyond & present[:-1] & present[1:]
    none = np.zeros((1, m), dtype=bool)
    outer = ~np.vstack([none, present[:-2]]) | ~np.vstack([present[2:], none])
    cols = np.arange(m)
    ahead, back = np.minimum(cols + 5, m - 1), np.maximum(cols - 5, 0)
    width_then = t[order[:-1], ahead] - t[order[1:], ahead]
    width_before = t[order[:-1], back] - t[order[1:], back]
    steady = np.abs(width_then - width_before) < cfg.stable_lane_slope * (ahead - back) * 1.0
    wide_edge = outer & (gap > cfg.max_lane_width_m) & steady
    split = np.vstack([none, ~(gap <= cfg.carriageway_gap_m) | median | wide_edge])
    group = np.cumsum(split, axis=0)
    n_groups = group.max() + 1
    weight = support[order] / max(float(support.max()), 1e-9)
    row, col = np.nonzero(present)  # row by row: each (group, station) sums its rows in order
    cell = group[row, col] * m + col
    count = np.bincount(cell, minlength=n_groups * m).reshape(n_groups, m)
    mass = np.bincount(cell, weight[row, col], minlength=n_groups * m).reshape(n_groups, m)
    choice = np.argmax(count + 1e-3 * mass, axis=0)
    if t_ego is not None:
        top = np.full(n_groups * m, -np.inf)
        bot = np.full(n_groups * m, np.inf)
        np.maximum.at(top, cell, ts[row, col])
        np.minimum.at(bot, cell, ts[row, col])
        top, bot = top.reshape(n_groups, m), bot.reshape(n_groups, m)
        holds = (t_ego <= top + 0.5) & (t_ego >= bot - 0.5) & np.isfinite(t_ego)
        last = n_groups - 1 - np.argmax(holds[::-1], axis=0)
        choice = np.where(holds.any(axis=0), last, choice)
    keep_sorted = present & (group == choice[None, :])
    keep = np.zeros_like(on)
    np.put_along_axis(keep, order, keep_sorted, axis=0)
    return keep & on


def _check_adjacency(
    t: np.ndarray, on: np.ndarray, rank: np.ndarray, step: float, cfg: LanesConfig
) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Every pair of neighbouring lines must hold a stable lane somewhere along their adjacency."""
    b_n, m = t.shape
    order, ts = _present_columns(t, on)
    need = max(int(round(cfg.min_section_length_m / step)), 1)
    upper, lower = order[:-1], order[1:]
    valid = np.isfinite(ts[:-1]) & np.isfinite(ts[1:])
    width = ts[:-1] - ts[1:]
    key = np.where(valid, upper * b_n + lower, -1)
    rows, cols = np.nonzero(valid)  # row by row; a pair of neighbours meets at most once per station
    cells = dict(_groups(key[rows, cols]))
    stable_len: dict[int, int] = {}
    for key_value, at in cells.items():
        c = cols[at]
        a, e = max(int(c.min()) - 1, 0), min(int(c.max()) + 2, m)  # one zero either side: same gradient
        w = np.zeros(e - a)
        w[c - a] = width[rows[at], c]
        slope = np.abs(np.gradient(w)) / step
        held = np.zeros(e - a, dtype=bool)
        held[c - a] = True
        good = (
            held & (w >= cfg.min_lane_width_m) & (w <= cfg.max_lane_width_m) & (slope < cfg.stable_lane_slope)
        )
        stable_len[key_value] = max((int(y - x) for x, y in _runs(good)), default=0)
    count = on.sum(axis=0)
    on = on.copy()
    dropped: list[tuple[int, int, int]] = []
    for key_value, length in sorted(stable_len.items()):
        if length >= need:
            continue
        a, b = divmod(key_value, b_n)
        r, c = rows[cells[key_value]], cols[cells[key_value]]
        first_row = np.all(r == 0)
        last_row = np.all(count[c] == r + 2)
        if first_row and not last_row:
            victim = a
        elif last_row and not first_row:
            victim = b
        else:
            victim = a if rank[a] > rank[b] else b
        on[victim, c] = False
        dropped.append((int(victim), int(c.min()), int(c.max())))
    return on, dropped


def _clean_runs(on: np.ndarray, min_run: int) -> np.ndarray:
    """Drop presence runs shorter than `min_run` stations."""
    out = on.copy()
    for b in range(len(on)):
        for s, e in _runs(on[b]):
            if e - s < min_run:
                out[b, s:e] = False
    return out


def _follow_tapers(
    t: np.ndarray, on: np.ndarray, step: float, w_lane: float, cfg: LanesConfig, seen: _Observed | None = None,
    solid: np.ndarray | None = None, frame: Frame | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Extend boundaries that appear or end back (forward) to where their new lane has zero width."""
    t = t.copy()
    on = on.copy()
    b_n, m = t.shape
    reach = int(round(cfg.max_taper_length_m / step))
    min_run = max(int(round(cfg.min_section_length_m / step)), 1)
    probe = max(int(round(40.0 / step)), 2)
    road = np.flatnonzero(on.sum(axis=0) >= 2)
    if len(road) == 0:
        return t, on
    for _ in range(3):
        before = on.sum()
        for b in range(b_n):
            for s, e in _runs(on[b]):
                for start, edge, inward in ((s, s, 1), (e - 1, e, -1)):
                    if (inward == 1 and edge == 0) or (inward == -1 and edge == m):
                        continue
                    if not _extend(t, on, b, start, inward, probe, reach, w_lane) \
                            and not (e - s >= min_run
                                     and _open_beside_edge(t, on, b, start, inward, reach,
                                                           min(cfg.narrow_lane_width_m, cfg.min_lane_width_m),
                                                           frame)):
                        end = road[0] if inward == 1 else road[-1]
                        if abs(start - end) <= reach:
                            _hold_to(t, on, b, start, end, seen if solid is not None and solid[b] else None)
        if on.sum() == before:
            break
    return t, on


def _hold_to(
    t: np.ndarray, on: np.ndarray, b: int, start: int, end: int, seen: _Observed | None = None
) -> None:
    """Carry boundary b from `start` to the road's end `end` at a constant offset from a neighbour.

    The neighbour is the nearest of those that reach furthest towards the end; where it moves against
    the other lines there (`_moves`) and b's nearest line on its other side does not, that one: where
    a 2+1 road's centre line moves across, the edge beside the passing lane's line stays, and so does
    the line. Lines start late or end early near the ends of a drive because they were not yet (or
    no longer) observed, not because the lane count changes. A line that ends on another one (within 1 m: a lane that
    closed) is not carried. The outermost line (none kept beyond it on that side), when it is solid
    (`seen` given), is not carried past the first stretch of `_ABSENT_RUN` stations where marking
    points were measured more than 1 m beyond it but none where it would run (those would be the
    line itself, only not fitted there; a shorter stretch can be a patch of clutter): the sensor
    saw that far there, and a solid line would have been seen (a broken line's far dashes are
    missed where a solid line beyond is still seen), so the line was absent, not unobserved (a
    lane that appears at full width near the start of a short drive, a ramp joining). Inner lines
    are carried as before: a broken line's last dash may end a gap early.
    """
    span = np.arange(start - 1, end - 1, -1) if end < start else np.arange(start + 1, end + 1)
    others = [j for j in range(len(t)) if j != b and on[j, start]]
    if not others or len(span) == 0:
        return
    def cover(j: int) -> float:
        return round(float(on[j, span].mean()), 1)

    nb = max(others, key=lambda j: (cover(j), -abs(t[j, start] - t[b, start])))
    across = [j for j in others if (t[j, start] - t[b, start]) * (t[nb, start] - t[b, start]) < 0]
    if across and _moves(t, on, nb, b, start, others, span):
        alt = min(across, key=lambda j: abs(t[j, start] - t[b, start]))
        if cover(alt) == cover(nb) and not _moves(t, on, alt, b, start, others, span):
            nb = alt
    offset = t[b, start] - t[nb, start]
    if min(abs(t[j, start] - t[b, start]) for j in others) < 1.0:
        return
    if seen is not None and not any(np.sign(offset) * (t[j, start] - t[b, start]) > 0 for j in others):
        carried = t[nb, span] + offset
        absent = seen.beyond(span, carried, float(np.sign(offset))) & ~seen.near(span, carried)
        runs = [a for a, e in _runs(absent) if e - a >= _ABSENT_RUN]
        span = span[: runs[0] if runs else len(span)]
    span = span[on[nb, span] & ~on[b, span]]
    t[b, span] = t[nb, span] + offset
    on[b, span] = True


def _moves(t: np.ndarray, on: np.ndarray, j: int, b: int, start: int, others: list[int], span: np.ndarray) -> bool:
    """Whether line j's spacing to more than half of the other present lines changes by over 1 m along
    `span` from their spacing at `start` (`tracks._strays`): j moves against the road there, the others
    stay."""
    ks = np.concatenate([[start], span])
    rest = [q for q in others if q not in (j, b)]
    return _strays(np.where(on[j, ks], t[j, ks], np.nan), np.where(on[rest][:, ks], t[rest][:, ks], np.nan), 1.0)


def _open_beside_edge(t: np.ndarray, on: np.ndarray, b: int, start: int, inward: int, reach: int,
                      min_width: float, frame: Frame | None = None) -> bool:
    """Carry line b back (forward) at its offset to its inner neighbour p while the lane beyond it opens
    (closes) along the carriageway's edge e (`_follow_tapers` asks only for a line kept over at least
    `min_section_length_m`: a line seen for a few metres at a drive's end shows no lane).

    An entry or exit lane whose line is painted (or found) only where the lane is wide: the line
    starts with most of a lane between it and the edge, and before its start the edge comes in towards
    p until the edge is one lane (b's) from p. `min_width` is the narrowest lane cars use
    (`narrow_lane_width_m`), not `min_lane_width_m`: a line is kept only where it has a lane of that
    width beside it, so at an exit whose lane grows from the edge its line starts near that width, and
    was carried back at its offset to the diverging edge instead (highway_exit s2: a 0.6 m lane beside
    the through lane over 100 m). The edge's course, not b's paint, shows the taper, so
    `_extend` (which measures the taper along b) does not see it. Only when e is the outermost line,
    the lane beyond b is at least `min_width` wide where b starts, and the edge's spacing to p shrinks
    without a jump to b's spacing within `reach` stations (the taper's far end, where b meets e),
    while p keeps its spacing to every other line seen there (it is e that moves, not p: on a 2+1
    road the centre line moves across while the edges stay, and a new lane line beside the edge is
    not carried along the centre line); and only when this holds on one side of b. Where no other line
    is seen along the walk (a two-lane carriageway whose far edge is not painted or not seen), the
    spacings cannot tell which of p and e moves: the recentred frame keeps their middle, so both swing
    by half the taper. Then the world decides (`frame`): p must run straighter than e, within a fifth
    of e's deviation from its own best quadratic over the walk and a walk's length on each side
    (`_bend`; corridor_017 s1: the through line 0.01 m, the entry lane's edge 0.9 m). The walk follows
    p and e where they are fitted, not only where the carriageway choice kept them: before b starts, the
    two lanes between p and e are one space too wide for a lane, so that choice keeps one of the two
    lines per station (corridor_007 s2: each alone on alternating stretches, the walk stopped at once)."""
    rows = [j for j in range(len(t)) if j != b and on[j, start]]
    tb = t[b, start]
    found: list[tuple[int, int, float, float, list[int]]] = []
    for d in (1.0, -1.0):
        beyond = [j for j in rows if d * (t[j, start] - tb) > 0]
        inner = [j for j in rows if d * (t[j, start] - tb) < 0]
        if len(beyond) != 1 or not inner:
            continue
        e = beyond[0]
        p = min(inner, key=lambda j: abs(t[j, start] - tb))
        g_in, g_out = d * (tb - t[p, start]), d * (t[e, start] - tb)
        if g_out < min_width:
            continue
        walked: list[int] = []
        previous = g_out
        closed = False
        for i in range(1, reach + 1):
            k = start - inward * i
            if not 0 <= k < t.shape[1] or on[b, k] or not (np.isfinite(t[e, k]) and np.isfinite(t[p, k])):
                break
            width = d * (t[e, k] - t[p, k]) - g_in
            if width > previous + 0.1 or (i == 1 and abs(width - g_out) > 0.5):
                break
            walked.append(k)
            if width <= 0.05:
                closed = True
                break
            previous = min(previous, width)
        if not closed:
            continue
        others = [q for q in rows if q not in (e, p) and on[q, walked].all()]
        moved = [float(np.max(np.abs((t[p, walked] - t[q, walked]) - (t[p, start] - t[q, start])))) for q in others]
        if others and max(moved) < 0.2 * g_out:
            found.append((e, p, d, g_in, walked))
        elif not others and frame is not None:
            n = len(walked)
            lo, hi = sorted((start + inward * n, walked[-1] - inward * n))
            around = np.arange(max(lo, 0), min(hi, t.shape[1] - 1) + 1)
            if _bend(frame, t, on, p, around) < 0.2 * _bend(frame, t, on, e, around):
                found.append((e, p, d, g_in, walked))
    if len(found) != 1:
        return False
    e, p, d, g_in, walked = found[0]
    for k in walked[:-1]:
        t[b, k] = t[p, k] + d * g_in
    t[b, walked[-1]] = t[e, walked[-1]]
    on[b, walked] = True
    return True


def _bend(frame: Frame, t: np.ndarray, on: np.ndarray, j: int, ks: np.ndarray) -> float:
    """Largest deviation of line j's world course at stations `ks` (where it is present) from its best
    quadratic: a line along the road (on a curve too) stays within its noise, a line that comes in
    between two parallel stretches does not. Infinite when the line is present at fewer than 10 stations."""
    ks = ks[on[j, ks]]
    if len(ks) < 10:
        return float("inf")
    xy = frame.xy[ks] + frame.normal[ks] * t[j, ks][:, None]
    chord = xy[-1] - xy[0]
    u = chord / max(float(np.linalg.norm(chord)), 1e-9)
    x = (xy - xy[0]) @ u
    y = (xy - xy[0]) @ np.array([-u[1], u[0]])
    return float(np.max(np.abs(y - np.polyval(np.polyfit(x, y, 2), x))))


def _extend(
    t: np.ndarray, on: np.ndarray, b: int, start: int, inward: int, probe: int, reach: int, w_lane: float
) -> bool:
    """Follow boundary b from station `start` outwards (against `inward`) while its new lane closes.

    An outermost line stops where another line lies beyond it: there, that line is the edge, and a
    taper's line does not run inside it (an edge that starts after an exit's gore, followed back along
    the old edge, bent the recentred frame 3.5 m on corridor_010 s2)."""
    window = np.arange(start, start + inward * probe, inward)
    window = window[(window >= 0) & (window < t.shape[1])]
    tb = t[b, start]
    others = [j for j in range(len(t)) if j != b and on[j, start]]
    left = [j for j in others if t[j, start] > tb]
    right = [j for j in others if t[j, start] < tb]
    nb_left = min(left, key=lambda j: t[j, start] - tb) if left else None
    nb_right = max(right, key=lambda j: t[j, start] - tb) if right else None
    best = None
    for grow, other in ((nb_left, nb_right), (nb_right, nb_left)):
        if grow is None:
            continue
        w = np.abs(t[grow, window] - t[b, window])
        ok = np.isfinite(w) & on[grow, window] & on[b, window]
        if ok.sum() < 2:
            continue
        x = (window[ok] - start) * inward
        slope = np.polyfit(x, w[ok], 1)[0]
        w0 = abs(t[grow, start] - tb)
        if slope <= 1e-4 or w0 > 0.8 * w_lane:
            continue
        if best is None or w0 < best[0]:
            best = (w0, grow, other, slope)
    if best is None:
        return False
    w0, grow, other, slope = best
    sign = 1.0 if t[grow, start] > tb else -1.0
    previous = w0
    for i in range(1, reach + 1):
        k = start - inward * i
        if k < 0 or k >= t.shape[1] or on[b, k] or not np.isfinite(t[grow, k]):
            return True
        if other is not None and np.isfinite(t[other, k]):
            tk = t[other, k] + (tb - t[other, start])
        elif other is None:
            tk = t[grow, k] - sign * max(w0 - slope * i, 0.0)
            with np.errstate(invalid="ignore"):
                beyond = on[:, k] & (sign * (tk - t[:, k]) > 0)
            beyond[b] = False
            if beyond.any():
                return True
        else:
            return True
        width = sign * (t[grow, k] - tk)
        if width <= 0.05 or (width < 0.5 and width >= previous):
            t[b, k] = t[grow, k]
            on[b, k] = True
            return True
        previous = width
        t[b, k] = tk
        on[b, k] = True
    return True
