"""Order-2 spherical-harmonic irradiance of an environment map (Ramamoorthi & Hanrahan 2001).

Basis: the real SH of the surfel contract (3DGS ordering and signs: l = 0, 1, 2 and
m = -l..l), evaluated on world directions (Z up). `sh_irradiance` returns irradiance
coefficients, already multiplied by the clamped-cosine factors A_0 = pi, A_1 = 2 pi / 3,
A_2 = pi / 4, so that E(n) = sum_k c_k Y_k(n) (`eval_sh_irradiance`).
"""
from __future__ import annotations

import math

import numpy as np

from lsd3d_usd.env.mapping import pixel_solid_angles

from lsd3d_usd.shmath import C0, C1, C2, sh_basis9  # noqa: F401

BAND_FACTORS = np.array([math.pi] + [2.0 * math.pi / 3.0] * 3 + [math.pi / 4.0] * 5)


def sh_basis(dirs: np.ndarray) -> np.ndarray:
    """(..., 3) unit directions -> (..., 9) real SH values, 3DGS ordering and signs."""
    return sh_basis9(np.asarray(dirs, dtype=np.float64))


def sh_project(image: np.ndarray) -> np.ndarray:
    """Radiance SH coefficients (9, C) of a latlong map (H, W, C): solid-angle weighted sum."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[1] != 2 * img.shape[0]:
        raise ValueError(f"sh_project: need a (H, 2H, C) latlong image, got {img.shape}")
    H, W, C = img.shape
    w = pixel_solid_angles(W, H)
    out = np.zeros((9, C))
    step = max(1, 65536 // W)                                   # row blocks: bounded memory
    for r0 in range(0, H, step):
        r1 = min(H, r0 + step)
        Y = sh_basis(_rows(W, H, r0, r1)).reshape(-1, 9)
        L = (img[r0:r1] * w[r0:r1, None, None]).reshape(-1, C)
        out += Y.T @ L
    return out


def _rows(W, H, r0, r1):
    """Pixel-centre directions of rows r0..r1 (same convention as mapping.pixel_directions)."""
    u = (np.arange(W) + 0.5) / W
    v = (np.arange(r0, r1) + 0.5) / H
    lon = np.pi * (1.0 - 2.0 * u)[None, :]
    lat = np.pi * (0.5 - v)[:, None]
    return np.stack(np.broadcast_arrays(np.cos(lat) * np.sin(lon), -np.cos(lat) * np.cos(lon),
                                        np.sin(lat)), axis=-1)


def sh_irradiance(image: np.ndarray) -> np.ndarray:
    """Irradiance SH coefficients (9, C) of a latlong map; see `eval_sh_irradiance`."""
    return sh_project(image) * BAND_FACTORS[:, None]


def eval_sh_irradiance(coeffs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance E(n) = integral of L(w) max(0, n.w) dw, for (..., 3) unit normals -> (..., C)."""
    c = np.asarray(coeffs, dtype=np.float64)
    if c.shape[0] != 9:
        raise ValueError(f"eval_sh_irradiance: need (9, C) coefficients, got {c.shape}")
    return sh_basis(normals) @ c
