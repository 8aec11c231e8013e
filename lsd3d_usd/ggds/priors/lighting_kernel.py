"""The procedural prior's lighting of its surface in one numba pass per pixel.

``ProceduralPrior.render_reference`` is the reference: torch, a whole-image temporary per
operation (~40 ms of a 960×540 target). This kernel computes the same per covered pixel —
the normal turned to face the camera, Lambert under the sun (times its visibility) and the
sky's irradiance SH, Schlick's Fresnel, the reflection direction and weight of the sky, and
the normalised Blinn-Phong sun lobe — in float32 as the reference does, within float32
rounding of it but for the sun lobe's power: (n·h)^alpha with alpha up to 2000 multiplies a
rounding of n·h by alpha, so near-mirror highlights differ by up to ~5e-4 of their value
(roughness 0.02), 1e-5 at 0.15; tests/test_ggds_priors_surface.py. The sky along the
reflection, the fog, the background and the exposure stay with the caller: the sky is the
env's own lookup. The SH constants (shmath) are compiled in: numba's cache watches this
file only.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from lsd3d_usd.jitopts import run_in_slices
from lsd3d_usd.shmath import C0, C1, C2

f32 = np.float32
MIN_SLICE = 4096      # pixels per thread's slice, at least


@njit(cache=True, inline="always")
def _unit(x, y, z):
    """torch.nn.functional.normalize of one float32 3-vector."""
    d = max(f32(math.sqrt(x * x + y * y + z * z)), f32(1e-12))
    return x / d, y / d, z / d


@njit(cache=True, nogil=True)
def _light(surf, valid, view, normal, vis, sun, e_sun, sh, col, refl):
    """Per pixel k (covered: valid[k]): col[k] = the diffuse and sun-lobe radiance of the
    surface surf[k] (albedo, spec, roughness, mirror), refl[k] = (reflected direction, weight
    of the sky seen along it)."""
    pi = f32(math.pi)
    for k in range(surf.shape[0]):
        if not valid[k]:
            continue
        vx, vy, vz = _unit(view[k, 0], view[k, 1], view[k, 2])
        nx, ny, nz = _unit(normal[k, 0], normal[k, 1], normal[k, 2])
        if nx * vx + ny * vy + nz * vz > 0:       # face the camera
            nx, ny, nz = -nx, -ny, -nz
        ndl = max(nx * sun[0] + ny * sun[1] + nz * sun[2], f32(0.0)) * vis[k]
        # the sky's irradiance at n: its SH (degrees 0-2, shmath.sh_basis9) times sh (9, 3)
        b1, b2, b3 = -f32(C1) * ny, f32(C1) * nz, -f32(C1) * nx
        b4, b5 = f32(C2[0]) * nx * ny, f32(C2[1]) * ny * nz
        b6 = f32(C2[2]) * (f32(2.0) * nz * nz - nx * nx - ny * ny)
        b7, b8 = f32(C2[3]) * nx * nz, f32(C2[4]) * (nx * nx - ny * ny)
        vn = vx * nx + vy * ny + vz * nz
        cos_v = min(max(-vn, f32(0.0)), f32(1.0))
        spec, rough, mirror = surf[k, 3], surf[k, 4], surf[k, 5]
        F = spec + (f32(1.0) - spec) * (f32(1.0) - cos_v) ** 5
        rx, ry, rz = vx - f32(2.0) * vn * nx, vy - f32(2.0) * vn * ny, vz - f32(2.0) * vn * nz
        g = f32(1.0) - rough
        refl[k, 0], refl[k, 1], refl[k, 2] = rx, ry, rz
        refl[k, 3] = F * max(mirror, g * g)
        hx, hy, hz = _unit(sun[0] - vx, sun[1] - vy, sun[2] - vz)
        alpha = min(max(f32(2.0) / (rough * rough) - f32(2.0), f32(1.0)), f32(2000.0))
        nh = max(nx * hx + ny * hy + nz * hz, f32(0.0))
        lobe = (alpha + f32(8.0)) / (f32(8.0) * pi) * nh ** alpha
        fl = F * lobe * ndl
        for c in range(3):
            e_sky = (f32(C0) * sh[0, c] + b1 * sh[1, c] + b2 * sh[2, c] + b3 * sh[3, c]
                     + b4 * sh[4, c] + b5 * sh[5, c] + b6 * sh[6, c] + b7 * sh[7, c]
                     + b8 * sh[8, c])
            e = ndl * e_sun[c] + max(e_sky, f32(0.0))
            col[k, c] = surf[k, c] / pi * e + fl * e_sun[c]


def light(surf, valid, view, normal, vis, sun, e_sun, sh):
    """(col (P, 3), refl (P, 4)) float32 of P pixels (see _light; uncovered pixels' rows are
    left as they are: zeros): surf (P, 6) from surface_kernel.surface_properties, valid (P,),
    view directions and normals (P, 3, any length), sun visibility (P,), the unit direction
    towards the sun (3,), the sun's irradiance (3,) and the sky's irradiance SH (9, 3)."""
    P = len(surf)
    surf = np.ascontiguousarray(surf, np.float32).reshape(P, 6)
    valid = np.ascontiguousarray(valid, np.bool_).reshape(P)
    view = np.ascontiguousarray(view, np.float32).reshape(P, 3)
    normal = np.ascontiguousarray(normal, np.float32).reshape(P, 3)
    vis = np.ascontiguousarray(vis, np.float32).reshape(P)
    sun = np.ascontiguousarray(sun, np.float32).reshape(3)
    e_sun = np.ascontiguousarray(e_sun, np.float32).reshape(3)
    sh = np.ascontiguousarray(sh, np.float32).reshape(9, 3)
    col = np.zeros((P, 3), np.float32)
    refl = np.zeros((P, 4), np.float32)
    run_in_slices(_light, P, (surf, valid, view, normal, vis), (sun, e_sun, sh), (col, refl),
                  MIN_SLICE)
    return col, refl
