"""EXR writing (half, zip, tags, cache), the env USD layer (DomeLight_1, variants), CLI."""
import datetime as dt
import math
import os

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from pxr import Usd, UsdLux

from lsd3d_usd.env import (EnvParams, read_env, read_env_prim, render_sky, sh_irradiance,
                           sun_direction, uv_to_direction, write_env, write_env_layer)
from lsd3d_usd.errors import InputError

TZ = dt.timezone(dt.timedelta(hours=2))
P = EnvParams(when=dt.datetime(2026, 6, 21, 10, 0, tzinfo=TZ), weather="clear")


@pytest.fixture(scope="module")
def exr(tmp_path_factory):
    return write_env(P, tmp_path_factory.mktemp("tex"), 128, 64)


def test_exr_is_half_zip_tagged_and_roundtrips(exr):
    import OpenImageIO as oiio
    assert exr.name == f"env_{P.content_hash(128, 64)}.exr"
    inp = oiio.ImageInput.open(str(exr))
    spec = inp.spec()
    inp.close()
    assert str(spec.format) == "half" and spec.getattribute("compression") == "zip"
    assert (spec.width, spec.height) == (128, 64)
    img, meta = read_env(exr)
    assert meta["oiio:ColorSpace"] == "lin_rec709_scene"
    np.testing.assert_allclose(meta["chromaticities"][:2], (0.64, 0.33), atol=1e-6)
    ref = render_sky(P, 128, 64)
    np.testing.assert_allclose(img, ref, rtol=2e-3, atol=1e-6)      # half precision
    np.testing.assert_allclose(meta["lsd3d:shIrradiance"], sh_irradiance(ref), rtol=1e-5)
    np.testing.assert_allclose(meta["lsd3d:sun"]["direction"], sun_direction(P), atol=1e-6)


def test_exr_is_reused_while_parameters_are_unchanged(tmp_path):
    a = write_env(P, tmp_path / "e.exr", 64, 32)
    m1 = os.stat(a).st_mtime_ns
    b = write_env(P, tmp_path / "e.exr", 64, 32)
    assert a == b and os.stat(b).st_mtime_ns == m1
    c = write_env(EnvParams(when=P.when, weather="rain"), tmp_path / "e.exr", 64, 32)
    assert read_env(c)[1]["lsd3d:params"]["weather"] == "rain"
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp")]
    with pytest.raises(InputError):
        write_env(P, tmp_path / "e.png", 64, 32)


def test_env_layer_domelight_orientation_and_variants(tmp_path):
    layer = tmp_path / "scene" / "layers" / "env.usda"
    rain = EnvParams(when=dt.datetime(2026, 10, 15, 17, 0, tzinfo=TZ), weather="rain")
    write_env_layer(layer, [P, ("rainy", rain)], width=128, height=64)
    stage = Usd.Stage.Open(str(layer))
    env = stage.GetPrimAtPath("/World/Env")
    vs = env.GetVariantSets().GetVariantSet("environment")
    assert set(vs.GetVariantNames()) == {P.variant_name(), "rainy"}
    assert vs.GetVariantSelection() == P.variant_name()
    dome = UsdLux.DomeLight_1(stage.GetPrimAtPath("/World/Env/Dome"))
    assert dome and dome.GetPoleAxisAttr().Get() == "Z"
    assert dome.GetTextureFormatAttr().Get() == "latlong"
    tex = dome.GetTextureFileAttr()
    assert tex.Get().path.startswith("../textures/env_")            # relative to the layer
    assert os.path.isfile(tex.Get().resolvedPath)
    assert tex.GetColorSpace() == "lin_rec709_scene"
    assert not dome.GetPrim().GetAttribute("xformOpOrder").HasAuthoredValue()   # no extra rotation
    info = read_env_prim(stage)
    assert info["shIrradiance"].shape == (9, 3) and info["weather"] == "clear"
    # the brightest texel of the dome's texture, mapped with the poleAxis-Z convention,
    # is the sun direction stored on the prim
    img, _ = read_env(info["texture"])
    lum = img.sum(-1)
    j, i = np.unravel_index(np.argmax(lum), lum.shape)
    d = uv_to_direction(np.array([(i + 0.5) / img.shape[1], (j + 0.5) / img.shape[0]]))
    s = np.array(info["sunDirection"])
    assert math.degrees(math.acos(np.clip(d @ s, -1, 1))) < 1.5      # 1 texel = 2.8 deg here
    # the DistantLight shines from the sun: its -Z axis points along -sun
    from pxr import UsdGeom, Gf
    sun = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Env/Sun"))
    m = sun.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    minus_z = m.TransformDir(Gf.Vec3d(0, 0, -1))
    np.testing.assert_allclose(np.array(minus_z), -s, atol=1e-5)
    # switching the variant switches the environment
    vs.SetVariantSelection("rainy")
    assert read_env_prim(stage)["weather"] == "rain"
    assert read_env_prim(stage)["wetGround"] == 1.0


def test_layer_appends_variants_and_rejects_bad_names(tmp_path, exr):
    layer = tmp_path / "env.usda"
    write_env_layer(layer, [("a", exr)])
    write_env_layer(layer, [("b", exr)])
    stage = Usd.Stage.Open(str(layer))
    vs = stage.GetPrimAtPath("/World/Env").GetVariantSets().GetVariantSet("environment")
    assert set(vs.GetVariantNames()) == {"a", "b"}
    with pytest.raises(InputError):
        write_env_layer(layer, [("9 bad", exr)])
    with pytest.raises(InputError):
        write_env_layer(layer, [tmp_path / "missing.exr"])


def test_cli_env_writes_and_reports_errors(tmp_path, capsys):
    from lsd3d_usd.cli import main
    out = tmp_path / "env.exr"
    rc = main(["env", "--prompt", "foggy dawn in Oslo blorp", "--resolution", "64x32",
               "-o", str(out), "--usd", str(tmp_path / "env.usda"), "--weather", "snow"])
    assert rc == 0 and out.is_file()
    err = capsys.readouterr().err
    assert "blorp" in err
    meta = read_env(out)[1]
    assert meta["lsd3d:params"]["weather"] == "snow"            # the flag overrides "foggy"
    assert meta["lsd3d:params"]["place"] == "oslo"
    assert main(["env", "--lat", "10", "-o", str(out)]) == 1
    assert main(["env", "--resolution", "64x64", "-o", str(out)]) == 1
    assert main(["env", "-o", str(tmp_path / "x.png")]) == 1
    assert "error" in capsys.readouterr().err
