"""`generate`: the whole pipeline on a small hand-authored layout; bad input writes nothing;
re-runs reuse unchanged layers; GGDS writes only overs; Ctrl-C leaves a resumable scene."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf

from conftest import ROOT
from lsd3d_usd import scene as S
from lsd3d_usd import validation
from lsd3d_usd.errors import InputError
from lsd3d_usd.config import generate_config
from lsd3d_usd.pipeline import RunOptions, generate as _generate

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"


RUN_KEYS = ("resume", "force", "retire_runs", "keep_checkpoint")


def opts(out, **kw):
    """(config, run options) of a small scene; run-control keys go to RunOptions."""
    base = dict(layout=LAYOUT, steps=0, surfels=4000, env_resolution=(128, 64),
                resolution=(64, 48), views=4, perceptual=False, prompt="sunny morning in Madrid")
    base.update(kw)
    run = {k: base.pop(k) for k in RUN_KEYS if k in base}
    return generate_config(**base), RunOptions(out=Path(out), progress=False, log=lambda *a: None,
                                               **run)


def generate(o):
    return _generate(*o)


def test_steps_zero_builds_a_valid_scene_and_reuses_it(tmp_path):
    out = tmp_path / "scene"
    summary = generate(opts(out))
    assert summary["surfels"]["count"] == 4000 and not summary["surfels"]["reused"]
    names = [i.name for i in S.Scene.open(out).layers()]
    assert names == ["surfels", "cameras", "actors", "env", "proxy", "layout"]
    assert summary["actors"]["moving"] > 0
    # Actor assets are referenced from the scene's own assets/ folder, never copied elsewhere.
    assert sorted(p.name for p in (out / "assets").glob("*.usda")) == [
        "adult.usda", "adult_broad.usda", "bus.usda", "car.usda", "child.usda", "cyclist.usda",
        "truck.usda", "van.usda"]                  # a street has people by default
    assert summary["actors"]["pedestrians"] > 0
    errors = [p for p in validation.validate(out) if p.severity == "error"]
    assert errors == [], [p.line() for p in errors]
    # The layout layer is the input exactly as given.
    assert (out / "layers" / "layout.usda").read_bytes() == LAYOUT.read_bytes()
    surf = (out / "layers" / "surfels.usdc").read_bytes()
    again = generate(opts(out))
    assert again["surfels"]["reused"] and again["proxy"]["built"] == 0
    assert (out / "layers" / "surfels.usdc").read_bytes() == surf


@pytest.mark.parametrize("bad,match", [
    (dict(steps=3, prior="diffusers:/nonexistent/model"), "no such directory"),
    (dict(layout=Path("/nonexistent/layout.usda")), "no such file"),
])
def test_bad_input_writes_nothing(tmp_path, bad, match):
    out = tmp_path / "scene"
    with pytest.raises(InputError, match=match):
        generate(opts(out, **bad))
    assert not out.exists()


def test_layout_without_lanes_is_refused(tmp_path):
    lay = tmp_path / "nolanes.usda"
    lay.write_text('#usda 1.0\n(\n defaultPrim = "World"\n metersPerUnit = 1\n upAxis = "Z"\n)\n'
                   'def Xform "World" {\n def Scope "Layout" {\n }\n}\n')
    out = tmp_path / "scene"
    with pytest.raises(InputError, match="no drivable lanes"):
        generate(opts(out, layout=lay))
    assert not out.exists()


def test_output_folder_with_other_content_is_refused(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        generate(opts(out))
    assert os.listdir(out) == ["notes.txt"]


def test_output_folder_with_a_different_scene_is_refused(tmp_path):
    out = tmp_path / "scene"
    generate(opts(out))
    other = ROOT / "samples" / "layouts" / "curved_road.usda"
    before = sorted(p.name for p in (out / "layers").iterdir())
    with pytest.raises(InputError, match="holds a different scene"):
        generate(opts(out, layout=other))
    assert sorted(p.name for p in (out / "layers").iterdir()) == before


class _Stop(Exception):
    pass


def test_ggds_writes_overs_and_survives_interrupt(tmp_path, monkeypatch):
    pytest.importorskip("lsd3d_usd.ggds.priors.procedural")
    from lsd3d_usd.ggds.run import optimisation as R
    out = tmp_path / "scene"
    generate(opts(out))
    surfels_before = (out / "layers" / "surfels.usdc").read_bytes()

    real_step = R.GGDSRun.step
    calls = {"n": 0}

    def interrupting_step(self):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(R.GGDSRun, "step", interrupting_step)
    with pytest.raises(KeyboardInterrupt):
        generate(opts(out, steps=6, checkpoint_every=2))
    monkeypatch.setattr(R.GGDSRun, "step", real_step)
    sc = S.Scene.open(out)
    runs = [i for i in sc.layers() if i.name.startswith("ggds_")]
    assert len(runs) == 1
    assert runs[0].provenance["stepsDone"] == 3 and not runs[0].provenance["complete"]
    assert [p for p in validation.validate(out) if p.severity == "error"] == []
    summary = generate(opts(out, steps=6, resume=True))
    assert summary["ggds"]["steps"] == 6
    # where the time outside the steps went: each part once, together within the wall time
    g = summary["ggds"]
    ph = g["phases_s"]
    assert set(ph) == {"inputs", "init", "colour_start", "eval", "plots", "write"}
    assert min(ph.values()) >= 0 and sum(ph.values()) <= g["wall_s"] + 0.1
    layer = Sdf.Layer.FindOrOpen(str(runs[0].path))
    spec = layer.GetPrimAtPath(S.SURFELS_PATH)
    assert spec.specifier == Sdf.SpecifierOver and not spec.attributes
    for chunk in (out / "layers" / f"{runs[0].name}_chunks").glob("chunk_*.usdc"):
        cl = Sdf.Layer.FindOrOpen(str(chunk))
        cspec = cl.GetPrimAtPath("/" + cl.defaultPrim)
        assert cspec.specifier == Sdf.SpecifierOver
        assert set(cspec.attributes.keys()) <= {
            "positions", "orientations", "scales", "opacities", "extent",
            "radiance:sphericalHarmonicsCoefficients", "radiance:sphericalHarmonicsDegree"}
    prov = S.read_provenance(layer)
    assert prov["complete"] and prov["stepsDone"] == 6
    assert len(json.loads((out / "ggds" / runs[0].name / "views.json").read_text())) == 4
    # GGDS never rewrites the initial surfels.
    assert (out / "layers" / "surfels.usdc").read_bytes() == surfels_before
    for f in ("loss.png", "before_after.png", "summary.json"):
        assert (out / "ggds" / runs[0].name / f).is_file()


def test_generated_scene_has_cameras_to_look_through(tmp_path, capsys):
    """layers/cameras.usda: the very views GGDS trained on (pose and intrinsics), held-out
    views and overviews as UsdGeom.Camera prims; `render --camera` works on a fresh scene."""
    from pxr import UsdGeom

    from lsd3d_usd.cli import main
    from lsd3d_usd.conditioning.view_sampling import View
    from lsd3d_usd.render.camera import from_usd
    out = tmp_path / "scene"
    summary = generate(opts(out, steps=2, **{"ggds.held_out": 2}))
    assert summary["cameras"] == {"train": 4, "held_out": 2, "overview": 5, "reused": False}
    stage = S.Scene.open(out).open_stage()
    cams = sorted(str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdGeom.Camera))
    assert cams == sorted([f"/World/Cameras/Train/Train_{k:03d}" for k in range(4)]
                          + [f"/World/Cameras/HeldOut/HeldOut_{k:03d}" for k in range(2)]
                          + [f"/World/Cameras/Overview/{n}" for n in
                             ("Top", "SouthWest", "SouthEast", "NorthEast", "NorthWest")])
    from lsd3d_usd.ggds.run.store import run_views
    run = next(li for li in S.Scene.open(out).layers() if li.is_run)
    trained = [View.from_json(d) for d in run_views(S.Scene.open(out), run.name)]
    assert len(trained) == 4
    for k, v in enumerate(trained):
        prim = stage.GetPrimAtPath(f"/World/Cameras/Train/Train_{k:03d}")
        cam = from_usd(prim, None, v.camera.width, v.camera.height, conform="stretch")
        np.testing.assert_allclose(cam.pose, v.camera.pose, atol=1e-5)
        np.testing.assert_allclose(cam.K, v.camera.K, rtol=1e-5)
        assert prim.GetAttribute("lsd3d:camera:lane").Get() == v.lane_id
    # unchanged settings: the layer is kept as it is
    layer_bytes = (out / "layers" / "cameras.usda").read_bytes()
    assert generate(opts(out, steps=0, **{"ggds.held_out": 2}))["cameras"]["reused"]
    assert (out / "layers" / "cameras.usda").read_bytes() == layer_bytes
    capsys.readouterr()
    for cam in ("/World/Cameras/Train/Train_000", "/World/Cameras/Overview/Top"):
        assert main(["render", str(out), "--camera", cam, "--resolution", "64",
                     "-o", str(tmp_path / "frames"), "--no-progress"]) == 0
    from lsd3d_usd.views.images import read_image
    for name, h in (("Train_000", 48), ("Top", 36)):   # heights from each aperture's aspect
        im = read_image(tmp_path / "frames" / f"{name}.png")
        assert im.shape[:2] == (h, 64) and im[..., :3].std() > 0.02
