"""numba kernels of the tile rasteriser: binning, forward compositing, hand-written backward.

Per (tile, surfel) pair the kernels read the 16 packed parameters of projection.PARAM_NAMES,
copied in pair order by bin_sorted so the reads are sequential (a random surfel row per pair
was half the kernel time). Everything in the hot loops is float32 (a float64 literal would
promote the loop): constants are np.float32. The kernels use error_model="numpy": Python's
ZeroDivisionError check puts a branch in every division and stops LLVM from vectorising.
Tiles run in parallel (prange); inside a tile the surfel loop is outside and the pixel loop
inside. The forward evaluates a surfel on each row of its rectangle in blocks of LANES = 8
adjacent pixels (one AVX2 vector) and composites them branch-free with masks; per-pixel state
lives in one array in blocks of constant-offset planes, so LLVM vectorises the lane loop.
Alpha is latency-bound (each block waits on one chain of divide, exp and compare), hence the
short exp_neg and the FMA contraction. Nothing in the lane loop is integer: numba widens int32
arithmetic to int64, and int64 lanes (a column index converted to float, the 2^-n of exp_neg)
took 512-bit adds, shifts and converts per block; the column centres are a state plane and
2^-n is written as float bits (pow2_neg): 25-35 % off the forward, outputs bitwise the same. The backward computes alpha and the per-pixel geometry
of a surfel on its rows x an aligned power-of-two column span in one vectorised loop
(_geom_block), then runs its scalar chain rule over the exact rectangle (a lane-masked
backward in the forward's layout was measured 1.4x slower, probably because the scalar loop
skips the many pixels past their last contributor). With contraction the two loop shapes may
round alpha an ulp apart (a check of 37 M surfel-pixel pairs: 0.1 % differ, one crosses the
alpha threshold); gradients agree with the uncontracted kernels to 1e-5 relative. The
backward walks each pixel's contributors back to front from the stored final transmittance
and last contributor (as the CUDA rasterisers do) and writes one gradient row per pair; rows
are summed per surfel afterwards in a fixed order, so the result does not depend on thread
scheduling. Tiles are visited in a fixed shuffled order (tile_order): prange hands each
thread a contiguous block of iterations, and image rows differ in work (horizon vs sky), so
a shuffle balances them.
The 2DGS depth distortion is an optional argument of forward/backward (None or arrays): numba
compiles one variant per argument type and prunes `if dist is not None` branches at compile
time, so the default kernels are the plain ones (bitwise-identical outputs; the compiled
code differs from the pre-distortion kernels by a few instructions).
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from lsd3d_usd.jitopts import prange_only

f32 = np.float32
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)
_TWO = np.float32(2.0)
_EXP_CLAMP = np.float32(16.0)
_LOG2E = np.float32(1.4426950408889634)
# 2^-f on [0, 1) as p(f) = 1 + P1 f + P2 f^2 + ... + P6 f^6: relative-error weighted
# least-squares fit (fitted here in float64, then rounded): 1.0e-8 in float64, 2.1e-7 in float32.
_P1 = np.float32(-6.93147004e-01)
_P2 = np.float32(2.40224183e-01)
_P3 = np.float32(-5.54907322e-02)
_P4 = np.float32(9.58027784e-03)
_P5 = np.float32(-1.27655233e-03)
_P6 = np.float32(1.09857116e-04)
_LOWPASS = np.float32(2.0)  # 1/sigma^2, sigma = sqrt(2)/2 px
_M1 = np.float32(-1.0)


@intrinsic
def pow2_neg(typingctx, n):
    """2^-n as float32 for an integer 0 <= n <= 126, exactly: the exponent field 127 - n
    written in 32-bit integer arithmetic and the bits read as a float. (numba widens int32
    arithmetic to int64, and int64 lanes took a 512-bit shift and convert per 8 pixels.)"""
    def codegen(context, builder, sig, args):
        i32 = ir.IntType(32)
        v = builder.trunc(args[0], i32) if args[0].type.width > 32 else args[0]
        e = builder.shl(builder.sub(i32(127), v), i32(23))
        return builder.bitcast(e, ir.FloatType())
    return types.float32(n), codegen


@njit(inline="always")
def exp_neg(y):
    """exp(-y) for y >= 0 in float32 arithmetic that vectorises (libm expf does not):
    y log2(e) = n + f, 2^-n exactly from an integer shift, 2^-f by a degree-6 polynomial in
    Estrin form. Relative error ~3e-7 for small y, ~1e-6 (from rounding y log2 e) near 16,
    absolute error < 1.1e-7 everywhere. y >= 16 (and NaN) give exp(-16) = 1.1e-7, far below
    any alpha threshold. The dependency chain is short (about 8 operations deep): in the
    kernels alpha is latency-bound, and the former Taylor series + 6 squarings was 20 deep."""
    x = (y if y < _EXP_CLAMP else _EXP_CLAMP) * _LOG2E
    n = np.int32(x)  # x >= 0: truncation is floor
    f = x - f32(n)
    f2 = f * f
    p = (_ONE + _P1 * f) + f2 * ((_P2 + _P3 * f) + f2 * ((_P4 + _P5 * f) + f2 * _P6))
    return p * pow2_neg(n)


@intrinsic
def prefetch_row(typingctx, arr, row):
    """Hint the CPU to load row `row` of the 2-D array arr into the cache (llvm.prefetch;
    no effect on results, no bounds check)."""
    def codegen(context, builder, sig, args):
        aryty = sig.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        r = context.cast(builder, args[1], sig.args[1], types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary,
                                       [r, context.get_constant(types.intp, 0)], wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])  # read, keep, data
        return context.get_dummy_value()
    return types.void(arr, row), codegen


_PREFETCH = 16  # pairs ahead


@njit(cache=True)
def bin_tiles(rects, order, tile, ntx, nty):
    # The plain version of bin_sorted (a given global order, serial): tests compare them.
    """(tile_start (ntiles+1,), tile_splats (npairs,) int32): per tile the surfels touching it in
    the given (depth) order. rects are inclusive pixel ranges [i0, i1, j0, j1]."""
    ntiles = ntx * nty
    counts = np.zeros(ntiles + 1, np.int64)
    for k in order:
        i0, i1, j0, j1 = rects[k, 0], rects[k, 1], rects[k, 2], rects[k, 3]
        if i0 > i1 or j0 > j1:
            continue
        for ty in range(j0 // tile, j1 // tile + 1):
            for tx in range(i0 // tile, i1 // tile + 1):
                counts[ty * ntx + tx + 1] += 1
    for t in range(ntiles):
        counts[t + 1] += counts[t]
    pos = counts[:-1].copy()
    out = np.empty(counts[ntiles], np.int32)
    for k in order:
        i0, i1, j0, j1 = rects[k, 0], rects[k, 1], rects[k, 2], rects[k, 3]
        if i0 > i1 or j0 > j1:
            continue
        for ty in range(j0 // tile, j1 // tile + 1):
            for tx in range(i0 // tile, i1 // tile + 1):
                t = ty * ntx + tx
                out[pos[t]] = k
                pos[t] += 1
    return counts, out


@njit(inline="always")
def _radix_by_depth(a, depth_bits):
    """Stable in-place LSD radix sort of the indices a by depth_bits[a] (non-negative int32),
    8-bit digits; a digit all entries share is skipped."""
    n = a.shape[0]
    b = np.empty(n, np.int32)
    ka = np.empty(n, np.int32)
    kb = np.empty(n, np.int32)
    for q in range(n):
        ka[q] = depth_bits[a[q]]
    src, dst, ks, kd = a.copy(), b, ka, kb
    cnt = np.empty(256, np.int64)
    for sh in range(0, 32, 8):
        cnt[:] = 0
        for q in range(n):
            cnt[(ks[q] >> sh) & 255] += 1
        if cnt[(ks[0] >> sh) & 255] == n:
            continue
        run = 0
        for d in range(256):
            c = cnt[d]
            cnt[d] = run
            run += c
        for q in range(n):
            d = (ks[q] >> sh) & 255
            j = cnt[d]
            cnt[d] = j + 1
            dst[j] = src[q]
            kd[j] = ks[q]
        src, dst = dst, src
        ks, kd = kd, ks
    for q in range(n):
        a[q] = src[q]


@njit(parallel=prange_only(), cache=True)
def bin_sorted(rects, depth_bits, prm, tile, ntx, nty):
    """Tile lists of all surfels in depth order, without a global sort: (tile, surfel) pairs
    are counted and scattered in parallel chunks of surfels (so each tile's list is in index
    order), then each tile's list is sorted in parallel by a stable LSD radix sort (8-bit
    digits, 4x faster than a quicksort here) on depth_bits: the float32 depths (all > 0)
    viewed as int32, which order like the floats; ties keep index order, as a stable sort.

    Returns tile_start (ntiles+1,), tile_splats (npairs,) int32 (surfel of each pair, the
    same lists as bin_tiles in depth order), each pair's packed parameters and rectangle
    copied in pair order (pair_prm (npairs,16), pair_rect (npairs,4): the kernels then read
    memory sequentially instead of one random surfel row per pair, whose latency was half
    the kernel time), and surf_off (M+1,): where each surfel's pairs start in surfel_pairs'
    output (its pair count is the number of tiles its rectangle covers)."""
    ntiles = ntx * nty
    m = rects.shape[0]
    nch = 16
    step = (m + nch - 1) // nch
    # tile of a pixel column / row by table (rects lie inside the image): an integer
    # division by the runtime tile size per rectangle corner cost as much as the counting
    tof = np.empty(max(ntx, nty) * tile, np.int32)
    for x in range(tof.shape[0]):
        tof[x] = x // tile
    cnt = np.zeros((nch, ntiles), np.int64)
    surf_off = np.zeros(m + 1, np.int64)
    for ch in prange(nch):
        for k in range(ch * step, min(m, (ch + 1) * step)):
            tx0, tx1 = tof[rects[k, 0]], tof[rects[k, 1]]
            ty0, ty1 = tof[rects[k, 2]], tof[rects[k, 3]]
            surf_off[k + 1] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    cnt[ch, ty * ntx + tx] += 1
    for k in range(m):
        surf_off[k + 1] += surf_off[k]
    counts = np.zeros(ntiles + 1, np.int64)
    for t in range(ntiles):
        run = counts[t]
        for ch in range(nch):
            c = cnt[ch, t]
            cnt[ch, t] = run
            run += c
        counts[t + 1] = run
    npairs = counts[ntiles]
    out = np.empty(npairs, np.int32)
    for ch in prange(nch):
        for k in range(ch * step, min(m, (ch + 1) * step)):
            tx0, tx1 = tof[rects[k, 0]], tof[rects[k, 1]]
            for ty in range(tof[rects[k, 2]], tof[rects[k, 3]] + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * ntx + tx
                    out[cnt[ch, t]] = k
                    cnt[ch, t] += 1
    pair_prm = np.empty((npairs, prm.shape[1]), prm.dtype)
    pair_rect = np.empty((npairs, 4), rects.dtype)
    for t in prange(ntiles):
        lo = counts[t]
        n = counts[t + 1] - lo
        if n == 0:
            continue
        _radix_by_depth(out[lo:lo + n], depth_bits)
        for q in range(n):
            k = lo + q
            if q + _PREFETCH < n:  # the rows are random: ask for them ahead of the copy
                prefetch_row(prm, out[k + _PREFETCH])
                prefetch_row(rects, out[k + _PREFETCH])
            sidx = out[k]
            for c in range(prm.shape[1]):
                pair_prm[k, c] = prm[sidx, c]
            for c in range(4):
                pair_rect[k, c] = rects[sidx, c]
    return counts, out, pair_prm, pair_rect, surf_off


@njit(parallel=prange_only(), cache=True)
def surfel_pairs(tile_start, tile_splats, pair_rect, surf_off, tile, ntx):
    """Per visible surfel the positions of its pairs, ascending (surfel j owns
    [surf_off[j], surf_off[j+1])): the slot of a pair is its tile's row-major place in the
    surfel's rectangle of tiles, so this needs no sort and no atomics. Only the backward
    needs it (random writes: kept out of the forward)."""
    out = np.empty(tile_splats.shape[0], np.int64)
    for t in prange(tile_start.shape[0] - 1):
        ty = t // ntx
        tx = t - ty * ntx
        for k in range(tile_start[t], tile_start[t + 1]):
            tx0 = pair_rect[k, 0] // tile
            tx1 = pair_rect[k, 1] // tile
            ty0 = pair_rect[k, 2] // tile
            out[surf_off[tile_splats[k]] + (ty - ty0) * (tx1 - tx0 + 1) + (tx - tx0)] = k
    return out


@njit(inline="always")
def _span(li0, li1):
    """Smallest power-of-two aligned column span [c0, c0 + 2^sh) holding [li0, li1]."""
    sh = 0
    while (li0 >> sh) != (li1 >> sh):
        sh += 1
    return (li0 >> sh) << sh, sh


@njit(inline="always", error_model="numpy")
def _splat_at(dx, dy, zc, a1, a2, b1, b2, ex, ey):
    """The surfel at pixel offset (dx, dy) from its projected centre: (rho, z, use3, uu, vv,
    iw). rho: squared Mahalanobis distance, the ray-splat intersection's (homography rows a, b,
    e; 1/W = iw) or the screen low-pass filter's, whichever is smaller (use3: the first); z:
    depth there. One definition for both kernels, so they compute the same alpha."""
    uu = a1 * dx + a2 * dy
    vv = b1 * dx + b2 * dy
    iw = _ONE / (_ONE + ex * dx + ey * dy)
    r3 = (uu * uu + vv * vv) * (iw * iw)
    r2 = _LOWPASS * (dx * dx + dy * dy)
    use3 = r3 <= r2
    rho = r3 if use3 else r2
    z = zc * iw if use3 else zc
    return rho, z, use3, uu, vv, iw


@njit(inline="always", error_model="numpy")
def _geom_block(x0, y0, c0, sh, lj0, nq, xb, yb, zc, a1, a2, b1, b2, ex, ey, op, near,
                alpha_max, abuf, zbuf, gbuf, ubuf, vbuf, wbuf, sbuf, full):
    """alpha and depth (and with full, what the backward needs: Gaussian value, u, v, 1/W,
    ray-splat branch) of one surfel on a block of its rows x an aligned 2^sh column span,
    in one branch-free loop over nq = rows << sh entries (block-local index q = row << sh |
    column - c0). Small splats get small spans, so little is evaluated outside their
    rectangle, and the single loop vectorises (error_model numpy: no ZeroDivisionError
    branch; 1/0 gives inf, which the min() with the low-pass term absorbs)."""
    m = (1 << sh) - 1
    for q in range(nq):
        dx = (f32(x0 + c0 + (q & m)) + _HALF) - xb
        dy = (f32(y0 + lj0 + (q >> sh)) + _HALF) - yb
        rho, z, use3, uu, vv, iw = _splat_at(dx, dy, zc, a1, a2, b1, b2, ex, ey)
        gk = exp_neg(_HALF * rho)
        a = min(alpha_max, op * gk)
        abuf[q] = a if z >= near else _ZERO
        zbuf[q] = z
        if full:
            gbuf[q] = gk
            ubuf[q] = uu * iw
            vbuf[q] = vv * iw
            wbuf[q] = iw
            sbuf[q] = use3


LANES = 8  # pixels per block: 8 adjacent pixels of one tile row (one AVX2 vector)
# Per-block state planes (LANES floats each, block after block): the offsets are constants, so
# LLVM sees the planes never overlap and vectorises the lane loop without runtime checks. The
# integer state (last / median contributor, argmax) is held as float32 list positions within
# the tile (exact below 2^24, checked by the caller): one array, no aliasing between types.
(_Q_T, _Q_R, _Q_G, _Q_B, _Q_D, _Q_NX, _Q_NY, _Q_NZ, _Q_MED, _Q_LAST, _Q_LMED, _Q_WM, _Q_AM,
 _Q_MA, _Q_MMU, _Q_MS, _Q_X) = [np.uint64(i * LANES) for i in range(17)]
_NQ = 17
_BLOCK = np.uint64(_NQ * LANES)
MAX_TILE_PAIRS = 1 << 24  # list positions held exactly in float32


@njit(parallel=prange_only(), cache=True, error_model="numpy", fastmath={"contract"})
def forward(prm, rects, tile_start, tile_splats, tile_order, width, height, tile, ntx, nty,
            near, alpha_min, alpha_max, t_min, dist, amax):
    """Front-to-back compositing; prm and rects are per pair (bin_sorted's pair_prm,
    pair_rect), tile_splats the surfel of each pair; tile a multiple of LANES; tile_order
    every tile exactly once (the outputs are written tile by tile, never filled). Returns (rgb
    (H,W,3), T_final, depth_acc = sum w z, normal_acc (H,W,3) = sum w n, depth_median, last
    (list position + 1 of the last contributor, per pixel), med (list position of the median
    contributor or -1), evals (ntiles, 2): per tile the Gaussians evaluated (rows x blocks x
    LANES) and the pixels inside the surfels' exact rectangles (the useful part of them)).

    Each surfel is evaluated on the rows of its screen rectangle within the tile, each row on
    the blocks of LANES pixels the rectangle touches, in one branch-free loop over the lanes:
    alpha, then a masked composite (lanes outside the rectangle, below alpha_min or finished
    (T < t_min) add exactly nothing). That loop vectorises; the scalar version with a branch
    per pixel mispredicted on every alpha test. The accumulators take w * value with w = 0
    for masked lanes, so they store unconditionally; FMA contraction is allowed (the
    reference tests bound the error).

    amax: None, or an (H,W) int32 array that receives the surfel with the largest weight
    (-1 if none); with None that tracking is compiled out.
    dist: None, or a (3,H,W) float32 array that receives per pixel the depth-distortion
    moments of the contributors in u = 1/z: A = sum w, mu = sum w u / A, S = sum w (u - mu)^2
    (Welford's weighted update: every term is >= 0, no cancellation). With None numba prunes
    every use at compile time, so the default variant is the plain kernel."""
    # uninitialised: tile_order holds every tile once and each tile writes all its pixels
    # (and its evals row) at its end, so a fill before would be a serial pass for nothing
    rgb = np.empty((height, width, 3), f32)
    tfin = np.empty((height, width), f32)
    dacc = np.empty((height, width), f32)
    nacc = np.empty((height, width, 3), f32)
    dmed = np.empty((height, width), f32)
    last = np.empty((height, width), np.int32)
    med = np.empty((height, width), np.int32)
    evals = np.empty((ntx * nty, 2), np.int64)
    nbr = tile // LANES  # blocks per tile row
    nblk = nbr * tile
    for it in prange(ntx * nty):
        t = tile_order[it]
        ty = t // ntx
        tx = t - ty * ntx
        x0 = tx * tile
        y0 = ty * tile
        st = np.zeros(nblk * _NQ * LANES, f32)
        for b in range(nblk):
            jj = b // nbr
            ib = (b - jj * nbr) * LANES
            o = np.uint64(b) * _BLOCK
            for c in range(LANES):
                inside = (y0 + jj < height) & (x0 + ib + c < width)
                st[o + _Q_T + np.uint64(c)] = _ONE if inside else _ZERO  # outside: finished
                st[o + _Q_LMED + np.uint64(c)] = _M1
                st[o + _Q_X + np.uint64(c)] = f32(x0 + ib + c) + _HALF
                if amax is not None:
                    st[o + _Q_AM + np.uint64(c)] = _M1
        k0 = tile_start[t]
        k1 = tile_start[t + 1]
        nev = 0
        nrect = 0
        for k in range(k0, k1):
            if t_min > _ZERO and (k - k0) & 31 == 31:  # every 32 surfels: is the tile finished?
                tmax = _ZERO
                for b in range(nblk):
                    o = np.uint64(b) * _BLOCK
                    for c in range(LANES):
                        tmax = max(tmax, st[o + _Q_T + np.uint64(c)])
                if tmax < t_min:
                    break
            li0 = max(rects[k, 0] - x0, 0)
            li1 = min(rects[k, 1] - x0, tile - 1)
            lj0 = max(rects[k, 2] - y0, 0)
            lj1 = min(rects[k, 3] - y0, tile - 1)
            xb, yb, zc = prm[k, 0], prm[k, 1], prm[k, 2]
            a1, a2, b1, b2 = prm[k, 3], prm[k, 4], prm[k, 5], prm[k, 6]
            ex, ey, op = prm[k, 7], prm[k, 8], prm[k, 9]
            cr, cg, cb = prm[k, 10], prm[k, 11], prm[k, 12]
            nx, ny, nz = prm[k, 13], prm[k, 14], prm[k, 15]
            kl = f32(k - k0)
            kl1 = f32(k - k0 + 1)
            xlo = f32(x0 + li0) + _HALF
            xhi = f32(x0 + li1) + _HALF
            bb0 = li0 // LANES
            bb1 = li1 // LANES
            nev += (lj1 - lj0 + 1) * (bb1 - bb0 + 1) * LANES
            nrect += (lj1 - lj0 + 1) * (li1 - li0 + 1)
            for jj in range(lj0, lj1 + 1):
                dy = (f32(y0 + jj) + _HALF) - yb
                for bb in range(bb0, bb1 + 1):
                    ib = bb * LANES
                    o = np.uint64(jj * nbr + bb) * _BLOCK
                    for c in range(LANES):
                        q = o + np.uint64(c)
                        xc = st[q + _Q_X]
                        dx = xc - xb
                        rho, z, _, _, _, _ = _splat_at(dx, dy, zc, a1, a2, b1, b2, ex, ey)
                        a = min(alpha_max, op * exp_neg(_HALF * rho))
                        tp = st[q + _Q_T]
                        live = ((xc >= xlo) & (xc <= xhi) & (tp >= t_min) & (z >= near)
                                & (a >= alpha_min))
                        ae = a if live else _ZERO
                        ze = z if live else _ZERO
                        w = ae * tp
                        st[q + _Q_R] += w * cr
                        st[q + _Q_G] += w * cg
                        st[q + _Q_B] += w * cb
                        st[q + _Q_D] += w * ze
                        st[q + _Q_NX] += w * nx
                        st[q + _Q_NY] += w * ny
                        st[q + _Q_NZ] += w * nz
                        st[q + _Q_T] = tp * (_ONE - ae)
                        st[q + _Q_LAST] = max(st[q + _Q_LAST], kl1 if live else _ZERO)
                        um = live & (tp > _HALF)
                        omed = st[q + _Q_MED]
                        st[q + _Q_MED] = z if um else omed
                        st[q + _Q_LMED] = max(st[q + _Q_LMED], kl if um else _M1)
                        if amax is not None:
                            owm = st[q + _Q_WM]
                            better = w > owm
                            st[q + _Q_WM] = w if better else owm
                            oam = st[q + _Q_AM]
                            st[q + _Q_AM] = kl if better else oam
                        if dist is not None:
                            oa = st[q + _Q_MA]
                            omu = st[q + _Q_MMU]
                            an = oa + w
                            iz = _ONE / (z if live else _ONE)
                            dl = iz - omu
                            mu = omu + dl * (w / (an if w > _ZERO else _ONE))
                            ds = w * dl * (iz - mu)
                            upd = w > _ZERO
                            st[q + _Q_MA] = an if upd else oa
                            st[q + _Q_MMU] = mu if upd else omu
                            st[q + _Q_MS] += ds if upd else _ZERO
        evals[t, 0] = nev
        evals[t, 1] = nrect
        for b in range(nblk):
            jj = b // nbr
            j = y0 + jj
            ib = (b - jj * nbr) * LANES
            o = np.uint64(b) * _BLOCK
            for c in range(LANES):
                i = x0 + ib + c
                if i >= width or j >= height:
                    continue
                q = o + np.uint64(c)
                rgb[j, i, 0] = st[q + _Q_R]
                rgb[j, i, 1] = st[q + _Q_G]
                rgb[j, i, 2] = st[q + _Q_B]
                tfin[j, i] = st[q + _Q_T]
                dacc[j, i] = st[q + _Q_D]
                nacc[j, i, 0] = st[q + _Q_NX]
                nacc[j, i, 1] = st[q + _Q_NY]
                nacc[j, i, 2] = st[q + _Q_NZ]
                dmed[j, i] = st[q + _Q_MED]
                fl = st[q + _Q_LAST]
                last[j, i] = np.int32(k0 + np.int64(fl)) if fl > _ZERO else 0
                fm = st[q + _Q_LMED]
                med[j, i] = np.int32(k0 + np.int64(fm)) if fm >= _ZERO else -1
                if amax is not None:
                    fa = st[q + _Q_AM]
                    amax[j, i] = tile_splats[k0 + np.int64(fa)] if fa >= _ZERO else -1
                if dist is not None:
                    dist[0, j, i] = st[q + _Q_MA]
                    dist[1, j, i] = st[q + _Q_MMU]
                    dist[2, j, i] = st[q + _Q_MS]
    return rgb, tfin, dacc, nacc, dmed, last, med, evals


@njit(parallel=prange_only(), cache=True, error_model="numpy", fastmath={"contract"})
def backward(prm, rects, tile_start, tile_splats, tile_order, width, height, tile, ntx, nty,
             near, alpha_min, alpha_max, tfin, last, med,
             g_rgb, g_t, g_d, g_n, g_med, dist, g_dist):
    """Gradient rows (npairs, 16) w.r.t. the packed parameters, one row per (tile, surfel)
    pair of tile_splats (prm, rects: per pair, as forward). g_t is dL/dT_final.

    dist, g_dist: None (pruned at compile time), or forward's (3,H,W) moments A, mu, S and
    dL/dD_u per pixel for D_u = A S = sum_{i>j} w_i w_j (u_i - u_j)^2, u = 1/z. With the final
    moments, dD_u/dw_k = A (u_k - mu)^2 + S (goes into q = dL/dw_k like every other output)
    and dD_u/du_k = 2 w_k A (u_k - mu), times du/dz = -1/z^2 into gz."""
    npairs = tile_splats.shape[0]
    out = np.empty((npairs, 16), f32)     # zeroed per tile below, in parallel
    npx = tile * tile
    for it in prange(ntx * nty):
        t = tile_order[it]
        k0 = tile_start[t]
        k1 = tile_start[t + 1]
        out[k0:k1] = 0
        if k1 == k0:
            continue
        ty = t // ntx
        tx = t - ty * ntx
        x0 = tx * tile
        y0 = ty * tile
        # the tile's scratch planes as views of one zeroed block (one allocation, not 26)
        scr = np.zeros(23 * npx, f32)
        pxs = scr[0:npx]
        pys = scr[npx:2 * npx]
        T = scr[2 * npx:3 * npx]
        sg = scr[3 * npx:4 * npx]
        tg = scr[4 * npx:5 * npx]  # T_final * dL/dT_final
        gr = scr[5 * npx:6 * npx]
        gg = scr[6 * npx:7 * npx]
        gb = scr[7 * npx:8 * npx]
        gd = scr[8 * npx:9 * npx]
        gnx = scr[9 * npx:10 * npx]
        gny = scr[10 * npx:11 * npx]
        gnz = scr[11 * npx:12 * npx]
        gm = scr[12 * npx:13 * npx]
        m_a = scr[13 * npx:14 * npx]
        m_mu = scr[14 * npx:15 * npx]
        m_s = scr[15 * npx:16 * npx]
        g_u = scr[16 * npx:17 * npx]
        abuf = scr[17 * npx:18 * npx]
        zbuf = scr[18 * npx:19 * npx]
        pxr = pxs[:tile]  # x of the pixel centres of one tile row
        gbuf = scr[19 * npx:20 * npx]
        ubuf = scr[20 * npx:21 * npx]
        vbuf = scr[21 * npx:22 * npx]
        wbuf = scr[22 * npx:23 * npx]
        ints = np.zeros(2 * npx, np.int32)
        lst = ints[0:npx]
        lmed = ints[npx:2 * npx]
        lmed[:] = -1
        sbuf = np.empty(npx, np.bool_)
        kmax = k0
        for p in range(npx):
            i = x0 + p % tile
            j = y0 + p // tile
            pxs[p] = f32(i) + _HALF
            pys[p] = f32(j) + _HALF
            if i >= width or j >= height:
                continue
            T[p] = tfin[j, i]
            tg[p] = tfin[j, i] * g_t[j, i]
            lst[p] = last[j, i]
            lmed[p] = med[j, i]
            gr[p] = g_rgb[j, i, 0]
            gg[p] = g_rgb[j, i, 1]
            gb[p] = g_rgb[j, i, 2]
            gd[p] = g_d[j, i]
            gnx[p] = g_n[j, i, 0]
            gny[p] = g_n[j, i, 1]
            gnz[p] = g_n[j, i, 2]
            gm[p] = g_med[j, i]
            if dist is not None:
                m_a[p] = dist[0, j, i]
                m_mu[p] = dist[1, j, i]
                m_s[p] = dist[2, j, i]
                g_u[p] = g_dist[j, i]
            kmax = max(kmax, last[j, i])
        for k in range(kmax - 1, k0 - 1, -1):
            li0 = max(rects[k, 0] - x0, 0)
            li1 = min(rects[k, 1] - x0, tile - 1)
            lj0 = max(rects[k, 2] - y0, 0)
            lj1 = min(rects[k, 3] - y0, tile - 1)
            xb, yb, zc = prm[k, 0], prm[k, 1], prm[k, 2]
            a1, a2, b1, b2 = prm[k, 3], prm[k, 4], prm[k, 5], prm[k, 6]
            ex, ey, op = prm[k, 7], prm[k, 8], prm[k, 9]
            cr, cg, cb = prm[k, 10], prm[k, 11], prm[k, 12]
            nx, ny, nz = prm[k, 13], prm[k, 14], prm[k, 15]
            d_xb = _ZERO
            d_yb = _ZERO
            d_zc = _ZERO
            d_a1 = _ZERO
            d_a2 = _ZERO
            d_b1 = _ZERO
            d_b2 = _ZERO
            d_ex = _ZERO
            d_ey = _ZERO
            d_op = _ZERO
            d_cr = _ZERO
            d_cg = _ZERO
            d_cb = _ZERO
            d_nx = _ZERO
            d_ny = _ZERO
            d_nz = _ZERO
            c0, sh = _span(li0, li1)
            _geom_block(x0, y0, c0, sh, lj0, (lj1 - lj0 + 1) << sh, xb, yb, zc, a1, a2, b1, b2,
                        ex, ey, op, near, alpha_max, abuf, zbuf, gbuf, ubuf, vbuf, wbuf, sbuf,
                        True)
            for jj in range(lj0, lj1 + 1):
                dy = pys[jj * tile] - yb
                qb = ((jj - lj0) << sh) - c0
                for c in range(li0, li1 + 1):
                    p = jj * tile + c
                    a = abuf[qb + c]
                    if k >= lst[p] or a < alpha_min:
                        continue
                    om = _ONE - a
                    tb = T[p] / om
                    T[p] = tb
                    w = a * tb
                    z = zbuf[qb + c]
                    q = cr * gr[p] + cg * gg[p] + cb * gb[p] + z * gd[p] \
                        + nx * gnx[p] + ny * gny[p] + nz * gnz[p]
                    gzd = _ZERO
                    if dist is not None:
                        if w > _ZERO:  # as forward: w = 0 (then z may be < near) adds nothing
                            iz = _ONE / z
                            e = iz - m_mu[p]
                            q += g_u[p] * (m_a[p] * e * e + m_s[p])
                            gzd = -_TWO * g_u[p] * w * m_a[p] * e * iz * iz
                    d_a = tb * q - (sg[p] + tg[p]) / om
                    sg[p] += w * q
                    d_cr += w * gr[p]
                    d_cg += w * gg[p]
                    d_cb += w * gb[p]
                    d_nx += w * gnx[p]
                    d_ny += w * gny[p]
                    d_nz += w * gnz[p]
                    gz = w * gd[p]
                    if dist is not None:
                        gz += gzd
                    if lmed[p] == k:
                        gz += gm[p]
                    # the geometry of this pixel, from the vectorised row
                    dx = pxr[c] - xb
                    iw = wbuf[qb + c]
                    u = ubuf[qb + c]
                    v = vbuf[qb + c]
                    g_rho = _ZERO
                    if a < alpha_max:  # not clamped
                        d_op += d_a * gbuf[qb + c]
                        g_rho = -_HALF * d_a * a
                    if sbuf[qb + c]:
                        du = _TWO * u * g_rho
                        dv = _TWO * v * g_rho
                        dU = du * iw
                        dV = dv * iw
                        dW = -(du * u + dv * v + gz * z) * iw
                        d_a1 += dU * dx
                        d_a2 += dU * dy
                        d_b1 += dV * dx
                        d_b2 += dV * dy
                        d_ex += dW * dx
                        d_ey += dW * dy
                        d_zc += gz * iw
                        d_xb -= dU * a1 + dV * b1 + dW * ex
                        d_yb -= dU * a2 + dV * b2 + dW * ey
                    else:
                        d_xb -= _TWO * _LOWPASS * dx * g_rho
                        d_yb -= _TWO * _LOWPASS * dy * g_rho
                        d_zc += gz
            o = out[k]
            o[0] = d_xb
            o[1] = d_yb
            o[2] = d_zc
            o[3] = d_a1
            o[4] = d_a2
            o[5] = d_b1
            o[6] = d_b2
            o[7] = d_ex
            o[8] = d_ey
            o[9] = d_op
            o[10] = d_cr
            o[11] = d_cg
            o[12] = d_cb
            o[13] = d_nx
            o[14] = d_ny
            o[15] = d_nz
    return out


@njit(cache=True)
def reduce_pairs(rows, tile_splats, n):
    """Sum the per-pair gradient rows into (n, 16) per-surfel gradients (float32): the plain
    serial version of what project_backward does through surfel_pairs (tests compare them)."""
    g = np.zeros((n, rows.shape[1]), f32)
    for k in range(tile_splats.shape[0]):
        s = tile_splats[k]
        for c in range(rows.shape[1]):
            g[s, c] += rows[k, c]
    return g
