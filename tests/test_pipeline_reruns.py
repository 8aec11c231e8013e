"""Scene integrity across re-runs and against hostile scene folders: checkpoints cannot run
code, paths read from a scene stay inside it, a re-run never leaves a GGDS run silently active
on surfels or light it was not made for, --resume continues with the run's own settings."""
import json
import os
from pathlib import Path

import pytest
from pxr import Sdf, Vt

from conftest import ROOT, error_line, generate_small
from lsd3d_usd import scene as S
from lsd3d_usd import validation
from lsd3d_usd.errors import InputError

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"
SMALL = ["--layout", LAYOUT, "--surfels", "3000", "--env-resolution", "128x64",
         "--resolution", "64x48", "--views", "4", "--no-actors", "--no-progress",
         "--set", "ggds.held_out=2"]


def gen(out, run=None, **kw):
    """The small scene, without GGDS unless asked (steps=N)."""
    return generate_small(out, run, **{"steps": 0, "seed": 0, "ggds": {"held_out": 2}, **kw})




def errors_of(path):
    return [p.line() for p in validation.validate(path) if p.severity == "error"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A small scene with one finished 3-step run."""
    out = tmp_path_factory.mktemp("integrity") / "scene"
    gen(out, steps=3)
    return out


def copy_scene(src, dst):
    import shutil
    shutil.copytree(src, dst)
    return dst


# ----------------------------------------------------------------------------- checkpoints
def test_finished_run_keeps_no_checkpoint_and_layer_holds_overs_only(finished):
    sc = S.Scene.open(finished)
    run = sc.runs()[0]
    files = sc.run_files(run.name)
    assert not (files.dir / "state.json").exists() and not list(files.dir.glob("state-*"))
    assert files.summary.is_file()
    layer = Sdf.Layer.FindOrOpen(str(run.path))
    chunks = [c.path for c in layer.GetPrimAtPath(S.SURFELS_PATH).nameChildren]
    assert len(chunks) == 4
    for path in ["/World", S.SURFELS_PATH] + chunks:
        assert layer.GetPrimAtPath(path).specifier == Sdf.SpecifierOver, path
    assert run.provenance["complete"] and errors_of(finished) == []
    deps = json.loads(run.provenance["dependsOn"]) if isinstance(run.provenance["dependsOn"], str) \
        else run.provenance["dependsOn"]
    assert set(deps) == {"surfels", "env"}


def test_pickled_checkpoint_is_refused_and_never_unpickled(tmp_path, run_cli):
    out = tmp_path / "scene"
    gen(out)
    run_dir = out / "ggds" / "ggds_20260101-000000"
    run_dir.mkdir(parents=True)
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))
    import pickle
    (run_dir / "state.pt").write_bytes(pickle.dumps({"params": Payload()}))
    r = run_cli("generate", "-o", out, "--resume", *SMALL)
    error_line(r, "state.pt", "pickled checkpoint")
    assert not marker.exists()


def test_truncated_or_foreign_checkpoint_is_one_line(tmp_path, run_cli, monkeypatch):
    out = tmp_path / "scene"
    gen(out)
    from lsd3d_usd.ggds.run import optimisation as R
    real = R.GGDSRun.step
    n = {"k": 0}

    def stop_at_3(self):
        n["k"] += 1
        if n["k"] == 3:
            raise KeyboardInterrupt
        return real(self)
    monkeypatch.setattr(R.GGDSRun, "step", stop_at_3)
    with pytest.raises(KeyboardInterrupt):
        gen(out, steps=6)
    monkeypatch.setattr(R.GGDSRun, "step", real)
    run = S.Scene.open(out).unfinished_runs()[0]
    d = out / "ggds" / run
    tensors = next(d.glob("state-*.safetensors"))
    tensors.write_bytes(tensors.read_bytes()[:200])
    r = run_cli("generate", "-o", out, "--resume", *SMALL)
    error_line(r, "unreadable checkpoint", tensors.name)
    meta = json.loads((d / "state.json").read_text())
    meta["tensors"] = "../../../etc/passwd"
    (d / "state.json").write_text(json.dumps(meta))
    error_line(run_cli("generate", "-o", out, "--resume", *SMALL), "bad tensor file name")


# ----------------------------------------------------------------------------- paths
def test_muted_layer_outside_the_scene_is_refused(tmp_path, run_cli):
    out = tmp_path / "a" / "b" / "scene"
    gen(out)
    precious = tmp_path / "a" / "precious.usdc"
    precious.write_bytes(b"keep me")
    root = Sdf.Layer.FindOrOpen(str(out / "scene.usda"))
    data = dict(root.customLayerData)
    lsd = dict(data["lsd3d"])
    lsd["mutedLayers"] = Vt.StringArray(["../../precious.usdc"])
    data["lsd3d"] = lsd
    root.customLayerData = data
    root.Save()
    error_line(run_cli("scene", "remove", out, "precious", "--delete"), "../../precious.usdc",
                   "not a layer file inside layers/")
    error_line(run_cli("scene", "layers", out), "precious")
    assert precious.read_bytes() == b"keep me"


def test_scene_inside_refuses_escapes(tmp_path):
    sc = S.Scene.create(tmp_path / "s")
    assert sc.inside("layers/x.usdc") == (tmp_path / "s" / "layers" / "x.usdc").resolve()
    for bad in ("../x", "/etc/passwd", "layers/../../x"):
        with pytest.raises(InputError, match="outside the scene folder"):
            sc.inside(bad)


# ----------------------------------------------------------------------------- re-runs
@pytest.mark.parametrize("change", [{"surfels": 2000}, {"seed": 2}, {"prompt": "rainy night"}])
def test_changing_what_a_run_was_made_on_refuses_then_retires(finished, tmp_path, change):
    out = copy_scene(finished, tmp_path / "scene")
    run = S.Scene.open(out).runs()[0].name
    before = {p.name: p.read_bytes() for p in (out / "layers").iterdir() if p.is_file()}
    with pytest.raises(InputError, match=rf"{run}.*--retire-runs"):
        gen(out, **change)
    assert {p.name: p.read_bytes() for p in (out / "layers").iterdir() if p.is_file()} == before
    gen(out, run={"retire_runs": True}, **change)
    sc = S.Scene.open(out)
    info = {li.name: li for li in sc.layers()}[run]
    assert info.muted and info.provenance["stale"]
    assert errors_of(out) == []
    # the unchanged settings again: nothing to retire, nothing refused
    gen(out, **change)


def test_unchanged_rerun_keeps_the_run_active(finished, tmp_path):
    out = copy_scene(finished, tmp_path / "scene")
    gen(out)
    assert not S.Scene.open(out).runs()[0].muted


def test_import_ply_over_a_run_needs_retire(finished, tmp_path, run_cli):
    out = copy_scene(finished, tmp_path / "scene")
    ply = tmp_path / "s.ply"
    assert run_cli("splats", "export-ply", out / "layers" / "surfels.usdc", "-o", ply).returncode == 0
    run = S.Scene.open(out).runs()[0].name
    error_line(run_cli("splats", "import-ply", ply, "-o", out), run, "--retire-runs")
    r = run_cli("splats", "import-ply", ply, "-o", out, "--retire-runs")
    assert r.returncode == 0, r.stderr
    assert S.Scene.open(out).runs()[0].muted


def test_resume_uses_recorded_settings_and_refuses_conflicts(tmp_path, run_cli, monkeypatch):
    out = tmp_path / "scene"
    from lsd3d_usd.ggds.run import optimisation as R
    real = R.GGDSRun.step
    n = {"k": 0}

    def stop(self):
        n["k"] += 1
        if n["k"] == 3:
            raise KeyboardInterrupt
        return real(self)
    monkeypatch.setattr(R.GGDSRun, "step", stop)
    with pytest.raises(KeyboardInterrupt):
        gen(out, steps=8, checkpoint_every=4, ggds={"held_out": 2, "lr": {"sh_dc": 0.02}})
    monkeypatch.setattr(R.GGDSRun, "step", real)
    error_line(run_cli("generate", "-o", out, "--resume", "--seed", "2"),
                   "conflicting", "seed 2")
    r = run_cli("generate", "-o", out, "--resume", "--steps", "5", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "with its recorded settings" in r.stderr
    sc = S.Scene.open(out)
    run = sc.runs()[0]
    assert run.provenance["stepsDone"] == 5 and not run.provenance["complete"]
    assert json.loads(run.provenance["generate"])["ggds"]["lr"]["sh_dc"] == 0.02
    r = run_cli("generate", "-o", out, "--resume", "--no-progress")
    assert r.returncode == 0, r.stderr
    run = S.Scene.open(out).runs()[0]
    assert run.provenance["stepsDone"] == 8 and run.provenance["complete"]
    error_line(run_cli("generate", "-o", out, "--resume", "--seed", "2"),
                   "no unfinished GGDS run")


# ----------------------------------------------------------------------------- one line
def test_generate_output_and_json_paths_checked_before_work(tmp_path, run_cli):
    f = tmp_path / "file"
    f.write_text("x")
    error_line(run_cli("generate", "-o", f, *SMALL, "--steps", "0"), "not a folder")
    error_line(run_cli("generate", "-o", tmp_path / "s", "--json", f / "s.json",
                           *SMALL, "--steps", "0"), "--json", "is a file, not a folder")
    assert not (tmp_path / "s").exists()
    error_line(run_cli("generate", "-o", tmp_path / "s", "--set", "ggds.lr.sh_dcc=1"),
                   "did you mean 'ggds.lr.sh_dc'")
    assert not (tmp_path / "s").exists()


def test_stale_temp_files_are_cleaned_on_open(tmp_path):
    sc = S.Scene.create(tmp_path / "s")
    dead = tmp_path / "s" / "layers" / ".surfels.tmp-999999999-0123abcd.usdc"
    dead.write_bytes(b"half")
    mine = tmp_path / "s" / "layers" / f".env.tmp-{os.getpid()}-0123abcd.usda"
    mine.write_bytes(b"in progress")
    S.Scene.open(sc.root)
    assert not dead.exists() and mine.exists()
