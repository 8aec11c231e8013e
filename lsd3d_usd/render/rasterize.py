"""Differentiable rasteriser of 2D Gaussian surfels (2DGS, Huang et al. 2024): the one
functional entry point, `rasterize`.

One call: the inputs are validated (render/checks.py, the same for every backend), the
backend (render/backends.py: "numba" by default, "torch") computes the accumulations and
their gradients, and the outputs every backend shares are composed here: the background
behind the final transmittance, the expected depth, world-space normals, the semantic image.
Settings go in as one RasterSettings, images and stats come out as one RasterResult
(render/raster_types.py).
"""
from __future__ import annotations

import time

import torch

from lsd3d_usd.render import projection as proj
from lsd3d_usd.render.backends import get_backend
from lsd3d_usd.render.checks import check_inputs
from lsd3d_usd.render.raster_types import Backend, RasterResult, RasterSettings


def rasterize(means, quats, scales, opacities, sh, viewmat, K, width, height, *,
              settings: RasterSettings | None = None, background=None, semantic_ids=None,
              backend: str | Backend = "numba", values_checked: bool = False) -> RasterResult:
    """Render 2D Gaussian surfels (gsplat-style arrays in, a RasterResult out).

    means (N,3), quats (N,4) xyzw, scales (N,2) linear std-devs along the local x/y axes,
    opacities (N,) in [0,1], sh (N,K,3) (K = (deg+1)^2, 3DGS ordering): torch tensors (or
    numpy arrays) on one device. viewmat (4,4) world->camera in OpenCV axes, K (3,3) pixel
    intrinsics (pixel centres at +0.5), width, height. settings: RasterSettings (None: the
    defaults; RasterSettings.for_camera(camera) takes a camera's near/far). background: None,
    (3,) or (H,W,3) composited behind with the final transmittance (the env map per pixel
    direction). semantic_ids: optional (N,) int per surfel, giving result.semantic.
    backend: a name registered in render/backends.py ("numba", "torch") or a backend object.

    Gradients flow from rgb, alpha, depth_acc/depth_expected, depth_median, normal and
    distortion to means, quats, scales, opacities, sh (and background). Bad input is one
    InputError line naming the array and the index. values_checked: True only for the arrays
    of a SurfelField whose values the scene reader validated (SurfelField.checked, as
    views.frame.render_surfels passes it): the per-value scans of the surfels are skipped.
    """
    t_start = time.perf_counter()
    settings = RasterSettings() if settings is None else settings
    impl = get_backend(backend)
    inputs, background, sem = check_inputs(means, quats, scales, opacities, sh, viewmat, K, width,
                                           height, settings, background, semantic_ids,
                                           values_checked)
    t_backend = time.perf_counter()
    out = impl.forward(inputs, settings)
    stats = out.stats
    stats.timings["backend_s"] = time.perf_counter() - t_backend
    rgb, alpha, dacc = out.rgb, out.alpha, out.depth_acc
    if background is not None:
        rgb = rgb + (1.0 - alpha)[..., None] * background.to(rgb.device, rgb.dtype)
    depth = torch.where(alpha > 1e-6, dacc / alpha.clamp_min(1e-6), torch.zeros_like(dacc))
    normal = out.normal
    if settings.normal_space == "world":
        rot_c, _ = proj.camera_frame(inputs.viewmat)
        normal = normal @ rot_c.to(normal.device, normal.dtype)
    semantic = None
    if sem is not None:
        ext = torch.cat([sem.to(out.argmax.device), sem.new_full((1,), -1).to(out.argmax.device)])
        semantic = ext[out.argmax]  # argmax -1 (nothing) picks the appended -1
    stats.timings["total_s"] = time.perf_counter() - t_start
    return RasterResult(rgb=rgb, alpha=alpha, depth_expected=depth, depth_acc=dacc,
                        depth_median=out.depth_median, normal=normal, semantic=semantic,
                        distortion=out.distortion, visible_index=out.visible_index, stats=stats)
