"""Real spherical harmonics colour, degree 0-3 (3DGS convention), in torch.

colour(d) = max(0, 0.5 + sum_lm c_lm * Y_lm(d)), coefficients ordered by degree l then
m = -l..l, d the unit direction from the camera centre to the surfel (world space).
Evaluated in torch so gradients reach the coefficients (and the positions, through d).
"""
from __future__ import annotations

import torch

from lsd3d_usd.shmath import C0, C1, C2, C3  # noqa: F401  (the real SH constants)


def sh_degree_of(k: int) -> int:
    """Degree of a coefficient count K = (deg+1)^2."""
    for deg in range(4):
        if (deg + 1) ** 2 == k:
            return deg
    raise ValueError(f"SH coefficient count {k} is not (deg+1)^2 for deg 0-3")


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """(N,3) unit directions -> (N,(degree+1)^2) basis values."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy),
                C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Colour (N,3) from coefficients (N,K,3) seen along unit dirs (N,3), using the first
    (degree+1)^2 coefficients."""
    k = (degree + 1) ** 2
    basis = sh_basis(dirs, degree).to(sh.dtype)
    rgb = (basis.unsqueeze(-1) * sh[:, :k, :]).sum(dim=1) + 0.5
    return rgb.clamp_min(0.0)
