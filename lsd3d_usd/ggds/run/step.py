"""One GGDS step, and the render of a run's surfels it is built on.

Each step: pick a view; render the surfels x; ask the prior for a target x̂ at a noise level
t ~ U[t_min, t_max] (t_min annealed linearly down, as in the paper) from the view's proxy
G-buffer; minimise the configured loss terms (ggds/losses/terms.py: ω(t)(|x − x̂|₁ +
perceptual) + proxy normal and disparity losses + the 2DGS normal-consistency and
depth-distortion regularisers + TV on the render); update only the surfels the view touched
(selective Adam); then the MCMC strategy adds opacity-gated SGLD noise in each surfel's
tangent plane and relocates dead surfels.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from lsd3d_usd.ggds.filters import box_filter
from lsd3d_usd.ggds.losses import image as losses
from lsd3d_usd.ggds.losses.terms import StepContext
from lsd3d_usd.ggds.run.context import FrozenContext
from lsd3d_usd.ggds.run.evaluate import psnr
from lsd3d_usd.ggds.run.state import RunState
from lsd3d_usd.ggds.run.training_views import TrainingViews
from lsd3d_usd.render.raster_types import RasterResult, RasterSettings
from lsd3d_usd.render.rasterize import rasterize


@dataclass
class LossSet:
    """(LossTerm, weight) pairs and the state each term's setup built once per run."""
    terms: list
    state: dict = field(default_factory=dict)

    @property
    def needs(self) -> set:
        """Extra render outputs the terms read (e.g. "distortion")."""
        return {n for term, _ in self.terms for n in term.needs}


def render(state: RunState, context: FrozenContext | None, camera, params=None, *,
           background=None, backend: str = "numba", **settings) -> RasterResult:
    """Rasterise the (activated) parameters — ``params``, default the state's — with the
    frozen context rows that can reach ``camera``; ``settings`` are RasterSettings fields
    (near/far come from the camera)."""
    a = state.activated(params)
    if context is not None:   # trainable rows first: visible_index < n are ours
        a = context.append_to(a, camera)
    return rasterize(a["means"], a["quats"], a["scales"], a["opacities"], a["sh"],
                     camera.viewmat, camera.K, camera.width, camera.height,
                     settings=RasterSettings.for_camera(camera, **settings),
                     background=background, backend=backend)


@torch.no_grad()
def observe_residual(state: RunState, x: torch.Tensor, x_hat: torch.Tensor, cam,
                     rows: torch.Tensor) -> None:
    """Feed the strategy the residual |x − x̂| (3×3 box mean) at the projected centres of
    the surfels this view showed (error-driven densification, optim/strategy.py)."""
    r = box_filter((x - x_hat).abs().mean(-1), 1)
    p = state.params["means"][rows].double().numpy()
    uv, z = cam.project(p)
    i, j = np.floor(uv[:, 0]), np.floor(uv[:, 1])
    ok = (z > cam.near) & (i >= 0) & (j >= 0) & (i < cam.width) & (j < cam.height)
    vals = torch.full((len(p),), float("nan"))
    ii = torch.from_numpy(i[ok].astype(np.int64))
    jj = torch.from_numpy(j[ok].astype(np.int64))
    vals[torch.from_numpy(ok)] = r[jj, ii]
    state.strategy.observe(rows, vals, state.n)


def take_step(state: RunState, views: TrainingViews, context: FrozenContext | None, prior,
              env, loss_set: LossSet, *, backend: str = "numba") -> dict:
    """One step (module doc); returns its history record (also appended to state.history)."""
    t0 = time.perf_counter()
    cfg, k = state.cfg, state.step_index
    vi = int(state.rng.integers(len(views)))
    vd = views.get(vi)
    cam = vd.view.camera
    t_view = time.perf_counter()
    dist_kw = {"distortion": True} if "distortion" in loss_set.needs else {}
    out = render(state, context, cam, background=vd.background, normal_space="camera",
                 backend=backend, **dist_kw)
    x = out.rgb
    t_render = time.perf_counter()
    t = float(state.rng.uniform(state.t_min(k), cfg.t_max))
    with torch.no_grad():
        x_hat = prior.target(x.detach().clamp(0, None), vd.gbuffer, env, t,
                             n_steps=cfg.n_denoise, seed=cfg.seed * 100003 + k)
    t_prior = time.perf_counter()
    w = losses.omega(t, cfg.omega)
    if vd.mask is not None:   # outside the focus the target stands in: no difference there
        x = torch.where(vd.mask[..., None], x, x_hat)
    ctx = StepContext(x, x_hat, out, vd.gbuffer, cam, t, cfg, loss_set.state)
    terms = {}
    for term, weight in loss_set.terms:
        terms[term.name] = (weight * w if term.image else weight) * term.fn(ctx)
    loss = sum(terms.values())
    for p in state.params.values():
        p.grad = None
    t_loss = time.perf_counter()
    loss.backward()
    t_backward = time.perf_counter()
    rows = out.visible_index
    if context is not None:
        rows = rows[rows < state.n]
    lrs = state.lrs(k)
    state.optimizer.lrs = lrs
    state.optimizer.step(rows)
    state.ground(rows)
    state.floor_colour(rows)
    if state.strategy.densify_frac > 0:
        observe_residual(state, x.detach(), x_hat, cam, rows)
    info = state.strategy.step_post_backward(state.params, state.optimizer, k + 1, lrs["means"],
                                             rows, filter_coef=state.filter_coef)
    if info["relocated"]:
        state.track_relocation()
    state.step_index += 1
    t_end = time.perf_counter()
    dt = t_end - t0
    timing = {"view_s": t_view - t0, "render_s": t_render - t_view, "prior_s": t_prior - t_render,
              "loss_s": t_loss - t_prior, "backward_s": t_backward - t_loss,
              "update_s": t_end - t_backward}
    state.seconds += dt
    rec = {"step": k, "view": vi, "t": round(t, 4), "loss": float(loss.detach()), "seconds": dt,
           "visible": int(rows.numel()), "psnr_target": psnr(x.detach(), x_hat),
           **{kk: float(v.detach()) for kk, v in terms.items()}, **info, **timing}
    state.history.append(rec)
    return rec
