"""Blender opens a generated scene (the real consumer: Blender's own USD importer, through the
``bpy`` module of the ``[interop]`` extra): proxy meshes per chunk, animated actors, cameras,
and the surfel preview as one point cloud per chunk with the surfels' colours; a Workbench
render from a scene camera shows the surfels. And an asset Blender exported gets its
per-instance paint in our renderer.

Blender runs in a child process (tools/blender_import.py): bpy bundles its own USD, which
does not share a process with usd-core."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from conftest import ROOT, generate_small
from lsd3d_usd.scene import PROXY_PATH, SURFEL_PREVIEW_PATH, Scene, chunk_prim_name
from lsd3d_usd.splats import chunkio

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("bpy") is None,
    reason="bpy is not installed (pip install -e '.[interop]'; its 4.2 wheels need Python 3.11)")

TOOL = ROOT / "tools" / "blender_import.py"


def _blender(*args, timeout=600):
    r = subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return r


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("blender") / "scene"
    generate_small(out, steps=0, surfels=20000, actors=True, parked=2, moving=3,
                   actor_seconds=1.0)
    return out


def test_blender_imports_a_generated_scene(scene, tmp_path):
    rep_path = tmp_path / "report.json"
    _blender(TOOL, scene, "--json", rep_path, "--render", tmp_path / "preview.png",
             "--camera", "Train_000", "--resolution", "96x54", "--only-preview")
    rep = json.loads(rep_path.read_text())
    stage = Usd.Stage.Open(str(scene / "scene.usda"))
    # proxy: every chunk's meshes
    want = {p.GetName(): sum(1 for q in Usd.PrimRange(p) if q.IsA(UsdGeom.Mesh))
            for p in stage.GetPrimAtPath(PROXY_PATH).GetChildren()}
    assert rep["proxy"] == want and all(want.values())
    # actors: each one imported, the moving ones animated
    roles = {p.GetName(): p.GetAttribute("lsd3d:actor:role").Get()
             for p in Usd.PrimRange(stage.GetPrimAtPath("/World/Actors"))
             if p.HasAttribute("lsd3d:actor:role")}
    assert set(rep["actors"]) == set(roles) and "moving" in roles.values()
    for name, a in rep["actors"].items():
        assert a["meshes"], name
        assert a["animated"] == (roles[name] == "moving"), name
        # the per-instance paint reaches Blender through the paint material (the body), the
        # glass and the wheels keep theirs
        paint = UsdGeom.PrimvarsAPI(next(p for p in stage.Traverse() if p.GetName() == name)
                                    ).GetPrimvar("displayColor").Get()[0]
        assert a["meshes"]["Body"]["material"] == pytest.approx(list(paint), abs=1e-4), name
        assert a["meshes"]["Cabin"]["material"] != a["meshes"]["Body"]["material"]
    # cameras
    cams = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
    assert len(rep["cameras"]) == len(cams) > 0
    # the surfel preview: one point cloud per chunk, its count, the surfels' colours
    root = Scene.open(scene).layer_path("surfels")
    chunks = chunkio.read_chunk_map(root)
    assert set(rep["preview"]) == {chunk_prim_name(*k) for k in chunks}
    for key, info in chunks.items():
        name = chunk_prim_name(*key)
        got = rep["preview"][name]
        assert got["points"] == info["preview"] > 0
        dc = np.clip(chunkio.read_chunk(root, key).colors(), 0, 1).mean(0)
        assert np.abs(np.asarray(got["mean_color"]) - dc).max() < 0.05, (name, got, dc)
        widths = np.asarray(UsdGeom.Points(stage.GetPrimAtPath(
            f"{SURFEL_PREVIEW_PATH}/{name}")).GetWidthsAttr().Get())
        assert got["mean_radius"] == pytest.approx(widths.mean() / 2, rel=1e-3)
    # the render from a scene camera shows the surfels (the preview alone, meshes hidden)
    assert rep["render"]["covered"] >= 0.30, rep["render"]


BLENDER_CUBE = r"""
import sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.mesh.primitive_cube_add(size=2.0, location=(0, 0, 1))
mat = bpy.data.materials.new("Grey")
mat.use_nodes = True
mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.8, 0.8, 1)
bpy.context.active_object.data.materials.append(mat)
bpy.ops.wm.usd_export(filepath=sys.argv[1], export_materials=True)
"""


def test_blender_exported_asset_gets_its_paint(tmp_path):
    from lsd3d_usd.actors.compose import add_actors
    from lsd3d_usd.actors.usdio import ActorSet
    from lsd3d_usd.layout.generator import generate
    from lsd3d_usd.layout.usdio import layout_to_stage

    lib = tmp_path / "lib"
    lib.mkdir()
    _blender("-c", BLENDER_CUBE, lib / "car.usda", timeout=300)
    layout = generate(3, (200.0, 200.0))
    sc = Scene.create(tmp_path / "scene")
    sc.write_layer("layout", layout_to_stage(layout))
    add_actors(sc, layout, parked=3, moving=2, seed=1, seconds=1.0, fps=5.0, assets_dir=lib)
    stage = sc.open_stage()
    read = ActorSet(stage)
    assert len(read) >= 4
    paints = set()
    for a in read.actors:
        pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(a.path)).GetPrimvar("displayColor")
        paint = np.asarray(pv.Get(), np.float32).reshape(3)
        paints.add(tuple(paint))
        assert a.meshes and all(np.allclose(m.colors, paint) for m in a.meshes), a.path
    assert len(paints) >= 2
    # and in Blender, through the paint material, stronger than the cube's own
    rep_path = tmp_path / "report.json"
    _blender(TOOL, sc.root, "--json", rep_path)
    rep = json.loads(rep_path.read_text())
    assert len(rep["actors"]) == len(read)
    for a in read.actors:
        paint = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(a.path)).GetPrimvar("displayColor").Get()[0]
        meshes = rep["actors"][a.path.rsplit("/", 1)[-1]]["meshes"]
        assert meshes and all(m["material"] == pytest.approx(list(paint), abs=1e-4)
                              for m in meshes.values()), (a.path, meshes)
