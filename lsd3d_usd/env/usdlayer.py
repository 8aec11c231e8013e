"""The env layer: /World/Env with a VariantSet "environment", one variant per environment.

Each variant holds
* /World/Env/Dome — a ``DomeLight_1`` with ``poleAxis = "Z"`` and a latlong EXR
  (relative asset path, ``colorSpace`` metadata on ``inputs:texture:file``). With poleAxis Z
  the dome needs no xform: the map's zenith row is +Z and its centre -Y, exactly the
  convention of `lsd3d_usd.env.mapping`.
* /World/Env/Sun — a ``DistantLight`` toward the sun carrying the part of the sun's
  illuminance the (half-float clamped) map does not hold; intensity in klx so that a white
  Lambertian surface's E/pi is in the map's kcd/m^2.
* attributes on /World/Env (``lsd3d:env:*``): SH irradiance (float3[9], the 3DGS basis
  ordering, E(n) = sum c_k Y_k(n)), sun direction, fog parameters for the renderer,
  wet-ground / snow-cover / vegetation hints for the prior, colour space, parameters.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, Vt

import lsd3d_usd  # noqa: F401  (schema registration before any stage)
from lsd3d_usd import scene
from lsd3d_usd.env import colorspace as cs
from lsd3d_usd.env.exr import read_env, write_env
from lsd3d_usd.env.params import EnvParams
from lsd3d_usd.errors import InputError

VARIANT_SET = "environment"
NS = "lsd3d:env:"


def _quat_z_to(direction) -> "Gf.Quatf":
    """Rotation taking +Z to `direction` (a DistantLight shines along its -Z)."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    s = np.linalg.norm(axis)
    c = float(np.dot(z, d))
    if s < 1e-9:
        return Gf.Quatf(1, 0, 0, 0) if c > 0 else Gf.Quatf(0, 1, 0, 0)
    axis /= s
    ang = math.atan2(s, c)
    h = math.sin(ang / 2)
    return Gf.Quatf(math.cos(ang / 2), *(float(a * h) for a in axis))


def _relative_asset(texture: Path, layer_dir: Path) -> str:
    rel = os.path.relpath(Path(texture).absolute(), layer_dir.absolute()).replace(os.sep, "/")
    return rel if rel.startswith("..") else "./" + rel


def _default_texture_dir(layer_path: Path) -> Path:
    d = layer_path.absolute().parent
    return d.parent / scene.TEXTURES_DIR if d.name == scene.LAYERS_DIR else d / scene.TEXTURES_DIR


def _author_variant(stage, env_path, name: str, exr: Path, meta: dict, layer_dir: Path,
                    extras=None):
    env = stage.GetPrimAtPath(env_path)
    vset = env.GetVariantSets().AddVariantSet(VARIANT_SET)
    vset.AddVariant(name)
    vset.SetVariantSelection(name)
    space = meta.get("lsd3d:colorSpace", "lin_rec709")
    sun = meta["lsd3d:sun"]
    fog = meta["lsd3d:fog"]
    hints = meta["lsd3d:hints"]
    with vset.GetVariantEditContext():
        dome = UsdLux.DomeLight_1.Define(stage, env_path.AppendChild("Dome"))
        tex = dome.CreateTextureFileAttr(Sdf.AssetPath(_relative_asset(exr, layer_dir)))
        tex.SetColorSpace(cs.USD_NAMES[space])
        dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
        dome.CreatePoleAxisAttr("Z")
        dome.CreateIntensityAttr(1.0)
        dome.CreateExposureAttr(0.0)

        light = UsdLux.DistantLight.Define(stage, env_path.AppendChild("Sun"))
        resid = np.asarray(sun["residual_illuminance"], np.float64)
        lum = float(0.2126 * resid[0] + 0.7152 * resid[1] + 0.0722 * resid[2]) \
            if space == "lin_rec709" else float(resid.mean())
        color = resid / lum if lum > 0 else np.ones(3)
        light.CreateIntensityAttr(lum)
        light.CreateColorAttr(Gf.Vec3f(*(float(c) for c in color)))
        light.CreateAngleAttr(float(sun["angular_diameter_deg"]))
        xf = UsdGeom.Xformable(light.GetPrim())
        xf.ClearXformOpOrder()
        xf.AddOrientOp().Set(_quat_z_to(sun["direction"]))
        if lum <= 0:
            UsdGeom.Imageable(light.GetPrim()).CreateVisibilityAttr(UsdGeom.Tokens.invisible)

        def attr(n, t, v):
            env.CreateAttribute(NS + n, t, custom=True).Set(v)

        sh = np.asarray(meta["lsd3d:shIrradiance"], np.float64)
        attr("shIrradiance", Sdf.ValueTypeNames.Float3Array,
             Vt.Vec3fArray([Gf.Vec3f(*map(float, row)) for row in sh]))
        attr("sunDirection", Sdf.ValueTypeNames.Float3, Gf.Vec3f(*map(float, sun["direction"])))
        attr("sunElevation", Sdf.ValueTypeNames.Float, float(sun["elevation_deg"]))
        attr("sunAzimuth", Sdf.ValueTypeNames.Float, float(sun["azimuth_deg"]))
        attr("sunIlluminance", Sdf.ValueTypeNames.Color3f,
             Gf.Vec3f(*map(float, sun["direct_illuminance"])))
        attr("fog:density", Sdf.ValueTypeNames.Float, float(fog["density"]))
        attr("fog:color", Sdf.ValueTypeNames.Color3f, Gf.Vec3f(*map(float, fog["color"])))
        attr("fog:heightFalloff", Sdf.ValueTypeNames.Float, float(fog["height_falloff"]))
        attr("fog:baseHeight", Sdf.ValueTypeNames.Float, float(fog["base_height"]))
        attr("wetGround", Sdf.ValueTypeNames.Float, float(hints["wet_ground"]))
        attr("snowCover", Sdf.ValueTypeNames.Float, float(hints["snow_cover"]))
        attr("vegetation", Sdf.ValueTypeNames.Token, hints["vegetation"])
        attr("season", Sdf.ValueTypeNames.Token, hints["season"])
        attr("weather", Sdf.ValueTypeNames.Token, hints["weather"])
        attr("colorSpace", Sdf.ValueTypeNames.Token, cs.USD_NAMES[space])
        attr("units", Sdf.ValueTypeNames.String, meta.get("lsd3d:units", ""))
        attr("paramsHash", Sdf.ValueTypeNames.String, meta.get("lsd3d:paramsHash", ""))
        attr("params", Sdf.ValueTypeNames.String, json.dumps(meta.get("lsd3d:params", {}),
                                                             sort_keys=True))
        if extras is not None:
            extras(stage, name, exr)


def write_env_layer(stage_or_path, envs, selected: str | None = None,
                    texture_dir=None, width: int = 2048, height: int = 1024,
                    layer_dir=None, append: bool = True, variant_extras=None):
    """Author /World/Env with one variant per environment.

    envs: EnvParams, EXR paths written by `write_env`, or (variant name, either) pairs; a
    single item is accepted too. EnvParams are rendered (cached) into `texture_dir`
    (default: the scene's textures/ beside layers/, else textures/ beside the layer).
    stage_or_path: a Usd.Stage to author into (returned, not saved), or a .usda path,
    written atomically with scene.save_stage (an existing env layer there gets the new
    variants added when `append`). `selected`: variant to select (default: the first given).
    ``variant_extras``: None, or a callable (stage, variant name, EXR path) run inside each new
    variant's edit context (what a scene adds: its display exposure, its far field).
    """

    if isinstance(envs, (EnvParams, str, Path, tuple)):
        envs = [envs]
    if not envs:
        raise InputError("write_env_layer: no environments given")
    path = None
    if isinstance(stage_or_path, Usd.Stage):
        stage = stage_or_path
        real = stage.GetRootLayer().realPath
        layer_dir = Path(layer_dir or (Path(real).parent if real else Path.cwd()))
    else:
        path = Path(stage_or_path)
        if path.suffix.lower() not in (".usda", ".usd", ".usdc"):
            raise InputError(f"{path}: the env layer must be a .usda/.usdc/.usd file")
        layer_dir = path.absolute().parent
        if append and path.exists():
            stage = scene.open_stage(path)
        else:
            stage = scene.new_stage()
    tex_dir = Path(texture_dir) if texture_dir else (
        _default_texture_dir(path) if path else layer_dir / scene.TEXTURES_DIR)

    env_path = stage.GetPrimAtPath(scene.ENV_PATH).GetPath() if stage.GetPrimAtPath(
        scene.ENV_PATH) else UsdGeom.Xform.Define(stage, scene.ENV_PATH).GetPath()
    names, recorded = [], []
    for item in envs:
        name, src = item if isinstance(item, tuple) else (None, item)
        if isinstance(src, EnvParams):
            exr = write_env(src, tex_dir, width, height)
            name = name or src.variant_name()
        else:
            exr = Path(src)
            if not exr.is_file():
                raise InputError(f"{exr}: environment EXR not found")
        img_meta = read_env(exr)[1]
        if "lsd3d:sun" not in img_meta:
            raise InputError(f"{exr}: not an lsd3d environment map (no lsd3d:sun metadata); "
                             f"write it with `lsd3d-usd env`")
        if name is None:
            name = EnvParams.from_dict(img_meta["lsd3d:params"]).variant_name()
        if not name or not (name[0].isalpha() or name[0] == "_") or not all(
                c.isalnum() or c == "_" for c in name):
            raise InputError(f"variant name {name!r}: use letters, digits and _ (not starting "
                             f"with a digit)")
        _author_variant(stage, env_path, name, exr, img_meta, layer_dir, variant_extras)
        names.append(name)
        recorded.append({"variant": name, "texture": _relative_asset(exr, layer_dir),
                         "paramsHash": img_meta.get("lsd3d:paramsHash", "")})
    vset = stage.GetPrimAtPath(env_path).GetVariantSets().GetVariantSet(VARIANT_SET)
    sel = selected or names[0]
    if sel not in vset.GetVariantNames():
        raise InputError(f"variant {sel!r} is not among {vset.GetVariantNames()}")
    vset.SetVariantSelection(sel)
    if path is None:
        return stage
    # its own key: a scene's env layer keeps generate's parameters (lsd3d.params) beside it
    prov = scene.provenance("env", environments=json.dumps(recorded))
    return scene.save_stage(stage, path, provenance=prov)


def read_env_prim(stage) -> dict:
    """What the selected environment says: SH (9,3), sun direction, fog, hints, texture."""
    env = stage.GetPrimAtPath(scene.ENV_PATH)
    if not env:
        raise InputError(f"no {scene.ENV_PATH} prim in the stage")
    out = {}
    for a in env.GetAttributes():
        n = a.GetName()
        if n.startswith(NS):
            out[n[len(NS):]] = a.Get()
    if "shIrradiance" in out:
        out["shIrradiance"] = np.array([list(v) for v in out["shIrradiance"]], np.float64)
    dome = env.GetChild("Dome")
    if dome:
        f = UsdLux.DomeLight_1(dome).GetTextureFileAttr()
        out["texture"] = f.Get().resolvedPath or f.Get().path
        out["poleAxis"] = UsdLux.DomeLight_1(dome).GetPoleAxisAttr().Get()
    return out


FAR_HEIGHT = NS + "farField:height"
FAR_ALBEDO = NS + "farField:albedo"


def author_far_field(stage, height: float, albedo) -> None:
    """The ground beyond the scene (env.farfield) on /World/Env: its height (m) and albedo
    (linear RGB), authored where the stage's edit target is (inside a variant's edit context
    they belong to that environment). Readers light it with the selected environment."""
    a = np.asarray(albedo, np.float64).reshape(-1)
    if not math.isfinite(float(height)) or a.shape != (3,) or not np.all(np.isfinite(a)) \
            or a.min() < 0:
        raise InputError(f"far field: need a finite height and 3 non-negative albedo values, got "
                         f"{height}, {albedo}")
    env = stage.GetPrimAtPath(scene.ENV_PATH)
    env.CreateAttribute(FAR_HEIGHT, Sdf.ValueTypeNames.Float, custom=True).Set(float(height))
    env.CreateAttribute(FAR_ALBEDO, Sdf.ValueTypeNames.Color3f, custom=True).Set(
        Gf.Vec3f(*(float(v) for v in a)))


def residual_sun(env) -> np.ndarray:
    """(3,) illuminance (klx) of the sun that the map does not hold: /World/Env/Sun's intensity
    × colour (``env``: the /World/Env prim), 0 without a visible Sun light. The map's SH
    irradiance plus this is the whole light of the sky and sun."""
    sun = env.GetChild("Sun")
    if not sun or UsdGeom.Imageable(sun).ComputeVisibility() == UsdGeom.Tokens.invisible:
        return np.zeros(3)
    lx = UsdLux.LightAPI(sun)
    try:
        out = float(lx.GetIntensityAttr().Get() or 0.0) * np.asarray(
            lx.GetColorAttr().Get() or (1, 1, 1), np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InputError(f"{sun.GetPath()}: the sun's intensity and colour must be a float and "
                         "3 floats") from None
    if not np.all(np.isfinite(out)) or out.min() < 0:
        raise InputError(f"{sun.GetPath()}: the sun's intensity × colour must be finite and "
                         f"non-negative, got {tuple(out)}")
    return out


def _env_value(env, name: str, shape: tuple, what: str) -> np.ndarray:
    a = env.GetAttribute(NS + name)
    v = a.Get() if a else None
    try:
        arr = np.asarray([list(x) for x in v] if len(shape) == 2 else v, np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape or not np.all(np.isfinite(arr)):
        raise InputError(f"{env.GetPath()}.{NS}{name}: {what} needs it as {shape or 'one'} "
                         f"finite value(s), got {v!r}")
    return arr


def read_far_field(stage):
    """The env.farfield.FarField /World/Env describes (radiance in the env map's units: a
    level Lambertian ground of its albedo under the map's SH irradiance and the sun the map
    does not hold, as the actors are lit; fogged by the env's fog density), or None when it
    has none. A bad or half-authored one is one InputError naming the attribute."""
    from lsd3d_usd.env.farfield import FarField, ground_radiance

    env = stage.GetPrimAtPath(scene.ENV_PATH)
    if not env:
        return None
    authored = [a.HasAuthoredValue() if a else False
                for a in (env.GetAttribute(FAR_HEIGHT), env.GetAttribute(FAR_ALBEDO))]
    if not any(authored):
        return None
    if not all(authored):
        missing = FAR_ALBEDO if authored[0] else FAR_HEIGHT
        raise InputError(f"{env.GetPath()}.{missing}: the far field needs both its height and "
                         "its albedo")
    what = "the far field"
    height = float(_env_value(env, "farField:height", (), what))
    albedo = _env_value(env, "farField:albedo", (3,), what)
    if albedo.min() < 0:
        raise InputError(f"{env.GetPath()}.{FAR_ALBEDO}: negative albedo {tuple(albedo)}")
    density = 0.0
    if env.GetAttribute(NS + "fog:density"):
        density = float(_env_value(env, "fog:density", (), what))
        if density < 0:
            raise InputError(f"{env.GetPath()}.{NS}fog:density: negative fog density {density}")
    radiance = ground_radiance(albedo, _env_value(env, "shIrradiance", (9, 3), what),
                               _env_value(env, "sunDirection", (3,), what), residual_sun(env))
    if not np.all(np.isfinite(radiance)):
        raise InputError(f"{env.GetPath()}: the far field's light is not finite (shIrradiance, "
                         "the Sun light)")
    return FarField(height, tuple(float(v) for v in radiance), density)
