"""Equirectangular (latlong) mapping between image coordinates and world directions.

The convention is exactly the one a ``DomeLight_1`` with ``poleAxis = "Z"`` implies
(UsdLux schema docs, which restate the OpenEXR latlong spec):

* OpenEXR, Y up: pixel (min x, min y) has latitude +pi/2, longitude +pi; pixel
  (max x, max y) latitude -pi/2, longitude -pi. Latitude 0 / longitude 0 is +Z,
  longitude +pi/2 is +X, latitude +-pi/2 is +-Y.
* poleAxis "Z": the poles become +-Z and latitude 0 / longitude 0 points to -Y.
  That is the proper rotation (x, y, z) -> (x, -z, y), so longitude +pi/2 stays +X.

Hence, for our Z-up world (x east, y north, z up) and u, v in [0, 1] over the image
width / height (v = 0 is the top row, the zenith)::

    lon = pi * (1 - 2u)          lat = pi * (1/2 - v)
    d   = (cos(lat) sin(lon), -cos(lat) cos(lon), sin(lat))

The image centre (u = 0.5) looks south (-Y), u = 0.25 east (+X), u = 0.75 west (-X),
the left/right edge north (+Y).
"""
from __future__ import annotations

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import check_image_size


def uv_to_direction(uv: np.ndarray) -> np.ndarray:
    """(..., 2) uv in [0, 1] (v = 0 top row) -> (..., 3) unit directions, Z up."""
    uv = np.asarray(uv)
    lon = np.pi * (1.0 - 2.0 * uv[..., 0])
    lat = np.pi * (0.5 - uv[..., 1])
    cl = np.cos(lat)
    return np.stack([cl * np.sin(lon), -cl * np.cos(lon), np.sin(lat)], axis=-1)


def direction_to_uv(dirs: np.ndarray) -> np.ndarray:
    """(..., 3) directions (need not be unit length) -> (..., 2) uv, u in [0, 1)."""
    d = np.asarray(dirs, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1)
    if np.any(n == 0):
        raise ValueError("direction_to_uv: zero-length direction")
    z = np.clip(d[..., 2] / n, -1.0, 1.0)
    lon = np.arctan2(d[..., 0], -d[..., 1])
    u = np.mod(0.5 - lon / (2.0 * np.pi), 1.0)
    v = 0.5 - np.arcsin(z) / np.pi
    return np.stack([u, v], axis=-1)


# Aliases named as in the issue text.
env_direction_to_uv = direction_to_uv


def pixel_directions(width: int, height: int, dtype=np.float32) -> np.ndarray:
    """(H, W, 3) unit directions through the pixel centres of a latlong image."""
    u = (np.arange(width, dtype=np.float64) + 0.5) / width
    v = (np.arange(height, dtype=np.float64) + 0.5) / height
    lon = np.pi * (1.0 - 2.0 * u)
    lat = np.pi * (0.5 - v)
    cl, sl = np.cos(lat)[:, None], np.sin(lat)[:, None]
    out = np.empty((height, width, 3), dtype=dtype)
    out[..., 0] = cl * np.sin(lon)[None, :]
    out[..., 1] = -cl * np.cos(lon)[None, :]
    out[..., 2] = sl
    return out


def pixel_solid_angles(width: int, height: int) -> np.ndarray:
    """(H,) exact solid angle of one pixel in each row (sums to 4 pi over the image)."""
    edges = np.pi * np.arange(height + 1) / height          # polar angle of row edges
    band = np.cos(edges[:-1]) - np.cos(edges[1:])           # 2 pi band area / (2 pi)
    return band * (2.0 * np.pi / width)


def check_resolution(width: int, height: int) -> None:
    if int(width) != width or int(height) != height or width < 8 or height < 4:
        raise InputError(f"environment resolution {width}x{height}: need integers, at least 8x4")
    if width != 2 * height:
        raise InputError(f"environment resolution {width}x{height}: a latlong map must be 2:1 "
                         f"(width = 2 x height), e.g. 2048x1024")
    check_image_size(width, height, "environment resolution")
