"""The procedural materials and weather (ggds/priors/materials.py) in one numba pass.

`materials.py` is the reference: torch, one material function per class, each a chain of
whole-array operations. This kernel computes the same per point — class, material, weather,
the clamps the prior applies — without a temporary per operation or a sort by class: the
prior's surface (the albedo, specular reflectance, roughness and wet mirror factor of every
covered pixel) took ~70 ms of a 960×540 target in torch. It mirrors the reference's
precision step by step (positions and lattice coordinates float64, the rest float32, Python
scalars rounded to float32 where torch rounds them), so the two agree bit for bit;
tests/test_ggds_priors_surface.py holds it to the reference class by class and in weather.
numba's cache watches this file only: the noise it calls (noise.fbm_at) is compiled into it,
so after an edit of noise.py clear the cache (those tests fail on a stale kernel); the colours
come from materials.py at each call (`_palettes`).
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit

from lsd3d_usd.ggds.priors import materials as mat
from lsd3d_usd.ggds.priors.noise import _mix_nb, _PRIMES, fbm_at
from lsd3d_usd.jitopts import run_in_slices
from lsd3d_usd.semantics import CLASS_ID

f32 = np.float32

_ROAD, _MARK, _CROSS = CLASS_ID["road"], CLASS_ID["lane_marking"], CLASS_ID["crosswalk"]
_CURB, _SIDEWALK, _BUILDING = CLASS_ID["curb"], CLASS_ID["sidewalk"], CLASS_ID["building"]
_VEG, _VEHICLE, _POLE = CLASS_ID["vegetation"], CLASS_ID["vehicle"], CLASS_ID["pole"]
_SIGN, _TERRAIN, _LIGHT = CLASS_ID["sign"], CLASS_ID["terrain"], CLASS_ID["traffic_light"]
if {c for c in mat.MATERIALS} != {_ROAD, _MARK, _CROSS, _CURB, _SIDEWALK, _BUILDING, _VEG,
                                   _VEHICLE, _POLE, _SIGN, _TERRAIN, _LIGHT}:
    raise ImportError("surface_kernel: materials.MATERIALS has classes this kernel does not shade")
_GROUND = np.array([CLASS_ID[c] for c in mat.GROUND_CLASSES], np.int64)

VEGETATION = tuple(mat.FOLIAGE)          # the vegetation states, by index


def _palettes() -> tuple:
    """materials.py's colours as the kernel takes them, read at each call: foliage and grass
    (V, 2, 3) by vegetation state, façade, car and sign palettes (K, 3), the pole's and the
    traffic light's tones (2, 3). Arguments, not globals: numba freezes a global array into
    the compiled kernel and its cache only watches this file, so an edit of materials.py
    would leave a cached kernel with the old colours."""
    return (np.array([mat.FOLIAGE[v] for v in VEGETATION], np.float32),
            np.array([mat.GRASS[v] for v in VEGETATION], np.float32),
            mat.FACADE_PALETTE.numpy().astype(np.float32),
            mat.CAR_COLORS.numpy().astype(np.float32),
            mat.SIGN_COLORS.numpy().astype(np.float32),
            np.array([mat.POLE_TONE, mat.TRAFFIC_LIGHT_TONE], np.float32))
_SHIFT = mat.WALL_CELL_SHIFT_M


@njit(cache=True, inline="always")
def _fbm(x, y, z, D, octaves, seed):
    """noise.fbm (value_noise: one octave) at one point, at its default lacunarity and gain."""
    return fbm_at(x, y, z, np.int64(D), np.int64(octaves), np.int64(seed), 2.0, 0.5)


@njit(cache=True, inline="always")
def _ss(e0, e1, x):
    """materials._smoothstep of a float32 x between float64 edges, rounded as torch does."""
    t = (x - f32(e0)) / f32(e1 - e0)
    t = min(max(t, f32(0.0)), f32(1.0))
    return t * t * (f32(3.0) - f32(2.0) * t)


@njit(cache=True, inline="always")
def _hash(a, b, c, n, seed):
    """noise.hash_float of n integer coordinates (a, b, c), float32."""
    h = (np.int64(seed) * 0x9E3779B1) & 0xFFFFFFFF
    h = _mix_nb(h ^ ((np.int64(a) * _PRIMES[0]) & 0xFFFFFFFF))
    if n > 1:
        h = _mix_nb(h ^ ((np.int64(b) * _PRIMES[1]) & 0xFFFFFFFF))
    if n > 2:
        h = _mix_nb(h ^ ((np.int64(c) * _PRIMES[2]) & 0xFFFFFFFF))
    return f32(h >> 8) * f32(1.0 / (1 << 24))


@njit(cache=True, inline="always")
def _cell(x, size):
    return np.int64(np.floor(x / size))


@njit(cache=True, inline="always")
def _mod1(x):
    """torch.remainder(x, 1.0) of a float64."""
    r = np.fmod(x, 1.0)
    if r < 0.0:
        r += 1.0
    return r


@njit(cache=True)
def _asphalt(x, y, seed):
    aggregate = _fbm(x / 0.012, y / 0.012, 0.0, 2, 1, seed + 1)
    fine = _fbm(x / 0.05, y / 0.05, 0.0, 2, 1, seed + 2)
    wear = _fbm(x / 3.0, y / 3.0, 0.0, 2, 3, seed + 3)
    patch = _ss(0.62, 0.66, _fbm(x / 9.0, y / 9.0, 0.0, 2, 2, seed + 4))
    crack_n = _fbm(x / 1.7, y / 1.7, 0.0, 2, 3, seed + 5)
    crack = f32(1.0) - _ss(0.0, 0.012, abs(crack_n - f32(0.5)))
    g = (f32(0.075) + f32(0.05) * (aggregate - f32(0.5)) + f32(0.02) * (fine - f32(0.5))
         + f32(0.035) * (wear - f32(0.5)))
    g = g * (f32(1.0) - f32(0.25) * patch) * (f32(1.0) - f32(0.45) * crack)
    return g, g * f32(1.0), g * f32(1.04)


@njit(cache=True)
def _concrete(x, y, z, seed, joint, tone):
    grain = _fbm(x / 0.05, y / 0.05, z / 0.05, 3, 2, seed + 21)
    stain = _fbm(x / 2.0, y / 2.0, 0.0, 2, 3, seed + 22)
    fx = _mod1(x / joint)
    fy = _mod1(y / joint)
    dist = f32(min(min(fx, 1 - fx), min(fy, 1 - fy))) * f32(joint)
    groove = f32(1.0) - _ss(0.004, 0.012, dist)
    g = (f32(tone) * (f32(1.0) + f32(0.15) * (grain - f32(0.5)) + f32(0.25) * (stain - f32(0.5)))
         * (f32(1.0) - f32(0.5) * groove))
    return g, g * f32(0.98), g * f32(0.94)


@njit(cache=True, inline="always")
def _lerp(a, b, w):
    return a + (b - a) * w


@njit(cache=True)
def _facade(x, y, z, nx, ny, nz, seed, floor_height, ground_z, window_spacing, palette):
    t0, t1 = -ny, nx
    tl = np.sqrt(t0 * t0 + t1 * t1)
    if tl > f32(1e-3):
        t0, t1 = t0 / max(tl, f32(1e-3)), t1 / max(tl, f32(1e-3))
    else:
        t0, t1 = f32(1.0), f32(0.0)
    u = x * np.float64(t0) + y * np.float64(t1)
    off = x * np.float64(nx) + y * np.float64(ny)
    plane = _cell(off + _SHIFT, 2.0)
    cu = _cell(u, 16.0)
    bid = _hash(cu, plane, np.int64(np.rint(nx * f32(4))) + np.int64(np.rint(ny * f32(4))), 3,
                seed + 40)
    tone = _hash(cu, plane, 0, 2, seed + 41)
    wall = palette[min(np.int64(tone * f32(len(palette))), len(palette) - 1)]
    k = f32(0.85) + f32(0.3) * bid
    grain = f32(1.0) + f32(0.12) * (_fbm(x / 0.15, y / 0.15, z / 0.15, 3, 2, seed + 42) - f32(0.5))
    r, g, b = wall[0] * k * grain, wall[1] * k * grain, wall[2] * k * grain
    spacing = window_spacing * np.float64(f32(0.8) + f32(0.4) * bid)
    v = z - ground_z
    storey = np.floor(v / floor_height)
    fv = f32(_mod1(v / floor_height))
    col = np.floor(u / spacing)
    fu = f32(_mod1(u / spacing))
    ground = storey < 1
    half_w = f32(0.375) if ground else f32(0.25)
    v0 = f32(0.05) if ground else f32(0.30)
    v1 = f32(0.85) if ground else f32(0.80)
    du = abs(fu - f32(0.5))
    win = f32(1.0) if (du < half_w and fv > v0 and fv < v1) else f32(0.0)
    frame = (f32(1.0) if (du < half_w + f32(0.03) and fv > v0 - f32(0.03)
                          and fv < v1 + f32(0.02)) else f32(0.0)) - win
    cid = _hash(np.int64(col), np.int64(storey),
                _cell(x + _SHIFT, 40.0) + _cell(y + _SHIFT, 40.0), 3, seed + 43)
    gk = f32(0.6) + f32(0.8) * cid
    cur = f32(1.0) if cid > f32(0.8) else f32(0.0)
    r = _lerp(r, f32(0.05) * gk + cur * f32(0.25), win)
    g = _lerp(g, f32(0.06) * gk + cur * f32(0.22), win)
    b = _lerp(b, f32(0.07) * gk + cur * f32(0.18), win)
    fw = min(max(frame, f32(0.0)), f32(1.0)) * f32(0.7)
    r, g, b = _lerp(r, f32(0.55), fw), _lerp(g, f32(0.55), fw), _lerp(b, f32(0.53), fw)
    ledge = f32(1.0) if (fv < f32(0.04) and not ground) else f32(0.0)
    k = f32(1.0) - f32(0.25) * ledge
    r, g, b = r * k, g * k, b * k
    plinth = (f32(1.0) if v < 0.5 else f32(0.0)) * (f32(1.0) - win)
    k = f32(1.0) - f32(0.35) * plinth
    r, g, b = r * k, g * k, b * k
    spec = f32(0.03) + f32(0.06) * win
    rough = f32(0.85) - f32(0.8) * win
    roof = _ss(0.6, 0.8, nz)
    ra = f32(0.12) + f32(0.05) * _fbm(x / 0.05, y / 0.05, 0.0, 2, 1, seed + 44)
    return (_lerp(r, ra, roof), _lerp(g, ra, roof), _lerp(b, ra, roof),
            _lerp(spec, f32(0.03), roof), _lerp(rough, f32(0.9), roof))


@njit(cache=True)
def _material(c, x, y, z, nx, ny, nz, seed, floor_height, ground_z, window_spacing, veg, pal):
    """(r, g, b, spec, rough) float32 of class c's material at one point (materials.MATERIALS)."""
    if c == _ROAD:
        r, g, b = _asphalt(x, y, seed)
        return r, g, b, f32(0.03), f32(0.8)
    if c == _MARK or c == _CROSS:
        r, g, b = _asphalt(x, y, seed)
        wear = _fbm(x / 0.4, y / 0.4, 0.0, 2, 3, seed + 11)
        cover = _ss(0.25, 0.4, wear)
        w = f32(0.70) + f32(0.08) * (_fbm(x / 0.01, y / 0.01, 0.0, 2, 1, seed + 12) - f32(0.5))
        return (_lerp(r, w * f32(1.0), cover), _lerp(g, w * f32(1.0), cover),
                _lerp(b, w * f32(0.97), cover), f32(0.04), f32(0.6))
    if c == _CURB:
        r, g, b = _concrete(x, y, z, seed, 1.0, 0.38)
        return r, g, b, f32(0.03), f32(0.85)
    if c == _SIDEWALK:
        r, g, b = _concrete(x, y, z, seed, 0.5, 0.34)
        k = f32(0.88) + f32(0.24) * _hash(_cell(x, 0.5), _cell(y, 0.5), 0, 2, seed + 31)
        return r * k, g * k, b * k, f32(0.03), f32(0.85)
    if c == _BUILDING:
        return _facade(x, y, z, nx, ny, nz, seed, floor_height, ground_z, window_spacing, pal[2])
    if c == _VEG:
        clump = _fbm(x / 0.6, y / 0.6, z / 0.6, 3, 3, seed + 51)
        leaf = _fbm(x / 0.05, y / 0.05, z / 0.05, 3, 1, seed + 52)
        w = _ss(0.3, 0.75, clump)
        shade = f32(0.55) + f32(0.45) * _ss(0.25, 0.7, clump) * (f32(0.7) + f32(0.3) * leaf)
        a, e = pal[0][veg, 0], pal[0][veg, 1]
        return (_lerp(a[0], e[0], w) * shade, _lerp(a[1], e[1], w) * shade,
                _lerp(a[2], e[2], w) * shade, f32(0.02), f32(0.7))
    if c == _TERRAIN:
        mix = _ss(0.55, 0.7, _fbm(x / 4.0, y / 4.0, 0.0, 2, 4, seed + 61))
        k = f32(0.75) + f32(0.5) * _fbm(x / 0.03, y / 0.03, 0.0, 2, 1, seed + 62)
        a, e = pal[1][veg, 0], pal[1][veg, 1]
        return (_lerp(a[0], e[0], mix) * k, _lerp(a[1], e[1], mix) * k,
                _lerp(a[2], e[2], mix) * k, f32(0.02), f32(0.9))
    if c == _VEHICLE:
        h = _hash(_cell(x, 5.0), _cell(y, 5.0), 0, 2, seed + 71)
        cars = pal[3]
        col = cars[min(np.int64(h * f32(len(cars))), len(cars) - 1)]
        return col[0], col[1], col[2], f32(0.05), f32(0.15)
    if c == _POLE or c == _LIGHT:
        g = f32(1.0) + f32(0.1) * (_fbm(x / 0.1, y / 0.1, z / 0.1, 3, 1, seed + 81) - f32(0.5))
        tone = pal[5][0] if c == _POLE else pal[5][1]
        return tone[0] * g, tone[1] * g, tone[2] * g, f32(0.2), f32(0.4)
    if c == _SIGN:
        h = _hash(_cell(x, 3.0), _cell(y, 3.0), _cell(z, 3.0), 3, seed + 91)
        signs = pal[4]
        col = signs[min(np.int64(h * f32(len(signs))), len(signs) - 1)]
        return col[0], col[1], col[2], f32(0.06), f32(0.3)
    r, g, b = _concrete(x, y, z, seed, 2.0, 0.3)          # materials.default_material
    return r, g, b, f32(0.03), f32(0.85)


@njit(cache=True, nogil=True)
def _surface(p, n, cls, valid, seed, floor_height, ground_z, window_spacing, wetness, snow_cover,
             veg, pal, out):
    for k in range(p.shape[0]):
        if not valid[k]:        # not covered: what ProceduralPrior.surface leaves there
            out[k, 0], out[k, 1], out[k, 2] = f32(0.0), f32(0.0), f32(0.0)
            out[k, 3], out[k, 4], out[k, 5] = f32(0.0), f32(1.0), f32(0.0)
            continue
        x, y, z = p[k, 0], p[k, 1], p[k, 2]
        nx, ny, nz = n[k, 0], n[k, 1], n[k, 2]
        c = cls[k]
        r, g, b, spec, rough = _material(c, x, y, z, nx, ny, nz, seed, floor_height, ground_z,
                                         window_spacing, veg, pal)
        # materials.apply_weather
        ground = False
        for gc in _GROUND:
            ground = ground or c == gc
        mirror = f32(0.0)
        if wetness > 0 and ground:
            kw = f32(1.0 - 0.45 * wetness)
            r, g, b = r * kw, g * kw, b * kw
            rough = rough * f32(1.0 - 0.75 * wetness)
            mirror = f32(0.5 * wetness)
            if c == _ROAD:
                puddle = _ss(0.62 - 0.25 * wetness, 0.66 - 0.25 * wetness,
                             f32(1.0) - _fbm(x / 2.5, y / 2.5, 0.0, 2, 3, seed + 101))
                mirror = max(mirror, puddle * f32(wetness))
                kp = f32(1.0) - f32(0.5) * puddle * f32(wetness)
                r, g, b = r * kp, g * kp, b * kp
        if snow_cover > 0:
            up = _ss(0.55, 0.85, nz)
            patch = _fbm(x / 1.5, y / 1.5, 0.0, 2, 3, seed + 111)
            traffic = 0.6 if ground and c != _SIDEWALK else 1.0
            cover = up * _ss(1.0 - snow_cover * traffic, 1.15 - snow_cover * traffic,
                             patch + f32(0.15))
            sn = f32(0.82) + f32(0.08) * _fbm(x / 0.05, y / 0.05, z / 0.05, 3, 1, seed + 112)
            r = _lerp(r, sn * f32(0.96), cover)
            g = _lerp(g, sn * f32(0.98), cover)
            b = _lerp(b, sn * f32(1.0), cover)
            rough = _lerp(rough, f32(0.8), cover)
            mirror = mirror * (f32(1.0) - cover)
        # the clamps of materials.surface_reference
        out[k, 0] = min(max(r, f32(0.0)), f32(1.0))
        out[k, 1] = min(max(g, f32(0.0)), f32(1.0))
        out[k, 2] = min(max(b, f32(0.0)), f32(1.0))
        out[k, 3] = spec
        out[k, 4] = min(max(rough, f32(0.02)), f32(1.0))
        out[k, 5] = mirror


def surface_properties(p, n, cls, s: mat.MaterialSettings, valid=None) -> torch.Tensor:
    """materials.surface_reference in one pass: (N, 6) float32 albedo, specular reflectance,
    roughness and wet mirror factor of points p (N, 3, world; taken as float64, as the
    prior's G-buffers hold them) with unit normals n (N, 3) and classes cls (N,) under
    settings s. Where ``valid`` (N,) is False, what the prior gives a pixel nothing covers:
    (0, 0, 0, 0, 1, 0), whatever p holds."""
    if s.vegetation not in VEGETATION:
        raise ValueError(f"unknown vegetation state {s.vegetation!r} (one of {', '.join(VEGETATION)})")
    pa = np.ascontiguousarray(torch.as_tensor(p).detach().cpu().numpy(), np.float64).reshape(-1, 3)
    na = np.ascontiguousarray(torch.as_tensor(n).detach().cpu().numpy(), np.float32).reshape(-1, 3)
    ca = np.ascontiguousarray(torch.as_tensor(cls).detach().cpu().numpy(), np.int64).reshape(-1)
    va = (np.ones(len(pa), np.bool_) if valid is None else
          np.ascontiguousarray(torch.as_tensor(valid).detach().cpu().numpy(), np.bool_).reshape(-1))
    if not len(na) == len(ca) == len(va) == len(pa):
        raise ValueError(f"surface_properties: {len(pa)} points, {len(na)} normals, {len(ca)} "
                         f"classes, {len(va)} valid flags")
    out = np.empty((len(pa), 6), np.float32)
    run_in_slices(_surface, len(pa), (pa, na, ca, va),
                  (int(s.seed), float(s.floor_height), float(s.ground_z), float(s.window_spacing),
                   float(s.wetness), float(s.snow_cover), VEGETATION.index(s.vegetation),
                   _palettes()), (out,))
    return torch.from_numpy(out)
