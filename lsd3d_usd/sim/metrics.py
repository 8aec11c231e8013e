"""Driving scores of a closed-loop episode: arrays in, numbers out (float64; no USD).

Per step, `ScoreKeeper.update(StepState)` gives the instantaneous scores (a JSON-ready dict
for the env's ``info``); per episode, `ScoreKeeper.summary()` aggregates them. Definitions
and sources: docs/sim.md, section "Driving scores". In short:

- NC (no at-fault collision, nuPlan/NAVSIM): 0 for an at-fault contact with a vehicle,
  cyclist or pedestrian, 0.5 with a static object, else 1. A contact is classified once,
  at its first step, by nuPlan's rule: ego stopped -> not at fault; other stopped (static
  objects always) -> at fault; other behind the ego -> not at fault; other touching the
  ego's front edge -> at fault; else lateral, at fault only when the ego is off the
  drivable area or across lanes.
- DAC: all four ego corners in the drivable area. DDC (NAVSIM v2): distance driven
  against traffic over the last 1 s: < 2 m -> 1, < 6 m -> 0.5, else 0.
- TTC (NAVSIM): 0 when the ego and an agent, both projected at constant velocity over
  0..1 s in 0.1 s steps, overlap while the agent is ahead (or not behind when the ego is
  off-road, across lanes or in a junction); the ego stopped (< 5 mm/s) is never at risk.
- Comfort: NAVSIM's bounds on the ego's causal finite-difference kinematics.
- EP: ego progress along the route / reference progress, clipped to [0, 1], 1 when both
  are under 5 m. RC: the largest route progress reached / route length.
- Composites: PDMS (NAVSIM v1), HUGSIM's HD-Score, CARLA's Driving Score.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import shapely

from lsd3d_usd.errors import InputError
from lsd3d_usd.sim.geometry2d import (box_corners, box_inside, boxes_overlap, polygon_tree,
                                      relative_angle)

KINDS = ("vehicle", "pedestrian", "cyclist")

#: NAVSIM's comfort bounds (pdm_comfort_metrics.py), inclusive here: (min, max).
COMFORT_BOUNDS = {
    "lon_acc": (-4.05, 2.40),      # m/s^2
    "lat_acc": (-4.89, 4.89),      # m/s^2
    "jerk": (-8.37, 8.37),         # m/s^3, of the acceleration magnitude
    "yaw_rate": (-0.95, 0.95),     # rad/s
    "yaw_acc": (-1.93, 1.93),      # rad/s^2
}
#: NAVSIM also bounds the longitudinal jerk (4.13 m/s^3); reported, not applied (issue 55).
NAVSIM_MAX_LON_JERK = 4.13

#: CARLA leaderboard infraction coefficients (the Driving Score multiplies one per event).
CARLA_PENALTIES = {
    "collision_pedestrian": 0.50,
    "collision_vehicle": 0.60,
    "collision_static": 0.65,
    "red_light": 0.70,
    "stop_sign": 0.80,
}

STOPPED_SPEED = 0.05        # m/s: nuPlan's collision classification (ego and track)
TTC_STOPPED_SPEED = 5e-3    # m/s: NAVSIM's TTC skips a stopped ego
TTC_HORIZON = 1.0           # s
TTC_STEP = 0.1              # s
AHEAD_DEG = 30.0            # nuPlan is_agent_ahead
BEHIND_DEG = 150.0          # nuPlan is_agent_behind
DDC_HORIZON = 1.0           # s
DDC_COMPLIANT = 2.0         # m
DDC_VIOLATION = 6.0         # m
EP_MIN_PROGRESS = 5.0       # m
PDMS_WEIGHTS = {"ttc": 5.0, "comfort": 2.0, "ep": 5.0}
HUGSIM_WEIGHTS = {"ttc": 5.0, "comfort": 2.0}


def _f64(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


@dataclass(frozen=True)
class AgentBox:
    """One agent's ground footprint at a step: ``info["boxes"]`` holds ``to_json()`` of each
    (plain dicts: the Gymnasium info crosses processes in sim.remote and users index it);
    the sim's own readers (policies, episodes, record) read it back with `from_json`."""
    id: str                         # vehicle:k, cyclist:k, pedestrian:k, parked:<prim path>
    kind: str                       # in KINDS
    center: tuple[float, float]     # m
    yaw: float                      # rad
    length: float                   # m
    width: float                    # m
    velocity: tuple[float, float]   # m/s

    def to_json(self) -> dict:
        return {"id": self.id, "kind": self.kind, "center": list(self.center), "yaw": self.yaw,
                "length": self.length, "width": self.width, "velocity": list(self.velocity)}

    @classmethod
    def from_json(cls, d: dict) -> "AgentBox":
        return cls(d["id"], d["kind"], tuple(d["center"]), d["yaw"], d["length"], d["width"],
                   tuple(d["velocity"]))


@dataclass
class Agents:
    """Other agents at one step: N boxes with velocities, kinds and stable ids."""
    ids: Sequence[Any]
    xy: np.ndarray                 # (N, 2) centre, m
    yaw: np.ndarray                # (N,) rad
    length: np.ndarray             # (N,) m
    width: np.ndarray              # (N,) m
    velocity: np.ndarray           # (N, 2) m/s
    kind: Sequence[str]            # (N,) in KINDS

    def __post_init__(self):
        self.xy = _f64(self.xy).reshape(-1, 2)
        n = len(self.xy)
        self.yaw = _f64(self.yaw).reshape(-1)
        self.length = _f64(self.length).reshape(-1)
        self.width = _f64(self.width).reshape(-1)
        self.velocity = _f64(self.velocity).reshape(-1, 2)
        self.ids = list(self.ids)
        self.kind = [str(k) for k in self.kind]
        sizes = {len(self.ids), len(self.yaw), len(self.length), len(self.width),
                 len(self.velocity), len(self.kind)}
        if sizes != {n}:
            raise InputError(f"agents: arrays of different lengths ({n} centres, "
                             f"{sorted(sizes)})")
        bad = sorted(set(self.kind) - set(KINDS))
        if bad:
            raise InputError(f"agents: unknown kind {bad[0]!r} (expected one of {KINDS})")

    def __len__(self) -> int:
        return len(self.xy)

    def boxes(self) -> list[AgentBox]:
        return [AgentBox(str(self.ids[i]), self.kind[i], tuple(self.xy[i].tolist()),
                         float(self.yaw[i]), float(self.length[i]), float(self.width[i]),
                         tuple(self.velocity[i].tolist())) for i in range(len(self))]

    @classmethod
    def empty(cls) -> "Agents":
        z = np.zeros(0)
        return cls([], np.zeros((0, 2)), z, z, z, np.zeros((0, 2)), [])


@dataclass
class StepState:
    """The ego and the world at one step. Progress is metres along the route (projected
    when None); the flags are the env's: ``wrong_way`` the ego's centre is in a lane of the
    other direction, ``red_light`` / ``stop_sign`` the ego is running one (a run of True
    steps is one event), ``multiple_lanes`` / ``in_junction`` for the fault and TTC rules.
    ``lon_acc`` / ``lat_acc`` when the dynamics know them (else finite differences)."""
    t: float
    xy: np.ndarray
    yaw: float
    speed: float
    length: float
    width: float
    agents: Agents | None = None
    progress: float | None = None
    wrong_way: bool = False
    red_light: bool = False
    stop_sign: bool = False
    multiple_lanes: bool = False
    in_junction: bool = False
    lon_acc: float | None = None
    lat_acc: float | None = None


class _Kinematics:
    """Causal finite differences of the ego's pose series, one sample at a time.

    First derivatives (yaw rate, longitudinal acceleration) are defined from the second
    sample, second derivatives (yaw acceleration, jerk) from the third; before that 0.
    """

    def __init__(self):
        self.t = self.yaw = self.speed = None
        self.yaw_rate = self.acc = self.lon_acc = None   # None: not yet defined

    def __call__(self, t: float, yaw: float, speed: float, lon_acc=None, lat_acc=None):
        out = dict.fromkeys(("lon_acc", "lat_acc", "jerk", "lon_jerk", "yaw_rate",
                             "yaw_acc"), 0.0)
        if self.t is None:
            yaw_u, yaw_rate, dt = float(yaw), None, None
        else:
            dt = float(t) - self.t
            if not dt > 0:
                raise InputError(f"sim metrics: time must increase (t={t} after {self.t})")
            yaw_u = self.yaw + (float(yaw) - self.yaw + math.pi) % (2 * math.pi) - math.pi
            yaw_rate = (yaw_u - self.yaw) / dt
        lon = lon_acc if lon_acc is not None else (
            None if dt is None else (float(speed) - self.speed) / dt)
        lat = lat_acc if lat_acc is not None else (
            None if yaw_rate is None else float(speed) * yaw_rate)
        acc = None if lon is None or lat is None else math.hypot(lon, lat)
        if yaw_rate is not None:
            out["yaw_rate"] = yaw_rate
            if self.yaw_rate is not None:
                out["yaw_acc"] = (yaw_rate - self.yaw_rate) / dt
        if lon is not None:
            out["lon_acc"] = float(lon)
            if self.lon_acc is not None and dt is not None:
                out["lon_jerk"] = (lon - self.lon_acc) / dt
        if lat is not None:
            out["lat_acc"] = float(lat)
        if acc is not None and self.acc is not None and dt is not None:
            out["jerk"] = (acc - self.acc) / dt
        self.t, self.yaw, self.speed = float(t), yaw_u, float(speed)
        self.yaw_rate, self.lon_acc, self.acc = yaw_rate, lon, acc
        return out


def ego_kinematics(t, xy, yaw, speed=None) -> dict[str, np.ndarray]:
    """Longitudinal / lateral acceleration, jerk (of the acceleration magnitude),
    longitudinal jerk, yaw rate and yaw acceleration of a pose series, by causal finite
    differences (the values `ScoreKeeper` reports per step). ``speed`` None: from xy."""
    t = _f64(t).reshape(-1)
    xy = _f64(xy).reshape(-1, 2)
    yaw = _f64(yaw).reshape(-1)
    if speed is None:
        speed = np.zeros(len(t))
        if len(t) > 1:
            speed[1:] = np.hypot(*np.diff(xy, axis=0).T) / np.diff(t)
            speed[0] = speed[1]
    speed = _f64(speed).reshape(-1)
    if not len(t) == len(xy) == len(yaw) == len(speed):
        raise InputError("ego_kinematics: t, xy, yaw and speed differ in length")
    k = _Kinematics()
    rows = [k(t[i], yaw[i], speed[i]) for i in range(len(t))]
    keys = ("lon_acc", "lat_acc", "jerk", "lon_jerk", "yaw_rate", "yaw_acc")
    return {key: np.array([r[key] for r in rows], dtype=np.float64) for key in keys}


def comfort_failures(kin: dict, bounds: dict = COMFORT_BOUNDS) -> list[str]:
    """Names of the kinematic quantities outside their bounds (empty: comfort held)."""
    return [k for k, (lo, hi) in bounds.items() if not lo <= float(kin[k]) <= hi]


def collision_type(ego_xy, ego_yaw, ego_speed, ego_length, ego_width,
                   other_xy, other_yaw, other_length, other_width, other_speed,
                   static: bool = False) -> str:
    """nuPlan's classification of a contact: stopped_ego, stopped_track, active_rear,
    active_front or active_lateral."""
    if abs(float(ego_speed)) <= STOPPED_SPEED:
        return "stopped_ego"
    if static or abs(float(other_speed)) <= STOPPED_SPEED:
        return "stopped_track"
    if relative_angle(ego_xy, ego_yaw, other_xy) > math.radians(BEHIND_DEG):
        return "active_rear"
    front = _f64(ego_xy) + 0.5 * ego_length * np.array([math.cos(ego_yaw), math.sin(ego_yaw)])
    if boxes_overlap(front, ego_yaw, 0.0, ego_width, other_xy, other_yaw, other_length,
                     other_width):
        return "active_front"
    return "active_lateral"


def at_fault(ctype: str, ego_off_lane: bool) -> bool:
    """NAVSIM's rule: front and stopped-track contacts, and lateral ones when the ego is
    off the drivable area or across lanes, are the ego's fault."""
    return ctype in ("stopped_track", "active_front") or (
        ctype == "active_lateral" and bool(ego_off_lane))


def driving_direction_score(wrong_way_m: float) -> float:
    """NAVSIM v2 DDC from the distance driven against traffic in the last second."""
    if wrong_way_m < DDC_COMPLIANT:
        return 1.0
    return 0.5 if wrong_way_m < DDC_VIOLATION else 0.0


def ego_progress_score(progress: float, reference: float,
                       min_progress: float = EP_MIN_PROGRESS) -> float:
    """EP: ego progress over the larger of (reference, ego) progress, in [0, 1]; 1 when
    both are under ``min_progress`` metres (NAVSIM)."""
    p, r = max(float(progress), 0.0), max(float(reference), 0.0)
    if max(p, r) < min_progress:
        return 1.0
    return p / max(p, r)


def route_completion(progress: float, route_length: float) -> float:
    """RC: route progress (m) over the route's length, clipped to [0, 1]."""
    if route_length <= 0:
        return 1.0
    return float(min(max(progress / route_length, 0.0), 1.0))


def pdms(nc: float, dac: float, ttc: float, comfort: float, ep: float) -> float:
    """NAVSIM v1 PDMS = NC x DAC x (5 TTC + 2 C + 5 EP) / 12 (DDC has weight 0 there)."""
    w = PDMS_WEIGHTS
    return float(nc * dac * (w["ttc"] * ttc + w["comfort"] * comfort + w["ep"] * ep)
                 / sum(w.values()))


def hugsim_step_score(nc: float, dac: float, ttc: float, comfort: float) -> float:
    """HUGSIM's per-frame score NC x DAC x (5 TTC + 2 COM) / 7."""
    w = HUGSIM_WEIGHTS
    return float(nc * dac * (w["ttc"] * ttc + w["comfort"] * comfort) / sum(w.values()))


def hd_score(rc: float, step_scores) -> float:
    """HUGSIM's HD-Score: RC x the mean of the per-frame scores."""
    s = _f64(step_scores).reshape(-1)
    return float(rc * s.mean()) if len(s) else 0.0


def infraction_penalty(counts: dict, penalties: dict = CARLA_PENALTIES) -> float:
    """CARLA's infraction penalty: the product of coefficient^count over the infractions."""
    out = 1.0
    for name, n in counts.items():
        if name not in penalties:
            raise InputError(f"unknown infraction {name!r} (expected one of "
                             f"{sorted(penalties)})")
        out *= penalties[name] ** int(n)
    return float(out)


def carla_driving_score(rc: float, counts: dict) -> float:
    """CARLA leaderboard Driving Score = RC x infraction penalty."""
    return float(rc * infraction_penalty(counts))


def _carla_key(kind: str) -> str:
    return {"pedestrian": "collision_pedestrian", "static": "collision_static"}.get(
        kind, "collision_vehicle")   # cyclists are vehicles in CARLA


@dataclass
class _Episode:
    nc: list = field(default_factory=list)
    dac: list = field(default_factory=list)
    ddc: list = field(default_factory=list)
    ttc: list = field(default_factory=list)
    comfort: list = field(default_factory=list)
    hugsim: list = field(default_factory=list)
    wrong_way_m: list = field(default_factory=list)


class ScoreKeeper:
    """Accumulates the driving scores of one episode, one `StepState` at a time.

    ``route``: the route polyline (K, 2) or a shapely LineString; ``drivable``: a shapely
    geometry of the drivable area (None: DAC always 1); ``obstacles``: static polygons
    (buildings, poles, trunks, signs); ``reference``: the reference planner's progress,
    a float (metres over the episode) or a pair (t, progress) of arrays for per-step EP.
    """

    def __init__(self, route, *, drivable=None, obstacles: Sequence = (),
                 obstacle_ids: Sequence | None = None, route_length: float | None = None,
                 reference=None):
        self.route = route if isinstance(route, shapely.LineString) else \
            shapely.LineString(_f64(route).reshape(-1, 2))
        self.route_length = float(self.route.length if route_length is None
                                  else route_length)
        self.drivable = drivable
        if drivable is not None:
            shapely.prepare(drivable)
        self.obstacles = list(obstacles)
        self.obstacle_ids = (list(obstacle_ids) if obstacle_ids is not None
                             else [f"static:{i}" for i in range(len(self.obstacles))])
        if len(self.obstacle_ids) != len(self.obstacles):
            raise InputError("sim metrics: obstacle_ids and obstacles differ in length")
        self._tree = polygon_tree(self.obstacles) if self.obstacles else None
        self._ref_series = None
        self._ref_total = None
        if reference is not None:
            if np.ndim(reference) == 0:
                self._ref_total = float(reference)
            else:
                rt, rs = (_f64(a).reshape(-1) for a in reference)
                if len(rt) != len(rs) or len(rt) == 0:
                    raise InputError("sim metrics: reference (t, progress) arrays differ "
                                     "in length or are empty")
                self._ref_series = (rt, rs)
        self._kin = _Kinematics()
        self._ep = _Episode()
        self._step = 0
        self._t0 = self._t = None
        self._xy = None
        self._s0 = None
        self._s = 0.0
        self._s_max = -math.inf
        self._contacts: dict = {}        # other id -> its event (ongoing contacts)
        self._events: list = []
        self._window: deque = deque()    # (t, metres against traffic in that step)
        self._red = self._stop = False
        self._counts = {"red_light": 0, "stop_sign": 0}
        self._offroad = 0

    # -- per step ----------------------------------------------------------------------
    def update(self, s: StepState) -> dict:
        """Score one step; returns the per-step values (JSON-serialisable)."""
        xy = _f64(s.xy).reshape(2)
        yaw, speed = float(s.yaw), float(s.speed)
        L, W = float(s.length), float(s.width)
        agents = s.agents if s.agents is not None else Agents.empty()
        t = float(s.t)
        kin = self._kin(t, yaw, speed, s.lon_acc, s.lat_acc)

        # progress, RC, EP
        prog = float(s.progress) if s.progress is not None else \
            float(self.route.project(shapely.Point(xy)))
        if self._s0 is None:
            self._s0, self._t0 = prog, t
        self._s, self._s_max = prog, max(self._s_max, prog)
        rc = route_completion(self._s_max, self.route_length)
        ep = None
        if self._ref_series is not None:
            rt, rs = self._ref_series
            ep = ego_progress_score(prog - self._s0, float(np.interp(t, rt, rs)) - rs[0])

        # DAC
        dac = 1.0
        if self.drivable is not None and not bool(box_inside(self.drivable, xy, yaw, L, W)):
            dac = 0.0
            self._offroad += 1
        off_lane = dac == 0.0 or bool(s.multiple_lanes)

        # DDC: metres against traffic over the last DDC_HORIZON seconds
        step_m = 0.0 if self._xy is None else float(np.hypot(*(xy - self._xy)))
        self._window.append((t, step_m if s.wrong_way else 0.0))
        while self._window and self._window[0][0] < t - DDC_HORIZON - 1e-9:
            self._window.popleft()
        wrong_m = float(sum(m for _, m in self._window))
        ddc = driving_direction_score(wrong_m)

        # contacts and NC
        new_events, nc, contact = self._collisions(xy, yaw, speed, L, W, agents, off_lane, t)

        # TTC
        ttc = self._ttc(xy, yaw, speed, L, W, agents,
                        off_lane or bool(s.in_junction))

        # comfort
        failed = comfort_failures(kin)
        comfort = 0.0 if failed else 1.0

        # signals: a run of True steps is one event
        red_event = bool(s.red_light) and not self._red
        stop_event = bool(s.stop_sign) and not self._stop
        self._red, self._stop = bool(s.red_light), bool(s.stop_sign)
        self._counts["red_light"] += red_event
        self._counts["stop_sign"] += stop_event

        hug = hugsim_step_score(nc, dac, ttc, comfort)
        e = self._ep
        for name, v in (("nc", nc), ("dac", dac), ("ddc", ddc), ("ttc", ttc),
                        ("comfort", comfort), ("hugsim", hug), ("wrong_way_m", wrong_m)):
            getattr(e, name).append(v)
        out = {
            "step": self._step, "t": t, "progress_m": prog, "rc": rc, "ep": ep,
            "nc": nc, "dac": dac, "ddc": ddc, "wrong_way_m": wrong_m, "ttc": ttc,
            "comfort": comfort, "comfort_failed": failed,
            **{k: float(v) for k, v in kin.items()},
            "contact": contact, "at_fault_collision": nc < 1.0,
            "new_collisions": new_events, "red_light": red_event, "stop_sign": stop_event,
            "pdms": None if ep is None else pdms(nc, dac, ttc, comfort, ep),
            "hugsim": hug,
        }
        self._step += 1
        self._t, self._xy = t, xy
        return out

    def _collisions(self, xy, yaw, speed, L, W, agents: Agents, off_lane: bool, t: float):
        current = {}   # id -> (kind, other_xy, other_yaw, other_len, other_wid, speed, static)
        if len(agents):
            hit = np.flatnonzero(boxes_overlap(xy, yaw, L, W, agents.xy, agents.yaw,
                                               agents.length, agents.width))
            for i in hit:
                current[agents.ids[i]] = (agents.kind[i], agents.xy[i], agents.yaw[i],
                                          agents.length[i], agents.width[i],
                                          float(np.hypot(*agents.velocity[i])), False)
        if self._tree is not None:
            ego = shapely.Polygon(box_corners(xy, yaw, L, W)) if L > 0 and W > 0 else \
                shapely.Point(xy)
            for j in self._tree.query(ego, predicate="intersects"):
                c = self.obstacles[j].centroid
                current[self.obstacle_ids[j]] = ("static", np.array([c.x, c.y]), 0.0, 0.0,
                                                 0.0, 0.0, True)
        new_events, nc = [], 1.0
        contacts = {}
        for oid, (kind, oxy, oyaw, olen, owid, ospeed, static) in current.items():
            ev = self._contacts.get(oid)
            if ev is None:
                ctype = collision_type(xy, yaw, speed, L, W, oxy, oyaw, olen, owid, ospeed,
                                       static)
                ev = {"step": self._step, "t": t, "other": str(oid), "kind": kind,
                      "type": ctype, "at_fault": at_fault(ctype, off_lane)}
                self._events.append(ev)
                new_events.append(dict(ev))
            contacts[oid] = ev
            if ev["at_fault"]:
                nc = min(nc, 0.5 if kind == "static" else 0.0)
        self._contacts = contacts
        return new_events, nc, bool(current)

    def _ttc(self, xy, yaw, speed, L, W, agents: Agents, loose: bool) -> float:
        if abs(speed) < TTC_STOPPED_SPEED:
            return 1.0
        times = np.arange(0.0, TTC_HORIZON + 1e-9, TTC_STEP)
        head = np.array([math.cos(yaw), math.sin(yaw)])
        ego_xy = xy + speed * times[:, None] * head                       # (T, 2)
        innocent = {oid for oid, ev in self._contacts.items() if not ev["at_fault"]}
        if len(agents):
            oxy = agents.xy[None] + times[:, None, None] * agents.velocity[None]   # (T, N, 2)
            over = boxes_overlap(ego_xy[:, None], yaw, L, W, oxy, agents.yaw[None],
                                 agents.length[None], agents.width[None]).any(axis=0)
            if over.any():
                ang = relative_angle(xy, yaw, agents.xy)
                ahead = ang < math.radians(AHEAD_DEG)
                behind = ang > math.radians(BEHIND_DEG)
                risky = over & (ahead | (loose & ~behind))
                for i in np.flatnonzero(risky):
                    if agents.ids[i] not in innocent:
                        return 0.0
        if self._tree is not None and L > 0 and W > 0:
            polys = shapely.polygons(box_corners(ego_xy, yaw, L, W))
            pairs = self._tree.query(polys, predicate="intersects")
            if pairs.shape[1] and any(self.obstacle_ids[j] not in innocent
                                      for j in pairs[1]):
                return 0.0
        return 1.0

    # -- per episode -------------------------------------------------------------------
    def summary(self, reference=None) -> dict:
        """Episode scores (JSON-serialisable). ``reference`` overrides the constructor's
        reference progress (metres over the episode) for EP and PDMS."""
        e = self._ep
        n = len(e.nc)
        if n == 0:
            raise InputError("sim metrics: summary() before any update()")
        progress = max(self._s - self._s0, 0.0)
        rc = route_completion(self._s_max, self.route_length)
        ref = reference if reference is not None else self._ref_total
        if ref is None and self._ref_series is not None:
            rt, rs = self._ref_series
            ref = float(np.interp(self._t, rt, rs)) - rs[0]
        ep = None if ref is None else ego_progress_score(progress, ref)
        nc, dac, ddc = min(e.nc), min(e.dac), min(e.ddc)
        ttc, comfort = float(np.mean(e.ttc)), float(np.mean(e.comfort))
        counts = {k: 0 for k in CARLA_PENALTIES}
        counts_all = dict(counts)
        for ev in self._events:
            counts_all[_carla_key(ev["kind"])] += 1
            if ev["at_fault"]:
                counts[_carla_key(ev["kind"])] += 1
        for k in ("red_light", "stop_sign"):
            counts[k] = counts_all[k] = self._counts[k]
        return {
            "steps": n, "duration_s": float(self._t - self._t0),
            "nc": float(nc), "dac": float(dac), "ddc": float(ddc),
            "ttc": ttc, "ttc_all": bool(min(e.ttc) == 1.0),
            "comfort": comfort, "comfort_all": bool(min(e.comfort) == 1.0),
            "ep": ep, "rc": rc, "progress_m": float(progress),
            "route_length_m": self.route_length,
            "max_wrong_way_m": float(max(e.wrong_way_m)), "offroad_steps": self._offroad,
            "pdms": None if ep is None else pdms(nc, dac, ttc, comfort, ep),
            "hd_score": hd_score(rc, e.hugsim),
            "driving_score": carla_driving_score(rc, counts),
            "infraction_penalty": infraction_penalty(counts),
            "driving_score_all_contacts": carla_driving_score(rc, counts_all),
            "infractions": counts,
            "contacts": len(self._events),
            "at_fault_collisions": sum(ev["at_fault"] for ev in self._events),
            "collisions": [dict(ev) for ev in self._events],
        }
