"""Reading a composed stage into arrays (views.stage_data), proxy_arrays, and the one
"concatenate surfel fields" rule."""
import os

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom

import lsd3d_usd  # noqa: F401
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.semantics import CLASSES
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.splats.ply import write_gaussian_splat_prim
from lsd3d_usd.splats.usdio import write_surfels
from lsd3d_usd.views.stage_data import SceneReader, TextureCache, read_dome, scene_surfels


def _field(n, x0, classes=CLASSES, seed=0):
    rng = np.random.default_rng(seed)
    pos = np.stack([np.full(n, x0), rng.uniform(-1, 1, n), rng.uniform(0, 2, n)], 1).astype(np.float32)
    return SurfelField(pos, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)).astype(np.float32),
                       np.full((n, 2), 0.1, np.float32), np.full(n, 0.9, np.float32),
                       np.zeros((n, 1, 3), np.float32),
                       np.zeros(n, np.int32) if classes else None, classes)


def test_concat_drops_semantics_only_when_tables_differ():
    a, b = _field(3, 0.0), _field(2, 1.0, classes=("road", "other"))
    with pytest.raises(ValueError, match="different semantic class tables"):
        SurfelField.concat([a, b])
    c = SurfelField.concat([a, b], drop_mismatched_semantics=True)
    assert c.n == 5 and c.semantic_ids is None and c.semantic_classes == ()
    d = SurfelField.concat([a, _field(2, 1.0, classes=())], drop_mismatched_semantics=True)
    assert d.semantic_classes == CLASSES and list(d.semantic_ids) == [0, 0, 0, -1, -1]


def test_scene_surfels_reads_every_prim_type_in_world_space_without_actors():
    stage = S.new_stage()
    write_surfels(stage, "/World/Surfels/Chunk_0_0", _field(10, 5.0))
    xf = UsdGeom.Xform.Define(stage, "/World/Moved")
    xf.AddTranslateOp().Set(Gf.Vec3d(0.0, 100.0, 0.0))
    write_gaussian_splat_prim(stage, "/World/Moved/Splats", _field(4, 7.0, classes=()))
    write_surfels(stage, "/World/Hidden", _field(6, 9.0))
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/Hidden")).MakeInvisible()
    write_surfels(stage, f"{S.ACTORS_PATH}/Parked/Car_000/Surfels", _field(8, 3.0))
    f = scene_surfels(stage)
    assert f.n == 14                                   # chunk + 3DGS; not hidden, not the actor
    assert np.allclose(np.sort(np.unique(np.round(f.positions[:, 0]))), [5.0, 7.0])
    assert (f.positions[f.positions[:, 0] > 6, 1] > 98).all()   # the parent's transform applied
    assert f.semantic_classes == CLASSES               # one table (the 3DGS prim has none)
    assert scene_surfels(S.new_stage()) is None


def test_reader_caches_static_surfels_and_follows_animated_ones():
    stage = S.new_stage()
    write_surfels(stage, "/World/Surfels", _field(5, 1.0))
    r = SceneReader(stage, actors=False)
    assert r.surfels(0.0) is r.surfels(10.0)           # read once: nothing animated
    xf = UsdGeom.Xform.Define(stage, "/World/Anim")
    op = xf.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 0.0)
    op.Set(Gf.Vec3d(0, 10, 0), 10.0)
    write_surfels(stage, "/World/Anim/Surfels", _field(5, 2.0))
    r = SceneReader(stage, actors=False)
    a, b = r.surfels(0.0), r.surfels(10.0)
    moved = a.positions[:, 0] > 1.5
    assert np.allclose(b.positions[moved, 1] - a.positions[moved, 1], 10.0)
    assert np.array_equal(a.positions[~moved], b.positions[~moved])
    assert np.allclose(r.surfels(None).positions, a.positions)   # None = the earliest time


def _write_exr(path, value):
    import OpenImageIO as oiio
    img = np.full((4, 8, 3), value, np.float32)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(8, 4, 3, "float"))
    out.write_image(img)
    out.close()


def test_texture_cache_decodes_once_and_sees_file_changes(tmp_path, monkeypatch):
    from lsd3d_usd.views import stage_data
    exr = tmp_path / "sky.exr"
    _write_exr(exr, 0.5)
    stage = S.new_stage()
    from pxr import UsdLux
    dome = UsdLux.DomeLight.Define(stage, "/World/Env/Sky")
    dome.GetTextureFileAttr().Set(Sdf.AssetPath(str(exr)))
    reads = []
    real = stage_data.read_image
    monkeypatch.setattr(stage_data, "read_image", lambda p: reads.append(p) or real(p))
    cache = TextureCache()
    a, b = read_dome(stage, None, cache), read_dome(stage, None, cache)
    assert len(reads) == 1 and np.allclose(a.image, 0.5) and np.allclose(b.image, 0.5)
    _write_exr(exr, 2.0)
    os.utime(exr, (1e9, 1e9))                          # a different modification time
    assert np.allclose(read_dome(stage, None, cache).image, 2.0) and len(reads) == 2
    read_dome(stage, None)                              # no cache given: a private one
    assert len(reads) == 3


def test_proxy_arrays_concatenates_chunks_and_classes_in_order(tmp_path):
    from lsd3d_usd.proxy.mesh import MeshPart
    from lsd3d_usd.proxy.usdio import proxy_arrays, write_proxy
    from lsd3d_usd.semantics import CLASS_ID

    def quad(x, cls, pid):
        v = np.array([[x, 0, 0], [x + 1, 0, 0], [x + 1, 1, 0], [x, 1, 0]], np.float64)
        return MeshPart(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), cls, pid)

    path = write_proxy({(1, 0): [quad(100.0, "road", "r1")],
                        (0, 0): [quad(0.0, "sidewalk", "s0"), quad(2.0, "road", "r0")]},
                       tmp_path / "proxy.usdc")
    V, F, ids = proxy_arrays(path)
    assert F.dtype == np.int64 and F.max() == len(V) - 1
    # chunk (0,0) first, its classes sorted (road, sidewalk); then chunk (1,0)
    assert list(ids) == [CLASS_ID["road"]] * 2 + [CLASS_ID["sidewalk"]] * 2 + [CLASS_ID["road"]] * 2
    assert V[F[0], 0].min() == 2.0 and V[F[-1], 0].min() == 100.0
    empty = S.new_stage()
    UsdGeom.Xform.Define(empty, S.PROXY_PATH)
    S.save_stage(empty, tmp_path / "empty.usda")
    with pytest.raises(InputError, match="empty.usda: the proxy has no geometry"):
        proxy_arrays(tmp_path / "empty.usda")


def test_reader_level_of_detail_cuts_static_surfels_and_draws_animated_ones_in_full():
    from lsd3d_usd.render.camera import Camera, look_at
    stage = S.new_stage()
    write_surfels(stage, "/World/Surfels", _field(400, 1.0))
    write_surfels(stage, "/World/Behind", _field(300, -30.0, seed=1))
    cam = Camera.from_fov(64, 48, 60.0, look_at([-10.0, 0.0, 1.0], [1.0, 0.0, 1.0]), near=0.1,
                          far=100.0)
    full = SceneReader(stage, actors=False).surfels_seen(cam)
    r = SceneReader(stage, actors=False, lod_px=4.0)
    cut = r.surfels_seen(cam)
    assert full.n == 700 and 0 < cut.n <= 400          # the wall at x = -30 is behind it
    assert r.surfels_seen(cam).n == cut.n and r._tree[1] is not None   # one tree, kept
    assert r.surfels(None).n == 700                    # the reader's field: the same surfels
    xf = UsdGeom.Xform.Define(stage, "/World/Anim")
    op = xf.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 0.0)
    op.Set(Gf.Vec3d(0, 10, 0), 10.0)
    write_surfels(stage, "/World/Anim/Surfels", _field(5, 2.0))
    r = SceneReader(stage, actors=False, lod_px=4.0)
    assert r.surfels_seen(cam, 0.0).n == 705           # animated: no tree per frame


def test_streaming_reader_cuts_chunks_read_before_level_of_detail_was_asked_for():
    from lsd3d_usd.render.camera import Camera, look_at
    from lsd3d_usd.views.stage_data import ChunkStreamer
    stage = S.new_stage()
    write_surfels(stage, f"{S.SURFELS_PATH}/Chunk_0_0", _field(400, 1.0))
    stage.GetPrimAtPath(S.WORLD).CreateAttribute("lsd3d:scene:chunkSize",
                                                 Sdf.ValueTypeNames.Double).Set(100.0)
    r = SceneReader(stage, actors=False)
    r.stream = ChunkStreamer(stage, 300.0)
    cam = Camera.from_fov(64, 48, 60.0, look_at([-10.0, 0.0, 1.0], [1.0, 0.0, 1.0]), near=0.1,
                          far=100.0)
    assert r.surfels_seen(cam).n == 400                # full detail: every loaded surfel
    r.lod_px = 4.0                                     # asked for later: the chunk gets a tree
    cut = r.surfels_seen(cam)
    assert cut is not None and 0 < cut.n <= 400 and len(r.stream.trees()) == 1
