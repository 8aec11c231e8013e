"""The ground beyond the scene (env.farfield): the plane against a float64 ray-by-ray
reference, its edge cases, the env layer's attributes, and every consumer drawing it alike."""
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from pxr import Usd

from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.gbuffer import GBuffer
from lsd3d_usd.conditioning.light import PriorEnv
from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.env.farfield import FarField, ground_radiance
from lsd3d_usd.env.sh import eval_sh_irradiance
from lsd3d_usd.env.usdlayer import FAR_ALBEDO, author_far_field, read_far_field
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
from lsd3d_usd.proxy.usdio import ground_level
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.views.stage_data import read_dome


def reference(bg, origin, dirs, ff):
    """Ray by ray in float64: where the ray meets z = height ahead of an origin above it."""
    out = np.array(bg, np.float64)
    for i, d in enumerate(np.asarray(dirs, np.float64)):
        if origin[2] > ff.height and d[2] < -1e-6:
            t = (origin[2] - ff.height) / -d[2]
            T = math.exp(-ff.fog_density * t)
            out[i] = np.maximum(out[i] + (np.asarray(ff.radiance) - np.asarray(ff.ground)) * T, 0)
    return out


def test_plane_matches_the_reference_ray_by_ray():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:50, 2] = -1e-9       # grazing the horizon: the env map alone
    bg = rng.uniform(0, 5, size=(4000, 3)).astype(np.float32)
    for origin, fog in (((3.0, -2.0, 30.0), 2e-3), ((0.0, 0.0, 1.6), 1e-4), ((0, 0, 200.0), 0.0)):
        ff = FarField(0.5, (1.0, 2.0, 0.5), fog, (3.0, 0.5, 1.0))       # some channels < 0
        got = ff.apply(bg, np.array(origin), d)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, reference(bg, origin, d, ff), rtol=1e-5, atol=1e-5)
        up = d[:, 2] >= 0
        np.testing.assert_array_equal(got[up], bg[up])          # the sky is untouched
        np.testing.assert_array_equal(got[:50], bg[:50])
    np.testing.assert_array_equal(ff.apply(bg, (0, 0, 0.5), d), bg)   # on the plane
    np.testing.assert_array_equal(ff.apply(bg, (0, 0, -4.0), d), bg)  # under it


def test_plane_recolours_the_ground_half_and_fades_into_it_at_the_horizon():
    lookup = lambda d: np.where(np.asarray(d)[:, 2:3] < 0, 2.0, 9.0) * np.ones((1, 3))
    ff = FarField(0.0, (1.0, 1.0, 1.0), 1e-4).over(lookup)
    assert ff.ground == (2.0, 2.0, 2.0)                         # the map straight down
    dz = np.array([1.0, 1e-1, 1e-3, 1e-5])
    d = np.stack([np.sqrt(1 - dz ** 2), np.zeros(4), -dz], -1)
    bg = np.array([[2.0] * 3, [2.0] * 3, [5.0] * 3, [7.0] * 3], np.float32)  # hazier near the horizon
    got = ff.apply(bg, (0, 0, 30.0), d)[:, 0]
    assert got[0] == pytest.approx(1.0 + (1 - math.exp(-1e-4 * 30)), rel=1e-5)  # the plane below
    assert got[1] == pytest.approx(2.0 - math.exp(-1e-4 * 300), rel=1e-5)
    assert got[2] == pytest.approx(5.0 - math.exp(-1e-4 * 3e4), rel=1e-5)       # the map's haze kept
    assert got[3] == pytest.approx(7.0, rel=1e-6)               # at the horizon: the map itself
    scaled = ff.scaled((2.0, 1.0, 0.5))
    assert scaled.radiance == (2.0, 1.0, 0.5) and scaled.ground == (4.0, 2.0, 1.0)


def test_ground_radiance_is_a_lambertian_level_surface():
    rng = np.random.default_rng(1)
    sh = rng.uniform(0.1, 2.0, size=(9, 3))
    sun = np.array([0.3, -0.2, 0.8])
    lux = np.array([5.0, 4.5, 4.0])
    E = eval_sh_irradiance(sh, np.array([[0.0, 0, 1]]))[0] + lux * 0.8 / np.linalg.norm(sun)
    alb = np.array([0.1, 0.2, 0.05])
    np.testing.assert_allclose(ground_radiance(alb, sh, sun, lux), alb * E / math.pi, rtol=1e-12)
    # the sun under the horizon lights nothing
    np.testing.assert_allclose(ground_radiance(alb, sh, -sun, lux),
                               alb * eval_sh_irradiance(sh, np.array([[0.0, 0, 1]]))[0] / math.pi)


def test_procedural_prior_draws_it_behind_the_proxy():
    """A G-buffer with no proxy at all: every pixel is background, so the plane shows."""
    H, W = 6, 8
    cam_pos = torch.tensor([0.0, 0.0, 20.0])
    dirs = torch.nn.functional.normalize(torch.randn(H, W, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    gb = GBuffer(depth=torch.full((H, W), float("inf")), normal=torch.zeros(H, W, 3),
                 semantic=torch.full((H, W), -1, dtype=torch.long), world_pos=torch.full((H, W, 3), float("nan")),
                 view_dirs=dirs, camera_position=cam_pos)
    ff = FarField(2.0, (0.5, 0.6, 0.2), 0.0)
    env = PriorEnv(exposure=0.5, far_field=ff)
    prior = ProceduralPrior()
    got = prior.render(gb, env)
    sky = prior.sky(dirs.reshape(-1, 3), env).reshape(H, W, 3)
    down = dirs[..., 2] < 0
    want = (sky[down] + torch.tensor([0.5, 0.6, 0.2])) * 0.5       # no map: its ground is 0
    np.testing.assert_allclose(got[down].numpy(), want.clamp(0, 1).numpy(), atol=1e-6)
    np.testing.assert_allclose(got[~down].numpy(), (sky[~down] * 0.5).clamp(0, 1).numpy(), atol=1e-6)


def test_procedural_ground_albedo_is_its_terrain():
    prior = ProceduralPrior()
    green = prior.ground_albedo(PriorEnv())
    assert green.shape == (3,) and green[1] > green[0] > green[2] > 0      # grass
    snow = prior.ground_albedo(PriorEnv(snow_cover=1.0, vegetation="snow"))
    assert snow.min() > 2 * green.max()
    autumn = prior.ground_albedo(PriorEnv(vegetation="autumn"))
    assert autumn[0] > autumn[1] > autumn[2] and autumn[0] > green[0]


def test_env_layer_round_trip_and_bad_values(tmp_path):
    stage = S.new_stage()
    stage.DefinePrim(S.ENV_PATH, "Xform")
    assert read_far_field(stage) is None                         # no far field: none drawn
    author_far_field(stage, 1.25, (0.1, 0.2, 0.05))
    with pytest.raises(InputError, match="shIrradiance"):        # nothing to light it with
        read_far_field(stage)
    env = stage.GetPrimAtPath(S.ENV_PATH)
    from pxr import Gf, Sdf, Vt
    env.CreateAttribute("lsd3d:env:shIrradiance", Sdf.ValueTypeNames.Float3Array).Set(
        Vt.Vec3fArray([Gf.Vec3f(1, 1, 1)] + [Gf.Vec3f(0, 0, 0)] * 8))
    env.CreateAttribute("lsd3d:env:sunDirection", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(0, 0, 1))
    env.CreateAttribute("lsd3d:env:sunIlluminance", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(5, 5, 5))
    from pxr import UsdLux     # the part of the sun the map does not hold lights it
    UsdLux.DistantLight.Define(stage, env.GetPath().AppendChild("Sun")).CreateIntensityAttr(2.0)
    env.CreateAttribute("lsd3d:env:fog:density", Sdf.ValueTypeNames.Float).Set(1e-3)
    ff = read_far_field(stage)
    assert ff.height == 1.25 and ff.fog_density == pytest.approx(1e-3)
    np.testing.assert_allclose(ff.radiance, ground_radiance((0.1, 0.2, 0.05), [[1, 1, 1]] + [[0] * 3] * 8,
                                                            (0, 0, 1), (2, 2, 2)), rtol=1e-6)
    env.GetAttribute(FAR_ALBEDO).Set(Gf.Vec3f(-1, 0, 0))
    with pytest.raises(InputError, match="farField:albedo"):
        read_far_field(stage)
    with pytest.raises(InputError, match="far field"):
        author_far_field(stage, float("nan"), (0.1, 0.1, 0.1))


@pytest.mark.parametrize("name, type_name, value, needle", [
    ("farField:height", "String", "high", "farField:height"),
    ("farField:albedo", "Token", "green", "farField:albedo"),
    ("shIrradiance", "Float", 1.0, "shIrradiance"),
    ("sunDirection", "String", "up", "sunDirection"),
    ("fog:density", "Float", float("inf"), "fog:density"),
    ("fog:density", "Float", -1.0, "fog:density"),
])
def test_a_bad_far_field_attribute_is_one_error_naming_it(name, type_name, value, needle):
    from pxr import Gf, Sdf, Vt
    stage = S.new_stage()
    env = stage.DefinePrim(S.ENV_PATH, "Xform")
    author_far_field(stage, 0.0, (0.1, 0.2, 0.05))
    env.CreateAttribute("lsd3d:env:shIrradiance", Sdf.ValueTypeNames.Float3Array).Set(
        Vt.Vec3fArray([Gf.Vec3f(1, 1, 1)] * 9))
    env.CreateAttribute("lsd3d:env:sunDirection", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(0, 0, 1))
    assert read_far_field(stage) is not None
    env.RemoveProperty("lsd3d:env:" + name)
    env.CreateAttribute("lsd3d:env:" + name, getattr(Sdf.ValueTypeNames, type_name)).Set(value)
    with pytest.raises(InputError, match=needle.replace(":", ".")):
        read_far_field(stage)


def test_half_a_far_field_is_an_error():
    stage = S.new_stage()
    env = stage.DefinePrim(S.ENV_PATH, "Xform")
    author_far_field(stage, 0.0, (0.1, 0.2, 0.05))
    env.RemoveProperty(FAR_ALBEDO)
    with pytest.raises(InputError, match="farField:albedo.*both"):
        read_far_field(stage)


def test_generated_scene_draws_the_same_ground_everywhere(small_scene):
    """The scene records its far field at its ground level, and the prior's conditioning and
    the rig/eval renderer (views) draw the same background for a camera high above it."""
    sc = S.Scene.open(small_scene)
    stage = sc.open_stage(load=False)
    ff = read_far_field(stage)
    assert ff is not None
    assert ff.height == pytest.approx(ground_level(sc.layer_path("proxy")))
    assert abs(ff.height) < 0.5                                 # the sample is level at z 0
    cam = Camera.from_fov(96, 54, 60.0, pose=look_at((-250.0, -250.0, 120.0), (0, 0, 0)))
    cond = Conditioning.of_scene(sc, proxy=(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros(1, np.int32)))
    # the plane has the prior's terrain colour, lit as the prior lights open ground (the map's
    # SH holds part of the sun at this scene's 128x64 map: counted once, not twice)
    env_prim = stage.GetPrimAtPath(S.ENV_PATH)
    albedo = np.asarray(env_prim.GetAttribute(FAR_ALBEDO).Get(), np.float64)
    np.testing.assert_allclose(albedo, ProceduralPrior(seed=5).ground_albedo(cond.env), rtol=1e-5)
    lit = albedo * cond.light.irradiance(np.array([[0.0, 0.0, 1.0]]))[0]
    np.testing.assert_allclose(np.asarray(ff.radiance) * cond.light.exposure, lit, rtol=0.04)
    a = cond.background(cam).numpy()
    b = read_dome(Usd.Stage.Open(str(sc.root / "scene.usda"))).pixels(cam)
    np.testing.assert_allclose(a, b, rtol=2e-3, atol=2e-4)
    # the lower half of that view is the plane, not the env map's ground half
    from lsd3d_usd.render.camera import pixel_rays
    _, d = pixel_rays(cam)
    env_only = cond.light.envmap(torch.from_numpy(d.astype(np.float32))).numpy() * cond.light.exposure
    low = d[..., 2] < -0.2      # steeply down: mostly the plane's own colour (the map's haze is kept)
    plane = np.asarray(ff.radiance) * cond.light.exposure
    assert np.abs(a[low] - plane).mean() < 0.25 * np.abs(env_only[low] - plane).mean()
    up = d[..., 2] > 0
    np.testing.assert_allclose(a[up], env_only[up], rtol=1e-5, atol=1e-7)       # the sky as it was


def _patch(x0, z, cls, n=4):
    """An up-facing n×n grid patch at height z (z may vary per vertex)."""
    from lsd3d_usd.proxy.mesh import MeshPart
    g = np.linspace(0, 10, n)
    x, y = np.meshgrid(g + x0, g)
    V = np.stack([x.ravel(), y.ravel(), np.broadcast_to(z, x.shape).ravel()], -1).astype(np.float64)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            F += [(a, b, d), (a, d, c)]
    return MeshPart(V, np.array(F, np.int32), cls, f"{cls}_{x0}")


def test_ground_level_is_the_median_of_the_ground_classes(tmp_path):
    from lsd3d_usd.proxy.usdio import write_proxy
    rng = np.random.default_rng(3)
    z_road = rng.uniform(2.0, 3.0, (4, 4))
    parts = {(0, 0): [_patch(0, z_road, "road"), _patch(0, 40.0, "building", 2)],
             (1, 0): [_patch(100, 2.5, "terrain"), _patch(100, -30.0, "vegetation")]}
    path = write_proxy(parts, tmp_path / "proxy.usdc")
    got = ground_level(path)
    assert 2.0 <= got <= 3.0            # roofs and tree tops do not pull it up
    # two chunks of 16 ground vertices: the median of the two chunks' medians, weighted
    assert got == pytest.approx(min(np.median(z_road), 2.5))
    path2 = write_proxy({(0, 0): [_patch(0, 40.0, "building", 2)]}, tmp_path / "p2" / "proxy.usdc")
    assert ground_level(path2) is None


def test_pinhole_lookup_draws_the_plane_in_the_same_pass():
    """The views' one-pass lookup (numba) against FarField.apply over the plain lookup."""
    from lsd3d_usd.env.lookup import env_lookup, env_lookup_pinhole
    from lsd3d_usd.render.camera import pixel_directions
    rng = np.random.default_rng(4)
    image = rng.uniform(0, 3, (32, 64, 3)).astype(np.float32)
    ff = FarField(1.0, (0.5, 2.5, 1.0), 3e-3, (1.5, 0.5, 1.0))
    for eye, target in (((0, 0, 31.0), (80, 20, 0)), ((5, 5, 2.6), (60, 0, 1.0)), ((0, 0, 0.5), (9, 0, 0))):
        cam = Camera.from_fov(48, 27, 80.0, pose=look_at(eye, target))
        d = pixel_directions(cam)
        plain = env_lookup(torch.from_numpy(image), torch.from_numpy(d.astype(np.float32))).numpy()
        want = ff.apply(plain, np.asarray(eye, np.float64), d)
        got = env_lookup_pinhole(image, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                                 cam.pose[:3, :3], np.eye(3), False, ff, eye[2])
        with pytest.raises(ValueError, match="height"):       # never the plane seen from z 0
            env_lookup_pinhole(image, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                               cam.pose[:3, :3], np.eye(3), False, ff)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
        if eye[2] > ff.height + 1:
            assert np.abs(got - plain).max() > 0.1               # the plane is there
        else:
            np.testing.assert_allclose(got, plain, rtol=1e-5, atol=1e-6)   # seen from under it


def test_the_env_layer_is_remade_when_what_its_far_field_rests_on_changes():
    """generate reuses the env layer by its inputs' hash: the far field's (the layout and proxy
    settings for its height, the prior's terrain and seed for its colour) are among them."""
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.pipeline import _env_layer_hash
    base = generate_config(seed=1)
    h = _env_layer_hash("env", "layout", base)
    assert h == _env_layer_hash("env", "layout", generate_config(seed=1))
    assert h != _env_layer_hash("env2", "layout", base)
    assert h != _env_layer_hash("env", "layout2", base)
    assert h != _env_layer_hash("env", "layout", generate_config(seed=2))      # the terrain's seed
    assert h != _env_layer_hash("env", "layout", generate_config(seed=1, proxy={"traffic_lights": False}))


def test_env_variant_added_to_a_scene_gets_its_exposure_and_far_field(small_scene, tmp_path,
                                                                      run_cli):
    # `lsd3d-usd env --usd SCENE/layers/env.usda` adds a variant as generate authors its own:
    # the display exposure and the ground beyond the scene; a layer outside a scene gets neither
    import shutil

    from lsd3d_usd.conditioning.light import scene_light
    from lsd3d_usd.env.exr import read_env
    from lsd3d_usd.env.params import EnvParams

    scene = tmp_path / "scene"
    shutil.copytree(small_scene, scene)
    before = Usd.Stage.Open(str(scene / S.ROOT_FILE))
    old = read_far_field(before)
    assert old is not None
    old_albedo = np.array(before.GetPrimAtPath(S.ENV_PATH).GetAttribute(FAR_ALBEDO).Get())
    exr = scene / "textures" / "rain.exr"
    run_cli("env", "--prompt", "rainy autumn evening in Seattle", "--resolution", "64x32",
            "-o", exr, "--usd", scene / S.LAYERS_DIR / "env.usda", "--variant", "rain",
            check=True)
    stage = before
    stage.Reload()          # the layers this process holds are the files before the command
    env = stage.GetPrimAtPath(S.ENV_PATH)
    assert env.GetVariantSets().GetVariantSet("environment").GetVariantSelection() == "rain"
    far = read_far_field(stage)
    assert far is not None and far.height == pytest.approx(old.height)
    albedo = np.array(env.GetAttribute(FAR_ALBEDO).Get())
    params = EnvParams.from_dict(read_env(exr)[1]["lsd3d:params"])
    light = scene_light(params, exr)
    # the scene's prior (procedural) continues its own terrain, weathered for the rain
    want = ProceduralPrior(seed=5).ground_albedo(light.prior_env)
    np.testing.assert_allclose(albedo, want, rtol=1e-5)
    assert np.abs(albedo - old_albedo).max() > 0.02
    shown = env.GetAttribute("lsd3d:env:displayExposure").Get()
    assert shown == pytest.approx(light.exposure, rel=1e-6)
    from pxr import UsdLux
    dome = UsdLux.DomeLight_1(env.GetChild("Dome"))
    assert dome.GetExposureAttr().Get() == pytest.approx(math.log2(light.exposure), rel=1e-6)
    assert read_dome(stage).far_field is not None
    # GGDS and eval still condition on the environment generate made (its map, its far
    # field), whatever variant the layer selects for the views
    from lsd3d_usd.conditioning.scene import scene_env
    sc = S.Scene.open(scene)
    made, made_texture = scene_env(S.Scene.open(small_scene))
    params_now, texture = scene_env(sc, stage=stage)
    assert params_now.to_dict() == made.to_dict()
    assert texture.name == made_texture.name and texture.resolve() != exr.resolve()
    assert read_far_field(stage).height == pytest.approx(old.height)
    assert np.array(env.GetAttribute(FAR_ALBEDO).Get()) == pytest.approx(old_albedo)
    # eval renders with the environment its targets are conditioned on
    from lsd3d_usd.conditioning.scene import select_generated_environment
    from lsd3d_usd.env.usdlayer import read_env_prim
    views = Usd.Stage.Open(str(scene / S.ROOT_FILE))
    assert Path(read_env_prim(views)["texture"]).name == "rain.exr"
    select_generated_environment(sc, views)
    assert Path(read_env_prim(views)["texture"]).resolve() == texture.resolve()
    assert np.array(views.GetPrimAtPath(S.ENV_PATH).GetAttribute(FAR_ALBEDO).Get()) == \
        pytest.approx(old_albedo)
    # the session layer's choice is not saved with the scene
    views.Save()
    assert Path(read_env_prim(Usd.Stage.Open(str(scene / S.ROOT_FILE)))["texture"]).name == \
        "rain.exr"
    # generate's variant is not written over, by its name or by the same conditions
    got = run_cli("env", "--resolution", "64x32", "-o", tmp_path / "same.exr", "--usd",
                  scene / S.LAYERS_DIR / "env.usda", "--variant", made.variant_name())
    assert got.returncode != 0 and "--variant" in got.stderr and made.variant_name() in got.stderr
    assert not (tmp_path / "same.exr").exists()
    # the scene's own layer is generate's to remake: --replace is refused, nothing written
    before_bytes = (scene / S.LAYERS_DIR / "env.usda").read_bytes()
    got = run_cli("env", "--prompt", "snowy winter morning", "--resolution", "64x32",
                  "-o", tmp_path / "snow.exr", "--usd", scene / S.LAYERS_DIR / "env.usda",
                  "--replace")
    assert got.returncode != 0 and "--replace" in got.stderr and "scene's own env layer" in got.stderr
    assert (scene / S.LAYERS_DIR / "env.usda").read_bytes() == before_bytes
    assert not (tmp_path / "snow.exr").exists()
    # outside a scene: the plain env layer, as before
    run_cli("env", "--prompt", "rainy autumn evening in Seattle", "--resolution", "64x32",
            "-o", tmp_path / "e.exr", "--usd", tmp_path / "env.usda", check=True)
    assert read_far_field(Usd.Stage.Open(str(tmp_path / "env.usda"))) is None
