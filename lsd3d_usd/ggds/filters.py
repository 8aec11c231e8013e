"""Image filters for the priors: box filter (clipped windows) and the guided filter
(He, Sun, Tang 2010), self-guided per channel (edge-preserving smoothing)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def box_filter(img: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over the (2r+1)^2 window clipped to the image, for (H, W) or (H, W, C)."""
    if r <= 0:
        return img
    squeeze = img.ndim == 2
    x = img[..., None] if squeeze else img
    y = F.avg_pool2d(x.permute(2, 0, 1)[None], 2 * r + 1, stride=1, padding=r, count_include_pad=False)
    out = y[0].permute(1, 2, 0)
    return out[..., 0] if squeeze else out


def guided_filter(x: torch.Tensor, r: int, eps: float, guide: torch.Tensor | None = None) -> torch.Tensor:
    """Guided filter of x (H, W, C) with a per-channel guide (default: x itself).
    q = mean(a) * I + mean(b), a = cov(I, x) / (var(I) + eps), b = mean(x) - a mean(I).
    eps -> 0 or r = 0 returns x; large eps tends to the box mean."""
    if r <= 0:
        return x
    I = x if guide is None else guide
    mI = box_filter(I, r)
    mx = box_filter(x, r)
    cov = box_filter(I * x, r) - mI * mx
    var = box_filter(I * I, r) - mI * mI
    a = cov / (var + eps)
    b = mx - a * mI
    return box_filter(a, r) * I + box_filter(b, r)
