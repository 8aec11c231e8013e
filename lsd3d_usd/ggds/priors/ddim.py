"""DDPM noise schedule and deterministic DDIM sampling / inversion (Song et al. 2021).

Levels are integer training timesteps k = 0..T-1 with cumulative signal alpha_bar[k], plus
the clean level k = -1 with alpha_bar = 1 (the data itself). A continuous noise level
t in (0, 1] maps to k = round(t * T) - 1, so t < 0.5 / T is the clean level.

The deterministic DDIM update between any two levels, with eps predicted at the current
level, is
    x0  = (z - sqrt(1 - ab_from) * eps) / sqrt(ab_from)
    z'  = sqrt(ab_to) * x0 + sqrt(1 - ab_to) * eps,
used downwards for denoising and upwards for inversion (the Euler step of the probability-flow
ODE in the variables z / sqrt(ab) and sqrt(1 - ab) / sqrt(ab)). Both walk the same grid of
levels, so inversion followed by denoising differs from the identity only by where eps is
evaluated (start vs end of each interval): zero for an eps that does not depend on the
level's input, decreasing with the step count for a smooth one (tools/bench_ddim.py).

Schedule tables are float64; a step is computed in the dtype of z (pass float64 tensors for
exact work).
"""
from __future__ import annotations

import math
from typing import Callable

import torch

from lsd3d_usd.errors import InputError

# eps_fn(z, k) -> predicted noise, same shape as z; k is a training timestep 0..T-1.
EpsFn = Callable[[torch.Tensor, int], torch.Tensor]


class DDIMSchedule:
    """Cumulative-alpha table of a DDPM noise schedule.

    Default: Stable Diffusion's "scaled_linear" betas, linspace(sqrt(0.00085), sqrt(0.012), T)^2
    with T = 1000.
    """

    def __init__(self, num_train_timesteps: int = 1000, beta_start: float = 0.00085,
                 beta_end: float = 0.012, beta_schedule: str = "scaled_linear",
                 alphas_cumprod: torch.Tensor | None = None):
        if alphas_cumprod is not None:
            ab = torch.as_tensor(alphas_cumprod, dtype=torch.float64).flatten()
            num_train_timesteps = ab.numel()
        else:
            if beta_schedule == "scaled_linear":
                betas = torch.linspace(math.sqrt(beta_start), math.sqrt(beta_end),
                                       num_train_timesteps, dtype=torch.float64) ** 2
            elif beta_schedule == "linear":
                betas = torch.linspace(beta_start, beta_end, num_train_timesteps, dtype=torch.float64)
            else:
                raise InputError(f"unsupported beta_schedule {beta_schedule!r} (scaled_linear, linear)")
            ab = torch.cumprod(1.0 - betas, dim=0)
        if num_train_timesteps < 2 or not bool(((ab > 0) & (ab < 1)).all()):
            raise InputError("alphas_cumprod must hold values in (0, 1)")
        self.num_train_timesteps = int(num_train_timesteps)
        self.alphas_cumprod = ab

    @classmethod
    def from_diffusers_config(cls, config) -> "DDIMSchedule":
        """From a diffusers scheduler config (dict-like: num_train_timesteps, beta_*)."""
        get = config.get if hasattr(config, "get") else (lambda k, d=None: getattr(config, k, d))
        return cls(int(get("num_train_timesteps", 1000)), float(get("beta_start", 0.00085)),
                   float(get("beta_end", 0.012)), str(get("beta_schedule", "scaled_linear")))

    def alpha_bar(self, k: int) -> float:
        """Cumulative signal at level k (k = -1: clean, 1.0)."""
        if k < 0:
            return 1.0
        return float(self.alphas_cumprod[k])

    def level(self, t: float) -> int:
        """Level k for a continuous noise level t in [0, 1]."""
        t = float(t)
        if not 0.0 <= t <= 1.0:
            raise InputError(f"noise level t must be in [0, 1], got {t}")
        return min(self.num_train_timesteps - 1, max(-1, round(t * self.num_train_timesteps) - 1))

    def levels(self, k_start: int, n_steps: int) -> list[int]:
        """Decreasing levels from k_start to -1 in (at most) n_steps evenly spaced steps."""
        if n_steps < 1:
            raise InputError(f"number of DDIM steps must be >= 1, got {n_steps}")
        if k_start < 0:
            return [-1]
        grid = torch.linspace(float(k_start), -1.0, n_steps + 1, dtype=torch.float64).round().long().tolist()
        out = []
        for k in grid:
            if not out or k < out[-1]:
                out.append(int(k))
        return out

    def step(self, z: torch.Tensor, eps: torch.Tensor, k_from: int, k_to: int) -> torch.Tensor:
        """Deterministic DDIM (eta = 0) move from level k_from to k_to with eps at k_from."""
        a_from, a_to = self.alpha_bar(k_from), self.alpha_bar(k_to)
        x0 = (z - math.sqrt(1.0 - a_from) * eps) / math.sqrt(a_from)
        return math.sqrt(a_to) * x0 + math.sqrt(1.0 - a_to) * eps

    def predict_x0(self, z: torch.Tensor, eps: torch.Tensor, k: int) -> torch.Tensor:
        a = self.alpha_bar(k)
        return (z - math.sqrt(1.0 - a) * eps) / math.sqrt(a)

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, k: int) -> torch.Tensor:
        """Forward process sample z_k = sqrt(ab) x0 + sqrt(1 - ab) noise."""
        a = self.alpha_bar(k)
        return math.sqrt(a) * x0 + math.sqrt(1.0 - a) * noise

    def denoise(self, z: torch.Tensor, eps_fn: EpsFn, k_start: int, n_steps: int) -> torch.Tensor:
        """N-step deterministic DDIM from level k_start to the clean level."""
        ks = self.levels(k_start, n_steps)
        for k_from, k_to in zip(ks[:-1], ks[1:]):
            z = self.step(z, eps_fn(z, k_from), k_from, k_to)
        return z

    def invert(self, z0: torch.Tensor, eps_fn: EpsFn, k_end: int, n_steps: int) -> torch.Tensor:
        """DDIM inversion: run the deterministic ODE from the clean level up to k_end, over the
        same levels `denoise(.., k_end, n_steps)` walks down. At the clean level eps is
        evaluated at timestep 0 (the nearest level the model was trained on)."""
        ks = self.levels(k_end, n_steps)[::-1]
        z = z0
        for k_from, k_to in zip(ks[:-1], ks[1:]):
            z = self.step(z, eps_fn(z, max(k_from, 0)), k_from, k_to)
        return z


def eps_from_model_output(out: torch.Tensor, z: torch.Tensor, alpha_bar: float,
                          prediction_type: str = "epsilon") -> torch.Tensor:
    """Convert a network output to eps (SD 1.x / SDXL predict eps; SD 2.x-v predicts v)."""
    if prediction_type == "epsilon":
        return out
    if prediction_type == "v_prediction":
        return math.sqrt(alpha_bar) * out + math.sqrt(1.0 - alpha_bar) * z
    if prediction_type == "sample":
        return (z - math.sqrt(alpha_bar) * out) / math.sqrt(1.0 - alpha_bar)
    raise InputError(f"unsupported prediction_type {prediction_type!r}")
