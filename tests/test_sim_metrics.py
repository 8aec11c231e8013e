"""Driving scores (lsd3d_usd.sim.metrics) on hand-built trajectories whose scores are known,
and the oriented-box geometry (lsd3d_usd.sim.geometry2d) against shapely."""
import json
import math

import numpy as np
import pytest
import shapely

from lsd3d_usd.errors import InputError
from lsd3d_usd.sim import metrics as m
from lsd3d_usd.sim.geometry2d import (box_corners, box_geometry, box_inside, boxes_overlap,
                                      relative_angle)

DT = 0.1
L, W = 4.5, 2.0
ROAD = shapely.box(-20.0, -4.0, 200.0, 4.0)       # a straight road along +x, 8 m wide
ROUTE = np.array([[0.0, 0.0], [100.0, 0.0]])


def vehicle(oid, x, y=0.0, vx=0.0, yaw=0.0, kind="vehicle", length=L, width=W):
    return (oid, (x, y), yaw, length, width, (vx, 0.0), kind)


def agents(rows):
    if not rows:
        return None
    ids, xy, yaw, ln, wd, vel, kind = zip(*rows)
    return m.Agents(ids, xy, yaw, ln, wd, vel, kind)


def drive(xs, speeds, *, ys=None, yaws=None, others=None, flags=None, **keeper):
    """Run a ScoreKeeper over an ego pose series; returns (keeper, per-step outputs)."""
    sk = m.ScoreKeeper(ROUTE, drivable=ROAD, **keeper)
    outs = []
    for k, (x, v) in enumerate(zip(xs, speeds)):
        st = m.StepState(t=k * DT, xy=(x, 0.0 if ys is None else ys[k]),
                         yaw=0.0 if yaws is None else yaws[k], speed=v, length=L, width=W,
                         agents=agents(others(k) if others else []),
                         **(flags(k) if flags else {}))
        outs.append(sk.update(st))
    return sk, outs


def cruise(n, v=10.0, x0=0.0):
    return [x0 + v * DT * k for k in range(n)], [v] * n


# -- geometry ------------------------------------------------------------------------------
def test_box_corners_are_counter_clockwise_front_first():
    c = box_corners((1.0, 2.0), math.pi / 2, 4.0, 2.0)
    np.testing.assert_allclose(c, [[2, 4], [0, 4], [0, 0], [2, 0]], atol=1e-12)
    assert shapely.Polygon(c).exterior.is_ccw
    assert box_corners(np.zeros((3, 5, 2)), np.zeros(5), 1.0, 1.0).shape == (3, 5, 4, 2)


def test_sat_overlap_matches_shapely_on_random_boxes_including_degenerate():
    rng = np.random.default_rng(7)
    n = 3000
    xy = rng.uniform(-4, 4, (n, 2))
    yaw = rng.uniform(-np.pi, np.pi, (2, n))
    size = rng.uniform(0, 4, (2, n, 2))
    size[rng.random((2, n, 2)) < 0.15] = 0.0           # segments and points
    got = boxes_overlap((0.0, 0.0), yaw[0], size[0, :, 0], size[0, :, 1],
                        xy, yaw[1], size[1, :, 0], size[1, :, 1])
    disagree = 0
    for i in range(n):
        a = box_geometry((0.0, 0.0), yaw[0, i], size[0, i, 0], size[0, i, 1])
        b = box_geometry(xy[i], yaw[1, i], size[1, i, 0], size[1, i, 1])
        if bool(got[i]) != a.intersects(b):
            disagree += 1
            assert a.distance(b) < 1e-7, (i, a, b)     # only at float64 touching
    assert disagree <= 3
    assert 0.2 < got.mean() < 0.8                        # both outcomes exercised


def test_sat_touching_boxes_overlap_and_a_gap_separates():
    for yaw in (0.0, 0.5236, -2.0):
        u = np.array([math.cos(yaw), math.sin(yaw)])
        for gap, want in ((0.0, True), (1e-6, False)):
            b = (4.0 + gap) * u                      # end to end along the heading
            got = bool(boxes_overlap((0, 0), yaw, 4.0, 2.0, b, yaw, 4.0, 2.0))
            ref = box_geometry((0, 0), yaw, 4.0, 2.0).intersects(
                box_geometry(b, yaw, 4.0, 2.0))
            assert got == want
            if gap == 0.0 and yaw == 0.0:
                assert ref
    # a point on a box's edge, a zero-size box inside, crossing segments, parallel segments
    assert boxes_overlap((0, 0), 0, 4, 2, (2, 0.3), 0.7, 0, 0)
    assert boxes_overlap((0, 0), 0, 4, 2, (0, 0), 0.3, 0, 0)
    assert boxes_overlap((0, 0), 0, 4, 0, (0, 0), math.pi / 2, 4, 0)
    assert not boxes_overlap((0, 0), 0, 4, 0, (0, 0.5), 0, 4, 0)
    assert not boxes_overlap((0, 0), 0, 0, 0, (1e-3, 0), 0, 0, 0)


def test_box_inside_and_relative_angle():
    assert box_inside(ROAD, (10, 0), 0, L, W)
    assert box_inside(ROAD, (10, 3.0), 0, L, W)          # corner on the edge is inside
    assert not box_inside(ROAD, (10, 3.5), 0, L, W)
    ang = relative_angle((0, 0), 0.0, [[1, 0], [0, 1], [-1, 0], [0, 0]])
    np.testing.assert_allclose(ang, [0, np.pi / 2, np.pi, 0])


# -- kinematics and comfort ----------------------------------------------------------------
def brake_series(n=30):
    v = np.full(n, 10.0)
    for k in range(11, 16):
        v[k] = 10.0 - 8.0 * DT * (k - 10)
    v[16:] = v[15]
    x = np.concatenate([[0.0], np.cumsum(v[1:] * DT)])
    return x, v


def test_hard_brake_fails_comfort_at_those_steps_only():
    x, v = brake_series()
    sk, outs = drive(x, v)
    failed = [o["step"] for o in outs if o["comfort"] == 0.0]
    assert failed == list(range(11, 17))         # -8 m/s^2 at 11..15, jerk at 11 and 16
    assert outs[12]["comfort_failed"] == ["lon_acc"]
    assert set(outs[11]["comfort_failed"]) == {"lon_acc", "jerk"}
    assert outs[16]["comfort_failed"] == ["jerk"]
    assert outs[13]["lon_acc"] == pytest.approx(-8.0)
    s = sk.summary()
    assert s["comfort"] == pytest.approx(1 - 6 / 30) and not s["comfort_all"]
    kin = m.ego_kinematics(np.arange(30) * DT, np.c_[x, np.zeros(30)], np.zeros(30), v)
    for key in ("lon_acc", "lat_acc", "jerk", "lon_jerk", "yaw_rate", "yaw_acc"):
        np.testing.assert_allclose(kin[key], [o[key] for o in outs], atol=1e-9)


def test_kinematics_of_a_circle():
    t = np.arange(40) * DT
    r, v = 20.0, 8.0                                # yaw rate 0.4 rad/s, lat acc 3.2
    th = v / r * t
    xy = np.c_[r * np.sin(th), r * (1 - np.cos(th))]
    kin = m.ego_kinematics(t, xy, th + np.pi * 2 * (t > 2))    # wrapped yaw is unwrapped
    np.testing.assert_allclose(kin["yaw_rate"][1:], 0.4, atol=1e-9)
    np.testing.assert_allclose(kin["lat_acc"][2:], 3.2, rtol=1e-3)
    np.testing.assert_allclose(kin["yaw_acc"], 0.0, atol=1e-9)
    assert not m.comfort_failures({k: a[5] for k, a in kin.items()})


# -- collisions ----------------------------------------------------------------------------
def test_collision_at_a_given_step_is_one_event_for_nc_and_carla():
    # ego at 10 m/s reaches a parked van at x=30 at step 26 (front 26+2.25 >= 30-2.25) and
    # stays in contact 5 steps (the van is then removed).
    xs, vs = cruise(26)
    xs += [26.0] * 14
    vs += [10.0] + [0.0] * 13                        # hits at 10 m/s, then stopped
    sk, outs = drive(xs, vs, others=lambda k: [vehicle("van", 30.0)] if k <= 30 else [])
    nc = [o["nc"] for o in outs]
    assert nc[:26] == [1.0] * 26 and nc[26:31] == [0.0] * 5 and nc[31:] == [1.0] * 9
    assert [o["step"] for o in outs if o["new_collisions"]] == [26]
    ev = outs[26]["new_collisions"][0]
    assert ev["type"] == "stopped_track" and ev["at_fault"] and ev["other"] == "van"
    s = sk.summary()
    assert s["nc"] == 0.0 and s["at_fault_collisions"] == 1 and s["contacts"] == 1
    assert s["infractions"]["collision_vehicle"] == 1
    assert s["infraction_penalty"] == pytest.approx(0.6)
    assert s["driving_score"] == pytest.approx(s["rc"] * 0.6)
    assert s["rc"] == pytest.approx(0.26)
    json.dumps(outs, allow_nan=False)
    json.dumps(s, allow_nan=False)


def test_a_second_contact_with_the_same_agent_is_a_second_event():
    xs, vs = cruise(40)
    present = lambda k: [vehicle("a", xs[k] + 4.0, vx=10.0)] if k in (5, 6, 20) else []
    sk, _ = drive(xs, vs, others=present)
    s = sk.summary()
    assert s["contacts"] == 2
    # the car ahead moves at the ego's speed: its rear in the ego's front -> at fault
    assert [c["type"] for c in s["collisions"]] == ["active_front", "active_front"]
    assert s["infraction_penalty"] == pytest.approx(0.36)


def test_rear_ended_while_stopped_is_not_at_fault():
    n = 30
    sk, outs = drive([0.0] * n, [0.0] * n,
                     others=lambda k: [vehicle("tail", -12.0 + 0.5 * k, vx=5.0)])
    s = sk.summary()
    assert s["contacts"] == 1 and s["at_fault_collisions"] == 0
    assert s["collisions"][0]["type"] == "stopped_ego"
    assert s["nc"] == 1.0 and s["infraction_penalty"] == 1.0
    assert s["driving_score_all_contacts"] == pytest.approx(s["rc"] * 0.6)
    assert all(o["ttc"] == 1.0 for o in outs)


def test_hit_from_behind_while_moving_is_not_at_fault_but_lateral_off_road_is():
    xs, vs = cruise(10)
    sk, _ = drive(xs, vs, others=lambda k: [vehicle("b", xs[k] - 4.0, vx=12.0)])
    assert sk.summary()["collisions"][0]["type"] == "active_rear"
    assert sk.summary()["nc"] == 1.0
    # a car alongside touching the ego's flank, the ego partly off the road: at fault
    ys = [3.5] * 10
    sk, _ = drive(xs, vs, ys=ys,
                  others=lambda k: [vehicle("c", xs[k] - 1.0, y=1.6, vx=10.0)])
    ev = sk.summary()["collisions"][0]
    assert ev["type"] == "active_lateral" and ev["at_fault"]


def test_static_obstacle_and_pedestrian_penalties():
    pole = shapely.Point(20.0, 0.5).buffer(0.2)
    xs, vs = cruise(25)
    sk, outs = drive(xs, vs, obstacles=[pole], obstacle_ids=["pole"])
    s = sk.summary()
    assert s["nc"] == 0.5 and s["infractions"]["collision_static"] == 1
    assert s["infraction_penalty"] == pytest.approx(0.65)
    first = next(o for o in outs if o["new_collisions"])
    assert first["new_collisions"][0]["other"] == "pole"
    assert first["step"] == 18                       # front x + 2.25 >= 19.8 from x = 18
    sk, _ = drive(xs, vs, others=lambda k: [vehicle("p", 15.0, kind="pedestrian",
                                                    length=0.5, width=0.5)])
    s = sk.summary()
    assert s["nc"] == 0.0 and s["infraction_penalty"] == pytest.approx(0.5)


# -- DAC, DDC, TTC, signals ----------------------------------------------------------------
def test_excursion_off_the_road():
    xs, vs = cruise(40)
    ys = [0.0] * 40
    for k in range(20, 25):
        ys[k] = 3.5                                   # left corners at y = 4.5 > 4
    sk, outs = drive(xs, vs, ys=ys)
    assert [o["step"] for o in outs if o["dac"] == 0.0] == list(range(20, 25))
    s = sk.summary()
    assert s["dac"] == 0.0 and s["offroad_steps"] == 5
    assert s["pdms"] is None and s["hd_score"] < s["rc"]


@pytest.mark.parametrize("steps,want", [(1, 1.0), (5, 0.5), (10, 0.0)])
def test_wrong_way_driving(steps, want):
    xs, vs = cruise(40)                               # 1 m per step
    sk, outs = drive(xs, vs, flags=lambda k: {"wrong_way": 10 <= k < 10 + steps})
    s = sk.summary()
    assert s["ddc"] == want
    assert s["max_wrong_way_m"] == pytest.approx(min(steps, 11))
    assert outs[39]["ddc"] == 1.0


def test_ttc_fires_one_second_before_contact_with_a_car_ahead_only():
    xs, vs = cruise(40)
    others = lambda k: [vehicle("parked", 50.0), vehicle("side", xs[k], y=-3.0, vx=10.0),
                        vehicle("chaser", xs[k] - 8.0, vx=20.0)]
    sk, outs = drive(xs, vs, others=others)
    # the chaser behind touches the ego at step 4 (not at fault) and is never a TTC risk;
    # the parked car: ego x + 10 m >= 45.5 from step 36
    ttc = [o["ttc"] for o in outs]
    assert ttc[:36] == [1.0] * 36 and ttc[36:] == [0.0] * 4
    assert sk.summary()["ttc"] == pytest.approx(36 / 40)
    sk, outs = drive([40.0] * 5, [0.0] * 5, others=lambda k: [vehicle("parked", 50.0)])
    assert all(o["ttc"] == 1.0 for o in outs)          # a stopped ego is not at risk


def test_red_lights_and_stop_signs_count_once_per_event():
    xs, vs = cruise(60)
    flags = lambda k: {"red_light": k in (20, 21, 22, 40), "stop_sign": k == 50}
    sk, outs = drive(xs, vs, flags=flags)
    assert [o["step"] for o in outs if o["red_light"]] == [20, 40]
    s = sk.summary()
    assert s["infractions"]["red_light"] == 2 and s["infractions"]["stop_sign"] == 1
    assert s["infraction_penalty"] == pytest.approx(0.7 * 0.7 * 0.8)
    assert s["driving_score"] == pytest.approx(s["rc"] * 0.392)


# -- progress and composites ---------------------------------------------------------------
def test_route_completion_and_ego_progress():
    xs, vs = cruise(50)                                # x 0 .. 49 on a 100 m route
    sk, outs = drive(xs, vs, reference=(np.arange(50) * DT, 12.0 * np.arange(50) * DT))
    s = sk.summary()
    assert s["rc"] == pytest.approx(0.49) and s["progress_m"] == pytest.approx(49.0)
    assert s["ep"] == pytest.approx(49.0 / (12.0 * 4.9))
    assert outs[3]["ep"] == 1.0                       # both under 5 m
    assert outs[10]["ep"] == pytest.approx(10.0 / 12.0)
    assert sk.summary(reference=40.0)["ep"] == 1.0
    assert m.ego_progress_score(3.0, 4.0) == 1.0
    assert m.ego_progress_score(0.0, 10.0) == 0.0
    assert m.ego_progress_score(-2.0, 10.0) == 0.0
    assert m.route_completion(150.0, 100.0) == 1.0
    # clean run: NC = DAC = TTC = C = 1
    assert s["pdms"] == pytest.approx((5 + 2 + 5 * s["ep"]) / 12)
    assert s["hd_score"] == pytest.approx(s["rc"])
    assert s["driving_score"] == pytest.approx(s["rc"])


def test_composites_on_the_collision_run():
    xs, vs = cruise(26)
    xs += [26.0] * 4
    vs += [10.0] + [0.0] * 3
    sk, outs = drive(xs, vs, others=lambda k: [vehicle("van", 30.0)], reference=40.0)
    s = sk.summary()
    assert s["pdms"] == 0.0                           # NC = 0 multiplies everything
    steps = [m.hugsim_step_score(o["nc"], o["dac"], o["ttc"], o["comfort"]) for o in outs]
    assert s["hd_score"] == pytest.approx(s["rc"] * np.mean(steps))
    # before the van: TTC fails from step 16 (x + 10 >= 25.5), comfort fails at the stop
    assert outs[15]["hugsim"] == 1.0 and outs[16]["hugsim"] == pytest.approx(2 / 7)
    assert m.pdms(1, 1, 1, 1, 1) == 1.0
    assert m.pdms(0.5, 1, 1, 0, 1) == pytest.approx(0.5 * 10 / 12)
    assert m.carla_driving_score(0.8, {"collision_pedestrian": 1, "red_light": 1}) == \
        pytest.approx(0.8 * 0.35)


def test_bad_input_names_it():
    sk = m.ScoreKeeper(ROUTE)
    sk.update(m.StepState(t=0.0, xy=(0, 0), yaw=0.0, speed=0.0, length=L, width=W))
    with pytest.raises(InputError, match="time must increase"):
        sk.update(m.StepState(t=0.0, xy=(0, 0), yaw=0.0, speed=0.0, length=L, width=W))
    with pytest.raises(InputError, match="unknown kind 'truck'"):
        agents([vehicle("x", 0.0, kind="truck")])
    with pytest.raises(InputError, match="unknown infraction"):
        m.infraction_penalty({"speeding": 1})
    with pytest.raises(InputError, match="before any update"):
        m.ScoreKeeper(ROUTE).summary()
