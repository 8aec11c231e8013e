import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from pxr import Sdf, UsdGeom, UsdLux, UsdSemantics

from lsd3d_usd import scene, semantics
from lsd3d_usd.cli import main
from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, look_at, to_usd
from lsd3d_usd.views.images import read_image, srgb_encode, tonemap
from lsd3d_usd.views.preview import render_preview
from lsd3d_usd.views.stage_data import EnvMap

W, H = 64, 36


def _write_exr(path, img):
    import OpenImageIO as oiio
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(img.shape[1], img.shape[0], 3, "float"))
    out.write_image(np.ascontiguousarray(img, np.float32))
    out.close()


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    """A 40x40 m road quad (labelled 'road'), a camera looking along it, a sky dome whose
    texture is blue above the horizon and red below."""
    d = tmp_path_factory.mktemp("scene")
    stage = scene.new_stage()
    mesh = UsdGeom.Mesh.Define(stage, "/World/Proxy/Ground")
    mesh.GetPointsAttr().Set([(-20, -20, 0), (20, -20, 0), (20, 20, 0), (-20, 20, 0)])
    mesh.GetFaceVertexCountsAttr().Set([4])
    mesh.GetFaceVertexIndicesAttr().Set([0, 1, 2, 3])
    UsdSemantics.LabelsAPI.Apply(mesh.GetPrim(), "class").CreateLabelsAttr(["road"])
    sky = np.zeros((16, 32, 3), np.float32)
    sky[:8] = (0.2, 0.4, 0.9)
    sky[8:] = (0.9, 0.1, 0.1)
    _write_exr(d / "sky.exr", sky)
    dome = UsdLux.DomeLight.Define(stage, "/World/Env/Sky")
    dome.GetTextureFileAttr().Set(Sdf.AssetPath("./sky.exr"))
    dome.GetTextureFormatAttr().Set("latlong")
    cam = Camera.from_fov(W, H, 60.0, look_at([0, -18, 1.5], [0, 0, 1.5]), near=0.1, far=500)
    to_usd(stage, "/World/Cameras/Front", cam)
    scene.save_stage(stage, d / "scene.usda")
    assert main(["splats", "init", str(d / "scene.usda"), "-o", str(d / "surfels.usdc"),
                 "--count", "40000", "--opacity", "1.0"]) == 0
    root = Sdf.Layer.FindOrOpen(str(d / "scene.usda"))
    root.subLayerPaths.append("./surfels.usdc")
    root.Save()
    return d / "scene.usda"


def test_render_exr_shows_surfels_and_env(scene_file, tmp_path):
    files = render_preview(scene_file, "/World/Cameras/Front", tmp_path, resolution=(W, H), fmt="exr",
                           progress=False)
    img = read_image(files[0])
    assert img.shape == (H, W, 5)
    rgb, alpha = img[..., :3], img[..., 3]
    # Bottom rows see the road: nearly opaque (1-sigma disks tile the area; gaps between
    # disk centres keep a few % transmittance), road colour over the red lower hemisphere.
    a = alpha[-5:, :, None]
    assert a.min() > 0.8 and a.mean() > 0.97
    expect = a * semantics.CLASS_COLORS[0] + (1 - a) * np.array([0.9, 0.1, 0.1])
    np.testing.assert_allclose(rgb[-5:], expect, atol=0.01)
    # Top rows see the sky: the blue half of the env map, no surfels.
    assert np.all(alpha[:3] < 1e-3)
    np.testing.assert_allclose(rgb[:3].reshape(-1, 3), np.tile([0.2, 0.4, 0.9], (3 * W, 1)), atol=1e-4)
    assert np.all(img[-5:, :, 4] > 0)  # depth channel


def test_render_command_png_frames(scene_file, tmp_path):
    assert main(["render", str(scene_file), "--camera", "/World/Cameras/Front", "-o", str(tmp_path),
                 "--resolution", f"{W}x{H}", "--frames", "1:2"]) == 0
    a = read_image(tmp_path / "Front.0001.png")
    b = read_image(tmp_path / "Front.0002.png")
    assert a.shape == (H, W, 3)
    np.testing.assert_array_equal(a, b)  # nothing animated
    sky = srgb_encode(tonemap(np.array([0.2, 0.4, 0.9])))
    np.testing.assert_allclose(a[0, 0], sky, atol=1 / 255 + 1e-6)


def test_missing_camera_and_no_surfels_errors(scene_file, tmp_path, capsys):
    with pytest.raises(InputError, match=r"no prim at /World/Cameras/Back.*Front"):
        render_preview(scene_file, "/World/Cameras/Back", tmp_path, progress=False)
    with pytest.raises(InputError, match="not a Camera"):
        render_preview(scene_file, "/World/Proxy/Ground", tmp_path, progress=False)
    stage = scene.new_stage()
    to_usd(stage, "/World/Cam", Camera.from_fov(8, 8, 60.0))
    scene.save_stage(stage, tmp_path / "empty.usda")
    assert main(["render", str(tmp_path / "empty.usda"), "--camera", "/World/Cam", "-o",
                 str(tmp_path.parent / f"{tmp_path.name}_out")]) == 1
    assert "no surfels" in capsys.readouterr().err
    assert main(["render", str(scene_file), "--camera", "/World/Cameras/Front", "-o", str(tmp_path),
                 "--resolution", "axb"]) == 1


def test_env_lookup_orientation():
    # 4x8 map: column blocks tell the longitude; rows the latitude.
    img = np.zeros((4, 8, 3), np.float32)
    img[:, :, 0] = np.arange(8)[None, :]
    img[:, :, 1] = np.arange(4)[:, None]
    env = EnvMap(img, np.eye(3))
    # Straight up is the top row; -Y (south) is the image centre (u=0.5); +X is u=0.25.
    assert env.lookup(np.array([[0, 0, 1.0]]))[0, 1] == pytest.approx(0.0)
    assert env.lookup(np.array([[0, -1.0, 0]]))[0, 0] == pytest.approx(3.5)
    assert env.lookup(np.array([[1.0, 0, 0]]))[0, 0] == pytest.approx(1.5)
    # A dome rotated 90 degrees about Z: what was east is now north.
    Rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    env_r = EnvMap(img, Rz)
    assert env_r.lookup(np.array([[0, 1.0, 0]]))[0, 0] == pytest.approx(1.5)


def test_render_help_states_the_real_default_widths(capsys):
    from lsd3d_usd.render.camera import DEFAULT_WIDTH
    from lsd3d_usd.views.rig import DEFAULT_WIDTH as RIG_WIDTH
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"default {DEFAULT_WIDTH} wide" in text and f"(default {RIG_WIDTH})" in text
    assert (DEFAULT_WIDTH, RIG_WIDTH) == (960, 480)
    assert "--no-progress" in text


def test_default_width_is_960(scene_file, tmp_path):
    assert main(["render", str(scene_file), "--camera", "/World/Cameras/Front", "-o", str(tmp_path),
                 "--no-progress", "--format", "exr"]) == 0
    assert read_image(tmp_path / "Front.exr").shape[:2] == (540, 960)
