"""The world around the ego, stepped online: vehicles, cyclists and pedestrians of
`actors.street.Street` (the same models that make a scene's actors layer), with the ego as
an external vehicle of the traffic model, placed on the lane graph each step from its
simulated pose, so the others follow it, yield to it at junctions and stop behind it.

Arrays out: `World.agents()` gives every other agent's box, velocity and kind now.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lsd3d_usd.actors.street import SIDEWALK_TOP, Street, StreetParams
from lsd3d_usd.layout.routes import LaneGraph, Route
from lsd3d_usd.sim.dynamics import EgoState, VehicleLimits
from lsd3d_usd.sim.metrics import Agents

LANE_SNAP = 1.0       # m beyond a lane's half width where the ego still counts as on it


@dataclass
class AgentSpec:
    """What spawns: box sizes per agent (length, width), pedestrians with their kind."""
    vehicles: list
    cyclists: list
    pedestrians: list       # [(kind, length, width, child)]


class World:
    """The street around an ego driving ``route``; seeded by ``seed``."""

    def __init__(self, layout, graph: LaneGraph, route: Route, ego: EgoState,
                 limits: VehicleLimits, spec: AgentSpec, seed: int,
                 params: StreetParams = StreetParams(), walkable=None):
        self.graph = graph
        self.route = route
        self.limits = limits
        self.params = params
        self.ego_d = 0.0                # route distance of the ego's box centre
        lane, s = route.idx[0], 0.0
        c = ego.box_centre(limits)
        self.ego_d, _ = route.project(c)
        j, s = route.locate(self.ego_d)
        lane = route.idx[j]
        self.street = Street(layout, spec.vehicles, spec.cyclists, spec.pedestrians, seed, params,
                             walkable, graph, ego=(limits.length, limits.width,
                                                   (float(c[0]), float(c[1]), ego.yaw), lane, s))
        self.sim = self.street.sim
        self.ego_vehicle = self.street.ego
        # agents keep their slot (index) for the episode: one that leaves the map at a dead
        # end is hidden and comes back at a lane where traffic enters (constant density)
        self.slots = self.vehicles()
        self.gone: dict[int, float] = {}          # slot -> time it left
        self.t = 0.0
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5A5]))
        self.signals = None             # a sim.signals.SignalPlan: the traffic stops at red
        self.place_ego(ego)

    # ---- the ego on the lane graph
    def place_ego(self, ego: EgoState) -> None:
        """Tell the traffic model where the ego is: on the route's lane it projects to when
        within the lane (plus LANE_SNAP), else on the nearest lane heading its way, else on
        no lane (the others then only avoid it through their own boxes)."""
        c = ego.box_centre(self.limits)
        d, off = self.route.project(c, near=self.ego_d)
        j, s = self.route.locate(d)
        lane = self.route.idx[j]
        plan = self.route.idx[j + 1:j + 3]
        if abs(off) > self.graph.width[lane] / 2 + LANE_SNAP:
            lp = self.graph.nearest_lane(c, heading=ego.yaw)
            if lp is not None and lp.distance <= self.graph.width[lp.lane] / 2 + LANE_SNAP \
                    and abs(lp.relative_heading) < math.pi / 2:
                lane, s, plan = lp.lane, lp.s, []
            else:
                lane, s, plan = -1, 0.0, []
        else:
            self.ego_d = d
        self.sim.place_external(self.ego_vehicle, (float(c[0]), float(c[1]), ego.yaw), ego.v,
                                lane, s, plan)

    def step(self, dt: float) -> None:
        """Advance the others by ``dt`` (in the traffic model's sub-steps)."""
        sub = max(1, int(math.ceil(dt / self.params.idm.dt_max - 1e-9)))
        for k in range(sub):
            if self.signals is not None:
                self.sim.signals = self.signals.lane_states(self.t + k * dt / sub)
            self.street.step(dt / sub)
        self.t += dt
        self._leave_and_return()

    def _leave_and_return(self, wait: float = 2.0, clear: float = 15.0) -> None:
        g, sim = self.graph, self.sim
        for k, v in enumerate(self.slots):
            if k in self.gone:
                continue
            dead_end = not v.plan and not any(g.bike[j] == v.cyclist or not g.bike[j] for j in g.succ[v.lane])
            # IDM stops s0 short of the wall at the lane end
            if dead_end and v.s + v.length / 2 >= g.length[v.lane] - sim.p.stop_margin - sim.p.s0 - 1.0 \
                    and v.v < 0.5:
                sim.veh.remove(v)
                v.holds.clear()
                self.gone[k] = self.t
        for k in sorted(self.gone):
            if self.t - self.gone[k] < wait:
                continue
            v = self.slots[k]
            lanes = [i for i in g.entries() if g.length[i] >= v.length + 4.0] if not v.cyclist else \
                [i for i in range(len(g.ids)) if not g.pred[i] and g.length[i] >= v.length + 4.0]
            if not lanes:
                continue
            lane = lanes[int(self.rng.integers(len(lanes)))]
            s = v.length / 2 + 1.0
            p = g.geoms[lane].point(s)[:2]
            e = self.sim.pose(self.ego_vehicle)[:2]
            if math.hypot(p[0] - e[0], p[1] - e[1]) < clear or not sim._spawn_ok(lane, s, v.length, 8.0):
                continue
            v.lane, v.s, v.plan, v.forced, v.holds = lane, s, [], [], {}
            v.offset = sim.cyclist_offset(lane, v.width) if v.cyclist else 0.0
            v.v = 0.5 * min(g.limit[lane] * v.factor, v.v_max)
            sim._fill_plan(v)
            sim.veh.append(v)
            del self.gone[k]

    def ego_stop_distance(self, horizon: float = 120.0) -> float:
        """Bumper distance within which the traffic rules make the ego stop (a junction it
        holds no reservation for, an occupied crosswalk), inf when none."""
        return self.sim.must_stop_before(self.ego_vehicle, horizon)

    def ego_leader(self, horizon: float = 120.0) -> tuple[float, float]:
        """(bumper gap, speed) of the vehicle ahead of the ego on its lane and route."""
        return self.sim.leader(self.sim.veh.index(self.ego_vehicle), horizon)

    # ---- the others now
    def vehicles(self):
        """The vehicles and cyclists on the map now (not the ego)."""
        return [v for v in self.sim.veh if not v.external]

    def shown(self) -> list[bool]:
        """Per slot then per pedestrian: is it on the map now."""
        return [k not in self.gone for k in range(len(self.slots))] + [True] * len(self.street.crowd.people)

    def agents(self) -> Agents:
        """Every other agent's box (centre, yaw, length, width), velocity and kind now."""
        ids, xy, yaw, L, W, vel, kind = [], [], [], [], [], [], []
        for k, v in enumerate(self.slots):
            if k in self.gone:
                continue
            x, y, h = self.sim.pose(v)
            ids.append(f"{'cyclist' if v.cyclist else 'vehicle'}:{k}")
            xy.append((x, y))
            yaw.append(h)
            L.append(v.length)
            W.append(v.width)
            vel.append((v.v * math.cos(h), v.v * math.sin(h)))
            kind.append("cyclist" if v.cyclist else "vehicle")
        for k, p in enumerate(self.street.crowd.people):
            ids.append(f"pedestrian:{k}")
            xy.append(tuple(p.xy))
            yaw.append(p.yaw)
            L.append(p.length)
            W.append(p.width)
            vel.append((p.v * math.cos(p.yaw), p.v * math.sin(p.yaw)))
            kind.append("pedestrian")
        if not ids:
            return Agents.empty()
        return Agents(ids, np.array(xy), np.array(yaw), np.array(L), np.array(W), np.array(vel), kind)

    def poses(self) -> list[tuple[float, float, float, float]]:
        """(x, y, z, yaw) of each vehicle slot then each pedestrian (gone slots where they
        left; `shown` says which are on the map)."""
        out = []
        for v in self.slots:
            x, y, h = self.sim.pose(v)
            out.append((x, y, self.street.vehicle_z(v), h))
        for p in self.street.crowd.people:
            out.append((float(p.xy[0]), float(p.xy[1]), self._person_z(p), float(p.yaw)))
        return out

    def _person_z(self, p) -> float:
        return 0.02 if p.state == "cross" else SIDEWALK_TOP

    def occupied_crosswalks(self) -> set:
        return set(self.sim.occupied)
