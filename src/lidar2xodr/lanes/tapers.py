"""Entry and exit lanes: straight taper lines beside the edge, and lanes typed by how their width changes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar2xodr.config import LanesConfig
from lidar2xodr.data import LaneModel
from lidar2xodr.lanes.frame import Frame, _Points
from lidar2xodr.lanes.structure import _Structure
from lidar2xodr.lanes.tracks import _Fit

LANE_TYPES = ("driving", "entry", "exit")
_SLOPE_STEP = 0.005  # slope grid of the taper line search: 0.25 m over a 50 m window


@dataclass
class _Taper:
    """A lane between the carriageway's edge (row `outer`) and a straight line converging onto it.

    `t` is the line's offset at every station (NaN outside the lane's stations k0..k1, 0 width at the
    narrow end), `points` the marking points on it, `narrow_last` whether its width shrinks along s,
    `side` -1 for the right of the carriageway in s/t (+1 left), `first_width` its width at the wide
    end, where the line was first (last) seen.
    """

    row: int
    outer: int
    k0: int
    k1: int
    t: np.ndarray
    points: np.ndarray
    narrow_last: bool
    side: int
    first_width: float
    angle_deg: float


def _straight_lines(s: np.ndarray, w: np.ndarray, k: np.ndarray, step: float,
                    cfg: LanesConfig) -> list[tuple[float, float, float, float]]:
    """Seeds (a, b, s_lo, s_hi) of straight lines w = a + b s with a taper's slope in the points (s, w).

    Per window of 2 x `taper_min_length_m` (half overlapping): a Hough vote over a grid of slopes
    (`stable_lane_slope` to `taper_max_slope`, both signs) and intercept bands `taper_line_tolerance_m`
    wide (two grids half a band apart), where every station votes once per band (a blob or a line
    crossing the road at one station does not outvote a line along it). A window's best band is a
    seed when it holds points at a quarter of `taper_min_length_m` of stations or more.
    """
    tol = cfg.taper_line_tolerance_m
    half = np.arange(cfg.stable_lane_slope, cfg.taper_max_slope + 1e-9, _SLOPE_STEP)
    slopes = np.concatenate([-half[::-1], half])
    window = 2.0 * cfg.taper_min_length_m
    near = w <= cfg.max_lane_width_m + tol
    if not near.any():
        return []
    cell = np.unique(np.stack([k[near], np.floor(w[near] / 0.1).astype(np.int64)], axis=1), axis=0)
    kc, wc = cell[:, 0], (cell[:, 1] + 0.5) * 0.1
    sc = kc * step
    need = 0.25 * cfg.taper_min_length_m / step
    n_k = int(kc.max()) + 1
    seeds = []
    for lo in np.arange(sc.min(), sc.max() + 1e-9, 0.5 * window):
        m = slice(np.searchsorted(sc, lo, "left"), np.searchsorted(sc, lo + window, "left"))  # cells by station
        if len(np.unique(kc[m])) < need:
            continue
        mid = lo + 0.5 * window
        c = wc[m][None, :] - slopes[:, None] * (sc[m][None, :] - mid)
        best = (0, 0.0, 0.0)
        for shift in (0.0, 0.5):
            band = np.floor(c / tol + shift).astype(np.int64)
            b0 = int(band.min())
            n_band = int(band.max()) - b0 + 1
            code = np.arange(len(slopes))[:, None] * n_band + (band - b0)
            votes = np.bincount(np.unique(code * n_k + kc[m][None, :]) // n_k)
            j = int(np.argmax(votes))
            if votes[j] > best[0]:
                i_slope, i_band = divmod(j, n_band)
                best = (int(votes[j]), float(slopes[i_slope]), (i_band + b0 + 0.5 - shift) * tol)
        if best[0] >= need:
            seeds.append((best[2] - best[1] * mid, best[1], float(lo), float(lo + window)))
    return seeds


@dataclass
class _SortedByS:
    """The points beyond the edge in order of station (s, their offset w from the edge, station index
    k, which never decreases along s), with `order` their indices in the unsorted arrays. A straight
    line w = a + b s can only pass within `tol` of them over the s where it lies inside their range
    of w, one slice of this order."""

    order: np.ndarray
    s: np.ndarray
    w: np.ndarray
    k: np.ndarray
    w_range: tuple[float, float]

    @classmethod
    def of(cls, s: np.ndarray, w: np.ndarray, k: np.ndarray) -> _SortedByS:
        order = np.argsort(s, kind="stable")
        return cls(order, s[order], w[order], k[order], (float(w.min()), float(w.max())) if len(w) else (0.0, 0.0))

    def reach(self, line: tuple[float, float], tol: float) -> slice:
        """The slice that holds every point within `tol` of the line (1 m of s to spare)."""
        a, b = line
        if abs(b) < 1e-6 or len(self.s) == 0:
            return slice(0, len(self.s))
        s0, s1 = sorted(((self.w_range[0] - tol - a) / b, (self.w_range[1] + tol - a) / b))
        return slice(np.searchsorted(self.s, s0 - 1.0, "left"), np.searchsorted(self.s, s1 + 1.0, "right"))


def _line_run(pts: _SortedByS, line: tuple[float, float], seed: tuple[float, float], step: float,
              cfg: LanesConfig) -> np.ndarray:
    """Indices (ascending, into the unsorted arrays) of the points on the line (within
    `taper_line_tolerance_m`) in its stretch that overlaps the seed window most, stretches being split
    at gaps over `taper_max_gap_m` without points."""
    tol = cfg.taper_line_tolerance_m
    near = pts.reach(line, tol)
    on = near.start + np.flatnonzero(np.abs(pts.w[near] - (line[0] + line[1] * pts.s[near])) < tol)
    if len(on) == 0:
        return on
    k_on = pts.k[on]
    ks = k_on[np.r_[True, np.diff(k_on) != 0]]
    cut = np.flatnonzero(np.diff(ks) * step > cfg.taper_max_gap_m)
    firsts, lasts = ks[np.r_[0, cut + 1]], ks[np.r_[cut, len(ks) - 1]]
    stretch = np.zeros(len(ks), dtype=np.int64)
    stretch[cut + 1] = 1
    in_seed = (ks * step >= seed[0]) & (ks * step < seed[1])
    j = int(np.argmax(np.bincount(np.cumsum(stretch)[in_seed], minlength=len(firsts))))
    return np.sort(pts.order[on[(k_on >= firsts[j]) & (k_on <= lasts[j])]])


def _taper_lanes(pts: _Points, structure: _Structure, side: int, step: float,
                 cfg: LanesConfig) -> tuple[list[_Taper], list[str]]:
    """Entry and exit lanes on the `side` of the carriageway from straight lines converging onto its edge.

    A marking line that runs at a steady angle onto the outermost kept line (or away from it) bounds a
    lane that ends (begins) where the two meet: a taper. Such a line never has a stable lane beside it,
    so the lane structure drops it; here it is found again from the marking points lying more than
    `assign_distance_m` beyond the edge (`_straight_lines`, then refitted by least squares on the points
    of its stretch until that stretch stops changing) and kept only when all of these hold:
    - points lie on it at stations spanning `taper_min_length_m`, its width changes by
      `stable_lane_slope` to `taper_max_slope` per metre and the points' RMS distance to it is at most
      half `taper_line_tolerance_m` (one consistent angle: clutter, posts and blobs are not straight);
    - it is seen within `taper_meet_width_m` of the edge (its meeting point, where the width reaches
      zero, is extrapolated from there) and nowhere farther out than `max_lane_width_m` (a ramp's edge
      goes on diverging beyond a lane width; a guard rail never comes that close at an angle);
    - the edge it meets is one line over the whole lane and goes on as the outermost line for
      `min_section_length_m` beyond the meeting point (or to the end of the road): no lane lies
      outside it there (where a ramp's edge meets the road at a gore, the ramp's lane goes on outside);
    - the lane, from where its line is first (last) seen to the meeting point, is at least
      `min_section_length_m` long (a shorter one could not be a lane section; a note says so).
    Its points are all those within `taper_line_tolerance_m` of the line on the lane's stations, the line
    taken both as a width from the edge and as a straight line in the frame's own offsets (an edge bent
    towards it, or a frame bent by such an edge, does not hide its points), also those close to the edge
    near the meeting point and up to `taper_meet_width_m` / slope beyond it (an edge bent by them puts
    the meeting point too far out): they are kept out of the edge's fit, which they would bend towards
    the line.
    The lane starts where its line is first seen (ends where last seen), at the width measured there:
    nothing tells what the unseen road before it holds. Its border is the fitted straight line, so the
    width falls linearly to exactly zero at the meeting station. Overlapping lanes: the one with points
    at most stations wins. Returns the tapers (rows not yet assigned) and notes.
    """
    on, t = structure.on, structure.t
    n_rows, m = structure.n, on.shape[1]
    valid = on.sum(axis=0) >= 2
    outer_at = np.argmax(np.where(on, side * np.where(on, t, 0.0), -np.inf), axis=0) if len(on) else np.zeros(
        m, dtype=np.int64)
    edge = t[outer_at, np.arange(m)] if len(on) else np.full(m, np.nan)
    outer_row = np.where(on.any(axis=0), structure.rows[outer_at], 0) if len(on) else outer_at
    k_all = pts.k
    use = pts.inside & valid[k_all]
    w_all = side * (pts.t - np.where(use, edge[k_all], 0.0))
    sel = np.flatnonzero(use & (w_all > cfg.assign_distance_m) & (w_all < 2.0 * cfg.max_lane_width_m))
    if len(sel) < 10:
        return [], []
    s, w, k = pts.s[sel], w_all[sel], k_all[sel]
    tol = cfg.taper_line_tolerance_m
    found: list[tuple[int, _Taper]] = []
    notes: list[str] = []
    seen_lines: set[tuple[int, int]] = set()
    by_k: np.ndarray | None = None
    k_sorted = k_all
    by_s = _SortedByS.of(s, w, k)
    for a, b, lo, hi in _straight_lines(s, w, k, step, cfg):
        run = _line_run(by_s, (a, b), (lo, hi), step, cfg)
        for _ in range(20):
            if len(run) < 3:
                break
            slope, icpt = np.polyfit(s[run], w[run], 1)
            again = _line_run(by_s, (float(icpt), float(slope)), (lo, hi), step, cfg)
            if np.array_equal(again, run):
                break
            run = again
        if len(run) < 3:
            continue
        slope, icpt = np.polyfit(s[run], w[run], 1)
        line = (float(icpt), float(slope))
        ks = np.unique(k[run])
        if (int(ks[0]), int(ks[-1])) in seen_lines:
            continue
        seen_lines.add((int(ks[0]), int(ks[-1])))
        a, b = line
        rms = float(np.sqrt(np.mean((w[run] - (a + b * s[run])) ** 2)))
        if (len(ks) * step < cfg.taper_min_length_m or not cfg.stable_lane_slope <= abs(b) <= cfg.taper_max_slope
                or rms > 0.5 * tol or float(w[run].max()) > cfg.max_lane_width_m + tol):
            continue
        narrow_last = b < 0
        k_near, k_far = (int(ks[-1]), int(ks[0])) if narrow_last else (int(ks[0]), int(ks[-1]))
        if a + b * k_near * step > cfg.taper_meet_width_m:
            continue
        k_meet = int(round(-a / b / step))
        if not 0 <= k_meet < m or not valid[k_meet]:
            continue
        k0, k1 = (k_far, k_meet) if narrow_last else (k_meet, k_far)
        rows = np.unique(outer_row[k0 : k1 + 1])
        if len(rows) != 1 or not valid[k0 : k1 + 1].all():
            continue
        clear = int(round(cfg.min_section_length_m / step))
        beyond = np.arange(k_meet + 1, k_meet + clear + 1) if narrow_last else np.arange(k_meet - clear, k_meet)
        beyond = beyond[(beyond >= 0) & (beyond < m)]
        beyond = beyond[valid[beyond]]
        if np.any(outer_row[beyond] != rows[0]):
            continue
        if (k1 - k0 + 1) * step < cfg.min_section_length_m:
            s_at = float(np.flatnonzero(valid)[0]) * step
            notes.append(f"a line converging onto the carriageway's edge on s {k0 * step - s_at:.0f}-"
                         f"{k1 * step - s_at:.0f} m makes no lane: shorter than {cfg.min_section_length_m:g} m")
            continue
        kk = np.arange(k0, k1 + 1)
        width = np.clip(a + b * kk * step, 0.0, None)
        width[kk == k_meet] = 0.0
        row_t = np.full(m, np.nan)
        row_t[kk] = edge[kk] + side * width
        in_frame = np.polyfit(s[run], pts.t[sel[run]], 1)
        ext = int(round(cfg.taper_meet_width_m / abs(b) / step))
        lo_k, hi_k = (k0, k1 + ext) if narrow_last else (k0 - ext, k1)
        if by_k is None:
            by_k = np.argsort(k_all, kind="stable")
            k_sorted = k_all[by_k]
        idx = by_k[np.searchsorted(k_sorted, lo_k, "left") : np.searchsorted(k_sorted, hi_k, "right")]
        line_w = a + b * pts.s[idx]
        on_line = (np.abs(pts.t[idx] - np.polyval(in_frame, pts.s[idx])) < tol) | (
            use[idx] & (line_w > tol) & (np.abs(w_all[idx] - line_w) < tol))
        near = np.sort(idx[pts.inside[idx] & on_line])
        taper = _Taper(-1, int(rows[0]), k0, k1, row_t, near, narrow_last, side,
                       float(a + b * k_far * step), float(np.degrees(np.arctan(abs(b)))))
        found.append((len(ks), taper))
    kept: list[_Taper] = []
    for _, taper in sorted(found, key=lambda x: (-x[0], x[1].k0)):
        if all(taper.k1 < other.k0 or taper.k0 > other.k1 for other in kept):
            kept.append(taper)
    for i, taper in enumerate(sorted(kept, key=lambda x: x.k0)):
        taper.row = n_rows + i
    return sorted(kept, key=lambda x: x.k0), notes


def _add_tapers(fit: _Fit, structure: _Structure, label: np.ndarray, tapers: list[_Taper]) -> None:
    """Append each taper's line as a measured, kept boundary row and give it its points."""
    for taper in tapers:
        fit.t = np.vstack([fit.t, taper.t[None, :]])
        fit.support = np.append(fit.support, float(len(taper.points)))
        fit.rows = np.append(fit.rows, taper.row)
        structure.on = np.vstack([structure.on, np.isfinite(taper.t)[None, :]])
        structure.t = np.vstack([structure.t, taper.t[None, :]])
        structure.rows = np.append(structure.rows, taper.row)
        structure.n = len(fit.support)
        label[taper.points] = taper.row


def _travel_sign(frame: Frame, ego: np.ndarray | None, reach_m: float) -> int:
    """+1 when the ego first travels along s on the frame (the kept carriageway is the one it drove
    first), -1 against; +1 without a trajectory.

    The stage turns a frame the ego first drives against, so s runs the way the drive went (the
    paper's "away from the world origin" with the origin at the highway entry, i.e. the drive's
    start): a one-way carriageway's lanes are right lanes along s. The frame's own orientation comes
    from the markings and the local frame's origin, which can lie anywhere (a roadgen corridor
    driven towards its origin was built as the opposite direction's road: 16 m boundaries RMSE).
    Only where the ego drives on the frame counts: within `reach_m` of it (`max_normal_length_m`, the
    normals' reach: a road wider than that is two roads) and along it (its station changes by at least
    half the distance it moves). Elsewhere a point's foot can still lie
    inside the frame: on Town04 the ego drove a street 100 m beside a curve's axis first, against
    the curve's direction, and the curve was built as the opposite carriageway (14.7 m).
    """
    if ego is None or len(ego) < 2:
        return 1
    s, t, inside = frame.project(ego)
    ds = np.gradient(s)
    moved = np.linalg.norm(np.gradient(ego, axis=0), axis=1)
    on = inside & (np.abs(t) <= reach_m) & (np.abs(ds) >= 0.5 * moved)
    moving = np.flatnonzero(on & (np.abs(ds) > 1e-3))
    return 1 if len(moving) == 0 or ds[moving[0]] > 0 else -1


def _type_tapers(model: LaneModel, tapers: list[_Taper], new_id: np.ndarray, travel: int) -> None:
    """Lane types of the taper lanes in the model's sections, and a warning per lane built.

    Right-hand traffic: the lane travels like the ego (`travel`: +1 along s); one whose width shrinks
    to zero in its travel direction is an entry (acceleration) lane, one that grows from zero an exit
    (deceleration) lane.
    """
    for taper in tapers:
        bid = int(new_id[taper.row])
        kind = "entry" if taper.narrow_last == (travel > 0) else "exit"
        secs = []
        for sec in model.sections:
            ids = sec.boundary_ids
            end = ids[0] if taper.side > 0 else ids[-1]
            if end != bid:
                continue
            lane = 0 if taper.side > 0 else len(ids) - 2
            sec.lane_types = list(sec.lane_types or ["driving"] * (len(ids) - 1))
            sec.lane_types[lane] = kind
            secs.append(sec)
        side = "right" if taper.side * travel < 0 else "left"
        if not secs:
            model.warnings.append(f"an {kind} lane on the {side} (boundary {bid}) was left out of the lane sections")
            continue
        outer = [i for i in secs[0].boundary_ids if i != bid][-1 if taper.side < 0 else 0]
        s0, s1 = secs[0].s_start, secs[-1].s_end
        verb = "closes onto" if kind == "entry" else "opens from"
        seen = "first" if kind == "entry" else "last"
        model.warnings.append(
            f"{kind} lane on the {side} on s {s0:.0f}-{s1:.0f} m: a taper, its outer line (boundary {bid}) "
            f"{verb} boundary {outer} at {taper.angle_deg:.1f} deg ({taper.first_width:.1f} m wide where "
            f"{seen} seen)"
        )


def _lane_between(ids: list[int], a: int, b: int) -> bool:
    """Whether boundaries a and b are neighbours in a section's ordered boundary ids (a lane between them)."""
    return a in ids and b in ids and abs(ids.index(a) - ids.index(b)) == 1


def _type_by_width(model: LaneModel, travel: int, cfg: LanesConfig) -> None:
    """An outermost lane that opens from zero width where its section begins and is still at full
    width where its section ends is an exit lane (an entry lane mirrored): its measured taper is its
    narrow end, and it leaves the road at its wide end (a ramp's lane) rather than closing. Typed
    like `_type_tapers`' lanes, so it keeps its width there instead of a taper being invented.

    At the narrow end the lane must be new, whichever of its lines is (the section beside holds no
    lane between them: the inner line may begin at the taper's narrow end, `_open_beside_edge`); at
    the wide end its outer line must end there (a lane at full width beside an outer line that goes
    on is a ramp's merge or diverge for the junction builder). A lane still widening at its end by
    `branch_widening_m` is left to the junction builder (branches.find_events)."""
    by_id = {b.id: b for b in model.boundaries}
    secs = model.sections
    for j, sec in enumerate(secs):
        ids = sec.boundary_ids
        n = len(ids) - 1
        if n < 2:
            continue
        ks = np.flatnonzero((model.s >= sec.s_start - 1e-9) & (model.s <= sec.s_end + 1e-9))
        if len(ks) < 10:
            continue
        for lane in (0, n - 1):
            if lane == 0 and sec.divider_id is not None:
                continue
            if sec.lane_types is not None and sec.lane_types[lane] != "driving":
                continue
            w = by_id[ids[lane]].t[ks] - by_id[ids[lane + 1]].t[ks]
            w = w[np.isfinite(w)]
            if len(w) < 10:
                continue
            med = float(np.median(w))
            if med < cfg.min_lane_width_m:
                continue
            pair, outer = (ids[lane], ids[lane + 1]), ids[0 if lane == 0 else -1]
            lane_before = j > 0 and _lane_between(secs[j - 1].boundary_ids, *pair)
            lane_after = j < len(secs) - 1 and _lane_between(secs[j + 1].boundary_ids, *pair)
            outer_before = j > 0 and outer in secs[j - 1].boundary_ids
            outer_after = j < len(secs) - 1 and outer in secs[j + 1].boundary_ids
            head, tail = float(np.mean(w[:3])), float(np.mean(w[-3:]))
            opens = not lane_before and head < 0.5 * med and tail >= 0.8 * med
            closes = not lane_after and tail < 0.5 * med and head >= 0.8 * med
            if opens and not outer_after and j < len(secs) - 1 and tail <= med + cfg.branch_widening_m:
                narrow_last = False
            elif closes and not outer_before and j > 0:
                narrow_last = True
            else:
                continue
            types = list(sec.lane_types or ["driving"] * n)
            types[lane] = "entry" if narrow_last == (travel > 0) else "exit"
            sec.lane_types = types
