"""docs/extending.md's examples run: each `# file:` code block is written into a throw-away
package, its entry points are declared in a dist-info folder on PYTHONPATH, and the parts are
used through the command line and the registries."""
import json
import os
import re
import subprocess
import sys

import pytest

from conftest import ROOT

DOC = ROOT / "docs" / "extending.md"
LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"


def doc_blocks():
    """(files {relative path: code}, entry points {group: [line, ...]}) of the doc."""
    text = DOC.read_text(encoding="utf-8")
    files, groups = {}, {}
    for lang, body in re.findall(r"```(\w+)\n(.*?)```", text, flags=re.S):
        if lang in ("python", "toml") and body.startswith("# file: "):
            first, _, code = body.partition("\n")
            files[first[len("# file: "):].strip()] = code
        elif lang == "toml" and "entry-points" in body:
            group = re.search(r'entry-points\."([^"]+)"', body).group(1)
            groups.setdefault(group, []).extend(   # TOML string -> entry_points.txt value
                ln.replace('"', "") for ln in body.splitlines()[1:] if "=" in ln)
    return files, groups


@pytest.fixture
def plugin_path(tmp_path):
    files, groups = doc_blocks()
    for rel, code in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        (p.parent / "__init__.py").touch()
        p.write_text(code)       # a data file (a rig) ships inside its package too
    dist = tmp_path / "lsd3d_doc_examples-0.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: lsd3d-doc-examples\n"
                                   "Version: 0.0\n")
    (dist / "entry_points.txt").write_text("".join(
        f"[{g}]\n" + "\n".join(lines) + "\n" for g, lines in groups.items()))
    return tmp_path, files, groups


def test_the_doc_has_the_examples():
    files, groups = doc_blocks()
    assert {"lsd3d_usd.priors", "lsd3d_usd.losses", "lsd3d_usd.sensors", "lsd3d_usd.rigs",
            "lsd3d_usd.dataset_writers"} <= set(groups)
    assert len(files) >= 2


def test_prior_and_loss_from_entry_points_run_in_generate(plugin_path, tmp_path):
    path, _, _ = plugin_path
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(path), str(ROOT)]))
    out = tmp_path / "scene"
    r = subprocess.run([sys.executable, "-m", "lsd3d_usd", "generate", "--layout", LAYOUT,
                        "-o", out, "--prior", "flat:0.8", "--set", "ggds.weights.sky_alpha=0.5",
                        "--steps", "3", "--surfels", "2000", "--resolution", "64x48",
                        "--views", "4", "--env-resolution", "128x64", "--no-actors",
                        "--set", "ggds.held_out=1", "--keep-checkpoint", "--no-progress"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    from lsd3d_usd import scene as S
    sc = S.Scene.open(out)
    run = sc.runs()[0]
    params = run.provenance["params"]
    params = json.loads(params) if isinstance(params, str) else params
    assert params["prior"] == "flat" and params["gain"] == 0.8
    meta = json.loads((sc.run_files(run.name).dir / "state.json").read_text())
    assert all("sky_alpha" in rec for rec in meta["history"])
    plan = json.loads((sc.run_files(run.name).dir / "run.json").read_text())
    assert plan["generate"]["ggds"]["weights"]["sky_alpha"] == 0.5
    bad = subprocess.run([sys.executable, "-m", "lsd3d_usd", "generate", "-o", tmp_path / "x",
                          "--prior", "flat:abc", "--steps", "1", "--layout", LAYOUT],
                         capture_output=True, text=True, env=env, timeout=300)
    assert bad.returncode == 1 and "the argument is a gain" in bad.stderr
    assert not (tmp_path / "x").exists()


def _run_with_plugins(path, code: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(path), str(ROOT)]))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=300)


def test_sensor_type_and_rig_from_entry_points(plugin_path):
    """The doc's IMU sensor type (one file + one entry point) and its rig (one TOML file + one
    entry point): the rig loads by name wherever a rig name is accepted."""
    path, _, _ = plugin_path
    r = _run_with_plugins(path, """if True:
        import json
        from lsd3d_usd.sensors.rigs import load_rig
        from lsd3d_usd.views.options import RigOptions
        from lsd3d_usd.views.rig import rig_lidar
        rig = load_rig("city4")
        print(json.dumps({"name": rig.name, "cameras": [c.name for c in rig.cameras],
                          "heights": [c.height_for(640) for c in rig.cameras],
                          "lidar": rig.lidar.name, "run_lidar": rig_lidar(RigOptions(name="city4")).name,
                          "others": [[o.kind, o.name, o.rate_hz] for o in rig.others]}))
        """)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.splitlines()[-1])
    assert got == {"name": "city4", "cameras": ["Front", "Back"], "heights": [360, 360],
                   "lidar": "hdl32", "run_lidar": "hdl32", "others": [["imu", "IMU", 100.0]]}
    h = subprocess.run([sys.executable, "-m", "lsd3d_usd", "render", "--help"],
                       capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(path), str(ROOT)])))
    assert h.returncode == 0 and "city4" in h.stdout


def test_rig_file_unregistered_and_its_errors(plugin_path, tmp_path):
    """A rig file works by path with no registration; a bad key is one line naming the file,
    the sensor and the key."""
    from lsd3d_usd.errors import InputError
    from lsd3d_usd.sensors import SENSORS
    from lsd3d_usd.sensors.rigs import load_rig
    _, files, _ = plugin_path
    text = files["cityrig/city4.toml"]
    f = tmp_path / "mine.toml"
    f.write_text(text.replace('type = "imu"', 'type = "camera"\nhfov = 40.0\nsize = [64, 64]')
                 .replace("rate_hz = 100.0", ""))
    rig = load_rig(str(f))
    assert [c.name for c in rig.cameras] == ["Front", "Back", "IMU"] and rig.lidar.name == "hdl32"
    assert rig.cameras[0].pitch_deg == 2.0 and rig.cameras[1].yaw_deg == 180.0
    f.write_text(text)      # type imu: not registered in this process
    with pytest.raises(InputError, match=r"mine.toml: sensor\[2\] \(IMU\): type: unknown sensor type 'imu'"):
        load_rig(str(f))
    assert "imu" not in SENSORS
    f.write_text(text.replace("hfov = 90.0", "hfov = 190.0"))
    with pytest.raises(InputError) as e:
        load_rig(str(f))
    assert str(e.value).startswith(f"{f}: sensor[1] (Back): hfov: ") and "\n" not in str(e.value)
    with pytest.raises(InputError, match="--rig 'waymo6': unknown rig; known: waymo5, nuscenes6, or a rig FILE.toml"):
        load_rig("waymo6")


def test_dataset_writer_from_entry_point(plugin_path, tmp_path):
    """The doc's writer (one file + one entry point) is found by format name and fed samples."""
    path, _, _ = plugin_path
    r = _run_with_plugins(path, f"""if True:
        import json
        from pathlib import Path
        from types import SimpleNamespace
        import numpy as np
        from lsd3d_usd.datasets.drive import Sample
        from lsd3d_usd.datasets.timeline import Timeline
        from lsd3d_usd.datasets.writers import WRITERS
        root = Path({str(tmp_path)!r})
        w = WRITERS.get("poses")(root, None)
        w.begin_log(SimpleNamespace(plan=SimpleNamespace(index=0)))
        for tick in Timeline(10.0, None, 2.0, 1.0).ticks():
            ego = np.eye(4)
            ego[0, 3] = tick.time
            w.write(Sample(tick, tick.time, ego))
        print(json.dumps(w.finish([w.end_log()])))
        """)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.splitlines()[-1])
    lines = (tmp_path / "log_0000.jsonl").read_text().splitlines()
    assert got == {"logs": 1, "samples": len(lines)} and len(lines) >= 10
    assert json.loads(lines[1])["xyz"][0] == pytest.approx(0.1)
