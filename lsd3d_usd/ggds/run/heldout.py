"""Held-out evaluation of a finished surfel field against the prior, at any resolution: the
figure GGDSRun.evaluate reports (PSNR of the render against the prior's target at t = 1,
background = the env map), computed from arrays alone, so a benchmark can ask it of a scene
read back from USD, and at 2× the training resolution (aliasing: surfels trained at 1×
seen with twice the pixels)."""
from __future__ import annotations

import numpy as np
import torch

from lsd3d_usd.conditioning.views import View


def scaled(views: list[View], factor: float) -> list[View]:
    """The same views with ``factor`` × as many pixels per side (same field of view)."""
    out = []
    for v in views:
        c = v.camera
        w, h = max(1, round(c.width * factor)), max(1, round(c.height * factor))
        out.append(View(c.with_resolution(w, h), v.kind, v.lane_id, v.offset_m))
    return out


@torch.no_grad()
def render_and_target(field, view: View, prior, env, proxy, *, background_fn=None, shadow=None,
                      t_eval: float = 1.0, n_denoise: int = 5, seed: int = 10_000):
    """(render rgb (H,W,3), prior target (H,W,3)) of ``field`` (a SurfelField) for one view."""
    from lsd3d_usd.conditioning.gbuffer import view_gbuffer
    from lsd3d_usd.render.raster_types import RasterSettings
    from lsd3d_usd.render.rasterize import rasterize
    cam = view.camera
    gb = view_gbuffer(cam, proxy[0], proxy[1], proxy[2], shadow)
    bg = background_fn(cam) if background_fn is not None else None
    t = lambda a: torch.from_numpy(np.array(a, copy=True))  # noqa: E731  (USD arrays are read-only)
    x = rasterize(t(field.positions), t(field.orientations), t(field.scales), t(field.opacities),
                  t(field.sh), cam.viewmat, cam.K, cam.width, cam.height,
                  settings=RasterSettings.for_camera(cam), background=bg).rgb
    return x, prior.target(x.clamp(0, None), gb, env, t_eval, n_steps=n_denoise, seed=seed)


def psnr(x: torch.Tensor, y: torch.Tensor) -> float:
    mse = float(((x.clamp(0, 1) - y.clamp(0, 1)) ** 2).mean())
    return 99.0 if mse <= 1e-10 else -10.0 * float(np.log10(mse))


def heldout_psnr(field, views: list[View], prior, env, proxy, *, background_fn=None,
                 shadow=None, t_eval: float = 1.0, n_denoise: int = 5) -> list[float]:
    """PSNR per view (seeds as GGDSRun.evaluate: 10000 + index)."""
    return [psnr(*render_and_target(field, v, prior, env, proxy, background_fn=background_fn,
                                    shadow=shadow, t_eval=t_eval, n_denoise=n_denoise,
                                    seed=10_000 + j))
            for j, v in enumerate(views)]
