"""The UsdGeom.Points preview of the surfels (splats.preview): arrays against a float64
reference, what a plain usd-core reader sees in a generated scene, GGDS runs' previews and
muting, and fraction 0."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom
from scipy.spatial.transform import Rotation

from conftest import generate_small, random_field
from lsd3d_usd import validation
from lsd3d_usd.scene import SURFEL_PREVIEW_PATH, Scene, chunk_prim_name
from lsd3d_usd.splats import chunkio
from lsd3d_usd.splats.preview import (
    DEFAULT_FRACTION,
    preview_arrays,
    preview_count,
    preview_indices,
    preview_prim_name,
)

C0 = 0.28209479177387814


def test_preview_arrays_match_a_float64_reference():
    f = random_field(500, sh_degree=1, seed=3)
    fraction = 0.2
    idx = preview_indices(f.n, fraction, (2, -1))
    assert len(idx) == preview_count(f.n, fraction) == 100
    assert np.array_equal(idx, np.unique(idx)) and idx.min() >= 0 and idx.max() < f.n
    assert np.array_equal(idx, preview_indices(f.n, fraction, (2, -1)))      # deterministic
    assert not np.array_equal(idx, preview_indices(f.n, fraction, (2, 0)))   # per chunk
    a = preview_arrays(f, fraction, (2, -1))
    assert np.array_equal(a["points"], f.positions[idx])
    q = np.asarray(f.orientations[idx], np.float64)                          # xyzw
    ref_n = Rotation.from_quat(q / np.linalg.norm(q, axis=1, keepdims=True)).apply([0.0, 0, 1])
    assert np.abs(a["normals"] - ref_n).max() < 1e-5
    s = np.asarray(f.scales[idx], np.float64)
    ref_w = 2 * np.sqrt(2 * s[:, 0] * s[:, 1] / fraction)      # disks of radius sqrt(2) sigma
    assert np.allclose(a["widths"], ref_w, rtol=1e-5)
    ref_c = np.clip(0.5 + C0 * np.asarray(f.sh[idx, 0], np.float64), 0, 1)
    assert np.abs(a["colors"] - ref_c).max() < 1e-6
    assert np.array_equal(a["opacities"], np.clip(f.opacities[idx], 0, 1))
    # the points cover the area the whole field covers (each stands for 1/fraction surfels)
    covered = np.pi * (a["widths"].astype(np.float64) / 2) ** 2
    whole = 2 * np.pi * np.prod(np.asarray(f.scales, np.float64), axis=1)
    assert covered.sum() == pytest.approx(whole.sum(), rel=0.15)


def test_preview_degenerate_inputs():
    assert preview_count(0, 0.5) == 0 and len(preview_indices(0, 0.5)) == 0
    assert preview_count(1000, 0.0) == 0 and len(preview_indices(1000, 0.0)) == 0
    assert preview_count(3, 1e-6) == 1                   # a non-empty chunk keeps one point
    assert np.array_equal(preview_indices(7, 1.0), np.arange(7))
    f = random_field(1, seed=1)
    a = preview_arrays(f, 1e-6)
    assert len(a["points"]) == 1 and np.isfinite(a["widths"]).all()


# A reader with nothing of ours loaded: plain usd-core, as another tool opens the scene.
PLAIN_READER = r"""
import json, sys
import numpy as np
from pxr import Usd, UsdGeom
stage = Usd.Stage.Open(sys.argv[1])
out = {}
for prim in stage.GetPrimAtPath(sys.argv[2]).GetChildren():
    pts = UsdGeom.Points(prim)
    out[prim.GetName()] = {
        "type": prim.GetTypeName(), "purpose": pts.GetPurposeAttr().Get(),
        "n": len(pts.GetPointsAttr().Get()), "widths": len(pts.GetWidthsAttr().Get()),
        "normals": len(pts.GetNormalsAttr().Get()),
        "colors": np.asarray(pts.GetDisplayColorPrimvar().Get()).tolist(),
        "interp": pts.GetDisplayColorPrimvar().GetInterpolation()}
surf = stage.GetPrimAtPath("/World/Surfels").GetChildren()
out["_surfels"] = {p.GetName(): [str(p.GetAttribute("purpose").Get()),
                                 [str(t) for t in p.GetRelationship("proxyPrim").GetTargets()]]
                   for p in surf}
print(json.dumps(out))
"""


def _plain_read(scene_dir):
    r = subprocess.run([sys.executable, "-c", PLAIN_READER, str(scene_dir / "scene.usda"),
                        SURFEL_PREVIEW_PATH], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_generated_scene_preview_seen_by_plain_usd(small_scene):
    sc = Scene.open(small_scene)
    root = sc.layer_path("surfels")
    chunks = chunkio.read_chunk_map(root)
    runs = [p for p in sc.root.joinpath("layers").glob("ggds_*.usdc")]
    assert len(runs) == 1                       # SMALL_SCENE has one GGDS run
    got = _plain_read(small_scene)
    surfels = got.pop("_surfels")
    assert set(got) == {chunk_prim_name(*k) for k in chunks}
    for key, info in chunks.items():
        name = chunk_prim_name(*key)
        p = got[name]
        assert p["type"] == "Points" and p["purpose"] == "proxy" and p["interp"] == "vertex"
        assert p["n"] == p["widths"] == p["normals"] == len(p["colors"]) == info["preview"]
        assert info["preview"] == preview_count(info["count"], DEFAULT_FRACTION)
        assert surfels[name] == ["render", [f"{SURFEL_PREVIEW_PATH}/{name}"]]
        # the composed preview shows the run's surfels: their DC colours at the sampled rows
        field = chunkio.read_chunk(root, key, runs)
        ref = np.clip(0.5 + C0 * field.sh[preview_indices(field.n, DEFAULT_FRACTION, key), 0], 0, 1)
        assert np.abs(np.asarray(p["colors"]) - ref).max() < 1e-5
    assert not [p for p in validation.validate(small_scene) if p.severity == "error"]
    from lsd3d_usd.inspection import inspect
    pv = inspect(small_scene)["preview"]
    assert pv == {"path": SURFEL_PREVIEW_PATH, "prims": len(chunks),
                  "points": sum(v["preview"] for v in chunks.values())}


def test_muting_a_run_mutes_its_preview(small_scene):
    sc = Scene.open(small_scene)
    root = sc.layer_path("surfels")
    run = next(sc.root.joinpath("layers").glob("ggds_*.usdc"))
    stage = Usd.Stage.Open(str(sc.root_layer_path))
    key = sorted(chunkio.read_chunk_map(root))[0]
    path = f"{SURFEL_PREVIEW_PATH}/{chunk_prim_name(*key)}"
    prim = stage.GetPrimAtPath(path)
    # the run's colours come from its own chunk file, through the run layer
    stack = [s.layer.realPath for s in prim.GetPrimStack()]
    assert str(run) in stack
    run_chunk = chunkio.chunk_folder(run) / chunkio.chunk_file_name(key)
    assert str(run_chunk) in stack
    with_run = np.asarray(UsdGeom.Points(prim).GetDisplayColorPrimvar().Get())
    stage.MuteLayer(str(run))
    muted = np.asarray(UsdGeom.Points(stage.GetPrimAtPath(path)).GetDisplayColorPrimvar().Get())
    base = chunkio.read_chunk(root, key)
    ref = np.clip(0.5 + C0 * base.sh[preview_indices(base.n, DEFAULT_FRACTION, key), 0], 0, 1)
    assert np.abs(muted - ref).max() < 1e-5
    optimised = chunkio.read_chunk(root, key, [run])
    if not np.allclose(optimised.sh[:, 0], base.sh[:, 0]):   # GGDS changed the colours
        assert not np.allclose(with_run, muted)


def test_fraction_zero_writes_no_preview(tmp_path, cli_error, capsys):
    out = tmp_path / "scene"
    generate_small(out, steps=0, splats={"preview_fraction": 0.0})
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert not stage.GetPrimAtPath(SURFEL_PREVIEW_PATH)
    assert not [p for p in stage.Traverse() if p.IsA(UsdGeom.Points)
                and str(p.GetPath()).startswith("/World/Surfels")]
    root = Scene.open(out).layer_path("surfels")
    assert chunkio.preview_fraction_of(root) == 0.0
    for key in chunkio.read_chunk_map(root):
        f = chunkio.chunk_folder(root) / chunkio.chunk_file_name(key)
        assert not Sdf.Layer.FindOrOpen(str(f)).GetPrimAtPath(f"/{preview_prim_name(chunk_prim_name(*key))}")
        assert "preview" not in chunkio.read_chunk_map(root)[key]
    # a re-run with a preview rewrites the surfel layer (the fraction is one of its inputs)
    generate_small(out, steps=0, splats={"preview_fraction": 0.2})
    chunks = chunkio.read_chunk_map(root)
    assert chunkio.preview_fraction_of(root) == 0.2
    assert all(v["preview"] == preview_count(v["count"], 0.2) for v in chunks.values())
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert len(stage.GetPrimAtPath(SURFEL_PREVIEW_PATH).GetChildren()) == len(chunks)
    assert not [p for p in validation.validate(out) if p.severity == "error"]
    # the setting is a generate option, bounded
    from lsd3d_usd.cli import main
    assert main(["generate", "--list-options"]) == 0
    assert "splats.preview_fraction" in capsys.readouterr().out
    cli_error(["generate", "-o", tmp_path / "x", "--set", "splats.preview_fraction=1.5"],
              "splats.preview_fraction")


def test_surfel_files_and_monolithic_layers_get_a_preview(tmp_path, cli_error):
    from lsd3d_usd.splats.usdio import write_surfel_file

    f = random_field(400, seed=2)
    path = tmp_path / "s.usdc"
    write_surfel_file(str(path), f)
    stage = Usd.Stage.Open(str(path))
    pts = UsdGeom.Points(stage.GetPrimAtPath(f"{SURFEL_PREVIEW_PATH}/Surfels"))
    assert len(pts.GetPointsAttr().Get()) == preview_count(400, DEFAULT_FRACTION)
    surf = stage.GetPrimAtPath("/World/Surfels")
    assert surf.GetAttribute("purpose").Get() == "render"
    assert surf.GetRelationship("proxyPrim").GetTargets() == [pts.GetPath()]
    assert not [p for p in validation.validate(path) if p.severity == "error"]
    write_surfel_file(str(tmp_path / "none.usdc"), f, preview_fraction=0.0)
    assert not Usd.Stage.Open(str(tmp_path / "none.usdc")).GetPrimAtPath(SURFEL_PREVIEW_PATH)
    cli_error(["splats", "import-ply", tmp_path / "x.ply", "-o", tmp_path / "y.usdc",
               "--preview-fraction", "2"], "--preview-fraction")
