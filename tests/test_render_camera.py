import numpy as np
import pytest

import lsd3d_usd  # noqa: F401  (registers schema before any stage)
from pxr import Gf, Usd, UsdGeom

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, from_usd, look_at, pixel_rays, to_usd


def _stage(mpu=1.0):
    s = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(s, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(s, mpu)
    return s


def _gf_pixel(usd_cam, point, width, height, time=Usd.TimeCode.Default()):
    """Project a world point with USD's own frustum math (independent of our code)."""
    fr = usd_cam.GetCamera(time).frustum
    M = fr.ComputeViewMatrix() * fr.ComputeProjectionMatrix()
    p = M.Transform(Gf.Vec3d(*point))  # includes perspective divide
    return np.array([(p[0] + 1) / 2 * width, (1 - p[1]) / 2 * height])


def test_look_at_projects_target_to_principal_point_and_up_is_up():
    pose = look_at([10, -5, 2], [30, 7, 1])
    cam = Camera.from_fov(640, 480, 70.0, pose)
    uv, z = cam.project([[30, 7, 1], [10 + 20, -5 + 12, 1 + 5]])
    np.testing.assert_allclose(uv[0], [320, 240], atol=1e-9)
    assert z[0] > 0
    assert uv[1, 1] < 240  # a point above the target appears higher in the image (smaller v)
    np.testing.assert_allclose(cam.viewmat @ cam.pose, np.eye(4), atol=1e-12)


def test_usd_projection_matches_gf_frustum_with_offsets_and_transform():
    s = _stage()
    UsdGeom.Xform.Define(s, "/World")
    parent = UsdGeom.Xform.Define(s, "/World/Rig")
    parent.AddTranslateOp().Set(Gf.Vec3d(100, 200, 3))
    parent.AddRotateZOp().Set(30.0)
    c = UsdGeom.Camera.Define(s, "/World/Rig/Cam")
    c.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    c.AddRotateXYZOp().Set(Gf.Vec3f(80, 5, 20))
    c.GetFocalLengthAttr().Set(0.35)
    c.GetHorizontalApertureAttr().Set(0.36)
    c.GetVerticalApertureAttr().Set(0.2025)  # 16:9 filmback
    c.GetHorizontalApertureOffsetAttr().Set(0.03)
    c.GetVerticalApertureOffsetAttr().Set(-0.01)
    W, H = 480, 270
    cam = from_usd(c.GetPrim(), None, W, H)
    rng = np.random.default_rng(0)
    # points in front of the camera: along its USD -Z
    M = np.array(c.ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    for _ in range(20):
        local = np.array([rng.uniform(-2, 2), rng.uniform(-1, 1), -rng.uniform(2, 50), 1.0])
        pw = (M @ local)[:3]
        uv, z = cam.project(pw[None])
        # GfFrustum works in float32 for lens values: ~1e-5 px agreement is exact here.
        np.testing.assert_allclose(uv[0], _gf_pixel(c, pw, W, H), atol=1e-4)
        np.testing.assert_allclose(z[0], -local[2], rtol=1e-9)


def test_round_trip_camera_usd_camera():
    s = _stage()
    UsdGeom.Xform.Define(s, "/World")
    cams = UsdGeom.Xform.Define(s, "/World/Cameras")
    cams.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))  # parent transform must be compensated
    pose = look_at([5, 6, 1.5], [40, 10, 0.5])
    cam = Camera(960, 540, 700.0, 690.0, 470.0, 280.0, pose, near=0.2, far=3000.0)
    to_usd(s, "/World/Cameras/Front", cam, time=4.0)
    back = from_usd(s.GetPrimAtPath("/World/Cameras/Front"), 4.0, 960, 540, conform="stretch")
    for k in ("fx", "fy", "cx", "cy", "near", "far"):
        assert getattr(back, k) == pytest.approx(getattr(cam, k), rel=2e-6), k
    np.testing.assert_allclose(back.pose, pose, atol=1e-9)
    # Authored lens values are millimetres in tenths of a metre (metersPerUnit 1).
    c = UsdGeom.Camera(s.GetPrimAtPath("/World/Cameras/Front"))
    assert c.GetHorizontalApertureAttr().Get(4.0) == pytest.approx(0.36)


def test_conform_horizontal_keeps_square_pixels_and_hfov():
    s = _stage()
    c = UsdGeom.Camera.Define(s, "/Cam")  # default 20.955 x 15.2908 filmback, f=50
    cam = from_usd(c.GetPrim(), None, 400, 400)
    assert cam.fx == pytest.approx(50 * 400 / 20.955)
    assert cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (200, 200)
    cam2 = from_usd(c.GetPrim(), None, 400, None)  # height from the filmback aspect
    assert cam2.height == round(400 * 15.2908 / 20.955)


def test_pixel_rays_hit_expected_points():
    pose = look_at([0, 0, 10], [5, 3, 0], up=[0, 0, 1])
    cam = Camera(64, 48, 50.0, 55.0, 30.0, 26.0, pose)
    o, d = pixel_rays(cam)
    assert o.shape == d.shape == (48, 64, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    # Intersect with the ground plane z=0 and re-project: must land on the pixel centre.
    t = -o[..., 2] / d[..., 2]
    hits = o + t[..., None] * d
    uv, z = cam.project(hits.reshape(-1, 3))
    jj, ii = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
    np.testing.assert_allclose(uv[:, 0], jj.ravel(), atol=1e-8)
    np.testing.assert_allclose(uv[:, 1], ii.ravel(), atol=1e-8)
    assert np.all(z > 0)


def test_bad_inputs_raise_input_error():
    s = _stage()
    x = UsdGeom.Xform.Define(s, "/NotACam")
    with pytest.raises(InputError, match="/NotACam"):
        from_usd(x.GetPrim(), None, 10, 10)
    with pytest.raises(InputError):
        look_at([0, 0, 0], [0, 0, 5])  # parallel to up
    with pytest.raises(InputError):
        Camera(10, 10, 5, 5, 5, 5, np.eye(4), near=1.0, far=0.5)
