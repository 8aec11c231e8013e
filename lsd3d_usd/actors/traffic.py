"""Seeded traffic over the layout's lane graph: IDM car following with junction reservations.

Each vehicle drives along lane centre lines (arc length ``s`` on its current lane) and picks
the next lane among the driving successors with the simulation's seeded generator when it
enters a lane (two lanes planned ahead), so the run is a pure function of (layout, seed,
parameters). Longitudinal control is the Intelligent Driver Model (Treiber, Hennecke &
Helbing 2000):

    a = a_max * (1 - (v / v0)^4 - (s*(v, dv) / gap)^2),   s* = s0 + v T + v dv / (2 sqrt(a_max b))

with the gap to the nearest vehicle ahead along the planned lanes (or to a "wall" at the end
of the lane when the vehicle may not enter the next one: dead ends, and junction lanes it
holds no reservation for). v0 is the lane speed limit times a per-driver factor <= 1, and
the next lane's limit once it is within braking distance; speeds are clipped to the
current lane's limit. Junction entry is a first-come reservation: a vehicle at the head of
its lane gets the junction lane it is heading for when no other vehicle holds a lane that
crosses or merges with it (centre lines closer than ``conflict_distance``); it releases it
one vehicle length after leaving it. A hard guard keeps every bumper-to-bumper gap to the
leader >= ``min_gap`` (IDM alone can undershoot it after a late merge).

Cyclists are vehicles of this model too (``_Vehicle.cyclist``): they ride bike lanes where
the layout has them (``bike`` lanes of the graph are theirs alone) and otherwise the right
part of driving lanes (a lateral ``offset``), at their own desired speed, following and
followed in the same IDM chain. Crosswalks: a vehicle treats every occupied crosswalk ahead
on its lane or plan (`occupied`, set by the pedestrian model) as a wall ``stop_margin``
before the first point where its lane's width touches the crosswalk, and `crosswalk_clear`
tells a pedestrian whether every vehicle heading across a crosswalk can still stop before it.

Traffic lights (``signals``: controlled lane index -> "green" / "yellow" / "red", set from
outside each step, e.g. by the closed-loop simulator's signal plan; empty: no lights): a
vehicle whose next stop point (layout.signals.stop_lane) shows yellow or red treats it as a
wall and asks for no junction reservation, unless it cannot stop before it at the
comfortable deceleration ``b``; then it goes through (that decision holds until it leaves
the lane or the light turns green). An external vehicle (the ego) is driven from outside: it only gives up its
reservation while it waits (slower than ``WAIT_SPEED``) at a yellow or red.

Arrays in, arrays out: `simulate` returns a `TrafficRun` sampled at ``fps``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.layout.signals import stop_lane

WAIT_SPEED = 0.5     # m/s: an external vehicle slower than this at a yellow or red waits


@dataclass(frozen=True)
class IDMParams:
    a_max: float = 1.5          # m/s^2 comfortable acceleration
    b: float = 2.0              # m/s^2 comfortable deceleration
    b_max: float = 8.0          # m/s^2 physical braking limit
    T: float = 1.2              # s time headway
    s0: float = 2.0             # m standstill gap
    delta: float = 4.0
    min_gap: float = 1.0        # m hard bumper-to-bumper guard
    stop_margin: float = 1.0    # m before a lane end the vehicle may not pass
    conflict_distance: float = 1.5
    dt_max: float = 0.05        # s simulation step (output samples fall on steps)
    speed_factor: tuple = (0.8, 1.0)
    crosswalk_headway: float = 0.5   # s a pedestrian adds to a vehicle's braking distance
    crosswalk_buffer: float = 2.0    # m more it keeps from a vehicle before stepping out


@dataclass
class TrafficRun:
    """Samples at times ``t`` (n_t,) of every vehicle (n_v): world xyz (n_v, n_t, 3),
    yaw (radians, unwrapped over time), speed (m/s), lane index into ``lane_ids`` and s."""
    t: np.ndarray
    position: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    lane: np.ndarray
    s: np.ndarray
    lane_ids: list[str]
    lengths: np.ndarray
    lane_limits: np.ndarray
    seed: int = 0
    params: IDMParams = field(default_factory=IDMParams)
    cyclist: np.ndarray | None = None     # (n_v,) bool: a cyclist, not a motor vehicle
    offset: np.ndarray | None = None      # (n_v, n_t) lateral offset from the centre line (m, + left)
    widths: np.ndarray | None = None      # (n_v,) box widths

    @property
    def n(self) -> int:
        return int(self.position.shape[0])


@dataclass
class _Vehicle:
    length: float
    lane: int
    s: float
    v: float
    factor: float
    plan: list            # next lanes (indices), at most two
    forced: list          # remaining forced route (ego)
    holds: dict           # lane index -> release condition (lane it leads to, or -1 while on it)
    free: bool = True     # chooses successors once ``forced`` runs out (else stops at its end)
    cyclist: bool = False
    v_max: float = np.inf  # own top speed (cyclists)
    offset: float = 0.0    # lateral offset from the lane centre (m, + left)
    width: float = 1.8
    # moved from outside (a closed-loop ego): never stepped here; `pose` is its own, and
    # lane -1 while it is on no lane
    external: bool = False
    pose_override: tuple | None = None
    go_through: int = -1   # controlled lane whose yellow/red it could not stop for (goes on)


def _idm(v, v0, gap, dv, p: IDMParams) -> float:
    v0 = max(v0, 0.1)
    s_star = p.s0 + max(0.0, v * p.T + v * dv / (2.0 * np.sqrt(p.a_max * p.b)))
    gap = max(gap, 0.01)
    return p.a_max * (1.0 - (v / v0) ** p.delta - (s_star / gap) ** 2)


class Simulation:
    def __init__(self, layout, seed: int, params: IDMParams = IDMParams(), graph: LaneGraph | None = None):
        self.p = params
        self.g = graph if graph is not None else LaneGraph(layout, params.conflict_distance)
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1D3]))
        self.seed = int(seed)
        self.veh: list[_Vehicle] = []
        self.occupied: set[int] = set()     # crosswalks with a pedestrian on (or stepping onto) them
        self.signals: dict[int, str] = {}    # controlled lane index -> light state (module doc)

    # ---- setup
    def _choose(self, lane: int, cyclist: bool = False) -> int | None:
        succ = self.g.succ[lane]
        if self.g.bike.any():
            # cars never take a bike lane; a cyclist on a bike lane stays on bike lanes if it can
            own = [j for j in succ if self.g.bike[j]] if cyclist and self.g.bike[lane] else []
            succ = own or [j for j in succ if not self.g.bike[j]]
        if not succ:
            return None
        return int(succ[int(self.rng.integers(len(succ)))]) if len(succ) > 1 else int(succ[0])

    def _fill_plan(self, v: _Vehicle) -> None:
        last = v.plan[-1] if v.plan else v.lane
        while len(v.plan) < 2 and last is not None:
            nxt = v.forced.pop(0) if v.forced else (self._choose(last, v.cyclist) if v.free else None)
            if nxt is None:
                break
            v.plan.append(nxt)
            last = nxt

    def spawn(self, lengths, min_spacing: float = 8.0, max_tries: int = 200) -> list[_Vehicle]:
        """Place vehicles of the given lengths on non-junction lanes, spaced apart."""
        cand = np.flatnonzero(~self.g.junction & (self.g.length >= 12.0) & ~self.g.bike)
        if len(cand) == 0 and len(lengths):
            raise InputError("traffic: the layout has no drivable lane long enough (>= 12 m) "
                             "outside junctions to place moving actors on")
        w = self.g.length[cand] / self.g.length[cand].sum() if len(cand) else None
        for L in lengths:
            for _ in range(max_tries):
                lane = int(cand[self.rng.choice(len(cand), p=w)])
                lo, hi = L / 2 + 1.0, self.g.length[lane] - L / 2 - 1.0
                if hi <= lo:
                    continue
                s = float(self.rng.uniform(lo, hi))
                if self._spawn_ok(lane, s, L, min_spacing):
                    f = float(self.rng.uniform(*self.p.speed_factor))
                    v = _Vehicle(float(L), lane, s, 0.5 * f * self.g.limit[lane], f, [], [], {})
                    self._fill_plan(v)
                    self.veh.append(v)
                    break
        return self.veh

    def spawn_cyclists(self, specs, min_spacing: float = 6.0, max_tries: int = 200,
                       edge: float = 0.25) -> list[_Vehicle]:
        """Place cyclists ``specs`` = [(length, width, v_max), ...]: on bike lanes when the
        layout has any, else on driving lanes (not bus lanes, not junctions) in their right
        part, ``edge`` m clear of the lane's right edge. Returns the cyclists placed."""
        bike = ~self.g.junction & (self.g.length >= 12.0) & self.g.bike
        if not bike.any():
            types = [ln.lane_type for ln in (self.g.layout.lane_by_id(i) for i in self.g.ids)]
            bike = ~self.g.junction & (self.g.length >= 12.0) & np.array([t == "driving" for t in types])
        cand = np.flatnonzero(bike)
        out = []
        if len(cand) == 0:
            return out
        w = self.g.length[cand] / self.g.length[cand].sum()
        for L, W, vmax in specs:
            for _ in range(max_tries):
                lane = int(cand[self.rng.choice(len(cand), p=w)])
                lo, hi = L / 2 + 1.0, self.g.length[lane] - L / 2 - 1.0
                if hi <= lo:
                    continue
                s = float(self.rng.uniform(lo, hi))
                off = self.cyclist_offset(lane, W, edge)
                if self._spawn_ok(lane, s, L, min_spacing, off):
                    f = float(self.rng.uniform(*self.p.speed_factor))
                    v = _Vehicle(float(L), lane, s, 0.5 * f * min(vmax, self.g.limit[lane]), f, [], [], {},
                                 cyclist=True, v_max=float(vmax), offset=off, width=float(W))
                    self._fill_plan(v)
                    self.veh.append(v)
                    out.append(v)
                    break
        return out

    def cyclist_offset(self, lane: int, width: float, edge: float = 0.25) -> float:
        """Lateral offset of a cyclist on ``lane``: 0 on a bike lane, else the right part of
        the lane, ``edge`` m clear of its right edge."""
        if self.g.bike[lane]:
            return 0.0
        return -max(0.0, self.g.width[lane] / 2 - edge - width / 2)

    def _spawn_ok(self, lane, s, L, spacing, offset: float = 0.0) -> bool:
        p = self.g.geoms[lane].offset_point(s, offset) if offset else self.g.geoms[lane].point(s)
        for o in self.veh:
            if o.lane < 0:
                continue
            if o.lane == lane and abs(o.s - s) < (o.length + L) / 2 + spacing:
                return False
            q = self.g.geoms[o.lane].offset_point(o.s, o.offset) if o.offset else self.g.geoms[o.lane].point(o.s)
            if np.linalg.norm(p[:2] - q[:2]) < (o.length + L) / 2 + 0.5 and o.lane != lane:
                # a different lane this close: only fine if side by side (>= a lane apart)
                if np.linalg.norm(p[:2] - q[:2]) < 2.8:
                    return False
        return True

    def add_ego(self, route: list[int], length: float, s: float = 0.0, v: float | None = None,
                free: bool = False):
        """Vehicle 0: forced along ``route`` (lane indices); at its end it stops, or with
        ``free`` goes on with seeded choices."""
        lane = route[0]
        s = float(np.clip(s, 0.0, self.g.length[lane]))
        ego = _Vehicle(float(length), lane, s, float(self.g.limit[lane] * 0.8 if v is None else v),
                       1.0, [], list(route[1:]), {}, free)
        if self.g.junction[lane]:
            ego.holds[lane] = -1
        self._fill_plan(ego)
        self.veh.insert(0, ego)
        return ego

    # ---- one step
    def _ahead(self, i: int, horizon: float):
        """(gap bumper-to-bumper, leader speed) of the nearest obstacle ahead of vehicle i
        along its lane and plan, or (inf, 0)."""
        me = self.veh[i]
        best = (np.inf, 0.0)
        # same lane
        for j, o in enumerate(self.veh):
            if j == i or o.lane != me.lane:
                continue
            if o.s > me.s or (o.s == me.s and j < i):
                gap = o.s - me.s - (o.length + me.length) / 2
                if gap < best[0]:
                    best = (gap, o.v)
        if np.isfinite(best[0]):
            return best
        dist = self.g.length[me.lane] - me.s          # from my centre to the end of my lane
        prev = me.lane
        for nxt in me.plan:
            if dist - me.length / 2 > horizon:
                break
            if self._must_stop(me, prev, nxt, dist - me.length / 2 - self.p.stop_margin):
                return dist - me.length / 2 - self.p.stop_margin, 0.0
            for o in self.veh:
                if o.lane == nxt:
                    gap = dist + o.s - (o.length + me.length) / 2
                    if gap < best[0]:
                        best = (gap, o.v)
            if np.isfinite(best[0]):
                return best
            dist += self.g.length[nxt]
            prev = nxt
        if len(me.plan) < 2 and dist - me.length / 2 <= horizon:
            # the plan ends (dead end): a wall at its end
            return dist - me.length / 2 - self.p.stop_margin, 0.0
        return best

    def _crossings_ahead(self, me: _Vehicle, horizon: float):
        """(crosswalk, distance from the front bumper to where the lane touches it, s_out
        distance) of the crosswalks ahead on the vehicle's lane and plan, nearest first."""
        out = []
        base = -me.s - me.length / 2          # arc length of the lane start from my front
        for k, lane in enumerate([me.lane] + list(me.plan)):
            for cw, s_in, s_out in self.g.crossings[lane]:
                d_in, d_out = base + s_in, base + s_out
                if k == 0 and d_out + me.length < 0:
                    continue                  # the whole vehicle is past it
                out.append((cw, d_in, d_out))
            base += self.g.length[lane]
            if base > horizon:
                break
        return out

    def _crosswalk_gap(self, me: _Vehicle, horizon: float) -> float:
        """Bumper distance to the wall of the nearest occupied crosswalk ahead (inf: none).
        A crosswalk the front is already over is not a wall (the pedestrian did not step out
        in front of it: `crosswalk_clear`)."""
        if not self.occupied:
            return np.inf
        for cw, d_in, _ in self._crossings_ahead(me, horizon):
            if cw in self.occupied and d_in > -0.5:
                return d_in - self.p.stop_margin
        return np.inf

    def crosswalk_clear(self, cw: int) -> bool:
        """May a pedestrian step onto crosswalk ``cw`` now: no vehicle is over it, and every
        vehicle heading across it can stop before it at its comfortable deceleration."""
        p = self.p
        for me in self.veh:
            if me.lane < 0:
                continue
            for c, d_in, d_out in self._crossings_ahead(me, 150.0):
                if c != cw:
                    continue
                if d_in <= 0.0 and d_out + me.length >= 0.0:
                    return False              # over it
                need = me.v ** 2 / (2 * p.b) + me.v * p.crosswalk_headway + p.stop_margin + p.crosswalk_buffer
                if 0.0 < d_in < need:
                    return False
        return True

    def _must_stop(self, me: _Vehicle, cur: int, nxt: int, gap: float) -> bool:
        """May ``me`` not pass from ``cur`` into ``nxt`` (``gap``: bumper distance to that
        point): a junction it holds no reservation for, or a light it waits at."""
        if self._signal_wait(me, cur, nxt, gap):
            return True
        return bool(self.g.junction[nxt]) and nxt not in me.holds and not self.g.junction[cur]

    def _signal_wait(self, me: _Vehicle, cur: int, nxt: int, gap: float) -> bool:
        """Does ``me`` wait at the light between ``cur`` and ``nxt`` (module doc)?"""
        if not self.signals:
            return False
        lane = stop_lane(cur, nxt, self.signals, self.g.junction)
        if lane is None:
            return False
        if self.signals[lane] == "green":
            if me.go_through == lane:
                me.go_through = -1          # a decision holds for one yellow/red only
            return False
        if me.external:
            return me.v < WAIT_SPEED
        if me.go_through == lane:
            return False
        if gap < me.v ** 2 / (2.0 * self.p.b):
            me.go_through = lane        # too close to stop comfortably: it goes through
            return False
        return True

    def _grant(self) -> None:
        """Junction reservations, nearest-to-the-lane-end first."""
        want = []
        for i, me in enumerate(self.veh):
            if me.lane < 0 or not me.plan:
                continue
            rem = self.g.length[me.lane] - me.s
            if self.signals and \
                    self._signal_wait(me, me.lane, me.plan[0], rem - me.length / 2 - self.p.stop_margin):
                for c in me.plan:           # waiting at a light: it holds nothing ahead
                    me.holds.pop(c, None)
                continue
            if not self.g.junction[me.plan[0]] or me.plan[0] in me.holds:
                continue
            if self.g.junction[me.lane]:
                continue
            head = all(not (o.lane == me.lane and (o.s > me.s or (o.s == me.s and j < i)))
                       for j, o in enumerate(self.veh) if j != i)
            if head and rem - me.length / 2 < max(30.0, me.v ** 2 / (2 * self.p.b) + 10.0):
                want.append((rem, i))
        for _, i in sorted(want):
            me = self.veh[i]
            # the whole chain of junction lanes ahead must be free of conflicts
            chain = []
            for nxt in me.plan:
                if not self.g.junction[nxt]:
                    break
                chain.append(nxt)
            blocked = False
            for j, o in enumerate(self.veh):
                if j == i:
                    continue
                held = set(o.holds) | ({o.lane} if o.lane >= 0 and self.g.junction[o.lane] else set())
                for c in chain:
                    if held & self.g.conflicts[c]:
                        blocked = True
                        break
                if blocked:
                    break
            if not blocked:
                for c in chain:
                    me.holds[c] = -1

    def _release(self, me: _Vehicle) -> None:
        if me.lane < 0:
            me.holds.clear()
            return
        for lane in list(me.holds):
            if lane == me.lane or (me.external and lane in me.plan):
                continue     # an external vehicle keeps what it was granted until it is through
            # released once the vehicle is a length past the end of the held lane
            if not self.g.junction[me.lane] and me.s > me.length:
                del me.holds[lane]

    def step(self, dt: float) -> None:
        p = self.p
        self._grant()
        acc = np.zeros(len(self.veh))
        bound = np.full(len(self.veh), np.inf)
        for i, me in enumerate(self.veh):
            if me.external:
                continue
            horizon = max(120.0, me.v * 8.0)
            gap, v_lead = self._ahead(i, horizon)
            cw_gap = self._crosswalk_gap(me, horizon)
            if cw_gap < gap:
                gap, v_lead = cw_gap, 0.0
            v0 = min(self.g.limit[me.lane] * me.factor, me.v_max)
            if me.plan:
                nxt_lim = min(self.g.limit[me.plan[0]] * me.factor, me.v_max)
                rem = self.g.length[me.lane] - me.s
                if nxt_lim < v0 and rem < me.v ** 2 / (2 * p.b) + me.v * p.T + 5.0:
                    v0 = nxt_lim
            acc[i] = _idm(me.v, v0, gap, me.v - v_lead, p) if np.isfinite(gap) else \
                p.a_max * (1 - (me.v / max(v0, 0.1)) ** p.delta)
            bound[i] = gap - p.min_gap if np.isfinite(gap) else np.inf
        for i, me in enumerate(self.veh):
            if me.external:
                continue
            a = max(acc[i], -p.b_max)
            v_new = max(0.0, me.v + a * dt)
            ds = 0.5 * (me.v + v_new) * dt
            if ds > bound[i]:                # hard guard against the leader's old position
                ds = max(0.0, bound[i])
                v_new = min(v_new, 2.0 * ds / dt - me.v) if ds > 0 else 0.0
                v_new = max(v_new, 0.0)
            self._advance(me, ds)
            me.v = min(v_new, self.g.limit[me.lane], me.v_max)
        for me in self.veh:
            self._release(me)

    def _advance(self, me: _Vehicle, ds: float) -> None:
        me.s += ds
        while me.s > self.g.length[me.lane]:
            if not me.plan:  # dead end: stay at the end
                me.s = self.g.length[me.lane]
                me.v = 0.0
                return
            me.s -= self.g.length[me.lane]
            if me.go_through == me.lane:
                me.go_through = -1
            me.lane = me.plan.pop(0)
            if me.cyclist:
                me.offset = self.cyclist_offset(me.lane, me.width)
            self._fill_plan(me)

    # ---- run
    def pose(self, me: _Vehicle) -> tuple[float, float, float]:
        """(x, y, yaw) of a vehicle now (box centre)."""
        if me.pose_override is not None:
            return me.pose_override
        return self.g.geoms[me.lane].pose2d(me.s, me.offset)

    def add_external(self, length: float, width: float) -> _Vehicle:
        """A vehicle moved from outside (the closed-loop ego): the others follow it, yield to
        it and stop behind it; `place_external` sets where it is before each step."""
        v = _Vehicle(float(length), -1, 0.0, 0.0, 1.0, [], [], {}, free=False, width=float(width),
                     external=True)
        self.veh.insert(0, v)
        return v

    def place_external(self, v: _Vehicle, pose: tuple, speed: float, lane: int = -1,
                       s: float = 0.0, plan=()) -> None:
        """Where the external vehicle ``v`` is now: its box centre pose (x, y, yaw), speed, and
        the lane (index, -1 for none) and arc length its centre projects to, with the lanes
        it will drive next (``plan``, for junction reservations)."""
        if lane != v.lane:
            v.holds = {k: c for k, c in v.holds.items() if k in plan or k == lane}
            if lane >= 0 and self.g.junction[lane]:
                v.holds[lane] = -1
        v.pose_override = tuple(float(c) for c in pose)
        v.v, v.lane, v.s = float(speed), int(lane), float(s)
        v.plan = [int(k) for k in plan][:2]

    def must_stop_before(self, v: _Vehicle, horizon: float = 120.0) -> float:
        """Bumper distance the vehicle ``v`` must stop within by the model's rules (a junction
        it holds no reservation for, an occupied crosswalk), inf when none."""
        if v.lane < 0:
            return np.inf
        best = self._crosswalk_gap(v, horizon)
        dist = self.g.length[v.lane] - v.s
        prev = v.lane
        for nxt in v.plan:
            if dist - v.length / 2 > horizon:
                break
            if self._must_stop(v, prev, nxt, dist - v.length / 2 - self.p.stop_margin):
                best = min(best, dist - v.length / 2 - self.p.stop_margin)
                break
            dist += self.g.length[nxt]
            prev = nxt
        return best

    def leader(self, i: int, horizon: float = 120.0) -> tuple[float, float]:
        """(bumper gap, speed) of the nearest vehicle ahead of vehicle i along its lane and
        plan (inf, 0 when none); lane ends and junction rules are `must_stop_before`'s."""
        me = self.veh[i]
        if me.lane < 0:
            return np.inf, 0.0
        best = (np.inf, 0.0)
        dist = -me.s                      # arc length of the lane's start from my centre
        for lane in [me.lane] + list(me.plan):
            if dist - me.length / 2 > horizon:
                break
            for j, o in enumerate(self.veh):
                if j == i or o.lane != lane or (lane == me.lane and o.s < me.s):
                    continue
                gap = dist + o.s - (o.length + me.length) / 2
                if gap < best[0]:
                    best = (gap, o.v)
            if np.isfinite(best[0]):
                return best
            dist += self.g.length[lane]
        return best

    def run(self, seconds: float, fps: float, on_step=None, on_sample=None) -> TrafficRun:
        """Run for ``seconds``, sampling every 1/fps s. ``on_step(sim, dt)`` is called before
        every vehicle step (the pedestrian model moves there and sets ``occupied``),
        ``on_sample(sim, k)`` at every output sample k."""
        if not (fps > 0) or not (seconds >= 0):
            raise InputError(f"traffic: need fps > 0 and seconds >= 0, got fps={fps}, seconds={seconds}")
        n_t = int(round(seconds * fps)) + 1
        sub = max(1, int(np.ceil((1.0 / fps) / self.p.dt_max)))
        dt = 1.0 / fps / sub
        nv = len(self.veh)
        lane = np.zeros((nv, n_t), np.int32)
        s = np.zeros((nv, n_t))
        v = np.zeros((nv, n_t))
        off = np.zeros((nv, n_t))
        for k in range(n_t):
            if k:
                for _ in range(sub):
                    if on_step is not None:
                        on_step(self, dt)
                    self.step(dt)
            for i, me in enumerate(self.veh):
                lane[i, k], s[i, k], v[i, k], off[i, k] = me.lane, me.s, me.v, me.offset
            if on_sample is not None:
                on_sample(self, k)
        pos = np.zeros((nv, n_t, 3))
        yaw = np.zeros((nv, n_t))
        for i in range(nv):
            for k in range(n_t):
                g = self.g.geoms[lane[i, k]]
                x, y, yaw[i, k] = g.pose2d(float(s[i, k]), float(off[i, k]))
                pos[i, k] = x, y, np.interp(min(max(s[i, k], 0.0), g.length), g.cum, g.points[:, 2])
            yaw[i] = np.unwrap(yaw[i])
        return TrafficRun(np.arange(n_t) / fps, pos, yaw, v, lane, s, list(self.g.ids),
                          np.array([me.length for me in self.veh]), self.g.limit.copy(),
                          self.seed, self.p, np.array([me.cyclist for me in self.veh], bool),
                          off, np.array([me.width for me in self.veh]))


def simulate(layout, lengths, seed: int = 0, seconds: float = 8.0, fps: float = 10.0,
             params: IDMParams = IDMParams(), ego_route=None, ego_length: float = 4.8) -> TrafficRun:
    """Spawn ``len(lengths)`` vehicles (seeded) and run IDM traffic; deterministic per seed.
    With ``ego_route`` (lane ids) vehicle 0 is an ego car starting at the route's first lane
    and following it (then seeded choices)."""
    sim = Simulation(layout, seed, params)
    if ego_route:
        sim.add_ego(sim.g.route_indices(list(ego_route)), ego_length)
    sim.spawn(list(lengths))
    return sim.run(seconds, fps)
