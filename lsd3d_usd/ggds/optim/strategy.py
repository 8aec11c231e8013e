"""SGLD noise and relocation of dead surfels, as a strategy (3DGS-MCMC, Kheradmand et al. 2024),
adapted to geometry grounding: the noise moves surfels within their own tangent plane (scaled by
their disk), so exploration never pushes them off the proxy surface they were seeded on.

Error-driven densification within the budget (the count never changes): every surfel keeps
the mean image residual |render − target| seen at its centre over the views that showed it
(``observe``). At each relocation, besides the dead surfels, the most redundant live ones —
those far smaller than the finest training view's pixel there, i.e. whose 3D smoothing filter
(ggds/optim/antialias.py) keeps less than ``redundant_coef`` of their opacity: several of them share
one pixel of every view — are moved (at most ``densify_frac`` of the count at a time) onto
live surfels drawn in proportion to residual × opacity, and each such target is split: it and
the surfels placed on it share its disk, scales shrunk by 1/sqrt(k+1) (the same area in all),
spread over the disk in its tangent plane, colour and opacity copied, so detail the residual
says is missing can be learnt there.

Hooks follow gsplat's strategies: `step_post_backward(params, optimizer, step)` after each
optimizer update."""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from lsd3d_usd.ggds.settings import StrategyConfig
from lsd3d_usd.render.projection import quat_to_rotmat


def _tangents(quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The disks' unit tangent axes t_u, t_v (N,3) each, from (N,4) xyzw quaternions."""
    R = quat_to_rotmat(quats)
    return R[..., 0], R[..., 1]


@dataclass
class MCMCStrategy(StrategyConfig):
    """The strategy of a run: its settings are ggds.settings.StrategyConfig's leaves (declared
    once, with their help and limits there), plus the seed of its noise and relocations."""
    seed: int = 0

    @classmethod
    def of(cls, config: StrategyConfig, seed: int) -> "MCMCStrategy":
        return cls(**{f.name: getattr(config, f.name) for f in fields(config)}, seed=seed)

    def __post_init__(self):
        self._gen = torch.Generator().manual_seed(int(self.seed))
        self.relocated_total = 0
        self.densified_total = 0
        self.last_relocation: tuple[torch.Tensor, torch.Tensor] | None = None  # (dead, source)
        self.err_sum: torch.Tensor | None = None   # Σ residual at the centre, per surfel
        self.err_cnt: torch.Tensor | None = None   # views that showed it

    # ------------------------------------------------------------------ state
    def state_tensors(self) -> dict:
        out = {"strategy.rng": self._gen.get_state()}
        if self.err_sum is not None:
            out["strategy.err_sum"] = self.err_sum.contiguous()
            out["strategy.err_cnt"] = self.err_cnt.contiguous()
        return out

    def load_state_tensors(self, tensors: dict) -> None:
        self._gen.set_state(tensors["strategy.rng"])
        if "strategy.err_sum" in tensors:
            self.err_sum = tensors["strategy.err_sum"].clone()
            self.err_cnt = tensors["strategy.err_cnt"].clone()

    def observe(self, rows: torch.Tensor, residual: torch.Tensor, n: int) -> None:
        """Accumulate the residual seen at the centres of surfels ``rows`` (NaN: not seen)."""
        if self.err_sum is None:
            self.err_sum = torch.zeros(n)
            self.err_cnt = torch.zeros(n)
        ok = torch.isfinite(residual)
        self.err_sum.index_add_(0, rows[ok], residual[ok].float())
        self.err_cnt.index_add_(0, rows[ok], torch.ones(int(ok.sum())))

    @torch.no_grad()
    def step_post_backward(self, params: dict, optimizer, step: int, lr_means: float,
                           rows: torch.Tensor | None = None, filter_coef=None) -> dict:
        """``filter_coef``: callable → (N,) fraction of each surfel's opacity the 3D filter
        keeps (None: no filter, nothing counts as redundant)."""
        info = {"noised": 0, "relocated": 0, "densified": 0}
        rows = torch.arange(params["means"].shape[0]) if rows is None else rows
        if self.noise_scale > 0 and rows.numel():
            info["noised"] = self.add_noise(params, rows, lr_means)
        if self.relocate_every and step > 0 and step % self.relocate_every == 0:
            moved = []
            info["relocated"] = self.relocate(params, optimizer)
            if info["relocated"]:
                moved.append(self.last_relocation)
                if self.err_sum is not None:   # revived: their residual is measured afresh
                    self.err_sum[self.last_relocation[0]] = 0
                    self.err_cnt[self.last_relocation[0]] = 0
            if self.densify_frac > 0 and filter_coef is not None:
                info["densified"] = self._densify(params, optimizer, filter_coef())
                if info["densified"]:
                    moved.append(self.last_relocation)
            if moved:
                self.last_relocation = (torch.cat([m[0] for m in moved]),
                                        torch.cat([m[1] for m in moved]))
        return info

    def _densify(self, params, optimizer, coef: torch.Tensor) -> int:
        """Move redundant live surfels onto high-residual ones and split those (module doc)."""
        if self.err_sum is None:
            return 0
        op = torch.sigmoid(params["opacities"])
        seen = self.err_cnt > 0
        live = op >= self.dead_opacity
        donors = torch.nonzero(live & seen & (coef < self.redundant_coef)).flatten()
        mean_err = torch.where(seen, self.err_sum / self.err_cnt.clamp_min(1), 0.0)
        score = mean_err * op * (live & seen & (coef >= self.redundant_coef))
        cand = torch.nonzero(score > 0).flatten()
        limit = int(self.densify_frac * op.numel())
        if donors.numel() == 0 or cand.numel() == 0 or limit == 0:
            return 0
        if donors.numel() > limit:   # the most redundant first
            donors = donors[torch.argsort(coef[donors])[:limit]]
        src = cand[torch.multinomial(score[cand], donors.numel(), replacement=True,
                                     generator=self._gen)]
        k1 = (torch.bincount(src, minlength=op.numel()).to(torch.float32) + 1)
        for key in ("means", "quats", "scales", "opacities", "sh"):
            params[key][donors] = params[key][src]
        # Split: the target and its copies share its disk, each with 1/(k+1) of its area.
        targets = torch.unique(src)
        params["scales"][targets] -= 0.5 * torch.log(k1[targets])[:, None]
        params["scales"][donors] -= 0.5 * torch.log(k1[src])[:, None]
        t_u, t_v = _tangents(params["quats"][donors])
        s = params["scales"][donors].exp() * torch.sqrt(k1[src])[:, None]   # the target's old σ
        eta = torch.randn((donors.numel(), 2), generator=self._gen) * 0.5
        params["means"][donors] += t_u * (eta[:, :1] * s[:, :1]) + t_v * (eta[:, 1:] * s[:, 1:])
        optimizer.reset_rows(torch.cat([donors, targets]))
        for rows in (donors, targets):   # their residual is measured afresh
            self.err_sum[rows] = 0
            self.err_cnt[rows] = 0
        self.densified_total += int(donors.numel())
        self.last_relocation = (donors, src)
        return int(donors.numel())

    def add_noise(self, params, rows, lr_means) -> int:
        op = torch.sigmoid(params["opacities"][rows])
        gate = torch.sigmoid(-self.gate_sharpness * (op - self.gate_threshold))
        moving = gate > 1e-3
        if not moving.any():
            return 0
        r = rows[moving]
        t_u, t_v = _tangents(params["quats"][r])
        s = params["scales"][r].exp()
        eta = torch.randn((len(r), 2), generator=self._gen)
        step = (t_u * (eta[:, :1] * s[:, :1]) + t_v * (eta[:, 1:] * s[:, 1:]))
        # Scaled by the position learning rate relative to its initial value, so it anneals.
        params["means"][r] += self.noise_scale * gate[moving, None] * step * min(1.0, lr_means / 1e-3)
        return int(len(r))

    def relocate(self, params, optimizer) -> int:
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
        t_u, _ = _tangents(params["quats"][dead])
        s = params["scales"][dead].exp()[:, :1]
        params["means"][dead] += t_u * s * (torch.rand((dead.numel(), 1), generator=self._gen) - 0.5)
        optimizer.reset_rows(torch.cat([dead, torch.unique(src)]))
        self.relocated_total += int(dead.numel())
        self.last_relocation = (dead, src)
        return int(dead.numel())
