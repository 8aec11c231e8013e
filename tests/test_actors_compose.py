"""Actor assets and the actors layer: composition by reference, validation, time samples."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from pxr import Sdf, Usd, UsdGeom, UsdSemantics

from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors.compose import add_actors
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import ACTORS_PATH, Scene


@pytest.fixture(scope="module")
def layout():
    from lsd3d_usd.layout.generator import generate
    return generate(3, (200.0, 200.0))


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return A.write_library(tmp_path_factory.mktemp("lib"))


@pytest.fixture()
def scene(tmp_path, layout):
    from lsd3d_usd.layout.usdio import layout_to_stage
    sc = Scene.create(tmp_path / "scene")
    sc.write_layer("layout", layout_to_stage(layout))
    return sc


def test_library_asset_conventions(library):
    for kind, path in library.items():
        stage = Usd.Stage.Open(str(path))
        root = stage.GetDefaultPrim()
        assert root and root.GetName() == kind.capitalize()
        assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
        labels = UsdSemantics.LabelsAPI(root, "class").GetLabelsAttr().Get()
        assert list(labels) == ["vehicle"]
        hint = np.array(UsdGeom.ModelAPI(root).GetExtentsHint())
        info = A.read_asset(path)
        # extent matches the geometry, ground at z = 0, length along +X
        v = np.concatenate([m.vertices for m in info.meshes])
        assert np.allclose(hint[0], v.min(0), atol=1e-5) and np.allclose(hint[1], v.max(0), atol=1e-5)
        assert abs(v[:, 2].min()) < 1e-6
        assert info.dimensions[0] > info.dimensions[1]
    dims = {k: A.read_asset(p).dimensions[0] for k, p in library.items()}
    assert dims["car"] < dims["van"] < dims["truck"] < dims["bus"]


def test_check_asset_errors(tmp_path):
    with pytest.raises(InputError, match="nope.usda: no such file"):
        A.check_asset(tmp_path / "nope.usda")
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\ndef Xform \"A\" {\n")
    with pytest.raises(InputError, match="bad.usda"):
        A.check_asset(bad)
    nodef = tmp_path / "nodef.usda"
    nodef.write_text("#usda 1.0\ndef Xform \"A\" {}\n")
    with pytest.raises(InputError, match="no defaultPrim"):
        A.check_asset(nodef)


def test_reference_composition_and_mute(scene, layout, library):
    lib_dir = next(iter(library.values())).parent
    res = add_actors(scene, layout, parked=5, moving=4, seed=1, seconds=2.0, fps=5.0, assets_dir=lib_dir)
    stage = scene.open_stage()
    actors = [p for p in Usd.PrimRange(stage.GetPrimAtPath(ACTORS_PATH))
              if p.HasAttribute("lsd3d:actor:role")]
    assert len(actors) == len(res.parked) + res.run.n >= 8
    # every actor is a reference to a library file, and its meshes compose through it
    for p in actors:
        refs = [r for spec in p.GetPrimStack() for r in spec.referenceList.prependedItems]
        assert len(refs) == 1 and not Sdf.Layer.IsAnonymousLayerIdentifier(refs[0].assetPath)
        assert refs[0].assetPath.startswith("../")            # relative to layers/actors.usda
        assert any(c.IsA(UsdGeom.Mesh) for c in p.GetChildren())
    # the asset files are not copied into the scene folder
    names = {p.name for p in library.values()}
    assert not [f for f in scene.root.rglob("*") if f.name in names]
    # muting the actors layer removes every actor; unmuting brings them back
    scene.mute("actors")
    st = scene.open_stage()
    assert not st.GetPrimAtPath(ACTORS_PATH)
    assert not [p for p in st.Traverse() if p.HasAttribute("lsd3d:actor:role")]
    scene.unmute("actors")
    st2 = scene.open_stage()
    assert len([p for p in st2.Traverse() if p.HasAttribute("lsd3d:actor:role")]) == len(actors)


def test_time_samples_match_simulation(scene, layout, library):
    lib_dir = next(iter(library.values())).parent
    res = add_actors(scene, layout, parked=0, moving=3, seed=4, seconds=3.0, fps=10.0, assets_dir=lib_dir)
    stage = scene.open_stage()
    tcps = stage.GetTimeCodesPerSecond()
    assert tcps == res.tcps and stage.GetEndTimeCode() >= 3.0 * tcps
    moving = [p for p in Usd.PrimRange(stage.GetPrimAtPath(ACTORS_PATH + "/Moving"))
              if p.HasAttribute("lsd3d:actor:role")]
    assert len(moving) == res.run.n == 3
    for i, prim in enumerate(moving):
        xf = UsdGeom.Xformable(prim)
        for k in (0, 7, 30):
            t = res.run.t[k]
            M = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode(t * tcps))).T
            assert np.allclose(M[:3, 3], res.run.position[i, k], atol=1e-6)
            assert np.isclose(np.arctan2(M[1, 0], M[0, 0]),
                              np.arctan2(np.sin(res.run.yaw[i, k]), np.cos(res.run.yaw[i, k])), atol=1e-5)
        # between samples USD interpolates linearly
        t = 0.5 * (res.run.t[3] + res.run.t[4])
        M = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode(t * tcps))).T
        assert np.allclose(M[:3, 3], 0.5 * (res.run.position[i, 3] + res.run.position[i, 4]), atol=1e-6)


def test_deterministic_per_seed(tmp_path, layout, library):
    from lsd3d_usd.layout.usdio import layout_to_stage
    lib_dir = next(iter(library.values())).parent
    texts = []
    for name in ("a", "b"):
        sc = Scene.create(tmp_path / name)
        sc.write_layer("layout", layout_to_stage(layout))
        add_actors(sc, layout, parked=6, moving=4, seed=9, seconds=2.0, fps=5.0, assets_dir=lib_dir)
        layer = Sdf.Layer.FindOrOpen(str(sc.layer_path("actors")))
        layer.customLayerData = {}
        texts.append(layer.ExportToString())
    assert texts[0] == texts[1]


def test_parked_do_not_overlap(layout, library):
    from lsd3d_usd.actors.placement import footprint, parked_placements
    dims = {k: tuple(A.read_asset(p).dimensions) for k, p in library.items()}
    places = parked_placements(layout, 40, 0, dims)
    assert len(places) >= 10
    fps_ = [footprint(p.position, p.yaw, dims[p.kind][0], dims[p.kind][1]) for p in places]
    for i in range(len(fps_)):
        for j in range(i + 1, len(fps_)):
            assert not fps_[i].intersects(fps_[j])
    occupied = [footprint(s.center, s.heading, 4.5, 1.8) for s in layout.parking_spots if s.occupied]
    assert not any(f.intersects(o) for f in fps_ for o in occupied)


def test_missing_asset_is_named(scene, layout, library, tmp_path):
    import shutil
    lib = tmp_path / "lib2"
    shutil.copytree(next(iter(library.values())).parent, lib)
    add_actors(scene, layout, parked=2, moving=0, seed=0, assets_dir=lib)
    (lib / "car.usda").unlink()
    (lib / "van.usda").unlink()
    from lsd3d_usd.actors.usdio import ActorSet
    with pytest.raises(InputError, match=r"references missing asset '\.\./.*lib2/(car|van)\.usda'"):
        ActorSet(scene.open_stage())


def test_cli_actors_add(scene, library, capsys):
    from lsd3d_usd.cli import main
    lib_dir = next(iter(library.values())).parent
    assert main(["actors", "add", str(scene.root), "--parked", "3", "--moving", "2", "--seconds", "1",
                 "--assets", str(lib_dir)]) == 0
    assert "3 parked, 2 moving" in capsys.readouterr().out
    assert main(["actors", "add", str(scene.root), "--assets", str(scene.root / "nothing")]) == 1
    assert "nothing: no such folder" in capsys.readouterr().err


def test_parked_shortfall_says_why(tmp_path, layout, library):
    """A layout without any parking says so; one whose slots run out says how many there are."""
    from lsd3d_usd.actors.placement import parking_slots
    from lsd3d_usd.layout.usdio import layout_to_stage, read_layout
    lib_dir = next(iter(library.values())).parent
    crossing = read_layout(Path(__file__).resolve().parents[1] / "samples/layouts/hand_crossing.usda")
    assert parking_slots(crossing) == []
    sc = Scene.create(tmp_path / "a")
    sc.write_layer("layout", layout_to_stage(crossing))
    res = add_actors(sc, crossing, parked=12, moving=0, seed=0, assets_dir=lib_dir)
    assert res.parked == [] and res.notes == [
        "no parked actors: the layout has no parking (no free parking spot, no lane of type parking)"]
    n_slots = len(parking_slots(layout))
    assert n_slots > 0
    sc = Scene.create(tmp_path / "b")
    sc.write_layer("layout", layout_to_stage(layout))
    res = add_actors(sc, layout, parked=n_slots + 5, moving=0, seed=0, assets_dir=lib_dir)
    assert res.notes == [f"only {len(res.parked)} of {n_slots + 5} parked actors fit in the layout's "
                         f"{n_slots} free parking slots"]


def test_default_library_is_the_scenes_own(scene, layout):
    """Without --assets the actors reference SCENE/assets (written there): the scene folder
    is self-contained, whether or not it sits next to a source checkout."""
    from lsd3d_usd.cli import main
    assert main(["actors", "add", str(scene.root), "--parked", "2", "--moving", "1", "--seconds", "1"]) == 0
    stage = scene.open_stage()
    refs = [r.assetPath for p in stage.Traverse() if p.GetParent().GetName() in ("Parked", "Moving")
            for r in p.GetPrimStack()[0].referenceList.prependedItems]
    assert refs and all(r.startswith("../assets/") for r in refs)
    assert all((scene.root / "layers" / r).resolve().is_file() for r in refs)
