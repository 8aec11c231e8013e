"""OpenSCENARIO scenarios: reading (safe, parameters, catalogs), OpenDRIVE lane positions,
and the player's semantics against closed forms (scenarios written by scenariogeneration)."""
from __future__ import annotations

import math
import warnings

import pytest

pytest.importorskip("scenariogeneration")
from scenariogeneration import xodr, xosc  # noqa: E402

from lsd3d_usd.errors import InputError  # noqa: E402
from lsd3d_usd.layout.opendrive import read_opendrive  # noqa: E402
from lsd3d_usd.sim.scenario.lanes import lane_position  # noqa: E402
from lsd3d_usd.sim.scenario.player import ScenarioPlayer  # noqa: E402
from lsd3d_usd.sim.scenario.reader import read_scenario  # noqa: E402

DT = 0.05
W = 3.5


def write_road(path, geometry=None, right=2, left=0, length=400.0):
    odr = xodr.OpenDrive("road")
    r = xodr.create_road(geometry or [xodr.Line(length)], id=1, left_lanes=left, right_lanes=right,
                         lane_width=W)
    odr.add_road(r)
    odr.adjust_roads_and_lanes()
    odr.write_xml(str(path))


def write_junction(path, arm=100.0):
    """A four-arm junction (scenariogeneration's CommonJunctionCreator, radius 15 m): roads
    1..4 of ``arm`` m, each ending at the junction, connected straight on (1-3, 2-4) and 1-2."""
    odr = xodr.OpenDrive("junction")
    jc = xodr.CommonJunctionCreator(100, "j")
    for k in range(1, 5):
        r = xodr.create_road(xodr.Line(arm), id=k, left_lanes=1, right_lanes=1, lane_width=W)
        jc.add_incoming_road_circular_geometry(r, 15.0, (k - 1) * math.pi / 2, "successor")
        odr.add_road(r)
    for a, b in ((1, 3), (2, 4), (1, 2)):
        jc.add_connection(a, b)
    odr.add_junction_creator(jc)
    odr.adjust_roads_and_lanes()
    odr.write_xml(str(path))


def vehicle(name="car"):
    bb = xosc.BoundingBox(1.8, 4.5, 1.5, 1.4, 0, 0.75)
    fa = xosc.Axle(0.5, 0.8, 1.6, 2.8, 0.4)
    ba = xosc.Axle(0.5, 0.8, 1.6, 0, 0.4)
    return xosc.Vehicle(name, xosc.VehicleCategory.car, bb, fa, ba, 69, 10, 10)


def dyn(shape, dim, value):
    return xosc.TransitionDynamics(getattr(xosc.DynamicsShapes, shape),
                                   getattr(xosc.DynamicsDimension, dim), value)


def sim_time(t, delay=0.0, edge="none", rule="greaterThan", name="time", point="start"):
    return xosc.ValueTrigger(name, delay, getattr(xosc.ConditionEdge, edge),
                             xosc.SimulationTimeCondition(t, getattr(xosc.Rule, rule)), point)


def scenario(tmp_path, init, events, actors="Target", params=None, road=True, entities=None,
             catalog=None, name="s.xosc", stop=100.0, title="t"):
    """A scenario: Ego and Target (vehicles) unless ``entities``; ``init``: [(entity, action)];
    ``events``: [(trigger, [action])] in one maneuver of ``actors``; its stop trigger at
    ``stop`` seconds."""
    if road:
        write_road(tmp_path / "road.xodr")
    ents = xosc.Entities()
    for n, obj in (entities or [("Ego", vehicle()), ("Target", vehicle())]):
        ents.add_scenario_object(n, obj)
    ini = xosc.Init()
    for who, a in init:
        ini.add_init_action(who, a)
    man = xosc.Maneuver("man")
    events = events or [(sim_time(50), [speed(1)])]
    for k, (trig, acts) in enumerate(events):
        ev = xosc.Event(f"ev{k}", xosc.Priority.parallel)
        for j, a in enumerate(acts):
            ev.add_action(f"ev{k}a{j}", a)
        ev.add_trigger(trig)
        man.add_event(ev)
    mg = xosc.ManeuverGroup("mg")
    mg.add_actor(actors)
    mg.add_maneuver(man)
    act = xosc.Act("act", sim_time(0, rule="greaterOrEqual", name="go"))
    act.add_maneuver_group(mg)
    story = xosc.Story("story")
    story.add_act(act)
    sb = xosc.StoryBoard(ini, sim_time(stop, name="stop", point="stop"))
    sb.add_story(story)
    pd = xosc.ParameterDeclarations()
    for k, v in (params or {}).items():
        pd.add_parameter(xosc.Parameter(k, xosc.ParameterType.double, v))
    sce = xosc.Scenario(title, "lsd3d", pd, ents, sb, xosc.RoadNetwork(roadfile="road.xodr"),
                        catalog or xosc.Catalog())
    path = tmp_path / name
    sce.write_xml(str(path))
    return path


def lanepos(s, lane=-1, offset=0.0):
    return xosc.TeleportAction(xosc.LanePosition(s, offset, lane, 1))


def speed(v, shape="step", dim="time", value=0.0):
    return xosc.AbsoluteSpeedAction(v, dyn(shape, dim, value))


def play(path, seconds, ego=lambda t: None, dt=DT):
    sc = read_scenario(path)
    layout = read_opendrive(sc.road_file)
    p = ScenarioPlayer(sc, layout, dt)
    out = [(0.0, p.start())]
    for k in range(1, int(round(seconds / dt)) + 1):
        t = k * dt
        out.append((t, p.step(t, ego(t))))
    return p, out


# ---------------------------------------------------------------- lane positions

@pytest.mark.parametrize("geom", ["line", "arc"])
def test_lane_position_matches_opendrive_geometry(tmp_path, geom):
    R = 60.0
    g = [xodr.Line(120)] if geom == "line" else [xodr.Arc(1 / R, length=120)]
    write_road(tmp_path / "r.xodr", g, right=2, left=1)
    layout = read_opendrive(tmp_path / "r.xodr")
    for s in (0.0, 7.3, 59.99, 120.0):
        for lane, t in ((-1, -W / 2), (-2, -1.5 * W), (1, W / 2)):
            x, y, z, h = lane_position(layout, "1", lane, s, 0.4)
            tt = t + 0.4
            if geom == "line":
                ex, ey, eh = s, tt, 0.0
            else:
                th = s / R
                ex, ey, eh = (R - tt) * math.sin(th), R - (R - tt) * math.cos(th), th
            if lane > 0:
                eh += math.pi
            assert math.hypot(x - ex, y - ey) < 1e-3
            assert abs(math.remainder(h - eh, 2 * math.pi)) < 1e-3
    with pytest.raises(InputError, match="road 1 lane -3: no such lane"):
        lane_position(layout, "1", -3, 5.0, 0.0)


# ---------------------------------------------------------------- player semantics

def test_linear_speed_action_reaches_target_at_2s(tmp_path):
    path = scenario(tmp_path, [("Ego", lanepos(10)), ("Target", lanepos(50)), ("Target", speed(10))],
                    [(sim_time(1.0, rule="greaterOrEqual"), [speed(20, "linear", "time", 2.0)])])
    p, out = play(path, 4.0)
    v = {round(t, 6): st["Target"][4] for t, st in out}
    x = {round(t, 6): st["Target"][0] for t, st in out}
    assert v[1.0] == pytest.approx(10) and v[2.0] == pytest.approx(15)
    assert v[2.95] < 20 - 1e-6 and v[3.0] == pytest.approx(20, abs=1e-9)
    # x(t) = 50 + 10 t + 2.5 (t-1)^2 during the ramp, then +20 m/s
    assert x[3.0] == pytest.approx(50 + 30 + 10, abs=0.01)
    assert x[4.0] == pytest.approx(50 + 30 + 10 + 20, abs=0.01)


def test_sinusoidal_lane_change_crosses_boundary_at_half_time(tmp_path):
    lc = xosc.AbsoluteLaneChangeAction(-2, dyn("sinusoidal", "time", 3.0))
    path = scenario(tmp_path, [("Ego", lanepos(10)), ("Target", lanepos(50)), ("Target", speed(15))],
                    [(sim_time(1.0, rule="greaterOrEqual"), [lc])])
    p, out = play(path, 5.0)
    ys = [(t, st["Target"][1]) for t, st in out]
    cross = next(t for t, y in ys if y <= -W - 1e-9)     # lane -1/-2 boundary at y = -3.5
    assert cross == pytest.approx(2.5, abs=0.05 + 1e-9)
    y = dict((round(t, 6), yy) for t, yy in ys)
    assert y[2.5] == pytest.approx(-W, abs=0.01)
    assert y[4.0] == pytest.approx(-1.5 * W, abs=0.01) and y[5.0] == pytest.approx(-1.5 * W, abs=1e-6)


def test_trigger_fires_at_first_step_with_delay(tmp_path):
    # SimulationTime > 1.02 first holds at t = 1.05; with delay 0.5 the event starts at 1.55
    path = scenario(tmp_path, [("Ego", lanepos(10)), ("Target", lanepos(50)), ("Target", speed(10))],
                    [(sim_time(1.02, delay=0.5), [speed(0)])])
    p, out = play(path, 2.0)
    v = {round(t, 6): st["Target"][4] for t, st in out}
    assert v[1.5] == pytest.approx(10) and v[1.55] == pytest.approx(0)


def test_cut_in_on_time_headway(tmp_path):
    # ego at 20 m/s on lane -1 from s=0; target 30 m ahead on lane -2 at 15 m/s: the headway
    # 30 - 5t over 20 falls below 1 s after t = 2: the lane change starts at the next step
    th = xosc.EntityTrigger("hw", 0, xosc.ConditionEdge.none,
                            xosc.TimeHeadwayCondition("Target", 1.0, xosc.Rule.lessThan,
                                                      alongroute=True, freespace=False), "Ego")
    lc = xosc.RelativeLaneChangeAction(0, "Ego", dyn("sinusoidal", "time", 2.0))
    path = scenario(tmp_path, [("Ego", lanepos(0)), ("Ego", speed(20)),
                               ("Target", lanepos(30, -2)), ("Target", speed(15))], [(th, [lc])])
    _, out = play(path, 6.0, ego=lambda t: (20 * t, -W / 2, 0.0, 20.0))
    ys = {round(t, 6): st["Target"][1] for t, st in out}
    # fires at t = 2.05 (headway 19.75 / 20 s); the lane change runs from there
    assert ys[2.05] == pytest.approx(-1.5 * W) and ys[2.1] > -1.5 * W + 1e-6
    assert ys[3.05] == pytest.approx(-W, abs=0.01)                 # half way after 1 s
    assert ys[4.05] == pytest.approx(-W / 2, abs=1e-6)
    xs = {round(t, 6): st["Target"][0] for t, st in out}
    assert xs[6.0] == pytest.approx(30 + 15 * 6, abs=0.05)


def test_lead_vehicle_brakes_at_6(tmp_path):
    v0 = 50 / 3.6
    brake = speed(0, "linear", "rate", 6.0)
    path = scenario(tmp_path, [("Ego", lanepos(0)), ("Target", lanepos(40)), ("Target", speed(v0))],
                    [(sim_time(1.0, rule="greaterOrEqual"), [brake])])
    _, out = play(path, 5.0)
    t_stop = 1.0 + v0 / 6
    for t, st in out:
        x, v = st["Target"][0], st["Target"][4]
        if t <= 1.0:
            ev, ex = v0, 40 + v0 * t
        elif t < t_stop:
            ev, ex = v0 - 6 * (t - 1), 40 + v0 * t - 3 * (t - 1) ** 2
        else:
            ev, ex = 0.0, 40 + v0 + v0 * v0 / 12
        assert v == pytest.approx(ev, abs=1e-6) and x == pytest.approx(ex, abs=0.01), t


def test_storyboard_state_and_follow_trajectory(tmp_path):
    traj = xosc.Trajectory("tr", False)
    traj.add_shape(xosc.Polyline([0, 2, 4], [xosc.WorldPosition(100, -1.75), xosc.WorldPosition(120, -1.75),
                                             xosc.WorldPosition(120, -21.75)]))
    ft = xosc.FollowTrajectoryAction(traj, xosc.FollowingMode.position, xosc.ReferenceContext.relative, 1, 0)
    after = xosc.ValueTrigger("after", 0, xosc.ConditionEdge.none,
                              xosc.StoryboardElementStateCondition(xosc.StoryboardElementType.action, "ev0a0",
                                                                   xosc.StoryboardElementState.endTransition))
    path = scenario(tmp_path, [("Ego", lanepos(0)), ("Target", lanepos(50)), ("Target", speed(10))],
                    [(sim_time(0.5, rule="greaterOrEqual"), [ft]), (after, [speed(3)])])
    p, out = play(path, 5.0)
    st = {round(t, 6): s["Target"] for t, s in out}
    assert st[1.5][0] == pytest.approx(110) and st[1.5][4] == pytest.approx(10)
    assert st[4.5][:2] == pytest.approx((120, -21.75))
    assert st[5.0][4] == pytest.approx(3)     # the speed event followed the trajectory's end


# ---------------------------------------------------------------- reading

def test_parameters_resolved(tmp_path):
    path = scenario(tmp_path, [("Ego", lanepos(0)), ("Target", lanepos(50)),
                               ("Target", speed("$v0"))], [], params={"v0": 12.5})
    sc = read_scenario(path)
    assert sc.init["Target"][1].speed == 12.5
    assert sc.ego == "Ego" and sc.entities["Target"].length == 4.5


def _one_line(e):
    s = str(e.value)
    assert "\n" not in s
    return s


def test_undeclared_parameter(tmp_path):
    path = scenario(tmp_path, [("Ego", lanepos(0)), ("Target", speed("$nope"))], [])
    with pytest.raises(InputError) as e:
        read_scenario(path)
    assert "$nope is not declared" in _one_line(e) and "s.xosc:" in str(e.value)


def test_missing_opendrive(tmp_path):
    path = scenario(tmp_path, [("Ego", lanepos(0))], [])
    (tmp_path / "road.xodr").unlink()
    with pytest.raises(InputError) as e:
        read_scenario(path)
    assert "OpenDRIVE file 'road.xodr' not found" in _one_line(e)


def _catalog_scenario(tmp_path, directory):
    cat = xosc.Catalog()
    cat.add_catalog("VehicleCatalog", directory)
    ents = [("Ego", vehicle()), ("Target", xosc.CatalogReference("VehicleCatalog", "truck"))]
    return scenario(tmp_path, [("Ego", lanepos(0))], [], entities=ents, catalog=cat)


def test_catalog_resolved_and_missing(tmp_path):
    (tmp_path / "cat").mkdir()
    vc = xosc.CatalogFile()
    vc.create_catalog(str(tmp_path / "cat" / "vehicles.xosc"), "VehicleCatalog", "vehicles", "lsd3d")
    vc.add_to_catalog(vehicle("truck"))
    vc.dump()
    path = _catalog_scenario(tmp_path, "cat")
    sc = read_scenario(path)
    assert sc.entities["Target"].kind == "vehicle" and sc.entities["Target"].width == 1.8
    (tmp_path / "cat" / "vehicles.xosc").unlink()
    with pytest.raises(InputError) as e:
        read_scenario(path)
    assert "catalog 'VehicleCatalog' not found" in _one_line(e)


def test_catalog_outside_folder(tmp_path):
    (tmp_path / "sc").mkdir()
    path = _catalog_scenario(tmp_path / "sc", "../elsewhere")
    with pytest.raises(InputError) as e:
        read_scenario(path)
    assert "outside the scenario's folder" in _one_line(e)


def test_entity_bomb(tmp_path):
    path = scenario(tmp_path, [("Ego", lanepos(0))], [])
    text = path.read_text()
    lol = "".join(f'<!ENTITY l{k} "{"&l%d;" % (k - 1) * 10 if k else "lol"}">' for k in range(10))
    text = text.replace("<OpenSCENARIO", f"<!DOCTYPE OpenSCENARIO [{lol}]>\n<OpenSCENARIO", 1)
    text = text.replace('author="lsd3d"', 'author="&l9;"')
    path.write_text(text)
    with pytest.raises(InputError) as e:
        read_scenario(path)
    assert "refused" in _one_line(e) or "XML" in str(e.value)


def test_billion_step_trajectory(tmp_path):
    traj = xosc.Trajectory("tr", False)
    traj.add_shape(xosc.Polyline([0, 1e8], [xosc.WorldPosition(0, 0), xosc.WorldPosition(10, 0)]))
    ft = xosc.FollowTrajectoryAction(traj, xosc.FollowingMode.position, xosc.ReferenceContext.relative, 1, 0)
    path = scenario(tmp_path, [("Ego", lanepos(0)), ("Target", lanepos(50))], [(sim_time(0), [ft])])
    sc = read_scenario(path)
    with pytest.raises(InputError) as e:
        ScenarioPlayer(sc, read_opendrive(sc.road_file), 0.1)
    assert "FollowTrajectoryAction" in _one_line(e) and "1e+09 steps" in str(e.value)


def test_unsupported_element_warns_with_line(tmp_path):
    a = xosc.AbsoluteSpeedAction(5, dyn("linear", "time", 1))
    path = scenario(tmp_path, [("Ego", lanepos(0)), ("Target", lanepos(50))], [(sim_time(1), [a])])
    text = path.read_text().replace("<LongitudinalAction>", "<LongitudinalAction><Nonsense/>", 1)
    text = text.replace("<SpeedAction>", "<X>", 1).replace("</SpeedAction>", "</X>", 1)
    path.write_text(text)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        sc = read_scenario(path)
    msgs = [str(x.message) for x in w]
    assert any("<Nonsense> is not supported" in m and "s.xosc:" in m for m in msgs), msgs
    assert sc.unsupported


# ---------------------------------------------------------------- scenario build

def test_scenario_build_keeps_lanes_addressable(tmp_path):
    from lsd3d_usd.cli import main
    from lsd3d_usd.layout import usdio
    path = scenario(tmp_path, [("Ego", lanepos(10)), ("Target", lanepos(50))], [])
    scene = tmp_path / "scene"
    assert main(["scenario", "build", str(path), "-o", str(scene), "--steps", "0", "--no-actors",
                 "--surfels", "5000", "--resolution", "64x36", "--no-progress"]) == 0
    layout = usdio.read_layout(scene / "layers" / "layout.usda")
    x, y, z, h = lane_position(layout, "1", -2, 33.0, 0.5)
    assert (x, y, h) == pytest.approx((33.0, -1.5 * W + 0.5, 0.0), abs=1e-3)
    assert layout.metadata["scenario"]["ego"] == "Ego"


def test_scenario_build_bad_input_writes_nothing(tmp_path, capsys):
    from lsd3d_usd.cli import main
    path = scenario(tmp_path, [("Ego", lanepos(0))], [])
    (tmp_path / "road.xodr").unlink()
    assert main(["scenario", "build", str(path), "-o", str(tmp_path / "scene"), "--steps", "0"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not found" in err
    assert not (tmp_path / "scene").exists()


def test_pedestrian_crosses_when_ego_30m_away(tmp_path):
    ped = xosc.Pedestrian("walker", 80, xosc.PedestrianCategory.pedestrian,
                          xosc.BoundingBox(0.5, 0.6, 1.8, 0, 0, 0.9))
    init = [("Ego", lanepos(0)), ("Ego", speed(10)), ("Target", lanepos(200)),
            ("Walker", xosc.TeleportAction(xosc.WorldPosition(60, -12, 0, math.pi / 2)))]
    near = xosc.EntityTrigger("near", 0, xosc.ConditionEdge.rising, xosc.RelativeDistanceCondition(
        30, xosc.Rule.lessThan, xosc.RelativeDistanceType.longitudinal, "Walker", freespace=False), "Ego")
    path = scenario(tmp_path, init, [(near, [speed(1.5)])], actors="Walker",
                    entities=[("Ego", vehicle()), ("Target", vehicle()), ("Walker", ped)])
    p, out = play(path, 5.0, ego=lambda t: (10 * t, -W / 2, 0.0, 10.0))
    assert p.ego_init() == pytest.approx((0.0, -W / 2, 0.0, 0.0, 10.0))
    # the ego's x = 10 t passes 30 m short of the walker after t = 3: it walks from 3.05
    for t, st in out:
        y = -12 + 1.5 * max(t - 3.05, 0.0)
        assert st["Walker"][1] == pytest.approx(y, abs=1e-6), t


@pytest.mark.parametrize("order", [("Car1", "Car2"), ("Car2", "Car1")])
def test_synchronised_arrival_at_junction(tmp_path, order):
    """Car2 synchronises its arrival at the end of road 2 with Car1's at the end of road 1
    (both roads enter the junction): Car1 at 10 m/s from s = 20 gets there at 8 s, so must
    Car2 (3 m/s from s = 40; the action from t = 1 s: 57 m in 7 s), whichever is moved first."""
    write_junction(tmp_path / "road.xodr")

    def at(road, s):
        return xosc.TeleportAction(xosc.LanePosition(s, 0, -1, road))
    sync = xosc.SynchronizeAction("Car1", xosc.LanePosition(100, 0, -1, 1), xosc.LanePosition(100, 0, -1, 2),
                                  final_speed=xosc.AbsoluteSpeed(7.5))
    ents = {"Car1": vehicle(), "Car2": vehicle()}
    path = scenario(tmp_path, [("Ego", at(3, 10)), ("Car1", at(1, 20)), ("Car1", speed(10)),
                               ("Car2", at(2, 40)), ("Car2", speed(3))],
                    [(sim_time(1.0, rule="greaterOrEqual"), [sync])], actors="Car2", road=False,
                    entities=[("Ego", vehicle())] + [(n, ents[n]) for n in order])
    sc = read_scenario(path)
    layout = read_opendrive(sc.road_file)
    targets = {n: lane_position(layout, str(r), -1, 100.0)[:2] for n, r in (("Car1", 1), ("Car2", 2))}
    _, out = play(path, 9.0)

    def arrival(name):
        """The time the entity's reference point passes its target (linear between steps)."""
        tx, ty = targets[name]
        prev = None
        for t, st in out:
            x, y, _, yaw, _ = st[name]
            ahead = (tx - x) * math.cos(yaw) + (ty - y) * math.sin(yaw)
            if ahead <= 0:
                return t if prev is None else prev[0] + DT * prev[1] / (prev[1] - ahead)
            prev = (t, ahead)
        return math.inf
    st = dict((round(t, 6), s) for t, s in out)
    assert arrival("Car1") == pytest.approx(8.0, abs=1e-6)
    assert arrival("Car2") == pytest.approx(arrival("Car1"), abs=0.05)
    assert st[8.0]["Car2"][:2] == pytest.approx(targets["Car2"], abs=0.01)
    assert st[4.0]["Car2"][4] == pytest.approx(57 / 7, abs=1e-6) and st[8.5]["Car2"][4] == pytest.approx(7.5)
