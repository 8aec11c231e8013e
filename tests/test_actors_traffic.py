"""IDM traffic over the lane graph: gaps, speed limits, staying on lanes, determinism."""
from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import LineString, Point

from lsd3d_usd.actors.traffic import IDMParams, Simulation, simulate
from lsd3d_usd.layout.routes import LaneGraph, constant_speed_route
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.model import LaneCenter, Layout


@pytest.fixture(scope="module")
def layout():
    from lsd3d_usd.layout.generator import generate
    return generate(5, (200.0, 200.0))


@pytest.fixture(scope="module")
def run(layout):
    lengths = [4.55, 5.25, 4.55, 8.05, 4.55, 11.95] * 4
    return simulate(layout, lengths, seed=7, seconds=20.0, fps=10.0)


def test_min_gap_on_same_lane(run):
    p = run.params
    assert run.n >= 20
    for k in range(len(run.t)):
        for i in range(run.n):
            for j in range(i + 1, run.n):
                if run.lane[i, k] != run.lane[j, k]:
                    continue
                gap = abs(run.s[i, k] - run.s[j, k]) - (run.lengths[i] + run.lengths[j]) / 2
                assert gap >= p.min_gap - 1e-6, (i, j, k, gap)


def test_speeds_within_limits_and_moving(run):
    lim = run.lane_limits[run.lane]
    assert np.all(run.speed <= lim + 1e-9)
    assert np.all(run.speed >= 0)
    assert run.speed.max() > 5.0            # traffic does move
    # displacement between samples agrees with the speeds (no teleporting)
    step = np.linalg.norm(np.diff(run.position, axis=1), axis=2)
    assert np.all(step <= lim.max() / 10.0 + 1e-6)


def test_positions_on_lanes_and_links_followed(layout, run):
    lanes = {ln.id: ln for ln in layout.lanes}
    for i in range(run.n):
        for k in range(0, len(run.t), 7):
            lane = lanes[run.lane_ids[run.lane[i, k]]]
            d = LineString(lane.points[:, :2]).distance(Point(run.position[i, k, :2]))
            assert d < 1e-6
        changes = np.flatnonzero(np.diff(run.lane[i]))
        for k in changes:
            a, b = run.lane_ids[run.lane[i, k]], run.lane_ids[run.lane[i, k + 1]]
            assert b in lanes[a].successors or any(b in lanes[m].successors for m in lanes[a].successors)


def test_deterministic_and_seed_dependent(layout):
    a = simulate(layout, [4.5] * 10, seed=3, seconds=5.0, fps=10.0)
    b = simulate(layout, [4.5] * 10, seed=3, seconds=5.0, fps=10.0)
    c = simulate(layout, [4.5] * 10, seed=4, seconds=5.0, fps=10.0)
    assert np.array_equal(a.position, b.position) and np.array_equal(a.lane, b.lane)
    assert not np.array_equal(a.position[:, 0], c.position[:, 0])


def _straight(n=1, length=200.0, limit=10.0):
    lanes = [LaneCenter("a", points=[[0, 0, 0], [length, 0, 0]], speed_limit_mps=limit)]
    return Layout(lanes=lanes)


def test_follower_stops_behind_stopped_leader():
    """A vehicle at a dead end stops before the lane end; the follower keeps the IDM gap."""
    L = _straight(length=120.0)
    sim = Simulation(L, 0)
    sim.add_ego(sim.g.route_indices(["a"]), 4.5, s=60.0, v=10.0)   # stops at the lane end
    sim.add_ego(sim.g.route_indices(["a"]), 4.5, s=20.0, v=10.0)   # follower (inserted first)
    r = sim.run(30.0, 10.0)
    assert r.speed[:, -1].max() < 0.05
    lead, foll = (0, 1) if r.s[0, -1] > r.s[1, -1] else (1, 0)
    assert r.s[lead, -1] <= 120.0 - 4.5 / 2 - IDMParams().stop_margin + 1e-6
    gap = r.s[lead, -1] - r.s[foll, -1] - 4.5
    assert IDMParams().min_gap <= gap < IDMParams().s0 + 1.0


def test_route_validation_and_constant_speed(layout):
    g = LaneGraph(layout)
    i = next(k for k in range(len(g.ids)) if g.succ[k])
    route = [g.ids[i], g.ids[g.succ[i][0]]]
    pos, yaw = constant_speed_route(layout, route, 5.0, np.arange(0, 3, 0.5))
    assert np.allclose(np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1)[:2], 2.5, atol=0.05)
    with pytest.raises(InputError, match="not a lane of the layout; drivable lanes nearby"):
        constant_speed_route(layout, ["no_such_lane"], 5.0, [0.0])
    bad = next(k for k in range(len(g.ids)) if k != i and k not in g.succ[i])
    with pytest.raises(InputError, match="does not follow"):
        constant_speed_route(layout, [g.ids[i], g.ids[bad]], 5.0, [0.0])
