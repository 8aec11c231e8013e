"""Per-instance actor paint as an inherited constant primvar on the actor's reference root: it
fits any asset (no prim name assumed), and our renderer's actor reader honours it."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors.compose import add_actors
from lsd3d_usd.actors.usdio import PAINT_MATERIAL, ActorSet
from lsd3d_usd.scene import ACTORS_PATH, Scene

MATERIAL_GREY = (0.8, 0.8, 0.8)


def write_cube_asset(path, diffuse=MATERIAL_GREY):
    """A cube as Blender's USD exporter writes one: /root/Cube (Mesh, quads, no
    displayColor) bound to /root/_materials/Material (UsdPreviewSurface)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/root")
    stage.SetDefaultPrim(root.GetPrim())
    cube = UsdGeom.Mesh.Define(stage, "/root/Cube")
    v = np.array([[x, y, z] for x in (-2, 2) for y in (-1, 1) for z in (0, 1.5)], np.float32)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    cube.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(v))
    cube.CreateFaceVertexCountsAttr([4] * 6)
    cube.CreateFaceVertexIndicesAttr(sum(quads, []))
    cube.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([v.min(0), v.max(0)])))
    mat = UsdShade.Material.Define(stage, "/root/_materials/Material")
    sh = UsdShade.Shader.Define(stage, "/root/_materials/Material/Principled_BSDF")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*diffuse))
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(cube.GetPrim()).Bind(mat)
    stage.GetRootLayer().Save()
    return path


@pytest.fixture(scope="module")
def layout():
    from lsd3d_usd.layout.generator import generate
    return generate(3, (200.0, 200.0))


@pytest.fixture()
def scene(tmp_path, layout):
    from lsd3d_usd.layout.usdio import layout_to_stage
    sc = Scene.create(tmp_path / "scene")
    sc.write_layer("layout", layout_to_stage(layout))
    return sc


def _actor_prims(stage):
    return [p for p in Usd.PrimRange(stage.GetPrimAtPath(ACTORS_PATH))
            if p.HasAttribute("lsd3d:actor:role")]


def _paint(prim):
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    assert pv and pv.GetInterpolation() == "constant"
    return np.asarray(pv.Get(), np.float32).reshape(3)


def test_paint_fits_an_asset_with_other_prim_names(scene, layout, tmp_path):
    lib = tmp_path / "lib"
    lib.mkdir()
    cube = write_cube_asset(lib / "car.usda")
    assert A.read_asset(cube).meshes[0].colors[0] == pytest.approx(MATERIAL_GREY)  # its material
    add_actors(scene, layout, parked=4, moving=3, seed=2, seconds=1.0, fps=5.0, assets_dir=lib)
    layer = Sdf.Layer.FindOrOpen(str(scene.layer_path("actors")))
    stage = scene.open_stage()
    actors = _actor_prims(stage)
    assert len(actors) >= 4
    paints = {}
    for p in actors:
        spec = layer.GetPrimAtPath(p.GetPath())
        # nothing authored on the asset's prims: the one child is our own paint material
        assert list(spec.nameChildren.keys()) == [PAINT_MATERIAL], spec.nameChildren.keys()
        assert spec.nameChildren[PAINT_MATERIAL].specifier == Sdf.SpecifierDef
        paints[str(p.GetPath())] = _paint(p)
        # a renderer that shades by material: the paint beats the asset's own material
        mesh = stage.GetPrimAtPath(p.GetPath().AppendPath("Cube"))
        mat, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
        assert mat.GetPath() == p.GetPath().AppendChild(PAINT_MATERIAL)
        assert np.allclose(A.material_colour(mesh)[0], paints[str(p.GetPath())])
    assert len({tuple(v) for v in paints.values()}) >= 2      # per instance
    # the renderer's actor reader: every face of the cube takes its instance's paint
    read = ActorSet(stage)
    assert len(read) == len(actors)
    for a in read.actors:
        assert len(a.meshes) == 1 and a.meshes[0].name == "Cube" and len(a.meshes[0].faces) == 12
        assert np.allclose(a.meshes[0].colors, paints[a.path])


def test_library_paint_is_inherited_by_the_body_only(scene, layout, tmp_path):
    lib = tmp_path / "lib"
    A.write_library(lib, ("car",))
    stage = Usd.Stage.Open(str(lib / "car.usda"))
    body, cabin = (stage.GetPrimAtPath(f"/Car/{n}") for n in ("Body", "Cabin"))
    assert not UsdGeom.PrimvarsAPI(body).GetPrimvar("displayColor").HasAuthoredValue()
    assert np.allclose(_paint(stage.GetPrimAtPath("/Car")), A.SPECS["car"].paint)
    info = A.read_asset(lib / "car.usda")    # standalone: the asset's own paint
    cols = {m.name: m.colors[0] for m in info.meshes}
    assert np.allclose(cols["Body"], A.SPECS["car"].paint) and np.allclose(cols["Cabin"], A.GLASS)
    add_actors(scene, layout, parked=3, moving=0, seed=4, assets_dir=lib)
    st = scene.open_stage()
    paints = {str(p.GetPath()): _paint(p) for p in _actor_prims(st)}
    for a in ActorSet(st).actors:
        cols = {m.name: m.colors[0] for m in a.meshes}
        assert np.allclose(cols["Body"], paints[a.path])
        assert np.allclose(cols["Cabin"], A.GLASS) and np.allclose(cols["Wheels"], A.TYRE)
        # by material: the body takes the instance's paint, the other parts keep their own
        for part, want in (("Body", paints[a.path]), ("Cabin", A.GLASS), ("Wheels", A.TYRE)):
            prim = st.GetPrimAtPath(f"{a.path}/{part}")
            assert np.allclose(A.material_colour(prim)[0], want), (a.path, part)


def test_older_library_assets_are_rewritten(tmp_path):
    lib = tmp_path / "assets"
    A.write_library(lib, ("car",))
    path = lib / "car.usda"
    assert A.library_asset_current(path)
    layer = Sdf.Layer.FindOrOpen(str(path))     # as an older version wrote it
    data = dict(layer.customLayerData)
    data["lsd3d"] = {k: v for k, v in data["lsd3d"].items() if k != "assetVersion"}
    layer.customLayerData = data
    layer.Save()
    assert not A.library_asset_current(path)
    assert "car" in A.ensure_library(lib)
    assert A.library_asset_current(path) and A.ensure_library(lib) == []
