"""numba per-surfel projection (forward and hand-written backward) for the fast path.

Same math as projection.py (which the float64 reference uses; see its docstring), written as
per-surfel scalar float64 code in parallel loops: in torch the ~60 small array operations per
surfel cost seconds at 1 M surfels, here tens of milliseconds. The backward is the chain rule
of the forward written out step by step (comments name the step it reverses); the SH basis
derivatives are the basis polynomials' own (sh_grad_dot).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from lsd3d_usd.jitopts import prange_only
from lsd3d_usd.render.projection import EDGE_COS, LOWPASS_INV_SIGMA2, S_MIN
from lsd3d_usd.render.sh import C0, C1, C2, C3

_C2 = np.array(C2)
_C3 = np.array(C3)


@njit(inline="always")
def sh_basis_into(x, y, z, deg, out):
    """Real SH of degree <= 3 at the unit direction (x, y, z) into out[:(deg+1)²] (the order of
    render/sh.sh_basis)."""
    out[0] = C0
    if deg >= 1:
        out[1] = -C1 * y
        out[2] = C1 * z
        out[3] = -C1 * x
    if deg >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = _C2[0] * x * y
        out[5] = _C2[1] * y * z
        out[6] = _C2[2] * (2 * zz - xx - yy)
        out[7] = _C2[3] * x * z
        out[8] = _C2[4] * (xx - yy)
        if deg >= 3:
            out[9] = _C3[0] * y * (3 * xx - yy)
            out[10] = _C3[1] * x * y * z
            out[11] = _C3[2] * y * (4 * zz - xx - yy)
            out[12] = _C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
            out[13] = _C3[4] * x * (4 * zz - xx - yy)
            out[14] = _C3[5] * z * (xx - yy)
            out[15] = _C3[6] * x * (xx - 3 * yy)


@njit(inline="always")
def sh_grad_dot(x, y, z, deg, w):
    """sum_k w[k] * grad Y_k at (x, y, z), k >= 1, for the basis of sh_basis_into taken as
    polynomials in x, y, z (the caller projects out the radial part): the SH colour's
    derivative along the view direction, in real arithmetic."""
    gx = -C1 * w[3]
    gy = -C1 * w[1]
    gz = C1 * w[2]
    if deg >= 2:
        c = _C2
        gx += c[0] * y * w[4] - 2 * c[2] * x * w[6] + c[3] * z * w[7] + 2 * c[4] * x * w[8]
        gy += c[0] * x * w[4] + c[1] * z * w[5] - 2 * c[2] * y * w[6] - 2 * c[4] * y * w[8]
        gz += c[1] * y * w[5] + 4 * c[2] * z * w[6] + c[3] * x * w[7]
        if deg >= 3:
            c = _C3
            xx, yy, zz = x * x, y * y, z * z
            xy, xz, yz = x * y, x * z, y * z
            gx += (6 * c[0] * xy * w[9] + c[1] * yz * w[10] - 2 * c[2] * xy * w[11]
                   - 6 * c[3] * xz * w[12] + c[4] * (4 * zz - 3 * xx - yy) * w[13]
                   + 2 * c[5] * xz * w[14] + 3 * c[6] * (xx - yy) * w[15])
            gy += (3 * c[0] * (xx - yy) * w[9] + c[1] * xz * w[10]
                   + c[2] * (4 * zz - xx - 3 * yy) * w[11] - 6 * c[3] * yz * w[12]
                   - 2 * c[4] * xy * w[13] - 2 * c[5] * yz * w[14] - 6 * c[6] * xy * w[15])
            gz += (c[1] * xy * w[10] + 8 * c[2] * yz * w[11]
                   + c[3] * (6 * zz - 3 * xx - 3 * yy) * w[12] + 8 * c[4] * xz * w[13]
                   + c[5] * (xx - yy) * w[14])
    return gx, gy, gz


@njit(inline="always")
def _rotmat(qx, qy, qz, qw, R):
    R[0, 0] = 1 - 2 * (qy * qy + qz * qz)
    R[0, 1] = 2 * (qx * qy - qw * qz)
    R[0, 2] = 2 * (qx * qz + qw * qy)
    R[1, 0] = 2 * (qx * qy + qw * qz)
    R[1, 1] = 1 - 2 * (qx * qx + qz * qz)
    R[1, 2] = 2 * (qy * qz - qw * qx)
    R[2, 0] = 2 * (qx * qz - qw * qy)
    R[2, 1] = 2 * (qy * qz + qw * qx)
    R[2, 2] = 1 - 2 * (qx * qx + qy * qy)


# Not inlined: only surfels crossing the near plane take this path, and inlined twice into
# _project_one it cost ~2.5 s of project_visible's first-run compile (8.3-9.4 -> 6.1-6.4 s;
# a frame's projection the same, 28.8 ms both, outputs identical).
@njit(cache=True)
def _arc(A, B, C, D, E, F, near):
    """min/max of (A + B cos + C sin)/(D + E cos + F sin) over the arc part with denominator
    >= near (see projection._arc_extremes)."""
    a = A * E - B * D
    b = C * D - A * F
    c = B * F - C * E
    lo = np.inf
    hi = -np.inf
    rr = math.hypot(a, b)
    phi = math.atan2(a, b)
    off = math.acos(min(1.0, max(-1.0, c / max(rr, 1e-300))))
    r2 = math.hypot(E, F)
    phi2 = math.atan2(F, E)
    ca = (near - D) / max(r2, 1e-300)
    has_chord = abs(ca) <= 1.0
    off2 = math.acos(min(1.0, max(-1.0, ca)))
    tol = 1e-9 * (abs(D) + r2)
    for m in range(6):
        if m == 0:
            th = phi + off
        elif m == 1:
            th = phi - off
        elif m == 2:
            th = 0.0
        elif m == 3:
            th = math.pi
        elif m == 4:
            th = phi2 + off2
        else:
            th = phi2 - off2
        if m >= 4 and not has_chord:
            continue
        ct = math.cos(th)
        st = math.sin(th)
        z = D + E * ct + F * st
        if z >= near - tol:
            x = (A + B * ct + C * st) / max(z, 0.5 * near)
            lo = min(lo, x)
            hi = max(hi, x)
    return lo, hi


# Surfels per parallel work item: scratch arrays are allocated once per chunk, not per surfel
# (a heap allocation per surfel cost more than its arithmetic).
_CHUNK = 1024


@njit(inline="always")
def _extent(A, B, C, D, E, F, near):
    """min/max of (A + B cos + C sin)/(D + E cos + F sin) over the circle. When the whole
    circle lies in front of the near plane (D - |(E, F)| > near) the extremes are the roots of
    one quadratic (tangents of the projected ellipse, no trigonometry): x is attained iff
    |A - x D| <= |(x E - B, x F - C)|. Written about x0 = A/D so nothing cancels. Otherwise
    the clipped arc (_arc)."""
    # a plain root, not math.hypot: libm's overflow-safe hypot was 14 % of the projection
    # (one thread, README sim frame); E, F are depths in metres (times the bound radius),
    # and were E * E to overflow the test fails and the exact _arc below is taken
    if D - math.sqrt(E * E + F * F) > near:
        x0 = A / D
        bp = B - x0 * E
        cp = C - x0 * F
        qa = E * E + F * F - D * D  # < 0
        qb = -(bp * E + cp * F)
        qc = bp * bp + cp * cp
        sq = math.sqrt(max(qb * qb - qa * qc, 0.0))
        r1 = (-qb + sq) / qa
        r2 = (-qb - sq) / qa
        return x0 + min(r1, r2), x0 + max(r1, r2)
    return _arc(A, B, C, D, E, F, near)


@njit(inline="always")
def _project_one(i, means, quats, scales, opac, sh, deg, Rv, C, K, width, height, near, far,
                 alpha_min, bound_sigma, R, Y, prm, rect, zcs, bnd, want_bnd):
    """Project surfel i into row i of prm/rect/zcs (and bnd); True if it is visible."""
    nk = (deg + 1) * (deg + 1)
    qx, qy, qz, qw = (np.float64(quats[i, 0]), np.float64(quats[i, 1]),
                      np.float64(quats[i, 2]), np.float64(quats[i, 3]))
    qn = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if qn == 0.0:
        return False
    mx = np.float64(means[i, 0]) - C[0]
    my = np.float64(means[i, 1]) - C[1]
    mz = np.float64(means[i, 2]) - C[2]
    p2 = Rv[2, 0] * mx + Rv[2, 1] * my + Rv[2, 2] * mz
    op = np.float64(opac[i])
    if p2 < near or p2 > far or op < alpha_min:
        return False
    p0 = Rv[0, 0] * mx + Rv[0, 1] * my + Rv[0, 2] * mz
    p1 = Rv[1, 0] * mx + Rv[1, 1] * my + Rv[1, 2] * mz
    _rotmat(qx / qn, qy / qn, qz / qn, qw / qn, R)
    # camera-space axes: column j of Rv R
    su = max(np.float64(scales[i, 0]), S_MIN)
    sv = max(np.float64(scales[i, 1]), S_MIN)
    au0 = su * (Rv[0, 0] * R[0, 0] + Rv[0, 1] * R[1, 0] + Rv[0, 2] * R[2, 0])
    au1 = su * (Rv[1, 0] * R[0, 0] + Rv[1, 1] * R[1, 0] + Rv[1, 2] * R[2, 0])
    au2 = su * (Rv[2, 0] * R[0, 0] + Rv[2, 1] * R[1, 0] + Rv[2, 2] * R[2, 0])
    av0 = sv * (Rv[0, 0] * R[0, 1] + Rv[0, 1] * R[1, 1] + Rv[0, 2] * R[2, 1])
    av1 = sv * (Rv[1, 0] * R[0, 1] + Rv[1, 1] * R[1, 1] + Rv[1, 2] * R[2, 1])
    av2 = sv * (Rv[2, 0] * R[0, 1] + Rv[2, 1] * R[1, 1] + Rv[2, 2] * R[2, 1])
    n0 = Rv[0, 0] * R[0, 2] + Rv[0, 1] * R[1, 2] + Rv[0, 2] * R[2, 2]
    n1 = Rv[1, 0] * R[0, 2] + Rv[1, 1] * R[1, 2] + Rv[1, 2] * R[2, 2]
    n2 = Rv[2, 0] * R[0, 2] + Rv[2, 1] * R[1, 2] + Rv[2, 2] * R[2, 2]
    ndp = n0 * p0 + n1 * p1 + n2 * p2
    pn = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    if abs(ndp) < EDGE_COS * pn:
        return False
    # M = K [a_u a_v p]; rows m0, m1, m2
    m0u = K[0, 0] * au0 + K[0, 1] * au1 + K[0, 2] * au2
    m0v = K[0, 0] * av0 + K[0, 1] * av1 + K[0, 2] * av2
    m0w = K[0, 0] * p0 + K[0, 1] * p1 + K[0, 2] * p2
    m1u = K[1, 1] * au1 + K[1, 2] * au2
    m1v = K[1, 1] * av1 + K[1, 2] * av2
    m1w = K[1, 1] * p1 + K[1, 2] * p2
    zc = p2
    xb = m0w / zc
    yb = m1w / zc
    # bounds: r-sigma disk clipped at near, united with the low-pass disk
    if bound_sigma > 0:
        r = bound_sigma
    else:
        r = math.sqrt(2.0 * math.log(max(op / alpha_min, 1.0)))
    xlo, xhi = _extent(m0w, r * m0u, r * m0v, zc, r * au2, r * av2, near)
    ylo, yhi = _extent(m1w, r * m1u, r * m1v, zc, r * au2, r * av2, near)
    rl = r / math.sqrt(LOWPASS_INV_SIGMA2)
    bx0 = min(xlo, xb - rl)
    bx1 = max(xhi, xb + rl)
    by0 = min(ylo, yb - rl)
    by1 = max(yhi, yb + rl)
    bx0 -= 1e-3 + 1e-6 * abs(bx0)
    bx1 += 1e-3 + 1e-6 * abs(bx1)
    by0 -= 1e-3 + 1e-6 * abs(by0)
    by1 += 1e-3 + 1e-6 * abs(by1)
    if want_bnd:
        bnd[i, 0] = bx0
        bnd[i, 1] = bx1
        bnd[i, 2] = by0
        bnd[i, 3] = by1
    i0 = max(math.ceil(max(bx0, -1e9) - 0.5), 0.0)
    i1 = min(math.floor(min(bx1, 1e9) - 0.5), width - 1.0)
    j0 = max(math.ceil(max(by0, -1e9) - 0.5), 0.0)
    j1 = min(math.floor(min(by1, 1e9) - 0.5), height - 1.0)
    if i0 > i1 or j0 > j1:
        return False
    rect[i, 0] = i0
    rect[i, 1] = i1
    rect[i, 2] = j0
    rect[i, 3] = j1
    # homography relative to the centre, normalised by its value d at the centre
    hu0 = xb * au2 - m0u
    hu1 = xb * av2 - m0v
    hv0 = yb * au2 - m1u
    hv1 = yb * av2 - m1v
    d = hu0 * hv1 - hu1 * hv0
    prm[i, 0] = xb
    prm[i, 1] = yb
    prm[i, 2] = zc
    prm[i, 3] = -zc * hv1 / d
    prm[i, 4] = zc * hu1 / d
    prm[i, 5] = zc * hv0 / d
    prm[i, 6] = -zc * hu0 / d
    prm[i, 7] = (au2 * hv1 - av2 * hv0) / d
    prm[i, 8] = (av2 * hu0 - au2 * hu1) / d
    prm[i, 9] = op
    # colour from SH along the world direction camera -> surfel
    mn = math.sqrt(mx * mx + my * my + mz * mz)
    mn = max(mn, 1e-30)
    sh_basis_into(mx / mn, my / mn, mz / mn, deg, Y)
    for c in range(3):
        acc = 0.5
        for k in range(nk):
            acc += Y[k] * np.float64(sh[i, k, c])
        prm[i, 10 + c] = max(acc, 0.0)
    sgn = -1.0 if ndp > 0 else 1.0
    prm[i, 13] = sgn * n0
    prm[i, 14] = sgn * n1
    prm[i, 15] = sgn * n2
    zcs[i] = zc
    return True


# fastmath without the nnan / ninf / nsz / reassoc flags: fused multiply-adds (contract),
# reciprocals (arcp), approximate functions (afn). The projection (one thread, README sim
# frame) 23.7 -> 21.0 ms (contract alone: 22.4); its float32 parameters differ from the
# strict build's by at most 3e-11 relative.
@njit(parallel=prange_only(), cache=True, fastmath={"contract", "arcp", "afn"})
def _project_into(means, quats, scales, opac, sh, deg, Rv, C, K, width, height, near, far,
                  alpha_min, bound_sigma, prm, vis, rect, zcs, bnd, want_bnd):
    n = means.shape[0]
    for ch in prange((n + _CHUNK - 1) // _CHUNK):
        R = np.empty((3, 3))
        Y = np.zeros(16)
        for i in range(ch * _CHUNK, min(n, (ch + 1) * _CHUNK)):
            vis[i] = _project_one(i, means, quats, scales, opac, sh, deg, Rv, C, K, width,
                                  height, near, far, alpha_min, bound_sigma, R, Y, prm, rect,
                                  zcs, bnd, want_bnd)


@njit(cache=True)
def project(means, quats, scales, opac, sh, deg, Rv, C, K, width, height, near, far,
            alpha_min, bound_sigma):
    """Per surfel: packed kernel parameters (N,16) float32, visible (N,) bool, pixel rects
    (N,4) int32 inclusive [i0, i1, j0, j1], centre depth (N,) float32, and float64 bounds
    (N,4) [xmin, xmax, ymin, ymax]. bound_sigma <= 0: opacity-aware exact bounds. Rows of
    invisible surfels are zero."""
    n = means.shape[0]
    prm = np.zeros((n, 16), np.float32)
    vis = np.zeros(n, np.bool_)
    rect = np.zeros((n, 4), np.int32)
    zcs = np.zeros(n, np.float32)
    bnd = np.zeros((n, 4), np.float64)
    _project_into(means, quats, scales, opac, sh, deg, Rv, C, K, width, height, near, far,
                  alpha_min, bound_sigma, prm, vis, rect, zcs, bnd, True)
    for i in range(n):
        if not vis[i]:
            prm[i, :] = 0
            rect[i, :] = 0
            zcs[i] = 0
    return prm, vis, rect, zcs, bnd


@njit(parallel=prange_only(), cache=True)
def project_visible(means, quats, scales, opac, sh, deg, Rv, C, K, width, height, near, far,
                    alpha_min, bound_sigma):
    """The visible surfels only: (index (M,) int64 ascending, prm (M,16) float32, rect (M,4)
    int32, centre depth (M,) float32). One pass over all N, then a parallel gather."""
    n = means.shape[0]
    prm = np.empty((n, 16), np.float32)
    vis = np.empty(n, np.bool_)
    rect = np.empty((n, 4), np.int32)
    zcs = np.empty(n, np.float32)
    bnd = np.empty((1, 4), np.float64)
    _project_into(means, quats, scales, opac, sh, deg, Rv, C, K, width, height, near, far,
                  alpha_min, bound_sigma, prm, vis, rect, zcs, bnd, False)
    idx = np.flatnonzero(vis)
    m = idx.shape[0]
    prm_c = np.empty((m, 16), np.float32)
    rect_c = np.empty((m, 4), np.int32)
    z_c = np.empty(m, np.float32)
    for j in prange(m):
        i = idx[j]
        for c in range(16):
            prm_c[j, c] = prm[i, c]
        for c in range(4):
            rect_c[j, c] = rect[i, c]
        z_c[j] = zcs[i]
    return idx, prm_c, rect_c, z_c


@njit(parallel=prange_only(), cache=True)
def project_backward(idx, rows, surf_off, surf_pairs, means, quats, scales, opac, sh, deg, Rv,
                     C, K):
    """Gradients w.r.t. means (N,3), quats (N,4), scales (N,2), opacities (N,), sh (N,K,3) of
    the visible surfels idx (M,) from the per-pair gradient rows (npairs,16) of the packed
    parameters: visible surfel j owns rows surf_pairs[surf_off[j]:surf_off[j+1]] (summed here
    in that order, ascending pair position, in float32)."""
    n = means.shape[0]
    g_means = np.empty((n, 3), np.float32)
    g_quats = np.empty((n, 4), np.float32)
    g_scales = np.empty((n, 2), np.float32)
    g_opac = np.empty(n, np.float32)
    g_sh = np.empty(sh.shape, np.float32)
    flat = g_sh.reshape(-1)
    nsh = sh.shape[1] * sh.shape[2]      # SH values per surfel
    for ch in prange((n + _CHUNK - 1) // _CHUNK):    # zeros (SH: 190 B a surfel), in parallel
        for i in range(ch * _CHUNK, min(n, (ch + 1) * _CHUNK)):
            g_means[i, 0] = g_means[i, 1] = g_means[i, 2] = 0
            g_quats[i, 0] = g_quats[i, 1] = g_quats[i, 2] = g_quats[i, 3] = 0
            g_scales[i, 0] = g_scales[i, 1] = g_opac[i] = 0
            for q in range(i * nsh, (i + 1) * nsh):
                flat[q] = 0
    m = idx.shape[0]
    for ch in prange((m + _CHUNK - 1) // _CHUNK):
        R = np.empty((3, 3))
        GR = np.zeros((3, 3))
        Y = np.zeros(16)
        W = np.zeros(16)
        g = np.empty(16, np.float32)
        gcol = np.zeros(3)
        for j in range(ch * _CHUNK, min(m, (ch + 1) * _CHUNK)):
            _project_backward_one(j, idx, rows, surf_off, surf_pairs, means, quats, scales, sh,
                                  deg, Rv, C, K, R, GR, Y, W, g, gcol, g_means, g_quats,
                                  g_scales, g_opac, g_sh)
    return g_means, g_quats, g_scales, g_opac, g_sh


@njit(inline="always")
def _project_backward_one(j, idx, rows, surf_off, surf_pairs, means, quats, scales, sh, deg, Rv,
                          C, K, R, GR, Y, W, g, gcol, g_means, g_quats, g_scales, g_opac,
                          g_sh):
    nk = (deg + 1) * (deg + 1)
    if True:
        i = idx[j]
        for c in range(16):
            g[c] = 0
        for q in range(surf_off[j], surf_off[j + 1]):
            k = surf_pairs[q]
            for c in range(16):
                g[c] += rows[k, c]
        # ---- recompute the forward ----
        qx0, qy0, qz0, qw0 = (np.float64(quats[i, 0]), np.float64(quats[i, 1]),
                              np.float64(quats[i, 2]), np.float64(quats[i, 3]))
        qn = math.sqrt(qx0 * qx0 + qy0 * qy0 + qz0 * qz0 + qw0 * qw0)
        qx, qy, qz, qw = qx0 / qn, qy0 / qn, qz0 / qn, qw0 / qn
        _rotmat(qx, qy, qz, qw, R)
        mx = np.float64(means[i, 0]) - C[0]
        my = np.float64(means[i, 1]) - C[1]
        mz = np.float64(means[i, 2]) - C[2]
        p0 = Rv[0, 0] * mx + Rv[0, 1] * my + Rv[0, 2] * mz
        p1 = Rv[1, 0] * mx + Rv[1, 1] * my + Rv[1, 2] * mz
        p2 = Rv[2, 0] * mx + Rv[2, 1] * my + Rv[2, 2] * mz
        s_u0 = np.float64(scales[i, 0])
        s_v0 = np.float64(scales[i, 1])
        su = max(s_u0, S_MIN)
        sv = max(s_v0, S_MIN)
        tu0 = Rv[0, 0] * R[0, 0] + Rv[0, 1] * R[1, 0] + Rv[0, 2] * R[2, 0]
        tu1 = Rv[1, 0] * R[0, 0] + Rv[1, 1] * R[1, 0] + Rv[1, 2] * R[2, 0]
        tu2 = Rv[2, 0] * R[0, 0] + Rv[2, 1] * R[1, 0] + Rv[2, 2] * R[2, 0]
        tv0 = Rv[0, 0] * R[0, 1] + Rv[0, 1] * R[1, 1] + Rv[0, 2] * R[2, 1]
        tv1 = Rv[1, 0] * R[0, 1] + Rv[1, 1] * R[1, 1] + Rv[1, 2] * R[2, 1]
        tv2 = Rv[2, 0] * R[0, 1] + Rv[2, 1] * R[1, 1] + Rv[2, 2] * R[2, 1]
        n0 = Rv[0, 0] * R[0, 2] + Rv[0, 1] * R[1, 2] + Rv[0, 2] * R[2, 2]
        n1 = Rv[1, 0] * R[0, 2] + Rv[1, 1] * R[1, 2] + Rv[1, 2] * R[2, 2]
        n2 = Rv[2, 0] * R[0, 2] + Rv[2, 1] * R[1, 2] + Rv[2, 2] * R[2, 2]
        au0, au1, au2 = su * tu0, su * tu1, su * tu2
        av0, av1, av2 = sv * tv0, sv * tv1, sv * tv2
        m0u = K[0, 0] * au0 + K[0, 1] * au1 + K[0, 2] * au2
        m0v = K[0, 0] * av0 + K[0, 1] * av1 + K[0, 2] * av2
        m0w = K[0, 0] * p0 + K[0, 1] * p1 + K[0, 2] * p2
        m1u = K[1, 1] * au1 + K[1, 2] * au2
        m1v = K[1, 1] * av1 + K[1, 2] * av2
        m1w = K[1, 1] * p1 + K[1, 2] * p2
        zc = p2
        xb = m0w / zc
        yb = m1w / zc
        hu0 = xb * au2 - m0u
        hu1 = xb * av2 - m0v
        hv0 = yb * au2 - m1u
        hv1 = yb * av2 - m1v
        d = hu0 * hv1 - hu1 * hv0
        a1 = -zc * hv1 / d
        a2 = zc * hu1 / d
        b1 = zc * hv0 / d
        b2 = -zc * hu0 / d
        ex = (au2 * hv1 - av2 * hv0) / d
        ey = (av2 * hu0 - au2 * hu1) / d
        g_xb, g_yb, g_zc = np.float64(g[0]), np.float64(g[1]), np.float64(g[2])
        g_a1, g_a2, g_b1, g_b2 = np.float64(g[3]), np.float64(g[4]), np.float64(g[5]), np.float64(g[6])
        g_ex, g_ey = np.float64(g[7]), np.float64(g[8])
        g_opac[i] = g[9]
        # ---- reverse: homography parameters (X/d) ----
        g_d = -(a1 * g_a1 + a2 * g_a2 + b1 * g_b1 + b2 * g_b2 + ex * g_ex + ey * g_ey) / d
        id_ = 1.0 / d
        g_zc += (-hv1 * g_a1 + hu1 * g_a2 + hv0 * g_b1 - hu0 * g_b2) * id_
        g_hu0 = (-zc * g_b2 + av2 * g_ey) * id_ + hv1 * g_d
        g_hu1 = (zc * g_a2 - au2 * g_ey) * id_ - hv0 * g_d
        g_hv0 = (zc * g_b1 - av2 * g_ex) * id_ - hu1 * g_d
        g_hv1 = (-zc * g_a1 + au2 * g_ex) * id_ + hu0 * g_d
        g_au2 = (hv1 * g_ex - hu1 * g_ey) * id_
        g_av2 = (-hv0 * g_ex + hu0 * g_ey) * id_
        # hu = xb*(au2, av2) - (m0u, m0v); hv = yb*(au2, av2) - (m1u, m1v)
        g_xb += au2 * g_hu0 + av2 * g_hu1
        g_yb += au2 * g_hv0 + av2 * g_hv1
        g_au2 += xb * g_hu0 + yb * g_hv0
        g_av2 += xb * g_hu1 + yb * g_hv1
        g_m0u, g_m0v, g_m1u, g_m1v = -g_hu0, -g_hu1, -g_hv0, -g_hv1
        # xb = m0w/zc, yb = m1w/zc, zc = p2
        g_m0w = g_xb / zc
        g_m1w = g_yb / zc
        g_zc += -(xb * g_xb + yb * g_yb) / zc
        # M = K A: g_A = K^T g_M per column (u, v, w)
        g_au0 = K[0, 0] * g_m0u
        g_au1 = K[0, 1] * g_m0u + K[1, 1] * g_m1u
        g_au2 += K[0, 2] * g_m0u + K[1, 2] * g_m1u
        g_av0 = K[0, 0] * g_m0v
        g_av1 = K[0, 1] * g_m0v + K[1, 1] * g_m1v
        g_av2 += K[0, 2] * g_m0v + K[1, 2] * g_m1v
        g_p0 = K[0, 0] * g_m0w
        g_p1 = K[0, 1] * g_m0w + K[1, 1] * g_m1w
        g_p2 = K[0, 2] * g_m0w + K[1, 2] * g_m1w + g_zc
        # a = s t
        if s_u0 > S_MIN:
            g_scales[i, 0] = tu0 * g_au0 + tu1 * g_au1 + tu2 * g_au2
        if s_v0 > S_MIN:
            g_scales[i, 1] = tv0 * g_av0 + tv1 * g_av1 + tv2 * g_av2
        g_tu = (su * g_au0, su * g_au1, su * g_au2)
        g_tv = (sv * g_av0, sv * g_av1, sv * g_av2)
        # oriented normal n = sgn * Rv R[:,2]
        ndp = n0 * p0 + n1 * p1 + n2 * p2
        sgn = -1.0 if ndp > 0 else 1.0
        g_n = (sgn * np.float64(g[13]), sgn * np.float64(g[14]), sgn * np.float64(g[15]))
        # camera axes = Rv R: g_R[:, col] = Rv^T g_col
        for r in range(3):
            GR[r, 0] = Rv[0, r] * g_tu[0] + Rv[1, r] * g_tu[1] + Rv[2, r] * g_tu[2]
            GR[r, 1] = Rv[0, r] * g_tv[0] + Rv[1, r] * g_tv[1] + Rv[2, r] * g_tv[2]
            GR[r, 2] = Rv[0, r] * g_n[0] + Rv[1, r] * g_n[1] + Rv[2, r] * g_n[2]
        # rotation matrix of the unit quaternion
        gx = 2 * (qy * (GR[0, 1] + GR[1, 0]) + qz * (GR[0, 2] + GR[2, 0])
                  - 2 * qx * (GR[1, 1] + GR[2, 2]) + qw * (GR[2, 1] - GR[1, 2]))
        gy = 2 * (qx * (GR[0, 1] + GR[1, 0]) - 2 * qy * (GR[0, 0] + GR[2, 2])
                  + qz * (GR[1, 2] + GR[2, 1]) + qw * (GR[0, 2] - GR[2, 0]))
        gz = 2 * (qx * (GR[0, 2] + GR[2, 0]) + qy * (GR[1, 2] + GR[2, 1])
                  - 2 * qz * (GR[0, 0] + GR[1, 1]) + qw * (GR[1, 0] - GR[0, 1]))
        gw = 2 * (qz * (GR[1, 0] - GR[0, 1]) + qy * (GR[0, 2] - GR[2, 0])
                  + qx * (GR[2, 1] - GR[1, 2]))
        dq = qx * gx + qy * gy + qz * gz + qw * gw  # normalisation q/|q|
        g_quats[i, 0] = (gx - qx * dq) / qn
        g_quats[i, 1] = (gy - qy * dq) / qn
        g_quats[i, 2] = (gz - qz * dq) / qn
        g_quats[i, 3] = (gw - qw * dq) / qn
        # p = Rv (mean - C)
        gm0 = Rv[0, 0] * g_p0 + Rv[1, 0] * g_p1 + Rv[2, 0] * g_p2
        gm1 = Rv[0, 1] * g_p0 + Rv[1, 1] * g_p1 + Rv[2, 1] * g_p2
        gm2 = Rv[0, 2] * g_p0 + Rv[1, 2] * g_p1 + Rv[2, 2] * g_p2
        # colour = max(0, 0.5 + sum Y(dir) c), dir = m/|m|
        mn = max(math.sqrt(mx * mx + my * my + mz * mz), 1e-30)
        dx, dy, dz = mx / mn, my / mn, mz / mn
        sh_basis_into(dx, dy, dz, deg, Y)
        gcol[:] = 0
        for c in range(3):
            acc = 0.5
            for k in range(nk):
                acc += Y[k] * np.float64(sh[i, k, c])
            if acc > 0:
                gcol[c] = np.float64(g[10 + c])
                for k in range(nk):
                    g_sh[i, k, c] = Y[k] * gcol[c]
        if deg > 0 and (gcol[0] != 0 or gcol[1] != 0 or gcol[2] != 0):
            for k in range(1, nk):      # dL/dY_k
                W[k] = (np.float64(sh[i, k, 0]) * gcol[0] + np.float64(sh[i, k, 1]) * gcol[1]
                        + np.float64(sh[i, k, 2]) * gcol[2])
            gd0, gd1, gd2 = sh_grad_dot(dx, dy, dz, deg, W)
            dd = dx * gd0 + dy * gd1 + dz * gd2
            gm0 += (gd0 - dx * dd) / mn
            gm1 += (gd1 - dy * dd) / mn
            gm2 += (gd2 - dz * dd) / mn
        g_means[i, 0] = gm0
        g_means[i, 1] = gm1
        g_means[i, 2] = gm2
