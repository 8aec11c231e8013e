"""What the training views see of each surfel: which cameras have it in view, from how far,
and so how finely the views sample it (the pixel footprint, metres per pixel).

The footprint of the finest view is the sampling rate the 3D smoothing filter
(ggds/optim/antialias.py) is built from (as Mip-Splatting's: a primitive cannot hold detail finer
than the finest view that trained it); the views that see a surfel are the directions its
view-dependent colour is fitted for (ggds/colour_start/worldfit.py).

Visibility here is the frustum test only (centre in front of the camera between near and
far, projected inside the image grown by ``margin`` pixels): occlusion is ignored. That is
cheap (no rendering) and errs on the safe side for both uses: an occluded view can only make
a surfel's footprint finer than needed, and only adds a direction to its colour fit.
"""
from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np
from numba import njit, prange

from lsd3d_usd.jitopts import prange_only


@dataclass
class CameraSet:
    """Cameras as stacked float64 arrays (M cameras)."""
    R: np.ndarray        # (M,3,3) world -> camera rotation (OpenCV axes)
    t: np.ndarray        # (M,3)
    centres: np.ndarray  # (M,3)
    fx: np.ndarray       # (M,)
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    width: np.ndarray
    height: np.ndarray
    near: np.ndarray
    far: np.ndarray

    @classmethod
    def of(cls, cameras) -> "CameraSet":
        vm = np.stack([c.viewmat for c in cameras]) if cameras else np.zeros((0, 4, 4))
        a = lambda name: np.array([float(getattr(c, name)) for c in cameras], np.float64)  # noqa: E731
        return cls(vm[:, :3, :3], vm[:, :3, 3], np.stack([c.center for c in cameras])
                   if cameras else np.zeros((0, 3)), a("fx"), a("fy"), a("cx"), a("cy"),
                   a("width"), a("height"), a("near"), a("far"))

    def __len__(self) -> int:
        return len(self.fx)


def project(points: np.ndarray, cams: CameraSet, margin: float = 0.0):
    """(depth (n,M), inside (n,M) bool) of points (n,3) in every camera: camera z, and whether
    the point lies in front between near and far and projects inside the image grown by
    ``margin`` pixels on every side."""
    p = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    z = np.empty((len(p), len(cams)))
    ok = np.empty((len(p), len(cams)), np.bool_)
    _project(p, np.ascontiguousarray(cams.R), np.ascontiguousarray(cams.t), cams.fx, cams.fy,
             cams.cx, cams.cy, cams.width, cams.height, cams.near, cams.far, float(margin), z, ok)
    return z, ok


@njit(parallel=prange_only(), cache=True)
def _project(p, R, t, fx, fy, cx, cy, width, height, near, far, margin, z, ok):
    # one pass per point over the cameras (numpy's einsum and masks: ~8x slower)
    for n in prange(p.shape[0]):
        x0, x1, x2 = p[n, 0], p[n, 1], p[n, 2]
        for m in range(R.shape[0]):
            zc = R[m, 2, 0] * x0 + R[m, 2, 1] * x1 + R[m, 2, 2] * x2 + t[m, 2]
            z[n, m] = zc
            if not (zc >= near[m] and zc <= far[m]):
                ok[n, m] = False
                continue
            u = fx[m] * (R[m, 0, 0] * x0 + R[m, 0, 1] * x1 + R[m, 0, 2] * x2 + t[m, 0]) / zc + cx[m]
            v = fy[m] * (R[m, 1, 0] * x0 + R[m, 1, 1] * x1 + R[m, 1, 2] * x2 + t[m, 1]) / zc + cy[m]
            ok[n, m] = (u >= -margin and u <= width[m] + margin and v >= -margin
                        and v <= height[m] + margin)


def spheres_in_view(centres: np.ndarray, radii: np.ndarray, camera,
                    margin_px: float = 4.0) -> np.ndarray:
    """(n,) bool: the spheres (centres (n,3), radii (n,)) that reach into ``camera``'s view
    frustum (between near and far, image grown by ``margin_px`` on every side): a
    conservative test, so a surfel whose disk lies within its sphere and is left out can add
    nothing to the image."""
    c = np.ascontiguousarray(centres, np.float64).reshape(-1, 3)
    ok = np.empty(len(c), np.bool_)
    _spheres_in_view(c, np.ascontiguousarray(radii, np.float64), np.ascontiguousarray(
        camera.viewmat, np.float64), float(camera.fx), float(camera.fy), float(camera.cx),
        float(camera.cy), float(camera.width), float(camera.height), float(camera.near),
        float(camera.far), float(margin_px), ok)
    return ok


@njit(parallel=prange_only(), cache=True)
def _spheres_in_view(c, r, V, fx, fy, cx, cy, width, height, near, far, m, ok):
    # the four side planes of the grown image pass through the camera centre; their
    # inward normals in camera coordinates, normalised: (x, 0, z) for left and right,
    # (0, y, z) for top and bottom
    hl, hr = math.hypot(fx, cx + m), math.hypot(fx, width + m - cx)
    ht, hb = math.hypot(fy, cy + m), math.hypot(fy, height + m - cy)
    lx, lz = fx / hl, (cx + m) / hl                     # u >= -m
    rx, rz = -fx / hr, (width + m - cx) / hr
    ty, tz = fy / ht, (cy + m) / ht                     # v >= -m
    by, bz = -fy / hb, (height + m - cy) / hb
    for i in prange(c.shape[0]):
        x = V[0, 0] * c[i, 0] + V[0, 1] * c[i, 1] + V[0, 2] * c[i, 2] + V[0, 3]
        y = V[1, 0] * c[i, 0] + V[1, 1] * c[i, 1] + V[1, 2] * c[i, 2] + V[1, 3]
        z = V[2, 0] * c[i, 0] + V[2, 1] * c[i, 1] + V[2, 2] * c[i, 2] + V[2, 3]
        ri = r[i]
        ok[i] = (z >= near - ri and z <= far + ri
                 and lx * x + lz * z >= -ri and rx * x + rz * z >= -ri
                 and ty * y + tz * z >= -ri and by * y + bz * z >= -ri)


def footprint(points: np.ndarray, cameras, *, margin: float = 0.0,
              chunk: int = 65536) -> np.ndarray:
    """(n,) metres per pixel of the finest camera that has each point in view:
    min over those cameras of depth / focal length (inf where no camera sees the point)."""
    cams = cameras if isinstance(cameras, CameraSet) else CameraSet.of(list(cameras))
    p = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.full(len(p), np.inf)
    if len(cams) == 0:
        return out
    f = np.minimum(cams.fx, cams.fy)   # the larger pixel footprint of the two axes
    for a in range(0, len(p), chunk):
        z, ok = project(p[a:a + chunk], cams, margin)
        out[a:a + chunk] = np.where(ok, z / f, np.inf).min(axis=1)
    return out


def pick_views(points: np.ndarray, cameras, k: int, rng: np.random.Generator, *,
               margin: float = 0.0, chunk: int = 32768) -> np.ndarray:
    """(n,k) indices of cameras that have each point in view, drawn without replacement with
    probability proportional to the point's pixel density in them, (f/z)² (how many pixels a
    patch there covers: what the training loss weighs it by); when fewer than k see it, the
    ones that do repeat; -1 where none does."""
    cams = cameras if isinstance(cameras, CameraSet) else CameraSet.of(list(cameras))
    p = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.full((len(p), k), -1, np.int64)
    if len(cams) == 0 or k <= 0:
        return out
    f2 = cams.fx * cams.fy
    for a in range(0, len(p), chunk):
        z, ok = project(p[a:a + chunk], cams, margin)
        w = np.where(ok, f2 / np.where(ok, z, 1.0) ** 2, 0.0)
        # Weighted sampling without replacement: the k largest of u^(1/w) (Efraimidis-Spirakis),
        # in log form: log(u)/w, -inf where w = 0.
        with np.errstate(divide="ignore"):
            key = np.log(rng.random(w.shape)) / np.where(w > 0, w, 1.0)
        key[w <= 0] = -np.inf
        kk = min(k, len(cams))
        top = np.argpartition(-key, kk - 1, axis=1)[:, :kk]
        top_key = np.take_along_axis(key, top, 1)
        order = np.argsort(-top_key, axis=1)
        top, top_key = np.take_along_axis(top, order, 1), np.take_along_axis(top_key, order, 1)
        valid = np.isfinite(top_key)
        nvalid = valid.sum(1)
        # Fill the slots beyond the visible count by cycling through the visible ones.
        slot = np.arange(k)[None, :] % np.maximum(nvalid, 1)[:, None]
        full = np.take_along_axis(top, np.minimum(slot, kk - 1), 1)
        full[nvalid == 0] = -1
        out[a:a + chunk] = full
    return out


def views_seeing(views: list, positions: np.ndarray, sample: int = 20_000) -> list:
    """The views (conditioning.view_sampling.View) that have at least one of ``positions`` (N,3) in view
    (``project``'s frustum test); up to ``sample`` evenly spaced points are tested. A region's
    views that see none of its surfels would give them no gradient: a step there, its
    G-buffer and its prior target are wasted (a region of a few hundred surfels on a building
    overhanging a chunk border spent 24 of its 40 s on 128 such targets)."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    if len(p) > sample:
        p = p[np.linspace(0, len(p) - 1, sample).astype(np.int64)]
    if not views or not len(p):
        return []
    _, ok = project(p, CameraSet.of([v.camera for v in views]))
    return [v for v, seen in zip(views, ok.any(axis=0)) if seen]
