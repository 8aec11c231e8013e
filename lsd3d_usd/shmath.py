"""Real spherical harmonics (3DGS ordering and signs: degree l, then m = -l..l), the one
definition of their constants and of the order-2 basis, for numpy arrays and torch tensors
alike. colour(d) = 0.5 + sum_k c_k Y_k(d) for surfels; E(n) = sum_k c_k Y_k(n) for irradiance."""
from __future__ import annotations

import numpy as np
import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
      -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis9(d):
    """(..., 3) unit directions -> (..., 9) real SH values of degrees 0-2 (numpy or torch)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    c0 = x * 0 + C0
    terms = [c0, -C1 * y, C1 * z, -C1 * x,
             C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * z * z - x * x - y * y),
             C2[3] * x * z, C2[4] * (x * x - y * y)]
    if hasattr(d, "detach"):
        return torch.stack(terms, dim=-1)
    return np.stack(terms, axis=-1)
