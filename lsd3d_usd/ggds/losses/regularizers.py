"""2DGS regularisers computed from the rasteriser's outputs (Huang et al. 2024): normal
consistency between the rendered surfel normals and the normals of the rendered depth map.

The other 2DGS regulariser, depth distortion (sum over a pixel's contributor pairs of
w_i w_j (m_i - m_j)^2, m the NDC-like depth), needs every contributor's depth, so the tile
kernels compute it: rasterize(..., settings=RasterSettings(distortion=True)).distortion per
pixel, with its hand-written backward; GGDS adds GGDSConfig.w_distortion times its image mean."""
from __future__ import annotations

import torch


def depth_normals(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(H,W) camera-z depth → (H,W,3) unit normals in OpenCV camera axes (facing the camera),
    from central differences of the back-projected points; zero on the image border."""
    H, W = depth.shape
    K = K.to(depth.dtype)
    v, u = torch.meshgrid(torch.arange(H, dtype=depth.dtype) + 0.5,
                          torch.arange(W, dtype=depth.dtype) + 0.5, indexing="ij")
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    p = torch.stack([x, y, depth], dim=-1)
    n = torch.zeros_like(p)
    dx = p[1:-1, 2:] - p[1:-1, :-2]
    dy = p[2:, 1:-1] - p[:-2, 1:-1]
    c = torch.cross(dx, dy, dim=-1)
    c = c / c.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # Orient towards the camera (negative z in OpenCV axes looks back at it).
    c = torch.where(c[..., 2:3] > 0, -c, c)
    n[1:-1, 1:-1] = c
    return n


def normal_consistency(rendered_normal: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
                       K: torch.Tensor, min_alpha: float = 0.5) -> torch.Tensor:
    """mean over covered pixels of 1 - cos(n_rendered, n_from_depth), camera axes.
    `rendered_normal` is the un-normalised alpha-weighted sum the rasteriser returns."""
    nd = depth_normals(depth, K).detach()  # as 2DGS: the depth normal is the target
    nr = rendered_normal / rendered_normal.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    mask = (alpha > min_alpha) & (nd.norm(dim=-1) > 0.5)
    if not mask.any():
        return rendered_normal.sum() * 0.0
    cos = (nr * nd).sum(-1)
    return (1.0 - cos)[mask].mean()
