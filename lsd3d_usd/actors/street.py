"""Vehicles, cyclists and pedestrians in one seeded run: `simulate_street`.

A pure function of (layout, seed, parameters), like `traffic.simulate`: the vehicles and
cyclists are one IDM simulation (`traffic.Simulation`), the pedestrians a
`pedestrians.Pedestrians` crowd on the layout's sidewalks (`sidewalks.build_walkable`).
Each simulation step moves the pedestrians first (against the vehicles' boxes as they
stand, stepping onto a crosswalk only when `Simulation.crosswalk_clear` says so), then
hands the occupied crosswalks to the vehicles, which stop before them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely

from lsd3d_usd.actors.pedestrians import CROSS, STAND, WAIT, WALK, Pedestrians, WalkParams, Walker
from lsd3d_usd.actors.sidewalks import Walkable, build_walkable
from lsd3d_usd.actors.traffic import IDMParams, Simulation, TrafficRun
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.limits import CYCLISTS, PEDESTRIANS

STATES = (WALK, WAIT, CROSS, STAND)
MAX_PEDESTRIANS = int(PEDESTRIANS.value)
MAX_CYCLISTS = int(CYCLISTS.value)
SIDEWALK_TOP = 0.17          # m: proxy road_z + curb_height, where a pedestrian's feet are


@dataclass(frozen=True)
class StreetParams:
    idm: IDMParams = field(default_factory=IDMParams)
    walk: WalkParams = field(default_factory=WalkParams)
    cyclist_speed: tuple = (4.0, 7.0)        # m/s own top speed, drawn per cyclist
    cyclist_edge: float = 0.25               # m from the right lane edge to the cyclist's box


@dataclass
class PeopleRun:
    """Pedestrian samples at times ``t``: world xyz (n, n_t, 3), yaw (radians, unwrapped),
    speed (m/s), distance walked (m), state (index into STATES), crosswalk (index or -1)."""
    t: np.ndarray
    position: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    walked: np.ndarray
    state: np.ndarray
    crosswalk: np.ndarray
    kinds: list
    dims: np.ndarray                         # (n, 2) box length, width

    @property
    def n(self) -> int:
        return int(self.position.shape[0])


@dataclass
class StreetRun:
    traffic: TrafficRun                      # vehicles then cyclists (traffic.cyclist)
    people: PeopleRun
    walkable: Walkable
    occupied: np.ndarray                     # (n_polygons, n_t) bool
    crossings: list                          # per traffic lane: (polygon, s_in, s_out)
    polygons: list = field(default_factory=list)   # the crosswalks, then mid-block corridors
    seed: int = 0


class Street:
    """The street stepped one step at a time: an IDM `traffic.Simulation` of vehicles and
    cyclists and a `pedestrians.Pedestrians` crowd, set up from (layout, seed) exactly as
    `simulate_street` does. ``ego`` = (length, width, (x, y, yaw), lane, s): an external
    vehicle (the closed-loop ego, `Simulation.add_external`) placed before anyone spawns, with
    ``ego_clearance`` m kept free around it; the others follow it, yield to it and stop for
    it. `step(dt)` moves the people (against the vehicles as they stand), then the vehicles."""

    def __init__(self, layout, vehicles=(), cyclists=(), pedestrians=(), seed: int = 0,
                 params: StreetParams = StreetParams(), walkable: Walkable | None = None,
                 graph: LaneGraph | None = None, ego=None, ego_clearance: float = 10.0):
        if len(pedestrians) > MAX_PEDESTRIANS or len(cyclists) > MAX_CYCLISTS:
            raise InputError(f"actors: at most {MAX_PEDESTRIANS} pedestrians and {MAX_CYCLISTS} cyclists "
                             f"(asked for {len(pedestrians)} and {len(cyclists)})")
        self.seed = int(seed)
        sim = self.sim = Simulation(layout, seed, params.idm, graph if graph is not None else
                                    LaneGraph(layout, params.idm.conflict_distance, bike_lanes=True))
        w = self.walkable = walkable if walkable is not None else build_walkable(
            layout, params.walk.track_offset, params.walk.stand_offset)
        if getattr(sim.g, "crossings_of", None) is not w:      # a graph reused over seeds keeps them
            sim.g.set_crosswalks([c.polygon for c in w.crosswalks])
            sim.g.crossings_of = w
        sim.g.truncate_crosswalks(len(w.crosswalks))          # no mid-block crossing of another run
        self.ego = None
        if ego is not None:
            length, width, pose, lane, s = ego
            self.ego = sim.add_external(length + 2 * ego_clearance, width)
            sim.place_external(self.ego, pose, 0.0, lane, s)
        if vehicles:
            sim.spawn([float(L) for L, _ in vehicles])
            for v, (_, W) in zip([v for v in sim.veh if not v.external], vehicles):
                v.width = float(W)
        self.n_motor = len(sim.veh)
        rng_c = np.random.default_rng(np.random.SeedSequence([int(seed), 0xC1C]))
        specs = [(float(L), float(W), float(rng_c.uniform(*params.cyclist_speed))) for L, W in cyclists]
        sim.spawn_cyclists(specs, edge=params.cyclist_edge)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x9ED]))
        self.crowd = Pedestrians(w, rng, params.walk, add_crossing=sim.g.add_crosswalk)
        _spawn_people(self.crowd, sim, pedestrians, rng)
        if self.ego is not None:
            self.ego.length = float(ego[0])
        sim.occupied = self.crowd.occupied()

    def move_people(self, sim: Simulation, dt: float) -> None:
        """The people's part of a step (`Simulation.run`'s on_step)."""
        self.crowd.step(dt, vehicle_boxes(sim), sim.crosswalk_clear)
        sim.occupied = self.crowd.occupied()

    def step(self, dt: float) -> None:
        self.move_people(self.sim, dt)
        self.sim.step(dt)

    def vehicle_z(self, me) -> float:
        """Ground height under a vehicle on its lane (0 off the lanes)."""
        if me.lane < 0:
            return 0.0
        g = self.sim.g.geoms[me.lane]
        return float(np.interp(min(max(me.s, 0.0), g.length), g.cum, g.points[:, 2]))


def simulate_street(layout, vehicles=(), cyclists=(), pedestrians=(), seed: int = 0,
                    seconds: float = 8.0, fps: float = 10.0,
                    params: StreetParams = StreetParams(), walkable: Walkable | None = None,
                    graph: LaneGraph | None = None) -> StreetRun:
    """Spawn and run. ``vehicles``: [(length, width)], ``cyclists``: [(length, width)],
    ``pedestrians``: [(kind, length, width, child)] — box sizes from the assets. Fewer
    actors than asked are placed when the layout has no room (the run says how many).
    ``walkable`` / ``graph`` (a ``LaneGraph(layout, bike_lanes=True)``) may be passed in to
    reuse them over many seeds."""
    street = Street(layout, vehicles, cyclists, pedestrians, seed, params, walkable, graph)
    sim, crowd, w, n_motor = street.sim, street.crowd, street.walkable, street.n_motor

    n_t = int(round(seconds * fps)) + 1
    n_p = len(crowd.people)
    P = np.zeros((n_p, n_t, 2))
    Y = np.zeros((n_p, n_t))
    V = np.zeros((n_p, n_t))
    D = np.zeros((n_p, n_t))
    ST = np.zeros((n_p, n_t), np.int8)
    CW = np.full((n_p, n_t), -1, np.int32)
    occ = []

    def on_sample(s: Simulation, k: int) -> None:
        for i, p in enumerate(crowd.people):
            P[i, k], Y[i, k], V[i, k], D[i, k] = p.xy, p.yaw, p.v, p.walked
            ST[i, k] = STATES.index(p.state)
            CW[i, k] = p.crosswalk if p.state in (WAIT, CROSS) else -1
        occ.append(crowd.occupied())

    run = sim.run(seconds, fps, on_step=street.move_people, on_sample=on_sample)
    run.cyclist[:n_motor] = False
    for i in range(n_p):
        Y[i] = np.unwrap(Y[i])
    OCC = np.zeros((len(crowd.polygons), n_t), bool)
    for k, cs in enumerate(occ):
        OCC[sorted(cs), k] = True
    z = np.full((n_p, n_t), SIDEWALK_TOP)
    if crowd.polygons and n_p:
        cw = shapely.union_all(np.array(crowd.polygons, dtype=object))
        on_cw = shapely.contains_xy(cw, P[..., 0].ravel(), P[..., 1].ravel()).reshape(n_p, n_t)
        z[on_cw] = 0.02
    people = PeopleRun(run.t, np.concatenate([P, z[..., None]], axis=2), Y, V, D, ST, CW,
                       [p.kind for p in crowd.people],
                       np.array([[p.length, p.width] for p in crowd.people]).reshape(-1, 2))
    crossings = [list(row) for row in sim.g.crossings]
    sim.g.truncate_crosswalks(len(w.crosswalks))
    return StreetRun(run, people, w, OCC, crossings, list(crowd.polygons), int(seed))


def vehicle_boxes(sim: Simulation):
    """(centres (n, 2), yaws (n,), half extents (n, 2)) of the simulation's vehicles now."""
    n = len(sim.veh)
    c, y, h = np.zeros((n, 2)), np.zeros(n), np.zeros((n, 2))
    for i, me in enumerate(sim.veh):
        x, yy, yaw = sim.pose(me)
        c[i], y[i], h[i] = (x, yy), yaw, (me.length / 2, me.width / 2)
    return c, y, h


def _spawn_people(crowd: Pedestrians, sim: Simulation, pedestrians, rng, tries: int = 60) -> None:
    w, p = crowd.w, crowd.p
    if not w.tracks:
        return
    others = vehicle_boxes(sim)
    lengths = np.array([t.length for t in w.tracks])
    tw = lengths / lengths.sum()
    tracks_geom = shapely.MultiLineString([t.points for t in w.tracks])
    stand_used = np.zeros(len(w.stand_spots), bool)
    n_corner = max(20, len(w.stand_spots) // 10)
    for kind, L, W, child in pedestrians:
        lo, hi = p.speed_child if child else p.speed_adult
        v_des = float(rng.uniform(lo, hi))
        placed = None
        r = rng.random()
        if r < p.stand_share and len(w.stand_spots):
            for _ in range(tries):
                j = int(rng.integers(min(n_corner, len(w.stand_spots))))
                if stand_used[j]:
                    continue
                xy = w.stand_spots[j]
                yaw = float(rng.uniform(-np.pi, np.pi))
                far = tracks_geom.distance(shapely.Point(*xy)) >= 0.5 * np.hypot(L, W) + 0.4
                if far and crowd.free_spot(xy, yaw, L, W, others):
                    stand_used[j] = True
                    placed = Walker(kind, L, W, v_des, STAND, xy=np.array(xy), yaw=yaw)
                    break
        elif r < p.stand_share + p.start_at_crosswalk and w.crosswalks:
            for _ in range(tries // 4):
                k = int(rng.integers(len(w.crosswalks)))
                c = w.crosswalks[k]
                fwd = bool(rng.random() < 0.5)
                tr, s = (c.track_a, c.s_a) if fwd else (c.track_b, c.s_b)
                t = w.tracks[tr]
                xy, yaw = t.point(s), float(t.heading(s))
                if crowd.free_spot(xy, yaw, L, W, others):
                    placed = Walker(kind, L, W, v_des, WAIT, track=tr, s=float(s), xy=xy, yaw=yaw,
                                    wait_left=float(rng.uniform(*p.wait)), crosswalk=k, forward=fwd)
                    break
        if placed is None:
            for _ in range(tries):
                tr = int(rng.choice(len(w.tracks), p=tw))
                t = w.tracks[tr]
                s = float(rng.uniform(0.0, t.length))
                xy, yaw = t.point(s), float(t.heading(s))
                if crowd.free_spot(xy, yaw, L, W, others):
                    placed = Walker(kind, L, W, v_des, WALK, track=tr, s=s, xy=xy, yaw=yaw)
                    break
        if placed is not None:
            crowd.people.append(placed)
