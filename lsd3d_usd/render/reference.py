"""The plain torch implementation of the 2DGS surfel renderer: the float64 reference the tests
hold the fast path to, and the "torch" backend of `rasterize` (any torch device, float64 or
float32, differentiable by autograd).

Same documented math as the numba backend, computed differently: explicit ray-plane
intersection per pixel and surfel (no homography), every surfel at every pixel (no tiles, no
screen bounds), all surfels composited in centre-depth order (no early stop unless t_min > 0
is asked for, to mimic the fast path exactly). Per-surfel projection is float64 and
camera-relative (as the numba path), the per-pixel work in the chosen dtype. Autograd keeps
(pixels x surfels) tensors: small scenes only (TorchBackend refuses above MAX_PAIRS); without
grad, a pixel subset of a large scene can be evaluated in surfel chunks.

Documented rules shared with the fast path:
  * scales clamped to >= projection.S_MIN; surfels culled when the centre depth is outside
    [near, far], when exactly edge-on (|cos| < projection.EDGE_COS) or opacity < alpha_min;
  * rho = min(u^2 + v^2, 2 |pixel - projected centre|^2); depth = ray-plane depth when the
    first term is used, else the centre depth; alpha = min(alpha_max, opacity exp(-rho/2)),
    zero when alpha < alpha_min or the depth is < near;
  * colour = max(0, 0.5 + SH(direction camera -> surfel)), normal oriented towards the camera;
  * median depth = depth of the last contributor entered with transmittance > 0.5;
  * depth distortion (distortion=True) = sum_i w_i sum_{j<i} w_j (m_i - m_j)^2 over the
    contributors (alpha > 0), m = far/(far-near) (1 - near/z): here literally, pairwise in
    blocks of surfels, plus each block against the running sums of all earlier surfels.
"""
from __future__ import annotations

import time

import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.render import projection as proj
from lsd3d_usd.render.raster_types import BackendOutput, RasterInputs, RasterSettings, RasterStats
from lsd3d_usd.render.sh import eval_sh, sh_degree_of

# pixels x surfels (in front of the camera) the torch backend accepts. Autograd keeps the
# (pixel, surfel) tensors of the forward: forward + backward peaked at ~0.26 kB per pair in
# float64 and ~0.18 kB in float32 (CPU, 7500 pixels x 400 surfels), so ~2.6 GB at the limit.
MAX_PAIRS = 10_000_000


def render_reference(means, quats, scales, opacities, sh, viewmat, K, width, height, *,
                     near=0.05, far=1e4, background=None, sh_degree=None,
                     alpha_min=1.0 / 255.0, alpha_max=0.99, t_min=0.0,
                     pixels=None, chunk=4096, normal_space="camera", distortion=False,
                     dtype=torch.float64, max_pairs=None):
    """Render on the device of ``means`` with per-pixel work in ``dtype`` (float64: the
    reference). pixels: optional (P,2) long tensor of (i, j) pixel indices, then all outputs
    are per listed pixel ((P,3) / (P,)) instead of images. max_pairs: refuse (InputError) when
    pixels x surfels in front of the camera exceed it. Returns a dict like rasterize's result:
    rgb, alpha, depth_expected, depth_acc, depth_median, normal, weight_argmax (surfel index
    of the largest weight, -1 if none), visible_index (the surfels that passed culling, in
    depth order), and with distortion=True "distortion"."""
    dt = dtype
    dev = means.device
    f64 = torch.float64
    viewmat = viewmat.to(dev)
    Kd = K.to(dev, dt)
    deg = sh_degree_of(sh.shape[1]) if sh_degree is None else sh_degree
    rot_c, centre = proj.camera_frame(viewmat)

    p_c, a_u, a_v, normal = proj.camera_space(means, quats, scales, viewmat)
    keep = proj.cull_mask(p_c, normal, opacities, near, far, alpha_min)
    idx = torch.nonzero(keep).flatten()
    idx = idx[torch.argsort(p_c[idx, 2].detach(), stable=True)]
    if pixels is None:
        jj, ii = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev),
                                indexing="ij")
        pix = torch.stack([ii.flatten(), jj.flatten()], 1)
    else:
        pix = pixels.to(dev).long()
    P = pix.shape[0]
    if max_pairs is not None and P * idx.numel() > max_pairs:
        raise InputError(f"rasterize: backend 'torch' evaluates every surfel at every pixel: "
                         f"{idx.numel():,} surfels in view x {P:,} pixels is more than its "
                         f"budget of {max_pairs:,} pairs; use backend='numba' or a smaller scene")
    # per surfel in float64 (camera-relative), then the per-pixel work in dt
    p_c, a_u, a_v, normal = (x[idx].to(dt) for x in (p_c, a_u, a_v, normal))
    op = opacities[idx].to(dt)
    dirs = means[idx].to(f64) - centre
    dirs = (dirs / dirs.norm(dim=1, keepdim=True)).to(dt)
    colour = eval_sh(sh[idx].to(dt), dirs, deg)
    s_u = a_u.norm(dim=1)
    s_v = a_v.norm(dim=1)
    t_u, t_v = a_u / s_u[:, None], a_v / s_v[:, None]
    flip = ((normal * p_c).sum(1, keepdim=True) > 0).to(dt)
    n_f = normal * (1 - 2 * flip)
    cproj = p_c @ Kd.T
    xb, yb = cproj[:, 0] / cproj[:, 2], cproj[:, 1] / cproj[:, 2]

    px = pix[:, 0].to(dt) + 0.5
    py = pix[:, 1].to(dt) + 0.5
    rays = torch.stack([px, py, torch.ones_like(px)], 1) @ torch.linalg.inv(Kd).T  # z = 1

    def zeros(*shape):
        return torch.zeros(*shape, dtype=dt, device=dev)

    T = torch.ones(P, dtype=dt, device=dev)
    alive = torch.ones(P, dtype=torch.bool, device=dev)
    rgb, dacc, nacc, dmed = zeros(P, 3), zeros(P), zeros(P, 3), zeros(P)
    wmax = zeros(P)
    amax = torch.full((P,), -1, dtype=torch.long, device=dev)
    dist = zeros(P)
    s_w, s_wm, s_wm2 = zeros(P), zeros(P), zeros(P)  # sum w, sum w m, sum w m^2 so far
    ndc = far / (far - near)
    for c0 in range(0, idx.numel(), chunk):
        sl = slice(c0, c0 + chunk)
        n_dot_p = (n_f[sl] * p_c[sl]).sum(1)                       # (S,)
        n_dot_d = rays @ n_f[sl].T                                  # (P,S)
        safe = n_dot_d.abs() > 1e-300
        tz = n_dot_p / torch.where(safe, n_dot_d, torch.ones_like(n_dot_d))  # depth (ray z = 1)
        hit = tz[:, :, None] * rays[:, None, :] - p_c[sl][None]     # (P,S,3)
        u = (hit * t_u[sl][None]).sum(-1) / s_u[sl]
        v = (hit * t_v[sl][None]).sum(-1) / s_v[sl]
        r3 = torch.where(safe, u * u + v * v, torch.full_like(u, float("inf")))
        r2 = proj.LOWPASS_INV_SIGMA2 * ((px[:, None] - xb[sl]) ** 2 + (py[:, None] - yb[sl]) ** 2)
        use3 = r3 <= r2
        rho = torch.where(use3, r3, r2)
        z = torch.where(use3, tz, p_c[sl, 2].expand_as(tz))
        alpha = torch.clamp(op[sl] * torch.exp(-0.5 * rho), max=alpha_max)
        alpha = torch.where((alpha >= alpha_min) & (z >= near), alpha, torch.zeros_like(alpha))
        # transmittance before each surfel, and the early stop of the fast path if asked for
        t_after = T[:, None] * torch.cumprod(1 - alpha, dim=1)
        if t_min > 0:
            # the fast path composites the surfel that takes T below t_min, then stops
            t_prev = torch.cat([T[:, None], t_after[:, :-1]], 1)
            ok = (t_prev >= t_min) & alive[:, None]
            alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
            stopped = (~ok).any(1) | (t_after[:, -1] < t_min)
            t_after = T[:, None] * torch.cumprod(1 - alpha, dim=1)
        t_before = torch.cat([T[:, None], t_after[:, :-1]], 1)
        w = alpha * t_before
        rgb = rgb + w @ colour[sl]
        dacc = dacc + (w * z).sum(1)
        nacc = nacc + w @ n_f[sl]
        contrib = (alpha > 0) & (t_before > 0.5)
        has = contrib.any(1)
        lastc = torch.where(contrib, torch.arange(contrib.shape[1], device=dev)[None],
                            torch.full_like(contrib, -1, dtype=torch.long)).max(1).values
        zsel = z.gather(1, lastc.clamp_min(0)[:, None])[:, 0]
        dmed = torch.where(has, zsel, dmed)
        cw, ci = w.detach().max(1)
        better = cw > wmax
        wmax = torch.where(better, cw, wmax)
        amax = torch.where(better & (cw > 0), idx[sl][ci], amax)
        if distortion:
            # m only where the surfel contributes (z may be 0 elsewhere: keep the graph finite)
            m = ndc * (1 - near / torch.where(alpha > 0, z, torch.ones_like(z)))
            m = torch.where(alpha > 0, m, torch.zeros_like(m))
            for b0 in range(0, m.shape[1], 64):
                wb, mb = w[:, b0:b0 + 64], m[:, b0:b0 + 64]
                diff2 = (mb[:, :, None] - mb[:, None, :]) ** 2          # (P,i,j)
                later = torch.tril(torch.ones(diff2.shape[1:], dtype=torch.bool, device=dev), -1)  # j < i
                pair = (wb[:, :, None] * wb[:, None, :] * diff2 * later).sum((1, 2))
                cross = (wb * (mb * mb * s_w[:, None] - 2 * mb * s_wm[:, None]
                               + s_wm2[:, None])).sum(1)
                dist = dist + pair + cross
                s_w = s_w + wb.sum(1)
                s_wm = s_wm + (wb * mb).sum(1)
                s_wm2 = s_wm2 + (wb * mb * mb).sum(1)
        T = t_after[:, -1]
        if t_min > 0:
            alive = alive & ~stopped

    alpha_out = 1 - T
    if background is not None:
        bg = background.to(dev, dt)
        if bg.dim() == 3:
            bg = bg.reshape(-1, 3) if pixels is None else bg[pix[:, 1], pix[:, 0]]
        rgb = rgb + T[:, None] * bg
    depth = torch.where(alpha_out > 1e-6, dacc / alpha_out.clamp_min(1e-6), torch.zeros_like(dacc))
    if normal_space == "world":
        nacc = nacc @ rot_c.to(dt)
    out = dict(rgb=rgb, alpha=alpha_out, depth_expected=depth, depth_acc=dacc,
               depth_median=dmed, normal=nacc, weight_argmax=amax)
    if distortion:
        out["distortion"] = dist
    if pixels is None:
        for k, val in out.items():
            out[k] = val.reshape(height, width, *val.shape[1:])
    out["visible_index"] = idx
    return out


def splat_alpha_maps(means, quats, scales, opacities, viewmat, K, width, height, *,
                     near=0.05, alpha_max=0.99):
    """(N,H,W) float64 alpha of each surfel alone (no compositing, no alpha threshold, culled
    surfels all zero): what a conservative screen bound must contain."""
    n = means.shape[0]
    out = torch.zeros(n, height, width, dtype=torch.float64)
    for i in range(n):
        sh = torch.zeros(1, 1, 3, dtype=torch.float64)
        r = render_reference(means[i:i + 1], quats[i:i + 1], scales[i:i + 1], opacities[i:i + 1],
                             sh, viewmat, K, width, height, near=near, alpha_min=0.0,
                             alpha_max=alpha_max)
        out[i] = r["alpha"]
    return out


class TorchBackend:
    """rasterize(..., backend="torch"): render_reference as a backend. Runs on the device of
    the surfel tensors (CPU here, CUDA elsewhere); differentiable by autograd, which makes it
    memory-heavy: small scenes only, refused above ``max_pairs`` pixels x surfels in view
    (MAX_PAIRS by default). dtype None: float64 if any surfel tensor is float64, else float32.
    settings.tile and settings.bound_sigma do not apply (every surfel is evaluated at every
    pixel: exact)."""
    name = "torch"

    def __init__(self, dtype: torch.dtype | None = None, max_pairs: int = MAX_PAIRS):
        self.dtype = dtype
        self.max_pairs = int(max_pairs)

    def forward(self, inputs: RasterInputs, settings: RasterSettings) -> BackendOutput:
        t0 = time.perf_counter()
        arrays = (inputs.means, inputs.quats, inputs.scales, inputs.opacities, inputs.sh)
        dt = self.dtype or (torch.float64 if any(x.dtype == torch.float64 for x in arrays)
                            else torch.float32)
        s = settings
        out = render_reference(*arrays, inputs.viewmat, inputs.K, inputs.width, inputs.height,
                               near=s.near, far=s.far, sh_degree=inputs.sh_degree,
                               alpha_min=s.alpha_min, alpha_max=s.alpha_max, t_min=s.t_min,
                               distortion=s.distortion, dtype=dt, max_pairs=self.max_pairs)
        vis = torch.sort(out["visible_index"]).values
        evals = inputs.width * inputs.height * int(vis.numel())
        stats = RasterStats(n_visible=int(vis.numel()), n_pairs=0, evals=evals, evals_rect=evals,
                            timings={"render_s": time.perf_counter() - t0})
        return BackendOutput(rgb=out["rgb"], alpha=out["alpha"], depth_acc=out["depth_acc"],
                             depth_median=out["depth_median"], normal=out["normal"],
                             distortion=out.get("distortion"),
                             argmax=out["weight_argmax"] if inputs.want_argmax else None,
                             visible_index=vis, stats=stats)
TORCH = TorchBackend()
