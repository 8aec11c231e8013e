"""Traffic-light phases: a fixed-time plan per junction over layout.signals' groups.

Each junction's groups split into two phases by approach axis (the first group's heading
and its opposite are phase 0; groups more than 45 degrees off that axis are phase 1). The
cycle, from each junction's seeded offset:

    phase 0 green GREEN s, yellow YELLOW s, all red ALL_RED s, then phase 1 the same
    (CYCLE = 2 (GREEN + YELLOW + ALL_RED) = 34 s)

Numbers (docs/sim.md, Signals): YELLOW from the ITE kinematic change interval
y = t + v / (2 a) with t = 1 s, v = 50 km/h, a = 3 m/s^2 (3.3 s; the US MUTCD allows 3-6 s);
ALL_RED from the clearance interval (W + L) / v for a 20 m junction and a 5 m car at 50 km/h
(1.8 s); GREEN is short, so that one 60 s episode sees every phase (real urban plans run
60-120 s cycles). A junction with one phase only still cycles (red while phase 1 would be
green). The offsets are a pure function of the episode's seed.
"""
from __future__ import annotations

import math

import numpy as np

from lsd3d_usd.layout.signals import stop_lane

GREEN = 12.0
YELLOW = 3.0
ALL_RED = 2.0
PHASE = GREEN + YELLOW + ALL_RED
CYCLE = 2 * PHASE
STATES = ("green", "yellow", "red")


def phase_state(t: float, phase: int, offset: float = 0.0) -> str:
    """State of a phase-``phase`` group at time ``t`` (s) of a junction whose cycle starts at
    ``-offset``: phase 0 is green on [0, GREEN) of the cycle, phase 1 on [PHASE, PHASE + GREEN)."""
    u = math.fmod(t + offset - phase * PHASE, CYCLE)
    if u < 0:
        u += CYCLE
    return "green" if u < GREEN else "yellow" if u < GREEN + YELLOW else "red"


def split_phases(headings: list[float]) -> list[int]:
    """Phase (0 or 1) of each heading: 0 within 45 degrees of the first heading's axis."""
    if not headings:
        return []
    h0 = headings[0]
    return [0 if abs(math.sin(h - h0)) < math.sin(math.pi / 4) else 1 for h in headings]


def _mark(points, at_end: bool, group: int):
    """(x, y, heading, group) at a lane's end (or start), heading along its last (first)
    segment of non-zero length; None for a lane without one."""
    p = np.asarray(points, np.float64)[:, :2]
    seg = np.diff(p, axis=0)
    ok = np.flatnonzero(np.hypot(seg[:, 0], seg[:, 1]) > 1e-9)
    if not len(ok):
        return None
    d = seg[ok[-1] if at_end else ok[0]]
    x, y = p[-1] if at_end else p[0]
    return float(x), float(y), math.atan2(float(d[1]), float(d[0])), int(group)


class SignalPlan:
    """The phases of ``groups`` (layout.signals.SignalGroup) on ``graph``'s lanes, offsets
    drawn from ``seed``."""

    def __init__(self, groups, graph, seed: int):
        self.groups = list(groups)
        self.ids = [g.id for g in self.groups]
        juncs: dict[str, list[int]] = {}
        for k, g in enumerate(self.groups):
            juncs.setdefault(g.junction, []).append(k)
        self.phase = [0] * len(self.groups)
        self.offset = [0.0] * len(self.groups)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x516]))
        for key in sorted(juncs):
            ks = sorted(juncs[key], key=lambda k: self.ids[k])
            off = float(rng.uniform(0.0, CYCLE))
            for k, ph in zip(ks, split_phases([self.groups[k].heading for k in ks])):
                self.phase[k], self.offset[k] = ph, off
        # lane index -> group index (a lane two groups name: the first)
        self.lane_group: dict[int, int] = {}
        for k, g in enumerate(self.groups):
            for lid in g.lane_ids:
                i = graph.index.get(lid)
                if i is not None:
                    self.lane_group.setdefault(i, k)
        self.junction = graph.junction
        # (x, y, heading, group) of every stop point, by the rule that stops the traffic
        # (stop_lane of each lane -> successor step): at the end of the lane being left, one
        # per group there
        marks: dict = {}
        for cur, nexts in enumerate(graph.succ):
            for nxt in nexts:
                lane = stop_lane(cur, nxt, self.lane_group, self.junction)
                if lane is not None and (cur, self.lane_group[lane]) not in marks:
                    k = self.lane_group[lane]
                    marks[(cur, k)] = _mark(graph.geoms[cur].points, True, k)
        for i, k in self.lane_group.items():     # a junction lane nothing leads into
            if self.junction[i] and not graph.pred[i] and stop_lane(-1, i, self.lane_group,
                                                                    self.junction) is not None:
                marks[(-1 - i, k)] = _mark(graph.geoms[i].points, False, k)
        self.stop_marks = [m for m in marks.values() if m is not None]

    def __len__(self) -> int:
        return len(self.groups)

    def state(self, k: int, t: float) -> str:
        return phase_state(t, self.phase[k], self.offset[k])

    def states(self, t: float) -> dict[str, str]:
        """Group id -> state at ``t``."""
        return {g: self.state(k, t) for k, g in enumerate(self.ids)}

    def lane_states(self, t: float) -> dict[int, str]:
        """Controlled lane index -> its group's state at ``t`` (the traffic model's input)."""
        return {i: self.state(k, t) for i, k in self.lane_group.items()}

    def group_at(self, cur: int, nxt: int) -> int | None:
        """The group controlling the step from lane ``cur`` into ``nxt`` (layout.signals'
        stop_lane), or None."""
        lane = stop_lane(cur, nxt, self.lane_group, self.junction)
        return None if lane is None else self.lane_group[lane]

    def route_stops(self, route) -> list[tuple[float, int]]:
        """(route distance, group) of every stop point the route crosses, in order."""
        out = []
        idx = route.idx
        for k in range(len(idx) - 1):
            g = self.group_at(idx[k], idx[k + 1])
            if g is not None:
                out.append((float(route.starts[k + 1]), g))
        return out
