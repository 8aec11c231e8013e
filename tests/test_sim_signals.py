"""Traffic lights in the closed loop: which lanes they control (layout.signals, the proxy's
lights), the fixed-time phases (sim.signals), running a red (CARLA's 0.7 penalty), the
planner and the traffic waiting at red."""
import math

import numpy as np
import pytest

from lsd3d_usd.actors.traffic import Simulation
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.layout.signals import signal_groups, stop_lane
from lsd3d_usd.layout.usdio import read_layout
from lsd3d_usd.proxy.chunks import ProxyParams, derive_fixtures
from lsd3d_usd.sim import signals as S
from lsd3d_usd.sim.env import DriveEnv
from lsd3d_usd.sim.policies import Constant, Planner
from lsd3d_usd.sim.scene import SimScene

from conftest import LAYOUT

EAST = "e_in,j_ew,w_out"        # the README sample's east approach: a derived traffic light
STOP_AT = 50.0                  # route distance of its stop point (e_in is 50 m long)


@pytest.fixture(scope="module")
def layout():
    return read_layout(LAYOUT)


@pytest.fixture(scope="module")
def opened(sim_scene):
    sc = SimScene(sim_scene)
    yield sc
    sc.close()


# -- which lanes -----------------------------------------------------------------------------
def test_the_simulators_lights_are_the_proxys(layout):
    groups = signal_groups(layout)
    proxy = [f for f in derive_fixtures(layout, ProxyParams()) if f.kind == "traffic_light"]
    assert [g.id for g in groups] == [f.id for f in proxy] == ["tl_e_in", "tl_n_in", "tl_s_in"]
    for g, f in zip(groups, proxy):
        assert g.light == (f.position[0], f.position[1], f.yaw)
    assert {g.junction for g in groups} == {"j_ew"}          # one 4-way junction
    assert all("w_in" not in g.lane_ids for g in groups)     # the stop sign's approach
    assert signal_groups(layout, derived=False) == []
    e = groups[0]
    assert e.stop == (10.0, 1.75) and e.heading == pytest.approx(math.pi)


def test_map_lights_replace_the_derived_ones_and_name_their_stop_points(layout):
    L = read_layout(LAYOUT)
    L.traffic_lights = [
        m.TrafficLight(id="map_e", position=np.array([12.0, 6.0, 0.0]), heading=0.0, lane_ids=["e_in"]),
        m.TrafficLight(id="map_e2", position=np.array([12.0, -6.0, 0.0]), heading=0.0, lane_ids=["e_in"]),
        m.TrafficLight(id="map_j", position=np.array([300.0, 300.0, 0.0]), heading=0.0,
                       lane_ids=["j_ns", "nowhere"]),
        m.TrafficLight(id="map_none", position=np.array([-300.0, 300.0, 0.0]), heading=0.0),
    ]
    groups = signal_groups(L)
    ids = [g.id for g in groups]
    # two heads naming e_in are one group; the derived lights near map_e are left out, as the
    # proxy leaves them out; a light naming no known lane controls nothing
    assert ids[:2] == ["map_e", "map_j"] and groups[0].map_lights == ("map_e", "map_e2")
    assert [i for i in ids if i.startswith("tl_")] == \
        [f.id for f in derive_fixtures(L, ProxyParams()) if f.kind == "traffic_light"]
    assert "tl_e_in" not in ids
    j = groups[1]
    assert j.lane_ids == ("j_ns",) and j.junction == "j_ew" and j.stop == (-1.75, 10.0)  # its start
    g = LaneGraph(L)
    ctl = {g.index["e_in"], g.index["j_ns"]}
    ix = g.index
    assert stop_lane(ix["e_in"], ix["j_ew"], ctl, g.junction) == ix["e_in"]
    assert stop_lane(ix["n_in"], ix["j_ns"], ctl, g.junction) == ix["j_ns"]
    assert stop_lane(ix["j_ns"], ix["s_out"], ctl, g.junction) is None
    assert stop_lane(ix["w_in"], ix["j_we"], ctl, g.junction) is None
    L.metadata = {"source": {"signalsComplete": True}}
    assert [g.id for g in signal_groups(L)] == ["map_e", "map_j"]


# -- phases ----------------------------------------------------------------------------------
def _reference_state(t, phase, offset):
    """The plan written out as a table (float64): phase 0 green [0, 12), yellow [12, 15),
    red [15, 34); phase 1 the same 17 s later."""
    u = (t + offset - 17.0 * phase) % 34.0
    return "green" if u < 12.0 else "yellow" if u < 15.0 else "red"


def test_phase_timing_is_exact():
    assert (S.GREEN, S.YELLOW, S.ALL_RED, S.CYCLE) == (12.0, 3.0, 2.0, 34.0)
    edges = {0.0: "green", 11.999: "green", 12.0: "yellow", 14.999: "yellow", 15.0: "red",
             33.999: "red", 34.0: "green", -0.001: "red", -20.0: "yellow"}
    for t, want in edges.items():
        assert S.phase_state(t, 0) == want, t
    for t, want in {16.999: "red", 17.0: "green", 29.0: "yellow", 32.0: "red", 51.0: "green"}.items():
        assert S.phase_state(t, 1) == want, t
    ts = np.arange(-40.0, 120.0, 0.05)
    for off in (0.0, 7.3, 33.9):
        got = [[S.phase_state(t, p, off) for t in ts] for p in (0, 1)]
        assert got == [[_reference_state(t, p, off) for t in ts] for p in (0, 1)]
        # never both phases moving: all red at least 2 s between them
        assert not any(a != "red" and b != "red" for a, b in zip(*got))
    assert S.split_phases([math.pi, -math.pi / 2, math.pi / 2, 0.1, 0.9]) == [0, 1, 1, 0, 1]
    assert S.split_phases([]) == []


def test_plan_is_seeded_per_junction_and_finds_the_routes_stop_points(layout):
    g = LaneGraph(layout)
    groups = signal_groups(layout)
    a, b, c = S.SignalPlan(groups, g, 1), S.SignalPlan(groups, g, 1), S.SignalPlan(groups, g, 2)
    assert a.offset == b.offset and a.offset != c.offset
    assert len(set(a.offset)) == 1 and 0.0 <= a.offset[0] < S.CYCLE     # one junction
    assert a.phase == [0, 1, 1]                 # east-west, then north and south
    for t in np.arange(0.0, 40.0, 0.5):
        st = a.states(t)
        assert st["tl_n_in"] == st["tl_s_in"]
        assert "red" in (st["tl_e_in"], st["tl_n_in"])
        assert a.lane_states(t) == {g.index["e_in"]: st["tl_e_in"], g.index["n_in"]: st["tl_n_in"],
                                    g.index["s_in"]: st["tl_s_in"]}
    assert a.route_stops(g.route(EAST.split(","))) == [(STOP_AT, 0)]
    assert a.route_stops(g.route(["w_in", "j_we", "e_out"])) == []       # a stop sign there


# -- in the loop -----------------------------------------------------------------------------
def _force(env, offset):
    """The east light's plan shifted so that t = 0 is ``offset`` s into its cycle."""
    env.signals.offset = [offset] * len(env.signals)


def _constant_run(env, offset):
    env.reset(seed=0, options={"route": EAST, "speed": 10.0})
    _force(env, offset)
    pol = Constant(env)
    obs, info = None, None
    rows = []
    while True:
        front = env.world.ego_d + env.limits.length / 2
        obs, _, term, trunc, info = env.step(pol(obs, info))
        rows.append((front, env.world.ego_d + env.limits.length / 2, info))
        if term or trunc:
            return rows


def test_running_a_red_counts_once_and_costs_point_seven(opened):
    env = DriveEnv(opened, rig="none", lidar="none", seconds=20.0, vehicles=0, pedestrians=0,
                   cyclists=0)
    rows = _constant_run(env, 15.0)             # red from t = 0 for 19 s
    s = env.episode_summary()
    assert rows[-1][2]["reason"] == "route_complete"
    assert s["infractions"]["red_light"] == 1
    assert s["driving_score"] == pytest.approx(0.7 * s["rc"]) and s["rc"] == 1.0
    ran = [k for k, (_, _, info) in enumerate(rows) if info["scores"]["red_light"]]
    assert len(ran) == 1
    before, after, _ = rows[ran[0]]
    assert before <= STOP_AT < after            # the step its front crosses the stop point
    first = rows[0]
    assert first[2]["signal"] == "red" and first[2]["red_light_m"] == pytest.approx(STOP_AT - first[1])
    assert rows[-1][2]["signal"] == "none" and math.isinf(rows[-1][2]["red_light_m"])
    for offset in (0.0, 9.0):                   # green, then yellow when it crosses: allowed
        rows = _constant_run(env, offset)
        s = env.episode_summary()
        assert s["infractions"]["red_light"] == 0 and s["driving_score"] == 1.0
    assert rows[0][2]["signal"] == "green" and math.isinf(rows[0][2]["red_light_m"])
    assert rows[-1][2]["signal"] == "none"
    env.close()


def test_the_planner_waits_at_a_red_and_goes_at_green(opened):
    env = DriveEnv(opened, rig="none", lidar="none", seconds=40.0, vehicles=0, pedestrians=0,
                   cyclists=0)
    obs, info = env.reset(seed=0, options={"route": EAST})
    _force(env, 15.0)                           # red until t = 19, then green
    pol = Planner(env)
    fronts = []
    while True:
        obs, _, term, trunc, info = env.step(pol(obs, info))
        fronts.append((env.t, env.world.ego_d + env.limits.length / 2, env.ego.v))
        if env.k == 1:                          # the world's traffic reads the same plan
            assert env.world.sim.signals == env.signals.lane_states(env.t - env.dt + 0.05)
        if term or trunc:
            break
    assert info["reason"] == "route_complete"
    s = env.episode_summary()
    assert s["infractions"]["red_light"] == 0 and s["driving_score"] == 1.0
    red = [(f, v) for t, f, v in fronts if t < 19.0 - 1e-9]
    assert max(f for f, _ in red) < STOP_AT     # held before the stop point while red
    assert min(v for f, v in red if f > STOP_AT - 6.0) < 0.1       # at rest near it
    assert max(f for f, _ in red) > STOP_AT - 6.0
    env.close()


def test_traffic_waits_at_red_and_leaves_the_junction_to_the_green(layout):
    sim = Simulation(layout, seed=0)
    g = sim.g
    east = sim.add_ego(g.route_indices(["e_in", "j_ew", "w_out"]), 4.5, s=10.0, v=10.0)
    sim.signals = {g.index["e_in"]: "red", g.index["n_in"]: "green", g.index["s_in"]: "green"}
    for _ in range(300):                         # 15 s of red
        sim.step(0.05)
    end = g.length[g.index["e_in"]]
    assert east.lane == g.index["e_in"] and east.v < 0.05
    # IDM comes to rest s0 before the wall stop_margin before the stop point
    assert end - sim.p.stop_margin - sim.p.s0 - 0.5 <= east.s + east.length / 2 <= end - sim.p.stop_margin
    assert not east.holds                        # waiting: it holds no junction lane
    # a crossing vehicle with green is not blocked by it
    north = sim.add_ego(g.route_indices(["n_in", "j_ns", "s_out"]), 4.5, s=20.0, v=8.0)
    for _ in range(200):
        sim.step(0.05)
    assert north.lane == g.index["s_out"]
    assert east.lane == g.index["e_in"]
    sim.signals[g.index["e_in"]] = "green"
    for _ in range(200):
        sim.step(0.05)
    assert east.lane in (g.index["j_ew"], g.index["w_out"])
    # without lights the same vehicle drives straight through
    free = Simulation(layout, seed=0)
    v = free.add_ego(g.route_indices(["e_in", "j_ew", "w_out"]), 4.5, s=10.0, v=10.0)
    for _ in range(300):
        free.step(0.05)
    assert v.lane != free.g.index["e_in"]


def test_traffic_too_close_to_stop_at_yellow_goes_through(layout):
    sim = Simulation(layout, seed=0)
    g = sim.g
    end = g.length[g.index["e_in"]]
    # front 8 m before the stop point at 10 m/s: 25 m needed at the comfortable 2 m/s^2
    near = sim.add_ego(g.route_indices(["e_in", "j_ew", "w_out"]), 4.5, s=end - 2.25 - 9.0, v=10.0)
    sim.signals = {g.index["e_in"]: "yellow"}
    for _ in range(20):
        sim.step(0.05)
    sim.signals = {g.index["e_in"]: "red"}     # it keeps going on the red that follows
    for _ in range(40):
        sim.step(0.05)
    assert near.lane != g.index["e_in"] and near.go_through == -1
    # far enough to stop: it stops
    far = Simulation(layout, seed=0)
    v = far.add_ego(g.route_indices(["e_in", "j_ew", "w_out"]), 4.5, s=5.0, v=10.0)
    far.signals = {g.index["e_in"]: "yellow"}
    for _ in range(300):
        far.step(0.05)
    assert v.lane == g.index["e_in"] and v.v < 0.05


def test_the_birds_eye_frame_shows_each_stop_bar_in_its_state(opened):
    from lsd3d_usd.sim.birdseye import SIGNAL_COLOURS, VIEW_M
    env = DriveEnv(opened, rig="none", lidar="none", seconds=40.0, vehicles=0, pedestrians=0,
                   cyclists=0, render_mode="rgb_array")
    env.reset(seed=0, options={"route": EAST, "start": 40.0})    # 10 m before the stop point
    marks = env.signals.stop_marks
    # the lights' groups, each at the end of the approach lane it governs (stop_lane's rule)
    assert sorted(env.signals.ids[k] for *_, k in marks) == ["tl_e_in", "tl_n_in", "tl_s_in"]
    east = [m_ for m_ in marks if env.signals.ids[m_[3]] == "tl_e_in"]
    assert len(east) == 1 and east[0][:2] == pytest.approx((10.0, 1.75))
    assert east[0][2] == pytest.approx(math.pi)

    def colour_at_east_bar():
        img = env.render()
        bev = env._bev
        cx, cy = bev._px(env.ego.box_centre(env.limits))
        x, y = bev._px(east[0][:2])
        scale = bev.size / (VIEW_M * bev.ppm)
        i, j = int((y - cy) * scale + bev.size / 2), int((x - cx) * scale + bev.size / 2)
        return tuple(int(c) for c in img[i, j])
    _force(env, 15.0)                           # the east approach red
    assert env.signals.state(east[0][3], env.t) == "red"
    assert colour_at_east_bar() == SIGNAL_COLOURS["red"]
    _force(env, 0.0)                            # the east approach green
    assert env.signals.state(east[0][3], env.t) == "green"
    assert colour_at_east_bar() == SIGNAL_COLOURS["green"]
    env.close()
