"""The colour start of a run: every surfel's SH colour fitted to the prior before the first
step, when the prior is world-consistent (Prior.shade_at; the procedural prior is, a
diffusion prior is not).

A per-surfel least-squares fit to the t = 1 targets of the training views (and the extra fit
views) that see it (worldfit.ViewFit; each training view's target is computed once and cached
by the prior, as the steps would ask for it), each view's samples weighted 1, or
``ggds.elevated_fit_weight`` for an elevated view (``View.kind``), and for surfels none
sees, to the prior evaluated in 3D over its disk from the nearest cameras (worldfit.fit_sh). With a frozen
context whose rows still carry class colours, those rows are fitted the same way.
"""
from __future__ import annotations

import numpy as np
import torch

from lsd3d_usd.conditioning.elevated_sampling import ELEVATED
from lsd3d_usd.ggds.colour_start.worldfit import ViewFit, facing_ids, fit_sh, zonal_slopes
from lsd3d_usd.memtune import release_free_memory
from lsd3d_usd.render.sh import sh_degree_of

# the start hands the heap's free memory back every this many views: each view's prior
# render leaves ~100 MB of temporaries between the long-lived per-view caches, and the
# fragments added up to ~0.9 GB of the README sample's peak (2.71 -> 2.36 GB, no slower)
TRIM_EVERY_VIEWS = 16


def _opaque_untrained(state, rows: np.ndarray, least: float) -> None:
    """Opacity at least ``least`` for ``rows``: surfels no training view sees (roofs, the
    backs of things) keep their initial opacity through the steps, and at the initial 0.8
    a surface of them lets about a quarter of the light through (a roof seen from above
    shows the insides of its walls)."""
    if least <= 0 or not rows.any():
        return
    lo = float(np.log(least / (1.0 - least)))
    idx = torch.from_numpy(np.flatnonzero(rows))
    o = state.params["opacities"].data
    o[idx] = o[idx].clamp(min=lo)


@torch.no_grad()
def colour_start(state, views, context, prior, cond, fit_views=()) -> bool:
    """Fit the colours of ``state``'s surfels (and of ``context``'s fit rows) in place; the
    training ``views`` (run.training_views.TrainingViews) keep their G-buffers cached for the steps,
    ``fit_views`` are used once. Returns whether it ran."""
    c = state.cfg
    env = cond.env
    f = state.field()
    if f.semantic_ids is None or f.n == 0:
        return False
    probe = prior.shade_at(f.positions[:1].astype(np.float64), f.normals()[:1],
                           f.semantic_ids[:1], env)
    if probe is None:
        return False
    fit_views = list(fit_views)
    degree = sh_degree_of(state.params["sh"].shape[1])
    normals = f.normals()
    fit = ViewFit(f.n, degree)
    ctx = context.fit_inputs() if context is not None else None
    ctx_fit = ViewFit(len(ctx[0]), degree) if ctx is not None else None
    n_train = len(views)
    trained = None
    for i in range(n_train + len(fit_views)):
        if i == n_train:
            trained = fit.count > 0       # rows a training view sees: the steps reach them
        if i and i % TRIM_EVERY_VIEWS == 0:
            release_free_memory()
        # a fit view is used once; a training view's G-buffer and target stay cached
        fit_only = i >= n_train
        view = fit_views[i - n_train] if fit_only else views.views[i]
        weight = c.elevated_fit_weight if view.kind == ELEVATED else 1.0
        if fit_only:
            cam = view.camera
            # no finer G-buffer: the fit averages a target over each surfel's disk
            # anyway (README sample: the same held-out PSNR, 30 s less)
            gb = cond.unpack(cond.packed(cam), key=(views.key, "fit", i), fine=False)
        else:
            cam, gb = view.camera, views.get(i).gbuffer
        target = prior.target(torch.zeros(cam.height, cam.width, 3), gb, env, 1.0,
                              n_steps=c.n_denoise, seed=c.seed)
        fit.add_view(f.positions, f.scales, normals, cam, target, gb.depth.numpy(), weight=weight)
        if ctx_fit is not None:
            ctx_fit.add_view(*ctx, cam, target, gb.depth.numpy(), weight=weight)
        if fit_only:
            prior.forget([gb.key])
    slopes = ctx_slopes = None
    if c.world_init_zonal_prior:   # each group's slope from every surfel the start fits
        fits = [(fit, normals, facing_ids(normals, f.semantic_ids))]
        if ctx_fit is not None and context.fit_classes is not None:
            fits.append((ctx_fit, ctx[2], facing_ids(ctx[2], context.fit_classes)))
        table = zonal_slopes(fits, c.world_init_ridge, c.world_init_ridge_tangent)
        slopes = (fits[0][2], table)
        ctx_slopes = (fits[1][2], table) if len(fits) > 1 else None
    sh, seen = fit.solve(normals, c.world_init_ridge, c.world_init_ridge_tangent, slopes=slopes)
    if not seen.all():
        rest = np.flatnonzero(~seen)
        sub = fit_sh(prior, env, f.subset(rest), [v.camera for v in views.views + fit_views],
                     degree=degree, shadow=cond.shadow, samples=c.world_init_samples,
                     ridge=c.world_init_ridge, ridge_tangent=c.world_init_ridge_tangent,
                     seed=c.seed)
        sh[rest] = sub
    state.params["sh"][:] = torch.from_numpy(sh)
    state.floor_colour()
    if trained is None:
        trained = fit.count > 0
    _opaque_untrained(state, ~trained, c.untrained_opacity)
    if ctx_fit is not None:   # unseen context rows keep their colours
        csh, cseen = ctx_fit.solve(ctx[2], c.world_init_ridge, c.world_init_ridge_tangent,
                                   slopes=ctx_slopes)
        context.set_fitted_sh(cseen, csh[cseen])
        context.started = int(cseen.sum())
    return True
