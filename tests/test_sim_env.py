"""The closed-loop env (lsd3d_usd.sim): Gymnasium's own checker, determinism, the world
reacting to the ego, the planner against the constant-velocity baseline, bad input."""
import json
import math

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import lsd3d_usd  # noqa: F401
from lsd3d_usd.actors.pedestrians import STAND
from lsd3d_usd.errors import InputError
from lsd3d_usd.sim import ENV_ID
from lsd3d_usd.sim.env import DriveEnv
from lsd3d_usd.sim.policies import Planner, load_policy
from lsd3d_usd.sim.scene import SimScene


@pytest.fixture(scope="module")
def scene(sim_scene):
    return sim_scene          # conftest: one scene shared by the sim tests


@pytest.fixture(scope="module")
def opened(scene):
    sc = SimScene(scene)
    yield sc
    sc.close()


def _drive(env, policy, seed, route=None, max_steps=2000):
    obs, info = env.reset(seed=seed, options={"route": route} if route else None)
    pol = policy if callable(policy) else load_policy(policy, env)
    for _ in range(max_steps):
        obs, _, term, trunc, info = env.step(pol(obs, info))
        if term or trunc:
            return info
    return info


def test_gymnasium_checker_passes_with_sensors_and_render(opened):
    env = DriveEnv(opened, rig="nuscenes6", width=32, seconds=1.0, vehicles=2, pedestrians=2,
                   cyclists=1, outputs=("rgb", "depth", "semantic", "instance"),
                   render_mode="rgb_array")
    check_env(env, skip_render_check=False)
    obs, _ = env.reset(seed=1)
    assert set(obs["cameras"]) == {"CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK",
                                   "CAM_BACK_LEFT", "CAM_BACK_RIGHT"}
    assert obs["cameras"]["CAM_FRONT"]["rgb"].shape == (18, 32, 3)
    assert obs["lidar"]["count"] > 100                       # hdl32 sees the street
    assert env.render().shape[2] == 3


def test_trajectory_mode_checker_and_registration(scene):
    env = gymnasium.make(ENV_ID, scene=scene, rig="none", action="trajectory", seconds=1.0,
                         vehicles=1, pedestrians=1, cyclists=0)
    check_env(env.unwrapped)
    assert env.action_space.shape == (8, 2)
    env.close()


def test_same_seed_same_observations_and_scores(opened):
    def episode():
        env = DriveEnv(opened, rig="nuscenes6", cameras=("CAM_FRONT",), width=32, seconds=1.5,
                       vehicles=3, pedestrians=2, cyclists=1)
        obs, info = env.reset(seed=7)
        pol = Planner(env)
        frames, scores = [], []
        for _ in range(15):
            obs, r, term, trunc, info = env.step(pol(obs, info))
            frames.append((obs["cameras"]["CAM_FRONT"]["rgb"].tobytes(),
                           obs["lidar"]["points"].tobytes(), obs["ego"]["pose"].tobytes()))
            scores.append(json.dumps(info["scores"], sort_keys=True))
            if term or trunc:
                break
        return frames, scores, env.episode_summary()
    a, b = episode(), episode()
    assert a[0] == b[0] and a[1] == b[1] and a[2] == b[2]


def test_a_vehicle_behind_a_stopped_ego_stops_with_the_minimum_gap(opened):
    env = DriveEnv(opened, rig="none", seconds=30.0, vehicles=0, pedestrians=0, cyclists=0)
    env.reset(seed=0, options={"route": "w_in,j_we,e_out", "start": 30.0})
    sim = env.world.sim
    follower = sim.add_ego(sim.g.route_indices(["w_in"]), 4.5, s=5.0, v=8.0, free=True)
    sim.veh.remove(follower)
    sim.veh.append(follower)                    # an ordinary vehicle 25 m behind, at 8 m/s
    env.world.slots.append(follower)
    env.actors.actors.append(env.actors.actors[0])
    env.actors._M.append(np.eye(4))
    env.actors._vis.append(True)
    gaps = []
    for _ in range(150):                         # the ego stands still in its lane
        env.step(np.array([-8.0, 0.0], np.float32))
        ego_rear = env.world.ego_d - env.limits.length / 2
        gaps.append(ego_rear - (follower.s + follower.length / 2))
    assert follower.v < 0.05 and follower.lane == sim.g.index["w_in"]
    assert min(gaps) >= sim.p.min_gap - 1e-6 and gaps[-1] < sim.p.s0 + 1.5
    assert env.episode_summary()["at_fault_collisions"] == 0


def test_the_planner_stops_for_a_pedestrian_on_a_crosswalk(opened):
    env = DriveEnv(opened, rig="none", seconds=25.0, vehicles=0, pedestrians=1, cyclists=0)
    obs, info = env.reset(seed=0, options={"route": "w_in,j_we,e_out"})
    polys = env.scene.layout.crosswalks
    route = env.route
    # the first crosswalk the route crosses: a pedestrian stands on it, in the ego's lane
    hits = []
    for cw in polys:
        c = np.asarray(cw.polygon, float)[:, :2].mean(0)
        d, off = route.project(c)
        if abs(off) < 3.0 and d > env.world.ego_d + 10:
            hits.append((d, c))
    d_cw, _ = min(hits, key=lambda h: h[0])
    p = env.world.street.crowd.people[0]
    xy = route.pose2d(d_cw)
    p.state, p.xy, p.yaw, p.v = STAND, np.array(xy[:2]), xy[2] + math.pi / 2, 0.0
    pol = Planner(env)
    closest = math.inf
    for _ in range(250):
        obs, _, term, trunc, info = env.step(pol(obs, info))
        front = env.world.ego_d + env.limits.length / 2
        closest = min(closest, d_cw - front)
        if term or trunc:
            break
    assert env.ego.v < 0.05 and 0.3 < closest < 6.0        # stopped before it, not on it
    assert env.episode_summary()["at_fault_collisions"] == 0


def test_the_planner_follows_a_cyclist(opened):
    env = DriveEnv(opened, rig="none", seconds=10.0, vehicles=0, pedestrians=0, cyclists=1)
    obs, info = env.reset(seed=0, options={"route": "w_in,j_we,e_out", "speed": 6.0})
    sim, g = env.world.sim, env.world.graph
    cyc = env.world.slots[0]
    assert cyc.cyclist
    cyc.lane, cyc.s, cyc.v, cyc.v_max = g.index["w_in"], env.world.ego_d + 18.0, 3.0, 3.0
    cyc.plan, cyc.holds = [g.index["j_we"], g.index["e_out"]], {}
    cyc.offset = sim.cyclist_offset(cyc.lane, cyc.width)
    pol = Planner(env)
    gaps = []
    for _ in range(80):
        obs, _, term, trunc, info = env.step(pol(obs, info))
        gaps.append(info["leader_gap_m"])
        if term or trunc:
            break
    assert min(gaps) > sim.p.min_gap and env.ego.v < 3.6          # behind it, at its pace
    assert env.episode_summary()["at_fault_collisions"] == 0


def test_planner_completes_where_constant_velocity_fails(opened):
    env = DriveEnv(opened, rig="none", seconds=40.0, vehicles=4, pedestrians=2, cyclists=1,
                   ep_reference="planner")
    route = "w_in,j_ws,s_out"                        # a turn: straight ahead leaves the road
    planner = _drive(env, "planner", 3, route)
    assert planner["reason"] == "route_complete"
    s = env.episode_summary()
    assert s["rc"] == 1.0 and s["nc"] == 1.0 and s["dac"] == 1.0 and s["pdms"] > 0.9
    const = _drive(env, "constant", 3, route)
    assert const["reason"] in ("off_road", "collision")
    assert env.episode_summary()["driving_score"] < s["driving_score"]


def test_bad_actions_and_options(opened):
    env = DriveEnv(opened, rig="none", seconds=2.0, vehicles=0, pedestrians=0, cyclists=0)
    env.reset(seed=0)
    with pytest.raises(InputError, match=r"action: shape \(3,\), expected \(2,\)"):
        env.step(np.zeros(3, np.float32))
    obs, r, term, trunc, info = env.step(np.array([np.nan, 0.0], np.float32))
    assert term and "NaN" in info["reason"]
    with pytest.raises(InputError, match="step after the episode ended"):
        env.step(np.zeros(2, np.float32))
    _, info = env.reset(seed=0)
    env.step(np.array([50.0, 3.0], np.float32))      # beyond the limits: clipped and counted
    assert env.clipped == 1 and env.ego.a <= env.limits.a_max + 1e-9
    with pytest.raises(InputError, match="'nope' is not a lane"):
        env.reset(seed=0, options={"route": "nope"})
    with pytest.raises(InputError, match="unknown key 'teleport'"):
        env.reset(seed=0, options={"teleport": 1})
    with pytest.raises(InputError, match="--rig 'no_such_rig'"):
        DriveEnv(opened, rig="no_such_rig")
    with pytest.raises(InputError, match="--action 'fly'"):
        DriveEnv(opened, action="fly")
    with pytest.raises(InputError, match="cannot import 'no_such_module'"):
        load_policy("no_such_module:drive", env)
    with pytest.raises(InputError, match="choose planner, constant, scenario or MODULE:CALLABLE"):
        load_policy("ramdom", env)


def test_stop_sign_the_planner_stops_at_and_constant_velocity_runs(opened):
    env = DriveEnv(opened, rig="none", seconds=40.0, vehicles=0, pedestrians=0, cyclists=0)
    route = "w_in,j_we,e_out"                     # the README sample's west approach: a stop sign
    info = _drive(env, "planner", 0, route)
    assert info["reason"] == "route_complete"
    s = env.episode_summary()
    assert s["infractions"]["stop_sign"] == 0 and s["driving_score"] == 1.0
    info = _drive(env, "constant", 0, route)
    s = env.episode_summary()
    assert s["infractions"]["stop_sign"] == 1 and s["driving_score"] == pytest.approx(0.8 * s["rc"])
