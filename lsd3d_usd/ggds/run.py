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

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from lsd3d_usd.configtree import to_dict
from lsd3d_usd.ggds import losses, params as P
from lsd3d_usd.ggds.adam import SelectiveAdam, lr_at
from lsd3d_usd.ggds.cameras import View
from lsd3d_usd.ggds.conditioning import ShadowMap, view_gbuffer
from lsd3d_usd.ggds.config import GGDSConfig
from lsd3d_usd.ggds.prior_base import GBuffer, Prior, PriorEnv
from lsd3d_usd.ggds.strategy import MCMCStrategy
from lsd3d_usd.ggds.terms import StepContext, active_terms
from lsd3d_usd.render.raster_types import RasterResult, RasterSettings
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.splats.field import SurfelField


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
    image terms and held-out PSNR compare only pixels whose proxy surface lies there."""

    def __init__(self, field: SurfelField, proxy: tuple[np.ndarray, np.ndarray, np.ndarray | None],
                 views: list[View], prior: Prior, env: PriorEnv, config: GGDSConfig, *,
                 background_fn=None, shadow: ShadowMap | None = None,
                 face_index: np.ndarray | None = None, terms=None, term_state: dict | None = None,
                 context: SurfelField | None = None, focus=None):
        self.cfg = config
        self.init_field = field
        self.focus = focus
        self.context = None
        if context is not None and context.n:
            c = context.with_sh_degree(field.sh_degree)
            self.context = {k: torch.from_numpy(np.ascontiguousarray(v, np.float32)) for k, v in
                            (("means", c.positions), ("quats", c.orientations),
                             ("scales", c.scales), ("opacities", c.opacities), ("sh", c.sh))}
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
                                     max_relocate_frac=st.max_relocate_frac, seed=config.seed)
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
        self._view_cache: dict[int, ViewData] = {}
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
        if i not in self._view_cache:
            v = self.views[i]
            gb = view_gbuffer(v.camera, self.vertices, self.faces, self.face_ids, self.shadow)
            bg = self.background_fn(v.camera) if self.background_fn else None
            self._view_cache[i] = ViewData(v, gb, bg, focus_mask(gb, self.focus))
        return self._view_cache[i]

    # ------------------------------------------------------------ rendering
    def render(self, camera, params=None, *, background=None, **settings) -> RasterResult:
        """Rasterise the (activated) parameters for ``camera``; ``settings`` are RasterSettings
        fields (near/far come from the camera)."""
        a = P.activated(self.params if params is None else params)
        if self.context is not None:   # trainable rows first: visible_index < n are ours
            a = {k: torch.cat([a[k], self.context[k]]) for k in a}
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
        info = self.strategy.step_post_backward(self.params, self.optimizer, k + 1, lrs["means"], rows)
        if info["relocated"] and self.face_index is not None:
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
        # A relocated surfel sits on its source's disk: it inherits the source's seed face.
        dead, src = self.strategy.last_relocation
        self.face_index[dead.numpy()] = self.face_index[src.numpy()]

    @torch.no_grad()
    def world_init(self, offsets_sigma: float = 0.7, batch: int = 400_000) -> bool:
        """Set every surfel's DC colour to the prior's colour averaged over its disk (centre and
        four points at ±offsets_sigma·σ along its axes), seen from the nearest training camera,
        when the prior can be evaluated in world space (Prior.shade_at; the procedural prior
        can, a diffusion prior cannot). Image-space GGDS steps refine from there. Returns
        whether it ran."""
        sem = self.init_field.semantic_ids
        if sem is None:
            return False
        from lsd3d_usd.splats.field import SH_C0, quat_to_matrix
        f = self.field()
        R = quat_to_matrix(f.orientations)
        s = f.scales.astype(np.float64) * offsets_sigma
        offs = np.stack([np.zeros((f.n, 3)), R[..., 0] * s[:, :1], -R[..., 0] * s[:, :1],
                         R[..., 1] * s[:, 1:], -R[..., 1] * s[:, 1:]], axis=1)  # (N,5,3)
        pts = f.positions.astype(np.float64)[:, None, :] + offs
        nrm = np.repeat(R[:, None, :, 2], 5, axis=1)
        ids = np.repeat(sem[:, None], 5, axis=1)
        flat_p, flat_n, flat_i = pts.reshape(-1, 3), nrm.reshape(-1, 3), ids.reshape(-1)
        vis = None
        if self.shadow is not None:
            vis = self.shadow.visibility(flat_p + 0.05 * flat_n)
        view = flat_p - self._nearest_eye(flat_p)
        cols = np.empty((len(flat_p), 3), np.float32)
        for a in range(0, len(flat_p), batch):
            b = slice(a, a + batch)
            c = self.prior.shade_at(flat_p[b], flat_n[b], flat_i[b], self.env, view_dirs=view[b],
                                    sun_visibility=None if vis is None else vis[b])
            if c is None:
                return False
            cols[b] = c.numpy()
        rgb = cols.reshape(f.n, 5, 3).mean(axis=1)
        self.params["sh"][:, 0, :] = torch.from_numpy((rgb - 0.5) / SH_C0)
        return True

    def _nearest_eye(self, points: np.ndarray) -> np.ndarray:
        """Centre of the nearest training camera per point (or a point 10 m above)."""
        if not self.views:
            return points + np.array([0.0, 0.0, 10.0])
        from scipy.spatial import cKDTree
        eyes = np.array([v.camera.center for v in self.views])
        _, k = cKDTree(eyes).query(points, k=1)
        return eyes[k]

    # ------------------------------------------------------------ results
    def field(self) -> SurfelField:
        return P.to_field(self.params, self.init_field)

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
        tensors["strategy.rng"] = self.strategy._gen.get_state()
        if self.face_index is not None:
            tensors["face_index"] = torch.from_numpy(np.ascontiguousarray(self.face_index))
        meta = {"step": self.step_index, "rng": self.rng.bit_generator.state,
                "history": list(self.history), "seconds": self.seconds,
                "config": to_dict(self.cfg), "optimizer": bool(optimizer)}
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
        self.strategy._gen.set_state(tensors["strategy.rng"])
        self.history = list(meta["history"])
        self.seconds = float(meta.get("seconds", 0.0))
        if "face_index" in tensors:
            self.face_index = tensors["face_index"].numpy().astype(np.int64).copy()

    @torch.no_grad()
    def evaluate(self, views: list[View], t_eval: float = 1.0) -> dict:
        """Held-out metrics: PSNR of renders against the prior's targets (t_eval), median
        relative depth error and median normal angle error against the proxy G-buffer, and
        the fraction of surfels more than 0.2 m from their seed proxy face."""
        psnrs, rel_errs, ang_errs = [], [], []
        for j, v in enumerate(views):
            cam = v.camera
            gb = view_gbuffer(cam, self.vertices, self.faces, self.face_ids, self.shadow)
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
        pos = self.params["means"].detach().numpy().astype(np.float64)[known]
        tri = self.vertices[self.faces[self.face_index[known]]].astype(np.float64)
        d = point_triangle_distance(pos, tri[:, 0], tri[:, 1], tri[:, 2])
        return float((d > threshold).mean())
