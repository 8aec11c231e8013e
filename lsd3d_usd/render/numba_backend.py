"""The "numba" backend: the fast CPU path (float32 kernels, hand-written backward).

Pipeline, all numba (no torch ops over the N surfels, no per-pixel autograd graph):
per-surfel projection, culling, SH colour and exact screen bounds (float64 per surfel,
camera-relative) compacted to the visible set (kernels_prep.project_visible); 16x16 tile
binning with a parallel per-tile depth sort (kernels.bin_sorted); the forward tile kernel
(kernels.forward). The backward: the tile kernel's hand-written backward (per pair), then the
projection's chain rule for the visible surfels only, scattered into the N-size gradients in
the same pass. With settings.distortion the tile kernels also carry the 2DGS depth-distortion
moments per pixel (a separately compiled variant: the default kernels do not see them).

The forward runs before the autograd.Function is applied; the Function only hands its
results out and keeps what the backward needs, so everything the forward found (visible
index, stats) flows back to the caller as plain return values.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.render import kernels
from lsd3d_usd.render import kernels_prep as kprep
from lsd3d_usd.render import precompile
from lsd3d_usd.render import projection as proj
from lsd3d_usd.render.raster_types import BackendOutput, RasterInputs, RasterSettings, RasterStats


@dataclass
class _View:
    """The camera and image numbers the kernels take, derived once per render."""
    Rv: np.ndarray          # (3,3) float64 world -> camera rotation
    C: np.ndarray           # (3,) float64 camera centre
    K: np.ndarray           # (3,3) float64
    width: int
    height: int
    tile: int
    ntx: int
    nty: int
    tile_order: np.ndarray  # fixed shuffled tile visiting order (load balance, see kernels)
    deg: int


@dataclass
class _Forward:
    """Forward results the backward needs (the kernels' saved state)."""
    arrs: tuple             # float32 numpy means, quats, scales, opacities, sh
    idx: np.ndarray         # visible surfels (M,) ascending
    pprm: np.ndarray        # packed parameters in pair order
    prect: np.ndarray
    tile_start: np.ndarray
    tile_splats: np.ndarray
    soff: np.ndarray
    tfin: np.ndarray        # final transmittance per pixel
    last: np.ndarray        # last contributor per pixel
    med: np.ndarray
    moments: np.ndarray | None
    outputs: tuple          # rgb, tfin, depth_acc, normal_acc, depth_median (numpy), distortion


def _ndc_scale2(s: RasterSettings) -> float:
    """s^2 with m = far/(far-near) (1 - near/z) = far/(far-near) - s/z: the distortion of m
    is s^2 times that of u = 1/z (it only sees differences), which float32 holds to full
    relative precision where m itself crowds against 1."""
    return (s.far * s.near / (s.far - s.near)) ** 2


class _Raster(torch.autograd.Function):
    """(means, quats, scales, opacities, sh) -> (rgb, alpha, depth_acc, normal_acc, depth_median,
    distortion), from a forward already computed by `NumbaBackend.forward`; the backward is
    the kernels' hand-written one. distortion is an empty non-differentiable tensor unless
    settings.distortion."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, fwd, view, settings, stats):
        ctx.state = (fwd, view, settings, stats)
        rgb, tfin, dacc, nacc, dmed, dist = fwd.outputs
        if dist is None:
            dist_t = torch.zeros(0)
            ctx.mark_non_differentiable(dist_t)
        else:
            dist_t = torch.from_numpy(dist)
        alpha = 1.0 - torch.from_numpy(tfin)
        return (torch.from_numpy(rgb), alpha, torch.from_numpy(dacc), torch.from_numpy(nacc),
                torch.from_numpy(dmed), dist_t)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_d, g_n, g_med, g_dist):
        precompile.wait_until("backward")
        f, v, s, stats = ctx.state
        t0 = time.perf_counter()

        def arr(g):
            return np.ascontiguousarray(g.detach().to(torch.float32).numpy())

        g_u = None if f.moments is None else arr(g_dist * _ndc_scale2(s))  # dL/dD_u
        rows = kernels.backward(
            f.pprm, f.prect, f.tile_start, f.tile_splats, v.tile_order, v.width, v.height,
            v.tile, v.ntx, v.nty, np.float32(s.near), np.float32(s.alpha_min),
            np.float32(s.alpha_max), f.tfin, f.last, f.med, arr(g_rgb), arr(-g_alpha), arr(g_d),
            arr(g_n), arr(g_med), f.moments, g_u)
        t1 = time.perf_counter()
        spairs = kernels.surfel_pairs(f.tile_start, f.tile_splats, f.prect, f.soff, v.tile, v.ntx)
        grads = kprep.project_backward(f.idx, rows, f.soff, spairs, *f.arrs, v.deg, v.Rv, v.C, v.K)
        del rows
        stats.timings.update(backward_kernel_s=t1 - t0, backward_s=time.perf_counter() - t0)
        out = [torch.from_numpy(g) if need else None
               for g, need in zip(grads, ctx.needs_input_grad[:5])]
        return (*out, None, None, None, None)


class NumbaBackend:
    """CPU, float32 (inputs of other dtypes are converted; gradients come back in float32 and
    autograd casts them to the inputs' dtype). Tensors on other devices are refused."""
    name = "numba"

    def forward(self, inputs: RasterInputs, settings: RasterSettings) -> BackendOutput:
        if inputs.device.type != "cpu":
            raise InputError(f"rasterize: backend 'numba' runs on the CPU, the surfels are on "
                             f"{inputs.device}; use backend='torch' there")
        precompile.wait_until("forward")    # a first generate's second process: its kernels
        s = settings
        t0 = time.perf_counter()
        f32 = torch.float32
        tensors = tuple(x.to(f32) for x in (inputs.means, inputs.quats, inputs.scales,
                                            inputs.opacities, inputs.sh))
        arrs = tuple(np.ascontiguousarray(x.detach().numpy()) for x in tensors)
        rot_c, centre = proj.camera_frame(inputs.viewmat)
        width, height, tile = inputs.width, inputs.height, int(s.tile)
        ntx, nty = (width + tile - 1) // tile, (height + tile - 1) // tile
        view = _View(np.ascontiguousarray(rot_c.numpy()), np.ascontiguousarray(centre.numpy()),
                     np.ascontiguousarray(inputs.K.numpy()), width, height, tile, ntx, nty,
                     np.random.default_rng(0).permutation(ntx * nty), inputs.sh_degree)
        bound_sigma = -1.0 if s.bound_sigma is None else float(s.bound_sigma)
        idx, prm, rects, zc = kprep.project_visible(
            *arrs, view.deg, view.Rv, view.C, view.K, width, height, s.near, s.far, s.alpha_min,
            bound_sigma)
        t1 = time.perf_counter()
        tile_start, tile_splats, pprm, prect, soff = kernels.bin_sorted(
            rects, zc.view(np.int32), prm, tile, ntx, nty)
        t2 = time.perf_counter()
        if int(np.diff(tile_start).max(initial=0)) >= kernels.MAX_TILE_PAIRS:
            raise InputError(f"rasterize: more than {kernels.MAX_TILE_PAIRS} surfels overlap one "
                             f"{tile}x{tile} tile; use a smaller tile")
        moments = np.zeros((3, height, width), np.float32) if s.distortion else None
        amax = np.empty((height, width), np.int32) if inputs.want_argmax else None
        rgb, tfin, dacc, nacc, dmed, last, med, evals = kernels.forward(
            pprm, prect, tile_start, tile_splats, view.tile_order, width, height, tile, ntx, nty,
            np.float32(s.near), np.float32(s.alpha_min), np.float32(s.alpha_max),
            np.float32(s.t_min), moments, amax)
        # D = s^2 A S (kernels.forward: moments of u = 1/z; m = const - s u)
        dist = None if moments is None else np.float32(_ndc_scale2(s)) * moments[0] * moments[2]
        t3 = time.perf_counter()
        fwd = _Forward(arrs, idx, pprm, prect, tile_start, tile_splats, soff, tfin, last, med,
                       moments, (rgb, tfin, dacc, nacc, dmed, dist))
        stats = RasterStats(n_visible=int(idx.shape[0]), n_pairs=int(tile_splats.shape[0]),
                            evals=int(evals[:, 0].sum()), evals_rect=int(evals[:, 1].sum()),
                            timings=dict(project_s=t1 - t0, bin_s=t2 - t1, raster_s=t3 - t2))
        rgb_t, alpha, dacc_t, nacc_t, dmed_t, dist_t = _Raster.apply(*tensors, fwd, view, s, stats)
        vis = torch.from_numpy(idx)
        argmax = None
        if amax is not None:  # visible-set index -> input index; -1 (none) maps to the last = -1
            ext = torch.cat([vis, torch.tensor([-1], dtype=torch.int64)])
            argmax = ext[torch.from_numpy(amax.astype(np.int64))]
        return BackendOutput(rgb=rgb_t, alpha=alpha, depth_acc=dacc_t, depth_median=dmed_t,
                             normal=nacc_t, distortion=dist_t if s.distortion else None,
                             argmax=argmax, visible_index=vis, stats=stats)
NUMBA = NumbaBackend()
