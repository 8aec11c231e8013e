"""Scene folder conventions: layer stack order, persistent muting, atomic writes, provenance."""
import os

import pytest
from pxr import Sdf, Usd, UsdGeom

from lsd3d_usd import scene
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import Scene


def _layer_with(prim_name):
    st = scene.new_stage()
    st.DefinePrim(f"/World/{prim_name}", "Xform")
    return st


def test_new_stage_conventions():
    st = scene.new_stage()
    assert UsdGeom.GetStageUpAxis(st) == "Z"
    assert UsdGeom.GetStageMetersPerUnit(st) == 1.0
    assert st.GetDefaultPrim().GetPath() == "/World"


def test_chunk_names_round_trip():
    for ij in [(0, 0), (3, 12), (-1, 0), (-7, -20)]:
        name = scene.chunk_prim_name(*ij)
        assert Sdf.Path.IsValidIdentifier(name)
        assert scene.parse_chunk_prim_name(name) == ij
    assert scene.chunk_prim_name(-1, 2) == "Chunk_m1_2"


def test_stack_order_strongest_first(tmp_path):
    sc = Scene.create(tmp_path / "s", seed=5)
    for name in ("surfels", "layout", "env", "proxy", "actors", "cameras"):
        sc.write_layer(name, _layer_with(name))
    sc.write_layer("ggds_20260101-000000.usdc", _layer_with("g1"))
    sc.write_layer("ggds_20260102-000000.usdc", _layer_with("g2"))
    root = Sdf.Layer.FindOrOpen(str(sc.root_layer_path))
    assert [p.split("/")[-1] for p in root.subLayerPaths] == [
        "ggds_20260102-000000.usdc", "ggds_20260101-000000.usdc", "surfels.usdc",
        "cameras.usda", "actors.usda", "env.usda", "proxy.usdc", "layout.usda"]
    stage = sc.open_stage()
    assert stage.GetPrimAtPath("/World/g1") and stage.GetPrimAtPath("/World/layout")
    assert stage.GetPrimAtPath("/World").HasAPI("Lsd3dSceneAPI")
    assert stage.GetPrimAtPath("/World").GetAttribute("lsd3d:scene:seed").Get() == 5


def test_mute_is_persistent_and_visible_to_plain_usd(tmp_path):
    sc = Scene.create(tmp_path / "s")
    sc.write_layer("surfels", _layer_with("base"))
    sc.write_layer("ggds_20260101-000000.usdc", _layer_with("run"))
    sc.mute("ggds_20260101-000000")
    # A plain USD open (as usdview would) no longer sees the run.
    plain = Usd.Stage.Open(str(sc.root_layer_path))
    assert not plain.GetPrimAtPath("/World/run") and plain.GetPrimAtPath("/World/base")
    infos = {i.name: i for i in Scene.open(sc.root).layers()}
    assert infos["ggds_20260101-000000"].muted
    sc.unmute("ggds_20260101-000000")
    assert Usd.Stage.Open(str(sc.root_layer_path), Usd.Stage.LoadAll).GetPrimAtPath("/World/run")
    sc.remove_layer("ggds_20260101-000000", delete_file=True)
    assert not (sc.root / "layers" / "ggds_20260101-000000.usdc").exists()
    with pytest.raises(InputError, match="no layer 'nope'"):
        sc.mute("nope")


def test_atomic_write_keeps_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "layer.usda"
    scene.save_stage(_layer_with("old"), path)
    before = path.read_bytes()
    st = _layer_with("new")
    monkeypatch.setattr(Sdf.Layer, "Export", lambda self, p, *a, **k: open(p, "w").write("partial") and False)
    with pytest.raises(OSError):
        scene.save_stage(st, path)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["layer.usda"]  # no temp file left


def test_overwrite_reloads_open_layer(tmp_path):
    path = tmp_path / "l.usda"
    scene.save_stage(_layer_with("a"), path)
    opened = Usd.Stage.Open(str(path))
    scene.save_stage(_layer_with("b"), path)
    assert opened.GetPrimAtPath("/World/b")


def test_provenance_round_trip(tmp_path):
    prov = scene.provenance("proxy", {"chunks": [[0, 0], [0, 1]], "size": 100, "names": ["a", "b"],
                                      "skip": None}, seed=3, timings={"build_s": 1.5})
    path = scene.save_stage(scene.new_stage(), tmp_path / "p.usdc", prov)
    got = scene.read_provenance(Sdf.Layer.FindOrOpen(str(path)))
    assert got["step"] == "proxy" and got["seed"] == 3 and got["tool"] == "lsd3d-usd"
    assert got["params"]["size"] == 100 and list(got["params"]["names"]) == ["a", "b"]
    assert "skip" not in got["params"]
    assert got["timings"]["build_s"] == 1.5


def test_create_refuses_existing_scene(tmp_path):
    Scene.create(tmp_path / "s")
    with pytest.raises(InputError, match="already holds a scene"):
        Scene.create(tmp_path / "s")
    with pytest.raises(InputError, match="not an lsd3d-usd scene"):
        Scene.open(tmp_path)


def test_layer_names_are_checked(tmp_path):
    sc = Scene.create(tmp_path / "s")
    with pytest.raises(InputError, match="unknown scene layer"):
        sc.layer_path("../../etc/passwd")
    assert sc.new_run_name().startswith("ggds_")


def test_open_takes_the_folder_or_its_root_layer(tmp_path):
    sc = Scene.create(tmp_path / "s")
    assert Scene.open(tmp_path / "s" / "scene.usda").root == sc.root == Scene.open(tmp_path / "s").root
    other = tmp_path / "s" / "layers" / "x.usda"
    other.write_text("#usda 1.0\n")
    with pytest.raises(InputError, match="not an lsd3d-usd scene .give the scene folder or its scene.usda"):
        Scene.open(other)
