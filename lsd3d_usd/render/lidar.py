"""A spinning LiDAR as a sensor model of the renderer: which rays a sweep samples and when, and
where each ray first meets the scene.

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

The kernel bins surfels into tiles of rays (16 columns × 4 rings) by conservative angular
bounds from each tile's origin, sorts each tile's list by the nearest distance a surfel can be
met at, and stops a ray once that bound passes its return: the result is the same as
compositing every surfel (``cast_reference``, float64, every surfel per ray, for small
scenes), at a fraction of the work. float64 throughout.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from lsd3d_usd.errors import InputError

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
MAX_HITS = 128          # per ray, composited before the return (more: the nearest are kept)
TILE_COLS = 16
TILE_RINGS = 4
MAX_COLUMNS = 100_000
MAX_RINGS = 1024
MAX_RAYS = 20_000_000


@dataclass(frozen=True)
class LidarModel:
    """A spinning LiDAR (see the module doc). Ranges in metres, angles in degrees."""
    name: str
    elevations_deg: tuple          # per ring, ascending
    columns: int
    hfov_deg: float = 360.0
    min_range: float = 0.5
    max_range: float = 75.0
    rotation_hz: float = 10.0
    range_sigma: float = 0.0       # Gaussian range noise (m), seeded per sweep
    drop_prob: float = 0.0         # probability a return is dropped, seeded per sweep
    mount: tuple = (0.0, 0.0, 2.0, 0.0, 0.0, 0.0)   # x, y, z (m), roll, pitch, yaw (deg) on the ego
    extras: dict = field(default_factory=dict, compare=False)

    def check(self, where: str = "lidar") -> "LidarModel":
        """One InputError line naming the first bad key."""
        el = np.asarray(self.elevations_deg, np.float64)
        if el.ndim != 1 or not 1 <= len(el) <= MAX_RINGS:
            raise InputError(f"{where}: beams: need 1 to {MAX_RINGS} beams, got {el.size}")
        if not np.all(np.isfinite(el)) or np.any(np.abs(el) >= 90.0):
            bad = el[~np.isfinite(el) | (np.abs(el) >= 90.0)][0]
            raise InputError(f"{where}: elevations: {bad:g} deg is outside (-90, 90)")
        if np.any(np.diff(el) < 0):
            raise InputError(f"{where}: elevations: must be ascending (ring 0 lowest)")
        if not isinstance(self.columns, (int, np.integer)) or not 1 <= self.columns <= MAX_COLUMNS:
            raise InputError(f"{where}: columns: {self.columns} is outside 1 .. {MAX_COLUMNS}")
        if len(el) * self.columns > MAX_RAYS:
            raise InputError(f"{where}: {len(el)} beams x {self.columns} columns = "
                             f"{len(el) * self.columns} rays exceed the limit of {MAX_RAYS}")
        if not (math.isfinite(self.hfov_deg) and 0.0 < self.hfov_deg <= 360.0):
            raise InputError(f"{where}: hfov: {self.hfov_deg} must be in (0, 360]")
        if not (math.isfinite(self.min_range) and self.min_range >= 0.0):
            raise InputError(f"{where}: min_range: {self.min_range} must be >= 0")
        if not (math.isfinite(self.max_range) and self.max_range > self.min_range):
            raise InputError(f"{where}: max_range: {self.max_range} must exceed min_range "
                             f"{self.min_range}")
        if self.max_range > 10_000.0:
            raise InputError(f"{where}: max_range: {self.max_range} m exceeds the limit of 10000 m")
        if not (math.isfinite(self.rotation_hz) and 0.01 <= self.rotation_hz <= 1000.0):
            raise InputError(f"{where}: rotation_hz: {self.rotation_hz} is outside 0.01 .. 1000")
        if not (math.isfinite(self.range_sigma) and 0.0 <= self.range_sigma <= 10.0):
            raise InputError(f"{where}: range_sigma: {self.range_sigma} is outside 0 .. 10 m")
        if not (math.isfinite(self.drop_prob) and 0.0 <= self.drop_prob < 1.0):
            raise InputError(f"{where}: drop_prob: {self.drop_prob} is outside [0, 1)")
        m = np.asarray(self.mount, np.float64)
        if m.shape != (6,) or not np.all(np.isfinite(m)):
            raise InputError(f"{where}: mount: need x, y, z, roll, pitch, yaw (finite)")
        return self

    @property
    def rings(self) -> int:
        return len(self.elevations_deg)

    @property
    def sweep_seconds(self) -> float:
        """Time from the first column to the end of the last."""
        return (self.hfov_deg / 360.0) / self.rotation_hz

    def azimuths_deg(self) -> np.ndarray:
        """(C,) azimuth of each column in the sensor frame."""
        j = np.arange(self.columns, dtype=np.float64)
        return self.hfov_deg / 2.0 - (j + 0.5) * self.hfov_deg / self.columns

    def column_times(self) -> np.ndarray:
        """(C,) seconds after the sweep starts at which each column fires."""
        j = np.arange(self.columns, dtype=np.float64)
        return (j + 0.5) / self.columns * self.sweep_seconds

    def directions(self) -> np.ndarray:
        """(R, C, 3) unit beam directions in the sensor frame."""
        el = np.radians(np.asarray(self.elevations_deg, np.float64))[:, None]
        az = np.radians(self.azimuths_deg())[None, :]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                            np.sin(el)), axis=-1)

    def ego_from_sensor(self) -> np.ndarray:
        """4x4 mount of the sensor on the ego (roll about x, pitch about y, yaw about z)."""
        x, y, z, roll, pitch, yaw = (float(v) for v in self.mount)
        return pose_matrix((x, y, z), roll, pitch, yaw)

    def describe(self) -> dict:
        return {"name": self.name, "beams": self.rings, "columns": int(self.columns),
                "elevations_deg": [float(e) for e in self.elevations_deg],
                "hfov_deg": self.hfov_deg, "min_range": self.min_range,
                "max_range": self.max_range, "rotation_hz": self.rotation_hz,
                "range_sigma": self.range_sigma, "drop_prob": self.drop_prob,
                "mount": [float(v) for v in self.mount]}


def pose_matrix(xyz, roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """4x4 rigid transform R = Rz(yaw) Ry(pitch) Rx(roll), then the translation."""
    r, p, y = (math.radians(v) for v in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    M = np.eye(4)
    M[:3, :3] = Rz @ Ry @ Rx
    M[:3, 3] = xyz
    return M


# ----------------------------------------------------------------------------- surfel frames
def surfel_frames(means, quats, scales, opacities):
    """float64 arrays the kernels take: centres (N,3), t_u, t_v, n (N,3 each), scales (N,2),
    opacities (N,) and the radius (N,) beyond which a disk's alpha is below ALPHA_MIN (0 for
    a surfel that never reaches it)."""
    c = np.ascontiguousarray(means, np.float64)
    q = np.asarray(quats, np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    x, y, z, w = q.T
    tu = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], 1)
    tv = np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], 1)
    n = np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], 1)
    s = np.maximum(np.ascontiguousarray(scales, np.float64)[:, :2], 1e-8)
    a = np.ascontiguousarray(opacities, np.float64).reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        q2 = 2.0 * np.log(np.minimum(a, ALPHA_MAX) / ALPHA_MIN)
    rad = np.where(q2 > 0, np.sqrt(np.maximum(q2, 0.0)) * s.max(axis=1), 0.0)
    return c, tu, tv, n, s, a, rad


@njit(cache=True, inline="always")
def _hit(ox, oy, oz, dx, dy, dz, c, tu, tv, nn, s, a, k):
    """(t, alpha) of ray o + t d against surfel k; t = -1 where it does not count."""
    den = dx * nn[k, 0] + dy * nn[k, 1] + dz * nn[k, 2]
    if abs(den) < 1e-12:
        return -1.0, 0.0
    wx, wy, wz = c[k, 0] - ox, c[k, 1] - oy, c[k, 2] - oz
    t = (wx * nn[k, 0] + wy * nn[k, 1] + wz * nn[k, 2]) / den
    px, py, pz = ox + t * dx - c[k, 0], oy + t * dy - c[k, 1], oz + t * dz - c[k, 2]
    u = (px * tu[k, 0] + py * tu[k, 1] + pz * tu[k, 2]) / s[k, 0]
    v = (px * tv[k, 0] + py * tv[k, 1] + pz * tv[k, 2]) / s[k, 1]
    al = a[k] * math.exp(-0.5 * (u * u + v * v))
    if al > ALPHA_MAX:
        al = ALPHA_MAX
    if al < ALPHA_MIN:
        return -1.0, 0.0
    return t, al


@njit(cache=True, inline="always")
def _hit_packed(ox, oy, oz, dx, dy, dz, P, p):
    """_hit with the surfel's parameters packed in row p of P (centre, t_u, t_v, n,
    1/s_u, 1/s_v, opacity): the tile's surfels are read in order, not scattered."""
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
    if al > ALPHA_MAX:
        al = ALPHA_MAX
    if al < ALPHA_MIN:
        return -1.0, 0.0
    return t, al


@njit(cache=True, parallel=True)
def _pack(idx, c, tu, tv, nn, s, a):
    P = np.empty((idx.shape[0], 15))
    for p in prange(idx.shape[0]):
        k = idx[p]
        for e in range(3):
            P[p, e] = c[k, e]
            P[p, 3 + e] = tu[k, e]
            P[p, 6 + e] = tv[k, e]
            P[p, 9 + e] = nn[k, e]
        P[p, 12] = 1.0 / s[k, 0]
        P[p, 13] = 1.0 / s[k, 1]
        P[p, 14] = a[k]
    return P


# ----------------------------------------------------------------------------- binning
@njit(cache=True)
def _tile_bounds(dirs, origins, tc, tr):
    """Per tile (ring group, column group): the reference origin (mean of its columns'),
    the largest distance of a column origin from it, and the world azimuth / elevation ranges
    of its rays (azimuths unwrapped about the tile's middle ray)."""
    R, C = dirs.shape[0], dirs.shape[1]
    nr, nc = (R + tr - 1) // tr, (C + tc - 1) // tc
    org = np.zeros((nc, 3))
    dmax = np.zeros(nc)
    for g in range(nc):
        j0, j1 = g * tc, min(C, (g + 1) * tc)
        for j in range(j0, j1):
            for e in range(3):
                org[g, e] += origins[j, e] / (j1 - j0)
        for j in range(j0, j1):
            d = math.sqrt((origins[j, 0] - org[g, 0]) ** 2 + (origins[j, 1] - org[g, 1]) ** 2
                          + (origins[j, 2] - org[g, 2]) ** 2)
            dmax[g] = max(dmax[g], d)
    az_mid = np.zeros((nr, nc))
    az_half = np.zeros((nr, nc))
    el_lo = np.zeros((nr, nc))
    el_hi = np.zeros((nr, nc))
    for h in range(nr):
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
                    el = math.asin(max(-1.0, min(1.0, d[2])))
                    lo, hi = min(lo, el), max(hi, el)
                    daz = math.atan2(d[1], d[0]) - mid
                    daz = (daz + math.pi) % (2 * math.pi) - math.pi
                    half = max(half, abs(daz))
            el_lo[h, g], el_hi[h, g], az_half[h, g] = lo, hi, half
    return org, dmax, az_mid, az_half, el_lo, el_hi


@njit(cache=True, inline="always")
def _overlaps(c, rad, k, o, dm, az_mid, az_half, el_lo, el_hi):
    """Whether surfel k (bounding sphere) can be met by a ray of a tile with reference origin
    o, origin spread dm and the given angular ranges; and its nearest possible distance."""
    wx, wy, wz = c[k, 0] - o[0], c[k, 1] - o[1], c[k, 2] - o[2]
    dist = math.sqrt(wx * wx + wy * wy + wz * wz)
    r = rad[k] + dm
    near = dist - r
    if dist <= r:
        return True, 0.0
    h = math.asin(min(1.0, r / dist))
    el = math.asin(max(-1.0, min(1.0, wz / dist)))
    if el + h < el_lo or el - h > el_hi:
        return False, near
    ce = math.cos(abs(el) + h)
    if ce <= 1e-9:
        return True, near       # the sphere reaches over a pole: any azimuth
    w = math.asin(min(1.0, math.sin(h) / ce)) if math.sin(h) < ce else math.pi
    daz = math.atan2(wy, wx) - az_mid
    daz = (daz + math.pi) % (2 * math.pi) - math.pi
    return abs(daz) <= az_half + w, near


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


@njit(cache=True, parallel=True)
def _bin(c, rad, oref, dref, org, dmax, az_mid, az_half, el_lo, el_hi, mid, half_max,
         full_turn, max_range, counts_only, offsets, tile_of, key):
    """Per surfel, the tiles it can reach, from the sweep's reference origin with the surfel's
    bounding sphere grown by the spread of the column origins (conservative for every
    column), and the nearest distance it can be met at from any of them. counts_only: the
    number per surfel in tile_of[k]; else (tile, nearest distance) pairs written from
    offsets[k]."""
    nr, nc = az_mid.shape
    N = c.shape[0]
    for k in prange(N):
        if rad[k] <= 0.0:
            if counts_only:
                tile_of[k] = 0
            continue
        wx, wy, wz = c[k, 0] - oref[0], c[k, 1] - oref[1], c[k, 2] - oref[2]
        dist = math.sqrt(wx * wx + wy * wy + wz * wz)
        r = rad[k] + dref
        if dist - r > max_range:
            if counts_only:
                tile_of[k] = 0
            continue
        w = math.pi
        if dist <= r:
            g0, g1 = 0, nc - 1
            e0, e1 = -10.0, 10.0
        else:
            h = math.asin(min(1.0, r / dist))
            el = math.asin(max(-1.0, min(1.0, wz / dist)))
            e0, e1 = el - h, el + h
            ce = math.cos(min(abs(el) + h, math.pi / 2))
            if ce <= 1e-9 or math.sin(h) >= ce:
                g0, g1 = 0, nc - 1
            else:
                w = math.asin(math.sin(h) / ce)
                g0, g1 = _candidate_groups(math.atan2(wy, wx), w, mid, half_max, full_turn)
        n = 0
        p = 0 if counts_only else offsets[k]
        near = max(dist - r, 0.0)      # a lower bound of the distance from any column origin
        wide = dist <= r or g1 - g0 + 1 >= nc
        az = math.atan2(wy, wx)
        for gg in range(g0, g1 + 1):
            g = gg % nc
            for hh in range(nr):
                if el_hi[hh, g] < e0 or el_lo[hh, g] > e1:
                    continue
                if not wide:
                    daz = az - az_mid[hh, g]
                    daz = (daz + math.pi) % (2 * math.pi) - math.pi
                    if abs(daz) > az_half[hh, g] + w:
                        continue
                if counts_only:
                    n += 1
                else:
                    tile_of[p] = hh * nc + g
                    key[p] = near
                    p += 1
        if counts_only:
            tile_of[k] = n


@njit(cache=True)
def _by_tile(tile_of, key, surfel_of_pair, n_tiles):
    """Pairs grouped by tile (counting sort), each tile's by nearest distance: (offsets,
    surfel index, key)."""
    M = tile_of.shape[0]
    counts = np.zeros(n_tiles + 1, np.int64)
    for p in range(M):
        counts[tile_of[p] + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    offsets = counts.copy()
    pos = counts[:-1].copy()
    idx = np.empty(M, np.int64)
    kk = np.empty(M, np.float64)
    for p in range(M):
        t = tile_of[p]
        idx[pos[t]] = surfel_of_pair[p]
        kk[pos[t]] = key[p]
        pos[t] += 1
    return offsets, idx, kk


@njit(cache=True, parallel=True)
def _sort_tiles(offsets, idx, key):
    for t in prange(offsets.shape[0] - 1):
        a, b = offsets[t], offsets[t + 1]
        if b - a > 1:
            order = np.argsort(key[a:b], kind="mergesort")
            idx[a:b] = idx[a:b][order]
            key[a:b] = key[a:b][order]


# ----------------------------------------------------------------------------- tracing
@njit(cache=True, parallel=True)
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
                    tt, al = _hit_packed(ox, oy, oz, dx, dy, dz, P, p)
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


@njit(cache=True, parallel=True)
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


def cast_surfels(frames, origins, dirs, *, min_range: float, max_range: float,
                 tile=(TILE_RINGS, TILE_COLS)):
    """(t (R, C) float64, surfel index (R, C) int64) of the returns of rays from
    ``origins`` (C, 3: one per column) along ``dirs`` (R, C, 3, unit) against the surfels
    ``frames`` (surfel_frames); and the binned pairs (for statistics)."""
    c, tu, tv, nn, s, a, rad = frames
    dirs = np.ascontiguousarray(dirs, np.float64)
    origins = np.ascontiguousarray(origins, np.float64)
    R, C = dirs.shape[:2]
    tr, tc = int(tile[0]), int(tile[1])
    out_t = np.full((R, C), np.inf)
    out_k = np.full((R, C), -1, np.int64)
    if len(c) == 0:
        return out_t, out_k, 0
    org, dmax, az_mid, az_half, el_lo, el_hi = _tile_bounds(dirs, origins, tc, tr)
    oref = origins.mean(axis=0)
    dref = float(np.max(np.linalg.norm(origins - oref, axis=1)))
    mid, half = _group_azimuths(dirs, tc)
    full = bool(abs((mid[0] - mid[-1]) + (mid[0] - mid[-1]) / max(len(mid) - 1, 1)) >= 2 * np.pi - 1e-6)
    args = (c, rad, oref, dref, org, dmax, az_mid, az_half, el_lo, el_hi, mid,
            float(half.max()), full, float(max_range))
    per = np.zeros(len(c), np.int64)
    _bin(*args, True, per, per, np.zeros(0))
    starts = np.zeros(len(c) + 1, np.int64)
    np.cumsum(per, out=starts[1:])
    tile_of = np.empty(starts[-1], np.int64)
    key = np.empty(starts[-1], np.float64)
    _bin(*args, False, starts, tile_of, key)
    surfel_of_pair = np.repeat(np.arange(len(c), dtype=np.int64), per)
    offsets, idx, key = _by_tile(tile_of, key, surfel_of_pair, az_mid.size)
    _sort_tiles(offsets, idx, key)
    P = _pack(idx, c, tu, tv, nn, s, a)
    _trace(dirs, origins, P, offsets, idx, key, tc, tr, float(min_range), float(max_range),
           out_t, out_k)
    out_k[~np.isfinite(out_t)] = -1
    return out_t, out_k, int(offsets[-1])


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


def cast(frames, actors: MeshActors | None, origins, dirs, column_times, *, min_range: float,
         max_range: float) -> RayHits:
    """The return of every ray among surfels and mesh actors (the nearer wins)."""
    st, sk, pairs = cast_surfels(frames, origins, dirs, min_range=min_range, max_range=max_range)
    mt, ma, mf = cast_meshes(actors, origins, dirs, column_times, min_range=min_range,
                             max_range=max_range)
    mesh = mt < st
    t = np.where(mesh, mt, st)
    return RayHits(t, np.where(mesh, -1, sk), np.where(mesh, ma, -1), np.where(mesh, mf, -1),
                   {"pairs": pairs})


def cast_reference(frames, origins, dirs, *, min_range: float, max_range: float):
    """The plain float64 reference of ``cast_surfels``: every surfel against every ray,
    composited in the order of t. Small scenes only."""
    c, tu, tv, nn, s, a, _ = frames
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

