"""Torch lookup of a latlong environment map by direction (for the renderer).

Bilinear, seamless across the longitude wrap (columns wrap modulo W) and at the poles
(above the top row centre the value blends toward the top row's mean, the one value the
pole can have; likewise at the bottom).
Differentiable with respect to the image. Uses the convention of `mapping`
(DomeLight_1, poleAxis Z; top row = zenith; image centre = -Y). Without gradients (the
G-buffer backgrounds and the prior's sky, ~460 lookups of a 480x270 view per GGDS region) a
numba kernel does the same in one pass (float64 inside), 2-3x faster than the torch ops.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from lsd3d_usd.env.exr import read_env
from lsd3d_usd.env.farfield import MIN_DOWN
from lsd3d_usd.jitopts import prange_only


def directions_to_pixel(directions: torch.Tensor, width: int, height: int):
    """(..., 3) -> continuous pixel coordinates (x, y), pixel centres at integer + 0.5."""
    d = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    lon = torch.atan2(d[..., 0], -d[..., 1])
    u = 0.5 - lon / (2 * math.pi)
    v = 0.5 - torch.asin(d[..., 2].clamp(-1.0, 1.0)) / math.pi
    return u * width, v * height


def env_lookup(image: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Radiance (..., C) of latlong `image` (H, W, C) in world `directions` (..., 3)."""
    if image.ndim != 3 or image.shape[0] < 2:
        raise ValueError(f"env_lookup: image must be (H, W, C) with H >= 2, got {tuple(image.shape)}")
    H, W, C = image.shape
    batch = directions.shape[:-1]
    if not (torch.is_grad_enabled() and (image.requires_grad or directions.requires_grad)) \
            and image.device.type == "cpu" and directions.device.type == "cpu" \
            and image.dtype in (torch.float32, torch.float64):
        img = np.ascontiguousarray(image.detach().numpy())
        out = np.empty((int(np.prod(batch, dtype=np.int64)), C), img.dtype)
        _lookup(img, np.ascontiguousarray(directions.detach().reshape(-1, 3).numpy(), img.dtype),
                img[0].mean(0, dtype=np.float64), img[H - 1].mean(0, dtype=np.float64), out)
        return torch.from_numpy(out).reshape(*batch, C)
    d = directions.reshape(-1, 3).to(image.dtype if image.is_floating_point() else torch.float32)
    px, py = directions_to_pixel(d, W, H)
    x = px - 0.5
    y = py - 0.5                                   # in [-0.5, H - 0.5]
    x0f = torch.floor(x)
    fx = (x - x0f).unsqueeze(-1)
    x0 = torch.remainder(x0f.long(), W)
    x1 = torch.remainder(x0 + 1, W)                # longitude wraps
    y0 = torch.floor(y).clamp(0, H - 2)
    fy = (y - y0).clamp(0.0, 1.0).unsqueeze(-1)
    y0 = y0.long()
    flat = image.reshape(H * W, C)
    r0, r1 = y0 * W, (y0 + 1) * W
    out = ((flat[r0 + x0] * (1 - fx) + flat[r0 + x1] * fx) * (1 - fy)
           + (flat[r1 + x0] * (1 - fx) + flat[r1 + x1] * fx) * fy)
    # Between the first/last row centre and the pole, blend toward the pole value (the mean of
    # that row): one value at the pole whatever the azimuth, so the lookup is continuous there.
    wt = (-y / 0.5).clamp(0.0, 1.0).unsqueeze(-1)
    wb = ((y - (H - 1)) / 0.5).clamp(0.0, 1.0).unsqueeze(-1)
    out = out * (1 - wt - wb) + image[0].mean(0) * wt + image[H - 1].mean(0) * wb
    return out.reshape(*batch, C)


def env_lookup_pinhole(image: np.ndarray, width: int, height: int, fx: float, fy: float,
                       cx: float, cy: float, rotation: np.ndarray, world_from_dome: np.ndarray,
                       pole_y: bool = False, far_field=None, camera_z: float | None = None) -> np.ndarray:
    """(height, width, C) radiance of latlong ``image`` (H, W, C) along the rays through the
    pixel centres of a pinhole camera whose world rotation ``rotation`` has the right, down
    and forward directions as columns, in one pass and without (height, width, 3) temporaries:
    the directions of render.camera.pixel_directions, taken into the dome frame
    (world_from_dome^T d; ``pole_y``: then from a Y pole axis to Z), rounded to float32 and
    sampled as env_lookup samples them. ``far_field`` (env.farfield.FarField, in the image's
    units; C == 3): its plane seen from height ``camera_z`` over it, as FarField.apply draws
    it, in the same pass."""
    img = np.ascontiguousarray(image)
    if img.ndim != 3 or img.shape[0] < 2 or img.dtype not in (np.float32, np.float64):
        raise ValueError(f"env_lookup_pinhole: image must be float (H, W, C) with H >= 2, got "
                         f"{img.dtype} {img.shape}")
    H = img.shape[0]
    h, w = int(height), int(width)
    out = np.empty((h * w, img.shape[2]), img.dtype)
    shift, oz, fog = np.zeros(img.shape[2]), 0.0, 0.0
    if far_field is not None:
        if img.shape[2] != 3 or camera_z is None:
            raise ValueError(f"env_lookup_pinhole: a far field needs an RGB image and the "
                             f"camera's height, got {img.shape} and {camera_z}")
        shift = np.asarray(far_field.radiance, np.float64) - np.asarray(far_field.ground, np.float64)
        oz, fog = float(camera_z) - float(far_field.height), max(float(far_field.fog_density), 0.0)
    _lookup_pinhole(img, float(fx), float(fy), float(cx), float(cy),
                    np.ascontiguousarray(rotation, np.float64),
                    np.ascontiguousarray(world_from_dome, np.float64),
                    bool(pole_y), img[0].mean(0, dtype=np.float64), img[H - 1].mean(0, dtype=np.float64),
                    h, w, out, oz, shift, fog)
    return out.reshape(h, w, img.shape[2])


@njit(parallel=prange_only(), cache=True)
def _lookup(image, dirs, top, bottom, out):
    """env_lookup's sampling, point by point (same formulas, float64)."""
    for n in prange(dirs.shape[0]):
        _sample(image, float(dirs[n, 0]), float(dirs[n, 1]), float(dirs[n, 2]), top, bottom, out, n)


@njit(parallel=prange_only(), cache=True)
def _lookup_pinhole(image, fx, fy, cx, cy, R, D, pole_y, top, bottom, h, w, out, oz, shift, fog):
    """env_lookup_pinhole, pixel by pixel into out (h w, C); the far field where oz > 0."""
    for r in prange(h):
        b = (r + 0.5 - cy) / fy
        for col in range(w):
            a = (col + 0.5 - cx) / fx
            # pixel_directions: a R0 + b R1 + R2, normalised
            x = a * R[0, 0] + b * R[0, 1] + R[0, 2]
            y = a * R[1, 0] + b * R[1, 1] + R[1, 2]
            z = a * R[2, 0] + b * R[2, 1] + R[2, 2]
            nrm = math.sqrt(x * x + y * y + z * z)
            x, y, z = x / nrm, y / nrm, z / nrm
            # into the dome frame: d @ world_from_dome
            dx = x * D[0, 0] + y * D[1, 0] + z * D[2, 0]
            dy = x * D[0, 1] + y * D[1, 1] + z * D[2, 1]
            dz = x * D[0, 2] + y * D[1, 2] + z * D[2, 2]
            if pole_y:
                dy, dz = -dz, dy
            n = r * w + col
            _sample(image, float(np.float32(dx)), float(np.float32(dy)), float(np.float32(dz)),
                    top, bottom, out, n)
            if oz > 0.0 and z < -MIN_DOWN:     # env.farfield.FarField.apply
                T = math.exp(-fog * (oz / -z))
                for c in range(out.shape[1]):
                    out[n, c] = max(out[n, c] + shift[c] * T, 0.0)


@njit(cache=True, inline="always")
def _sample(image, x, y, z, top, bottom, out, n):
    """Bilinear latlong sample of ``image`` in direction (x, y, z) into out[n] (float64
    inside; an index, not a row view: views in a parallel loop contend on their refcount)."""
    H, W, C = image.shape
    norm = max(math.sqrt(x * x + y * y + z * z), 1e-12)
    x, y, z = x / norm, y / norm, z / norm
    u = 0.5 - math.atan2(x, -y) / (2 * math.pi)
    v = 0.5 - math.asin(min(max(z, -1.0), 1.0)) / math.pi
    px = u * W - 0.5
    py = v * H - 0.5
    x0f = math.floor(px)
    fx = px - x0f
    x0 = int(x0f) % W
    x1 = (x0 + 1) % W
    y0 = min(max(math.floor(py), 0.0), H - 2.0)
    fy = min(max(py - y0, 0.0), 1.0)
    r0 = int(y0)
    wt = min(max(-py / 0.5, 0.0), 1.0)
    wb = min(max((py - (H - 1)) / 0.5, 0.0), 1.0)
    for c in range(C):
        val = ((image[r0, x0, c] * (1 - fx) + image[r0, x1, c] * fx) * (1 - fy)
               + (image[r0 + 1, x0, c] * (1 - fx) + image[r0 + 1, x1, c] * fx) * fy)
        out[n, c] = val * (1 - wt - wb) + top[c] * wt + bottom[c] * wb


class EnvMap:
    """An environment image as a torch tensor plus its convention; call it with directions."""

    convention = "latlong, DomeLight_1 poleAxis=Z: top row zenith (+Z), centre -Y, u=0.25 +X"

    def __init__(self, image, color_space: str = "lin_rec709", units: str = "kcd/m^2"):
        if isinstance(image, np.ndarray):
            image = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))
        if image.ndim != 3 or image.shape[1] != 2 * image.shape[0]:
            raise ValueError(f"EnvMap: need a (H, 2H, C) latlong image, got {tuple(image.shape)}")
        self.image = image
        self.color_space = color_space
        self.units = units

    @classmethod
    def from_exr(cls, path) -> "EnvMap":
        img, meta = read_env(path)
        return cls(img, color_space=meta.get("lsd3d:colorSpace", "lin_rec709"))

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    def __call__(self, directions: torch.Tensor) -> torch.Tensor:
        return env_lookup(self.image, directions)

    lookup = __call__
