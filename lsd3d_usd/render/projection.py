"""Per-surfel projection for the 2DGS rasteriser: camera-relative transform, the ray-splat
homography, culling and exact conservative screen bounds.

A surfel is the disk P(u, v) = p + s_u*u*t_u + s_v*v*t_v with Gaussian G = exp(-(u^2+v^2)/2).
With M = K [s_u t_u | s_v t_v | p] (camera space, 3x3) a pixel (x, y) sees the plane point
(u, v, 1) ~ h_u x h_v, h_u = x*m2 - m0, h_v = y*m2 - m1 (Huang et al. 2024, the two
homogeneous planes). Written relative to the projected centre (xb, yb), dx = x - xb,
dy = y - yb, and divided by D (the value at the centre), the solution is a homography:

    U = a1*dx + a2*dy,  V = b1*dx + b2*dy,  W = 1 + ex*dx + ey*dy
    u = U/W, v = V/W, intersection depth z = zc/W

so the kernels evaluate 9 numbers per surfel (xb, yb, zc, a1, a2, b1, b2, ex, ey), computed
with their screen bounds by kernels_prep.project (numba); the reference renderer
(reference.py) uses the torch helpers here and explicit ray-plane intersection instead.

Screen bounds (kernels_prep._extent): x(theta) along the circle of radius r (in sigma units) is
linear-fractional. When the whole circle is in front of the near plane its extremes are the
two roots of one quadratic (x is reached iff |A - x D| <= |(x E - B, x F - C)|); otherwise
(kernels_prep._arc) they are at the arc's stationary points or where the arc meets the near
plane. Exact either way, hence conservative.
r^2 = 2 ln(opacity/alpha_min) (opacity-aware), united with the low-pass disk r/sqrt(2) px.

Positions are made camera-relative in float64 (p - camera centre) before anything else, so a
scene 10 km from the origin renders as accurately as one at the origin.
"""
from __future__ import annotations

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


def cull_mask(p_c, normal, opacities, near, far, alpha_min):
    """Surfels that can contribute: centre in [near, far], not exactly edge-on, opacity >= alpha_min."""
    zc = p_c[:, 2]
    cos = (normal * p_c).sum(1).abs() / p_c.norm(dim=1).clamp_min(1e-300)
    return (zc >= near) & (zc <= far) & (cos >= EDGE_COS) & (opacities.to(torch.float64) >= alpha_min)
