"""Surfels validated once when the scene reader loads them (SurfelField.checked) are not
scanned value by value again per frame; every other caller's bad value is still one InputError."""
from dataclasses import replace

import numpy as np
import pytest
from pxr import Vt

import lsd3d_usd  # noqa: F401
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.render import checks
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.splats.lod import build_lod, gather_cuts
from lsd3d_usd.splats.usdio import SH_COEFFS_ATTR, write_surfels
from lsd3d_usd.views.frame import render_surfels
from lsd3d_usd.views.stage_data import SceneReader, scene_surfels


def _field(n=300, seed=0):
    rng = np.random.default_rng(seed)
    pos = np.stack([rng.uniform(-2, 2, n), np.full(n, 5.0), rng.uniform(0, 2, n)], 1)
    return SurfelField(pos.astype(np.float32), np.tile([0.7071, 0, 0, 0.7071], (n, 1)).astype(np.float32),
                       np.full((n, 2), 0.08, np.float32), np.full(n, 0.9, np.float32),
                       rng.normal(0, 0.3, (n, 4, 3)).astype(np.float32))


def _camera():
    return Camera.from_fov(48, 32, 60.0, look_at([0.0, -3.0, 1.0], [0.0, 5.0, 1.0]), near=0.1,
                           far=100.0)


def _stage(field):
    stage = S.new_stage()
    write_surfels(stage, f"{S.SURFELS_PATH}/Chunk_0_0", field)
    return stage


def test_reader_refuses_at_load_an_sh_value_the_rasteriser_refuses():
    stage = _stage(_field())
    attr = stage.GetPrimAtPath(f"{S.SURFELS_PATH}/Chunk_0_0").GetAttribute(SH_COEFFS_ATTR)
    sh = np.array(attr.Get(), np.float32).reshape(300, -1)
    sh[7, 2] = 3e7                   # finite, so validate's problems() let it through
    attr.Set(Vt.Vec3fArray.FromNumpy(sh.reshape(-1, 3)))
    with pytest.raises(InputError, match=r"Chunk_0_0\.sh: an SH coefficient .* at particle 7"):
        scene_surfels(stage)
    sh[7, 2] = np.nan
    attr.Set(Vt.Vec3fArray.FromNumpy(sh.reshape(-1, 3)))
    with pytest.raises(InputError, match=r"\.sh: .* at particle 7 \(1 bad of 300\)"):
        scene_surfels(stage)


def test_fields_the_reader_validated_are_drawn_without_a_scan_and_alike(monkeypatch):
    stage = _stage(_field())
    cam = _camera()
    full = scene_surfels(stage)
    cut = SceneReader(stage, actors=False, lod_px=4.0).surfels_seen(cam)
    assert full.checked and cut.checked                # the leaves, and the LOD nodes too
    unchecked = SurfelField(full.positions, full.orientations, full.scales, full.opacities,
                            full.sh, full.semantic_ids, full.semantic_classes)
    assert not unchecked.checked
    want = render_surfels(unchecked, cam)              # scanned: the reference image
    calls = []
    real = checks.first_bad_array
    monkeypatch.setattr(checks, "first_bad_array", lambda *a: calls.append(1) or real(*a))
    got = render_surfels(full, cam)
    assert calls == []                                 # no per-value scan of checked surfels
    assert np.array_equal(got.rgb.numpy(), want.rgb.numpy())
    assert np.array_equal(got.depth_median.numpy(), want.depth_median.numpy())
    render_surfels(unchecked, cam)
    assert calls == [1]                                # anything else is still scanned


def test_untrusted_callers_still_get_one_input_error():
    f = _field()
    f.sh[11, 1, 0] = np.nan
    cam = _camera()
    with pytest.raises(InputError, match=r"rasterize: sh has a non-finite value .* at index 11"):
        render_surfels(f, cam)                          # a field made by hand: unchecked
    with pytest.raises(InputError, match=r"rasterize: sh has a non-finite value .* at index 11"):
        rasterize(f.positions, f.orientations, f.scales, f.opacities, f.sh, cam.viewmat, cam.K,
                  cam.width, cam.height)
    ok = scene_surfels(_stage(_field()))
    assert ok.checked
    bad = replace(ok, sh=f.sh)                          # new values: no longer checked
    assert not bad.checked
    with pytest.raises(InputError, match="at index 11"):
        render_surfels(bad, cam)


def test_checked_is_kept_only_by_copies_of_checked_rows():
    ok = scene_surfels(_stage(_field()))
    made = _field(5, seed=1)
    assert ok.rows(2, 9).checked and ok.subset(np.array([4, 1])).checked
    assert SurfelField.concat([ok, ok.with_sh_degree(0).rows(0, 3)]).checked is False  # replace()d
    assert SurfelField.concat([ok, ok.rows(0, 3)]).checked
    assert not SurfelField.concat([ok, made]).checked
    tree = build_lod(ok)
    assert not tree.nodes.checked                       # build_lod alone does not check its nodes
    cam = _camera()
    cut = tree.cut(cam.viewmat, cam.K, cam.width, cam.height, cam.near, cam.far, 4.0)
    assert not gather_cuts([tree], [cut]).checked
    tree.nodes.mark_checked()
    assert gather_cuts([tree], [cut]).checked


def test_a_checked_field_cannot_be_edited_behind_its_mark():
    # the mark vouches for values: an in-place edit of a checked field (or of a view of one)
    # raises, and reassigning a value array makes the field unchecked, so the next frame
    # scans it and refuses the bad value
    ok = scene_surfels(_stage(_field()))
    view = ok.rows(0, 5)
    for arr in (ok.positions, ok.orientations, ok.scales, ok.opacities, ok.sh, view.sh):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = np.nan
    cam = _camera()
    bad_sh = ok.sh.copy()
    bad_sh[3, 0, 0] = np.nan
    ok.sh = bad_sh
    assert not ok.checked
    with pytest.raises(InputError, match="non-finite"):
        render_surfels(ok, cam)


def test_a_world_transform_that_overflows_is_refused_naming_it():
    # stored values that pass, placed by an ancestor's scale of 1e38 beyond float32: one
    # InputError naming the prim and the transform, nothing marked checked
    from pxr import UsdGeom
    stage = _stage(_field())
    UsdGeom.Xform.Define(stage, S.SURFELS_PATH).AddScaleOp().Set((1e38, 1e38, 1e38))
    with pytest.raises(InputError, match=r"Chunk_0_0\.positions: a non-finite position .*"
                                         r"after the prim's world transform"):
        scene_surfels(stage)
