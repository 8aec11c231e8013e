"""Policies that drive `DriveEnv`: a callable ``policy(obs, info) -> action``.

- ``planner``: a privileged rule-based driver. It follows the route with pure pursuit and
  sets its speed with IDM (the traffic model's own parameters) against the nearest of: the
  vehicle ahead on its lane and route, any agent whose box lies in its path within the
  horizon, a crossing agent whose constant-velocity path cuts the route ahead within 3 s,
  a junction it holds no reservation for and an occupied crosswalk (both from the traffic
  model's rules, ``info["stop_distance_m"]``), a stop sign's line, a yellow or red light's
  stop point (``info["red_light_m"]``) unless it cannot stop before it (at COMFORT_BRAKE for
  a yellow, at its braking limit for a red: then it goes through, once), and the end of the
  route.
- ``constant``: keeps its start speed (the route's first lane's limit when it starts still)
  along its start heading: no steering, no braking.
- ``scenario``: no driver: the scenario's storyboard drives the ego with its own actions
  (the env made with ``ego_driver="scenario"``, which ignores the action; esmini plays a
  scenario so without an external driver).
- ``MODULE:CALLABLE``: any importable callable with the same signature (a factory taking
  the env is called first when it is a class or carries ``make_policy``).

Every policy can answer in either action mode: ``control`` (acceleration, steering angle)
or ``trajectory`` (waypoints in the ego frame).
"""
from __future__ import annotations

import importlib
import math

import numpy as np

from lsd3d_usd.actors.traffic import IDMParams
from lsd3d_usd.errors import InputError
from lsd3d_usd.sim.control import TrackerGains, pure_pursuit
from lsd3d_usd.sim.metrics import AgentBox

POLICIES = ("planner", "constant", "scenario")
p_end_overrun = 1.0        # m: the planner aims its front this far past the route's end
JERK = 4.0                 # m/s^3 the planner's acceleration changes by at most ...
COMFORT_BRAKE = 3.0        # ... unless it must brake harder than this (m/s^2)
PATH_HALF_WIDTH = 1.4       # m: an agent's box nearer than this to the route is in the path


def _nearest_on(R: np.ndarray, ds: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance, route distance) of each point Q (m, 2) to the polyline R (n, 2) whose
    vertices lie at route distances ``ds`` (a 1 m sampling of the route ahead)."""
    A, B = R[:-1], R[1:]
    d = B - A
    dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
    f = np.clip(np.einsum("mij,ij->mi", Q[:, None, :] - A[None], d) / dd, 0.0, 1.0)   # (m, n)
    X = A[None] + f[..., None] * d[None]
    dist2 = np.einsum("mij,mij->mi", Q[:, None, :] - X, Q[:, None, :] - X)
    k = np.argmin(dist2, axis=1)
    m = np.arange(len(Q))
    return np.sqrt(dist2[m, k]), ds[:-1][k] + f[m, k] * (ds[1:][k] - ds[:-1][k])


class Planner:
    """The privileged planner (module doc)."""

    def __init__(self, env, idm: IDMParams = IDMParams(), horizon: float = 60.0,
                 speed_factor: float = 0.9):
        self.env = env
        self.p = idm
        self.horizon = horizon
        self.speed_factor = speed_factor
        self.gains = TrackerGains()
        self.through = None       # route distance of a light it decided to go through

    def _obstacle_gap(self, info) -> tuple[float, float]:
        """(bumper gap, speed along the route) of the nearest obstacle in the ego's path."""
        env = self.env
        route, ego, lim = env.route, env.ego, env.limits
        d_ego = env.world.ego_d
        front = lim.length / 2
        best = (math.inf, 0.0)
        gap, v_lead = info["leader_gap_m"], info["leader_speed"]
        if math.isfinite(gap):
            best = (gap, v_lead)
        stop = info["stop_distance_m"]
        if math.isfinite(stop) and stop < best[0]:
            best = (stop, 0.0)
        sign = info.get("stop_sign_m", math.inf)     # come to rest at a stop sign's line
        if math.isfinite(sign) and sign + 0.5 < best[0]:
            best = (sign + 0.5, 0.0)
        red = info.get("red_light_m", math.inf)
        if math.isfinite(red) and red < best[0] and self._stops_at_light(red, info):
            best = (red, 0.0)
        end = route.length - d_ego - front + p_end_overrun
        if end < best[0]:
            best = (end, 0.0)
        heading = route.heading(d_ego)
        boxes = [b for b in map(AgentBox.from_json, info["boxes"])
                 if abs(b.center[0] - ego.x) < self.horizon + 10
                 and abs(b.center[1] - ego.y) < self.horizon + 10]
        if not boxes:
            return best
        # every box, and every crossing agent's straight path over 3 s, against the route
        # ahead as one array of segments (a box in the path; a path cutting it first)
        lo = max(d_ego - 10.0, 0.0)
        ds = np.arange(lo, min(d_ego + self.horizon + 10.0, route.length) + 1.0, 1.0)
        R = route.points(ds)[:, :2]
        taus = np.arange(0.0, 3.01, 0.25)
        C = np.array([b.center for b in boxes], np.float64)
        V = np.array([b.velocity for b in boxes], np.float64)
        half = np.array([0.5 * b.width if b.kind != "pedestrian" else 0.5 for b in boxes])
        blen = np.array([b.length for b in boxes])
        P = C[:, None, :] + V[:, None, :] * taus[None, :, None]          # (n, T, 2)
        dist, along = _nearest_on(R, ds, P.reshape(-1, 2))
        dist, along = dist.reshape(P.shape[:2]), along.reshape(P.shape[:2])
        ahead = along - d_ego
        speed = np.hypot(V[:, 0], V[:, 1])
        u = np.array([math.cos(heading), math.sin(heading)])
        for k in range(len(boxes)):
            inpath = (0.0 < ahead[k] ) & (ahead[k] < self.horizon) & (dist[k] < PATH_HALF_WIDTH + half[k])
            if inpath[0]:                       # in the path now
                g = ahead[k, 0] - front - 0.5 * blen[k]
                if g < best[0]:
                    best = (g, max(float(V[k] @ u), 0.0))
                continue
            if speed[k] < 0.3 or ahead[k, 0] < -5.0 or not inpath.any():
                continue
            j = int(np.argmax(inpath))          # it reaches the path after taus[j] s ...
            a2 = ahead[k, j]
            t_ego = (a2 - front) / max(ego.v, 0.5)
            if taus[j] <= t_ego + 1.0:          # ... before the ego's front does: yield
                g = a2 - front - 1.0
                if g < best[0]:
                    best = (g, 0.0)
        return best

    def _stops_at_light(self, red: float, info) -> bool:
        """Stop for the yellow or red light ``red`` m ahead: unless the deceleration that
        takes exceeds COMFORT_BRAKE (yellow) or the IDM's braking limit (red); a light it
        goes through is not looked at again until the ego is past it or it turns green."""
        env = self.env
        at = env.world.ego_d + env.limits.length / 2 + red        # its route distance
        if self.through is not None and abs(self.through - at) < 1.0:
            return False
        limit = self.p.b_max if info.get("signal") == "red" else COMFORT_BRAKE
        if env.ego.v ** 2 / (2.0 * max(red, 0.01)) > limit:
            self.through = at
            return False
        return True

    def _target_speed(self, d: float) -> float:
        g = self.env.route.graph
        j, s = self.env.route.locate(d)
        lim = g.limit[self.env.route.idx[j]]
        # the next lane's limit within braking distance
        rem = g.length[self.env.route.idx[j]] - s
        if j + 1 < len(self.env.route.idx):
            nxt = g.limit[self.env.route.idx[j + 1]]
            if nxt < lim and rem < self.env.ego.v ** 2 / (2 * self.p.b) + 10.0:
                lim = nxt
        # curvature: keep the lateral acceleration comfortable on the path ahead
        ahead = max(8.0, self.env.ego.v * 2.0)
        h0, h1 = self.env.route.heading(d), self.env.route.heading(d + ahead)
        kappa = abs(math.remainder(h1 - h0, 2 * math.pi)) / ahead
        if kappa > 1e-4:
            lim = min(lim, math.sqrt(2.5 / kappa))
        return self.speed_factor * lim

    def acceleration(self, info) -> float:
        p, v = self.p, self.env.ego.v
        v0 = max(self._target_speed(self.env.world.ego_d), 0.1)
        gap, v_lead = self._obstacle_gap(info)
        free = p.a_max * (1.0 - (v / v0) ** p.delta)
        if not math.isfinite(gap):
            return free
        if gap <= 0.2:
            return -p.b_max
        s_star = p.s0 + max(0.0, v * p.T + v * (v - v_lead) / (2.0 * math.sqrt(p.a_max * p.b)))
        return max(p.a_max * (1.0 - (v / v0) ** p.delta - (s_star / max(gap, 0.01)) ** 2), -p.b_max)

    def steering(self) -> float:
        env = self.env
        ego, lim = env.ego, env.limits
        d = env.world.ego_d - lim.box_offset         # the route at the rear axle
        pts = env.route.points(d + np.arange(0.0, 40.0, 1.0))[:, :2]
        M = ego.matrix()
        local = (pts - M[:2, 3]) @ M[:2, :2]
        local = local[local[:, 0] > -0.5]
        if len(local) < 2:
            return 0.0
        return pure_pursuit(np.vstack([[0.0, 0.0], local]), ego.v, lim.wheelbase, self.gains)

    def __call__(self, obs, info):
        env = self.env
        if env.k == 0:
            self.through = None
        if info.get("signal") == "green" and not math.isfinite(info.get("red_light_m", math.inf)):
            self.through = None
        a = self.acceleration(info)
        if env.k == 0:
            self.a_prev = 0.0
        # comfort: the acceleration changes at most JERK m/s^3, except to brake hard
        step = JERK / env.settings.hz
        if a > -COMFORT_BRAKE:
            a = min(max(a, self.a_prev - step), self.a_prev + step)
        self.a_prev = a
        if env.settings.action == "control":
            steer = self.steering()
            if env.settings.steer == "rate":
                steer = (steer - env.ego.delta) * env.settings.hz
            return np.array([a, steer], np.float32)
        return self._waypoints(a)

    def _waypoints(self, a: float) -> np.ndarray:
        """The route ahead at the speed profile v + a t (no reversing), in the ego frame."""
        env = self.env
        s = env.settings
        v, d = env.ego.v, env.world.ego_d - env.limits.box_offset
        M = env.ego.matrix()
        out = []
        for k in range(1, s.waypoints + 1):
            t = k * s.waypoint_spacing
            stop_t = v / -a if a < 0 else math.inf
            tt = min(t, stop_t)
            dist = max(v * tt + 0.5 * a * tt * tt, 0.0)
            p = env.route.point(d + dist)[:2]
            out.append((p - M[:2, 3]) @ M[:2, :2])
        return np.asarray(out, np.float32)


class Constant:
    """Constant velocity along the start heading (module doc)."""

    def __init__(self, env):
        self.env = env
        self.v = None

    def __call__(self, obs, info):
        env = self.env
        if self.v is None or env.k == 0:
            g = env.route.graph
            self.v = env.ego.v if env.ego.v > 0.5 else 0.9 * float(g.limit[env.route.idx[0]])
        if env.settings.action == "control":
            # reach the speed, then hold it; the wheels stay straight
            a = np.clip((self.v - env.ego.v) * env.settings.hz, env.limits.a_min, env.limits.a_max)
            return np.array([a, 0.0], np.float32)
        s = env.settings
        return np.array([[self.v * k * s.waypoint_spacing, 0.0] for k in range(1, s.waypoints + 1)],
                        np.float32)


class ScenarioEgo:
    """The storyboard drives (module doc): a zero action of the env's action space."""

    def __init__(self, env):
        if getattr(env.settings, "ego_driver", "policy") != "scenario":
            raise InputError("--policy scenario: the env must be made with a scenario and "
                             "ego_driver='scenario' (sim run --scenario FILE --policy scenario)")
        self.action = np.zeros(env.action_space.shape, np.float32)

    def __call__(self, obs, info):
        return self.action


def load_policy(spec: str, env):
    """A policy for ``env``: "planner", "constant", "scenario" or "MODULE:CALLABLE". A class,
    or a callable with ``make_policy``, is called with the env to make the policy."""
    if spec == "planner":
        return Planner(env)
    if spec == "constant":
        return Constant(env)
    if spec == "scenario":
        return ScenarioEgo(env)
    mod, _, attr = str(spec).partition(":")
    if not mod or not attr:
        raise InputError(f"--policy {spec!r}: choose {', '.join(POLICIES)} or MODULE:CALLABLE")
    try:
        obj = importlib.import_module(mod)
    except Exception as e:       # the module's own import error, in one line
        raise InputError(f"--policy {spec!r}: cannot import {mod!r} ({type(e).__name__}: {e})") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise InputError(f"--policy {spec!r}: module {mod!r} has no {attr!r}")
        obj = getattr(obj, part)
    if isinstance(obj, type) or hasattr(obj, "make_policy"):
        maker = obj.make_policy if hasattr(obj, "make_policy") else obj
        try:
            obj = maker(env)
        except Exception as e:
            raise InputError(f"--policy {spec!r}: making the policy failed ({type(e).__name__}: {e})") from None
    if not callable(obj):
        raise InputError(f"--policy {spec!r}: {attr!r} is not callable")
    return obj
