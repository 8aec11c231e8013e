"""Adam that updates only the rows it is given (the surfels a view touched), as
gsplat's SelectiveAdam: surfels outside the sampled frusta keep their values and
moments untouched instead of drifting on stale momentum.

The update is one numba pass per parameter over the given rows (`_adam_rows`: gradient,
moments and value read and written in place); torch's gathers and scatters of the same
update (`step_reference`, kept as the tests' reference) took ~5x as long and were a fifth
of a GGDS step at SH degree 2."""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from lsd3d_usd.jitopts import prange_only
from lsd3d_usd.shmath import C0 as SH_C0

ROW_BLOCK = 1 << 17


@njit(inline="always")
def _rel_factor(c, rel_ref, rel_least):
    """sqrt(base colour / rel_ref) within [rel_least, 1] (SelectiveAdam's rel_ref)."""
    return min(max(math.sqrt(max(0.5 + SH_C0 * c, 0.0) / rel_ref), rel_least), 1.0)


@njit(cache=True, parallel=prange_only())
def _adam_rows(p, g, m, v, rows, t, lr, b1, b2, eps, col_scale, rel_ref, rel_least):
    """Adam on the rows ``rows`` (R,) of p, g, m, v (N,D) float32, in place. t (N,): each
    row's update count (this one included); col_scale (D,): the lr factor of each column.
    rel_ref > 0: p's rows are SH coefficients (K,3) flattened, and column j's step is also
    scaled by sqrt(c / rel_ref) within [rel_least, 1], c = 0.5 + C0 p[i, j % 3] the row's
    base colour in that channel before the update. Rows must be unique."""
    D = p.shape[1]
    for q in prange(rows.shape[0]):
        i = rows[q]
        c1 = np.float32(1.0 - b1 ** t[i])
        c2 = np.float32(1.0 - b2 ** t[i])
        f0 = f1 = f2 = 1.0      # scalars: an array here would be a heap allocation per row
        if rel_ref > 0:
            f0 = _rel_factor(p[i, 0], rel_ref, rel_least)
            f1 = _rel_factor(p[i, 1], rel_ref, rel_least)
            f2 = _rel_factor(p[i, 2], rel_ref, rel_least)
        for j in range(D):
            gj = g[i, j]
            mj = np.float32(m[i, j] * b1 + gj * (1.0 - b1))
            vj = np.float32(v[i, j] * b2 + gj * gj * (1.0 - b2))
            m[i, j] = mj
            v[i, j] = vj
            f = f0 if j % 3 == 0 else f1 if j % 3 == 1 else f2
            step = mj / c1 / (math.sqrt(vj / c2) + eps) * lr * col_scale[j] * f
            p[i, j] -= np.float32(step)


class SelectiveAdam:
    def __init__(self, params: dict[str, torch.Tensor], lrs: dict[str, float],
                 betas=(0.9, 0.999), eps: float = 1e-15,
                 lr_scales: dict[str, torch.Tensor] | None = None,
                 eps_by_key: dict[str, float] | None = None,
                 relative: dict[str, tuple[float, float]] | None = None):
        self.params, self.lrs = params, dict(lrs)
        # Optional key -> (ref, least) of SH parameters (N,K,3): each channel's steps scaled
        # by sqrt(its base colour / ref) within [least, 1] (dark_step_scale).
        self.relative = dict(relative or {})
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
        """One update of ``rows`` (unique row indices) from the parameters' gradients."""
        if rows.numel() == 0:
            return
        self.t[rows] += 1
        r = rows.numpy().astype(np.int64, copy=False)
        t = self.t.numpy()
        for k, p in self.params.items():
            if p.grad is None or self.lrs.get(k, 0.0) == 0.0:
                continue
            n = p.shape[0]
            flat = lambda x: x.detach().view(n, -1).numpy()   # views (in place), never copies
            pf, mf, vf = flat(p.data), flat(self.m[k]), flat(self.v[k])
            d = pf.shape[1]
            col = np.ones(d, np.float32)
            if k in self.lr_scales:
                col = np.ascontiguousarray(np.broadcast_to(
                    self.lr_scales[k].numpy().astype(np.float32), p.shape[1:]).reshape(d))
            ref, least = self.relative.get(k, (0.0, 1.0))
            _adam_rows(pf, np.ascontiguousarray(flat(p.grad)), mf, vf, r, t,
                       float(self.lrs[k]), self.b1, self.b2,
                       float(self.eps_by_key.get(k, self.eps)), col, float(ref), float(least))

    @torch.no_grad()
    def step_reference(self, rows: torch.Tensor) -> None:
        """`step` as torch gathers and scatters (the tests' reference)."""
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
                if k in self.relative:
                    update.mul_(dark_step_scale(p[r, 0], *self.relative[k])[:, None, :])
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


def dark_step_scale(dc: torch.Tensor, ref: float, least: float) -> torch.Tensor:
    """(R,3) factors of the SH steps of rows whose SH DC terms are ``dc`` (R,3):
    sqrt(base colour / ref) per channel, within [least, 1]. Adam's steps have one size
    whatever the colour, so a dark channel (shadows, façades at 0.08) takes steps that are a
    large part of its value and random-walks into chroma speckle; sqrt follows how much
    brighter a step looks there."""
    c = (0.5 + SH_C0 * dc).clamp_min(0)
    return (c / ref).sqrt_().clamp_(least, 1.0)


def lr_at(step: int, total: int, lr0: float, lr1: float) -> float:
    """Log-linear decay from lr0 to lr1 (as 3DGS's position schedule)."""
    if total <= 1:
        return lr0
    f = min(max(step / (total - 1), 0.0), 1.0)
    return math.exp(math.log(lr0) * (1 - f) + math.log(lr1) * f)
