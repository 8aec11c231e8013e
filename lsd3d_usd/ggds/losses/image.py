"""GGDS image and geometry losses (torch, differentiable, masked means that are 0 on an empty mask).

Shapes: images (H, W, C); depth / mask (H, W); normals (H, W, 3). A mask is a bool or
{0, 1} float tensor; None means every pixel. Every masked mean divides by
max(count, 1), so an empty mask gives exactly 0 with a valid (zero) gradient, never NaN.

omega(t), the weight of the image terms at noise level t; the choice, by `kind`:
  "uniform" (default): 1. The procedural prior's target does not get noisier with t, only
      more re-synthesised, so every level is equally trustworthy.
  "sds": 2 sqrt(ab (1 - ab)) with ab = alpha_bar(t). The SDS gradient with DreamFusion's
      weight w = 1 - ab, written in image space (eps_hat - eps = sqrt(ab / (1 - ab)) (x - x0_hat)
      up to the encoder Jacobian), is (1 - ab) sqrt(ab / (1 - ab)) (x - x0_hat)
      = sqrt(ab (1 - ab)) (x - x0_hat); normalised to peak 1 at ab = 1/2. Recommended with
      a diffusion prior, whose high-t targets are only loosely tied to the render.
  "signal": sqrt(ab): trust the target in proportion to the signal of x left in z_t.
"""
from __future__ import annotations

import math

import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.settings import OMEGA_KINDS
from lsd3d_usd.ggds.priors.ddim import DDIMSchedule

DEFAULT_SCHEDULE = DDIMSchedule()   # SD 1.x/2.x scaled-linear betas (ggds/priors/ddim.py)


def omega(t: float, kind: str = "uniform", schedule: DDIMSchedule | None = None) -> float:
    """Weight of the image losses at noise level t in [0, 1] (see module doc)."""
    if kind not in OMEGA_KINDS:
        raise InputError(f"unknown omega weighting {kind!r}; choose one of {', '.join(OMEGA_KINDS)}")
    if kind == "uniform":
        return 1.0
    schedule = DEFAULT_SCHEDULE if schedule is None else schedule
    ab = schedule.alpha_bar(schedule.level(t))
    if kind == "sds":
        return 2.0 * math.sqrt(ab * (1.0 - ab))
    return math.sqrt(ab)


def _mask(mask, shape_hw, device) -> torch.Tensor:
    if mask is None:
        return torch.ones(shape_hw, device=device)
    m = mask.to(device=device, dtype=torch.float32)
    if tuple(m.shape) != tuple(shape_hw):
        raise ValueError(f"mask is {tuple(m.shape)}, expected {tuple(shape_hw)}")
    return m


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of (H, W) or (H, W, C) values over mask (H, W); channels averaged; 0 if empty."""
    if values.ndim == mask.ndim + 1:
        values = values.mean(dim=-1)
    # where() (not multiplication) so NaN/inf outside the mask cannot leak into the sum
    v = torch.where(mask > 0, values * mask, torch.zeros_like(values))
    return v.sum() / mask.sum().clamp_min(1.0)


def l1_loss(x: torch.Tensor, target: torch.Tensor, mask=None) -> torch.Tensor:
    """Mean |x - target| over masked pixels and channels."""
    if x.shape != target.shape:
        raise ValueError(f"l1_loss: shapes differ {tuple(x.shape)} vs {tuple(target.shape)}")
    return masked_mean((x - target).abs(), _mask(mask, x.shape[:2], x.device))


def tv_loss(x: torch.Tensor, mask=None) -> torch.Tensor:
    """Anisotropic total variation: mean of |x[i+1,j] - x[i,j]| and |x[i,j+1] - x[i,j]| over
    neighbour pairs with both pixels in the mask (channels averaged)."""
    m = _mask(mask, x.shape[:2], x.device)
    if x.ndim == 2:
        x = x[..., None]
    dy = (x[1:] - x[:-1]).abs().mean(-1)
    dx = (x[:, 1:] - x[:, :-1]).abs().mean(-1)
    my = m[1:] * m[:-1]
    mx = m[:, 1:] * m[:, :-1]
    total = torch.where(my > 0, dy * my, torch.zeros_like(dy)).sum() + \
        torch.where(mx > 0, dx * mx, torch.zeros_like(dx)).sum()
    return total / (my.sum() + mx.sum()).clamp_min(1.0)


def normal_loss(n_render: torch.Tensor, n_proxy: torch.Tensor, mask=None,
                two_sided: bool = False, eps: float = 1e-8) -> torch.Tensor:
    """Mean of 1 - cos(angle) between rendered and proxy normals over the mask.

    Both are normalised (rendered normals are alpha-blended, hence shorter than 1); pixels
    where either has (near) zero length are left out. two_sided: 1 - |cos| (for normals
    whose sign is arbitrary)."""
    if n_render.shape != n_proxy.shape or n_render.shape[-1] != 3:
        raise ValueError(f"normal_loss: need matching (H, W, 3), got {tuple(n_render.shape)} vs {tuple(n_proxy.shape)}")
    m = _mask(mask, n_render.shape[:2], n_render.device)
    lr = (n_render * n_render).sum(-1)
    lp = (n_proxy * n_proxy).sum(-1)
    ok = (lr > eps) & (lp > eps) & torch.isfinite(lr) & torch.isfinite(lp)
    m = m * ok
    cos = (n_render * n_proxy).sum(-1) / torch.sqrt(torch.where(ok, lr * lp, torch.ones_like(lr)))
    if two_sided:
        cos = cos.abs()
    return masked_mean(1.0 - cos.clamp(-1.0, 1.0), m)


def disparity_loss(depth_render: torch.Tensor, depth_proxy: torch.Tensor, mask=None,
                   relative: bool = True, min_depth: float = 1e-3) -> torch.Tensor:
    """L1 between disparities 1/depth of the render and the proxy over valid pixels.

    relative=True (default): |1/d_r - 1/d_p| / (1/d_p) = |d_p / d_r - 1|, the relative depth
    error, so a 1 % error counts the same at 5 m and at 80 m and the loss does not depend on
    the scene's scale; False: absolute disparity difference in 1/m (weights near geometry more).
    Pixels where either depth is non-finite or below min_depth (render: no surfel there;
    proxy: sky) are left out."""
    if depth_render.shape != depth_proxy.shape:
        raise ValueError(f"disparity_loss: shapes differ {tuple(depth_render.shape)} vs {tuple(depth_proxy.shape)}")
    m = _mask(mask, depth_render.shape, depth_render.device)
    ok = torch.isfinite(depth_render) & torch.isfinite(depth_proxy) & \
        (depth_render > min_depth) & (depth_proxy > min_depth)
    m = m * ok
    one = torch.ones_like(depth_render)
    dr = torch.where(ok, depth_render, one)
    dp = torch.where(ok, depth_proxy, one).to(dr.dtype)
    diff = (1.0 / dr - 1.0 / dp).abs()
    if relative:
        diff = diff * dp
    return masked_mean(diff, m)
