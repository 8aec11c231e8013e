"""A scenario's entities as the world around the ego (`ScenarioWorld`): the seam between
`DriveEnv` and `ScenarioPlayer`. It has `sim.world.World`'s interface (agents, poses,
shown, step, place_ego, ego_d, ego_leader, ego_stop_distance, occupied_crosswalks), but its
agents are the scenario's non-ego entities, moved each step by the storyboard given the
ego's state; there is no seeded traffic, no street and no traffic rules of their own.

Positions: the player reports OpenSCENARIO reference points (a vehicle's rear axle
centre); boxes and rendered actors are placed at the bounding box centre, as the ego's.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import LaneGraph, Route
from lsd3d_usd.sim.dynamics import EgoState, VehicleLimits
from lsd3d_usd.sim.metrics import Agents
from lsd3d_usd.sim.scenario import reader as R
from lsd3d_usd.sim.scenario.player import ScenarioPlayer

ROUTE_SEARCH_BUDGET = 5000      # lane expansions of the ego's successor search
ROUTE_MAX_LENGTH = 5000.0       # m: the ego's route need not be longer


def entity_label(ent: R.Entity) -> str:
    """The sensors' class of an entity: pedestrian, cyclist (bicycles) or vehicle."""
    if ent.kind == "pedestrian":
        return "pedestrian"
    return "cyclist" if ent.category == "bicycle" else "vehicle"


def scenario_files(path) -> list[Path]:
    """The .xosc file ``path``, or every .xosc in folder ``path`` (sorted)."""
    p = Path(path)
    if p.is_dir():
        files = sorted(q for q in p.glob("*.xosc") if q.is_file())
        if not files:
            raise InputError(f"--scenario {path}: the folder holds no .xosc file")
        return files
    if not p.is_file():
        raise InputError(f"--scenario {path}: no such file or folder")
    return [p]


def ego_route_ids(player: ScenarioPlayer, graph: LaneGraph, ego_init) -> list[str]:
    """The ego's route: the lanes of the scenario's AssignRoute for the ego when it has one at
    t = 0, else the lane the ego starts on; then the longest successor path from its last
    lane (depth-first, bounded)."""
    x, y, _, yaw, _ = ego_init
    lp = graph.nearest_lane((x, y), heading=yaw)
    if lp is None or lp.distance > graph.width[lp.lane] / 2 + 1.0 or \
            abs(lp.relative_heading) >= math.pi / 2:
        raise InputError(f"{player.sc.path}: the ego {player.ego!r} starts on no lane of the scene "
                         f"(at {x:.1f}, {y:.1f}) heading its way")
    ids = [graph.ids[lp.lane]]
    routes = [a for t, a in player.ego_actions if t == 0.0 and isinstance(a, R.AssignRouteAction)]
    if routes:
        st = player.states[player.ego]
        kept = st.plan                   # the plan a storyboard-driven ego follows stays
        player._route(st, routes[-1])
        ids += [player.graph.ids[j] for j in st.plan if player.graph.ids[j] != ids[-1]]
        st.plan = kept
    # extend from the last lane with the longest path of successors that repeats no lane
    start = graph.index[ids[-1]]
    best, best_len = [], 0.0
    stack = [(start, [], 0.0)]
    n = 0
    while stack and n < ROUTE_SEARCH_BUDGET:
        i, path, length = stack.pop()
        n += 1
        if length > best_len:
            best, best_len = path, length
            if length >= ROUTE_MAX_LENGTH:
                break
        seen = set(ids) | {graph.ids[j] for j in path}
        for j in sorted(graph.car_successors(i), key=lambda j: graph.ids[j], reverse=True):
            if graph.ids[j] not in seen:
                stack.append((j, path + [j], length + float(graph.length[j])))
    return ids + [graph.ids[j] for j in best]


class ScenarioWorld:
    """The scenario's non-ego entities around an ego driving ``route`` (see the module doc)."""

    def __init__(self, player: ScenarioPlayer, graph: LaneGraph, route: Route, ego: EgoState,
                 limits: VehicleLimits):
        self.player = player
        self.graph = graph
        self.route = route
        self.limits = limits
        self.names = [n for n in player.states if n != player.ego]
        self.entities = [player.states[n].entity for n in self.names]
        self.t = 0.0
        self.ego = ego
        self.ego_d, _ = route.project(ego.box_centre(limits))

    # ---- the ego and time
    def place_ego(self, ego: EgoState) -> None:
        self.ego = ego
        self.ego_d, _ = self.route.project(ego.box_centre(self.limits), near=self.ego_d)

    def step(self, dt: float) -> None:
        """Advance the storyboard by ``dt`` with the ego where `place_ego` put it."""
        self.t += dt
        e = self.ego
        self.player.step(self.t, (e.x, e.y, e.yaw, e.v))

    # ---- the entities now
    def labels(self) -> list[str]:
        return [entity_label(ent) for ent in self.entities]

    def _boxes(self):
        """Per entity: box centre (x, y), z, yaw, speed."""
        out = []
        for n in self.names:
            st = self.player.states[n]
            cx, cy = st.entity.center[0], st.entity.center[1]
            c, s = math.cos(st.yaw), math.sin(st.yaw)
            out.append((st.x + c * cx - s * cy, st.y + s * cx + c * cy, st.z, st.yaw, st.v))
        return out

    def reference_poses(self) -> dict:
        """Agent id (as in `agents`) -> (x, y, z, yaw, speed) of the entity's OpenSCENARIO
        reference point (a vehicle's rear axle centre), what the trajectory CSV reports."""
        return {f"{lab}:{n}": (st.x, st.y, st.z, st.yaw, st.v)
                for lab, n, st in zip(self.labels(), self.names, (self.player.states[n] for n in self.names))}

    def shown(self) -> list[bool]:
        return [True] * len(self.names)

    def poses(self) -> list[tuple[float, float, float, float]]:
        return [(x, y, z, yaw) for x, y, z, yaw, _ in self._boxes()]

    def agents(self) -> Agents:
        if not self.names:
            return Agents.empty()
        b = self._boxes()
        return Agents([f"{lab}:{n}" for lab, n in zip(self.labels(), self.names)],
                      np.array([(x, y) for x, y, *_ in b]), np.array([q[3] for q in b]),
                      np.array([e.length for e in self.entities]),
                      np.array([e.width for e in self.entities]),
                      np.array([(v * math.cos(h), v * math.sin(h)) for _, _, _, h, v in b]),
                      self.labels())

    # ---- what the planner asks the world
    def ego_leader(self, horizon: float = 120.0) -> tuple[float, float]:
        """(bumper gap, speed along the route) of the nearest entity ahead on the ego's route
        within its lane (inf, 0 when none)."""
        best = (math.inf, 0.0)
        for ent, (x, y, _, yaw, v) in zip(self.entities, self._boxes()):
            d, off = self.route.project((x, y), near=self.ego_d, window=horizon)
            j, _ = self.route.locate(d)
            if d <= self.ego_d or abs(off) > self.graph.width[self.route.idx[j]] / 2:
                continue
            gap = d - self.ego_d - self.limits.length / 2 - ent.length / 2
            if gap < min(best[0], horizon):
                best = (gap, max(v * math.cos(yaw - self.route.heading(d)), 0.0))
        return best

    def ego_stop_distance(self, horizon: float = 120.0) -> float:
        return math.inf         # the scenario's entities follow the storyboard, not traffic rules

    def occupied_crosswalks(self) -> set:
        return set()
