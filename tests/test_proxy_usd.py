"""Proxy layer in USD: payload per chunk, labels, ids, incremental rebuilds, CLI."""
import copy
import os

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401  (registers the schema before any stage opens)
from pxr import Usd, UsdGeom, UsdSemantics

from lsd3d_usd.proxy.chunks import build_proxy
from lsd3d_usd.proxy.mesh import merge_parts
from lsd3d_usd.proxy.synthetic import grid_layout
from lsd3d_usd.proxy.usdio import build_proxy_layer, chunks_dir, read_proxy


@pytest.fixture(scope="module")
def layout():
    return grid_layout(2, 2)


@pytest.fixture()
def built(tmp_path, layout):
    path = tmp_path / "proxy.usdc"
    rep = build_proxy_layer(layout, path)
    return path, rep


def mtimes(path):
    files = [path] + sorted(chunks_dir(path).glob("*.usdc"))
    return {f.name: os.stat(f).st_mtime_ns for f in files}


def test_chunks_are_payloads_loaded_on_demand(built):
    path, rep = built
    assert sorted(rep.built) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
    assert not [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    chunk = stage.GetPrimAtPath("/World/Proxy/Chunk_1_0")
    assert chunk.HasPayload() and not chunk.IsLoaded()
    stage.Load(chunk.GetPath())
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert meshes and all(str(p.GetPath()).startswith("/World/Proxy/Chunk_1_0/") for p in meshes)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z


def test_meshes_carry_labels_ids_and_extent(built):
    path, _ = built
    stage = Usd.Stage.Open(str(path))
    n = 0
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        n += 1
        assert prim.HasAPI(UsdSemantics.LabelsAPI, "class")
        labels = list(prim.GetAttribute("semantics:labels:class").Get())
        assert labels == [prim.GetName()]
        chunk = prim.GetParent().GetName()
        assert prim.GetAttribute("lsd3d:proxy:id").Get() == f"{chunk}/{prim.GetName()}"
        mesh = UsdGeom.Mesh(prim)
        pts = np.asarray(mesh.GetPointsAttr().Get())
        ext = np.asarray(mesh.GetExtentAttr().Get())
        np.testing.assert_allclose(ext, [pts.min(0), pts.max(0)])
        idx = np.asarray(UsdGeom.PrimvarsAPI(prim).GetPrimvar("lsd3d:partIndex").Get())
        ids = prim.GetAttribute("lsd3d:proxy:partIds").Get()
        assert len(idx) == len(mesh.GetFaceVertexCountsAttr().Get()) and idx.max() < len(ids)
    assert n >= 4 * 8


def test_read_back_matches_the_built_parts(built, layout):
    path, _ = built
    back = read_proxy(path, chunks=[(0, 1)])
    assert list(back) == [(0, 1)]
    merged = merge_parts(build_proxy(layout, chunks=[(0, 1)])[(0, 1)])
    assert set(back[(0, 1)]) == set(merged)
    for cls, cm in merged.items():
        got = back[(0, 1)][cls]
        np.testing.assert_array_equal(got.faces, cm.faces)
        np.testing.assert_allclose(got.vertices, cm.vertices, atol=1e-4)   # float32 points
        assert got.part_ids == cm.part_ids


def test_unchanged_inputs_rewrite_nothing(built, layout):
    path, _ = built
    before = mtimes(path)
    rep = build_proxy_layer(copy.deepcopy(layout), path)
    assert rep.built == [] and len(rep.skipped) == 4 and not rep.root_written
    assert mtimes(path) == before


def test_changed_building_rebuilds_only_its_chunk(built, layout):
    path, _ = built
    before = mtimes(path)
    changed = copy.deepcopy(layout)

    def inner(b):       # farther than the 12 m margin from every chunk border
        lo, hi = b.footprint[:, :2].min(0) % 100, b.footprint[:, :2].max(0) % 100
        return (lo > 13).all() and (hi < 87).all() and (b.footprint[:, :2].max(0) // 100 ==
                                                        b.footprint[:, :2].min(0) // 100).all()
    bd = next(b for b in changed.buildings if inner(b))
    key = tuple(int(v) for v in bd.footprint[0, :2] // 100)
    bd.height_hint += 4.0
    rep = build_proxy_layer(changed, path)
    assert rep.built == [key] and rep.root_written
    after = mtimes(path)
    assert [k for k in before if before[k] != after[k]] == ["proxy.usdc", f"chunk_{key[0]}_{key[1]}.usdc"]
    top = read_proxy(path, chunks=[key])[key]["building"]
    i = top.part_ids.index(bd.id)
    assert top.vertices[top.faces[top.face_part == i]][..., 2].max() >= bd.height_hint


def test_chunk_subset_builds_only_what_is_asked(tmp_path, layout):
    path = tmp_path / "p.usdc"
    rep = build_proxy_layer(layout, path, chunks=[(1, 1)])
    assert rep.built == [(1, 1)]
    assert [f.name for f in chunks_dir(path).iterdir()] == ["chunk_1_1.usdc"]
    rep = build_proxy_layer(layout, path, chunks=[(0, 0)])
    assert rep.built == [(0, 0)]
    assert sorted(read_proxy(path)) == [(0, 0), (1, 1)]     # earlier chunks stay listed


def test_proxy_layer_passes_validate(built):
    from lsd3d_usd import validation
    path, _ = built
    problems = validation.validate(str(path))
    assert [p for p in problems if p.severity == "error"] == []


def test_cli_build_and_errors(tmp_path, layout, capsys):
    from lsd3d_usd.cli import main
    from lsd3d_usd.layout.usdio import write_layout

    lp = tmp_path / "layout.usda"
    write_layout(layout, lp)
    out = tmp_path / "proxy.usdc"
    assert main(["proxy", "build", "--layout", str(lp), "-o", str(out), "--chunk", "0,1"]) == 0
    assert "built 1 chunk" in capsys.readouterr().out
    assert sorted(read_proxy(out)) == [(0, 1)]
    assert main(["proxy", "build", "--layout", str(lp), "-o", str(out), "--chunk", "5,5"]) == 1
    err = capsys.readouterr().err
    assert "--chunk 5,5" in err and "outside" in err and len(err.strip().splitlines()) == 1
    assert main(["proxy", "build", "--layout", str(tmp_path / "missing.usda"), "-o", str(out)]) == 1
    assert "missing.usda" in capsys.readouterr().err
    assert main(["proxy", "build", "--layout", str(lp), "-o", str(tmp_path / "p.obj")]) == 1
    with pytest.raises(SystemExit):
        main(["proxy", "build", "--layout", str(lp), "-o", str(out), "--chunk", "a,b"])
    png = tmp_path / "top.png"
    assert main(["proxy", "preview", str(out), "-o", str(png), "--view", "top", "--size", "200x150"]) == 0
    import imageio.v3 as iio
    img = iio.imread(png)
    assert img.shape == (150, 200, 3) and img.std() > 5       # something was drawn
