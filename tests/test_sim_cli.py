"""`lsd3d-usd sim run` / `sim report`: episode folders, a failing policy, output checks."""
import json
import sys

import pytest

import lsd3d_usd  # noqa: F401
from lsd3d_usd.cli import main


@pytest.fixture(scope="module")
def scene(sim_scene):
    return sim_scene          # conftest: one scene shared by the sim tests


POLICY = '''
import numpy as np
episodes = {"n": 0}

def brake_then_fail(obs, info):
    if info["step"] == 0:
        episodes["n"] += 1
    if episodes["n"] == 2 and info["step"] >= 3:      # the second episode's stack crashes
        raise RuntimeError("stack crashed")
    return np.array([1.0, 0.0], np.float32)
'''


def test_sim_run_writes_episodes_and_report(scene, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["sim", "run", str(scene), "-o", str(out), "--rig", "nuscenes6", "--width", "32",
                 "--lidar", "none", "--episodes", "2", "--seconds", "1.5", "--video",
                 "--vehicles", "2", "--pedestrians", "2", "--cyclists", "1", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "episode 0:" in printed and "episode 1:" in printed
    for k in range(2):
        ep = out / f"episode_{k:03d}"
        m = json.loads((ep / "metrics.json").read_text())
        assert m["episode"] == k and m["seed"] == k
        assert len(m["steps"]) == 16 and m["reason"] == "time_limit"
        assert {"rc", "nc", "dac", "pdms", "driving_score", "hd_score"} <= set(m["summary"])
        rows = (ep / "trajectories.csv").read_text().splitlines()
        assert rows[0] == "id,kind,t,x,y,z,yaw,speed,point" and sum(r.startswith("ego,") for r in rows) == 16
        assert (ep / "birdseye.png").stat().st_size > 5000
        assert (ep / "CAM_FRONT.mp4").stat().st_size > 1000
    assert not list(out.glob(".episode_*"))
    assert main(["sim", "report", str(out), "--png", str(tmp_path / "r.png"),
                 "--json", str(tmp_path / "r.json")]) == 0
    table = capsys.readouterr().out
    assert "rc" in table and "ended: time_limit 2" in table
    data = json.loads((tmp_path / "r.json").read_text())
    assert data[str(out)]["episodes"] == 2 and data[str(out)]["rc"]["n"] == 2


def test_a_failing_policy_ends_its_episode_and_the_others_are_written(scene, tmp_path, capsys,
                                                                      monkeypatch):
    mod = tmp_path / "mystack.py"
    mod.write_text(POLICY)
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "run"
    code = main(["sim", "run", str(scene), "-o", str(out), "--rig", "none", "--routes", "3",
                 "--seconds", "2", "--policy", "mystack:brake_then_fail", "--no-reference",
                 "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and "ended by the policy" in err and "stack crashed" in err
    eps = sorted(out.glob("episode_*/metrics.json"))
    assert len(eps) == 3
    reasons = [json.loads(p.read_text())["reason"] for p in eps]
    assert reasons[1] == "policy_error" and reasons[0] == reasons[2] == "time_limit"
    failed = json.loads(eps[1].read_text())
    assert "RuntimeError: stack crashed" in failed["error"]
    sys.modules.pop("mystack", None)


def test_bad_sim_input_is_one_line(scene, tmp_path, cli_error):
    assert cli_error(["sim", "run", str(scene), "-o", str(scene / "inside")],
                     "inside the scene folder")
    assert cli_error(["sim", "run", str(scene), "-o", str(tmp_path / "x"), "--route", "nope"],
                     "'nope' is not a lane")
    assert cli_error(["sim", "run", str(scene), "-o", str(tmp_path / "x"), "--rig", "nope"],
                     "--rig 'nope'")
    assert cli_error(["sim", "run", str(scene), "-o", str(tmp_path / "x"), "--policy",
                      "no_such_mod:f", "--rig", "none"], "cannot import 'no_such_mod'")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    assert cli_error(["sim", "run", str(scene), "-o", str(tmp_path / "full")], "'notes.txt'")
    assert cli_error(["sim", "report", str(tmp_path / "full")], "no episode_*/metrics.json")


CTRL_C = '''
import numpy as np
episodes = {"n": 0}

def interrupted(obs, info):
    if info["step"] == 0:
        episodes["n"] += 1
    if episodes["n"] == 2 and info["step"] >= 2:      # Ctrl-C during the second episode
        raise KeyboardInterrupt
    return np.array([0.5, 0.0], np.float32)
'''


def test_ctrl_c_keeps_the_finished_episodes_whole(scene, tmp_path, capsys, monkeypatch):
    (tmp_path / "ctrlc_stack.py").write_text(CTRL_C)
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "run"
    code = main(["sim", "run", str(scene), "-o", str(out), "--rig", "none", "--episodes", "3",
                 "--seconds", "1", "--policy", "ctrlc_stack:interrupted", "--no-reference",
                 "--no-progress"])
    assert code == 130 and "interrupted" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["episode_000", "run.json"]
    m = json.loads((out / "episode_000" / "metrics.json").read_text())
    assert m["reason"] == "time_limit" and len(m["steps"]) == 11
    sys.modules.pop("ctrlc_stack", None)
