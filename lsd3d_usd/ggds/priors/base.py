"""The image-prior interface of GGDS.

A prior maps a rendered image x of one view, the proxy G-buffer of the same view
(conditioning.gbuffer.GBuffer) and the light (conditioning.light.PriorEnv) to a target image
x_hat at noise level t in (0, 1]: small t keeps x nearly as it is, t = 1 re-synthesises it
entirely. GGDS pulls the render towards x_hat.

Image convention everywhere in ggds/: (H, W, 3) float32 torch tensors, scene-linear RGB
scaled for display (roughly [0, 1]), row 0 at the top of the image.
"""
from __future__ import annotations

import math

import torch

from lsd3d_usd.conditioning.gbuffer import GBuffer
from lsd3d_usd.conditioning.light import PriorEnv
from lsd3d_usd.errors import InputError


def check_t(t: float) -> float:
    t = float(t)
    if not (0.0 < t <= 1.0) or math.isnan(t):
        raise InputError(f"prior noise level t must be in (0, 1], got {t}")
    return t


def check_image(x: torch.Tensor) -> None:
    if x.ndim != 3 or x.shape[-1] != 3:
        raise InputError(f"prior input image must be (H, W, 3), got {tuple(x.shape)}")


class Prior:
    """Base class: subclasses implement `target`; `name` goes into provenance."""

    name = "prior"
    # Weights of loss terms configured as None (ggds/losses/terms.py): a diffusion prior's loose
    # targets are where the perceptual term earns its place.
    default_weights = {"perceptual": 0.05}

    def default_weight(self, term: str) -> float:
        return float(self.default_weights.get(term, 0.0))

    def shade_at(self, points, normals, semantic, env: PriorEnv, view_dirs=None,
                 sun_visibility=None) -> torch.Tensor | None:
        """Optional: the prior's radiance at world points (N,3), when it can be evaluated in
        3D (GGDS then starts surfel colours from it). None: image space only."""
        return None

    def ground_albedo(self, env: PriorEnv):
        """Optional: the mean linear-RGB albedo (3,) of the prior's open ground (terrain), for
        the ground beyond the scene (env.farfield) to continue it. None: the env's ground
        colour stands in."""
        return None

    def target(self, x: torch.Tensor, gbuffer: GBuffer, env: PriorEnv, t: float,
               n_steps: int = 5, seed: int | None = None) -> torch.Tensor:
        """Target image x_hat (H, W, 3) for rendered image x (H, W, 3) at noise level t.

        Deterministic for a given seed; x is treated as detached (no gradient flows)."""
        raise NotImplementedError  # abstract: every prior defines it

    def forget(self, keys) -> None:
        """Optional: drop what was cached under these GBuffer keys (GGDS calls it when a
        run's training views are done with)."""

    def describe(self) -> dict:
        """Parameters for layer provenance."""
        return {"prior": self.name}


def heldout_target(prior: Prior, x: torch.Tensor, gbuffer: GBuffer, env: PriorEnv, j: int, *,
                   t: float = 1.0, n_steps: int = 5) -> torch.Tensor:
    """The target held-out view ``j`` is scored against: the prior at noise level ``t`` from
    the render ``x`` (negative radiance clamped), with the held-out seed of view ``j`` (the
    one place it is set: disjoint from the training steps' seeds, seed * 100003 + step)."""
    with torch.no_grad():
        return prior.target(x.clamp(0, None), gbuffer, env, t, n_steps=n_steps,
                            seed=10_000 + int(j))
