"""The kernels of a spinning LiDAR: where each ray of a sweep first meets the scene.

The sensor model (its beams, columns, timing and mount) is ``sensors.lidar.LidarModel``; the
kernels here take arrays (ray origins, directions, column times, ranges) so the renderer
does not depend on the sensors package above it.

The beams. A LidarModel has rings (one beam each, at fixed elevations) and columns (azimuths
swept as the head turns at ``rotation_hz``). Column j looks at azimuth
``hfov/2 - (j + 0.5) · hfov / columns`` in the sensor frame (x forward, y left, z up: the
head turns clockwise seen from above, starting behind the sensor for a 360° model) and fires
``(j + 0.5) / columns · (hfov / 360) / rotation_hz`` seconds after the sweep starts, so on a
moving ego each column has its own origin and orientation (rolling shutter). Ring i is the
i-th lowest elevation (ring 0 looks lowest, as Velodyne numbers its rings).

A return. Along a ray from o in direction d, a surfel (disk centre c, tangent axes t_u, t_v,
normal n, scales s_u, s_v, opacity a) is met at t = (c - o)·n / (d·n) where
alpha = min(0.99, a · exp(-(u² + v²)/2)) with u = (o + t d - c)·t_u / s_u, v likewise, counts
if alpha ≥ 1/255 (the rasteriser's alpha_min and alpha_max). Surfels are composited in the
order of t; the return is at the t where the transmittance Π(1 - alpha) first falls below
0.5 — the rasteriser's median-depth rule, exact per ray (no screen-space low-pass: a beam has
no pixel). No return where the transmittance stays at or above 0.5 within
[min_range, max_range]. Mesh actors are opaque: a ray's nearest triangle hit wins when it is
nearer than the surfels' return.

The kernel bins surfels into tiles of rays (8 columns × 4 rings) by conservative angular
bounds from each tile's origin, orders each tile's list by the nearest distance a surfel can be
met at (in buckets 3 % wide, each lowered to its floor), and stops a tile once that bound
passes every ray's return: the result is the same as
compositing every surfel (``cast_reference``, float64, every surfel per ray, for small
scenes), at a fraction of the work. float64 throughout.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from lsd3d_usd.jitopts import prange_only


ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
MIN_SCALE = 1e-7         # m: smaller disks are points, never met by a ray
MAX_HITS = 128          # per ray, composited before the return (more: the nearest are kept)
TILE_COLS = 8
TILE_RINGS = 4
TRACE_TILES = True
SECTOR_GROUPS = 8        # column groups binned from one origin
SPREAD_PRIME = 1000003   # _spread's multiplier: a prime, so coprime with any tile count it is not
BIN_BLOCK = 1024         # surfels per block of _bin's parallel loop
Q_MARGIN = 1e-9          # relative (and absolute) slack of a surfel's q_max
PAIR_SLOTS = 4           # (tile, distance) pairs a surfel's first binning pass can hold


# ----------------------------------------------------------------------------- surfel frames
@dataclass
class LidarSurfels:
    """The surfels as the kernels take them, float64: centres c (N,3), tangent axes tu, tv and
    normals n (N,3 each), scales s (N,2), opacities a (N,), the radius rad (N,) beyond which a
    disk's alpha is below ALPHA_MIN (0 for a surfel never met: one that never reaches it, or
    a degenerate one: a scale below MIN_SCALE, a value not finite), and ``packed``
    (N,16: centre, t_u, t_v, n, 1/s_u, 1/s_v, opacity, and q_max, the u² + v² beyond which
    its alpha is below ALPHA_MIN (Q_MARGIN wider; -1 for a surfel never met) — one surfel's parameters in one row
    the tracer reads together). Made once per loaded scene and reused by every sweep."""
    c: np.ndarray
    tu: np.ndarray
    tv: np.ndarray
    n: np.ndarray
    s: np.ndarray
    a: np.ndarray
    rad: np.ndarray
    packed: np.ndarray
    # binning buffers kept between sweeps (fresh pages cost ~15 % of the binning); a list
    # whose pop and append are atomic, so concurrent sweeps each get their own
    _spare: list = field(default_factory=list, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.c)

    def take_buffers(self, n: int):
        """(per (n,), slot tiles, slot keys (n * PAIR_SLOTS,)) for one binning: the ones the
        last sweep gave back, or new ones; give them back with give_buffers."""
        try:
            b = self._spare.pop()
        except IndexError:
            b = None
        if b is None or len(b[0]) != n:
            b = (np.empty(n, np.int64), np.empty(n * PAIR_SLOTS, np.int64),
                 np.empty(n * PAIR_SLOTS, np.float64))
        return b

    def give_buffers(self, b) -> None:
        if not self._spare:
            self._spare.append(b)

    def subset(self, idx) -> LidarSurfels:
        return LidarSurfels(*(np.ascontiguousarray(getattr(self, f)[idx]) for f in
                              ("c", "tu", "tv", "n", "s", "a", "rad", "packed")))


def surfel_frames(means, quats, scales, opacities) -> LidarSurfels:
    """The LidarSurfels of surfels given as ParticleField arrays (quaternions x, y, z, w)."""
    c = np.ascontiguousarray(means, np.float64).reshape(-1, 3)
    q = np.asarray(quats, np.float64).reshape(-1, 4)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    x, y, z, w = q.T
    tu = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], 1)
    tv = np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], 1)
    n = np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], 1)
    raw_s = np.asarray(scales, np.float64).reshape(len(c), -1)[:, :2] if len(c) else np.zeros((0, 2))
    s = np.ascontiguousarray(np.maximum(raw_s, 1e-8))
    a = np.ascontiguousarray(opacities, np.float64).reshape(-1)
    # u² + v² where the disk's alpha, min(a, ALPHA_MAX) · exp(-(u² + v²) / 2), falls to
    # ALPHA_MIN: its radius bounds the binning (clamped a), its unclamped value the trace
    with np.errstate(divide="ignore", invalid="ignore"):
        q_max = 2.0 * np.log(a / ALPHA_MIN)
    q2 = np.minimum(q_max, 2.0 * math.log(ALPHA_MAX / ALPHA_MIN))
    rad = np.where(q2 > 0, np.sqrt(np.maximum(q2, 0.0)) * s.max(axis=1), 0.0)
    # degenerate surfels are never met: a scale of 0 (a point), anything not finite
    ok = (np.all(np.isfinite(c), axis=1) & np.all(np.isfinite(q), axis=1)
          & np.all(np.isfinite(raw_s), axis=1) & (np.min(raw_s, axis=1) > MIN_SCALE)
          & np.isfinite(a))
    rad = np.where(ok, rad, 0.0)
    # a little wider than exact, so that rounding never drops a ray the exact test keeps
    q_max = np.where(ok & (q_max > 0), q_max * (1.0 + Q_MARGIN) + Q_MARGIN, -1.0)
    packed = np.concatenate([c, tu, tv, n, 1.0 / s, a[:, None], q_max[:, None]], axis=1)
    return LidarSurfels(c, np.ascontiguousarray(tu), np.ascontiguousarray(tv),
                        np.ascontiguousarray(n), s, a, rad, np.ascontiguousarray(packed))


@njit(cache=True, inline="always")
def _hit_packed(ox, oy, oz, dx, dy, dz, P, p):
    """_hit with the surfel's parameters in row p of P (LidarSurfels.packed)."""
    den = dx * P[p, 9] + dy * P[p, 10] + dz * P[p, 11]
    if abs(den) < 1e-12:
        return -1.0, 0.0
    wx, wy, wz = P[p, 0] - ox, P[p, 1] - oy, P[p, 2] - oz
    t = (wx * P[p, 9] + wy * P[p, 10] + wz * P[p, 11]) / den
    px, py, pz = t * dx - wx, t * dy - wy, t * dz - wz
    u = (px * P[p, 3] + py * P[p, 4] + pz * P[p, 5]) * P[p, 12]
    v = (px * P[p, 6] + py * P[p, 7] + pz * P[p, 8]) * P[p, 13]
    q = u * u + v * v
    if q > 2.0 * 6.2:       # exp(-6.2) < 1/255 · 0.99: below alpha_min for any opacity
        return -1.0, 0.0
    al = P[p, 14] * math.exp(-0.5 * q)
    al = min(al, ALPHA_MAX)
    if al < ALPHA_MIN:
        return -1.0, 0.0
    return t, al


# ----------------------------------------------------------------------------- binning
@njit(cache=True, parallel=prange_only())
def rotate_columns(rot, d):
    """(R, C, 3) directions: each column's ``d[:, c]`` (sensor frame) turned by its pose's
    rotation ``rot[c]`` (3, 3) — a sweep's rays in the world, the products summed in axis
    order (as an einsum does, in float64)."""
    R, C = d.shape[0], d.shape[1]
    out = np.empty((R, C, 3))
    for r in prange(R):
        for c in range(C):
            x, y, z = d[r, c, 0], d[r, c, 1], d[r, c, 2]
            for i in range(3):
                out[r, c, i] = rot[c, i, 0] * x + rot[c, i, 1] * y + rot[c, i, 2] * z
    return out


@njit(cache=True, parallel=prange_only())
def _tile_bounds(dirs, tc, tr):
    """Per tile (ring group, column group): the world azimuth of its middle ray, the largest
    azimuth difference of its rays from it, and the range of the sines of its rays'
    elevations (the sine rises with the elevation: compared as they are, no asin)."""
    R, C = dirs.shape[0], dirs.shape[1]
    nr, nc = (R + tr - 1) // tr, (C + tc - 1) // tc
    az_mid = np.zeros((nr, nc))
    az_half = np.zeros((nr, nc))
    el_lo = np.zeros((nr, nc))
    el_hi = np.zeros((nr, nc))
    for h in prange(nr):
        i0, i1 = h * tr, min(R, (h + 1) * tr)
        for g in range(nc):
            j0, j1 = g * tc, min(C, (g + 1) * tc)
            im, jm = (i0 + i1 - 1) // 2, (j0 + j1 - 1) // 2
            mid = math.atan2(dirs[im, jm, 1], dirs[im, jm, 0])
            az_mid[h, g] = mid
            lo, hi, half = 10.0, -10.0, 0.0
            for i in range(i0, i1):
                for j in range(j0, j1):
                    d = dirs[i, j]
                    el = max(-1.0, min(1.0, d[2]))      # the sine of the elevation
                    lo, hi = min(lo, el), max(hi, el)
                    daz = math.atan2(d[1], d[0]) - mid
                    daz = (daz + math.pi) % (2 * math.pi) - math.pi
                    half = max(half, abs(daz))
            el_lo[h, g], el_hi[h, g], az_half[h, g] = lo, hi, half
    return az_mid, az_half, el_lo, el_hi


@njit(cache=True, inline="always")
def _wrap(a):
    """a brought into [-pi, pi] (a within a few turns of it)."""
    while a > math.pi:
        a -= 2 * math.pi
    while a < -math.pi:
        a += 2 * math.pi
    return a


@njit(cache=True, inline="always")
def _cone(c, rad, k, o, dm):
    """The directions from o in which surfel k (its bounding sphere grown by dm, the spread
    of the origins it stands for) can be seen: (nearest distance, sines of the lowest and
    highest elevation, azimuth of the centre, azimuthal half-width, whether every azimuth
    is). The elevations' sines come from the sphere's angular radius h (sin h = r / dist) by
    the angle-sum formulas: square roots, not asin, sin and cos per surfel."""
    wx, wy, wz = c[k, 0] - o[0], c[k, 1] - o[1], c[k, 2] - o[2]
    hyp2 = wx * wx + wy * wy
    dist = math.sqrt(hyp2 + wz * wz)
    r = rad[k] + dm
    if dist <= r:
        return 0.0, -10.0, 10.0, 0.0, math.pi, True
    sh = r / dist
    ch = math.sqrt(max(0.0, 1.0 - sh * sh))
    se, ce_ = wz / dist, math.sqrt(hyp2) / dist             # sine and cosine of the elevation
    lo, hi = se * ch - ce_ * sh, se * ch + ce_ * sh         # sin(el - h), sin(el + h)
    if ce_ * ch - se * sh < 0.0:        # el + h beyond the zenith
        hi = 1.0
    if ce_ * ch + se * sh < 0.0:        # el - h beyond the nadir
        lo = -1.0
    lo, hi = lo - 1e-12, hi + 1e-12     # rounding never narrows the bound
    ce = ce_ * ch - abs(se) * sh        # cos(|el| + h)
    if ce <= 1e-9 or sh >= ce:
        return dist - r, lo, hi, 0.0, math.pi, True     # over a pole: any azimuth
    # a cap of angular radius h at elevation el spans asin(sin h / cos el) in azimuth;
    # cos(|el| + h) <= cos el keeps the bound conservative, and so does tan(asin x) =
    # x / sqrt(1 - x²) >= asin x (a square root, not asin: 4e-5 rad, 0.08 %, wider at x = 0.05)
    x = sh / ce
    return dist - r, lo, hi, math.atan2(wy, wx), x / math.sqrt(1.0 - x * x), False


@njit(cache=True)
def _group_azimuths(dirs, tc):
    """Per column group: the world azimuth of its middle column's rays (unwrapped so that it
    decreases along the sweep, as the head turns clockwise) and the group's half-width."""
    R, C = dirs.shape[0], dirs.shape[1]
    nc = (C + tc - 1) // tc
    mid = np.zeros(nc)
    half = np.zeros(nc)
    im = R // 2
    prev = 0.0
    for g in range(nc):
        j0, j1 = g * tc, min(C, (g + 1) * tc)
        jm = (j0 + j1 - 1) // 2
        a = math.atan2(dirs[im, jm, 1], dirs[im, jm, 0])
        if g > 0:
            while a > prev + math.pi:
                a -= 2 * math.pi
            while a < prev - math.pi:
                a += 2 * math.pi
        mid[g] = a
        prev = a
        h = 0.0
        for i in range(R):
            for j in range(j0, j1):
                d = math.atan2(dirs[i, j, 1], dirs[i, j, 0]) - a
                d = (d + math.pi) % (2 * math.pi) - math.pi
                h = max(h, abs(d))
        half[g] = h
    return mid, half


@njit(cache=True, inline="always")
def _candidate_groups(az, w, mid, half_max, full_turn):
    """(first, last) column groups (last may exceed the count: wrap) whose azimuths can reach
    the interval az ± w about the sweep's reference origin."""
    nc = mid.shape[0]
    step = (mid[0] - mid[nc - 1]) / max(nc - 1, 1) if nc > 1 else 2 * math.pi
    if step <= 0:
        return 0, nc - 1
    # bring az into [mid[-1] - pi, mid[-1] + 2 pi) around the sweep's azimuths
    a = az
    while a > mid[0] + math.pi:
        a -= 2 * math.pi
    while a < mid[nc - 1] - math.pi:
        a += 2 * math.pi
    f = (mid[0] - a) / step
    span = (w + half_max) / step + 1.0
    lo = int(math.floor(f - span))
    hi = int(math.ceil(f + span))
    if full_turn:
        if hi - lo + 1 >= nc:
            return 0, nc - 1
        return lo, hi       # indices taken modulo nc
    return max(lo, 0), min(hi, nc - 1)


@njit(cache=True, inline="always")
def _bin_group(g, near, e0, e1, az, w, anyaz, mid, half, el_lo, el_hi, az_mid, az_half,
               rings_sorted, lim, n, p, tile_of, key):
    """_bin's pairs of one surfel (its cone from a sector's origin) in column group g:
    written at p while n < lim; (p, n) after them."""
    nr, nc = az_mid.shape
    if not anyaz and abs(_wrap(az - mid[g])) > half[g] + w:
        return p, n         # the whole column group is beside the surfel
    h0 = 0
    if rings_sorted:        # the first ring group reaching up to e0
        a_, b_ = 0, nr
        while a_ < b_:
            m_ = (a_ + b_) >> 1
            if el_hi[m_, g] < e0:
                a_ = m_ + 1
            else:
                b_ = m_
        h0 = a_
    for hh in range(h0, nr):
        if el_lo[hh, g] > e1:
            if rings_sorted:
                break
            continue
        if el_hi[hh, g] < e0:
            continue
        if not anyaz and abs(_wrap(az - az_mid[hh, g])) > az_half[hh, g] + w:
            continue
        if n < lim:
            tile_of[p] = hh * nc + g
            key[p] = near
            p += 1
        n += 1
    return p, n


@njit(cache=True, parallel=prange_only())
def _bin(c, rad, oref, dref, sec_org, sec_d, sec_groups, az_mid, az_half, el_lo, el_hi,
         rings_sorted, mid, half, half_max, full_turn, max_range, mode, cap, per, offsets,
         tile_of, key):
    """Per surfel, the tiles it can reach and the nearest distance it can be met at from
    their rays. Candidate column groups come from the sweep's reference origin with the
    surfel's bounding sphere grown by the spread of all column origins; the tiles of each
    sector (``sec_groups`` consecutive column groups) among them are then tested from the
    sector's own origin, grown by the sector's spread (centimetres on a moving ego, where the
    whole sweep spreads a metre). per[k] gets surfel k's number of (tile, nearest distance)
    pairs; mode 0 writes no pairs, mode 1 writes them from offsets[k], mode 2 writes the first
    ``cap`` of them from k * cap (one pass for the many surfels with few pairs)."""
    nr, nc = az_mid.shape
    N = c.shape[0]
    el_min, el_max = np.min(el_lo), np.max(el_hi)
    nblk = (N + BIN_BLOCK - 1) // BIN_BLOCK
    for q_ in prange(nblk):     # blocks scattered over the threads: work follows the sensor
        b_ = _spread(q_, nblk)
        for k in range(b_ * BIN_BLOCK, min(N, (b_ + 1) * BIN_BLOCK)):
            n = 0
            p = offsets[k] if mode == 1 else k * cap
            lim = 1 << 62
            if mode == 2:
                lim = cap
            elif mode == 0:
                lim = 0
            # beyond range from every origin: rejected before _cone's trigonometry
            wx, wy, wz = c[k, 0] - oref[0], c[k, 1] - oref[1], c[k, 2] - oref[2]
            reach = max_range + rad[k] + dref
            if rad[k] > 0.0 and wx * wx + wy * wy + wz * wz <= reach * reach:
                near0, lo0, hi0, az0, w0, every = _cone(c, rad, k, oref, dref)
                # above or below every beam (a building's upper floors, a tree's crown):
                # rejected before the sectors' cones
                if near0 <= max_range and hi0 >= el_min and lo0 <= el_max:
                    if every:
                        g0, g1 = 0, nc - 1
                    else:
                        g0, g1 = _candidate_groups(az0, w0, mid, half_max, full_turn)
                    # the sectors the candidate groups fall in, each with its own (tighter)
                    # cone: only its groups that cone can reach are visited (the sweep-wide cone
                    # spreads by the whole sweep's travel, a metre on a moving ego)
                    g = g0 % nc
                    left = g1 - g0 + 1
                    while left > 0:
                        sec = g // sec_groups
                        qb = min((sec + 1) * sec_groups, nc)
                        a, b = g, min(qb, g + left) - 1          # this sector's part of g0..g1
                        left -= b - a + 1
                        g = qb % nc
                        near, e0, e1, az, w, anyaz = _cone(c, rad, k, sec_org[sec], sec_d[sec])
                        if near > max_range:
                            continue
                        lo, hi = a, b
                        if not anyaz:
                            lo, hi = _candidate_groups(az, w, mid, half_max, full_turn)
                        if hi - lo + 1 >= nc:
                            lo, hi = a, b
                        # the cone's groups lo..hi (modulo nc: disjoint when fewer than nc) in a..b
                        for shift in (-nc, 0, nc):
                            for gg in range(max(a, lo + shift), min(b, hi + shift) + 1):
                                p, n = _bin_group(gg, near, e0, e1, az, w, anyaz, mid, half,
                                                  el_lo, el_hi, az_mid, az_half, rings_sorted,
                                                  lim, n, p, tile_of, key)
            per[k] = n


@njit(cache=True)
def _by_tile(per, cap, slot_tile, slot_key, over_start, over_tile, over_key, n_tiles):
    """Pairs grouped by tile (counting sort), in surfel order within a tile: (offsets, surfel
    index, key). Surfel k's pairs are slots k * cap ... when per[k] <= cap, else the next run
    of the overflow pairs (over_start: their offsets, surfels with per > cap in order)."""
    N = per.shape[0]
    counts = np.zeros(n_tiles + 1, np.int64)
    j = 0
    for k in range(N):
        if per[k] <= cap:
            for i in range(k * cap, k * cap + per[k]):
                counts[slot_tile[i] + 1] += 1
        else:
            for i in range(over_start[j], over_start[j + 1]):
                counts[over_tile[i] + 1] += 1
            j += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    offsets = counts.copy()
    pos = counts[:-1].copy()
    M = offsets[n_tiles]
    idx = np.empty(M, np.int64)
    kk = np.empty(M, np.float64)
    j = 0
    for k in range(N):
        if per[k] <= cap:
            for i in range(k * cap, k * cap + per[k]):
                t = slot_tile[i]
                idx[pos[t]] = k
                kk[pos[t]] = slot_key[i]
                pos[t] += 1
        else:
            for i in range(over_start[j], over_start[j + 1]):
                t = over_tile[i]
                idx[pos[t]] = k
                kk[pos[t]] = over_key[i]
                pos[t] += 1
            j += 1
    return offsets, idx, kk


@njit(cache=True, inline="always")
def _spread(q, n):
    """A permutation of 0..n-1 that scatters every run of q over all of it: a parallel loop
    hands each thread a run of q, and the tiles' work is anything but even (the ground's
    ring groups hold most pairs, the sky's none)."""
    q, n = np.int64(q), np.int64(n)
    if n < 2 or n % SPREAD_PRIME == 0:
        return q
    return (q * SPREAD_PRIME) % n


KEY_OCTAVES = (-1, 10)   # the keys _bucket_tiles orders: 0.5 m to 1 km (outside: the ends)
KEY_SPLITS = 5           # bits of mantissa a bucket keeps: 32 buckets an octave (3 % apart)


@njit(cache=True, parallel=prange_only())
def _bucket_tiles(offsets, idx, key):
    """Each tile's pairs grouped by key into buckets 1/32 of an octave wide (a counting sort,
    ties in surfel order), each key lowered to its bucket's floor. The trace needs no finer
    order: it stops at the first key beyond every ray's return, and a floor is still a
    lower bound of where the surfel can be met (its hits are composited by t in any order).
    The bucket is the key's float64 exponent and top mantissa bits (keys are >= 0)."""
    bits = key.view(np.int64)
    shift = 52 - KEY_SPLITS
    base = np.int64(1023 + KEY_OCTAVES[0]) << KEY_SPLITS       # the bucket of 2**KEY_OCTAVES[0]
    nb = (KEY_OCTAVES[1] - KEY_OCTAVES[0]) << KEY_SPLITS
    n = offsets.shape[0] - 1
    for q in prange(n):
        t = _spread(q, n)
        a, b = offsets[t], offsets[t + 1]
        m = b - a
        if m < 2:
            continue
        cnt = np.zeros(nb + 2, np.int64)
        bk = np.empty(m, np.int64)
        for i in range(m):
            v = min(max((bits[a + i] >> shift) - base + 1, 0), nb)     # 0: below 0.5 m
            bk[i] = v
            cnt[v + 1] += 1
        for v in range(nb + 1):
            cnt[v + 1] += cnt[v]
        ids = idx[a:b].copy()
        for i in range(m):
            v = bk[i]
            p = a + cnt[v]
            cnt[v] += 1
            idx[p] = ids[i]
            bits[p] = 0 if v == 0 else (v - 1 + base) << shift


# ----------------------------------------------------------------------------- tracing
@njit(cache=True, parallel=prange_only())
def _trace(dirs, origins, P, offsets, idx, key, tc, tr, tmin, tmax, out_t, out_k):
    R, C = dirs.shape[0], dirs.shape[1]
    nr, nc = (R + tr - 1) // tr, (C + tc - 1) // tc
    for t_ in prange(nr * nc):
        h, g = t_ // nc, t_ % nc
        lo, hi = offsets[t_], offsets[t_ + 1]
        ht = np.empty(MAX_HITS)
        ha = np.empty(MAX_HITS)
        hk = np.empty(MAX_HITS, np.int64)
        for i in range(h * tr, min(R, (h + 1) * tr)):
            for j in range(g * tc, min(C, (g + 1) * tc)):
                ox, oy, oz = origins[j, 0], origins[j, 1], origins[j, 2]
                dx, dy, dz = dirs[i, j, 0], dirs[i, j, 1], dirs[i, j, 2]
                n = 0
                best = np.inf     # the return so far (inf: none)
                for p in range(lo, hi):
                    if key[p] > min(best, tmax):
                        break
                    k = idx[p]
                    tt, al = _hit_packed(ox, oy, oz, dx, dy, dz, P, k)
                    if tt < tmin or tt > tmax or tt >= best:
                        continue
                    # insert by t (a full buffer drops its farthest hit)
                    if n == MAX_HITS:
                        if tt >= ht[n - 1]:
                            continue
                        n -= 1
                    q = n
                    while q > 0 and ht[q - 1] > tt:
                        ht[q], ha[q], hk[q] = ht[q - 1], ha[q - 1], hk[q - 1]
                        q -= 1
                    ht[q], ha[q], hk[q] = tt, al, k
                    n += 1
                    # the return: where the transmittance first falls below 0.5
                    T = 1.0
                    for m in range(n):
                        T *= 1.0 - ha[m]
                        if T < 0.5:
                            best = ht[m]
                            out_k[i, j] = hk[m]
                            n = m + 1       # hits behind the return no longer matter
                            break
                out_t[i, j] = best


@njit(cache=True, parallel=prange_only())
def _trace_tiles(dirs, origins, P, offsets, idx, key, tc, tr, tmin, tmax, out_t, out_k):
    """_trace with a tile's rays taken together: each candidate surfel is met by all the
    tile's rays in one tight loop (scalar: Python's error model checks each division; with
    numpy's it vectorises and is no faster, docs/sensors.md) (most pairs miss: the disk's
    Gaussian is below alpha_min there: such a pair skips the rest), and only the rays it reaches go
    through the ordered insert, their t worked out again by the same operations. The
    tile stops once the candidates' nearest distance passes every ray's return: each ray sees
    a superset of the surfels _trace gives it, the extra ones beyond its return."""
    R, C = dirs.shape[0], dirs.shape[1]
    nr, nc = (R + tr - 1) // tr, (C + tc - 1) // tc
    mm = tr * tc
    for g in prange(nc):
        # a column group per iteration, its ring groups in turn: the threads' halves of the
        # sweep are halves of its azimuths, each with ground and sky (by rows of tiles one
        # thread got the ground's ring groups, with most of the pairs), and the buffers
        # are made once per column, not per tile
        ox, oy, oz = np.empty(mm), np.empty(mm), np.empty(mm)
        dx, dy, dz = np.empty(mm), np.empty(mm), np.empty(mm)
        qq = np.empty(mm)
        best = np.empty(mm)
        kk = np.empty(mm, np.int64)
        nh = np.empty(mm, np.int64)
        ht = np.empty((mm, MAX_HITS))
        ha = np.empty((mm, MAX_HITS))
        hk = np.empty((mm, MAX_HITS), np.int64)
        for h in range(nr):
            _trace_tile(h, g, nc, R, C, tr, tc, dirs, origins, P, offsets, idx, key, tmin,
                        tmax, out_t, out_k, ox, oy, oz, dx, dy, dz, qq, best, kk, nh, ht, ha,
                        hk)


@njit(cache=True)
def _trace_tile(h, g, nc, R, C, tr, tc, dirs, origins, P, offsets, idx, key, tmin, tmax,
                out_t, out_k, ox, oy, oz, dx, dy, dz, qq, best, kk, nh, ht, ha, hk):
    """_trace_tiles' tile (ring group h, column group g), in the buffers given."""
    Q_MAX = 2.0 * 6.2
    t_ = h * nc + g
    lo, hi = offsets[t_], offsets[t_ + 1]
    i0, i1 = h * tr, min(R, (h + 1) * tr)
    j0, j1 = g * tc, min(C, (g + 1) * tc)
    m_ = (i1 - i0) * (j1 - j0)
    best[:m_] = np.inf
    kk[:m_] = -1
    nh[:m_] = 0
    r = 0
    for i in range(i0, i1):
        for j in range(j0, j1):
            ox[r], oy[r], oz[r] = origins[j, 0], origins[j, 1], origins[j, 2]
            dx[r], dy[r], dz[r] = dirs[i, j, 0], dirs[i, j, 1], dirs[i, j, 2]
            r += 1
    limit = tmax
    for p in range(lo, hi):
        if key[p] > limit:
            break
        k = idx[p]
        cx, cy, cz = P[k, 0], P[k, 1], P[k, 2]
        ux, uy, uz = P[k, 3], P[k, 4], P[k, 5]
        vx, vy, vz = P[k, 6], P[k, 7], P[k, 8]
        nx, ny, nz = P[k, 9], P[k, 10], P[k, 11]
        isu, isv = P[k, 12], P[k, 13]
        # beyond q_max the surfel's alpha is below ALPHA_MIN whatever t is: only the rays
        # within both bounds are worth the exact test (Q_MAX: the same for every opacity)
        qk = min(P[k, 15], Q_MAX)
        met = 0
        for r in range(m_):
            den = dx[r] * nx + dy[r] * ny + dz[r] * nz
            wx, wy, wz = cx - ox[r], cy - oy[r], cz - oz[r]
            t = (wx * nx + wy * ny + wz * nz) / den
            px, py, pz = t * dx[r] - wx, t * dy[r] - wy, t * dz[r] - wz
            u = (px * ux + py * uy + pz * uz) * isu
            v = (px * vx + py * vy + pz * vz) * isv
            q = u * u + v * v
            qq[r] = q
            met += q <= qk
        if met == 0:
            continue        # most pairs: no ray of the tile comes near the disk
        changed = False
        for r in range(m_):
            if not qq[r] <= qk:
                continue
            # t again (the same operations: the same bits) for the few rays that come near
            den = dx[r] * nx + dy[r] * ny + dz[r] * nz
            if abs(den) < 1e-12:
                continue
            wx, wy, wz = cx - ox[r], cy - oy[r], cz - oz[r]
            t = (wx * nx + wy * ny + wz * nz) / den
            if t < tmin or t > tmax or t >= best[r]:
                continue
            al = P[k, 14] * math.exp(-0.5 * qq[r])
            al = min(al, ALPHA_MAX)
            if al < ALPHA_MIN:
                continue
            n = nh[r]
            if n == MAX_HITS:
                if t >= ht[r, n - 1]:
                    continue
                n -= 1
            q = n
            while q > 0 and ht[r, q - 1] > t:
                ht[r, q], ha[r, q], hk[r, q] = ht[r, q - 1], ha[r, q - 1], hk[r, q - 1]
                q -= 1
            ht[r, q], ha[r, q], hk[r, q] = t, al, k
            n += 1
            T = 1.0
            for m in range(n):
                T *= 1.0 - ha[r, m]
                if T < 0.5:
                    best[r] = ht[r, m]
                    kk[r] = hk[r, m]
                    n = m + 1
                    changed = True
                    break
            nh[r] = n
        if changed:
            limit = 0.0
            for r in range(m_):
                limit = max(limit, min(best[r], tmax))
    r = 0
    for i in range(i0, i1):
        for j in range(j0, j1):
            out_t[i, j] = best[r]
            out_k[i, j] = kk[r]
            r += 1


@njit(cache=True, parallel=prange_only())
def _trace_meshes(dirs, origins, col_group, local_from_world, verts, faces, face_lo,
                  face_hi, box_lo, box_hi, tmin, tmax, out_t, out_a, out_f):
    """Nearest triangle hit per ray over mesh actors (actor-local geometry; per column group
    its local-from-world transform at that group's time). out_a: the actor index, out_f the
    face."""
    R, C = dirs.shape[0], dirs.shape[1]
    A = face_lo.shape[0]
    for j in prange(C):
        g = col_group[j]
        for i in range(R):
            best = np.inf
            who = -1
            face = -1
            for q in range(A):
                M = local_from_world[g, q]
                ox = M[0, 0] * origins[j, 0] + M[0, 1] * origins[j, 1] + M[0, 2] * origins[j, 2] + M[0, 3]
                oy = M[1, 0] * origins[j, 0] + M[1, 1] * origins[j, 1] + M[1, 2] * origins[j, 2] + M[1, 3]
                oz = M[2, 0] * origins[j, 0] + M[2, 1] * origins[j, 1] + M[2, 2] * origins[j, 2] + M[2, 3]
                dx = M[0, 0] * dirs[i, j, 0] + M[0, 1] * dirs[i, j, 1] + M[0, 2] * dirs[i, j, 2]
                dy = M[1, 0] * dirs[i, j, 0] + M[1, 1] * dirs[i, j, 1] + M[1, 2] * dirs[i, j, 2]
                dz = M[2, 0] * dirs[i, j, 0] + M[2, 1] * dirs[i, j, 1] + M[2, 2] * dirs[i, j, 2]
                # slab test against the actor's local box
                t0, t1 = tmin, min(tmax, best)
                ok = True
                for e, (o_, d_) in enumerate(((ox, dx), (oy, dy), (oz, dz))):
                    if abs(d_) < 1e-15:
                        if o_ < box_lo[q, e] or o_ > box_hi[q, e]:
                            ok = False
                        continue
                    ta, tb = (box_lo[q, e] - o_) / d_, (box_hi[q, e] - o_) / d_
                    if ta > tb:
                        ta, tb = tb, ta
                    t0, t1 = max(t0, ta), min(t1, tb)
                if not ok or t0 > t1:
                    continue
                for f in range(face_lo[q], face_hi[q]):
                    v0, v1, v2 = verts[faces[f, 0]], verts[faces[f, 1]], verts[faces[f, 2]]
                    e1x, e1y, e1z = v1[0] - v0[0], v1[1] - v0[1], v1[2] - v0[2]
                    e2x, e2y, e2z = v2[0] - v0[0], v2[1] - v0[1], v2[2] - v0[2]
                    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
                    det = e1x * px + e1y * py + e1z * pz
                    if abs(det) < 1e-15:
                        continue
                    inv = 1.0 / det
                    sx, sy, sz = ox - v0[0], oy - v0[1], oz - v0[2]
                    uu = (sx * px + sy * py + sz * pz) * inv
                    if uu < 0.0 or uu > 1.0:
                        continue
                    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
                    vv = (dx * qx + dy * qy + dz * qz) * inv
                    if vv < 0.0 or uu + vv > 1.0:
                        continue
                    tt = (e2x * qx + e2y * qy + e2z * qz) * inv
                    if tmin <= tt < best and tt <= tmax:
                        best, who, face = tt, q, f
            out_t[i, j] = best
            out_a[i, j] = who
            out_f[i, j] = face


@dataclass
class RayHits:
    """Per ray (R, C): distance of the return (inf: none), the surfel it came from (-1: none or
    a mesh), the mesh actor and face it came from (-1: none or a surfel)."""
    t: np.ndarray
    surfel: np.ndarray
    actor: np.ndarray
    face: np.ndarray
    stats: dict = field(default_factory=dict)


def _sweep_ordered(mid) -> bool:
    """Whether the column groups' azimuths fall by a near-constant step (a sweep, as
    ``LidarModel.directions`` orders them), which lets a surfel's candidate groups be found by
    the step: within half a step of the line through the first and last."""
    if len(mid) < 2:
        return True
    step = (mid[0] - mid[-1]) / (len(mid) - 1)
    line = mid[0] - step * np.arange(len(mid))
    return bool(step > 0 and np.max(np.abs(mid - line)) <= 0.5 * step)


def cast_surfels(surfels, origins, dirs, *, min_range: float, max_range: float,
                 tile=(TILE_RINGS, TILE_COLS)):
    """(t (R, C) float64, surfel index (R, C) int64) of the returns of rays from
    ``origins`` (C, 3: one per column) along ``dirs`` (R, C, 3, unit) against the surfels
    ``surfels`` (LidarSurfels); and statistics (binned pairs, seconds binning and tracing). Any rays give exact
    returns; rays in sweep order (columns of falling azimuth, as ``LidarModel.directions``)
    are binned by angle, others against every column group (slower)."""
    c, rad = surfels.c, surfels.rad
    dirs = np.ascontiguousarray(dirs, np.float64)
    origins = np.ascontiguousarray(origins, np.float64)
    R, C = dirs.shape[:2]
    tr, tc = int(tile[0]), int(tile[1])
    out_t = np.full((R, C), np.inf)
    out_k = np.full((R, C), -1, np.int64)
    if len(c) == 0 or R == 0 or C == 0:
        return out_t, out_k, {"pairs": 0, "bin_s": 0.0, "trace_s": 0.0}
    az_mid, az_half, el_lo, el_hi = _tile_bounds(dirs, tc, tr)
    oref = origins.mean(axis=0)
    dref = float(np.max(np.linalg.norm(origins - oref, axis=1)))
    mid, half = _group_azimuths(dirs, tc)
    full = bool(abs((mid[0] - mid[-1]) + (mid[0] - mid[-1]) / max(len(mid) - 1, 1)) >= 2 * np.pi - 1e-6)
    half_max = float(half.max())
    if not _sweep_ordered(mid):
        half_max = 1e3      # columns not in sweep order: every column group is a candidate
    # sectors of SECTOR_GROUPS column groups, each binned from its own origin
    nc = az_mid.shape[1]
    col_sec = np.minimum(np.arange(C) // (tc * SECTOR_GROUPS), (nc - 1) // SECTOR_GROUPS)
    n_sec = int(col_sec[-1]) + 1
    sec_org = np.stack([origins[col_sec == q].mean(axis=0) for q in range(n_sec)])
    sec_d = np.array([np.max(np.linalg.norm(origins[col_sec == q] - sec_org[q], axis=1))
                      for q in range(n_sec)])
    # ring groups whose elevation ranges rise with the index in every column group (any
    # model whose elevations are sorted, on a level enough ego) are searched, not scanned
    rings_sorted = bool(np.all(np.diff(el_lo, axis=0) >= 0) and np.all(np.diff(el_hi, axis=0) >= 0))
    args = (c, rad, oref, dref, sec_org, sec_d, SECTOR_GROUPS, az_mid, az_half, el_lo, el_hi,
            rings_sorted, mid, half, half_max, full, float(max_range))
    t0 = time.perf_counter()
    # one pass writes up to PAIR_SLOTS pairs per surfel (most have one or two); the few with
    # more are binned again, alone, into a buffer of their exact size
    N = len(c)
    bufs = surfels.take_buffers(N)
    per, slot_tile, slot_key = bufs       # _bin sets every per[k]
    _bin(*args, 2, PAIR_SLOTS, per, per, slot_tile, slot_key)
    over = np.flatnonzero(per > PAIR_SLOTS)
    over_start = np.zeros(len(over) + 1, np.int64)
    np.cumsum(per[over], out=over_start[1:])
    over_tile = np.empty(over_start[-1], np.int64)
    over_key = np.empty(over_start[-1], np.float64)
    if len(over):
        oc, orad = np.ascontiguousarray(c[over]), np.ascontiguousarray(rad[over])
        _bin(oc, orad, *args[2:], 1, 0, np.zeros(len(over), np.int64), over_start,
             over_tile, over_key)
    offsets, idx, key = _by_tile(per, PAIR_SLOTS, slot_tile, slot_key, over_start, over_tile,
                                 over_key, az_mid.size)
    surfels.give_buffers(bufs)
    _bucket_tiles(offsets, idx, key)
    t1 = time.perf_counter()
    (_trace_tiles if TRACE_TILES else _trace)(dirs, origins, surfels.packed, offsets, idx, key, tc, tr, float(min_range),
           float(max_range), out_t, out_k)
    out_k[~np.isfinite(out_t)] = -1
    return out_t, out_k, {"pairs": int(offsets[-1]), "bin_s": t1 - t0,
                          "trace_s": time.perf_counter() - t1}


@dataclass
class MeshActors:
    """Mesh actors for the LiDAR: actor-local geometry (vertices (V,3), faces (F,3)), each
    actor's face range and local box; ``local_from_world(times)`` gives (len(times), A, 4, 4)."""
    vertices: np.ndarray
    faces: np.ndarray
    face_lo: np.ndarray
    face_hi: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    local_from_world: object        # callable: times (G,) -> (G, A, 4, 4)

    @property
    def count(self) -> int:
        return len(self.face_lo)


def cast_meshes(actors: MeshActors, origins, dirs, column_times, *, min_range: float,
                max_range: float, tile_cols: int = TILE_COLS):
    """(t, actor index, face index), each (R, C), of the nearest mesh-actor hit per ray; the
    actors are placed at the mid time of each group of ``tile_cols`` columns."""
    dirs = np.ascontiguousarray(dirs, np.float64)
    R, C = dirs.shape[:2]
    out_t = np.full((R, C), np.inf)
    out_a = np.full((R, C), -1, np.int64)
    out_f = np.full((R, C), -1, np.int64)
    if actors is None or actors.count == 0:
        return out_t, out_a, out_f
    groups = (C + tile_cols - 1) // tile_cols
    col_group = (np.arange(C) // tile_cols).astype(np.int64)
    times = np.array([np.mean(column_times[g * tile_cols:(g + 1) * tile_cols])
                      for g in range(groups)])
    M = np.ascontiguousarray(actors.local_from_world(times), np.float64)
    _trace_meshes(dirs, np.ascontiguousarray(origins, np.float64), col_group, M,
                  np.ascontiguousarray(actors.vertices, np.float64),
                  np.ascontiguousarray(actors.faces, np.int64),
                  np.ascontiguousarray(actors.face_lo, np.int64),
                  np.ascontiguousarray(actors.face_hi, np.int64),
                  np.ascontiguousarray(actors.box_lo, np.float64),
                  np.ascontiguousarray(actors.box_hi, np.float64),
                  float(min_range), float(max_range), out_t, out_a, out_f)
    return out_t, out_a, out_f


def cast(surfels, actors: MeshActors | None, origins, dirs, column_times, *, min_range: float,
         max_range: float) -> RayHits:
    """The return of every ray among surfels and mesh actors (the nearer wins)."""
    st, sk, stats = cast_surfels(surfels, origins, dirs, min_range=min_range,
                                 max_range=max_range)
    t0 = time.perf_counter()
    mt, ma, mf = cast_meshes(actors, origins, dirs, column_times, min_range=min_range,
                             max_range=max_range)
    stats["meshes_s"] = time.perf_counter() - t0
    mesh = mt < st
    t = np.where(mesh, mt, st)
    return RayHits(t, np.where(mesh, -1, sk), np.where(mesh, ma, -1), np.where(mesh, mf, -1),
                   stats)


def cast_reference(surfels, origins, dirs, *, min_range: float, max_range: float):
    """The plain float64 reference of ``cast_surfels``: every surfel against every ray,
    composited in the order of t. Small scenes only."""
    c, tu, tv, nn, s, a = surfels.c, surfels.tu, surfels.tv, surfels.n, surfels.s, surfels.a
    R, C = dirs.shape[:2]
    out_t = np.full((R, C), np.inf)
    out_k = np.full((R, C), -1, np.int64)
    for j in range(C):
        o = np.asarray(origins[j], np.float64)
        for i in range(R):
            d = np.asarray(dirs[i, j], np.float64)
            den = nn @ d
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.einsum("ij,ij->i", c - o, nn) / den
            p = o + t[:, None] * d - c
            u = np.einsum("ij,ij->i", p, tu) / s[:, 0]
            v = np.einsum("ij,ij->i", p, tv) / s[:, 1]
            al = np.minimum(a * np.exp(-0.5 * (u * u + v * v)), ALPHA_MAX)
            ok = (np.abs(den) >= 1e-12) & (al >= ALPHA_MIN) & (t >= min_range) & (t <= max_range)
            ok &= surfels.rad > 0       # degenerate surfels are never met
            ok &= np.isfinite(t)
            ks = np.flatnonzero(ok)
            if not len(ks):
                continue
            order = ks[np.argsort(t[ks], kind="stable")]
            T = np.cumprod(1.0 - al[order])
            below = np.flatnonzero(T < 0.5)
            if len(below):
                out_t[i, j] = t[order[below[0]]]
                out_k[i, j] = order[below[0]]
    return out_t, out_k

