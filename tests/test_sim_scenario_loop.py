"""Scenarios in the closed loop: a scene built from a scenario's road (`scenario build`), its
entities as DriveEnv's world (scored, labelled by the sensors), its outcome in the episode."""
from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("scenariogeneration")
from scenariogeneration import xosc  # noqa: E402

from lsd3d_usd.errors import InputError  # noqa: E402
from tests.test_sim_scenario import (  # noqa: E402
    W, dyn, lanepos, scenario, sim_time, speed, vehicle, write_road)

V50 = 50 / 3.6


def write_scenario(folder, name, init, events, actors="Target", stop=8.0):
    """Ego and Target on the shared road; ``events``: [(trigger, [action])] of ``actors``."""
    return scenario(folder, init, events, actors, road=False, name=f"{name}.xosc", stop=stop,
                    title=name)


def braking_lead(folder):
    """The lead 30 m ahead at 50 km/h brakes at 6 m/s^2 to a stop after 2 s."""
    return write_scenario(folder, "braking_lead",
                          [("Ego", lanepos(10)), ("Ego", speed(V50)), ("Target", lanepos(40)),
                           ("Target", speed(V50))],
                          [(sim_time(2.0, rule="greaterOrEqual"), [speed(0, "linear", "rate", 6.0)])])


def cut_in(folder):
    """A slower vehicle on the neighbouring lane changes into the ego's lane ahead when the
    ego's time headway to it falls below 1 s."""
    th = xosc.EntityTrigger("hw", 0, xosc.ConditionEdge.rising,
                            xosc.TimeHeadwayCondition("Target", 1.0, xosc.Rule.lessThan,
                                                      alongroute=True, freespace=False), "Ego")
    lc = xosc.RelativeLaneChangeAction(0, "Ego", dyn("sinusoidal", "time", 2.5))
    return write_scenario(folder, "cut_in",
                          [("Ego", lanepos(10)), ("Ego", speed(12)), ("Target", lanepos(45, -2)),
                           ("Target", speed(8))], [(th, [lc])], stop=12.0)


@pytest.fixture(scope="module")
def road_scene(tmp_path_factory):
    """A scene built by `scenario build` around a straight two-lane road (400 m)."""
    from lsd3d_usd.cli import main
    folder = tmp_path_factory.mktemp("xosc")
    write_road(folder / "road.xodr")
    path = braking_lead(folder)
    scene = folder / "scene"
    assert main(["scenario", "build", str(path), "-o", str(scene), "--steps", "0", "--no-actors",
                 "--surfels", "3000", "--resolution", "64x48", "--views", "4",
                 "--env-resolution", "128x64", "--no-progress"]) == 0
    return folder, scene


def drive(scene, path, policy, **kw):
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.policies import load_policy
    env = DriveEnv(str(scene), scenario=str(path), rig="none", lidar="none", seconds=20.0, **kw)
    try:
        obs, info = env.reset(seed=0)
        first = (obs["ego"]["pose"].copy(), float(obs["ego"]["speed"]), info)
        pol = load_policy(policy, env)
        while True:
            obs, _, term, trunc, info = env.step(pol(obs, info))
            if term or trunc:
                return env, first, info
    finally:
        env.close()


def test_braking_lead_discriminates(road_scene):
    folder, scene = road_scene
    path = folder / "braking_lead.xosc"
    env, (pose, v0, first), info = drive(scene, path, "planner")
    # the ego starts where Init puts it (rear axle at s = 10 on lane -1), at 50 km/h
    assert pose[[0, 1, 3]] == pytest.approx([10.0, -W / 2, 0.0], abs=1e-6)
    assert v0 == pytest.approx(V50, abs=1e-4) and env.settings.vehicles == 0
    assert [b["id"] for b in first["boxes"]] == ["vehicle:Target"]
    assert first["boxes"][0]["center"] == pytest.approx([40 + 1.4, -W / 2], abs=1e-6)
    assert info["reason"] == "scenario_end" and info["scores"]["nc"] == 1.0
    assert info["scenario"]["stop_trigger_fired"] and info["scenario"]["name"] == "braking_lead"
    env, _, info = drive(scene, path, "constant")
    assert info["reason"] == "collision"
    assert not info["scenario"]["stop_trigger_fired"]


def test_cut_in_planner_no_collision(road_scene):
    folder, scene = road_scene
    path = cut_in(folder)
    env, _, info = drive(scene, path, "planner")
    assert info["reason"] == "scenario_end" and info["scores"]["nc"] == 1.0
    # the target did change into the ego's lane
    tgt = [b for b in info["boxes"] if b["id"] == "vehicle:Target"][0]
    assert tgt["center"][1] == pytest.approx(-W / 2, abs=0.05)


def test_sensors_show_and_label_the_lead(road_scene):
    from lsd3d_usd.sim.env import DriveEnv
    folder, scene = road_scene
    path = write_scenario(folder, "lead_ahead", [("Ego", lanepos(10)), ("Target", lanepos(25))], [])
    env = DriveEnv(str(scene), scenario=str(path), rig="nuscenes6", cameras=("CAM_FRONT",),
                   width=64, outputs=("rgb", "instance"), lidar="auto")
    try:
        obs, info = env.reset(seed=0)
        iid = int(env.sensors.instances.ids[1])      # actor 0 is the ego, 1 the first entity
        row = [r for r in env.sensors.instances.rows if r["id"] == iid][0]
        assert row["class"] == "vehicle" and row["role"] == "moving"
        assert (obs["cameras"]["CAM_FRONT"]["instance"] == iid).sum() > 20
        n = int(obs["lidar"]["count"])
        assert (obs["lidar"]["instance"][:n] == iid).sum() > 20
    finally:
        env.close()


def test_scenario_settings_refused(road_scene):
    from lsd3d_usd.sim.env import DriveEnv
    folder, scene = road_scene
    with pytest.raises(InputError, match="vehicles=3: seeded traffic"):
        DriveEnv(str(scene), scenario=str(folder / "braking_lead.xosc"), rig="none", vehicles=3)
    with pytest.raises(InputError, match="nope.xosc"):
        DriveEnv(str(scene), scenario=str(folder / "nope.xosc"), rig="none")


def test_sim_run_scenario_folder_and_report(road_scene, tmp_path, capsys):
    from lsd3d_usd.cli import main
    folder, scene = road_scene
    sets = tmp_path / "set"
    sets.mkdir()
    write_road(sets / "road.xodr")
    braking_lead(sets)
    write_scenario(sets, "idle", [("Ego", lanepos(10)), ("Target", lanepos(100))], [], stop=1.0)
    out = tmp_path / "run"
    assert main(["sim", "run", str(scene), "-o", str(out), "--scenario", str(sets), "--rig", "none",
                 "--no-reference", "--policy", "constant", "--seconds", "10", "--no-progress"]) == 0
    metas = [json.loads((out / f"episode_{k:03d}" / "metrics.json").read_text()) for k in range(2)]
    assert [m["scenario"]["name"] for m in metas] == ["braking_lead", "idle"]
    assert [m["reason"] for m in metas] == ["collision", "scenario_end"]
    # the stop trigger (time > 1 s) fires at the first step after 1 s: the episode ends there
    assert metas[1]["scenario"]["stop_trigger_fired"]
    assert metas[1]["steps"][-1]["t"] == pytest.approx(1.1)
    assert metas[1]["steps"][-1]["scenario"]["stop_trigger_fired"]
    assert not metas[1]["steps"][-2]["scenario"]["stop_trigger_fired"]
    capsys.readouterr()
    assert main(["sim", "report", str(out)]) == 0
    table = capsys.readouterr().out
    assert "braking_lead" in table and "idle" in table
    assert np.isfinite(metas[0]["summary"]["nc"])


def _csv_rows(path, who):
    import csv
    with open(path) as f:
        return [r for r in csv.DictReader(f) if r["id"] == who]


def test_policy_scenario_replays_the_egos_own_actions(road_scene, tmp_path):
    """--policy scenario: the storyboard drives the ego (a linear SpeedAction 10 -> 20 m/s
    over 2 s and a 3 s sinusoidal lane change from t = 1 s): the trajectory CSV's rear-axle
    rows match the closed form within 1 cm, the lane boundary is crossed at 2.5 s."""
    from lsd3d_usd.cli import main
    folder, scene = road_scene
    path = write_scenario(folder, "ego_replay",
                          [("Ego", lanepos(10)), ("Ego", speed(10)), ("Target", lanepos(300))],
                          [(sim_time(1.0, rule="greaterOrEqual"),
                            [speed(20, "linear", "time", 2.0),
                             xosc.AbsoluteLaneChangeAction(-2, dyn("sinusoidal", "time", 3.0))])],
                          actors="Ego")
    out = tmp_path / "run"
    assert main(["sim", "run", str(scene), "-o", str(out), "--scenario", str(path), "--policy",
                 "scenario", "--rig", "none", "--no-reference", "--hz", "20", "--seconds", "6",
                 "--no-progress"]) == 0
    ep = out / "episode_000"
    rows = _csv_rows(ep / "trajectories.csv", "ego")
    assert len(rows) == 121 and {r["point"] for r in rows} == {"rear_axle"}
    for r in rows:
        t, x, y, v = (float(r[k]) for k in ("t", "x", "y", "speed"))
        u = min(max(t - 1.0, 0.0), 2.0)
        ev = 10 + 5 * u
        ex = 10 + 10 * t + 2.5 * u * u + 10 * max(t - 3.0, 0.0)
        w = min(max((t - 1.0) / 3.0, 0.0), 1.0)
        ey = -W / 2 - W * 0.5 * (1 - np.cos(np.pi * w))
        assert (x, y, v) == pytest.approx((ex, ey, ev), abs=0.01), t
    cross = next(float(r["t"]) for r in rows if float(r["y"]) <= -W)
    assert cross == pytest.approx(2.5, abs=0.05)
    # the other entity is reported at its OpenSCENARIO reference point, not its box centre
    tgt = _csv_rows(ep / "trajectories.csv", "vehicle:Target")
    assert {r["point"] for r in tgt} == {"reference"} and float(tgt[0]["x"]) == pytest.approx(300)
    m = json.loads((ep / "metrics.json").read_text())
    assert m["reason"] == "time_limit" and m["settings"]["ego_driver"] == "scenario"


def test_ego_named_or_first(road_scene, cli_error, tmp_path):
    from lsd3d_usd.sim.env import DriveEnv
    folder, scene = road_scene
    path = scenario(folder, [("A", lanepos(10)), ("B", lanepos(60))], [], road=False,
                    name="two.xosc", entities=[("A", vehicle()), ("B", vehicle())], actors="B")
    for ego, x in ((None, 10.0), ("B", 60.0)):
        env = DriveEnv(str(scene), scenario=str(path), ego=ego, rig="none", ep_reference="none")
        try:
            obs, info = env.reset(seed=0)
            assert obs["ego"]["pose"][0] == pytest.approx(x) and info["scenario"]["ego"] == (ego or "A")
            assert [b["id"] for b in info["boxes"]] == [f"vehicle:{'B' if ego is None else 'A'}"]
        finally:
            env.close()
    base = ["sim", "run", scene, "-o", tmp_path / "o", "--rig", "none", "--no-progress"]
    cli_error(base + ["--scenario", path, "--ego", "Nobody"], "--ego 'Nobody'",
              "two.xosc", "A, B")
    cli_error(base + ["--ego", "A"], "--ego A: needs --scenario")
    cli_error(base + ["--policy", "scenario"], "--policy scenario: needs --scenario")
    assert not (tmp_path / "o").exists()


def test_entities_are_drawn_at_their_bounding_box(road_scene):
    """A scenario's 10 m x 2.6 m x 3.6 m truck gets the scene's nearest vehicle asset stretched
    to that box: its dims and its mesh's extent follow the box, and the camera labels it."""
    from lsd3d_usd.sim.env import DriveEnv
    folder, scene = road_scene
    bb = xosc.BoundingBox(2.6, 10.0, 3.6, 2.0, 0, 1.8)
    axle = xosc.Axle(0.5, 0.8, 2.2, 6.0, 0.5)
    truck = xosc.Vehicle("truck", xosc.VehicleCategory.truck, bb, axle,
                         xosc.Axle(0.5, 0.8, 2.2, 0, 0.5), 30, 5, 5)
    path = scenario(folder, [("Ego", lanepos(10)), ("Target", lanepos(30))], [], road=False,
                    entities=[("Ego", vehicle()), ("Target", truck)], name="truck.xosc")
    env = DriveEnv(str(scene), scenario=str(path), rig="none", lidar="none")
    try:
        env.reset(seed=0)
        a = env.actors.actors[1]                  # actor 0 is the ego, 1 the first entity
        np.testing.assert_allclose(a.dims, (10.0, 2.6, 3.6))
        kind = env.scene.closest_kind(a.label, (10.0, 2.6, 3.6))
        t = next(t for t in env.scene.templates[a.label] if t.kind == kind)
        s = np.array([10.0, 2.6, 3.6]) / np.asarray(t.dims, np.float64)
        v0 = np.concatenate([m.vertices for m in t.meshes])
        v1 = np.concatenate([m.vertices for m in a.meshes])
        np.testing.assert_allclose(v1.max(0) - v1.min(0), (v0.max(0) - v0.min(0)) * s, rtol=1e-9)
        assert not np.allclose(s, 1.0)            # the asset was not already this size
    finally:
        env.close()
