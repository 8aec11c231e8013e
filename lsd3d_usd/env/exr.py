"""Write / read environment EXRs (half float, zip) with OpenImageIO, cached by content hash.

Metadata carried in the EXR header: the colour space (OIIO `oiio:ColorSpace` with USD's
colour-space name, plus the standard EXR `chromaticities`), the parameter hash and JSON,
units, the latlong convention, the order-2 SH irradiance, the sun direction and the part
of the sun's illuminance a DistantLight must carry, and the fog the renderer applies.
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from lsd3d_usd.env import colorspace as cs
from lsd3d_usd.env.params import EnvParams
from lsd3d_usd.env.sh import sh_irradiance
from lsd3d_usd.env.sky import SkyModel, render_sky
from lsd3d_usd.errors import InputError

UNITS = "kcd/m^2 (1.0 = 1000 cd/m^2)"
CONVENTION = "latlong; DomeLight_1 poleAxis=Z; top row = +Z (zenith); image centre = -Y; u=0.25 = +X"


def env_filename(params: EnvParams, width: int, height: int) -> str:
    return f"env_{params.content_hash(width, height)}.exr"


def _stored_hash(path: Path) -> str | None:
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        return None
    try:
        return inp.spec().getattribute("lsd3d:paramsHash")
    finally:
        inp.close()


def write_exr(path, image: np.ndarray, attributes: dict) -> Path:
    """Atomically write a (H, W, 3) float image as a half-float zip EXR with attributes."""
    path = Path(path)
    H, W, C = image.shape
    if not np.all(np.isfinite(image)):
        raise InputError(f"{path}: refusing to write an environment map with NaN/inf values")
    if float(np.max(image)) > 65504.0:
        raise InputError(f"{path}: value {float(np.max(image)):.4g} exceeds the half-float range")
    spec = oiio.ImageSpec(W, H, C, "half")
    spec.attribute("compression", "zip")
    for k, v in attributes.items():
        if k == "chromaticities":
            spec.attribute(k, oiio.TypeDesc("float[8]"), tuple(float(x) for x in v))
        else:
            spec.attribute(k, v)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".exr", dir=path.parent)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            raise InputError(f"{path}: cannot open for writing ({oiio.geterror()})")
        ok = out.write_image(np.ascontiguousarray(image, dtype=np.float32))
        out.close()
        if not ok:
            raise InputError(f"{path}: writing failed ({oiio.geterror()})")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read_env(path) -> tuple[np.ndarray, dict]:
    """(H, W, 3) float32 image and a dict of the lsd3d / colour attributes."""
    path = Path(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read environment map ({oiio.geterror()})")
    try:
        spec = inp.spec()
        img = inp.read_image("float")
        meta = {}
        for a in spec.extra_attribs:
            if a.name.startswith("lsd3d:") or a.name in ("oiio:ColorSpace", "chromaticities"):
                meta[a.name] = a.value
    finally:
        inp.close()
    if img is None or img.ndim != 3 or img.shape[2] < 3:
        raise InputError(f"{path}: not an RGB image")
    for k in ("lsd3d:params", "lsd3d:shIrradiance", "lsd3d:sun", "lsd3d:fog", "lsd3d:hints"):
        if k in meta:
            meta[k] = json.loads(meta[k])
    return np.ascontiguousarray(img[..., :3], dtype=np.float32), meta


def write_env(params: EnvParams, out, width: int = 2048, height: int = 1024,
              force: bool = False, timings: dict | None = None) -> Path:
    """Render and write the environment EXR; reuse the existing file if its stored parameter
    hash matches. `out` is a directory (file named env_<hash>.exr) or an .exr path."""
    out = Path(out)
    digest = params.content_hash(width, height)
    path = out if out.suffix.lower() == ".exr" else out / env_filename(params, width, height)
    if out.suffix and out.suffix.lower() != ".exr":
        raise InputError(f"{out}: environment output must be a directory or an .exr file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, expected an .exr file path")
    if not force and path.exists() and _stored_hash(path) == digest:
        if timings is not None:
            timings["cached"] = 0.0
        return path
    r = params.resolved()
    model = SkyModel(r)
    img = render_sky(r, width, height, model=model)
    t0 = time.perf_counter()
    sh = sh_irradiance(img)
    t_sh = time.perf_counter() - t0
    to_space = cs.rec709_to(r.color_space)
    fog = r.fog(color=tuple(to_space @ model.fog_rgb.astype(np.float64)))
    sun = {
        "direction": [float(v) for v in model.sun_dir],
        "elevation_deg": model.sun_elevation, "azimuth_deg": model.sun_azimuth,
        "visibility": model.sun_visibility,
        # klx, so that E/pi is in the map's kcd/m^2
        "residual_illuminance": [float(v) / 1000.0 for v in to_space @ model.sun_residual_illuminance],
        "direct_illuminance": [float(v) / 1000.0 for v in to_space @ model.sun_direct_lux],
        "angular_diameter_deg": 0.533,
    }
    hints = {"wet_ground": r.wet_ground, "snow_cover": r.snow_cover, "vegetation": r.vegetation,
             "season": r.season, "weather": r.weather}
    attrs = {
        "oiio:ColorSpace": cs.USD_NAMES[r.color_space],
        "chromaticities": cs.chromaticities(r.color_space),
        "lsd3d:colorSpace": r.color_space,
        "lsd3d:paramsHash": digest,
        "lsd3d:params": json.dumps(r.to_dict(), sort_keys=True),
        "lsd3d:units": UNITS,
        "lsd3d:convention": CONVENTION,
        "lsd3d:shIrradiance": json.dumps(sh.tolist()),
        "lsd3d:sun": json.dumps(sun),
        "lsd3d:fog": json.dumps({"density": fog.density, "color": list(fog.color),
                                 "height_falloff": fog.height_falloff,
                                 "base_height": fog.base_height}),
        "lsd3d:hints": json.dumps(hints),
    }
    t0 = time.perf_counter()
    write_exr(path, img, attrs)
    if timings is not None:
        timings.update(model.timings)
        timings["sh irradiance"] = t_sh
        timings["exr write"] = time.perf_counter() - t0
    return path
