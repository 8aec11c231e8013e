"""Geometry, multi-view and temporal checks on synthetic frames with known answers; novel
view and trajectory construction."""
import numpy as np
import pytest

from conftest import ROOT
from lsd3d_usd.errors import InputError
from lsd3d_usd.eval import geometry as G
from lsd3d_usd.eval import temporal as T
from lsd3d_usd.eval import lane_views as V
from lsd3d_usd.conditioning.view_sampling import building_paths, inside_paths, sample_views
from lsd3d_usd.layout.usdio import read_layout
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.render.gbuffer import render_gbuffer
from lsd3d_usd.semantics import CLASS_ID

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"

# A wall in the plane y = 20 (facing -y), class "building", and cameras on y = 0 looking at it.
WALL_V = np.array([[-200.0, 20.0, -50.0], [200.0, 20.0, -50.0], [200.0, 20.0, 50.0], [-200.0, 20.0, 50.0]])
WALL_F = np.array([[0, 1, 2], [0, 2, 3]])
WALL_C = np.full(2, CLASS_ID["building"], np.int32)


def _cam(x, w=64, h=48):
    eye = np.array([x, 0.0, 1.5])
    return Camera.from_fov(w, h, 60.0, pose=look_at(eye, eye + [0.0, 1.0, 0.0]), near=0.1, far=500.0)


def _frame_from_gbuffer(gb, depth_scale=1.0, normal=None):
    """A 'surfel render' that is exactly the proxy (optionally scaled depth / other normals)."""
    d = np.where(gb.mask, gb.depth * depth_scale, 0.0).astype(np.float32)
    n = gb.normal if normal is None else np.broadcast_to(np.asarray(normal, np.float32), gb.normal.shape)
    return {"alpha": gb.mask.astype(np.float32), "depth_median": d, "depth_expected": d,
            "normal_world": np.where(gb.mask[..., None], n, 0.0).astype(np.float32)}


def test_class_agreement_known_depth_and_normal_errors():
    cam = _cam(0.0)
    gb = render_gbuffer(WALL_V, WALL_F, cam, WALL_C)
    acc = G.ClassAgreement()
    tilt = np.radians(10.0)
    # proxy normal faces the camera (-y); tilt the surfel normal by 10 degrees about z
    acc.add(_frame_from_gbuffer(gb, 1.02, normal=[np.sin(tilt), -np.cos(tilt), 0.0]), gb, cam)
    r = acc.result()
    b = r["per_class"]["building"]
    assert b["pixels"] == 64 * 48 and b["coverage"] == 1.0
    assert b["depth_rel_err_median"] == pytest.approx(0.02, abs=1e-5)
    assert b["normal_err_deg_median"] == pytest.approx(10.0, abs=1e-3)
    # Normals pointing away from the camera are the same surface: the proxy normal is flipped
    # towards the camera before comparing, the surfel normal is already camera-facing.
    acc2 = G.ClassAgreement()
    acc2.add(_frame_from_gbuffer(gb, 1.0), gb, cam)
    assert acc2.result()["all"]["normal_err_deg_median"] == pytest.approx(0.0, abs=1e-3)
    assert acc2.result()["all"]["depth_rel_err_median"] == pytest.approx(0.0, abs=1e-6)


def test_coverage_counts_holes():
    cam = _cam(0.0)
    gb = render_gbuffer(WALL_V, WALL_F, cam, WALL_C)
    fr = _frame_from_gbuffer(gb)
    fr["alpha"][:, :16] = 0.0   # a quarter of the image has no surfels
    acc = G.ClassAgreement()
    acc.add(fr, gb, cam)
    assert acc.result()["per_class"]["building"]["coverage"] == pytest.approx(0.75)


def test_reprojection_depth_error_zero_when_consistent_and_exact_when_scaled():
    a, b = _cam(0.0), _cam(1.0)
    ga = render_gbuffer(WALL_V, WALL_F, a, WALL_C)
    gb = render_gbuffer(WALL_V, WALL_F, b, WALL_C)
    r = G.reprojection_depth_error(a, _frame_from_gbuffer(ga), ga, b, _frame_from_gbuffer(gb), gb)
    assert r["median"] == pytest.approx(0.0, abs=1e-6) and r["frac_over_5pct"] == 0.0
    # the views overlap partly: 1 m sideways at 20 m with a 60 deg field of view
    assert 0.8 < r["shared_frac"] < 1.0
    # b's surfels 10 % too far: |z - 1.1 z| / z = 0.1 everywhere both see the wall
    r = G.reprojection_depth_error(a, _frame_from_gbuffer(ga), ga, b, _frame_from_gbuffer(gb, 1.1), gb)
    assert r["median"] == pytest.approx(0.1, abs=1e-5)


def test_reprojection_masks_what_the_proxy_hides():
    # A box in front of the wall, seen only from b: wall pixels of a hidden in b do not count.
    a, b = _cam(0.0), _cam(6.0)
    occ_V = np.array([[4.0, 10.0, -5.0], [9.0, 10.0, -5.0], [9.0, 10.0, 10.0], [4.0, 10.0, 10.0]])
    Vb = np.concatenate([WALL_V, occ_V])
    Fb = np.concatenate([WALL_F, WALL_F + 4])
    Cb = np.concatenate([WALL_C, WALL_C])
    ga = render_gbuffer(WALL_V, WALL_F, a, WALL_C)
    gb_no = render_gbuffer(WALL_V, WALL_F, b, WALL_C)
    gb = render_gbuffer(Vb, Fb, b, Cb)
    fa = _frame_from_gbuffer(ga)
    r_no = G.reprojection_depth_error(a, fa, ga, b, _frame_from_gbuffer(gb_no), gb_no)
    r = G.reprojection_depth_error(a, fa, ga, b, _frame_from_gbuffer(gb), gb)
    assert r["pixels"] < r_no["pixels"]
    assert r["median"] == pytest.approx(0.0, abs=1e-6)   # the occluder never counts as an error


def _textured(cam, gb):
    """Display image of a smooth world-space texture on the wall (view-independent)."""
    p = gb.position
    img = np.stack([0.5 + 0.4 * np.sin(p[..., 0] * 0.7), 0.5 + 0.4 * np.cos(p[..., 2] * 0.9),
                    0.5 + 0.2 * np.sin((p[..., 0] + p[..., 2]) * 0.5)], -1)
    return np.where(gb.mask[..., None], img, 0.0)


def test_warp_error_small_for_consistent_frames_and_masks_wrong_depth():
    cams = [_cam(0.3 * i, 96, 72) for i in range(4)]
    gbs = [render_gbuffer(WALL_V, WALL_F, c, WALL_C) for c in cams]
    imgs = [_textured(c, g) for c, g in zip(cams, gbs)]
    frames = [_frame_from_gbuffer(g) for g in gbs]
    r = T.trajectory_warp_errors(cams, imgs, frames)
    assert r["pairs"] == 3 and r["valid_frac"] > 0.9
    assert r["warp_err"] < 0.1 * r["naive_err"]
    # depth off by 20 %: the reprojected depth disagrees with prev's, those pixels are masked
    bad = [_frame_from_gbuffer(g, 1.2) for g in gbs]
    one = T.warp_error(cams[0], imgs[0], frames[0], cams[1], imgs[1], bad[1])
    assert one["valid_frac"] < 0.05


def test_bilinear_is_exact_on_linear_images():
    yy, xx = np.mgrid[0:10, 0:12].astype(np.float64)
    img = np.stack([xx, yy, xx + 2 * yy], -1)
    u, v = np.array([3.7, 5.5]), np.array([2.2, 8.5])
    np.testing.assert_allclose(T.bilinear(img, u, v), [[3.2, 1.7, 6.6], [5.0, 8.0, 21.0]], atol=1e-12)


# ------------------------------------------------------------------ views
@pytest.fixture(scope="module")
def layout():
    return read_layout(LAYOUT)


def test_novel_views_distances_headings_and_determinism(layout):
    seen = sample_views(layout, 6, 64, 48, seed=3)
    bins = (0.5, 2.0, 8.0)
    nv = V.novel_views(seen, bins, 7, seed=11, layout=layout)
    assert len(nv) == 21
    assert [n.bin_m for n in nv] == [0.5] * 7 + [2.0] * 7 + [8.0] * 7
    fps = building_paths(layout)
    for i, n in enumerate(nv):
        src = seen[n.source].camera
        assert n.source == i % 7 % 6
        disp = n.view.camera.center - src.center
        np.testing.assert_allclose(np.linalg.norm(disp), n.bin_m, rtol=1e-9)
        assert -min(0.25 * n.bin_m, V.MAX_DROP_M) - 1e-9 <= disp[2] <= 0.25 * n.bin_m + 1e-9
        assert abs(n.yaw_deg) <= min(V.HEADING_DEG_PER_M * n.bin_m, V.MAX_HEADING_DEG) + 1e-9
        R = n.view.camera.pose[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        # heading turned about z only: the pitch of the optical axis is unchanged
        assert n.view.camera.pose[2, 2] == pytest.approx(src.pose[2, 2], abs=1e-12)
        assert not inside_paths(n.view.camera.center, fps)
        assert n.nearest_train_m <= n.bin_m + 1e-9
    again = V.novel_views(seen, bins, 7, seed=11, layout=layout)
    assert all(np.array_equal(a.view.camera.pose, b.view.camera.pose) for a, b in zip(nv, again))
    other = V.novel_views(seen, bins, 7, seed=12, layout=layout)
    assert not np.array_equal(nv[0].view.camera.pose, other[0].view.camera.pose)
    with pytest.raises(InputError, match="positive"):
        V.novel_views(seen, (1.0, -2.0), 2, seed=0)


def test_lane_trajectory_is_smooth_and_evenly_spaced(layout):
    cams, info = V.lane_trajectory(layout, 12, 0.5, 64, 48)
    c = np.array([k.center for k in cams])
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    np.testing.assert_allclose(step, 0.5, atol=0.02)
    fwd = np.array([k.pose[:3, 2] for k in cams])
    turn = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], axis=1), -1, 1)))
    assert turn.max() < 5.0
    assert info["frames"] == 12 and info["lane"]


def test_sample_depth_bilinear_on_smooth_surfaces_nearest_at_edges():
    yy, xx = np.mgrid[0:8, 0:10].astype(np.float64)
    depth = 10.0 + 0.1 * xx + 0.05 * yy          # a smooth slope
    valid = np.ones_like(depth, bool)
    u, v = np.array([3.25, 7.9]), np.array([2.75, 4.5])
    np.testing.assert_allclose(G.sample_depth(depth, valid, u, v),
                               10.0 + 0.1 * (u - 0.5) + 0.05 * (v - 0.5), rtol=1e-12)
    # a depth edge between columns 4 and 5: no blending, the nearest pixel's depth
    step = np.where(xx >= 5, 30.0, 10.0)
    assert G.sample_depth(step, valid, np.array([5.2]), np.array([3.0]))[0] == 30.0
    assert G.sample_depth(step, valid, np.array([4.9]), np.array([3.0]))[0] == 10.0
