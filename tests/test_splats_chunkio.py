"""Surfels per chunk as payloads: every surfel in exactly one chunk, nothing read until a
chunk is loaded, run overs that compose over (and mute back to) the initial surfels."""
import numpy as np
import pytest
from pxr import Sdf, Usd

from conftest import random_field
from lsd3d_usd import scene as S
from lsd3d_usd.splats import chunkio


def test_split_by_chunk_puts_every_surfel_in_the_chunk_holding_it():
    rng = np.random.default_rng(0)
    pos = rng.uniform(-250, 250, (5000, 3))
    pos[:10, 0] = [-100, 0, 100, -1e-9, 99.999999, 200, -200, 0, 0, 0]   # on and near borders
    parts = chunkio.split_by_chunk(pos, 100.0)
    idx = np.concatenate(list(parts.values()))
    assert np.array_equal(np.sort(idx), np.arange(len(pos)))            # once each
    for (i, j), ii in parts.items():                                     # float64 reference
        x, y = pos[ii, 0], pos[ii, 1]
        assert np.all((i * 100.0 <= x) & (x < (i + 1) * 100.0))
        assert np.all((j * 100.0 <= y) & (y < (j + 1) * 100.0))
    assert chunkio.split_by_chunk(np.zeros((0, 3)), 100.0) == {}


def _chunked_scene(tmp_path):
    """A scene folder with two surfel chunks and a root layer listing them."""
    sc = S.Scene.create(tmp_path / "s")
    root = sc.layer_path("surfels")
    folder = chunkio.chunks_base(root) / "v1"
    f = random_field(400, seed=1)
    f.positions[:, 0] = np.abs(f.positions[:, 0]) % 200.0            # x in [0, 200): chunks 0, 1
    f.positions[:, 1] = np.abs(f.positions[:, 1]) % 100.0
    infos = {}
    for key, idx in chunkio.split_by_chunk(f.positions, 100.0).items():
        part = f.subset(idx)
        chunkio.write_chunk(folder, key, part)
        infos[key] = chunkio.chunk_info(key, part)
    chunkio.write_root(root, folder, infos, {"inputsHash": "v1"})
    sc.add_layer("surfels")
    return sc, f, infos


def test_load_none_reads_no_surfel_file_and_one_chunk_reads_one(tmp_path):
    sc, f, infos = _chunked_scene(tmp_path)
    assert sorted(infos) == [(0, 0), (1, 0)]
    files = [str(chunkio.chunk_folder(sc.layer_path("surfels")) / chunkio.chunk_file_name(k))
             for k in sorted(infos)]
    stage = Usd.Stage.Open(str(sc.root_layer_path), Usd.Stage.LoadNone)
    used = {layer.realPath for layer in stage.GetUsedLayers()}
    assert not any(fp in used for fp in files)
    prim = stage.GetPrimAtPath(f"{S.SURFELS_PATH}/Chunk_1_0")
    assert prim.GetTypeName() == "Lsd3dSurfelField" and not prim.IsLoaded()
    stage.Load(prim.GetPath())
    used = {layer.realPath for layer in stage.GetUsedLayers()}
    assert files[1] in used and files[0] not in used
    from lsd3d_usd.splats.usdio import read_surfels
    got = read_surfels(prim)
    assert got.n == infos[(1, 0)]["count"] and np.all(got.positions[:, 0] >= 100.0)
    assert chunkio.read_chunk_map(sc.layer_path("surfels")) == {
        k: {**v, "inputsHash": ""} for k, v in infos.items()}


def test_run_overs_compose_and_mute_back(tmp_path):
    sc, f, infos = _chunked_scene(tmp_path)
    run_root = sc.layer_path("ggds_20260101-000000.usdc")
    folder = chunkio.chunks_base(run_root)
    base = chunkio.read_chunk(sc.layer_path("surfels"), (0, 0))
    moved = base.subset(np.arange(base.n))
    moved.positions = moved.positions + np.float32(0.5)
    chunkio.write_run_chunk(folder, (0, 0), moved, ("positions", "orientations", "scales",
                                                    "opacities", "sh"))
    chunkio.write_root(run_root, folder, {(0, 0): {}}, define=False)
    layer = Sdf.Layer.FindOrOpen(str(run_root))
    assert all(layer.GetPrimAtPath(p).specifier == Sdf.SpecifierOver
               for p in ("/World", S.SURFELS_PATH, f"{S.SURFELS_PATH}/Chunk_0_0"))
    sc.add_layer(run_root.name)
    from lsd3d_usd.splats.usdio import read_surfels
    stage = Usd.Stage.Open(str(sc.root_layer_path))
    p00 = read_surfels(stage.GetPrimAtPath(f"{S.SURFELS_PATH}/Chunk_0_0")).positions
    p10 = read_surfels(stage.GetPrimAtPath(f"{S.SURFELS_PATH}/Chunk_1_0")).positions
    np.testing.assert_allclose(p00, base.positions + 0.5)                   # the run wins
    np.testing.assert_array_equal(p10, chunkio.read_chunk(sc.layer_path("surfels"), (1, 0)).positions)
    np.testing.assert_allclose(chunkio.read_chunk(sc.layer_path("surfels"), (0, 0), [run_root])
                               .positions, base.positions + 0.5)
    sc.mute(run_root.stem)                                                  # reverts every chunk
    stage = Usd.Stage.Open(str(sc.root_layer_path))
    np.testing.assert_array_equal(
        read_surfels(stage.GetPrimAtPath(f"{S.SURFELS_PATH}/Chunk_0_0")).positions, base.positions)


def test_new_version_replaces_the_folder_only_after_the_root(tmp_path):
    sc, f, infos = _chunked_scene(tmp_path)
    root = sc.layer_path("surfels")
    old = chunkio.chunk_folder(root)
    folder = chunkio.chunks_base(root) / "v2"
    chunkio.write_chunk(folder, (0, 0), f.subset(np.arange(3)))
    assert chunkio.chunk_folder(root) == old             # the root still points at v1
    chunkio.write_root(root, folder, {(0, 0): {}})
    chunkio.prune_chunk_folders(root)
    assert chunkio.chunk_folder(root) == folder.resolve() and not old.exists()


def test_chunk_folder_outside_the_layer_folder_is_refused(tmp_path):
    sc, f, infos = _chunked_scene(tmp_path)
    root = sc.layer_path("surfels")
    layer = Sdf.Layer.FindOrOpen(str(root))
    S.save_layer(layer, root, {"chunkFolder": "../../elsewhere"})
    from lsd3d_usd.errors import InputError
    with pytest.raises(InputError, match="lies outside"):
        chunkio.chunk_folder(root)
