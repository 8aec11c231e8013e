"""Display encoding and image files: tone mapping, sRGB, reading images and writing frames
(PNG: tone-mapped 8-bit sRGB; EXR: scene-linear float RGBA + Z) with OpenImageIO."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lsd3d_usd.colour import srgb_encode  # noqa: F401  (the display transfer, one definition)
from lsd3d_usd.errors import InputError

TONEMAPS = ("aces", "reinhard", "clamp")


def tonemap(rgb: np.ndarray, exposure: float = 0.0, method: str = "aces") -> np.ndarray:
    """Scene-linear image (an array) -> display-linear in [0, 1]."""
    # in place on one copy: a frame per step (the simulator) need not allocate ten images
    x = np.asarray(np.multiply(rgb, 2.0 ** exposure))
    np.maximum(x, 0.0, out=x)
    if method == "aces":  # Narkowicz's fit of the ACES filmic curve
        y = np.multiply(x, 2.51)
        y += 0.03
        y *= x
        den = np.multiply(x, 2.43)
        den += 0.59
        den *= x
        den += 0.14
        y /= den
    elif method == "reinhard":
        y = np.add(x, 1.0)
        np.divide(x, y, out=y)
    elif method == "clamp":
        y = x
    else:
        raise InputError(f"unknown tone map {method!r}; choose from {', '.join(TONEMAPS)}")
    return np.clip(y, 0.0, 1.0, out=y)


def display_uint8(rgb: np.ndarray, exposure: float = 0.0, method: str = "aces") -> np.ndarray:
    """Scene-linear RGB -> what a screen shows: tone-mapped, sRGB-encoded, 8 bit."""
    y = srgb_encode(tonemap(rgb, exposure, method))
    y *= 255.0
    return np.round(y, out=y).astype(np.uint8)


def read_image(path) -> np.ndarray:
    """Float32 (h, w, c) pixels of an image file (OpenImageIO)."""
    # local import: not loaded for --help
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


def write_image(path, pixels: np.ndarray, channels=None, compression: str | None = None) -> Path:
    """Write (h, w[, c]) pixels atomically, in the format of the file's extension (uint8 /
    uint16 PNG, float EXR); ``channels``: channel names (EXR)."""
    # local import: not loaded for --help
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    px = np.ascontiguousarray(pixels)
    if px.ndim == 2:
        px = px[..., None]
    h, w, c = px.shape
    kind = {np.dtype(np.uint8): "uint8", np.dtype(np.uint16): "uint16",
            np.dtype(np.float32): "float"}.get(px.dtype)
    if kind is None:
        raise InputError(f"{path}: cannot write {px.dtype} pixels")
    spec = oiio.ImageSpec(w, h, c, kind)
    if channels:
        spec.channelnames = tuple(channels)
    if compression:
        spec.attribute("compression", compression)
    return _write_atomic(path, spec, px)


def write_frame(path, frame, fmt: str = "png", exposure: float = 0.0,
                tonemap_method: str = "aces") -> Path:
    """Write a rendered frame (views.frame.Frame) atomically: PNG (8-bit sRGB, tone-mapped) or
    EXR (float RGBA + Z = frame.depth_expected, scene-linear, exposure applied)."""
    # local import: not loaded for --help
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = frame.rgb
    h, w = rgb.shape[:2]
    if fmt == "png":
        pixels = display_uint8(rgb, exposure, tonemap_method)
        spec = oiio.ImageSpec(w, h, 3, "uint8")
    elif fmt == "exr":
        pixels = np.concatenate([rgb * (2.0 ** exposure), frame.alpha[..., None],
                                 frame.depth_expected[..., None]], axis=2).astype(np.float32)
        spec = oiio.ImageSpec(w, h, 5, "float")
        spec.channelnames = ("R", "G", "B", "A", "Z")
        spec.alpha_channel, spec.z_channel = 3, 4
        spec.attribute("compression", "zip")
    else:
        raise InputError(f"unknown image format {fmt!r}; choose png or exr")
    return _write_atomic(path, spec, np.ascontiguousarray(pixels))


def _write_atomic(path: Path, spec, px: np.ndarray) -> Path:
    """Write ``px`` with OpenImageIO ``spec`` to a temporary file beside ``path``, then rename
    it over ``path`` (a reader never sees half an image); one InputError line on failure."""
    # local import: not loaded for --help
    import OpenImageIO as oiio

    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None or not out.open(str(tmp), spec):
        raise InputError(f"{path}: cannot write image: {oiio.geterror()}")
    try:
        ok = out.write_image(px)
    finally:
        out.close()
    if not ok:
        tmp.unlink(missing_ok=True)
        raise InputError(f"{path}: writing failed: {out.geterror()}")
    os.replace(tmp, path)
    return path
