"""Differentiable CPU rasteriser of 2D Gaussian surfels (2DGS, Huang et al. 2024): the one
functional entry point, `rasterize`.

Pipeline, all numba inside one torch.autograd.Function (no torch ops over the N surfels, no
per-pixel autograd graph): input validation in one pass; per-surfel projection, culling, SH
colour and exact screen bounds (float64 per surfel, camera-relative) compacted to the visible
set; 16x16 tile binning with a parallel per-tile depth sort; the forward tile kernel. The
backward: the tile kernel's hand-written backward (per pair), then the projection's chain rule
for the visible surfels only, scattered into the N-size gradients in the same pass.
With distortion=True the tile kernels also carry the 2DGS depth-distortion moments per pixel
(a separately compiled variant: the default kernels do not see them).

Outputs are documented in `rasterize`; the float64 reference is render/reference.py.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.render import kernels
from lsd3d_usd.render import kernels_prep as kprep
from lsd3d_usd.render import projection as proj
from lsd3d_usd.render.sh import sh_degree_of


def _as_tensor(x, name, dtype=torch.float32):
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        try:
            x = torch.as_tensor(x)
        except Exception as e:  # noqa: BLE001 - re-raised as a user error
            raise InputError(f"rasterize: {name} is not an array ({e})") from None
    if not x.is_floating_point():
        x = x.to(dtype)
    return x


def _check_shape(x, name, shape):
    """shape: tuple with None for free dims."""
    if x.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"rasterize: {name} has shape {tuple(x.shape)}, expected {want}")


def _check(x, name, shape, negative=False):
    """shape: tuple with None for free dims. Then no NaN/Inf (and, with negative, no value < 0),
    found in one numba pass; the index of the first bad element is named."""
    _check_shape(x, name, shape)
    flat = x.detach().reshape(-1).numpy()
    q = int(kprep.first_bad(flat, negative)) if flat.size else -1
    if q < 0:
        return
    where = np.unravel_index(q, tuple(x.shape))
    index = tuple(int(i) for i in where) if name in ("viewmat", "K") else int(where[0])
    if np.isfinite(flat[q]):
        raise InputError(f"rasterize: {name} has a negative value at index {index}")
    raise InputError(f"rasterize: {name} has a non-finite value (NaN or Inf) at index {index}")


def _ndc_scale2(plan):
    """s^2 with m = far/(far-near) (1 - near/z) = far/(far-near) - s/z: the distortion of m
    is s^2 times that of u = 1/z (it only sees differences), which float32 holds to full
    relative precision where m itself crowds against 1."""
    near, far = plan["near"], plan["far"]
    return (far * near / (far - near)) ** 2


class _Raster(torch.autograd.Function):
    """(means, quats, scales, opacities, sh) -> (rgb, alpha, depth_acc, normal_acc, depth_median,
    distortion): numba projection + tile kernels forward, their hand-written backward.
    distortion is (H,W) with plan["distortion"], else an empty non-differentiable tensor."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, plan):
        t0 = time.perf_counter()
        arrs = tuple(np.ascontiguousarray(x.detach().numpy())
                     for x in (means, quats, scales, opacities, sh))
        idx, prm, rects, zc = kprep.project_visible(
            *arrs, plan["deg"], plan["Rv"], plan["C"], plan["K"], plan["width"], plan["height"],
            plan["near"], plan["far"], plan["alpha_min"], plan["bound_sigma"])
        t1 = time.perf_counter()
        tile_start, tile_splats, pprm, prect, soff = kernels.bin_sorted(
            rects, zc.view(np.int32), prm, plan["tile"], plan["ntx"], plan["nty"])
        t2 = time.perf_counter()
        moments = (np.zeros((3, plan["height"], plan["width"]), np.float32)
                   if plan["distortion"] else None)
        if int(np.diff(tile_start).max(initial=0)) >= kernels.MAX_TILE_PAIRS:
            raise InputError(f"rasterize: more than {kernels.MAX_TILE_PAIRS} surfels overlap one "
                             f"{plan['tile']}x{plan['tile']} tile; use a smaller tile")
        amax = (np.empty((plan["height"], plan["width"]), np.int32)
                if plan["argmax"] else None)
        rgb, tfin, dacc, nacc, dmed, last, med, evals = kernels.forward(
            pprm, prect, tile_start, tile_splats, plan["tile_order"], plan["width"],
            plan["height"], plan["tile"], plan["ntx"], plan["nty"], np.float32(plan["near"]),
            np.float32(plan["alpha_min"]), np.float32(plan["alpha_max"]), np.float32(plan["t_min"]),
            moments, amax)
        if moments is None:
            dist = torch.zeros(0)
            ctx.mark_non_differentiable(dist)
        else:  # D = s^2 A S (kernels.forward: moments of u = 1/z; m = const - s u)
            dist = torch.from_numpy(np.float32(_ndc_scale2(plan)) * moments[0] * moments[2])
        t3 = time.perf_counter()
        plan.update(evals=int(evals[:, 0].sum()), evals_rect=int(evals[:, 1].sum()),
                    argmax_surfel=amax, visible_index=idx,
                    n_pairs=int(tile_splats.shape[0]), project_s=t1 - t0, bin_s=t2 - t1,
                    raster_s=t3 - t2)
        ctx.plan = plan
        ctx.aux = (arrs, idx, pprm, prect, tile_start, tile_splats, soff, tfin, last, med, moments)
        alpha = 1.0 - torch.from_numpy(tfin)
        return (torch.from_numpy(rgb), alpha, torch.from_numpy(dacc), torch.from_numpy(nacc),
                torch.from_numpy(dmed), dist)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_d, g_n, g_med, g_dist):
        plan = ctx.plan
        arrs, idx, pprm, prect, tile_start, tile_splats, soff, tfin, last, med, moments = ctx.aux
        t0 = time.perf_counter()

        def arr(g):
            return np.ascontiguousarray(g.detach().to(torch.float32).numpy())

        g_u = None if moments is None else arr(g_dist * _ndc_scale2(plan))  # dL/dD_u
        rows = kernels.backward(
            pprm, prect, tile_start, tile_splats, plan["tile_order"], plan["width"], plan["height"],
            plan["tile"], plan["ntx"], plan["nty"], np.float32(plan["near"]),
            np.float32(plan["alpha_min"]), np.float32(plan["alpha_max"]), tfin, last, med,
            arr(g_rgb), arr(-g_alpha), arr(g_d), arr(g_n), arr(g_med), moments, g_u)
        t1 = time.perf_counter()
        spairs = kernels.surfel_pairs(tile_start, tile_splats, prect, soff, plan["tile"],
                                      plan["ntx"])
        grads = kprep.project_backward(idx, rows, soff, spairs, *arrs, plan["deg"], plan["Rv"],
                                       plan["C"], plan["K"])
        del rows
        plan.update(bwd_kernel_s=t1 - t0, bwd_total_s=time.perf_counter() - t0)
        out = []
        for g, need in zip(grads, ctx.needs_input_grad[:5]):
            out.append(torch.from_numpy(g) if need else None)
        return (*out, None)


def rasterize(means, quats, scales, opacities, sh, viewmat, K, width, height, *,
              near=0.05, far=1e4, background=None, sh_degree=None, semantic_ids=None,
              tile=16, alpha_min=1.0 / 255.0, t_min=1e-4, alpha_max=0.99, bound_sigma=None,
              normal_space="camera", return_extras=True, distortion=False):
    """Render 2D Gaussian surfels (gsplat-style arrays in, dict out).

    means (N,3), quats (N,4) xyzw, scales (N,2) linear std-devs along the local x/y axes,
    opacities (N,) in [0,1], sh (N,K,3) (K = (deg+1)^2, 3DGS ordering), viewmat (4,4) world->
    camera in OpenCV axes, K (3,3) pixel intrinsics (pixel centres at +0.5), width, height.
    background: None, (3,) or (H,W,3) composited behind with the final transmittance (the env
    map per pixel direction). sh_degree: degree to use (default: all coefficients).
    semantic_ids: optional (N,) int per surfel. bound_sigma: None = exact opacity-aware screen
    bounds (conservative: no pixel with alpha >= alpha_min is missed); a number = fixed k-sigma
    bounds (faster, lossy). t_min: early stop when transmittance falls below it. tile: tile
    size in pixels, a multiple of 8 (the kernels' lane block).

    Returns a dict of float32 tensors:
      rgb (H,W,3)            colour, background included;
      alpha (H,W)            1 - final transmittance;
      depth_expected (H,W)   sum(w z)/alpha (camera z, metres), 0 where alpha < 1e-6;
      depth_acc (H,W)        sum(w z) (un-normalised, as 2DGS);
      depth_median (H,W)     depth where the transmittance crosses 0.5 (last contributor
                             entered with T > 0.5), 0 where nothing contributes;
      normal (H,W,3)         sum(w n), un-normalised, each surfel normal oriented towards the
                             camera; OpenCV camera axes, or world axes with normal_space="world";
      semantic (H,W) int64   semantic id of the largest-weight contributor, -1 if none (None
                             without semantic_ids);
      distortion (H,W)       only with distortion=True: the 2DGS depth distortion (Huang et al.
                             2024) sum_i w_i sum_{j<i} w_j (m_i - m_j)^2 over the contributors,
                             m = far/(far-near) (1 - near/z) (NDC-like depth in [0,1) on
                             [near, far)); the default path compiles without it;
      stats (dict)           n_visible, n_pairs, evals (Gaussians the kernel evaluated),
                             evals_rect (those inside the surfels' exact rectangles),
                             timings (with return_extras).
    Gradients flow from rgb, alpha, depth_acc/depth_expected, depth_median, normal and
    distortion to means, quats, scales, opacities, sh (and background).
    """
    t_start = time.perf_counter()
    means = _as_tensor(means, "means")
    quats = _as_tensor(quats, "quats")
    scales = _as_tensor(scales, "scales")
    opacities = _as_tensor(opacities, "opacities")
    sh = _as_tensor(sh, "sh")
    viewmat = _as_tensor(viewmat, "viewmat")
    K = _as_tensor(K, "K")
    _check_shape(means, "means", (None, 3))
    n = means.shape[0]
    checks = ((means, "means", (n, 3), False), (quats, "quats", (n, 4), False),
              (scales, "scales", (n, 2), True), (opacities, "opacities", (n,), False),
              (sh, "sh", (n, None, 3), False))
    for x, name, shape, _ in checks:
        _check_shape(x, name, shape)
    flats = tuple(np.ascontiguousarray(x.detach().reshape(-1).numpy()) for x, *_ in checks)
    if all(f.dtype == np.float32 for f in flats):  # the usual case: one parallel scan of all
        bad = int(kprep.first_bad_array(flats, tuple(c[3] for c in checks)))
        if bad >= 0:
            _check(*checks[bad])  # names the array and the index
    else:
        for c in checks:
            _check(*c)
    _check(viewmat, "viewmat", (4, 4))
    _check(K, "K", (3, 3))
    width, height, tile = int(width), int(height), int(tile)
    if width <= 0 or height <= 0:
        raise InputError(f"rasterize: bad image size {width}x{height}")
    if tile <= 0 or tile % kernels.LANES:
        raise InputError(f"rasterize: tile must be a positive multiple of {kernels.LANES}, "
                         f"not {tile}")
    if not (0 < near < far):
        raise InputError(f"rasterize: need 0 < near < far, got near={near}, far={far}")
    if abs(float(K[2, 0])) > 0 or abs(float(K[2, 1])) > 0 or float(K[2, 2]) != 1.0:
        raise InputError("rasterize: K must be a pinhole intrinsics matrix with last row (0, 0, 1)")
    i = int(kprep.first_zero_row(np.ascontiguousarray(quats.detach().numpy())))
    if i >= 0:
        raise InputError(f"rasterize: quats has a zero quaternion at index {i}")
    try:
        full_deg = sh_degree_of(sh.shape[1])
    except ValueError as e:
        raise InputError(f"rasterize: sh: {e}") from None
    deg = full_deg if sh_degree is None else int(sh_degree)
    if not 0 <= deg <= full_deg:
        raise InputError(f"rasterize: sh_degree {deg} needs more than the {sh.shape[1]} coefficients given")
    if background is not None:
        background = _as_tensor(background, "background")
        if background.dim() == 1:
            _check(background, "background", (3,))
        else:
            _check(background, "background", (height, width, 3))
    if normal_space not in ("camera", "world"):
        raise InputError(f"rasterize: normal_space must be 'camera' or 'world', not {normal_space!r}")

    rot_c, centre = proj.camera_frame(viewmat)
    ntx = (width + tile - 1) // tile
    nty = (height + tile - 1) // tile
    plan = dict(deg=deg, Rv=np.ascontiguousarray(rot_c.numpy()), C=np.ascontiguousarray(centre.numpy()),
                K=np.ascontiguousarray(K.detach().to(torch.float64).numpy()), width=width,
                height=height, tile=tile, ntx=ntx, nty=nty, near=float(near), far=float(far),
                alpha_min=float(alpha_min), alpha_max=float(alpha_max), t_min=float(t_min),
                bound_sigma=-1.0 if bound_sigma is None else float(bound_sigma),
                tile_order=np.random.default_rng(0).permutation(ntx * nty),
                distortion=bool(distortion), argmax=semantic_ids is not None)
    f32 = torch.float32
    rgb, alpha, dacc, nacc, dmed, dist = _Raster.apply(means.to(f32), quats.to(f32), scales.to(f32),
                                                 opacities.to(f32), sh.to(f32), plan)

    if background is not None:
        bg = background.to(torch.float32)
        rgb = rgb + (1.0 - alpha)[..., None] * bg
    depth = torch.where(alpha > 1e-6, dacc / alpha.clamp_min(1e-6), torch.zeros_like(dacc))
    if normal_space == "world":
        nacc = nacc @ rot_c.to(torch.float32)
    out = dict(rgb=rgb, alpha=alpha, depth_expected=depth, depth_acc=dacc, depth_median=dmed,
               normal=nacc, semantic=None)
    if distortion:
        out["distortion"] = dist
    idx = torch.from_numpy(plan["visible_index"])
    if semantic_ids is not None:
        sem = torch.as_tensor(semantic_ids).long()
        if sem.shape != (n,):
            raise InputError(f"rasterize: semantic_ids has shape {tuple(sem.shape)}, expected ({n},)")
        vis_sem = torch.cat([sem[idx], torch.tensor([-1])])
        amax = plan["argmax_surfel"]  # visible-set index of the largest weight, -1 if none
        out["semantic"] = vis_sem[torch.from_numpy(amax.astype(np.int64))]  # -1 -> last = -1
    if return_extras:
        out["stats"] = dict(
            n_visible=int(idx.numel()), n_pairs=plan["n_pairs"], evals=plan["evals"],
            evals_rect=plan["evals_rect"],
            project_s=plan["project_s"], bin_s=plan["bin_s"], raster_s=plan["raster_s"],
            total_s=time.perf_counter() - t_start, plan=plan, visible_index=idx)
    return out
