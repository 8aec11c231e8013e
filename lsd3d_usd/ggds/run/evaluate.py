"""Held-out evaluation of surfels against the prior: PSNR of the render against the prior's
held-out target (priors.base.heldout_target; background = the env map), median depth and
normal errors against the proxy G-buffer, and the fraction of surfels off their seed proxy
face. One render path for a run in progress (its parameters and context) and for a finished
field read back from USD, at any resolution (2×: aliasing, surfels trained at 1× seen with
twice the pixels)."""
from __future__ import annotations

import math

import numpy as np
import torch

from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.conditioning.view_sampling import View
from lsd3d_usd.ggds.priors.base import heldout_target
from lsd3d_usd.ggds.run.training_views import focus_mask
from lsd3d_usd.render.raster_types import RasterSettings
from lsd3d_usd.render.rasterize import rasterize


def psnr(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB of images clamped to [0, 1], over ``mask`` (None: every pixel); 99 for an
    error below 1e-10 (or an empty mask)."""
    err = (x.clamp(0, 1) - y.clamp(0, 1)) ** 2
    mse = float(err.mean() if mask is None else err[mask].mean() if mask.any() else 0.0)
    return 99.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def scaled(views: list[View], factor: float) -> list[View]:
    """The same views with ``factor`` × as many pixels per side (same field of view)."""
    out = []
    for v in views:
        c = v.camera
        w, h = max(1, round(c.width * factor)), max(1, round(c.height * factor))
        out.append(View(c.with_resolution(w, h), v.kind, v.lane_id, v.offset_m))
    return out


def field_renderer(field):
    """render(camera, background, **settings) -> RasterResult of a SurfelField as stored."""
    def t(a):   # USD arrays are read-only
        return torch.from_numpy(np.array(a, copy=True))
    arrays = [t(field.positions), t(field.orientations), t(field.scales), t(field.opacities),
              t(field.sh)]

    def render(camera, *, background=None, **settings):
        return rasterize(*arrays, camera.viewmat, camera.K, camera.width, camera.height,
                         settings=RasterSettings.for_camera(camera, **settings),
                         background=background)
    return render


@torch.no_grad()
def render_and_target(render, view: View, prior, cond: Conditioning, j: int, *,
                      t_eval: float = 1.0, n_denoise: int = 5, **settings):
    """(RasterResult of ``render`` for one view, the prior's held-out target, the view's
    G-buffer)."""
    cam = view.camera
    gb = cond.gbuffer(cam)
    out = render(cam, background=cond.background(cam), **settings)
    return out, heldout_target(prior, out.rgb, gb, cond.env, j, t=t_eval, n_steps=n_denoise), gb


@torch.no_grad()
def evaluate_views(render, views: list[View], prior, cond: Conditioning, *, t_eval: float = 1.0,
                   n_denoise: int = 5, focus=None) -> dict:
    """Held-out figures of ``render`` over ``views``: psnr_novel (mean over views, pixels in
    ``focus`` only), depth_rel_err and normal_err_deg (medians over pixels where the proxy
    and the surfels are both present), and psnr per view."""
    psnrs, rel_errs, ang_errs = [], [], []
    for j, v in enumerate(views):
        out, x_hat, gb = render_and_target(render, v, prior, cond, j, t_eval=t_eval,
                                           n_denoise=n_denoise, normal_space="world")
        psnrs.append(psnr(out.rgb, x_hat, focus_mask(gb, focus)))
        mask = gb.valid & (out.alpha > 0.5)
        if mask.any():
            d = out.depth_expected[mask]
            rel_errs.append((d - gb.depth[mask]).abs() / gb.depth[mask])
            n = out.normal[mask]
            n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
            pn = gb.normal[mask]
            cos = (n * pn).sum(-1).abs().clamp(max=1.0)  # rendered normals face the camera
            ang_errs.append(torch.rad2deg(torch.acos(cos)))
    return {"psnr_novel": float(np.mean(psnrs)) if psnrs else float("nan"),
            "depth_rel_err": float(torch.cat(rel_errs).median()) if rel_errs else float("nan"),
            "normal_err_deg": float(torch.cat(ang_errs).median()) if ang_errs else float("nan"),
            "psnr_per_view": psnrs}


def heldout_psnr(field, views: list[View], prior, cond: Conditioning, *, t_eval: float = 1.0,
                 n_denoise: int = 5) -> list[float]:
    """PSNR per view of a finished SurfelField against the held-out targets (every pixel)."""
    return evaluate_views(field_renderer(field), views, prior, cond, t_eval=t_eval,
                          n_denoise=n_denoise)["psnr_per_view"]


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


def off_surface_fraction(means: np.ndarray, face_index: np.ndarray | None, vertices: np.ndarray,
                         faces: np.ndarray, threshold: float = 0.2) -> float:
    """Fraction of surfels farther than ``threshold`` from their seed proxy face (surfels
    whose seed face is not among the proxy's faces, index -1, are left out)."""
    if face_index is None or len(faces) == 0:
        return float("nan")
    known = face_index >= 0
    if not known.any():
        return float("nan")
    rows = np.flatnonzero(known)
    off = 0
    for a in range(0, len(rows), 1 << 16):   # float64 temporaries of a block of rows
        r = rows[a:a + (1 << 16)]
        tri = vertices[faces[face_index[r]]].astype(np.float64)
        d = point_triangle_distance(means[r].astype(np.float64), tri[:, 0], tri[:, 1], tri[:, 2])
        off += int((d > threshold).sum())
    return off / len(rows)
