"""Preview frames of a composed stage: surfels + env map, seen from a USD camera.

Reads every ParticleField prim (our Lsd3dSurfelField and official 3DGS fields,
flattened to surfels by the reader) with its world transform, the camera prim,
and the first visible DomeLight's latlong texture; rasterises the surfels with
the env map composited behind per pixel direction; writes PNG (tone-mapped,
sRGB-encoded, 8 bit) or EXR (scene-linear float RGBA + Z) with OpenImageIO.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, from_usd, pixel_rays

TONEMAPS = ("aces", "reinhard", "clamp")


# --- stage contents --------------------------------------------------------------------

def _time(t):
    from pxr import Usd
    return Usd.TimeCode.Default() if t is None else Usd.TimeCode(t)


def gather_surfels(stage, time=None):
    """All visible ParticleField prims of the stage as one SurfelField in world space,
    or None when there are no particles."""
    from pxr import UsdGeom

    from lsd3d_usd.splats.field import SurfelField
    from lsd3d_usd.splats.init import transform_surfels
    from lsd3d_usd.splats.usdio import read_surfels, surfel_prims

    t = _time(time)
    fields = []
    for prim in surfel_prims(stage):
        img = UsdGeom.Imageable(prim)
        if img and img.ComputeVisibility(t) == UsdGeom.Tokens.invisible:
            continue
        f = read_surfels(prim, t)
        if f.n == 0:
            continue
        M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), dtype=np.float64).T
        fields.append(transform_surfels(f, M))
    if not fields:
        return None
    try:
        return SurfelField.concat(fields)
    except ValueError:
        # Different class tables: render anyway, without semantic ids.
        from dataclasses import replace
        return SurfelField.concat([replace(f, semantic_ids=None, semantic_classes=()) for f in fields])


@dataclass
class EnvMap:
    """A latlong env texture (scene-linear RGB, float32) with its dome orientation."""
    image: np.ndarray            # (h, w, 3)
    world_from_dome: np.ndarray  # (3,3) rotation of the DomeLight
    pole_axis: str = "Z"         # "Z" (our convention) or "Y" (OpenEXR latlong, Y up)
    source: str = ""

    def lookup(self, dirs: np.ndarray) -> np.ndarray:
        """Bilinear radiance (…,3) for world directions (…,3), wrapping in longitude."""
        from lsd3d_usd.env.mapping import direction_to_uv

        d = np.asarray(dirs, np.float64) @ self.world_from_dome  # = R^T d: into the dome frame
        if self.pole_axis == "Y":
            d = np.stack([d[..., 0], -d[..., 2], d[..., 1]], axis=-1)
        uv = direction_to_uv(d)
        h, w = self.image.shape[:2]
        x = uv[..., 0] * w - 0.5
        y = np.clip(uv[..., 1] * h - 0.5, 0.0, h - 1.0)
        x0 = np.floor(x).astype(np.int64)
        y0 = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros_like(x0)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        x0m, x1m = x0 % w, (x0 + 1) % w
        y1 = np.minimum(y0 + 1, h - 1)
        im = self.image
        top = im[y0, x0m] * (1 - fx) + im[y0, x1m] * fx
        bot = im[y1, x0m] * (1 - fx) + im[y1, x1m] * fx
        return (top * (1 - fy) + bot * fy).astype(np.float32)


_ENV_CACHE: dict = {}


def read_image(path: str) -> np.ndarray:
    """Float32 (h, w, c) pixels of an image file (OpenImageIO)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read image: {oiio.geterror()}")
    try:
        px = inp.read_image("float")
    finally:
        inp.close()
    if px is None:
        raise InputError(f"{path}: cannot read image pixels")
    return np.asarray(px, np.float32)


def read_env(stage, time=None) -> EnvMap | None:
    """The first visible DomeLight with a texture, or None (black background)."""
    from pxr import Usd, UsdGeom, UsdLux

    try:
        import lsd3d_usd.env.mapping  # noqa: F401  (the env step's latlong convention)
    except ImportError:
        return None
    t = _time(time)
    dome_types = [UsdLux.DomeLight] + ([UsdLux.DomeLight_1] if hasattr(UsdLux, "DomeLight_1") else [])
    for prim in Usd.PrimRange(stage.GetPseudoRoot()):
        kind = next((k for k in dome_types if prim.IsA(k)), None)
        if kind is None:
            continue
        if UsdGeom.Imageable(prim).ComputeVisibility(t) == UsdGeom.Tokens.invisible:
            continue
        light = kind(prim)
        asset = light.GetTextureFileAttr().Get(t)
        if not asset or not asset.path:
            continue
        path = asset.resolvedPath or asset.path
        if not os.path.isfile(path):
            raise InputError(f"{prim.GetPath()}.inputs:texture:file: texture {asset.path!r} not found")
        fmt = light.GetTextureFormatAttr().Get(t)
        if fmt not in (None, "automatic", "latlong"):
            raise InputError(f"{prim.GetPath()}: texture format {fmt!r} not supported (latlong only)")
        key = (path, os.path.getmtime(path))
        if key not in _ENV_CACHE:
            _ENV_CACHE.clear()
            _ENV_CACHE[key] = read_image(path)
        img = _ENV_CACHE[key]
        rgb = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
        lx = UsdLux.LightAPI(prim)
        gain = float(lx.GetIntensityAttr().Get(t) or 1.0) * 2.0 ** float(lx.GetExposureAttr().Get(t) or 0.0)
        col = np.asarray(lx.GetColorAttr().Get(t) or (1, 1, 1), np.float32)
        M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), dtype=np.float64).T[:3, :3]
        U, _, Vt = np.linalg.svd(M)
        pole = light.GetPoleAxisAttr().Get() if hasattr(light, "GetPoleAxisAttr") else None
        up = UsdGeom.GetStageUpAxis(stage)
        pole_axis = "Y" if (pole == "Y" or (pole in (None, "scene") and up == "Y")) else "Z"
        return EnvMap((rgb * (gain * col)).astype(np.float32), U @ Vt, pole_axis, str(prim.GetPath()))
    return None


def env_background(env: EnvMap | None, camera: Camera) -> np.ndarray | None:
    if env is None:
        return None
    _, d = pixel_rays(camera)
    return env.lookup(d)


# --- rendering ----------------------------------------------------------------------------

def render_frame(field, camera: Camera, env: EnvMap | None = None, sh_degree=None) -> dict:
    """Rasterise ``field`` for ``camera`` with the env composited behind. numpy dict out."""
    import torch

    from lsd3d_usd.render.raster_types import RasterSettings
    from lsd3d_usd.render.rasterize import rasterize

    bg = env_background(env, camera)
    with torch.no_grad():
        out = rasterize(
            torch.from_numpy(np.ascontiguousarray(field.positions)),
            torch.from_numpy(np.ascontiguousarray(field.orientations)),
            torch.from_numpy(np.ascontiguousarray(field.scales)),
            torch.from_numpy(np.ascontiguousarray(field.opacities)),
            torch.from_numpy(np.ascontiguousarray(field.sh)),
            torch.from_numpy(camera.viewmat.astype(np.float32)),
            torch.from_numpy(camera.K.astype(np.float32)),
            camera.width, camera.height,
            settings=RasterSettings.for_camera(camera, sh_degree=sh_degree),
            background=None if bg is None else torch.from_numpy(bg),
            semantic_ids=None if field.semantic_ids is None else torch.from_numpy(field.semantic_ids),
        )
    return out.numpy()


def tonemap(rgb: np.ndarray, exposure: float = 0.0, method: str = "aces") -> np.ndarray:
    """Scene-linear -> display-linear in [0, 1]."""
    x = np.maximum(rgb * (2.0 ** exposure), 0.0)
    if method == "aces":  # Narkowicz's fit of the ACES filmic curve
        y = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
    elif method == "reinhard":
        y = x / (1.0 + x)
    elif method == "clamp":
        y = x
    else:
        raise InputError(f"unknown tone map {method!r}; choose from {', '.join(TONEMAPS)}")
    return np.clip(y, 0.0, 1.0)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def write_frame(path, frame: dict, fmt: str = "png", exposure: float = 0.0, tonemap_method: str = "aces"):
    """Write a rendered frame atomically: PNG (8-bit sRGB, tone-mapped, alpha=1) or EXR
    (float RGBA + Z = expected camera depth, scene-linear, untouched)."""
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = frame["rgb"]
    h, w = rgb.shape[:2]
    if fmt == "png":
        enc = srgb_encode(tonemap(rgb, exposure, tonemap_method))
        pixels = np.round(enc * 255.0).astype(np.uint8)
        spec = oiio.ImageSpec(w, h, 3, "uint8")
    elif fmt == "exr":
        alpha = frame.get("alpha", np.ones((h, w), np.float32))
        depth = frame.get("depth_expected", np.zeros((h, w), np.float32))
        pixels = np.concatenate([rgb * (2.0 ** exposure), alpha[..., None], depth[..., None]],
                                axis=2).astype(np.float32)
        spec = oiio.ImageSpec(w, h, 5, "float")
        spec.channelnames = ("R", "G", "B", "A", "Z")
        spec.alpha_channel, spec.z_channel = 3, 4
        spec.attribute("compression", "zip")
    else:
        raise InputError(f"unknown image format {fmt!r}; choose png or exr")
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None or not out.open(str(tmp), spec):
        raise InputError(f"{path}: cannot write image: {oiio.geterror()}")
    try:
        ok = out.write_image(np.ascontiguousarray(pixels))
    finally:
        out.close()
    if not ok:
        tmp.unlink(missing_ok=True)
        raise InputError(f"{path}: writing failed: {out.geterror()}")
    os.replace(tmp, path)
    return path


# --- the preview command's core ------------------------------------------------------------

def _camera_prim(stage, camera_path: str):
    from pxr import Sdf, Usd, UsdGeom

    if not Sdf.Path.IsValidPathString(camera_path) or not camera_path.startswith("/"):
        raise InputError(f"--camera {camera_path!r}: not an absolute prim path (e.g. /World/Cameras/Front)")
    prim = stage.GetPrimAtPath(camera_path)
    if not prim or not prim.IsA(UsdGeom.Camera):
        cams = [str(p.GetPath()) for p in Usd.PrimRange(stage.GetPseudoRoot()) if p.IsA(UsdGeom.Camera)]
        what = "no prim" if not prim else f"prim of type {prim.GetTypeName() or 'none'}, not a Camera,"
        raise InputError(f"{stage.GetRootLayer().identifier}: {what} at {camera_path}; cameras in the stage: "
                         f"{', '.join(cams[:10]) if cams else 'none'}")
    return prim


def frame_name(camera_path: str, time, fmt: str, multiple: bool) -> str:
    base = camera_path.rstrip("/").rsplit("/", 1)[-1]
    if not multiple:
        return f"{base}.{fmt}"
    t = float(time)
    tag = f"{int(t):04d}" if t == int(t) else f"{t:09.3f}"
    return f"{base}.{tag}.{fmt}"


def render_preview(scene_path, camera_path: str, out_dir, *, times=(None,), resolution=None,
                   fmt: str = "png", exposure: float = 0.0, tonemap_method: str = "aces",
                   use_env: bool = True, sh_degree=None, progress: bool = True) -> list[Path]:
    """Render frames of ``scene_path`` (scene folder or USD file) from ``camera_path``.
    Returns the written files."""
    from tqdm import tqdm

    from lsd3d_usd import scene

    if fmt not in ("png", "exr"):
        raise InputError(f"--format {fmt!r}: choose png or exr")
    if tonemap_method not in TONEMAPS:
        raise InputError(f"--tonemap {tonemap_method!r}: choose from {', '.join(TONEMAPS)}")
    stage = scene.open_stage(scene_path)
    prim = _camera_prim(stage, camera_path)
    width, height = resolution if resolution else (None, None)
    written = []
    times = list(times)
    static = all(t is None for t in times)
    cache = None
    for t in tqdm(times, desc="render", unit="frame", disable=not progress or len(times) < 2):
        cam = from_usd(prim, t, width, height)
        if cache is None or not static:
            field = gather_surfels(stage, t)
            if field is None:
                raise InputError(f"{scene_path}: no surfels to render (no visible ParticleField prim "
                                 "with particles; run mesh -> surfel initialisation or import a PLY)")
            env = read_env(stage, t) if use_env else None
            cache = (field, env)
        field, env = cache
        frame = render_frame(field, cam, env, sh_degree)
        path = Path(out_dir) / frame_name(camera_path, t if t is not None else 0, fmt, len(times) > 1)
        written.append(write_frame(path, frame, fmt, exposure, tonemap_method))
    return written
