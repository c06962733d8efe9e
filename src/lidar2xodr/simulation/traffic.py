"""Traffic and the ego as agents on the route: car following, lane changes, overtakes and cut-ins.

Every agent lives in route coordinates (u along the route, lambda to its left). The ego is agent 0
and obeys the same rules, so it never drives through anyone.

Decisions:
- Longitudinal: the Intelligent Driver Model (IDM) with per-class parameters; desired speed is
  capped by the route's curve speed (lateral acceleration 1.8 m/s^2).
- Ego speed: an Ornstein-Uhlenbeck process (sigma 12 km/h at 110 km/h, 60 s correlation) around
  --speed-kmh, kept within mean +- 30 km/h (and +-40 % of it), slowed by traffic, curves and
  U-turns, so the realised mean is a little below --speed-kmh. Traffic desired speeds (per class,
  motorway values below) scale with --speed-kmh / 110, so a 50 km/h drive gets city traffic.
- Lane changes last 4-6 s (quintic lateral profile; cut-ins 3-4 s). Traffic overtakes on the left
  (right-hand traffic; mirrored for LHT maps) when its leader is slower, returns to the right lane
  when it is free, and leaves lanes that end within 300 m. About one in five drivers is aggressive
  and cuts in front of the ego with gaps down to 8 m. The ego changes lanes on its own roughly
  once a minute, overtakes slow leaders, starts in the rightmost lane and moves there before a
  U-turn.
- Density (vehicles per km and lane, same direction): low 4, mid 10, high 20; oncoming traffic
  (on two-way roads) half of that. Vehicles live in a window from 350 m behind to 900 m ahead of
  the ego (so they appear and vanish out of sensor range) within the ego's current pass.
- Classes: car 70 %, van 12 %, truck 15 %, motorcycle 3 %; trucks keep to the rightmost lane (the two
  rightmost on roads with three lanes or more) and never overtake.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lidar2xodr.simulation.route import Route

DT = 0.05
DENSITY = {"none": 0.0, "low": 4.0, "mid": 10.0, "high": 20.0}
WINDOW_BEHIND = 350.0
WINDOW_AHEAD = 900.0


@dataclass(frozen=True)
class VehicleClass:
    name: str
    share: float
    length: tuple[float, float]
    width: tuple[float, float]
    height: tuple[float, float]
    clearance: float
    speed_kmh: tuple[float, float]  # mean, sigma of the desired speed
    a_max: float
    headway: float


CLASSES = (
    VehicleClass("car", 0.70, (4.2, 4.95), (1.78, 1.95), (1.40, 1.60), 0.15, (125.0, 15.0), 1.4, 1.3),
    VehicleClass("van", 0.12, (4.9, 6.0), (1.95, 2.1), (1.9, 2.7), 0.2, (110.0, 10.0), 1.0, 1.5),
    VehicleClass("truck", 0.15, (12.0, 16.5), (2.5, 2.55), (3.6, 4.0), 0.5, (86.0, 3.0), 0.5, 1.8),
    VehicleClass("motorcycle", 0.03, (2.0, 2.3), (0.75, 0.9), (1.3, 1.5), 0.1, (130.0, 15.0), 2.0, 1.2),
)


@dataclass
class Agents:
    """Agent states on the DT grid: the ego densely, traffic as records of the agents present at each step.

    Records of step k are rows start[k]:start[k+1] of agent, u, lam, dlam and v. Agent ids index the
    per-agent arrays; id 0 is the ego.
    """

    times: np.ndarray  # (T,) seconds from the drive start
    ego_u: np.ndarray  # (T,)
    ego_lam: np.ndarray  # (T,)
    ego_v: np.ndarray  # (T,)
    start: np.ndarray  # (T + 1,)
    agent: np.ndarray  # (M,) int
    u: np.ndarray  # (M,)
    lam: np.ndarray  # (M,)
    dlam: np.ndarray  # (M,) lateral speed d(lambda)/dt
    v: np.ndarray  # (M,) speed along the route (positive for oncoming too)
    heading_sign: np.ndarray  # (A,) +1 travels with the route, -1 oncoming
    cls: list[str]
    size: np.ndarray  # (A, 3) length, width, height
    clearance: np.ndarray  # (A,)
    rho: np.ndarray  # (A,) body reflectivity
    lane_changes: list[dict] = field(default_factory=list)  # the ego's


class _Pool:
    """Growable per-agent arrays."""

    def __init__(self) -> None:
        self.n = 0
        cap = 64
        self.u = np.full(cap, np.nan)
        self.lam = np.full(cap, np.nan)
        self.v = np.zeros(cap)
        self.v0 = np.zeros(cap)
        self.active = np.zeros(cap, dtype=bool)
        self.sign = np.ones(cap, dtype=np.int64)
        self.track = np.full(cap, -1, dtype=np.int64)
        self.lc_t0 = np.full(cap, -1e9)
        self.lc_dur = np.ones(cap)
        self.lc_off = np.zeros(cap)
        self.length = np.zeros(cap)
        self.width = np.zeros(cap)
        self.height = np.zeros(cap)
        self.clear = np.zeros(cap)
        self.a_max = np.ones(cap)
        self.headway = np.ones(cap)
        self.rho = np.zeros(cap)
        self.aggressive = np.zeros(cap, dtype=bool)
        self.wander_a = np.zeros(cap)
        self.wander_w = np.zeros(cap)
        self.wander_p = np.zeros(cap)
        self.cls: list[str] = []
        self._fill = {name: arr[0] for name, arr in vars(self).items() if isinstance(arr, np.ndarray)}

    def add(self) -> int:
        if self.n == len(self.u):
            for name, arr in list(vars(self).items()):
                if isinstance(arr, np.ndarray):
                    setattr(self, name, np.concatenate([arr, np.full(len(arr), self._fill[name], dtype=arr.dtype)]))
        self.n += 1
        return self.n - 1


class TrafficSim:
    """Runs ego and traffic until the ego has driven `length_m` along the route."""

    def __init__(self, route: Route, traffic: str, speed_kmh: float, rng: np.random.Generator) -> None:
        self.route = route
        self.rng = rng
        self.density = DENSITY[traffic] / 1000.0
        self.mean_v = speed_kmh / 3.6
        self.speed_scale = speed_kmh / 110.0  # traffic speeds are motorway speeds scaled like the ego's
        self.v_lo = max(self.mean_v - 30 / 3.6, 0.6 * self.mean_v)
        self.v_hi = min(self.mean_v + 30 / 3.6, 1.4 * self.mean_v)
        self.keep = -1 if route.odr.roads[route.nodes[0][0]].rule.upper() != "LHT" else 1
        self.p = _Pool()
        seg = np.cumsum([leg.kind == "turn" for leg in route.legs])
        self.segment = seg[route.leg_index]  # pass number of each sample (turns start a new one)
        self.on_turn = np.array([route.legs[k].kind == "turn" for k in route.leg_index])
        turn_u = [leg.u0 for leg in route.legs if leg.kind == "turn"]
        self.turn_u0 = np.array(turn_u + [np.inf])
        self.lane_changes: list[dict] = []

    # ------------------------------------------------------------------ spawning

    def _new_vehicle(self, cls: VehicleClass, v0: float, u: float, lam: float, track: int, sign: int) -> int:
        p, rng = self.p, self.rng
        i = p.add()
        p.cls.append(cls.name)
        p.u[i], p.lam[i], p.track[i], p.sign[i] = u, lam, track, sign
        p.length[i] = rng.uniform(*cls.length)
        p.width[i] = rng.uniform(*cls.width)
        p.height[i] = rng.uniform(*cls.height)
        p.clear[i] = cls.clearance
        p.a_max[i] = cls.a_max * rng.uniform(0.8, 1.2)
        p.headway[i] = cls.headway * rng.uniform(0.8, 1.3)
        p.v0[i] = v0
        p.v[i] = min(v0, self.route.v_limit[self.route.index(u)])
        p.rho[i] = rng.uniform(0.05, 0.7)
        p.aggressive[i] = rng.random() < 0.2 and cls.name != "truck"
        p.wander_a[i] = rng.uniform(0.03, 0.15)
        p.wander_w[i] = 2 * np.pi / rng.uniform(15.0, 40.0)
        p.wander_p[i] = rng.uniform(0, 2 * np.pi)
        p.active[i] = True
        return i

    def _spawn_ego(self) -> None:
        r, p = self.route, self.p
        i = p.add()
        p.cls.append("ego")
        lanes = r.same
        k = self._keep_slot(lanes.lam[0])
        if k < 0:
            raise RuntimeError("route starts without a driving lane")
        p.u[i], p.lam[i], p.track[i], p.sign[i] = 0.0, lanes.lam[0, k], lanes.track[0, k], 1
        p.length[i], p.width[i], p.height[i], p.clear[i] = 4.8, 1.9, 1.5, 0.15
        p.a_max[i], p.headway[i], p.v0[i] = 1.2, 1.4, self.mean_v
        p.v[i] = min(self.mean_v, r.v_limit[0])
        p.active[i] = True

    def _keep_slot(self, row: np.ndarray) -> int:
        ok = np.flatnonzero(~np.isnan(row))
        if len(ok) == 0:
            return -1
        return int(ok[0] if self.keep < 0 else ok[-1])

    def _fill(self, ego_u: float, sign: int, lo: float, hi: float, initial: bool) -> None:
        """Bring the vehicle count in [lo, hi] up to the density, spawning at the window edges."""
        r, p, rng = self.route, self.p, self.rng
        lanes = r.same if sign > 0 else r.oncoming
        dens = self.density * (1.0 if sign > 0 else 0.5)
        if dens <= 0:
            return
        probe = np.linspace(lo, hi, 12)
        idx = r.index(probe)
        n_lanes = np.mean((~np.isnan(lanes.lam[idx])).sum(axis=1))
        want = dens * n_lanes * (hi - lo)
        have = int((p.active[: p.n] & (p.sign[: p.n] == sign)).sum()) - (1 if sign > 0 else 0)
        tries = int(max(0, want - have)) if initial else min(2, int(max(0, round(want - have))))
        ego_seg = self.segment[r.index(ego_u)]
        for _ in range(tries):
            cls = CLASSES[int(rng.choice(len(CLASSES), p=[c.share for c in CLASSES]))]
            v0 = max(3.0, rng.normal(*cls.speed_kmh) / 3.6 * self.speed_scale)
            if initial:
                u = rng.uniform(lo, hi)
            elif sign > 0:
                # drivers slower than the ego appear ahead of it, faster ones behind, so the ego meets them
                u = hi - rng.uniform(0, 60) if v0 < p.v0[0] else lo + rng.uniform(0, 60)
            else:
                u = hi - rng.uniform(0, 60)
            i = int(r.index(u))
            if self.segment[i] != ego_seg or self.on_turn[i]:
                continue
            row = lanes.lam[i]
            slots = np.flatnonzero(~np.isnan(row) & (2 * lanes.half[i] >= 2.6))
            if cls.name == "truck" and sign > 0:
                n_keep = 1 if len(slots) <= 2 else 2
                slots = slots[:n_keep] if self.keep < 0 else slots[-n_keep:]
            if len(slots) == 0:
                continue
            k = int(rng.choice(slots))
            if self._occupied(u, row[k], sign, 35.0 if initial else 60.0):
                continue
            self._new_vehicle(cls, v0, u, row[k], int(lanes.track[i, k]), sign)

    def _occupied(self, u: float, lam: float, sign: int, gap: float) -> bool:
        p = self.p
        a = p.active[: p.n] & (p.sign[: p.n] == sign)
        near = np.abs(p.u[: p.n] - u) < gap + 0.5 * p.length[: p.n]
        return bool((a & near & (np.abs(p.lam[: p.n] - lam) < 2.0)).any())

    # ------------------------------------------------------------------ the loop

    def run(self, length_m: float) -> Agents:
        r, p, rng = self.route, self.p, self.rng
        self._spawn_ego()
        end_u = min(length_m, r.length - 0.5)
        self._fill(0.0, 1, max(0.0, -WINDOW_BEHIND), min(r.length, WINDOW_AHEAD), True)
        self._fill(0.0, -1, 0.0, min(r.length, WINDOW_AHEAD), True)
        rec_agent: list[np.ndarray] = []
        rec_u: list[np.ndarray] = []
        rec_lam: list[np.ndarray] = []
        rec_dlam: list[np.ndarray] = []
        rec_v: list[np.ndarray] = []
        ego: list[tuple[float, float, float]] = []
        prev_lam = p.lam.copy()
        ou = 0.0
        t = 0.0
        step = 0
        was_turn = False
        max_steps = int(length_m / 2.0 / DT) + 10_000
        while True:
            n = p.n
            a = np.flatnonzero(p.active[1:n]) + 1
            rec_agent.append(a)
            rec_u.append(p.u[a])
            rec_lam.append(p.lam[a])
            known = a < len(prev_lam)
            d = np.zeros(len(a))
            d[known] = (p.lam[a[known]] - prev_lam[a[known]]) / DT
            rec_dlam.append(np.nan_to_num(d))
            rec_v.append(p.v[a])
            prev_lam = p.lam.copy()
            ego.append((p.u[0], p.lam[0], p.v[0]))
            if p.u[0] >= end_u or step >= max_steps:
                break
            ou += -ou * DT / 60.0 + (12.0 / 3.6) * math.sqrt(2 * DT / 60.0) * rng.standard_normal()
            p.v0[0] = float(np.clip(self.mean_v + ou * self.speed_scale, self.v_lo, self.v_hi))
            ego_i = int(r.index(p.u[0]))
            on_turn = bool(self.on_turn[ego_i])
            if on_turn and not was_turn:
                self._enter_turn(ego_i)
            self._lanes(t, on_turn, was_turn)
            was_turn = on_turn
            if step % 10 == 0:
                self._decide(t, step)
            self._longitudinal()
            t += DT
            step += 1
            self._lateral(t)
            self._despawn()
            if step % 20 == 0 and not on_turn:
                self._fill(p.u[0], 1, p.u[0] - WINDOW_BEHIND, p.u[0] + WINDOW_AHEAD, False)
                self._fill(p.u[0], -1, p.u[0] + 0.6 * WINDOW_AHEAD, p.u[0] + WINDOW_AHEAD, False)
        A = p.n
        e = np.array(ego)
        counts = np.array([len(a) for a in rec_agent])
        return Agents(
            times=np.arange(len(e)) * DT, ego_u=e[:, 0], ego_lam=e[:, 1], ego_v=e[:, 2],
            start=np.concatenate([[0], np.cumsum(counts)]), agent=np.concatenate(rec_agent),
            u=np.concatenate(rec_u), lam=np.concatenate(rec_lam), dlam=np.concatenate(rec_dlam),
            v=np.concatenate(rec_v), heading_sign=p.sign[:A].copy(), cls=list(p.cls),
            size=np.column_stack([p.length[:A], p.width[:A], p.height[:A]]), clearance=p.clear[:A].copy(),
            rho=p.rho[:A].copy(), lane_changes=self.lane_changes,
        )

    def _enter_turn(self, ego_i: int) -> None:
        r, p = self.route, self.p
        leg = r.legs[int(r.leg_index[ego_i])]
        assert leg.turn is not None
        prev = r.legs[int(r.leg_index[ego_i]) - 1]
        road = r.odr.roads[prev.road]
        start = leg.turn.origin
        s_turn = leg.s0
        x, y, h = (a[0] for a in road.reference(s_turn))
        lam_r = float(np.dot(start[:2] - (x, y), (-math.sin(h) * prev.direction, math.cos(h) * prev.direction))
                      + prev.c)
        leg.turn.residual = float(p.lam[0] - lam_r)

    def _lanes(self, t: float, ego_on_turn: bool, ego_was_turn: bool) -> None:
        """Keep every agent on its lane track; handle ended tracks as forced lane changes."""
        r, p = self.route, self.p
        n = p.n
        act = np.flatnonzero(p.active[:n])
        if ego_on_turn:
            act = act[act != 0]
        idx = r.index(p.u[act])
        for sign, lanes in ((1, r.same), (-1, r.oncoming)):
            sel = p.sign[act] == sign
            a, i = act[sel], idx[sel]
            if len(a) == 0:
                continue
            if sign < 0:
                d = np.abs(lanes.lam[i] - p.lam[a, None])
                d[np.isnan(d)] = np.inf
                k = np.argmin(d, axis=1)
                gone = ~np.isfinite(d[np.arange(len(a)), k])
                p.active[a[gone]] = False
                continue
            match = lanes.track[i] == p.track[a, None]
            lost = ~match.any(axis=1)
            for j in np.flatnonzero(lost):
                ag, row = a[j], i[j]
                if ag == 0 and ego_was_turn:
                    k = self._keep_slot(lanes.lam[row])
                    if k >= 0:
                        p.track[0], p.lam[0], p.lc_t0[0] = lanes.track[row, k], lanes.lam[row, k], -1e9
                    continue
                d = np.abs(lanes.lam[row] - p.lam[ag])
                d[np.isnan(d)] = np.inf
                k = int(np.argmin(d))
                if not np.isfinite(d[k]):
                    if ag != 0:
                        p.active[ag] = False
                    continue
                self._start_change(ag, row, k, t, 4.0)

    def _start_change(self, ag: int, row: int, k: int, t: float, dur: float) -> None:
        p, lanes = self.p, self.route.same
        new_lam = lanes.lam[row, k]
        p.lc_off[ag] = p.lam[ag] - new_lam
        p.lc_t0[ag] = t
        p.lc_dur[ag] = dur
        old = p.track[ag]
        p.track[ag] = lanes.track[row, k]
        if ag == 0 and abs(p.lc_off[ag]) > 1.0:
            road, lane_from = self.route.lane_at(p.u[0], p.lam[0])
            self.lane_changes.append({
                "t_start": round(t, 3), "t_end": round(t + dur, 3), "road": road, "from_lane": lane_from,
                "to_lane": int(lanes.lane_id[row, k]), "from_track": int(old), "to_track": int(p.track[ag]),
            })

    def _neighbours(self, sign: int) -> tuple[np.ndarray, np.ndarray]:
        """Gap to and speed of the nearest vehicle ahead overlapping each agent laterally."""
        p = self.p
        n = p.n
        act = p.active[:n] & (p.sign[:n] == sign)
        gap = np.full(n, np.inf)
        vl = np.full(n, np.inf)
        ids = np.flatnonzero(act)
        if len(ids) < 2:
            return gap, vl
        du = (p.u[ids][None, :] - p.u[ids][:, None]) * sign
        dl = np.abs(p.lam[ids][None, :] - p.lam[ids][:, None])
        g = du - 0.5 * (p.length[ids][None, :] + p.length[ids][:, None])
        ahead = (du > 0) & (dl < 0.5 * (p.width[ids][None, :] + p.width[ids][:, None]) + 0.3)
        g = np.where(ahead, g, np.inf)
        j = np.argmin(g, axis=1)
        gap[ids] = g[np.arange(len(ids)), j]
        vl[ids] = np.where(np.isfinite(gap[ids]), p.v[ids][j], np.inf)
        return gap, vl

    def _longitudinal(self) -> None:
        r, p = self.route, self.p
        n = p.n
        for sign in (1, -1):
            gap, vl = self._neighbours(sign)
            a = np.flatnonzero(p.active[:n] & (p.sign[:n] == sign))
            if len(a) == 0:
                continue
            v = p.v[a]
            v0 = np.minimum(p.v0[a], r.v_limit[r.index(p.u[a])]) if sign > 0 else p.v0[a]
            s_star = 3.0 + v * p.headway[a] + v * (v - vl[a]) / (2 * np.sqrt(p.a_max[a] * 2.0))
            s_star = np.where(np.isfinite(vl[a]), np.maximum(s_star, 3.0), 0.0)
            s = np.maximum(gap[a], 0.5)
            acc = p.a_max[a] * (1 - (v / np.maximum(v0, 0.5)) ** 4 - (s_star / s) ** 2)
            acc = np.clip(acc, -8.0, p.a_max[a])
            v_new = np.maximum(v + acc * DT, 0.0)
            p.u[a] += sign * 0.5 * (v + v_new) * DT
            p.v[a] = v_new

    def _lateral(self, t: float) -> None:
        r, p = self.route, self.p
        n = p.n
        a = np.flatnonzero(p.active[:n] & (p.sign[:n] > 0))
        if self.on_turn[r.index(p.u[0])]:
            a = a[a != 0]
        if len(a) == 0:
            return
        i = r.index(p.u[a])
        match = r.same.track[i] == p.track[a, None]
        ok = match.any(axis=1)
        k = np.argmax(match, axis=1)
        centre = r.same.lam[i, k]
        x = (t - p.lc_t0[a]) / p.lc_dur[a]
        q = np.clip(x, 0, 1)
        q = q * q * q * (10 + q * (-15 + 6 * q))
        wander = p.wander_a[a] * np.sin(p.wander_w[a] * t + p.wander_p[a])
        lam = centre + p.lc_off[a] * (1 - q) + wander
        p.lam[a] = np.where(ok, lam, p.lam[a])

    def _despawn(self) -> None:
        r, p = self.route, self.p
        n = p.n
        act = np.flatnonzero(p.active[:n])
        act = act[act != 0]
        if len(act) == 0:
            return
        u = p.u[act]
        ego_u = p.u[0]
        i = r.index(u)
        out = (u < ego_u - WINDOW_BEHIND - 100) | (u > ego_u + WINDOW_AHEAD + 100) | (u <= 0) | (u >= r.length - 1)
        out |= self.on_turn[i] | (self.segment[i] != self.segment[r.index(ego_u)])
        p.active[act[out]] = False

    # ------------------------------------------------------------------ decisions

    def _decide(self, t: float, step: int) -> None:
        r, p, rng = self.route, self.p, self.rng
        n = p.n
        gap, vl = self._neighbours(1)
        for ag in np.flatnonzero(p.active[:n] & (p.sign[:n] > 0)):
            if t - p.lc_t0[ag] < p.lc_dur[ag] + 2.0:
                continue
            row = int(r.index(p.u[ag]))
            if self.on_turn[row]:
                continue
            lanes = r.same
            match = np.flatnonzero(lanes.track[row] == p.track[ag])
            if len(match) == 0:
                continue
            k = int(match[0])
            valid = ~np.isnan(lanes.lam[row]) & (2 * lanes.half[row] >= 2.6)
            right, left = k + self.keep, k - self.keep
            can = {d: 0 <= d < len(valid) and bool(valid[d]) for d in (right, left)}
            ego = ag == 0
            target = None
            dur = rng.uniform(4.0, 6.0)
            if ego and self.turn_u0[np.searchsorted(self.turn_u0, p.u[0])] - p.u[0] < 700:
                keep_k = self._keep_slot(np.where(valid, lanes.lam[row], np.nan))
                if keep_k >= 0 and keep_k != k:
                    target = right if can[right] else None
            elif lanes.remaining[row, k] < 300:
                options = [d for d in (right, left) if can[d] and lanes.remaining[row, d] > lanes.remaining[row, k]]
                target = options[0] if options else None
            else:
                slow = gap[ag] < 70 and vl[ag] < p.v0[ag] - 2.5
                back_gap, back_v = self._follower(ag)
                pressed = back_gap < 50 and back_v > p.v[ag] + 1.0
                right_free = can[right] and self._lane_leader_speed(ag, row, right) >= p.v[ag] - 1.0
                if slow and can[left] and p.cls[ag] != "truck":
                    target = left
                elif can[right] and not slow and (pressed or right_free) and rng.random() < (0.3 if ego else 0.5):
                    target = right  # keep right: yield to faster traffic, return after overtaking
                elif ego and rng.random() < 0.01:
                    opts = [d for d in (right, left) if can[d]]
                    target = opts[int(rng.integers(len(opts)))] if opts else None
                elif not ego and p.aggressive[ag] and rng.random() < 0.15:
                    ek = np.flatnonzero(lanes.track[row] == p.track[0])
                    du = p.u[ag] - p.u[0]
                    if len(ek) and abs(int(ek[0]) - k) == 1 and 5 < du < 45 and not self.on_turn[r.index(p.u[0])]:
                        target, dur = int(ek[0]), rng.uniform(3.0, 4.0)
            if target is None or not self._gap_ok(ag, row, target):
                continue
            self._start_change(ag, row, target, t, dur)

    def _gap_ok(self, ag: int, row: int, k: int) -> bool:
        """Enough room in lane slot k: ahead and behind, by speed difference; aggressive drivers accept less."""
        p, lanes = self.p, self.route.same
        lam_t, half = lanes.lam[row, k], lanes.half[row, k]
        n = p.n
        others = np.flatnonzero(p.active[:n] & (p.sign[:n] > 0))
        others = others[others != ag]
        inlane = np.abs(p.lam[others] - lam_t) < half + 0.5 * p.width[others]
        o = others[inlane]
        du = p.u[o] - p.u[ag]
        g = np.abs(du) - 0.5 * (p.length[o] + p.length[ag])
        aggressive = p.aggressive[ag]
        front = du > 0
        need_front = np.where(front, 8.0 if aggressive else 15.0 + 1.0 * np.maximum(p.v[ag] - p.v[o], 0), 0)
        need_back = np.where(~front, (5.0 if aggressive else 10.0) + 3.0 * np.maximum(p.v[o] - p.v[ag], 0), 0)
        return bool(np.all(g >= np.maximum(need_front, need_back)))


    def _band(self, ag: int, lam: float, half: float) -> np.ndarray:
        """Other same-direction agents overlapping the lateral band lam +- half."""
        p = self.p
        n = p.n
        others = np.flatnonzero(p.active[:n] & (p.sign[:n] > 0))
        others = others[others != ag]
        return others[np.abs(p.lam[others] - lam) < half + 0.5 * p.width[others]]

    def _follower(self, ag: int) -> tuple[float, float]:
        """Gap to and speed of the nearest agent behind in the agent's own band."""
        p = self.p
        o = self._band(ag, p.lam[ag], 0.5 * p.width[ag])
        du = p.u[ag] - p.u[o]
        behind = du > 0
        if not behind.any():
            return np.inf, 0.0
        j = int(np.argmin(np.where(behind, du, np.inf)))
        return float(du[j] - 0.5 * (p.length[ag] + p.length[o[j]])), float(p.v[o[j]])

    def _lane_leader_speed(self, ag: int, row: int, k: int) -> float:
        """Speed of the next vehicle ahead (within 120 m) in lane slot k; inf when the lane is free."""
        p, lanes = self.p, self.route.same
        o = self._band(ag, lanes.lam[row, k], lanes.half[row, k])
        du = p.u[o] - p.u[ag]
        ahead = (du > 0) & (du < 120)
        if not ahead.any():
            return np.inf
        return float(p.v[o[int(np.argmin(np.where(ahead, du, np.inf)))]])
