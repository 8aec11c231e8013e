"""Anti-aliasing of the surfels: a per-surfel frequency limit from the sampling rate of the
training views (the 3D smoothing filter of Mip-Splatting, Yu et al. CVPR 2024, for 2D disks).

A surfel trained only by views whose pixels are ≥ T metres wide where it sits can hold no
detail finer than T: nothing in the training images constrains it. Without a limit, disks
shrink below the training pixels (the rasteriser's screen-space low-pass still shows them
one pixel wide), and a render closer or at a higher resolution shows them as separate dots —
a fish-scale / moiré pattern. The filter convolves every disk with an isotropic Gaussian of
standard deviation σ_f = k·T in its own plane: for a disk with in-plane standard deviations
(s_u, s_v) that is again a disk, with

    s'_u² = s_u² + σ_f²,  s'_v² = s_v² + σ_f²,  opacity' = opacity · s_u s_v / (s'_u s'_v)

(the opacity factor keeps the disk's integral, √(det Σ / det Σ') in 2D, as Mip-Splatting's
3D filter keeps the 3D one). It is applied to the activated parameters before every render,
so the optimiser learns the unfiltered values and the gradients pass through it; the scene
layer holds the filtered values (the filter is fixed per surfel, so baking it in renders the
same pictures in any ParticleField renderer).

T is the finest view's pixel footprint, ggds/sampling.footprint: min over the training
cameras that have the surfel in view of depth / focal length.
"""
from __future__ import annotations

import numpy as np
import torch

from lsd3d_usd.conditioning.visibility import footprint


def filter_sigma(positions: np.ndarray, cameras, k: float, *, margin_frac: float = 0.15,
                 fallback: str = "max") -> np.ndarray:
    """(N,) σ_f = k · (finest training footprint) in metres, float32. Surfels no camera sees
    take the largest σ_f of the seen ones (``fallback="max"``; Mip-Splatting does the same:
    they get no detail from the views, so they may as well be smooth) or 0 (``"zero"``).
    ``margin_frac``: the image is grown by this fraction of its width for the in-view test (a
    surfel just outside still reaches into the image with its disk)."""
    cams = list(cameras)
    if k <= 0 or not cams or len(positions) == 0:
        return np.zeros(len(positions), np.float32)
    margin = margin_frac * max(c.width for c in cams)
    t = footprint(positions, cams, margin=margin)
    seen = np.isfinite(t)
    fill = float(t[seen].max()) if seen.any() and fallback == "max" else 0.0
    return (k * np.where(seen, t, fill)).astype(np.float32)


def smooth(scales: torch.Tensor, opacities: torch.Tensor, sigma: torch.Tensor | None):
    """(scales', opacities') of disks (N,2), (N,) convolved in-plane with isotropic Gaussians
    of standard deviation ``sigma`` (N,) (module doc). Differentiable; sigma = 0 is the
    identity, and a zero-scale disk becomes the filter's blob with zero opacity."""
    if sigma is None:
        return scales, opacities
    s_new = torch.sqrt(scales * scales + (sigma * sigma)[:, None])
    den = s_new[:, 0] * s_new[:, 1]
    coef = torch.where(den > 0, (scales[:, 0] * scales[:, 1]) / den.clamp_min(1e-30),
                       torch.ones_like(den))
    return s_new, opacities * coef
