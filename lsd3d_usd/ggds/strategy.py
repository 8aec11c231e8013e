"""SGLD noise and relocation of dead surfels, as a strategy (3DGS-MCMC, Kheradmand et al. 2024),
adapted to geometry grounding: the noise moves surfels within their own tangent plane (scaled by
their disk), so exploration never pushes them off the proxy surface they were seeded on.

Hooks follow gsplat's strategies: `step_post_backward(params, optimizer, step)` after each
optimizer update."""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class MCMCStrategy:
    noise_scale: float = 0.5          # tangent-plane noise in units of the surfel's std-dev
    gate_sharpness: float = 100.0     # k in sigmoid(-k (opacity - t)): only near-dead surfels move
    gate_threshold: float = 0.005     # t
    relocate_every: int = 50          # steps between relocations (0 = never)
    dead_opacity: float = 0.005       # surfels below this are relocated
    max_relocate_frac: float = 0.05   # at most this fraction per relocation
    cap: int = 4_000_000              # never exceed this count (the paper's 4 M)
    seed: int = 0

    def __post_init__(self):
        self._gen = torch.Generator().manual_seed(int(self.seed))
        self.relocated_total = 0
        self.last_relocation: tuple[torch.Tensor, torch.Tensor] | None = None  # (dead, source)

    @torch.no_grad()
    def step_post_backward(self, params: dict, optimizer, step: int, lr_means: float,
                           rows: torch.Tensor | None = None) -> dict:
        info = {"noised": 0, "relocated": 0}
        rows = torch.arange(params["means"].shape[0]) if rows is None else rows
        if self.noise_scale > 0 and rows.numel():
            info["noised"] = self._noise(params, rows, lr_means)
        if self.relocate_every and step > 0 and step % self.relocate_every == 0:
            info["relocated"] = self._relocate(params, optimizer)
        return info

    def _noise(self, params, rows, lr_means) -> int:
        op = torch.sigmoid(params["opacities"][rows])
        gate = torch.sigmoid(-self.gate_sharpness * (op - self.gate_threshold))
        moving = gate > 1e-3
        if not moving.any():
            return 0
        r = rows[moving]
        q = params["quats"][r]
        q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
        x, y, z, w = q.unbind(1)
        t_u = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)], 1)
        t_v = torch.stack([2 * (x * y - z * w), 1 - 2 * (x * x + z * z), 2 * (y * z + x * w)], 1)
        s = params["scales"][r].exp()
        eta = torch.randn((len(r), 2), generator=self._gen)
        step = (t_u * (eta[:, :1] * s[:, :1]) + t_v * (eta[:, 1:] * s[:, 1:]))
        # Scaled by the position learning rate relative to its initial value, so it anneals.
        params["means"][r] += self.noise_scale * gate[moving, None] * step * min(1.0, lr_means / 1e-3)
        return int(len(r))

    def _relocate(self, params, optimizer) -> int:
        op = torch.sigmoid(params["opacities"])
        dead = torch.nonzero(op < self.dead_opacity).flatten()
        alive = torch.nonzero(op >= self.dead_opacity).flatten()
        if dead.numel() == 0 or alive.numel() == 0:
            return 0
        limit = max(1, int(self.max_relocate_frac * op.numel()))
        if dead.numel() > limit:
            dead = dead[torch.randperm(dead.numel(), generator=self._gen)[:limit]]
        # Sources sampled in proportion to opacity; each source shares its opacity with the
        # copies placed on it so the composite opacity stays the same: 1-(1-o)^(1/(k+1)).
        src = alive[torch.multinomial(op[alive], dead.numel(), replacement=True, generator=self._gen)]
        counts = torch.bincount(src, minlength=op.numel()).to(torch.float32)
        k1 = counts[src] + 1
        new_op = (1 - (1 - op[src]).clamp_min(1e-6) ** (1 / k1)).clamp(1e-4, 1 - 1e-4)
        logit = torch.log(new_op / (1 - new_op))
        for key in ("means", "quats", "scales", "sh"):
            params[key][dead] = params[key][src]
        params["opacities"][dead] = logit
        params["opacities"][src] = logit
        # Offset the copies inside the source's tangent plane so they do not coincide.
        q = params["quats"][dead]
        q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
        x, y, z, w = q.unbind(1)
        t_u = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)], 1)
        s = params["scales"][dead].exp()[:, :1]
        params["means"][dead] += t_u * s * (torch.rand((dead.numel(), 1), generator=self._gen) - 0.5)
        optimizer.reset_rows(torch.cat([dead, torch.unique(src)]))
        self.relocated_total += int(dead.numel())
        self.last_relocation = (dead, src)
        return int(dead.numel())
