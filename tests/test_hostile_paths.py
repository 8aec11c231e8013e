"""Writes and deletes never go through a symbolic link or outside the folder they belong to
(issue 40, cases 1-3 and the scene part of 7)."""
import os
import shutil

import pytest

from lsd3d_usd import safepaths
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError


def _tree(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ------------------------------------------------------------------------ helpers
def test_safepaths_refuse_links_and_outside(tmp_path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    (root / "d").mkdir(parents=True)
    (outside / "keep").mkdir(parents=True)
    (outside / "keep" / "x").write_text("precious")
    os.symlink(outside, root / "link")
    for fn, args in [(safepaths.rmtree, (root / "link",)), (safepaths.rmtree, (root / "link" / "keep",)),
                     (safepaths.unlink, (root / "link" / "keep" / "x",)),
                     (safepaths.rmtree, (outside / "keep",)), (safepaths.rmtree, (root / ".." / "outside",))]:
        with pytest.raises(InputError) as e:
            fn(*args, root)
        assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="symbolic link"):
        safepaths.check_tree(root, root / "..")
    assert _tree(outside) == ["keep", "keep/x"]
    (root / "d" / "f").write_text("")
    safepaths.rmtree(root / "d", root)           # a plain folder inside is removed
    assert not (root / "d").exists()


# ------------------------------------------------------------------ 1. viewer cache
def test_viewer_cache_symlink_is_not_followed(tmp_path):
    from tests.test_viewer_server import make_scene
    from lsd3d_usd.viewer.service import ViewerService
    root = tmp_path / "scene"
    make_scene(root)
    outside = tmp_path / "OUTSIDE"
    for k in range(9):
        (outside / f"surfels_old{k}").mkdir(parents=True)
        (outside / f"surfels_old{k}" / "data.bin").write_bytes(b"precious")
    before = _tree(outside)
    os.symlink(outside, root / "viewer_cache")
    svc = ViewerService(root, validate=False)
    for runs in ([], None):
        cfg = svc.config(runs)
        assert cfg.chunks and not cfg.folder.is_relative_to(outside)
    assert _tree(outside) == before
    assert any("symbolic link" in p["message"] for p in svc.problems)


# --------------------------------------------------- 2. generate re-run through links
@pytest.mark.parametrize("linked", ["layers/proxy_chunks", "layers/surfels_chunks", "ggds"])
def test_rerun_refuses_symlinked_scene_folders(small_scene, tmp_path, linked):
    from tests.conftest import generate_small
    from lsd3d_usd.validation import validate
    copy = tmp_path / "S"
    shutil.copytree(small_scene, copy, symlinks=True)
    outside = tmp_path / "outside"
    shutil.move(copy / linked, outside)
    (outside / "chunk_9_9.usdc").write_text("precious")
    (outside / "chunk_precious.usdc").write_text("precious")
    os.symlink(outside, copy / linked)
    before, scene_before = _tree(outside), (copy / S.ROOT_FILE).read_bytes()
    problems = [p for p in validate(copy) if p.check == "lsd3d:SymbolicLink"]
    assert problems and linked in problems[0].message
    with pytest.raises(InputError, match="symbolic link") as e:
        generate_small(copy)
    assert "\n" not in str(e.value)
    assert _tree(outside) == before and (copy / S.ROOT_FILE).read_bytes() == scene_before


def test_proxy_build_refuses_a_linked_chunk_folder(tmp_path):
    from lsd3d_usd.layout.usdio import read_layout
    from lsd3d_usd.proxy.usdio import build_proxy_layer
    from tests.conftest import LAYOUT
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "chunk_9_9.usdc").write_text("precious")
    os.symlink(outside, tmp_path / "proxy_chunks")
    with pytest.raises(InputError, match="symbolic link"):
        build_proxy_layer(read_layout(LAYOUT), tmp_path / "proxy.usdc")
    assert _tree(outside) == ["chunk_9_9.usdc"] and not (tmp_path / "proxy.usdc").exists()


# ----------------------------------------------- 7. scene remove checks before changing
def test_scene_remove_of_a_linked_run_changes_nothing(tmp_path, cli_error):
    from tests.test_viewer_server import RUN, make_scene
    root = tmp_path / "scene"
    make_scene(root)
    outside = tmp_path / "outside"
    shutil.move(root / "ggds" / RUN, outside)
    os.symlink(outside, root / "ggds" / RUN)
    before = (root / S.ROOT_FILE).read_bytes()
    cli_error(["scene", "remove", root, RUN, "--delete"], "symbolic link")
    assert (root / S.ROOT_FILE).read_bytes() == before and (outside / "summary.json").is_file()


# ---------------------------------------------------- 3. batch outputs outside the spec
def _spec(folder, text):
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / "spec.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("body,needle", [
    ('[batch]\noutput = "../../outside_b"\n[[scene]]\nname = "a"', "batch.output"),
    ('[[scene]]\nname = "a"\noutput = "/tmp"', "scene[0] ('a').output"),
    ('[batch]\noutput = "../../"\n[[scene]]\nname = "a"\noutput = "../../../"', "batch.output"),
    ('[[scene]]\nname = "a"\noutput = "../../.."', "holds the spec's folder"),
    ('[batch]\noutput = "o"\n[[scene]]\nname = "a"\noutput = "../link/x"', "scene[0] ('a').output"),
])
def test_batch_outputs_outside_need_permission(tmp_path, cli_error, body, needle):
    folder = tmp_path / "a" / "b" / "specs"
    p = _spec(folder, body)
    (folder / "link").symlink_to(tmp_path)
    before = _tree(tmp_path)
    line = cli_error(["batch", p, "--dry-run"], needle)
    assert "outside" in line or "holds the spec" in line
    assert _tree(tmp_path) == before


def test_batch_allowed_outputs_and_dry_run_shows_real_paths(tmp_path, capsys):
    from lsd3d_usd.batch.spec import load_spec
    from lsd3d_usd.cli import main
    from tests.conftest import LAYOUT
    shared = tmp_path / "shared"
    folder = tmp_path / "specs"
    p = _spec(folder, f'[batch]\noutput = "../shared/b"\nallowed_outputs = ["../shared"]\n'
                      f'[[scene]]\nname = "a"\nlayout = "{LAYOUT}"\nsteps = 0\n'
                      f'[[scene]]\nname = "c"\nlayout = "{LAYOUT}"\nsteps = 0\noutput = "../x/../c2"\n')
    spec = load_spec(p)
    assert spec.output == shared / "b" and spec.scenes[1].output == shared / "c2"
    # the allowed folder itself is no scene folder
    _spec(folder, f'[batch]\nallowed_outputs = ["../shared"]\n[[scene]]\nname = "a"\noutput = "{shared}"')
    with pytest.raises(InputError, match="outside the spec's folder"):
        load_spec(p)
    _spec(folder, f'[batch]\noutput = "../shared/b"\nallowed_outputs = ["../shared"]\n'
                  f'[[scene]]\nname = "a"\nlayout = "{LAYOUT}"\nsteps = 0\n')
    capsys.readouterr()
    assert main(["batch", str(p), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"output: {shared / 'b'}" in out and f"scene a: {shared / 'b' / 'a'}" in out
    assert not shared.exists()


# ------------------------------------------------------ 11. batch specs: bounded work
def test_batch_scene_count_and_spec_size_limits(tmp_path, cli_error):
    p = _spec(tmp_path, "".join(f'[[scene]]\nname = "s{i}"\n' for i in range(10_001)))
    cli_error(["batch", p, "--dry-run"], "spec.toml", "scene count 10001 scenes exceeds the limit of 10000")
    p.write_text("# " + "x" * (16 * 1024 * 1024) + "\n[[scene]]\nname = \"a\"\n")
    cli_error(["batch", p, "--dry-run"], "spec.toml", "exceeds the limit of 16777216 bytes")
    assert sorted(os.listdir(tmp_path)) == ["spec.toml"]


def test_batch_planning_reads_a_shared_layout_once(tmp_path, monkeypatch):
    from lsd3d_usd.batch import tasks
    from lsd3d_usd.batch.spec import load_spec
    calls = []
    real = tasks.read_layout_for
    monkeypatch.setattr(tasks, "read_layout_for", lambda cfg: calls.append(1) or real(cfg))
    p = _spec(tmp_path, "".join(f'[[scene]]\nname = "s{i}"\nsteps = 0\nextent = [120, 120]\n'
                                f'prompt = "p{i}"\n' for i in range(30)))
    plans = tasks.plan_batch(load_spec(p))
    assert len(plans) == 30 and len(calls) == 1
    assert len({pl.tasks[-1].inputs_hash for pl in plans}) == 30   # still one task per scene


# ----------------------------------------------- 4. composition outside the scene
def _outside_camera(tmp_path):
    from pxr import Usd, UsdGeom
    out = tmp_path / "outside.usda"
    st = Usd.Stage.CreateNew(str(out))
    UsdGeom.Camera.Define(st, "/World/Cameras/Evil")
    st.GetRootLayer().Save()
    return out


@pytest.mark.parametrize("how", ["absolute", "dotdot", "texture"])
def test_render_and_validate_refuse_paths_outside_the_scene(tmp_path, cli_error, how, monkeypatch):
    from pxr import Sdf
    from tests.test_viewer_server import make_scene
    from lsd3d_usd.validation import validate
    root = tmp_path / "scene"
    make_scene(root, chunks=((0, 0),), n=20, run=False, cameras={"Top": ((-10, 20, 30), (50, 50, 0))})
    outside = _outside_camera(tmp_path)
    layer = Sdf.Layer.FindOrOpen(str(root / S.ROOT_FILE))
    if how == "texture":
        spec = Sdf.CreatePrimInLayer(layer, "/World/Env/Dome")
        spec.specifier = Sdf.SpecifierOver
        Sdf.AttributeSpec(spec, "inputs:texture:file", Sdf.ValueTypeNames.Asset).default = \
            Sdf.AssetPath(str(tmp_path / "sky.exr"))
        (tmp_path / "sky.exr").write_bytes(b"x")
    else:
        layer.subLayerPaths.insert(0, str(outside) if how == "absolute" else "./layers/../../outside.usda")
    layer.Save()
    before = sorted(os.listdir(root))
    bad = [p for p in validate(root) if p.check == "lsd3d:OutsideScene"]
    assert bad and ("outside.usda" in bad[0].message or "sky.exr" in bad[0].message)
    cam = "/World/Cameras/Evil" if how != "texture" else "/World/Cameras/Top"
    cli_error(["render", root, "--camera", cam, "--resolution", "32x24", "-o", tmp_path / "f"],
              "outside the scene folder", "LSD3D_ASSET_ROOTS")
    assert not (tmp_path / "f").exists() and sorted(os.listdir(root)) == before
    # a folder the user names is allowed
    monkeypatch.setenv("LSD3D_ASSET_ROOTS", str(tmp_path))
    assert not [p for p in validate(root) if p.check == "lsd3d:OutsideScene"]


def test_layout_sublayers_outside_its_folder_are_refused(tmp_path, cli_error):
    from tests.conftest import LAYOUT
    folder = tmp_path / "lay"
    folder.mkdir()
    (tmp_path / "lane.usda").write_bytes(LAYOUT.read_bytes())
    text = LAYOUT.read_text()
    head, rest = text.split("(", 1)
    (folder / "L.usda").write_text(head + "(\n    subLayers = [@../lane.usda@, @../../../../../../etc/passwd@]\n" + rest)
    cli_error(["layout", "lanes", folder / "L.usda"], "L.usda", "outside the scene folder")


# ------------------------------------------- 7. generate --retire-runs checks first
def test_retire_runs_changes_nothing_when_generate_would_fail(small_scene, tmp_path):
    from pxr import Sdf
    from tests.conftest import generate_small
    copy = tmp_path / "S"
    shutil.copytree(small_scene, copy, symlinks=True)
    surf = copy / "layers" / "surfels.usdc"
    layer = Sdf.Layer.FindOrOpen(str(surf))
    data = dict(layer.customLayerData)
    lsd = dict(data["lsd3d"])
    lsd["chunkFolder"] = "../../elsewhere"
    data["lsd3d"] = lsd
    layer.customLayerData = data
    layer.Save()
    runs_before = [(i.name, i.muted) for i in S.Scene.open(copy).layers()]
    root_before = (copy / S.ROOT_FILE).read_bytes()
    with pytest.raises(InputError, match="chunk folder '../../elsewhere' lies outside"):
        generate_small(copy, run={"retire_runs": True}, surfels=2000)
    assert (copy / S.ROOT_FILE).read_bytes() == root_before
    assert [(i.name, i.muted) for i in S.Scene.open(copy).layers()] == runs_before


# ------------------------------------------- 26. --resume after a kill before GGDS
def test_resume_before_ggds_started_continues_generate(small_scene, tmp_path):
    copy = tmp_path / "S"
    shutil.copytree(small_scene, copy, symlinks=True)
    sc = S.Scene.open(copy)
    for r in sc.runs():                       # as if killed before GGDS started
        sc.remove_layer(r.name, delete_file=True)
    assert not S.Scene.open(copy).runs()
    logs = []
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.pipeline import RunOptions, generate
    from tests.conftest import SMALL_SCENE
    generate(generate_config(**SMALL_SCENE), RunOptions(out=copy, progress=False, resume=True,
                                                        log=logs.append))
    assert any("no GGDS run was started" in m for m in logs)
    runs = S.Scene.open(copy).runs()
    assert len(runs) == 1 and runs[0].provenance["complete"]


# ------------------------------------------- 27. a resumed run's before/after figure
def test_resumed_run_plots_its_initial_surfels(tmp_path, monkeypatch):
    import numpy as np
    from lsd3d_usd.ggds.run import lifecycle
    from lsd3d_usd.ggds.run import optimisation as R
    from tests.conftest import generate_small
    real, n = R.GGDSRun.step, {"k": 0}

    def stop(self):
        n["k"] += 1
        if n["k"] == 3:
            raise KeyboardInterrupt     # killed mid-run: a checkpoint, resumable
        return real(self)
    monkeypatch.setattr(R.GGDSRun, "step", stop)
    out = tmp_path / "S"
    with pytest.raises(KeyboardInterrupt):
        generate_small(out, steps=4, checkpoint_every=2, ggds={"held_out": 2})
    monkeypatch.setattr(R.GGDSRun, "step", real)
    seen = {}
    plots = lifecycle.write_plots
    monkeypatch.setattr(lifecycle, "write_plots",
                        lambda run, held, before, d: seen.update(before=before) or plots(run, held, before, d))
    generate_small(out, run={"resume": True}, steps=4, checkpoint_every=2, ggds={"held_out": 2})
    assert seen["before"] and all(np.isfinite(b).all() for b in seen["before"])
    run = S.Scene.open(out).runs()[0]
    assert run.provenance["complete"] and (out / "ggds" / run.name / "before_after.png").is_file()


def test_a_run_marked_complete_has_its_summary_and_figures(tmp_path, monkeypatch):
    """Case 27: the save that marks a run's steps complete comes last, so a kill right after
    it leaves the run's summary and figures already written (a resume skips complete
    regions and would never write them), and --resume finishes the run."""
    from lsd3d_usd.ggds.run import lifecycle
    from tests.conftest import generate_small
    real = lifecycle._save

    def killed_after(store, run, prior, inputs, **kw):
        out = real(store, run, prior, inputs, **kw)
        if kw.get("final"):
            raise KeyboardInterrupt      # the process dies right after the final save
        return out
    monkeypatch.setattr(lifecycle, "_save", killed_after)
    out = tmp_path / "S"
    with pytest.raises(KeyboardInterrupt):
        generate_small(out, steps=4, checkpoint_every=2, ggds={"held_out": 2})
    from lsd3d_usd.ggds.run.store import region_progress
    sc = S.Scene.open(out)
    run = sc.runs()[0]
    d = out / "ggds" / run.name
    assert region_progress(sc, run.name, "").get("complete")
    assert (d / "summary.json").is_file() and (d / "before_after.png").is_file()
    # and --resume finishes the run's layer from there
    generate_small(out, run={"resume": True}, steps=4, checkpoint_every=2, ggds={"held_out": 2})
    assert S.Scene.open(out).runs()[0].provenance["complete"]
