"""World-space start of the surfel colours, view-dependent: for a prior that can be evaluated
in 3D (Prior.shade_at; the procedural prior can), each surfel's spherical harmonics are fitted
by least squares to the prior's radiance at points spread over its disk, each seen from a
training camera that has the surfel in view.

Why view-dependent: the street is seen at grazing angles, where Fresnel makes asphalt and
paving reflect several times their head-on radiance (the procedural prior's broad sun lobe and
sky reflection; real road sheen alike). A colour taken from one direction (the nearest camera,
usually right above and steep) rendered the road of lane views at about half the target's
radiance: the largest single error of GGDS's start. Fitting the SH to the directions the views
actually take captures most of it in the degree-1 terms.

Per surfel i, samples k = 1..K at disk points q_k (a Vogel spiral out to ``offsets_sigma`` σ,
so the DC term is also the disk's mean, not its centre's value) seen from cameras e_k drawn
from those that have it in view (ggds/sampling.pick_views): colours c_k, basis rows
B_k = Y(d_k), d_k = unit(p_i - e_k) (the renderer's SH direction: camera centre to the surfel's
centre). Solve (BᵀB + K·C0²·Λ) x = Bᵀ(c - 0.5) per colour channel. Λ is a ridge in the surfel's
own frame: small on the zonal part of each degree (the function of the angle to the normal,
which is what Fresnel changes) and larger on the rest (the azimuth around the normal, which
the few sampled cameras cover poorly and a held-out view would extrapolate along). Measured
on the README sample (3000 surfels × 48 held-out cameras, colour at the surfel centre): one
direction 16.6 dB; degree 1 with K = 8 / 16 / 32: 21.0 / 22.1 / 22.6 dB; an isotropic ridge
as large as the zonal terms' own weight flattened the grazing-angle slope (street cameras see
the road within 25° of the horizon, so those terms are small) and cost 2 dB. Degree 2 did
not beat degree 1 at the same K.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from lsd3d_usd.conditioning.visibility import CameraSet, pick_views
from lsd3d_usd.ggds.colour_start.kernels import accumulate_view, summed_area
from lsd3d_usd.render.sh import C0, sh_basis
from lsd3d_usd.splats.field import quat_to_matrix

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def disk_pattern(k: int, radius: float) -> np.ndarray:
    """(k,2) points of a Vogel spiral filling the disk of ``radius`` (in σ units) evenly; the
    first is the centre's neighbourhood (r = radius·sqrt(0.5/k))."""
    j = np.arange(k, dtype=np.float64)
    r = radius * np.sqrt((j + 0.5) / k)
    a = j * GOLDEN_ANGLE
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def zonal_directions(normals: np.ndarray, degree: int) -> np.ndarray:
    """(N,S): per degree l ≥ 1, the unit coefficient direction of the zonal harmonic about
    each normal (Y_l(n) normalised, by the addition theorem); zero in the DC slot. A
    surfel's colour changes with the angle to its normal alone along these directions."""
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    Y = sh_basis(torch.from_numpy(n), degree).numpy()            # (N,S)
    U = np.zeros_like(Y)
    for l in range(1, degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        U[:, sl] = Y[:, sl] / np.linalg.norm(Y[:, sl], axis=1, keepdims=True)
    return U


def ridge_matrix(normals: np.ndarray | None, degree: int, ridge: float,
                 ridge_tangent: float) -> np.ndarray:
    """(N,S,S) (or (1,S,S) without normals) penalty on the non-DC SH coefficients: ``ridge``
    on the part of each degree that is a function of the angle to the surfel's normal alone
    (the zonal harmonic about n, coefficient direction Y_l(n) by the addition theorem) and
    ``ridge_tangent`` on the rest (dependence on the azimuth around the normal)."""
    S = (degree + 1) ** 2
    if normals is None:
        R = np.zeros((1, S, S))
        idx = np.arange(1, S)
        R[0, idx, idx] = ridge
        return R
    U = zonal_directions(normals, degree)
    R = np.zeros((len(U), S, S))
    for l in range(1, degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        u = U[:, sl]
        uu = np.einsum("ni,nj->nij", u, u)
        eye = np.eye(2 * l + 1)[None]
        R[:, sl, sl] = ridge * uu + ridge_tangent * (eye - uu)
    return R


def solve_sh(basis: np.ndarray, colours: np.ndarray, ridge: float, *, normals=None,
             ridge_tangent: float | None = None) -> np.ndarray:
    """Per-row ridge least squares: basis (N,K,S), colours (N,K,3) → coefficients (N,S,3)
    minimising Σ_k |0.5 + B_k x - c_k|² + K·C0²·xᵀΛx, Λ = ridge_matrix(normals, …) (the
    penalty scaled like BᵀB's DC entry, so it means the same for any K). Without normals (or
    ridge_tangent None) every non-DC term gets ``ridge``."""
    B = np.asarray(basis, np.float64)
    c = np.asarray(colours, np.float64) - 0.5
    N, K, S = B.shape
    degree = int(round(np.sqrt(S))) - 1
    A = np.einsum("nks,nkt->nst", B, B)
    if ridge_tangent is None:
        normals = None
    A += K * C0 * C0 * ridge_matrix(normals, degree, ridge, ridge_tangent or 0.0)
    A += 1e-12 * np.eye(S)[None]
    b = np.einsum("nks,nkc->nsc", B, c)
    return np.linalg.solve(A, b)


def cell_ids(positions: np.ndarray, normals: np.ndarray, classes: np.ndarray,
             cell: float) -> np.ndarray:
    """(N,) dense ids of the groups that share view-dependent colour: same ``cell``-metre
    grid cell, same semantic class, same dominant normal axis and sign."""
    g = np.floor(np.asarray(positions, np.float64) / cell).astype(np.int64)
    key = np.concatenate([g, _facing_key(normals, classes)], 1)
    return np.unique(key, axis=0, return_inverse=True)[1].reshape(-1)


def facing_ids(normals: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """(N,) ids of the groups of surfels with the same semantic class and the same dominant
    normal axis and sign (a road, a façade facing +x, ...): class·6 + axis·2 + sign, the
    same for any set of surfels; -1 for unlabelled surfels (class < 0)."""
    k = _facing_key(normals, classes)
    return np.where(k[:, 0] >= 0, k[:, 0] * 6 + k[:, 1] * 2 + k[:, 2], -1)


def _facing_key(normals, classes) -> np.ndarray:
    n = np.asarray(normals, np.float64)
    ax = np.argmax(np.abs(n), axis=1)
    sign = np.take_along_axis(n, ax[:, None], 1)[:, 0] >= 0
    return np.stack([np.asarray(classes, np.int64), ax, sign], 1)


def zonal_slopes(fits, ridge: float, ridge_tangent: float, *, min_share: float = 0.8,
                 min_members: int = 32) -> np.ndarray:
    """(G,degree,3) per group id (G = largest id + 1) and degree: the median zonal
    coefficient of the group's well-determined surfels (ViewFit.zonal_coefficients), pooled
    over ``fits`` = [(ViewFit, normals, groups (N,) ids, -1 = none)]; zero for a group with
    fewer than ``min_members`` of them."""
    zs, goods, gs = [], [], []
    for fit, normals, groups in fits:
        seen, z, good = fit.zonal_coefficients(normals, ridge, ridge_tangent,
                                               min_share=min_share)
        zs.append(z)
        goods.append(good)
        gs.append(np.asarray(groups)[seen])
    degree = fits[0][0].degree
    g = np.concatenate(gs) if gs else np.zeros(0, np.int64)
    z, good = np.concatenate(zs), np.concatenate(goods)
    table = np.zeros((max(int(g.max()) + 1, 0) if len(g) else 0, degree, 3))
    for gid in np.unique(g[g >= 0]):       # unlabelled (-1): no group
        for l in range(degree):
            ok = (g == gid) & good[:, l]
            if ok.sum() >= min_members:
                table[gid, l] = np.median(z[ok, l], axis=0)
    return table


def solve_sh_pooled(basis: np.ndarray, colours: np.ndarray, groups: np.ndarray,
                    normals: np.ndarray, ridge: float, ridge_tangent: float) -> np.ndarray:
    """Least squares with a DC term per surfel and the higher SH terms shared by each group:
    minimise Σ_i Σ_k |0.5 + C0 x0_i + Bv_ik·y_g(i) − c_ik|² + ridges on y. Per surfel the DC
    term is eliminated exactly (samples centred on the surfel's own mean), so y_g is fitted
    to how colour changes with direction inside each surfel, pooled over the group, and then
    x0_i = (mean_k c_ik − 0.5 − mean_k Bv_ik·y_g)/C0. Ridges as solve_sh, in the frame of the
    group's mean normal."""
    B = np.asarray(basis, np.float64)
    c = np.asarray(colours, np.float64)
    N, K, S = B.shape
    degree = int(round(np.sqrt(S))) - 1
    Bv = B[:, :, 1:]
    Bc = Bv - Bv.mean(axis=1, keepdims=True)
    cc = c - c.mean(axis=1, keepdims=True)
    G = int(groups.max()) + 1 if N else 0
    A = np.zeros((G, S - 1, S - 1))
    b = np.zeros((G, S - 1, 3))
    np.add.at(A, groups, np.einsum("nks,nkt->nst", Bc, Bc))
    np.add.at(b, groups, np.einsum("nks,nkc->nsc", Bc, cc))
    cnt = np.bincount(groups, minlength=G).astype(np.float64)
    nsum = np.zeros((G, 3))
    np.add.at(nsum, groups, np.asarray(normals, np.float64))
    R = ridge_matrix(nsum + np.where(np.linalg.norm(nsum, axis=1, keepdims=True) > 0, 0.0,
                                     [0.0, 0.0, 1.0]), degree, ridge, ridge_tangent)
    A += (cnt * K * C0 * C0)[:, None, None] * R[:, 1:, 1:] + 1e-12 * np.eye(S - 1)[None]
    y = np.linalg.solve(A, b)                                           # (G,S-1,3)
    out = np.empty((N, S, 3))
    out[:, 1:] = y[groups]
    out[:, 0] = (c.mean(axis=1) - 0.5 - np.einsum("ns,nsc->nc", Bv.mean(axis=1), y[groups])) / C0
    return out


@torch.no_grad()
def fit_sh(prior, env, field, cameras, *, degree: int, shadow=None, samples: int = 16,
           ridge: float = 0.003, ridge_tangent: float | None = 1.0, offsets_sigma: float = 0.7,
           cell: float = 0.0, seed: int = 0, batch_points: int = 100_000) -> np.ndarray | None:
    """(N,(degree+1)²,3) SH coefficients of ``field``'s surfels fitted to ``prior`` (module
    doc), or None when the prior cannot be evaluated in world space or the field has no
    semantic ids. ``cameras``: the training cameras; a surfel none of them sees is shaded as
    seen from the nearest camera centre (or from 10 m above when there are no cameras).
    ``cell`` > 0: the view-dependent terms are shared by the surfels of one ``cell``-metre
    grid cell, class and normal direction (solve_sh_pooled), so few samples per surfel
    suffice; 0: each surfel fits its own (solve_sh). ``batch_points``: sample points shaded
    at once (the prior's shading temporaries are about 1 kB per point)."""
    sem = field.semantic_ids
    if sem is None:
        return None
    S = (degree + 1) ** 2
    out = np.zeros((field.n, S, 3), np.float32)
    if field.n == 0:
        return out
    cams = CameraSet.of(list(cameras))
    rng = np.random.default_rng(seed)
    pattern = disk_pattern(samples, offsets_sigma)
    tree = None
    if len(cams):
        tree = cKDTree(cams.centres)
    if cell > 0:
        allB = np.empty((field.n, samples, S), np.float32)
        allC = np.empty((field.n, samples, 3), np.float32)
    batch = max(1, batch_points // samples)
    for a in range(0, field.n, batch):
        sl = slice(a, min(a + batch, field.n))
        p = field.positions[sl].astype(np.float64)
        n = len(p)
        R = quat_to_matrix(field.orientations[sl])
        s = field.scales[sl].astype(np.float64)
        pts = (p[:, None, :] + R[:, None, :, 0] * (s[:, None, :1] * pattern[None, :, :1])
               + R[:, None, :, 1] * (s[:, None, 1:] * pattern[None, :, 1:]))   # (n,K,3)
        idx = pick_views(p, cams, samples, rng)
        if tree is not None:
            _, near = tree.query(p, k=1)
            eyes = cams.centres[np.where(idx >= 0, idx, near[:, None])]      # (n,K,3)
        else:
            eyes = np.broadcast_to(p[:, None, :] + [0.0, 0.0, 10.0], (n, samples, 3))
        nrm = np.repeat(R[:, None, :, 2], samples, axis=1)
        vis = None
        if shadow is not None:
            vis = shadow.visibility((pts + 0.05 * nrm).reshape(-1, 3))
        col = prior.shade_at(pts.reshape(-1, 3), nrm.reshape(-1, 3),
                             np.repeat(sem[sl][:, None], samples, axis=1).reshape(-1), env,
                             view_dirs=(pts - eyes).reshape(-1, 3), sun_visibility=vis)
        if col is None:
            return None
        col = col.numpy().reshape(n, samples, 3)
        d = p[:, None, :] - eyes
        d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
        basis = sh_basis(torch.from_numpy(d.reshape(-1, 3)), degree).numpy().reshape(n, samples, S)
        if cell > 0:
            allB[sl], allC[sl] = basis, col
        else:
            out[sl] = solve_sh(basis, col, ridge, normals=R[:, :, 2],
                               ridge_tangent=ridge_tangent).astype(np.float32)
    if cell > 0:
        nrm = field.normals()
        groups = cell_ids(field.positions, nrm, sem, cell)
        out[:] = solve_sh_pooled(allB, allC, groups, nrm, ridge,
                                 1.0 if ridge_tangent is None else ridge_tangent)
    return out


class ViewFit:
    """The per-surfel SH least squares accumulated from the training views' targets.

    For each view (``add_view``): every surfel whose centre projects inside the image onto the
    visible proxy surface (its depth within ``rel_tol`` of the view's proxy depth there, so
    occluded surfels get nothing) takes one sample: the target's colour at its centre —
    box-filtered over about its projected disk, so the DC term is the disk's mean — along the
    direction camera → centre, weighted by the pixels the disk covers there
    (π s_u s_v |cos θ| f² / z², what the training loss weighs it by; at least ``min_weight``).
    ``solve`` then fits each surfel's SH to its samples (ridges as solve_sh, in units of the
    surfel's total weight). Surfels no view sees are reported, not guessed."""

    def __init__(self, n: int, degree: int):
        S = (degree + 1) ** 2
        self.degree = degree
        # A is symmetric: its upper triangle row by row (S(S+1)/2 of S² values: at degree 2
        # 0.33 instead of 0.59 GB for a million surfels); matrices() unpacks a block of rows
        self.A = np.zeros((n, S * (S + 1) // 2))
        self._upper = np.triu_indices(S)
        self.b = np.zeros((n, S, 3))
        self.count = np.zeros(n, np.int64)

    def add_view(self, positions: np.ndarray, scales: np.ndarray, normals: np.ndarray, camera,
                 target, depth, *, rel_tol: float = 0.02, abs_tol: float = 0.02,
                 max_radius: int = 4, min_weight: float = 0.05, weight: float = 1.0) -> int:
        """Add one view's samples, each weighted ``weight`` × its own weight; returns how
        many surfels it saw. ``target`` (H,W,3) and ``depth`` (H,W: camera z, inf where empty)
        are the view's; positions may be float32 (widened per surfel)."""
        tgt = target.numpy() if isinstance(target, torch.Tensor) else np.asarray(target)
        dep = np.asarray(depth)
        if dep.shape != tgt.shape[:2] or tgt.ndim != 3 or tgt.shape[2] != 3:
            raise ValueError(f"ViewFit.add_view: target {tgt.shape} and depth {dep.shape} "
                             "must be (H,W,3) and (H,W)")
        if (camera.height, camera.width) != dep.shape:
            raise ValueError(f"ViewFit.add_view: depth {dep.shape} is not the camera's "
                             f"{camera.height}x{camera.width}")
        return accumulate_view(
            np.asarray(positions), np.asarray(scales), np.asarray(normals),
            np.ascontiguousarray(camera.viewmat, np.float64),
            np.ascontiguousarray(camera.center, np.float64), float(camera.fx), float(camera.fy),
            float(camera.cx), float(camera.cy), float(camera.near), dep, summed_area(tgt),
            float(rel_tol), float(abs_tol), int(max_radius), float(min_weight), float(weight),
            self.degree, self.A, self.b, self.count)

    def matrices(self, rows: np.ndarray) -> np.ndarray:
        """(R,S,S) float64: the normal matrices of ``rows``, unpacked."""
        S = (self.degree + 1) ** 2
        i, j = self._upper
        packed = self.A[rows]
        out = np.empty((len(packed), S, S))
        out[:, i, j] = packed
        out[:, j, i] = packed
        return out

    def solve(self, normals: np.ndarray, ridge: float, ridge_tangent: float,
              block: int = 65536, *, slopes: tuple | None = None):
        """(sh (N,S,3) float32, seen (N,) bool); rows not seen are zero. Solved in blocks of
        ``block`` surfels, so the temporaries stay small next to the accumulators.

        With ``slopes`` = (groups (N,) ids, table (G,degree,3) from zonal_slopes), the
        zonal ridge pulls each surfel towards its group's zonal coefficients instead of
        towards zero. Why: a surfel seen from one angle only (at grazing angles only, or at a
        chunk border by few views) cannot tell its zonal slope from its DC term; towards zero
        it keeps its grazing sheen when seen from closer or higher, towards its group's it
        dims as its well-seen peers do."""
        n, S = len(self.A), (self.degree + 1) ** 2
        out = np.zeros((n, S, 3), np.float32)
        seen = self.count > 0
        rows = np.flatnonzero(seen)
        normals = np.asarray(normals)
        for a in range(0, len(rows), block):
            r = rows[a:a + block]
            A = self.matrices(r)
            w = A[:, 0, 0].copy()
            reg = ridge_matrix(normals[r], self.degree, ridge, ridge_tangent)
            # in units of the surfel's total weight (A00 = C0² Σw), as solve_sh's K·C0²
            A += w[:, None, None] * reg + 1e-12 * np.eye(S)[None]
            b = self.b[r]
            if slopes is not None:   # the ridge centred on the group's slope
                b = b + w[:, None, None] * ridge * self._slope_mean(normals[r], slopes[0][r],
                                                                    slopes[1])
            out[r] = np.linalg.solve(A, b).astype(np.float32)
        return out, seen

    def zonal_coefficients(self, normals: np.ndarray, ridge: float, ridge_tangent: float,
                           block: int = 65536, *, min_share: float = 0.8):
        """(seen (N,) bool, z (R,degree,3), good (R,degree) bool) for the R seen surfels: each
        one's zonal coefficients from the plain solve and whether its data determine them
        (the spread of its views' angles carries at least ``min_share`` of the estimate
        against the ridge)."""
        sh, seen = self.solve(normals, ridge, ridge_tangent, block)
        rows = np.flatnonzero(seen)
        normals = np.asarray(normals)
        L = self.degree
        z = np.zeros((len(rows), L, 3))
        good = np.zeros((len(rows), L), bool)
        for a in range(0, len(rows), block):
            r = rows[a:a + block]
            U = zonal_directions(normals[r], L)
            A = self.matrices(r)
            w = np.maximum(A[:, 0, 0], 1e-300)
            for l in range(1, L + 1):
                u = np.zeros_like(U)
                u[:, l * l:(l + 1) * (l + 1)] = U[:, l * l:(l + 1) * (l + 1)]
                # the data's precision on the zonal coefficient once the DC term is free
                info = (np.einsum("ns,nst,nt->n", u, A, u)
                        - np.einsum("ns,ns->n", u, A[:, :, 0]) ** 2 / w)
                good[a:a + block, l - 1] = (ridge > 0) & (
                    info >= min_share / (1 - min_share) * w * ridge)
                z[a:a + block, l - 1] = np.einsum("ns,nsc->nc", u, sh[r].astype(np.float64))
        return seen, z, good

    def _slope_mean(self, normals, groups, table) -> np.ndarray:
        """(R,S,3): the group's zonal coefficients along each surfel's own zonal directions
        (zero outside the table: unlabelled, no slope). As those directions are the zonal
        ridge's eigenvectors (eigenvalue ``ridge``), Λ·mean = ridge·mean."""
        g = np.asarray(groups)
        inside = (g >= 0) & (g < len(table))
        U = zonal_directions(normals, self.degree)
        mean = np.zeros(U.shape + (3,))
        for l in range(1, self.degree + 1):
            sl = slice(l * l, (l + 1) * (l + 1))
            z = np.zeros((len(g), 3))
            z[inside] = table[g[inside], l - 1]
            mean[:, sl] = U[:, sl, None] * z[:, None, :]
        return mean
