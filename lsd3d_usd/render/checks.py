"""Input validation of `rasterize`, one place for every backend: shapes, finite values,
value ranges, settings. Bad input is one InputError line naming the array and the index.

Besides NaN/Inf and negative scales, two finite inputs are refused because they break the
gradients rather than the image:
  * a quaternion shorter than QUAT_MIN_NORM: normalising q/|q| has a gradient of size 1/|q|,
    which overflows float32 (a 1e-45 quaternion gave infinite gradients);
  * an SH coefficient larger in magnitude than SH_MAX: the colour and the SH direction
    gradient multiply the coefficients, and 3e38 overflowed to Inf and then NaN.
Refused rather than clamped: such values come from a diverging optimiser or a broken file,
and clamping would hide that while changing the picture. The bounds sit many orders of
magnitude beyond any real surfel (unit quaternions; colours are O(1), HDR O(10^2)).

CPU float32 surfel arrays are scanned with numba in one parallel pass over all five (a few
ms at 1 M surfels, where torch's isfinite + any took a third of a second), other CPU float32
or float64 arrays with a serial numba scan each, tensors on other devices or of other dtypes
with torch ops. All report the same first bad element.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from lsd3d_usd.errors import InputError
from lsd3d_usd.jitopts import prange_only
from lsd3d_usd.render.kernels import LANES
from lsd3d_usd.render.raster_types import RasterInputs, RasterSettings
from lsd3d_usd.render.sh import sh_degree_of

QUAT_MIN_NORM = 1e-20
SH_MAX = 1e6


@njit(cache=True)
def first_bad(flat, lo, hi):
    """Smallest flat index of a value that is non-finite or outside [lo, hi] in a 1-D array,
    -1 if none. A branch-free (vectorised) scan in blocks, then a search in the first bad
    block. Serial on purpose: a parallel region per input array cost more in thread wake-ups
    on a loaded machine than the scan itself."""
    n = flat.shape[0]
    for start in range(0, n, 65536):
        stop = min(n, start + 65536)
        bad = False
        for q in range(start, stop):  # x - x is NaN iff x is NaN or Inf
            v = flat[q]
            bad |= (v - v != 0) | (v < lo) | (v > hi)
        if bad:
            for q in range(start, stop):
                v = flat[q]
                if not np.isfinite(v) or v < lo or v > hi:
                    return q
    return -1


_SCAN = 65536


@njit(parallel=prange_only(), cache=True)
def first_bad_array(arrs, lo, hi):
    """Index into arrs (a tuple of 1-D float32 arrays) of the first one holding a value that is
    non-finite or outside [lo[i], hi[i]], -1 if none: one parallel scan over blocks of all of
    them (one thread wake-up for the whole input). first_bad then finds the index."""
    na = len(arrs)
    start = np.zeros(na + 1, np.int64)
    for i in range(na):
        start[i + 1] = start[i] + (arrs[i].shape[0] + _SCAN - 1) // _SCAN
    flags = np.zeros(start[na], np.bool_)
    for b in prange(start[na]):
        i = 0
        while b >= start[i + 1]:
            i += 1
        a = arrs[i]
        first = (b - start[i]) * _SCAN
        last = min(a.shape[0], first + _SCAN)
        lo_i = lo[i]
        hi_i = hi[i]
        bad = False
        for q in range(first, last):
            v = a[q]
            bad |= (v - v != 0) | (v < lo_i) | (v > hi_i)
        flags[b] = bad
    for i in range(na):
        for b in range(start[i], start[i + 1]):
            if flags[b]:
                return i
    return -1


@njit(cache=True)
def first_short_quat(q, min_norm):
    """Smallest row index of q (N, 4) whose norm (in float64) is below min_norm, -1 if none."""
    m2 = min_norm * min_norm
    n = q.shape[0]
    for start in range(0, n, 16384):  # a vectorised count per block, then the search
        stop = min(n, start + 16384)
        short = 0
        for i in range(start, stop):
            v0, v1 = np.float64(q[i, 0]), np.float64(q[i, 1])
            v2, v3 = np.float64(q[i, 2]), np.float64(q[i, 3])
            short += (v0 * v0 + v1 * v1 + v2 * v2 + v3 * v3) < m2
        if short:
            for i in range(start, stop):
                s = 0.0
                for c in range(4):
                    v = np.float64(q[i, c])
                    s += v * v
                if s < m2:
                    return i
    return -1


# ------------------------------------------------------------------------------ helpers
def _as_tensor(x, name):
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        try:
            x = torch.as_tensor(x)
        except Exception as e:  # noqa: BLE001 - re-raised as a user error
            raise InputError(f"rasterize: {name} is not an array ({e})") from None
    if not x.is_floating_point():
        x = x.to(torch.float32)
    return x


def _check_shape(x, name, shape):
    """shape: tuple with None for free dims."""
    if x.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"rasterize: {name} has shape {tuple(x.shape)}, expected {want}")


def _bounds(name):
    """(lo, hi) allowed for an array's values (besides being finite)."""
    if name == "scales":
        return 0.0, np.inf
    if name == "sh":
        return -SH_MAX, SH_MAX
    return -np.inf, np.inf


def first_bad_flat(x, lo, hi) -> int:
    """Flat index of the first non-finite / out-of-range element of tensor x, -1 if none."""
    if x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64):
        flat = np.ascontiguousarray(x.detach().reshape(-1).numpy())
        return int(first_bad(flat, flat.dtype.type(lo), flat.dtype.type(hi))) if flat.size else -1
    v = x.detach().reshape(-1)
    bad = ~torch.isfinite(v) | (v < lo) | (v > hi)
    hit = torch.nonzero(bad)
    return int(hit[0, 0]) if hit.numel() else -1


def _raise_at(x, name, q, lo, hi):
    where = np.unravel_index(q, tuple(x.shape))
    index = tuple(int(i) for i in where) if name in ("viewmat", "K", "background") else int(where[0])
    v = float(x.detach().reshape(-1)[q])
    if not np.isfinite(v):
        raise InputError(f"rasterize: {name} has a non-finite value (NaN or Inf) at index {index}")
    if v < 0 and lo == 0:
        raise InputError(f"rasterize: {name} has a negative value at index {index}")
    raise InputError(f"rasterize: {name} has a value of magnitude {abs(v):.3g} (more than "
                     f"{max(abs(lo), abs(hi)):.3g}) at index {index}")


def _check_values(x, name, shape):
    _check_shape(x, name, shape)
    lo, hi = _bounds(name)
    q = first_bad_flat(x, lo, hi)
    if q >= 0:
        _raise_at(x, name, q, lo, hi)


def _check_quats(quats):
    if quats.device.type == "cpu":
        i = int(first_short_quat(np.ascontiguousarray(quats.detach().numpy()), QUAT_MIN_NORM))
    else:
        short = torch.nonzero(quats.detach().double().norm(dim=1) < QUAT_MIN_NORM)
        i = int(short[0, 0]) if short.numel() else -1
    if i < 0:
        return
    norm = float(quats[i].detach().double().norm())
    if norm == 0.0:
        raise InputError(f"rasterize: quats has a zero quaternion at index {i}")
    raise InputError(f"rasterize: quats has a near-zero quaternion (norm {norm:.3g}, below "
                     f"{QUAT_MIN_NORM:g}) at index {i}")


def check_settings(s: RasterSettings) -> None:
    if not isinstance(s, RasterSettings):
        raise InputError(f"rasterize: settings must be a RasterSettings, not {type(s).__name__}")
    if not (0 < s.near < s.far):
        raise InputError(f"rasterize: need 0 < near < far, got near={s.near}, far={s.far}")
    if not isinstance(s.tile, (int, np.integer)) or s.tile <= 0 or s.tile % LANES:
        raise InputError(f"rasterize: tile must be a positive multiple of {LANES}, not {s.tile}")
    if not (0.0 <= s.alpha_min < s.alpha_max < 1.0):
        raise InputError(f"rasterize: need 0 <= alpha_min < alpha_max < 1, got alpha_min="
                         f"{s.alpha_min}, alpha_max={s.alpha_max}")
    if not (0.0 <= s.t_min < 1.0):
        raise InputError(f"rasterize: t_min must be in [0, 1), not {s.t_min}")
    if s.bound_sigma is not None and not s.bound_sigma > 0:
        raise InputError(f"rasterize: bound_sigma must be None (exact bounds) or > 0, not {s.bound_sigma}")
    if s.normal_space not in ("camera", "world"):
        raise InputError(f"rasterize: normal_space must be 'camera' or 'world', not {s.normal_space!r}")


# ------------------------------------------------------------------------------ the check
def check_inputs(means, quats, scales, opacities, sh, viewmat, K, width, height,
                 settings: RasterSettings, background=None, semantic_ids=None,
                 values_checked: bool = False):
    """Validate everything `rasterize` was given. Returns (RasterInputs, background tensor or
    None, semantic ids as an int64 tensor or None). ``values_checked``: the five surfel arrays'
    values were validated when they were read (a SurfelField.checked); shapes, devices,
    camera and settings are checked still, the per-value scans of the surfels skipped."""
    check_settings(settings)
    means = _as_tensor(means, "means")
    quats = _as_tensor(quats, "quats")
    scales = _as_tensor(scales, "scales")
    opacities = _as_tensor(opacities, "opacities")
    sh = _as_tensor(sh, "sh")
    _check_shape(means, "means", (None, 3))
    n = means.shape[0]
    checks = ((means, "means", (n, 3)), (quats, "quats", (n, 4)), (scales, "scales", (n, 2)),
              (opacities, "opacities", (n,)), (sh, "sh", (n, None, 3)))
    for x, name, shape in checks:
        _check_shape(x, name, shape)
    devices = {x.device for x, *_ in checks}
    if len(devices) > 1:
        raise InputError("rasterize: means, quats, scales, opacities and sh must be on one device, "
                         f"got {', '.join(sorted(str(d) for d in devices))}")
    if values_checked:
        pass            # validated when read (SurfelField.checked): no scan per frame
    elif means.device.type == "cpu" and all(x.dtype == torch.float32 for x, *_ in checks):
        # the usual case: one parallel scan of all five arrays
        flats = tuple(np.ascontiguousarray(x.detach().reshape(-1).numpy()) for x, *_ in checks)
        lo = np.array([_bounds(c[1])[0] for c in checks], np.float32)
        hi = np.array([_bounds(c[1])[1] for c in checks], np.float32)
        bad = int(first_bad_array(flats, lo, hi))
        if bad >= 0:
            _check_values(*checks[bad])  # names the array and the index
    else:
        for c in checks:
            _check_values(*c)
    viewmat = _as_tensor(viewmat, "viewmat")
    K = _as_tensor(K, "K")
    _check_values(viewmat, "viewmat", (4, 4))
    _check_values(K, "K", (3, 3))
    viewmat = viewmat.detach().to("cpu", torch.float64)
    K = K.detach().to("cpu", torch.float64)
    k2 = K.numpy()[2]  # numpy: three torch scalar comparisons cost ~10 us per render
    if k2[0] != 0 or k2[1] != 0 or k2[2] != 1.0:
        raise InputError("rasterize: K must be a pinhole intrinsics matrix with last row (0, 0, 1)")
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise InputError(f"rasterize: bad image size {width}x{height}")
    if not values_checked:
        _check_quats(quats)
    try:
        full_deg = sh_degree_of(sh.shape[1])
    except ValueError as e:
        raise InputError(f"rasterize: sh: {e}") from None
    deg = full_deg if settings.sh_degree is None else int(settings.sh_degree)
    if not 0 <= deg <= full_deg:
        raise InputError(f"rasterize: sh_degree {deg} needs more than the {sh.shape[1]} "
                         "coefficients given")
    if background is not None:
        background = _as_tensor(background, "background")
        _check_values(background, "background", (3,) if background.dim() == 1 else (height, width, 3))
    sem = None
    if semantic_ids is not None:
        sem = torch.as_tensor(semantic_ids)
        if sem.shape != (n,):
            raise InputError(f"rasterize: semantic_ids has shape {tuple(sem.shape)}, expected ({n},)")
        sem = sem.long()
    inputs = RasterInputs(means, quats, scales, opacities, sh, viewmat, K, width, height, deg,
                          want_argmax=sem is not None)
    return inputs, background, sem
