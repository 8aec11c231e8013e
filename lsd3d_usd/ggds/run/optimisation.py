"""One GGDS optimisation (geometry-grounded distillation sampling): its state and its step.

Each step: pick a view; render the surfels x; ask the prior for a target x̂ at a noise level
t ~ U[t_min, t_max] (t_min annealed linearly down, as in the paper) from the view's proxy
G-buffer; minimise the configured loss terms (ggds/terms.py: ω(t)(|x − x̂|₁ + perceptual) +
proxy normal and disparity losses + the 2DGS normal-consistency and depth-distortion
regularisers + TV on the render); update only the surfels the view touched (selective Adam);
then the MCMC strategy adds opacity-gated SGLD noise in each surfel's tangent plane and
relocates dead surfels. The run's lifecycle (loop, checkpoints, resume, held-out evaluation)
is ggds/runner.py.
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from lsd3d_usd.configtree import to_dict
from lsd3d_usd.ggds.losses import image as losses
from lsd3d_usd.ggds.optim import params as P
from lsd3d_usd.ggds.optim.adam import SelectiveAdam, lr_at
from lsd3d_usd.conditioning.views import View
from lsd3d_usd.conditioning.gbuffer import (FaceTable, PackedGBuffer, finer, pack_view_gbuffer, table_gbuffer)
from lsd3d_usd.conditioning.shadow import ShadowMap
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.conditioning.gbuffer import GBuffer
from lsd3d_usd.ggds.priors.base import Prior
from lsd3d_usd.conditioning.light import PriorEnv
from lsd3d_usd.ggds.optim.strategy import MCMCStrategy
from lsd3d_usd.ggds.losses.terms import StepContext, active_terms
from lsd3d_usd.render.raster_types import RasterResult, RasterSettings
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.splats.field import SurfelField


_RUN_KEYS = itertools.count()   # G-buffer keys unique across the runs of a process
# world_init hands the heap's free memory back every this many views: each view's prior
# render leaves ~100 MB of temporaries between the long-lived per-view caches, and the
# fragments added up to ~0.9 GB of the README sample's peak (2.71 -> 2.36 GB, no slower)
TRIM_EVERY_VIEWS = 16
CONTEXT_SIGMAS = 3.5


@dataclass
class ViewData:
    view: View
    gbuffer: GBuffer
    background: torch.Tensor | None     # (H,W,3) env radiance behind the surfels
    mask: torch.Tensor | None = None    # (H,W) bool: pixels the image terms compare (None: all)


def focus_mask(gbuffer: GBuffer, focus) -> torch.Tensor | None:
    """Pixels whose proxy surface lies inside ``focus`` (x0, y0, x1, y1), or that show no
    proxy surface (the sky): what a region's render can be compared on. Beyond the focus the
    scene's surfels are not loaded, so the render shows the sky where the prior sees geometry."""
    if focus is None:
        return None
    x0, y0, x1, y1 = focus
    w = gbuffer.world_pos
    inside = (w[..., 0] >= x0) & (w[..., 0] <= x1) & (w[..., 1] >= y0) & (w[..., 1] <= y1)
    return torch.where(gbuffer.valid, inside, torch.ones_like(inside))


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact distance from points to triangles, row-wise (float64, Ericson's regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v = vb / denom
        w = vc / denom
    q = a + ab * v[:, None] + ac * w[:, None]  # interior projection
    # Regions: vertices, edges (clamped projections); take the closest candidate.
    cands = [a, b, c]
    for s, e in ((a, b), (b, c), (a, c)):
        se = e - s
        t = np.clip(((p - s) * se).sum(1) / np.maximum((se * se).sum(1), 1e-30), 0, 1)
        cands.append(s + se * t[:, None])
    inside = (va >= 0) & (vb >= 0) & (vc >= 0) & (denom > 0)
    dist = np.min(np.stack([np.linalg.norm(p - x, axis=1) for x in cands]), axis=0)
    dist[inside] = np.linalg.norm(p[inside] - q[inside], axis=1)
    return dist


def psnr(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    err = (x.clamp(0, 1) - y.clamp(0, 1)) ** 2
    mse = float(err.mean() if mask is None else err[mask].mean() if mask.any() else 0.0)
    return 99.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


class GGDSRun:
    """State of one GGDS run: parameters, optimizer, strategy, views and history.

    ``terms``: (LossTerm, weight) pairs (default: ggds.terms.active_terms(config, prior));
    per-term state (e.g. the perceptual network) is built once here by each term's setup.
    ``context``: frozen surfels rendered with the trainable ones (a region's neighbours, for
    chunk-wise GGDS); ``focus`` (x0, y0, x1, y1): where the loaded surfels cover the scene —
    image terms and held-out PSNR compare only pixels whose proxy surface lies there;
    ``context_start`` (len(context),) bool: context rows whose colours the world-space start
    fits too (a neighbour's initial surfels: flat class colours that the trainable surfels
    would otherwise learn to compensate for where they blend with them)."""

    def __init__(self, field: SurfelField, proxy: tuple[np.ndarray, np.ndarray, np.ndarray | None],
                 views: list[View], prior: Prior, env: PriorEnv, config: GGDSConfig, *,
                 background_fn=None, shadow: ShadowMap | None = None,
                 face_index: np.ndarray | None = None, terms=None, term_state: dict | None = None,
                 context: SurfelField | None = None, focus=None, fit_views=(),
                 context_start: np.ndarray | None = None):
        self.cfg = config
        self.fit_views = list(fit_views)
        # what the result keeps of the initial field; the rest lives in the parameters
        self.semantics = (field.semantic_ids, field.semantic_classes)
        self.focus = focus
        self.context = None
        if context is not None and context.n:
            c = context if context.sh_degree == field.sh_degree else \
                context.with_sh_degree(field.sh_degree)   # no copy when the degrees agree
            self.context = {k: torch.from_numpy(np.ascontiguousarray(v, np.float32)) for k, v in
                            (("means", c.positions), ("quats", c.orientations),
                             ("scales", c.scales), ("opacities", c.opacities))}
            # Frozen colours in half precision (relative error 5e-4, under a display step):
            # a region's band holds ~1 M surfels; SH are over half their bytes (degree 1) and
            # 4/5 at degree 3.
            self.context["sh"] = torch.from_numpy(c.sh.astype(np.float16))
            # world radius beyond which a disk's alpha stays under the rasteriser's alpha_min
            # (opacity <= 1: sqrt(2 ln 255) = 3.33 sigma): the frustum cull of render()
            self._context_radii = CONTEXT_SIGMAS * c.scales.max(axis=1).astype(np.float64)
        self._context_fit = np.zeros(0, np.int64)
        if self.context is not None and context_start is not None:
            start = np.asarray(context_start, bool)
            if start.shape != (int(self.context["means"].shape[0]),):
                raise ValueError(f"context_start has shape {start.shape}, the context holds "
                                 f"{int(self.context['means'].shape[0])} surfels")
            self._context_fit = np.flatnonzero(start)
        # classes of the context rows the colour start fits (their group slopes)
        self._context_classes = None
        if len(self._context_fit) and context.semantic_ids is not None:
            self._context_classes = context.semantic_ids[self._context_fit]
        self.context_started = 0    # context rows whose colours the start fitted (or restored)
        self.params = P.to_params(field)
        for p in self.params.values():
            p.requires_grad_(True)
        k = self.params["sh"].shape[1]
        sh_scale = torch.full((k, 1), float(config.lr.sh_rest_factor))
        sh_scale[0] = 1.0
        self.optimizer = SelectiveAdam(self.params, self._lrs(0), lr_scales={"sh": sh_scale},
                                       eps_by_key={"sh": config.lr.adam_eps_sh})
        st = config.strategy
        self.strategy = MCMCStrategy(noise_scale=st.noise_scale, gate_sharpness=st.gate_sharpness,
                                     gate_threshold=st.gate_threshold,
                                     relocate_every=st.relocate_every, dead_opacity=st.dead_opacity,
                                     max_relocate_frac=st.max_relocate_frac,
                                     densify_frac=st.densify_frac,
                                     redundant_coef=st.redundant_coef, seed=config.seed)
        self.prior, self.env = prior, env
        self.vertices, self.faces, self.face_ids = proxy
        self.face_index = None if face_index is None else np.asarray(face_index, np.int64).copy()
        self.shadow = shadow
        self.background_fn = background_fn
        self.terms = active_terms(config, prior) if terms is None else list(terms)
        self.term_state = dict(term_state or {})
        for term, _ in self.terms:
            if term.setup is not None and term.name not in self.term_state:
                self.term_state[term.name] = term.setup(config, prior)
        self.render_needs = {n for term, _ in self.terms for n in term.needs}
        self.views = views
        # Per-surfel σ of the 3D smoothing filter (ggds/antialias.py), or None when off.
        self.filter3d = self._filter_sigma(field.positions, np.arange(field.n))
        # Per training view, what a step needs and cannot cheaply derive again: the packed
        # G-buffer and the background (33 B/px; the unpacked ViewData is 65).
        self._view_cache: dict[int, tuple[PackedGBuffer, torch.Tensor | None]] = {}
        self._faces = FaceTable.of(self.vertices, self.faces, self.face_ids)
        self._key = next(_RUN_KEYS)
        self.rng = np.random.default_rng(config.seed)
        self.step_index = 0
        self.history: list[dict] = []
        self.seconds = 0.0

    # ------------------------------------------------------------ schedules
    def _lrs(self, step: int) -> dict:
        c, lr = self.cfg, self.cfg.lr
        return {"means": lr_at(step, c.steps, lr.means, lr.means_end), "quats": lr.quats,
                "scales": lr.scales, "opacities": lr.opacities,
                "sh": lr.sh_dc if lr.sh_dc_end is None else lr_at(step, c.steps, lr.sh_dc,
                                                                  lr.sh_dc_end)}

    def t_min(self, step: int) -> float:
        c = self.cfg
        f = min(step / max(c.steps - 1, 1), 1.0)
        return c.t_min_start + (c.t_min_end - c.t_min_start) * f

    def view_data(self, i: int) -> ViewData:
        """Training view ``i`` with its G-buffer (keyed by run and view, so a prior can cache
        per view), background and focus mask."""
        if i not in self._view_cache:
            cam = self.views[i].camera
            self._view_cache[i] = (self._pack(cam),
                                   self.background_fn(cam) if self.background_fn else None)
        packed, bg = self._view_cache[i]
        gb = packed.unpack(self._faces, key=(self._key, i), fine=self._finer(self.views[i].camera))
        return ViewData(self.views[i], gb, bg, focus_mask(gb, self.focus))

    def _pack(self, camera) -> PackedGBuffer:
        return pack_view_gbuffer(camera, self.vertices, self.faces, self.shadow)

    def _finer(self, camera):
        return finer(camera, self.vertices, self.faces, self._faces, self.shadow)

    def release_views(self) -> None:
        """Drop what the steps kept per training view (packed G-buffers, backgrounds, the
        prior's cached targets: ~6 MB per view at 480x270); view_data builds them again."""
        self.prior.forget([(self._key, i) for i in self._view_cache])
        self._view_cache.clear()

    # ------------------------------------------------------------ anti-aliasing
    def _filter_sigma(self, positions: np.ndarray, rows: np.ndarray) -> torch.Tensor | None:
        from lsd3d_usd.ggds.optim.antialias import filter_sigma
        k = self.cfg.filter_3d
        if not k > 0:
            return None
        return torch.from_numpy(filter_sigma(positions[rows], [v.camera for v in self.views], k))

    @torch.no_grad()
    def _filter_coef(self) -> torch.Tensor | None:
        """(N,) fraction of each surfel's opacity the 3D filter keeps (None without it)."""
        if self.filter3d is None:
            return None
        from lsd3d_usd.ggds.optim.antialias import smooth
        s = self.params["scales"].exp()
        return smooth(s, torch.ones(len(s)), self.filter3d)[1]

    @torch.no_grad()
    def _observe_residual(self, x: torch.Tensor, x_hat: torch.Tensor, cam, rows: torch.Tensor):
        """Feed the strategy the residual |x − x̂| (3×3 box mean) at the projected centres of
        the surfels this view showed (error-driven densification, ggds/strategy.py)."""
        from lsd3d_usd.ggds.filters import box_filter
        r = box_filter((x - x_hat).abs().mean(-1), 1)
        p = self.params["means"][rows].double().numpy()
        uv, z = cam.project(p)
        i, j = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        ok = (z > cam.near) & (i >= 0) & (j >= 0) & (i < cam.width) & (j < cam.height)
        vals = torch.full((len(p),), float("nan"))
        ii = torch.from_numpy(i[ok].astype(np.int64))
        jj = torch.from_numpy(j[ok].astype(np.int64))
        vals[torch.from_numpy(ok)] = r[jj, ii]
        self.strategy.observe(rows, vals, self.params["means"].shape[0])

    def activated(self, params: dict) -> dict:
        """The renderer's values of ``params``: constrained (params.activated) and, with the
        3D smoothing filter on, each disk convolved with its frequency limit."""
        a = P.activated(params)
        if self.filter3d is not None:
            from lsd3d_usd.ggds.optim.antialias import smooth
            a["scales"], a["opacities"] = smooth(a["scales"], a["opacities"], self.filter3d)
        return a

    # ------------------------------------------------------------ rendering
    def render(self, camera, params=None, *, background=None, **settings) -> RasterResult:
        """Rasterise the (activated) parameters for ``camera``; ``settings`` are RasterSettings
        fields (near/far come from the camera)."""
        a = self.activated(self.params if params is None else params)
        if self.context is not None:   # trainable rows first: visible_index < n are ours
            # only the neighbours' surfels that can reach this view: the same image, without
            # per-surfel buffers and gradient rows for the rest (~1.5x a chunk's surfels)
            from lsd3d_usd.conditioning.visibility import spheres_in_view
            keep = torch.from_numpy(np.flatnonzero(spheres_in_view(
                self.context["means"].numpy(), self._context_radii, camera)))
            a = {k: torch.cat([a[k], self.context[k].index_select(0, keep).to(a[k].dtype)])
                 for k in a}
        return rasterize(a["means"], a["quats"], a["scales"], a["opacities"], a["sh"],
                         camera.viewmat, camera.K, camera.width, camera.height,
                         settings=RasterSettings.for_camera(camera, **settings), background=background)

    # ------------------------------------------------------------ one step
    def step(self) -> dict:
        t0 = time.perf_counter()
        cfg, k = self.cfg, self.step_index
        vi = int(self.rng.integers(len(self.views)))
        vd = self.view_data(vi)
        cam = vd.view.camera
        t_view = time.perf_counter()
        dist_kw = {"distortion": True} if "distortion" in self.render_needs else {}
        out = self.render(cam, background=vd.background, normal_space="camera", **dist_kw)
        x = out.rgb
        t_render = time.perf_counter()
        t = float(self.rng.uniform(self.t_min(k), cfg.t_max))
        with torch.no_grad():
            x_hat = self.prior.target(x.detach().clamp(0, None), vd.gbuffer, self.env, t,
                                      n_steps=cfg.n_denoise, seed=cfg.seed * 100003 + k)
        t_prior = time.perf_counter()
        w = losses.omega(t, cfg.omega)
        if vd.mask is not None:   # outside the focus the target stands in: no difference there
            x = torch.where(vd.mask[..., None], x, x_hat)
        ctx = StepContext(x, x_hat, out, vd.gbuffer, cam, t, cfg, self.term_state)
        terms = {}
        for term, weight in self.terms:
            terms[term.name] = (weight * w if term.image else weight) * term.fn(ctx)
        loss = sum(terms.values())
        for p in self.params.values():
            p.grad = None
        t_loss = time.perf_counter()
        loss.backward()
        t_backward = time.perf_counter()
        rows = out.visible_index
        if self.context is not None:
            rows = rows[rows < self.params["means"].shape[0]]
        lrs = self._lrs(k)
        self.optimizer.lrs = lrs
        self.optimizer.step(rows)
        if self.strategy.densify_frac > 0:
            self._observe_residual(x.detach(), x_hat, cam, rows)
        info = self.strategy.step_post_backward(self.params, self.optimizer, k + 1, lrs["means"],
                                                rows, filter_coef=self._filter_coef)
        if info["relocated"]:
            self._track_relocation()
        self.step_index += 1
        t_end = time.perf_counter()
        dt = t_end - t0
        timing = {"view_s": t_view - t0, "render_s": t_render - t_view, "prior_s": t_prior - t_render,
                  "loss_s": t_loss - t_prior, "backward_s": t_backward - t_loss,
                  "update_s": t_end - t_backward}
        self.seconds += dt
        rec = {"step": k, "view": vi, "t": round(t, 4), "loss": float(loss.detach()), "seconds": dt,
               "visible": int(rows.numel()), "psnr_target": psnr(x.detach(), x_hat),
               **{kk: float(v.detach()) for kk, v in terms.items()}, **info, **timing}
        self.history.append(rec)
        return rec

    def _track_relocation(self):
        # A relocated surfel sits on its source's disk: it inherits the source's seed face
        # and, seen by the same views, its frequency limit.
        dead, src = self.strategy.last_relocation
        if self.face_index is not None:
            self.face_index[dead.numpy()] = self.face_index[src.numpy()]
        if self.filter3d is not None:
            self.filter3d[dead] = self.filter3d[src]

    @torch.no_grad()
    def world_init(self) -> bool:
        """Start every surfel's SH colour from the prior, when the prior is world-consistent
        (Prior.shade_at; the procedural prior is, a diffusion prior is not): a per-surfel
        least-squares fit to the t = 1 targets of the training views (and ``fit_views``) that
        see it (worldfit.ViewFit; each training view's target is computed once and cached, as
        the steps would), and for surfels none sees, to the prior evaluated in 3D over its
        disk from the nearest cameras (worldfit.fit_sh). GGDS steps refine from there.
        Returns whether it ran."""
        from lsd3d_usd.ggds.colour_start.worldfit import (ViewFit, facing_ids, fit_sh, zonal_slopes)
        from lsd3d_usd.render.sh import sh_degree_of
        c = self.cfg
        f = self.field()
        if f.semantic_ids is None or f.n == 0:
            return False
        probe = self.prior.shade_at(f.positions[:1].astype(np.float64), f.normals()[:1],
                                    f.semantic_ids[:1], self.env)
        if probe is None:
            return False
        degree = sh_degree_of(self.params["sh"].shape[1])
        normals = f.normals()
        fit = ViewFit(f.n, degree)
        ctx = self._context_fit_inputs()
        ctx_fit = ViewFit(len(ctx[0]), degree) if ctx is not None else None
        from lsd3d_usd.memtune import release_free_memory
        n_train = len(self.views)
        for i in range(n_train + len(self.fit_views)):
            if i and i % TRIM_EVERY_VIEWS == 0:
                release_free_memory()
            fit_only = i >= n_train   # used once; a training view's G-buffer and target
            if fit_only:              # stay cached for the steps
                cam = self.fit_views[i - n_train].camera
                # no finer G-buffer: the fit averages a target over each surfel's disk
                # anyway (README sample: the same held-out PSNR, 30 s less)
                gb = self._pack(cam).unpack(self._faces, key=(self._key, "fit", i))
            else:
                cam, gb = self.views[i].camera, self.view_data(i).gbuffer
            target = self.prior.target(torch.zeros(cam.height, cam.width, 3), gb,
                                       self.env, 1.0, n_steps=c.n_denoise, seed=c.seed)
            fit.add_view(f.positions, f.scales, normals, cam, target, gb.depth.numpy())
            if ctx_fit is not None:
                ctx_fit.add_view(*ctx, cam, target, gb.depth.numpy())
            if fit_only:
                self.prior.forget([gb.key])
        slopes = ctx_slopes = None
        if c.world_init_zonal_prior:   # each group's slope from every surfel the start fits
            fits = [(fit, normals, facing_ids(normals, f.semantic_ids))]
            if ctx_fit is not None and self._context_classes is not None:
                fits.append((ctx_fit, ctx[2], facing_ids(ctx[2], self._context_classes)))
            table = zonal_slopes(fits, c.world_init_ridge, c.world_init_ridge_tangent)
            slopes = (fits[0][2], table)
            ctx_slopes = (fits[1][2], table) if len(fits) > 1 else None
        sh, seen = fit.solve(normals, c.world_init_ridge, c.world_init_ridge_tangent,
                             slopes=slopes)
        if not seen.all():
            rest = np.flatnonzero(~seen)
            sub = fit_sh(self.prior, self.env, f.subset(rest),
                         [v.camera for v in self.views + self.fit_views],
                         degree=degree, shadow=self.shadow, samples=c.world_init_samples,
                         ridge=c.world_init_ridge, ridge_tangent=c.world_init_ridge_tangent,
                         seed=c.seed)
            sh[rest] = sub
        self.params["sh"][:] = torch.from_numpy(sh)
        if ctx_fit is not None:   # unseen context rows keep their colours
            csh, cseen = ctx_fit.solve(ctx[2], c.world_init_ridge, c.world_init_ridge_tangent,
                                       slopes=ctx_slopes)
            rows = torch.from_numpy(self._context_fit[cseen])
            self.context["sh"][rows] = torch.from_numpy(csh[cseen]).to(torch.float16)
            self.context_started = int(cseen.sum())
        return True

    def _context_fit_inputs(self):
        """(positions, scales, normals) of the context rows the colour start fits, or None."""
        if not len(self._context_fit):
            return None
        from lsd3d_usd.splats.field import quat_normals
        rows = torch.from_numpy(self._context_fit)
        return tuple(self.context[k].index_select(0, rows).numpy() for k in ("means", "scales")) \
            + (quat_normals(self.context["quats"].index_select(0, rows).numpy()),)

    # ------------------------------------------------------------ results
    def field(self) -> SurfelField:
        """The surfels as the renderer sees them (the 3D filter baked in)."""
        return P.to_field(self.params, *self.semantics, activate=self.activated)

    def checkpoint(self, optimizer: bool = True) -> tuple[dict, dict]:
        """(tensors, meta): everything a resume needs, as flat named tensors (safetensors) and
        plain JSON data. Without ``optimizer`` the Adam moments are left out (a resume then
        restarts them at zero)."""
        tensors = {f"params.{k}": v.detach().contiguous() for k, v in self.params.items()}
        if optimizer:
            st = self.optimizer.state_dict()
            tensors.update({f"adam.m.{k}": v.contiguous() for k, v in st["m"].items()})
            tensors.update({f"adam.v.{k}": v.contiguous() for k, v in st["v"].items()})
            tensors["adam.t"] = st["t"].contiguous()
        tensors.update(self.strategy.state_tensors())
        if self.face_index is not None:
            tensors["face_index"] = torch.from_numpy(np.ascontiguousarray(self.face_index))
        if self.filter3d is not None:
            tensors["filter3d"] = self.filter3d.contiguous()
        if len(self._context_fit):   # the context colours the start fitted
            tensors["context.sh"] = self.context["sh"].index_select(
                0, torch.from_numpy(self._context_fit)).contiguous()
        meta = {"step": self.step_index, "rng": self.rng.bit_generator.state,
                "history": list(self.history), "seconds": self.seconds,
                "config": to_dict(self.cfg), "optimizer": bool(optimizer),
                "context_started": self.context_started}
        return tensors, meta

    def restore(self, tensors: dict, meta: dict) -> None:
        """Inverse of :meth:`checkpoint`. Shapes must match the run's surfels."""
        with torch.no_grad():
            for k, p in self.params.items():
                v = tensors.get(f"params.{k}")
                if v is None or v.shape != p.shape:
                    got = "missing" if v is None else f"shape {tuple(v.shape)}"
                    raise ValueError(f"checkpoint params.{k} is {got}, the scene's surfels give "
                                     f"{tuple(p.shape)}")
                p.copy_(v)
        if meta.get("optimizer", True) and "adam.t" in tensors:
            self.optimizer.load_state_dict({
                "m": {k: tensors[f"adam.m.{k}"] for k in self.params},
                "v": {k: tensors[f"adam.v.{k}"] for k in self.params}, "t": tensors["adam.t"]})
        self.step_index = int(meta["step"])
        self.rng.bit_generator.state = meta["rng"]
        self.strategy.load_state_tensors(tensors)
        self.history = list(meta["history"])
        self.seconds = float(meta.get("seconds", 0.0))
        if "face_index" in tensors:
            self.face_index = tensors["face_index"].numpy().astype(np.int64).copy()
        if self.filter3d is not None and "filter3d" in tensors:
            self.filter3d = tensors["filter3d"].clone()
        csh = tensors.get("context.sh")
        if csh is not None and len(self._context_fit):
            if csh.shape[0] != len(self._context_fit):
                raise ValueError(f"checkpoint context.sh holds {csh.shape[0]} rows, the "
                                 f"region's unfinished neighbours {len(self._context_fit)}")
            self.context["sh"][torch.from_numpy(self._context_fit)] = csh.to(torch.float16)
            self.context_started = int(meta.get("context_started", len(self._context_fit)))

    @torch.no_grad()
    def evaluate(self, views: list[View], t_eval: float = 1.0) -> dict:
        """Held-out metrics: PSNR of renders against the prior's targets (t_eval), median
        relative depth error and median normal angle error against the proxy G-buffer, and
        the fraction of surfels more than 0.2 m from their seed proxy face."""
        psnrs, rel_errs, ang_errs = [], [], []
        for j, v in enumerate(views):
            cam = v.camera
            gb = table_gbuffer(cam, self.vertices, self.faces, self._faces, self.shadow)
            bg = self.background_fn(cam) if self.background_fn else None
            out = self.render(cam, background=bg, normal_space="world")
            x_hat = self.prior.target(out.rgb.clamp(0, None), gb, self.env, t_eval,
                                      n_steps=self.cfg.n_denoise, seed=10_000 + j)
            psnrs.append(psnr(out.rgb, x_hat, focus_mask(gb, self.focus)))
            mask = gb.valid & (out.alpha > 0.5)
            if mask.any():
                d = out.depth_expected[mask]
                rel_errs.append((d - gb.depth[mask]).abs() / gb.depth[mask])
                n = out.normal[mask]
                n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
                pn = gb.normal[mask]
                cos = (n * pn).sum(-1).abs().clamp(max=1.0)  # rendered normals face the camera
                ang_errs.append(torch.rad2deg(torch.acos(cos)))
        res = {"psnr_novel": float(np.mean(psnrs)) if psnrs else float("nan"),
               "depth_rel_err": float(torch.cat(rel_errs).median()) if rel_errs else float("nan"),
               "normal_err_deg": float(torch.cat(ang_errs).median()) if ang_errs else float("nan")}
        res["off_surface_frac"] = self.off_surface_fraction()
        return res

    def off_surface_fraction(self, threshold: float = 0.2) -> float:
        """Fraction of surfels farther than ``threshold`` from their seed proxy face (surfels
        whose seed face is not among the run's proxy faces, index -1, are left out)."""
        if self.face_index is None or len(self.faces) == 0:
            return float("nan")
        known = self.face_index >= 0
        if not known.any():
            return float("nan")
        rows = np.flatnonzero(known)
        means = self.params["means"].detach().numpy()
        off = 0
        for a in range(0, len(rows), 1 << 16):   # float64 temporaries of a block of rows
            r = rows[a:a + (1 << 16)]
            tri = self.vertices[self.faces[self.face_index[r]]].astype(np.float64)
            d = point_triangle_distance(means[r].astype(np.float64), tri[:, 0], tri[:, 1],
                                        tri[:, 2])
            off += int((d > threshold).sum())
        return off / len(rows)
