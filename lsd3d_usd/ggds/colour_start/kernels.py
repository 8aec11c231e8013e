"""The numba kernel of the view-fitted colour start (worldfit.ViewFit.add_view): one pass over
the surfels per training view that projects each centre, tests it against the view's proxy
depth, reads the target's box mean over its disk from a summed-area table and adds its
weighted SH sample to the surfel's normal equations.

Each surfel owns its rows of the accumulators, so the loop runs in parallel without atomics.
Against the numpy version it replaces (kept in tests/test_ggds_colour_start_kernels.py as the float64
reference, which it matches to 1e-9), one view of the README sample's 0.9 M surfels takes
about 13 ms instead of ~150 ms (docs/ggds.md)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from lsd3d_usd.jitopts import prange_only
from lsd3d_usd.render.kernels_prep import sh_basis_into


def summed_area(image: np.ndarray) -> np.ndarray:
    """(H+1,W+1,C) float64 summed-area table of an (H,W,C) image (row and column 0 are zero):
    the sum over rows j0..j1-1 and columns i0..i1-1 is T[j1,i1] - T[j0,i1] - T[j1,i0] + T[j0,i0]."""
    img = np.asarray(image, np.float64)
    H, W, C = img.shape
    T = np.zeros((H + 1, W + 1, C))
    np.cumsum(np.cumsum(img, axis=0), axis=1, out=T[1:, 1:])
    return T


@njit(inline="always")
def _add_sample(n, positions, scales, normals, viewmat, centre, fx, fy, cx, cy, near, f,
                depth, table, rel_tol, abs_tol, max_radius, min_weight, view_weight, degree, basis,
                A, b):
    """Surfel n's sample of this view into A[n], b[n]; False when the view does not see it."""
    H, W = depth.shape
    px, py, pz = float(positions[n, 0]), float(positions[n, 1]), float(positions[n, 2])
    xc = viewmat[0, 0] * px + viewmat[0, 1] * py + viewmat[0, 2] * pz + viewmat[0, 3]
    yc = viewmat[1, 0] * px + viewmat[1, 1] * py + viewmat[1, 2] * pz + viewmat[1, 3]
    z = viewmat[2, 0] * px + viewmat[2, 1] * py + viewmat[2, 2] * pz + viewmat[2, 3]
    if not z > near:
        return False
    u = fx * xc / z + cx
    v = fy * yc / z + cy
    if not (u >= 0.0 and v >= 0.0 and u < W and v < H):
        return False
    i = int(math.floor(u))
    j = int(math.floor(v))
    zd = float(depth[j, i])
    if not (math.isfinite(zd) and abs(z - zd) <= rel_tol * zd + abs_tol):
        return False   # off the visible proxy surface: occluded
    dx, dy, dz = px - centre[0], py - centre[1], pz - centre[2]
    dist = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
    dx, dy, dz = dx / dist, dy / dist, dz / dist
    s0, s1 = float(scales[n, 0]), float(scales[n, 1])
    cos = abs(float(normals[n, 0]) * dx + float(normals[n, 1]) * dy + float(normals[n, 2]) * dz)
    sigma_px = math.sqrt(s0 * s1) * f / z
    weight = max(math.pi * s0 * s1 * cos * f * f / (z * z), min_weight) * view_weight
    r = min(max(int(np.round(0.7 * sigma_px)), 0), max_radius)
    # the target's mean over the (2r+1)² window clipped to the image
    j0, j1 = max(j - r, 0), min(j + r + 1, H)
    i0, i1 = max(i - r, 0), min(i + r + 1, W)
    area = float((j1 - j0) * (i1 - i0))
    sh_basis_into(dx, dy, dz, degree, basis)
    S = (degree + 1) * (degree + 1)
    for c in range(3):
        col = (table[j1, i1, c] - table[j0, i1, c] - table[j1, i0, c] + table[j0, i0, c]) / area
        for s in range(S):
            b[n, s, c] += weight * basis[s] * (col - 0.5)
    k = 0
    for s in range(S):          # the upper triangle, row by row (A is symmetric)
        ws = weight * basis[s]
        for t in range(s, S):
            A[n, k] += ws * basis[t]
            k += 1
    return True


@njit(parallel=prange_only(), cache=True)
def accumulate_view(positions, scales, normals, viewmat, centre, fx, fy, cx, cy, near,
                    depth, table, rel_tol, abs_tol, max_radius, min_weight, view_weight,
                    degree, A, b, count):
    """Add one view's samples to A (N,S(S+1)/2: each normal matrix's upper triangle row by
    row), b (N,S,3), count (N,) in place (worldfit.ViewFit
    has the model); returns how many surfels the view saw. positions/scales/normals: (N,3),
    (N,2), (N,3) any float type; viewmat (4,4), centre (3,) float64; depth (H,W) with inf
    where empty; table: summed_area of the target; view_weight scales every sample."""
    N = positions.shape[0]
    f = math.sqrt(fx * fy)
    seen = np.zeros(N, np.uint8)
    nblocks = min(N, 256)
    for blk in prange(nblocks):          # blocks, so each has one basis buffer
        basis = np.empty(16)
        for n in range(blk * N // nblocks, (blk + 1) * N // nblocks):
            if _add_sample(n, positions, scales, normals, viewmat, centre, fx, fy, cx, cy,
                           near, f, depth, table, rel_tol, abs_tol, max_radius, min_weight,
                           view_weight, degree, basis, A, b):
                count[n] += 1
                seen[n] = 1
    return int(seen.sum())
