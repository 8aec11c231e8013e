"""Adam that updates only the rows it is given (the surfels a view touched), as
gsplat's SelectiveAdam: surfels outside the sampled frusta keep their values and
moments untouched instead of drifting on stale momentum."""
from __future__ import annotations

import math

import torch

ROW_BLOCK = 1 << 17

class SelectiveAdam:
    def __init__(self, params: dict[str, torch.Tensor], lrs: dict[str, float],
                 betas=(0.9, 0.999), eps: float = 1e-15,
                 lr_scales: dict[str, torch.Tensor] | None = None,
                 eps_by_key: dict[str, float] | None = None,
                 row_scales: dict | None = None):
        self.params, self.lrs = params, dict(lrs)
        # Optional per-key callables: a block of rows' values -> lr factors broadcast over
        # them (e.g. a colour's steps shrunk with its brightness).
        self.row_scales = dict(row_scales or {})
        # eps per key: with eps ~ 0 Adam turns a tiny, noisy gradient into a full-size step.
        self.eps_by_key = dict(eps_by_key or {})
        # Optional per-element lr factors broadcast over a row (e.g. SH DC vs higher orders).
        self.lr_scales = dict(lr_scales or {})
        self.b1, self.b2, self.eps = betas[0], betas[1], eps
        self.m = {k: torch.zeros_like(v) for k, v in params.items()}
        self.v = {k: torch.zeros_like(v) for k, v in params.items()}
        # Per-row step counts: bias correction must count the updates a row received.
        n = next(iter(params.values())).shape[0]
        self.t = torch.zeros(n, dtype=torch.int64)

    @torch.no_grad()
    def step(self, rows: torch.Tensor) -> None:
        if rows.numel() == 0:
            return
        self.t[rows] += 1
        # Rows in blocks, updates in place: a step's temporaries stay a few blocks of rows
        # (a view can touch ~1 M surfels; at SH degree 3, 0.2 GB per whole-row temporary).
        for r in rows.split(ROW_BLOCK):
            t = self.t[r].to(torch.float64)
            c1 = (1 - self.b1 ** t).to(torch.float32)
            c2 = (1 - self.b2 ** t).to(torch.float32)
            for k, p in self.params.items():
                if p.grad is None or self.lrs.get(k, 0.0) == 0.0:
                    continue
                g = p.grad[r]
                m = self.m[k][r].mul_(self.b1).add_(g, alpha=1 - self.b1)
                v = self.v[k][r].mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
                self.m[k][r], self.v[k][r] = m, v
                shape = (-1,) + (1,) * (p.dim() - 1)
                denom = v.div_(c2.view(shape)).sqrt_().add_(self.eps_by_key.get(k, self.eps))
                update = m.div_(c1.view(shape)).div_(denom).mul_(self.lrs[k])
                if k in self.lr_scales:
                    update.mul_(self.lr_scales[k])
                if k in self.row_scales:
                    update.mul_(self.row_scales[k](p[r]))
                p.index_put_((r,), p[r].sub_(update))

    @torch.no_grad()
    def reset_rows(self, rows: torch.Tensor) -> None:
        for k in self.params:
            self.m[k][rows] = 0
            self.v[k][rows] = 0
        self.t[rows] = 0

    def state_dict(self) -> dict:
        return {"m": {k: v.clone() for k, v in self.m.items()},
                "v": {k: v.clone() for k, v in self.v.items()}, "t": self.t.clone(),
                "lrs": dict(self.lrs)}

    def load_state_dict(self, state: dict) -> None:
        for k in self.params:
            if state["m"][k].shape != self.params[k].shape:
                raise ValueError(f"optimizer state for {k} has shape {tuple(state['m'][k].shape)}, "
                                 f"parameters {tuple(self.params[k].shape)}")
            self.m[k] = state["m"][k].clone()
            self.v[k] = state["v"][k].clone()
        self.t = state["t"].clone()


def lr_at(step: int, total: int, lr0: float, lr1: float) -> float:
    """Log-linear decay from lr0 to lr1 (as 3DGS's position schedule)."""
    if total <= 1:
        return lr0
    f = min(max(step / (total - 1), 0.0), 1.0)
    return math.exp(math.log(lr0) * (1 - f) + math.log(lr1) * f)
