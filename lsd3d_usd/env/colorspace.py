"""Colour conversions for the sky (via colour-science), computed once and cached.

Internally the sky is scene-linear Rec.709 (D65); ACEScg output is a Bradford-adapted
matrix from Rec.709, so Rec.709 white stays ACES white. Names follow USD's
``Gf.ColorSpaceNames`` (colour interop forum ids), also used as the OIIO colour space.
"""
from __future__ import annotations

import warnings
from functools import lru_cache

import colour
import numpy as np

USD_NAMES = {"lin_rec709": "lin_rec709_scene", "acescg": "lin_ap1_scene"}


def _colour():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
    return colour


@lru_cache(maxsize=None)
def xyz_to_rec709() -> np.ndarray:
    return np.asarray(_colour().RGB_COLOURSPACES["ITU-R BT.709"].matrix_XYZ_to_RGB, np.float64)


@lru_cache(maxsize=None)
def rec709_to(space: str) -> np.ndarray:
    if space == "lin_rec709":
        return np.eye(3)
    if space == "acescg":
        c = _colour()
        return np.asarray(c.matrix_RGB_to_RGB(c.RGB_COLOURSPACES["ITU-R BT.709"],
                                              c.RGB_COLOURSPACES["ACEScg"],
                                              chromatic_adaptation_transform="Bradford"), np.float64)
    raise ValueError(f"unknown colour space {space!r}")


@lru_cache(maxsize=None)
def chromaticities(space: str) -> tuple[float, ...]:
    """EXR `chromaticities` attribute: red xy, green xy, blue xy, white xy."""
    cs = _colour().RGB_COLOURSPACES["ITU-R BT.709" if space == "lin_rec709" else "ACEScg"]
    p = np.asarray(cs.primaries, np.float64).ravel().tolist()
    return tuple(p + list(np.asarray(cs.whitepoint, np.float64)))


@lru_cache(maxsize=None)
def cmfs_1931():
    """(wavelengths nm, (N,3) CIE 1931 2-degree colour matching functions), 360-830 nm @ 1 nm."""
    c = _colour().MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    return np.asarray(c.wavelengths, np.float64), np.asarray(c.values, np.float64)


@lru_cache(maxsize=None)
def daylight_rgb(cct: float) -> tuple[float, float, float]:
    """Linear Rec.709 colour of CIE daylight of a correlated colour temperature, luminance 1."""
    c = _colour()
    x, y = c.temperature.CCT_to_xy_CIE_D(cct)
    xyz = np.array([x / y, 1.0, (1 - x - y) / y])
    return tuple(float(v) for v in xyz_to_rec709() @ xyz)


def xyY_to_rec709(x: np.ndarray, y: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Vectorised CIE xyY -> linear Rec.709 RGB, (..., 3) float32."""
    y = np.maximum(y, 1e-6)
    s = Y / y
    X = x * s
    Z = (1.0 - x - y) * s
    M = xyz_to_rec709().astype(np.float32)
    out = np.empty(Y.shape + (3,), np.float32)
    for i in range(3):
        out[..., i] = M[i, 0] * X + M[i, 1] * Y + M[i, 2] * Z
    return out
