"""Image filters for the priors: O(1)-per-pixel box filter and the guided filter
(He, Sun, Tang 2010), self-guided per channel (edge-preserving smoothing)."""
from __future__ import annotations

import torch


def box_filter(img: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over the (2r+1)^2 window clipped to the image, for (H, W) or (H, W, C), via
    summed-area tables (float64 accumulation so large images stay exact enough)."""
    if r <= 0:
        return img
    squeeze = img.ndim == 2
    x = img[..., None] if squeeze else img
    H, W = x.shape[:2]
    s = torch.zeros(H + 1, W + 1, x.shape[2], dtype=torch.float64, device=x.device)
    s[1:, 1:] = x.double().cumsum(0).cumsum(1)
    i = torch.arange(H, device=x.device)
    j = torch.arange(W, device=x.device)
    i0, i1 = (i - r).clamp(0, H), (i + r + 1).clamp(0, H)
    j0, j1 = (j - r).clamp(0, W), (j + r + 1).clamp(0, W)
    tot = s[i1][:, j1] - s[i0][:, j1] - s[i1][:, j0] + s[i0][:, j0]
    cnt = ((i1 - i0)[:, None] * (j1 - j0)[None, :]).to(torch.float64)[..., None]
    out = (tot / cnt).to(img.dtype)
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
