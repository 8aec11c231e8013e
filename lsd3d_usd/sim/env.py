"""`DriveEnv`: a driving stack drives in a generated scene (Gymnasium's Env API).

One step (default 0.1 s): the action moves the ego (controls through the kinematic bicycle
model, or waypoints a pure-pursuit + PI tracker follows); the world (vehicles, cyclists,
pedestrians of actors.street) reacts to the ego's new pose; every sensor of the rig renders
the new instant through views/ with the agents at their simulated poses; the scores are
updated (sim.metrics). The env is a pure function of (scene, settings, seed, actions).

Frames and units: world coordinates are the scene's (metres, Z up). The ego frame is x
forward, y left, z up, origin on the ground at the centre of the rear axle. Angles in
radians, speeds in m/s. docs/sim.md has the observation and action spaces in full.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lsd3d_usd.actors.placement import KIND_WEIGHTS
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import Route, parse_route, random_routes
from lsd3d_usd.sim.control import TrajectoryTracker
from lsd3d_usd.sim.dynamics import EgoState, VehicleLimits, clip_control, step_bicycle
from lsd3d_usd.sim.metrics import Agents, ScoreKeeper, StepState
from lsd3d_usd.sim.signals import SignalPlan
from lsd3d_usd.sim.world import AgentSpec, World
from lsd3d_usd.views.options import DEFAULT_LOD_PX

COMMANDS = ("left", "straight", "right", "follow")   # CARLA's high-level route options
ACTION_MODES = ("control", "trajectory")
MAX_AGENTS = 200
ROUTE_END_MARGIN = 3.0    # m: the route is complete when the ego's front is this near its end
STOP_SIGN_REACH = 15.0    # m between a stop sign and the stop line it governs
STOP_ZONE = 4.0           # m before a stop sign's line where the ego's front must come to rest
STOPPED = 0.1             # m/s: at rest (CARLA's stop-sign test uses the same speed)
MAX_SECONDS = 3600.0


@dataclass
class EnvSettings:
    """What an episode is made of (all of it recorded with the results)."""
    rig: str = "nuscenes6"            # rig name or FILE.toml; "none": no cameras
    lidar: str = "auto"               # "auto": the rig's own; a preset, FILE.toml, or "none"
    cameras: tuple | None = None      # a subset of the rig's camera names (None: all)
    width: int = 480                  # camera render width (height from the camera's aspect)
    outputs: tuple = ("rgb",)         # + "depth", "semantic", "instance"
    action: str = "control"           # or "trajectory"
    steer: str = "angle"              # control mode: "angle" or "rate"
    waypoints: int = 8                # trajectory mode: K waypoints ...
    waypoint_spacing: float = 0.5     # ... this many seconds apart
    hz: float = 10.0
    seconds: float = 60.0             # time limit (truncation)
    vehicles: int = 8
    cyclists: int = 2
    pedestrians: int = 12
    route_points: int = 20            # route ahead in the observation ...
    route_spacing: float = 2.0        # ... this many metres apart
    lidar_max_points: int | None = None   # default: the LiDAR's rays per sweep
    start_speed: float = 0.0
    stream_radius: float = 300.0
    lod_px: float = DEFAULT_LOD_PX    # camera level of detail (splats.lod); 0: full detail
    exposure: float = 0.0
    route_length: float = 200.0       # m of a drawn route (when none is given)
    ep_reference: str = "none"        # "planner": EP against the planner's progress (a shadow run)
    scenario: str | None = None       # an OpenSCENARIO file: its entities are the world
    ego: str | None = None            # the scenario's entity the ego is (None: the first)
    ego_driver: str = "policy"        # "scenario": the storyboard drives the ego, not the action
    signals: bool = True              # traffic lights run their phases (False: all dark)
    limits: VehicleLimits = field(default_factory=VehicleLimits)

    def check(self) -> "EnvSettings":
        if self.action not in ACTION_MODES:
            raise InputError(f"--action {self.action!r}: choose {' or '.join(ACTION_MODES)}")
        if self.steer not in ("angle", "rate"):
            raise InputError(f"steer {self.steer!r}: choose angle or rate")
        if not (0.5 <= self.hz <= 100.0):
            raise InputError(f"--hz {self.hz}: must be within 0.5 .. 100")
        if not (0.0 < self.seconds <= MAX_SECONDS):
            raise InputError(f"--seconds {self.seconds}: must be within (0, {MAX_SECONDS:g}]")
        for name in ("vehicles", "cyclists", "pedestrians"):
            n = getattr(self, name)
            if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= MAX_AGENTS:
                raise InputError(f"--{name} {n!r}: a whole number from 0 to {MAX_AGENTS}")
        if not (1 <= self.waypoints <= 50) or not (0.05 <= self.waypoint_spacing <= 5.0):
            raise InputError("trajectory: 1 .. 50 waypoints, 0.05 .. 5 s apart")
        if self.ep_reference not in ("none", "planner"):
            raise InputError(f"ep_reference {self.ep_reference!r}: none or planner")
        bad = sorted(set(self.outputs) - {"rgb", "depth", "semantic", "instance"})
        if bad:
            raise InputError(f"outputs: unknown {bad[0]!r} (rgb, depth, semantic, instance)")
        if not (0.0 <= self.lod_px <= 256.0):
            raise InputError(f"--lod-px {self.lod_px}: must be within 0 .. 256 (0: full detail)")
        if not (16 <= int(self.width) <= 3840):
            raise InputError(f"--width {self.width}: must be within 16 .. 3840")
        if self.ego_driver not in ("policy", "scenario"):
            raise InputError(f"ego_driver {self.ego_driver!r}: policy or scenario")
        if self.scenario is None and (self.ego is not None or self.ego_driver == "scenario"):
            what = f"--ego {self.ego}" if self.ego is not None else "--policy scenario"
            raise InputError(f"{what}: needs a scenario (--scenario FILE.xosc|DIR)")
        return self


def _kinds(rng: np.random.Generator, n: int) -> list[str]:
    keys = sorted(KIND_WEIGHTS)
    p = np.array([KIND_WEIGHTS[k] for k in keys])
    return [keys[int(rng.choice(len(keys), p=p / p.sum()))] for _ in range(n)]


class DriveEnv(gym.Env):
    """A closed-loop drive in a generated scene (see the module doc and docs/sim.md).

    ``scene``: a scene folder (or an opened `sim.scene.SimScene`, shared between envs);
    the keyword arguments are `EnvSettings` fields; ``render_mode="rgb_array"``: `render()`
    gives the bird's-eye view."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, scene, render_mode: str | None = None, **settings):
        from lsd3d_usd.sim.scene import SimScene        # opens USD: not needed for the spaces' docs
        from lsd3d_usd.sim.sensors import SensorRig
        self.settings = EnvSettings(**settings).check()
        if render_mode not in (None, "rgb_array"):
            raise InputError(f"render_mode {render_mode!r}: only 'rgb_array' (the bird's-eye view)")
        self.render_mode = render_mode
        self.metadata = dict(self.metadata, render_fps=self.settings.hz)
        self._own_scene = not isinstance(scene, SimScene)
        self.scene = (SimScene(scene, self.settings.stream_radius, lod_px=self.settings.lod_px)
                      if self._own_scene else scene)
        # a shared scene's reader draws at this env's level of detail (camera frames only)
        self.scene.reader.lod_px = float(self.settings.lod_px)
        self.sensors = SensorRig(self.scene, self.settings)
        self.dt = 1.0 / self.settings.hz
        self.limits = self.settings.limits
        self.observation_space = self._observation_space()
        self.action_space = self._action_space()
        self._bev = None
        self.world = None
        self.route: Route | None = None
        self.scenario = None
        if self.settings.scenario is not None:
            self._open_scenario(settings)

    def _open_scenario(self, given: dict) -> None:
        """Read the scenario once (one error line when it cannot be played). Its entities are
        the whole world: seeded traffic beside them is refused rather than silently mixed
        (the traffic model does not know the storyboard's entities)."""
        from lsd3d_usd.sim.scenario.reader import read_scenario
        s = self.settings
        extra = [k for k in ("vehicles", "cyclists", "pedestrians") if given.get(k)]
        if extra:
            raise InputError(f"scenario {s.scenario}: {extra[0]}={given[extra[0]]}: seeded traffic "
                             "beside a scenario's entities is not supported (leave it out)")
        s.vehicles = s.cyclists = s.pedestrians = 0
        self.scenario = read_scenario(s.scenario, s.ego)
        if not self.scenario.ego or self.scenario.ego not in self.scenario.entities:
            raise InputError(f"{s.scenario}: the scenario has no entity for the ego")

    # ---- spaces
    def _action_space(self):
        s, lim = self.settings, self.limits
        if s.action == "control":
            hi = lim.delta_rate_max if s.steer == "rate" else lim.delta_max
            return spaces.Box(np.array([lim.a_min, -hi], np.float32),
                              np.array([lim.a_max, hi], np.float32), dtype=np.float32)
        reach = lim.v_max * s.waypoint_spacing * s.waypoints
        return spaces.Box(-reach, reach, shape=(s.waypoints, 2), dtype=np.float32)

    def _observation_space(self):
        s = self.settings
        f32 = np.float32
        obs = dict(self.sensors.spaces())
        obs["ego"] = spaces.Dict({
            "speed": spaces.Box(0.0, self.limits.v_max, (), f32),
            "acceleration": spaces.Box(-50.0, 50.0, (), f32),
            "yaw_rate": spaces.Box(-10.0, 10.0, (), f32),
            "steering": spaces.Box(-self.limits.delta_max, self.limits.delta_max, (), f32),
            "pose": spaces.Box(-1e7, 1e7, (4,), np.float64),        # x, y, z, yaw (world)
        })
        obs["route"] = spaces.Box(-1e4, 1e4, (s.route_points, 2), f32)
        obs["command"] = spaces.Discrete(len(COMMANDS))
        return spaces.Dict(obs)

    # ---- episode
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = sorted(set(options) - {"route", "start", "speed"})
        if unknown:
            raise InputError(f"reset options: unknown key {unknown[0]!r} (route, start, speed)")
        s = self.settings
        rng = self.np_random
        g = self.scene.graph
        if self.scenario is not None:
            self._reset_scenario(options)
        elif options.get("route"):
            self.route = g.route(parse_route(options["route"]))
        else:
            ids = random_routes(g, 1, s.route_length, int(rng.integers(2**31)))[0]
            self.route = g.route(ids)
        lim = self.limits
        if self.scenario is not None:
            v0 = float(options.get("speed", self._ego_init[4]))
        else:
            d0 = float(options.get("start", min(5.0, self.route.length / 4)))
            x, y, yaw = self.route.pose2d(d0)
            z = float(self.route.point(d0)[2])
            v0 = float(options.get("speed", s.start_speed))
        if not (math.isfinite(v0) and 0.0 <= v0 <= lim.v_max):
            raise InputError(f"reset options: speed {v0!r} outside 0 .. {lim.v_max}")
        if self.scenario is not None:
            self._world_from_scenario(v0)
        else:
            self.ego = EgoState(x - lim.box_offset * math.cos(yaw), y - lim.box_offset * math.sin(yaw),
                                yaw, v0, z=z)
            self._seeded_world(rng)
        self.sensors.start_episode(self.actors, int(rng.integers(2**31)))
        self.signals = SignalPlan(self.scene.signal_groups if s.signals else [], g,
                                  int(rng.integers(2**31)))
        if isinstance(self.world, World):
            self.world.signals = self.signals if len(self.signals) else None
        pts, _ = self.route.polyline()
        reference = self._reference(seed, options) if s.ep_reference == "planner" else None
        self.scores = ScoreKeeper(pts[:, :2], drivable=self.scene.drivable,
                                  obstacles=self.scene.obstacles,
                                  obstacle_ids=self.scene.obstacle_ids,
                                  route_length=self.route.length, reference=reference)
        self.tracker = TrajectoryTracker(lim.wheelbase, s.waypoint_spacing)
        self.stops = self._stop_lines()
        front = self.world.ego_d + lim.length / 2
        self.lights = [[d, k, front > d] for d, k in self.signals.route_stops(self.route)]
        self.t = 0.0
        self.k = 0
        self.clipped = 0
        self.done_reason = None
        self.progress = self.world.ego_d
        self.last = self.scores.update(self._step_state())
        self._pose_actors()
        return self._observe(), self._info(self.last)

    def _seeded_world(self, rng) -> None:
        """The street of actors.street around the ego: seeded traffic and pedestrians."""
        s, g, lim = self.settings, self.scene.graph, self.limits
        kinds = _kinds(rng, s.vehicles)
        vdims = [self.scene.dims("vehicle", k) for k in kinds]
        cdims = self.scene.dims("cyclist")
        pkinds = [["adult", "adult_broad", "child"][int(rng.integers(3))] for _ in range(s.pedestrians)]
        pdims = [self.scene.dims("pedestrian", k) for k in pkinds]
        spec = AgentSpec([(d[0], d[1]) for d in vdims], [(cdims[0], cdims[1])] * s.cyclists,
                         [(k, d[0], d[1], k == "child") for k, d in zip(pkinds, pdims)])
        self.world = World(self.scene.layout, g, self.route, self.ego, lim, spec,
                           int(rng.integers(2**31)))
        veh = self.world.slots
        labels = ["cyclist" if v.cyclist else "vehicle" for v in veh] + \
            ["pedestrian"] * len(self.world.street.crowd.people)
        vkinds = iter(kinds)
        agent_kinds = [None if v.cyclist else next(vkinds, None) for v in veh] + \
            [p.kind for p in self.world.street.crowd.people]
        self.actors = self.scene.actors_for(labels, agent_kinds)

    def _reset_scenario(self, options: dict) -> None:
        """A fresh player at Init; the ego's route from where Init puts it."""
        from lsd3d_usd.sim.scenario.player import ScenarioPlayer
        from lsd3d_usd.sim.scenario.world import ego_route_ids
        if "start" in options:
            raise InputError("reset options: start: the scenario's Init places the ego")
        g = self.scene.graph
        self.player = ScenarioPlayer(self.scenario, self.scene.layout, self.dt,
                                     drive_ego=self.settings.ego_driver == "scenario")
        self.player.start()
        self._ego_init = self.player.ego_init()
        ids = parse_route(options["route"]) if options.get("route") else \
            ego_route_ids(self.player, g, self._ego_init)
        self.route = g.route(ids)

    def _world_from_scenario(self, v0: float) -> None:
        """The ego at the scenario's Init (its reference point, the rear axle centre, is the
        ego frame's origin); the entities drawn with the scene's template of their class
        whose bounding box is nearest to theirs, stretched to their box."""
        from lsd3d_usd.sim.scenario.world import ScenarioWorld
        x, y, _, yaw, _ = self._ego_init
        lim = self.limits
        c = (x + lim.box_offset * math.cos(yaw), y + lim.box_offset * math.sin(yaw))
        d, _ = self.route.project(c)
        self.ego = EgoState(x, y, yaw, v0, z=float(self.route.point(d)[2]))
        self.world = ScenarioWorld(self.player, self.scene.graph, self.route, self.ego, lim)
        labels = self.world.labels()
        kinds = [self.scene.closest_kind(lab, (e.length, e.width, e.height))
                 for lab, e in zip(labels, self.world.entities)]
        boxes = [(e.length, e.width, e.height) for e in self.world.entities]
        self.actors = self.scene.actors_for(labels, kinds, boxes)

    def scenario_state(self) -> dict | None:
        """The scenario's own outcome so far (None without a scenario)."""
        if self.scenario is None:
            return None
        return {"file": str(self.scenario.path), "name": Path(self.scenario.path).stem,
                "ego": self.scenario.ego, "stop_trigger_fired": bool(self.player.finished),
                "storyboard_completed": bool(self.player.completed)}

    def _reference(self, seed, options) -> tuple[np.ndarray, np.ndarray]:
        """(t, progress) of the planner on the same episode without sensors: the reference
        that EP compares with (NAVSIM compares with its PDM-Closed planner the same way)."""
        from dataclasses import asdict

        from lsd3d_usd.sim.policies import Planner
        kw = {k: v for k, v in asdict(self.settings).items() if k != "limits"}
        kw.update(rig="none", lidar="none", ep_reference="none", ego_driver="policy")
        shadow = DriveEnv(self.scene, limits=self.limits, **kw)
        obs, info = shadow.reset(seed=seed, options={**options, "route": self.route.ids})
        policy = Planner(shadow)
        t, prog = [0.0], [shadow.progress]
        while True:
            obs, _, term, trunc, info = shadow.step(policy(obs, info))
            t.append(shadow.t)
            prog.append(float(info["scores"]["progress_m"]))
            if term or trunc:
                break
        return np.array(t), np.array(prog)

    def step(self, action):
        if self.world is None:
            raise InputError("step before reset")
        if self.done_reason is not None:
            raise InputError(f"step after the episode ended ({self.done_reason}); call reset")
        s, lim = self.settings, self.limits
        a = np.asarray(action, np.float64)
        if a.shape != self.action_space.shape:
            raise InputError(f"action: shape {a.shape}, expected {self.action_space.shape} "
                             f"({s.action} mode)")
        if not np.all(np.isfinite(a)):
            self.done_reason = "nan_action"
            info = self._info(self.last)
            info["reason"] = "the action holds NaN or infinity: the episode ends"
            return self._observe(), 0.0, True, False, info
        if s.action == "control":
            acc, steer = float(a[0]), float(a[1])
        else:
            lo, hi = self.action_space.low, self.action_space.high
            if np.any(a < lo) or np.any(a > hi):
                self.clipped += 1
            acc, steer = self.tracker(np.clip(a, lo, hi), self.ego.v, self.dt)
            if s.steer == "rate":
                steer = (steer - self.ego.delta) / self.dt
        if s.ego_driver == "scenario":
            self._ego_from_storyboard()
        else:
            acc, steer, clipped = clip_control(acc, steer, lim, s.steer == "rate" and s.action == "control")
            if clipped and s.action == "control":
                self.clipped += 1
            self.ego = step_bicycle(self.ego, acc, steer, self.dt, lim,
                                    rate=(s.steer == "rate" and s.action == "control"))
            self.ego.z = self._ground_z()
            self.world.place_ego(self.ego)
            self.world.step(self.dt)
        self.t += self.dt
        self.k += 1
        before = self.progress
        complete = self.world.ego_d + lim.length / 2 >= self.route.length - ROUTE_END_MARGIN
        ran_stop = self._stop_signs()
        ran_red = self._red_lights()
        self.last = self.scores.update(self._step_state(complete, ran_stop, ran_red))
        self.progress = max(self.progress, float(self.last["progress_m"]))
        self._pose_actors()
        terminated, reason = False, None
        if self.last["contact"]:
            terminated, reason = True, "collision"
        elif not self.last["dac"]:
            terminated, reason = True, "off_road"
        elif complete:
            terminated, reason = True, "route_complete"
        elif self.scenario is not None and self.player.finished:
            terminated, reason = True, "scenario_end"
        truncated = not terminated and self.t >= s.seconds - 1e-9
        if truncated:
            reason = "time_limit"
        self.done_reason = reason
        reward = (self.progress - before) * float(self.last["nc"]) * float(self.last["dac"])
        if reason in ("collision", "off_road"):
            reward -= 10.0
        info = self._info(self.last)
        if reason:
            info["reason"] = reason
        return self._observe(), float(reward), terminated, truncated, info

    def _ego_from_storyboard(self) -> None:
        """--policy scenario: the storyboard moves the ego with the other entities; its
        acceleration, yaw rate and steering angle are the finite differences the bicycle
        model would need for the same motion (what the comfort scores and the observation
        read)."""
        prev, lim = self.ego, self.limits
        self.world.step(self.dt)
        x, y, _, yaw, v = self.player.ego_pose()
        rate = math.remainder(yaw - prev.yaw, 2 * math.pi) / self.dt
        delta = math.atan(lim.wheelbase * rate / v) if v > 0.1 else prev.delta
        self.ego = EgoState(x, y, yaw, v, float(np.clip(delta, -lim.delta_max, lim.delta_max)),
                            (v - prev.v) / self.dt, prev.z, rate)
        self.world.place_ego(self.ego)
        self.ego.z = self._ground_z()

    def close(self):
        if self._own_scene and getattr(self, "scene", None) is not None:
            self.scene.close()

    # ---- state to scores, sensors and observations
    def _ground_z(self) -> float:
        j, s = self.route.locate(self.world.ego_d)
        g = self.route.graph.geoms[self.route.idx[j]]
        return float(np.interp(s, g.cum, g.points[:, 2]))

    def _all_agents(self) -> Agents:
        """The world's agents and the scene's parked vehicles (static), once per step."""
        key = (id(self.world), self.k)
        if getattr(self, "_agents_at", None) != key:
            self._agents, self._agents_at = self._collect_agents(), key
        return self._agents

    def _collect_agents(self) -> Agents:
        ag = self.world.agents()
        if not self.scene.parked:
            return ag
        ids, xy, yaw, L, W = [], [], [], [], []
        for a, M in self.scene.parked:
            ids.append(f"parked:{a.path}")
            xy.append(M[:2, 3])
            yaw.append(math.atan2(M[1, 0], M[0, 0]))
            L.append(a.dims[0])
            W.append(a.dims[1])
        n = len(ids)
        return Agents(list(ag.ids) + ids, np.vstack([ag.xy, np.array(xy)]),
                      np.concatenate([ag.yaw, yaw]), np.concatenate([ag.length, L]),
                      np.concatenate([ag.width, W]), np.vstack([ag.velocity, np.zeros((n, 2))]),
                      list(ag.kind) + ["vehicle"] * n)

    def _stop_lines(self) -> list:
        """[route distance, satisfied] of the stop lines with a stop sign that the route
        crosses (CARLA scores running a stop sign; the layout's stop lines without a sign
        are only paint)."""
        import shapely
        layout = self.scene.layout
        signs = np.array([np.asarray(sg.position, float)[:2] for sg in layout.stop_signs]).reshape(-1, 2)
        if not len(signs):
            return []
        pts, _ = self.route.polyline()
        path = shapely.LineString(pts[:, :2])
        out = []
        for sl in layout.stop_lines:
            line = np.asarray(sl.points, float)[:, :2]
            if len(line) < 2 or np.min(np.hypot(*(signs[:, None, :] - line[None]).transpose(2, 0, 1))) \
                    > STOP_SIGN_REACH:
                continue
            hit = path.intersection(shapely.LineString(line))
            for p in getattr(hit, "geoms", [hit]):
                if not p.is_empty and p.geom_type == "Point":
                    out.append([self.route.project((p.x, p.y))[0], False])
        return sorted(out)

    def _stop_signs(self) -> bool:
        """Update the stop lines ahead; True on the step the ego's front passes one where it
        had not come to rest within STOP_ZONE m before it."""
        front = self.world.ego_d + self.limits.length / 2
        ran = False
        for stop in self.stops:
            d, ok = stop
            if ok is None:
                continue
            if not ok and d - STOP_ZONE <= front <= d + 0.5 and self.ego.v < STOPPED:
                stop[1] = ok = True
            if front > d + 0.5:
                ran = ran or not ok
                stop[1] = None                # passed
        return ran

    def stop_sign_distance(self) -> float:
        """Metres from the ego's front to the next stop sign's line it has yet to stop at."""
        front = self.world.ego_d + self.limits.length / 2
        return min((d - front for d, ok in self.stops if ok is False and d + 0.5 >= front),
                   default=math.inf)

    def _red_lights(self) -> bool:
        """True on the step the ego's front passes a signal's stop point while it is red
        (CARLA's red-light infraction; passing at yellow is allowed)."""
        front = self.world.ego_d + self.limits.length / 2
        ran = False
        for light in self.lights:
            d, k, passed = light
            if not passed and front > d:
                light[2] = True
                ran = ran or self.signals.state(k, self.t) == "red"
        return ran

    def next_signal(self) -> tuple[str, float]:
        """(state of the next signal on the route ahead ("none": none), metres from the ego's
        front to the next stop point that is red or yellow (inf: none))."""
        front = self.world.ego_d + self.limits.length / 2
        state, dist = "none", math.inf
        for d, k, passed in self.lights:
            if passed:
                continue
            st = self.signals.state(k, self.t)
            if state == "none":
                state = st
            if st != "green":
                dist = d - front
                break
        return state, dist

    def _step_state(self, complete: bool = False, ran_stop: bool = False,
                    ran_red: bool = False) -> StepState:
        e, lim = self.ego, self.limits
        c = e.box_centre(lim)
        g = self.scene.graph
        lp = g.nearest_lane(c)                     # any direction: is it the right one?
        wrong = lp is not None and lp.distance <= g.width[lp.lane] / 2 and \
            abs(math.remainder(e.yaw - lp.heading, 2 * math.pi)) > math.radians(135) and e.v > 0.1
        in_junction = lp is not None and lp.distance <= g.width[lp.lane] / 2 and bool(g.junction[lp.lane])
        return StepState(self.t, c, e.yaw, e.v, lim.length, lim.width, agents=self._all_agents(),
                         progress=self.route.length if complete else self.world.ego_d, wrong_way=bool(wrong), in_junction=in_junction,
                         lon_acc=e.a, lat_acc=e.v * e.yaw_rate, stop_sign=ran_stop,
                         red_light=ran_red)

    def _pose_actors(self) -> None:
        e, lim = self.ego, self.limits
        c = e.box_centre(lim)
        self.actors.set_pose(0, float(c[0]), float(c[1]), e.z, e.yaw)
        # the ego's own body is not drawn: its cameras sit where the real car's are, not
        # where the procedural car's cabin would put them (the LiDAR leaves it out too)
        self.actors.set_visible(0, False)
        for q, ((x, y, z, yaw), shown) in enumerate(zip(self.world.poses(), self.world.shown())):
            self.actors.set_pose(q + 1, x, y, z, yaw)
            self.actors.set_visible(q + 1, shown)

    def _route_obs(self) -> tuple[np.ndarray, int]:
        s = self.settings
        pts = self.route.ahead(self.world.ego_d, s.route_points, s.route_spacing)[:, :2]
        M = self.ego.matrix()
        local = (pts - M[:2, 3]) @ M[:2, :2]
        return local.astype(np.float32), self._command()

    def _command(self) -> int:
        """The next junction's turn within 40 m on the route: left / straight / right, or
        follow the lane when no junction is near."""
        j, s = self.route.locate(self.world.ego_d)
        ahead = -s
        for k in range(j, len(self.route.idx)):
            i = self.route.idx[k]
            if ahead > 40.0:
                break
            if self.route.graph.junction[i]:
                geom = self.route.graph.geoms[i]
                turn = math.remainder(float(geom.heading(geom.length)) - float(geom.heading(0.0)),
                                      2 * math.pi)
                return 0 if turn > math.radians(30) else 2 if turn < -math.radians(30) else 1
            ahead += self.route.graph.length[i]
        return 3

    def _observe(self) -> dict:
        e = self.ego
        obs = self.sensors.observe(self.ego, self.t, self.k)
        obs["ego"] = {"speed": np.float32(e.v), "acceleration": np.float32(np.clip(e.a, -50, 50)),
                      "yaw_rate": np.float32(np.clip(e.yaw_rate, -10, 10)),
                      "steering": np.float32(e.delta),
                      "pose": np.array([e.x, e.y, e.z, e.yaw], np.float64)}
        obs["route"], obs["command"] = self._route_obs()
        return obs

    def _info(self, scores: dict) -> dict:
        """Privileged data and the scores: never part of the observation."""
        boxes = [b.to_json() for b in self._all_agents().boxes()]     # sim.metrics.AgentBox
        gap, v_lead = self.world.ego_leader()
        signal, red_m = self.next_signal()
        return {"t": round(self.t, 9), "step": self.k, "scores": scores, "boxes": boxes,
                "route": list(self.route.ids), "route_length_m": self.route.length,
                "progress_m": self.progress, "clipped_actions": self.clipped,
                "stop_distance_m": float(self.world.ego_stop_distance()),
                "stop_sign_m": float(self.stop_sign_distance()),
                "red_light_m": float(red_m), "signal": signal,
                "leader_gap_m": float(gap), "leader_speed": float(v_lead),
                "occupied_crosswalks": sorted(self.world.occupied_crosswalks()),
                "command": COMMANDS[self._command()],
                **({"scenario": self.scenario_state()} if self.scenario is not None else {})}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from lsd3d_usd.sim.birdseye import BirdsEye
        if self._bev is None:
            self._bev = BirdsEye(self.scene)
        marks = [(x, y, h, self.signals.state(k, self.t)) for x, y, h, k in self.signals.stop_marks]
        return self._bev.frame(self.ego, self.limits, self._all_agents(), self.route, marks)

    def episode_summary(self) -> dict:
        return self.scores.summary()
