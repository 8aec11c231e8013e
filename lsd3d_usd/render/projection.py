"""Per-surfel projection for the 2DGS rasteriser: camera-relative transform, the ray-splat
homography, culling and exact conservative screen bounds.

A surfel is the disk P(u, v) = p + s_u*u*t_u + s_v*v*t_v with Gaussian G = exp(-(u^2+v^2)/2).
With M = K [s_u t_u | s_v t_v | p] (camera space, 3x3) a pixel (x, y) sees the plane point
(u, v, 1) ~ h_u x h_v, h_u = x*m2 - m0, h_v = y*m2 - m1 (Huang et al. 2024, the two
homogeneous planes). Written relative to the projected centre (xb, yb), dx = x - xb,
dy = y - yb, and divided by D (the value at the centre), the solution is a homography:

    U = a1*dx + a2*dy,  V = b1*dx + b2*dy,  W = 1 + ex*dx + ey*dy
    u = U/W, v = V/W, intersection depth z = zc/W

so the kernels evaluate 9 numbers per surfel (xb, yb, zc, a1, a2, b1, b2, ex, ey); the
reference renderer (reference.py) computes the same by explicit ray-plane intersection.

Positions are made camera-relative in float64 (p - camera centre) before anything else, so a
scene 10 km from the origin renders as accurately as one at the origin.
"""
from __future__ import annotations

import math

import numpy as np
import torch

# Scales below this (metres) are clamped: a zero-scale surfel then has a huge rho_3d and shows
# as the low-pass blob only, with finite numbers everywhere.
S_MIN = 1e-8
# Surfels whose plane contains the view ray through their centre to within this cosine are
# culled (exactly edge-on: the disk has no area on screen; the homography is singular).
EDGE_COS = 1e-6
# Low-pass filter: rho_2d = |pixel - centre|^2 / sigma^2, sigma = sqrt(2)/2 px (2DGS).
LOWPASS_INV_SIGMA2 = 2.0
# Layout of the packed per-surfel kernel parameters.
PARAM_NAMES = ("xb", "yb", "zc", "a1", "a2", "b1", "b2", "ex", "ey", "opacity",
               "r", "g", "b", "nx", "ny", "nz")
NPARAM = len(PARAM_NAMES)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N,4) xyzw quaternions (normalised here) -> (N,3,3) rotations; column j = local axis j."""
    q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-30)
    x, y, z, w = q.unbind(1)
    r = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=1)
    return r.reshape(-1, 3, 3)


def camera_frame(viewmat: torch.Tensor):
    """float64 (R (3,3), camera centre C (3,)) of a world->camera 4x4 matrix."""
    vm = viewmat.detach().to(torch.float64)
    rot, t = vm[:3, :3], vm[:3, 3]
    centre = -torch.linalg.solve(rot, t)
    return rot, centre


def camera_space(means, quats, scales, viewmat):
    """float64 camera-space centre p_c, scaled tangents a_u, a_v and unit normal n (N,3) each."""
    rot_c, centre = camera_frame(viewmat)
    p_c = (means.to(torch.float64) - centre) @ rot_c.T
    rot = quat_to_rotmat(quats.to(torch.float64))
    axes = torch.einsum("ij,njk->nik", rot_c, rot)  # camera-space local axes (columns)
    s = scales.to(torch.float64).clamp_min(S_MIN)
    a_u = axes[:, :, 0] * s[:, :1]
    a_v = axes[:, :, 1] * s[:, 1:2]
    return p_c, a_u, a_v, axes[:, :, 2]


def homography_rows(p_c, a_u, a_v, K):
    """M = K [a_u | a_v | p_c]: rows m0, m1, m2 as (N,3) tensors (u, v, w components)."""
    cols = torch.stack([a_u, a_v, p_c], dim=2)  # (N,3,3), columns
    m = torch.einsum("ij,njk->nik", K.to(torch.float64), cols)
    return m[:, 0, :], m[:, 1, :], m[:, 2, :]


def kernel_params(p_c, a_u, a_v, normal, K):
    """The 9 geometric kernel parameters (N,9) (float64, differentiable) and the oriented
    normal (N,3) facing the camera. Call only on non-culled surfels (zc >= near, not edge-on)."""
    m0, m1, m2 = homography_rows(p_c, a_u, a_v, K)
    zc = m2[:, 2]
    xb = m0[:, 2] / zc
    yb = m1[:, 2] / zc
    hu = xb[:, None] * m2[:, :2] - m0[:, :2]  # w component is 0 by construction
    hv = yb[:, None] * m2[:, :2] - m1[:, :2]
    d = hu[:, 0] * hv[:, 1] - hu[:, 1] * hv[:, 0]
    a1 = -zc * hv[:, 1] / d
    a2 = zc * hu[:, 1] / d
    b1 = zc * hv[:, 0] / d
    b2 = -zc * hu[:, 0] / d
    ex = (m2[:, 0] * hv[:, 1] - m2[:, 1] * hv[:, 0]) / d
    ey = (m2[:, 1] * hu[:, 0] - m2[:, 0] * hu[:, 1]) / d
    flip = ((normal * p_c).sum(1, keepdim=True) > 0).to(normal.dtype)
    n_facing = normal * (1 - 2 * flip)
    geo = torch.stack([xb, yb, zc, a1, a2, b1, b2, ex, ey], dim=1)
    return geo, n_facing


def cull_mask(p_c, normal, opacities, near, far, alpha_min):
    """Surfels that can contribute: centre in [near, far], not exactly edge-on, opacity >= alpha_min."""
    zc = p_c[:, 2]
    cos = (normal * p_c).sum(1).abs() / p_c.norm(dim=1).clamp_min(1e-300)
    return (zc >= near) & (zc <= far) & (cos >= EDGE_COS) & (opacities.to(torch.float64) >= alpha_min)


def bound_radius(opacities: np.ndarray, alpha_min: float, bound_sigma: float | None) -> np.ndarray:
    """Radius r (in sigma units, on rho = r^2) beyond which opacity*G < alpha_min.

    None: opacity-aware, exact (r^2 = 2 ln(opacity/alpha_min)); a number: that fixed k-sigma
    radius (faster, not conservative for opaque surfels: an accuracy setting)."""
    if bound_sigma is not None:
        return np.full(opacities.shape, float(bound_sigma))
    ratio = np.maximum(opacities.astype(np.float64) / alpha_min, 1.0)
    return np.sqrt(2.0 * np.log(ratio))


def _arc_extremes(num, den, r, near):
    """min/max over the disk {|q| <= r, den.q >= near} of (num.q)/(den.q), q = (u, v, 1).

    x(theta) on the circle is (A + B cos + C sin)/(D + E cos + F sin); it is linear-fractional,
    so its extremes over the convex region are at extreme points: stationary points on the arc
    ((AE-BD) sin + (CD-AF) cos = BF - CE) or where the arc meets the near plane. Exact."""
    A, B, C = num[:, 2], r * num[:, 0], r * num[:, 1]
    D, E, F = den[:, 2], r * den[:, 0], r * den[:, 1]
    a, b, c = A * E - B * D, C * D - A * F, B * F - C * E
    thetas = []
    rr = np.hypot(a, b)
    phi = np.arctan2(a, b)
    off = np.arccos(np.clip(c / np.maximum(rr, 1e-300), -1.0, 1.0))
    thetas += [phi + off, phi - off]
    r2 = np.hypot(E, F)
    phi2 = np.arctan2(F, E)
    cosarg = (near - D) / np.maximum(r2, 1e-300)
    has_chord = np.abs(cosarg) <= 1.0
    off2 = np.arccos(np.clip(cosarg, -1.0, 1.0))
    chord = [phi2 + off2, phi2 - off2]
    thetas += [np.zeros_like(A), np.full_like(A, np.pi)]  # any valid point is a safe candidate
    lo = np.full(A.shape, np.inf)
    hi = np.full(A.shape, -np.inf)
    tol = 1e-9 * (np.abs(D) + r2)
    for i, th in enumerate(thetas + chord):
        ct, st = np.cos(th), np.sin(th)
        z = D + E * ct + F * st
        ok = z >= near - tol
        if i >= len(thetas):
            ok &= has_chord
        z = np.maximum(z, near * 0.5)
        x = (A + B * ct + C * st) / z
        lo = np.where(ok, np.minimum(lo, x), lo)
        hi = np.where(ok, np.maximum(hi, x), hi)
    return lo, hi


def screen_bounds(p_c, a_u, a_v, K, opacities, *, near, alpha_min, bound_sigma=None):
    """Conservative pixel-coordinate AABBs (N,4) [xmin, xmax, ymin, ymax] (float64 numpy) of all
    pixels where a surfel can reach alpha >= alpha_min: the exact bound of the r-sigma disk
    clipped at the near plane, united with the low-pass filter's disk around the centre."""
    with torch.no_grad():
        m0, m1, m2 = (m.cpu().numpy() for m in homography_rows(p_c, a_u, a_v, K))
    op = opacities.detach().cpu().numpy()
    r = bound_radius(op, alpha_min, bound_sigma)
    xlo, xhi = _arc_extremes(m0, m2, r, near)
    ylo, yhi = _arc_extremes(m1, m2, r, near)
    zc = m2[:, 2]
    xb, yb = m0[:, 2] / zc, m1[:, 2] / zc
    rl = r / math.sqrt(LOWPASS_INV_SIGMA2)
    b = np.stack([np.minimum(xlo, xb - rl), np.maximum(xhi, xb + rl),
                  np.minimum(ylo, yb - rl), np.maximum(yhi, yb + rl)], axis=1)
    # margin for float32 evaluation in the kernels
    pad = 1e-3 + 1e-6 * np.abs(b)
    b[:, 0] -= pad[:, 0]
    b[:, 1] += pad[:, 1]
    b[:, 2] -= pad[:, 2]
    b[:, 3] += pad[:, 3]
    return b


def pixel_rects(bounds: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel index ranges (N,4) int64 [i0, i1, j0, j1] inclusive whose centres (i+0.5) lie in the
    bounds, clipped to the image; empty when i0 > i1 or j0 > j1."""
    with np.errstate(invalid="ignore"):
        lo_x = np.ceil(np.nan_to_num(bounds[:, 0], nan=np.inf, posinf=1e9, neginf=-1e9) - 0.5)
        hi_x = np.floor(np.nan_to_num(bounds[:, 1], nan=-np.inf, posinf=1e9, neginf=-1e9) - 0.5)
        lo_y = np.ceil(np.nan_to_num(bounds[:, 2], nan=np.inf, posinf=1e9, neginf=-1e9) - 0.5)
        hi_y = np.floor(np.nan_to_num(bounds[:, 3], nan=-np.inf, posinf=1e9, neginf=-1e9) - 0.5)
    rect = np.stack([np.clip(lo_x, 0, width), np.clip(hi_x, -1, width - 1),
                     np.clip(lo_y, 0, height), np.clip(hi_y, -1, height - 1)], axis=1)
    return rect.astype(np.int64)
