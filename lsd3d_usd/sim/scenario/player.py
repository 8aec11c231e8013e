"""Play a scenario's storyboard for its non-ego entities, step by step.

`ScenarioPlayer(scenario, layout, dt)`: `start()` places the entities from Init; each
`step(t, ego_state)` first moves every entity from the previous time to ``t`` under its
running actions (exact within the step for the speed shapes: Simpson over the smooth part),
then evaluates the triggers on the states at ``t`` (edges against the previous evaluation,
delays as the edged value ``delay`` seconds earlier) and starts the events they fire: their
actions begin at ``t``. Returns {entity: (x, y, z, yaw, speed)} at ``t``.

With ``drive_ego`` the ego is played like every other entity (its own actions: esmini
without an external driver, `sim run --policy scenario`) and ``ego_state`` is ignored;
`ego_pose()` is where the storyboard puts it.

Entities without an action keep following their lane (the lane graph of the layout, at
their speed; pedestrians and entities off every lane go straight on). Positions are the
OpenSCENARIO reference point (a vehicle's rear axle centre).
"""
from __future__ import annotations

import math
import warnings
from collections import deque
from dataclasses import dataclass, field

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.sim.scenario import reader as R
from lsd3d_usd.sim.scenario.lanes import lane_position, layout_lane, opendrive_lane_of, road_s

MAX_STEPS = 10_000_000       # a scenario whose timing needs more steps is refused
LANE_SNAP = 1.0              # m beyond a lane's half width where an entity still is on it
EPS = 1e-9


def shape_fn(shape: str, u: float) -> float:
    u = min(max(u, 0.0), 1.0)
    if shape == "step":
        return 1.0
    if shape == "linear":
        return u
    if shape == "cubic":
        return u * u * (3 - 2 * u)
    return 0.5 * (1 - math.cos(math.pi * u))     # sinusoidal


def _compare(a: float, rule: str, b: float) -> bool:
    return {"greaterThan": a > b, "lessThan": a < b, "equalTo": abs(a - b) < 1e-9,
            "greaterOrEqual": a >= b, "lessOrEqual": a <= b, "notEqualTo": abs(a - b) >= 1e-9}[rule]


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class EntityState:
    name: str
    entity: R.Entity
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0
    v: float = 0.0
    lane: int = -1               # lane graph index; -1: off the lanes (goes straight on)
    s: float = 0.0
    offset: float = 0.0          # m left of the lane centre
    plan: list = field(default_factory=list)    # lane indices to take next
    odometer: float = 0.0
    still: float = 0.0           # seconds at standstill
    long: object = None          # the running longitudinal action
    lat: object = None           # the running lateral action
    traj: object = None          # a trajectory (both domains)


# ---------------------------------------------------------------- action runners

class _Run:
    done = False
    domains: tuple = ()

    def __init__(self, action, where):
        self.action, self.where = action, where


class _Speed(_Run):
    domains = ("long",)

    def __init__(self, action, where, t0, st: EntityState, target):
        super().__init__(action, where)
        d = action.dynamics
        self.t0, self.v0, self.vt, self.shape = t0, st.v, target, d.shape
        self.dim, self.odo0 = d.dimension, st.odometer
        if d.shape == "step" or d.value == 0:
            self.T = 0.0
        elif d.dimension == "rate":
            self.T = abs(self.vt - self.v0) / d.value
        else:
            self.T = d.value        # seconds, or metres for dimension distance
        if self.T == 0:
            st.v, self.done = target, True

    def speed(self, t: float, st: EntityState) -> float:
        if self.dim == "distance":
            u = (st.odometer - self.odo0) / self.T
        else:
            u = (t - self.t0) / self.T
        return self.v0 + (self.vt - self.v0) * shape_fn(self.shape, u)

    def end_time(self) -> float:
        return self.t0 + self.T if self.dim != "distance" else math.inf


class _LaneChange(_Run):
    domains = ("lat",)

    def __init__(self, action, where, t0, st: EntityState, target_lane: int, player):
        super().__init__(action, where)
        d = action.dynamics
        if st.lane >= 0 and target_lane != st.lane:
            lp = player.graph.nearest_lane((st.x, st.y), lanes=[target_lane])
            st.lane, st.s, st.offset = target_lane, lp.s, lp.offset
            st.plan = []
        self.t0, self.odo0, self.d0, self.dt_ = t0, st.odometer, st.offset, action.target_offset
        self.shape, self.dim = d.shape, d.dimension
        dist = abs(self.dt_ - self.d0)
        self.T = 0.0 if d.shape == "step" or d.value == 0 else \
            (dist / d.value if d.dimension == "rate" else d.value)
        if self.T == 0:
            st.offset, self.done = self.dt_, True

    def offset(self, t: float, st: EntityState) -> float:
        u = ((st.odometer - self.odo0) if self.dim == "distance" else (t - self.t0)) / self.T
        if u >= 1 - EPS:
            self.done = True
        return self.d0 + (self.dt_ - self.d0) * shape_fn(self.shape, u)


class _Trajectory(_Run):
    domains = ("long", "lat")

    def __init__(self, action, where, t0, st: EntityState, player):
        super().__init__(action, where)
        self.pts = [player.pose_of(p, st)[:2] for _, p in action.vertices]
        if action.closed:
            self.pts.append(self.pts[0])
        times = [tv for tv, _ in action.vertices]
        self.times = None
        if action.timing is not None and all(tv is not None for tv in times):
            dom, scale, off = action.timing
            base = t0 if dom == "relative" else 0.0
            self.times = [base + off + scale * tv for tv in times]
            if any(b < a - EPS for a, b in zip(self.times, self.times[1:])):
                raise InputError(f"{where}: FollowTrajectoryAction: vertex times decrease")
        self.cum = [0.0]
        for a, b in zip(self.pts, self.pts[1:]):
            self.cum.append(self.cum[-1] + math.hypot(b[0] - a[0], b[1] - a[1]))
        self.d = 0.0

    def _at(self, d: float):
        cum, pts = self.cum, self.pts
        d = min(max(d, 0.0), cum[-1])
        j = 0
        while j < len(cum) - 2 and cum[j + 1] < d:
            j += 1
        seg = cum[j + 1] - cum[j]
        f = (d - cum[j]) / seg if seg > 0 else 0.0
        a, b = pts[j], pts[j + 1]
        return a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), math.atan2(b[1] - a[1], b[0] - a[0])

    def advance(self, t0: float, t1: float, st: EntityState) -> None:
        if self.times is not None:
            ts = self.times
            if t1 >= ts[-1] - EPS:
                d, self.done = self.cum[-1], True
                v = st.v
            elif t1 <= ts[0]:
                d, v = 0.0, 0.0
            else:
                j = max(k for k in range(len(ts) - 1) if ts[k] <= t1)
                span = ts[j + 1] - ts[j]
                f = (t1 - ts[j]) / span if span > 0 else 1.0
                d = self.cum[j] + f * (self.cum[j + 1] - self.cum[j])
                v = (self.cum[j + 1] - self.cum[j]) / span if span > 0 else 0.0
        else:
            d = self.d + st.v * (t1 - t0)
            v = st.v
            if d >= self.cum[-1] - EPS:
                self.done = True
        moved = max(d - self.d, 0.0)
        self.d = d
        st.x, st.y, st.yaw = self._at(d)
        st.v, st.odometer = v, st.odometer + moved


def _remaining(target, x: float, y: float, yaw: float) -> float:
    """Distance to ``target`` while it lies ahead (0 once passed: arrived)."""
    dx, dy = target[0] - x, target[1] - y
    return math.hypot(dx, dy) if dx * math.cos(yaw) + dy * math.sin(yaw) > 0 else 0.0


class _Synchronize(_Run):
    """The entity's speed each step is its distance to its target over the master's time to
    the master's target, both from the states at the step's start (`ScenarioPlayer.before`):
    with the master at constant speed the two remaining distances keep their ratio, so the
    two arrive at the same instant, whatever order the entities are moved in."""
    domains = ("long",)

    def __init__(self, action, where, t0, st, player):
        super().__init__(action, where)
        self.player = player
        self.target = player.pose_of(action.position, st)[:2]
        self.master_target = player.pose_of(action.master_position, st)[:2]

    def advance(self, t0: float, t1: float, st: EntityState) -> tuple[float, float]:
        """(distance to move over [t0, t1], speed at t1)."""
        h = t1 - t0
        self.player.state_of(self.action.master)
        mx, my, myaw, mv = self.player.before[self.action.master]
        x, y, yaw, v = self.player.before[st.name]
        d = _remaining(self.target, x, y, yaw)
        dm = _remaining(self.master_target, mx, my, myaw)
        final = self.action.final_speed
        if d <= 0 or dm <= 0:            # one of them is there already: the action ends
            self.done = True
            v = final if final is not None else v
            return v * h, v
        if mv <= 0.01:                   # the master stands: no arrival time to match yet
            return v * h, v
        tau = dm / mv
        vs = d / tau
        if tau <= h + EPS:               # both arrive within this step, at t0 + tau
            self.done = True
            vf = final if final is not None else vs
            return d + vf * (h - tau), vf
        return vs * h, vs


# ---------------------------------------------------------------- storyboard runtime

@dataclass
class _Element:
    kind: str                    # act, maneuverGroup, maneuver, event, action
    name: str
    obj: object
    state: str = "standby"
    runs: int = 0


class _CondState:
    def __init__(self):
        self.prev = None
        self.hist = deque()      # (t, edged value)


class ScenarioPlayer:
    """Steps a scenario's non-ego entities on a layout (see the module doc)."""

    def __init__(self, scenario: R.Scenario, layout, dt: float, drive_ego: bool = False):
        if not (dt > 0 and math.isfinite(dt)):
            raise InputError(f"scenario player: dt {dt} must be > 0")
        self.sc, self.layout, self.dt = scenario, layout, float(dt)
        self.drive_ego = bool(drive_ego)
        self.graph = LaneGraph(layout)
        self.ego = scenario.ego
        self.states: dict[str, EntityState] = {}
        self.t = 0.0
        self._ego_init = None
        self.ego_actions: list = []          # (t, action) the storyboard gives the ego
        self.before: dict = {}               # (x, y, yaw, v) per entity at the last step's start
        self.finished = False                # the storyboard's stop trigger fired
        self.warned: set = set()
        self._cond: dict[int, _CondState] = {}
        self._transitions: list = []         # (name, transition)
        self._mark = 0
        self._elements: list[_Element] = []
        self._by_name: dict[str, list[_Element]] = {}
        self._check_steps()

    # ---- set up
    def _check_steps(self) -> None:
        """Refuse timings no run could step through (a trajectory lasting 10^9 steps)."""
        acts = [a for acts in self.sc.init.values() for a in acts]
        for st in self.sc.stories:
            for act in st.acts:
                for g in act.groups:
                    for m in g.maneuvers:
                        for e in m.events:
                            acts += [pa.action for pa in e.actions]
        for a in acts:
            if isinstance(a, R.FollowTrajectoryAction) and a.timing is not None and a.vertices:
                _, scale, off = a.timing
                tmax = max(abs(off + scale * (tv or 0.0)) for tv, _ in a.vertices)
                if tmax / self.dt > MAX_STEPS:
                    raise InputError(f"{a.where}: FollowTrajectoryAction: its timing lasts {tmax:.4g} s, "
                                     f"{tmax / self.dt:.3g} steps of {self.dt:g} s (at most {MAX_STEPS})")
            if isinstance(a, R.SpeedAction) and a.dynamics.dimension == "time" and \
                    a.dynamics.value / self.dt > MAX_STEPS:
                raise InputError(f"{a.where}: SpeedAction lasts {a.dynamics.value:.4g} s, more than "
                                 f"{MAX_STEPS} steps of {self.dt:g} s")

    def _element(self, kind, name, obj) -> _Element:
        e = _Element(kind, name, obj)
        self._elements.append(e)
        self._by_name.setdefault(name, []).append(e)
        return e

    def start(self) -> dict:
        """Place the entities from Init (teleports, then speeds); the states at t = 0."""
        self.t = 0.0
        for name, ent in self.sc.entities.items():
            self.states[name] = EntityState(name, ent)
        for name, acts in self.sc.init.items():
            for a in acts:
                if isinstance(a, R.TeleportAction):
                    self._teleport(self.states[name], a.position)
        for name, acts in self.sc.init.items():
            for a in acts:
                if not isinstance(a, R.TeleportAction):
                    if name == self.ego:
                        self.ego_actions.append((0.0, a))
                        if not self.drive_ego:
                            if isinstance(a, R.SpeedAction) and a.speed is not None:
                                self.states[name].v = a.speed
                            continue
                    self._start_action(self.states[name], a, 0.0)
        e = self.states.get(self.ego)
        self._ego_init = None if e is None else (e.x, e.y, e.z, e.yaw, e.v)
        self._acts = []
        for story in self.sc.stories:
            self._element("story", story.name, story)
            for act in story.acts:
                ae = self._element("act", act.name, act)
                groups = []
                for g in act.groups:
                    ge = self._element("maneuverGroup", g.name, g)
                    mans = []
                    for m in g.maneuvers:
                        me = self._element("maneuver", m.name, m)
                        evs = [(self._element("event", e.name, e),
                                [self._element("action", pa.name, pa) for pa in e.actions]) for e in m.events]
                        mans.append((me, evs))
                    groups.append((ge, mans))
                self._acts.append((ae, groups))
        self._evaluate(0.0)
        return self.poses()

    def state_of(self, name: str) -> EntityState:
        if name not in self.states:
            raise InputError(f"{self.sc.path}: entityRef {name!r} names no entity")
        return self.states[name]

    def ego_init(self) -> tuple | None:
        """(x, y, z, yaw, speed) the scenario's Init gives the ego (None without an ego)."""
        return self._ego_init

    # ---- positions
    def pose_of(self, pos: R.Position, st: EntityState | None = None):
        """(x, y, z, yaw) of a Position (yaw None when it gives none)."""
        k = pos.kind
        if k == "world":
            return pos.x, pos.y, pos.z, pos.h
        if k == "lane":
            try:
                x, y, z, h = lane_position(self.layout, pos.road_id, pos.lane_id, pos.s, pos.offset)
            except InputError as e:
                raise InputError(f"{pos.where}: {e}") from None
            return x, y, z, h + (pos.h or 0.0)
        if k in ("relative_object", "relative_world", "relative_lane"):
            ref = self.state_of(pos.entity)
            if k == "relative_world":
                return ref.x + pos.dx, ref.y + pos.dy, ref.z, pos.h
            if k == "relative_object":
                c, s_ = math.cos(ref.yaw), math.sin(ref.yaw)
                return (ref.x + c * pos.dx - s_ * pos.dy, ref.y + s_ * pos.dx + c * pos.dy, ref.z,
                        ref.yaw + (pos.h or 0.0))
            od = opendrive_lane_of(self.layout, self.graph.ids[ref.lane]) if ref.lane >= 0 else None
            if od is not None:
                _, s_road = self._road_s(ref)
                lid = od[1] + pos.d_lane
                if (od[1] > 0) != (lid > 0) or lid == 0:
                    lid += 1 if pos.d_lane > 0 else -1     # lane 0 is the reference line
                lp = R.Position("lane", road_id=od[0], lane_id=lid, s=s_road + pos.ds,
                                offset=pos.offset, h=pos.h, where=pos.where)
                return self.pose_of(lp)
            w = self.graph.width[ref.lane] if ref.lane >= 0 else 3.5
            c, s_ = math.cos(ref.yaw), math.sin(ref.yaw)
            dy = pos.d_lane * w + pos.offset
            return ref.x + c * pos.ds - s_ * dy, ref.y + s_ * pos.ds + c * dy, ref.z, ref.yaw
        self._warn(pos.where, "Position of this kind")
        return (st.x, st.y, st.z, st.yaw) if st else (0.0, 0.0, 0.0, 0.0)

    def _road_s(self, st: EntityState):
        """(road id, road s) of an entity on an imported OpenDRIVE lane."""
        r = road_s(self.layout, self.graph.ids[st.lane], st.s)
        return (None, 0.0) if r is None else (r[0], r[2])

    def _teleport(self, st: EntityState, pos: R.Position) -> None:
        x, y, z, h = self.pose_of(pos, st)
        st.x, st.y, st.z = x, y, z
        st.yaw = h if h is not None else st.yaw
        st.plan = []
        self._snap(st)

    def _snap(self, st: EntityState) -> None:
        if st.entity.kind == "pedestrian" or not len(self.graph):
            st.lane = -1
            return
        lp = self.graph.nearest_lane((st.x, st.y), heading=st.yaw)
        if lp is not None and lp.distance <= self.graph.width[lp.lane] / 2 + LANE_SNAP \
                and abs(lp.relative_heading) < math.pi / 2:
            st.lane, st.s, st.offset = lp.lane, lp.s, lp.offset
        else:
            st.lane = -1

    # ---- actions
    def _start_action(self, st: EntityState, a, t: float, where: str = ""):
        where = getattr(a, "where", where)
        if isinstance(a, R.TeleportAction):
            self._teleport(st, a.position)
            return None
        if isinstance(a, R.SpeedAction):
            target = a.speed
            if target is None:
                ref = self.state_of(a.ref_entity)
                target = ref.v + a.rel_value if a.rel_type == "delta" else ref.v * a.rel_value
            run = _Speed(a, where, t, st, target)
        elif isinstance(a, R.LaneChangeAction):
            run = _LaneChange(a, where, t, st, self._target_lane(st, a), self)
        elif isinstance(a, R.FollowTrajectoryAction):
            if not a.vertices:
                return None
            run = _Trajectory(a, where, t, st, self)
        elif isinstance(a, R.AssignRouteAction):
            self._route(st, a)
            return None
        elif isinstance(a, R.SynchronizeAction):
            run = _Synchronize(a, where, t, st, self)
        else:
            self._warn(where, type(a).__name__ if not isinstance(a, R.Unsupported) else a.element)
            return None
        if run.done:
            return None
        for dom in run.domains:          # a new action overrides the running one of its domain
            old = getattr(st, dom)
            if old is not None:
                old.done = True
        if "long" in run.domains and "lat" in run.domains:
            st.long = st.lat = None
            st.traj = run
        else:
            st.traj = None
            setattr(st, run.domains[0], run)
        return run

    def _target_lane(self, st: EntityState, a: R.LaneChangeAction) -> int:
        if st.lane < 0:
            raise InputError(f"{a.where}: LaneChangeAction for {st.name}, which is on no lane")
        if a.lane_id is not None:
            od = opendrive_lane_of(self.layout, self.graph.ids[st.lane])
            if od is None:
                raise InputError(f"{a.where}: AbsoluteTargetLane needs a layout imported from OpenDRIVE")
            _, s_road = self._road_s(st)
            lid, _ = layout_lane(self.layout, od[0], a.lane_id, s_road)
            return self.graph.index[lid]
        ref = self.state_of(a.ref_entity)
        if ref.lane < 0:
            self._snap(ref)
        if ref.lane < 0:
            raise InputError(f"{a.where}: RelativeTargetLane: {ref.name} is on no lane")
        lane = ref.lane
        if a.rel_lanes:
            g = self.graph
            s_ref = g.nearest_lane((st.x, st.y), lanes=[lane]).s
            step = 1 if a.rel_lanes > 0 else -1
            for _ in range(abs(a.rel_lanes)):
                x, y, h = g.geoms[lane].pose2d(s_ref, step * g.width[lane])
                lp = g.nearest_lane((x, y), heading=h)
                if lp is None or lp.lane == lane or lp.distance > g.width[lp.lane] / 2:
                    raise InputError(f"{a.where}: LaneChangeAction: no lane {a.rel_lanes:+d} of "
                                     f"{ref.name}'s lane {g.ids[ref.lane]}")
                lane, s_ref = lp.lane, lp.s
        return lane

    def _route(self, st: EntityState, a: R.AssignRouteAction) -> None:
        """Plan the lanes through the waypoints (breadth-first over successors)."""
        g = self.graph
        plan, cur = [], st.lane
        for wp in a.waypoints:
            x, y, _, h = self.pose_of(wp, st)
            lp = g.nearest_lane((x, y), heading=h)
            if lp is None:
                continue
            if cur < 0:
                cur = lp.lane
                continue
            if lp.lane == cur:
                continue
            prev = {cur: None}
            todo = deque([cur])
            while todo and lp.lane not in prev and len(prev) < 20000:
                i = todo.popleft()
                for j in g.succ[i]:
                    if j not in prev:
                        prev[j] = i
                        todo.append(j)
            if lp.lane not in prev:
                raise InputError(f"{a.where}: AssignRouteAction: no lane path to the waypoint at "
                                 f"({x:.1f}, {y:.1f})")
            path, j = [], lp.lane
            while j != cur:
                path.append(j)
                j = prev[j]
            plan += path[::-1]
            cur = lp.lane
        st.plan = plan

    # ---- motion
    def _advance(self, st: EntityState, t0: float, t1: float) -> None:
        h = t1 - t0
        if st.traj is not None:
            st.traj.advance(t0, t1, st)
            if st.traj.done:
                st.traj = None
                self._snap(st)
            return
        run = st.long
        if run is not None:
            if isinstance(run, _Speed) and run.dim != "distance":
                te = run.end_time()
                a, b = t0, min(t1, te)
                dist = 0.0
                if b > a:
                    m = (a + b) / 2
                    dist = (b - a) / 6 * (run.speed(a, st) + 4 * run.speed(m, st) + run.speed(b, st))
                if t1 >= te - EPS:
                    run.done = True
                    dist += run.vt * max(t1 - te, 0.0)
                    v = run.vt
                else:
                    v = run.speed(t1, st)
            elif isinstance(run, _Synchronize):
                dist, v = run.advance(t0, t1, st)
            else:                        # distance-based: sub-steps
                n = 8
                dist, v = 0.0, st.v
                for k in range(n):
                    v0 = v
                    v = max(run.speed(t0 + (k + 1) * h / n, st), 0.0)
                    d = (v0 + v) / 2 * h / n
                    dist += d
                    st.odometer += d
                st.odometer -= dist      # added once below
                if isinstance(run, _Speed) and st.odometer + dist - run.odo0 >= run.T - EPS:
                    run.done, v = True, run.vt
            st.v = max(v, 0.0)
            if run.done:
                st.long = None
        else:
            dist = st.v * h
        self._move(st, max(dist, 0.0), t1)

    def _move(self, st: EntityState, dist: float, t1: float) -> None:
        st.odometer += dist
        g = self.graph
        if st.lane < 0:
            st.x += dist * math.cos(st.yaw)
            st.y += dist * math.sin(st.yaw)
            return
        st.s += dist
        while st.s > g.length[st.lane]:
            nxt = st.plan.pop(0) if st.plan and st.plan[0] in g.succ[st.lane] else \
                (g.car_successors(st.lane) or [None])[0]
            if nxt is None:
                x, y, yaw = g.geoms[st.lane].pose2d(g.length[st.lane], st.offset)
                extra = st.s - g.length[st.lane]
                st.lane = -1
                st.x, st.y, st.yaw = x + extra * math.cos(yaw), y + extra * math.sin(yaw), yaw
                return
            st.s -= g.length[st.lane]
            st.lane = nxt
        lat = st.lat
        old = st.offset
        if lat is not None:
            st.offset = lat.offset(t1, st)
            if lat.done:
                st.lat = None
        x, y, yaw = g.geoms[st.lane].pose2d(st.s, st.offset)
        st.z = float(g.geoms[st.lane].point(st.s)[2])
        if dist > 1e-9:                  # heading includes the lateral motion
            yaw += math.atan2(st.offset - old, dist)
        st.x, st.y, st.yaw = x, y, _wrap(yaw)

    # ---- conditions
    def _entity(self, name: str) -> EntityState:
        return self.state_of(name)

    def _cond_value(self, c: R.Condition, t: float) -> bool:
        p, k = c.params, c.kind
        if k == "SimulationTimeCondition":
            return _compare(t, p.get("rule", "greaterThan"), p["value"])
        if k == "StoryboardElementStateCondition":
            name, state = p.get("storyboardElementRef", ""), p.get("state", "")
            if state.endswith("Transition"):
                return (name, state) in self._transitions[self._window[0]:self._window[1]]
            want = {"runningState": "running", "completeState": "complete",
                    "standbyState": "standby"}.get(state)
            return any(e.state == want for e in self._by_name.get(name, []))
        if k == "ParameterCondition":
            val = self.sc.parameters.get(p.get("parameterRef", ""))
            try:
                return _compare(float(val), p.get("rule", "equalTo"), float(p.get("value")))
            except (TypeError, ValueError):
                return str(val) == str(p.get("value")) if p.get("rule") == "equalTo" else False
        if k.startswith("Unsupported:"):
            return False
        vals = [self._entity_cond(c, self._entity(n)) for n in c.entities]
        return (all(vals) if c.entity_rule == "all" else any(vals)) if vals else False

    def _entity_cond(self, c: R.Condition, st: EntityState) -> bool:
        p, k = c.params, c.kind
        rule, value = p.get("rule", "greaterThan"), p.get("value", 0.0)
        if k == "SpeedCondition":
            return _compare(st.v, rule, value)
        if k == "StandStillCondition":
            return st.still >= p.get("duration", 0.0) if isinstance(p.get("duration"), float) else \
                st.still >= float(p.get("duration", 0.0))
        if k == "TraveledDistanceCondition":
            return st.odometer >= value
        if k in ("ReachPositionCondition", "DistanceCondition"):
            x, y, _, _ = self.pose_of(p["position"], st)
            d = math.hypot(x - st.x, y - st.y)
            return d <= p.get("tolerance", 0.0) if k == "ReachPositionCondition" else _compare(d, rule, value)
        ref = self._entity(p.get("entityRef", ""))
        if k == "RelativeSpeedCondition":
            return _compare(st.v - ref.v, rule, value)
        free = p.get("freespace", "false") == "true"
        lon, lat = self._separation(st, ref, free)
        if k == "RelativeDistanceCondition":
            typ = p.get("relativeDistanceType", "cartesianDistance")
            d = abs(lon) if typ == "longitudinal" else abs(lat) if typ == "lateral" else math.hypot(lon, lat)
            return _compare(d, rule, value)
        if k == "TimeHeadwayCondition":
            longitudinal = p.get("alongRoute", "false") == "true" or \
                p.get("relativeDistanceType", "") == "longitudinal"
            if lon <= 0:
                return False
            d = lon if longitudinal else math.hypot(lon, lat)
            return st.v > 0 and _compare(d / st.v, rule, value)
        if k == "TimeToCollisionCondition":
            rx, ry = ref.x - st.x, ref.y - st.y
            dist = math.hypot(rx, ry)
            if dist < 1e-9:
                return _compare(0.0, rule, value)
            ux, uy = rx / dist, ry / dist
            closing = st.v * (math.cos(st.yaw) * ux + math.sin(st.yaw) * uy) - \
                ref.v * (math.cos(ref.yaw) * ux + math.sin(ref.yaw) * uy)
            if closing <= 0:
                return False
            gap = math.hypot(lon, lat) if free else dist
            return _compare(gap / closing, rule, value)
        return False

    def _centre(self, st: EntityState):
        cx = st.entity.center[0]
        return st.x + cx * math.cos(st.yaw), st.y + cx * math.sin(st.yaw)

    def _separation(self, st: EntityState, ref: EntityState, free: bool):
        """(longitudinal, lateral) of ``ref`` in ``st``'s frame (reference points; with
        ``free`` the gaps between the bounding boxes)."""
        if free:
            (ax, ay), (bx, by) = self._centre(st), self._centre(ref)
        else:
            ax, ay, bx, by = st.x, st.y, ref.x, ref.y
        c, s = math.cos(st.yaw), math.sin(st.yaw)
        dx, dy = bx - ax, by - ay
        lon, lat = c * dx + s * dy, -s * dx + c * dy
        if free:
            rel = ref.yaw - st.yaw
            hl = (st.entity.length + abs(math.cos(rel)) * ref.entity.length + abs(math.sin(rel)) * ref.entity.width) / 2
            hw = (st.entity.width + abs(math.sin(rel)) * ref.entity.length + abs(math.cos(rel)) * ref.entity.width) / 2
            lon = math.copysign(max(abs(lon) - hl, 0.0), lon)
            lat = math.copysign(max(abs(lat) - hw, 0.0), lat)
        return lon, lat

    def _condition(self, c: R.Condition, t: float) -> bool:
        cs = self._cond.setdefault(id(c), _CondState())
        raw = self._cond_value(c, t)
        prev, cs.prev = cs.prev, raw
        if c.edge == "none":
            val = raw
        elif prev is None:
            val = False
        elif c.edge == "rising":
            val = raw and not prev
        elif c.edge == "falling":
            val = prev and not raw
        else:
            val = raw != prev
        if c.delay <= 0:
            return val
        cs.hist.append((t, val))
        target = t - c.delay + 1e-6
        while len(cs.hist) > 1 and cs.hist[1][0] <= target:
            cs.hist.popleft()
        return cs.hist[0][0] <= target and cs.hist[0][1]

    def _trigger(self, trig: R.Trigger | None, t: float) -> bool:
        if trig is None:
            return True
        # every condition is evaluated each time (edges and delays need their history)
        results = [[self._condition(c, t) for c in g] for g in trig.groups]
        return any(all(r) for r in results if r)

    # ---- storyboard
    def _transition(self, e: _Element, state: str, transition: str) -> None:
        e.state = state
        self._transitions.append((e.name, transition))

    def _evaluate(self, t: float) -> None:
        self._window = (self._mark, len(self._transitions))
        self._mark = len(self._transitions)
        if self.sc.stop is not None and not self.finished and self._trigger(self.sc.stop, t):
            self.finished = True
        if self.finished:
            return
        for ae, groups in self._acts:
            act = ae.obj
            if ae.state == "standby" and self._trigger(act.start, t):
                self._transition(ae, "running", "startTransition")
                for ge, _ in groups:
                    self._transition(ge, "running", "startTransition")
            if ae.state != "running":
                continue
            if act.stop is not None and self._trigger(act.stop, t):
                self._stop_act(ae, groups)
                continue
            for ge, mans in groups:
                if ge.state != "running":
                    continue
                for me, evs in mans:
                    if me.state == "standby":
                        self._transition(me, "running", "startTransition")
                    if me.state != "running":
                        continue
                    for ee, aes in evs:
                        if ee.state != "standby":
                            continue
                        if not self._trigger(ee.obj.start, t):
                            continue
                        running = [x for x, _ in evs if x.state == "running"]
                        if ee.obj.priority == "skip" and running:
                            continue
                        if ee.obj.priority in ("overwrite", "override"):
                            for x, xa in evs:
                                if x.state == "running":
                                    self._end_event(x, xa, "stopTransition")
                        self._start_event(ee, aes, ge.obj.actors, t)

    def _start_event(self, ee: _Element, aes, actors, t: float) -> None:
        self._transition(ee, "running", "startTransition")
        ee.runs += 1
        for xe in aes:
            self._transition(xe, "running", "startTransition")
            pa = xe.obj
            runs = []
            for who in (actors if pa.actor is None else [pa.actor]):
                if who == self.ego:
                    self.ego_actions.append((t, pa.action))
                    if not self.drive_ego:
                        continue
                r = self._start_action(self.state_of(who), pa.action, t)
                if r is not None:
                    runs.append(r)
            xe.runs_ = runs
            if not runs:
                self._transition(xe, "complete", "endTransition")

    def _end_event(self, ee, aes, transition="endTransition") -> None:
        for xe in aes:
            if xe.state == "running":
                for r in getattr(xe, "runs_", []):
                    r.done = True
                self._transition(xe, "complete", transition)
        if ee.runs < ee.obj.max_executions and transition == "endTransition":
            self._transition(ee, "standby", transition)   # may run again
        else:
            self._transition(ee, "complete", transition)

    def _stop_act(self, ae, groups) -> None:
        for ge, mans in groups:
            for me, evs in mans:
                for ee, aes in evs:
                    if ee.state == "running":
                        self._end_event(ee, aes, "stopTransition")
                    ee.state = "complete"
                if me.state != "complete":
                    self._transition(me, "complete", "stopTransition")
            if ge.state != "complete":
                self._transition(ge, "complete", "stopTransition")
        self._transition(ae, "complete", "stopTransition")

    def _completions(self) -> None:
        for ae, groups in self._acts:
            if ae.state != "running":
                continue
            for ge, mans in groups:
                if ge.state != "running":
                    continue
                for me, evs in mans:
                    for ee, aes in evs:
                        if ee.state == "running":
                            for xe in aes:
                                if xe.state == "running" and all(r.done for r in xe.runs_):
                                    self._transition(xe, "complete", "endTransition")
                            if all(xe.state == "complete" for xe in aes):
                                self._end_event(ee, aes)
                    if me.state == "running" and all(ee.state == "complete" for ee, _ in evs):
                        self._transition(me, "complete", "endTransition")
                if all(me.state == "complete" for me, _ in mans):
                    ge.runs += 1
                    if ge.runs < ge.obj.max_executions:
                        for me, evs in mans:
                            me.state = "standby"
                            for ee, aes in evs:
                                ee.state, ee.runs = "standby", 0
                        self._transition(ge, "running", "startTransition")
                    else:
                        self._transition(ge, "complete", "endTransition")
            if all(ge.state == "complete" for ge, _ in groups):
                self._transition(ae, "complete", "endTransition")

    @property
    def completed(self) -> bool:
        """Every act of every story is complete."""
        return all(ae.state == "complete" for ae, _ in self._acts)

    # ---- stepping
    def step(self, t: float, ego_state) -> dict:
        """Advance to time ``t`` with the ego at ``ego_state`` = (x, y, yaw, speed); the
        non-ego entities' (x, y, z, yaw, speed) at ``t``."""
        if t < self.t - EPS:
            raise InputError(f"scenario player: time {t} is before the last step {self.t}")
        t0, self.t = self.t, float(t)
        self.before = {n: (st.x, st.y, st.yaw, st.v) for n, st in self.states.items()}
        for name, st in self.states.items():
            if name == self.ego and not self.drive_ego:
                continue
            self._advance(st, t0, self.t)
            st.still = st.still + (self.t - t0) if st.v < 1e-3 else 0.0
        if self.ego in self.states and ego_state is not None and not self.drive_ego:
            e = self.states[self.ego]
            x, y, yaw, v = (float(q) for q in ego_state[:4])
            e.odometer += math.hypot(x - e.x, y - e.y)
            e.still = e.still + (self.t - t0) if v < 1e-3 else 0.0
            e.x, e.y, e.yaw, e.v = x, y, yaw, v
            e.lane = -1
            self._snap(e)
        self._completions()
        self._evaluate(self.t)
        return self.poses()

    def poses(self) -> dict:
        return {n: (st.x, st.y, st.z, st.yaw, st.v) for n, st in self.states.items() if n != self.ego}

    def ego_pose(self) -> tuple:
        """The ego's (x, y, z, yaw, speed) now (its reference point)."""
        e = self.states[self.ego]
        return e.x, e.y, e.z, e.yaw, e.v

    def _warn(self, where: str, what: str) -> None:
        if (where, what) in self.warned:
            return
        self.warned.add((where, what))
        warnings.warn(f"{where}: <{what}> is not supported by the player; ignored",
                      R.ScenarioWarning, stacklevel=3)
