"""Triangle-mesh G-buffers: per-pixel camera depth, world normal, semantic id,
world position and face index (GGDS conditioning and geometry losses).

CPU z-buffer rasteriser in numba, float64 throughout:
1. setup (parallel over faces): vertices in camera space (camera-relative, so
   scenes far from the origin keep their precision), clip each triangle against
   the near plane (z >= near; a clipped triangle becomes a quad = two
   triangles), project, and keep screen positions with 1/z (affine in screen
   space for a planar triangle, so depth is exactly perspective-correct);
2. binning: sub-triangles into horizontal bands of rows by bounding box;
3. raster (parallel over bands): pixel centres (i + 0.5, j + 0.5) inside the
   triangle (edge functions, edges inclusive) pass a z-test (strict <, faces in
   index order, so ties keep the lowest face index: deterministic).
Depth beyond the far plane is dropped. Edge-on triangles (zero screen area)
cover nothing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from lsd3d_usd.errors import InputError
from lsd3d_usd.jitopts import prange_only
from lsd3d_usd.render.camera import Camera

BAND_ROWS = 8


@dataclass
class GBuffer:
    depth: np.ndarray        # (H,W) float32 camera z (along the optical axis); inf where empty
    normal: np.ndarray       # (H,W,3) float32 world-space face normal (t_u x t_v); 0 where empty
    semantic: np.ndarray     # (H,W) int32 class id; -1 where empty or unlabelled
    position: np.ndarray     # (H,W,3) float64 world position; nan where empty
    face_index: np.ndarray   # (H,W) int32 index of the visible face; -1 where empty

    @property
    def mask(self) -> np.ndarray:
        return self.face_index >= 0


@njit(cache=True, inline="always")
def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@njit(parallel=prange_only(), cache=True)
def _setup(vc, faces, fx, fy, cx, cy, near, W, H, tri, bbox):
    """tri[f, s] = (u0, v0, iz0, u1, v1, iz1, u2, v2, iz2) for sub-triangle s in {0, 1};
    bbox[f, s] = (x0, x1, y0, y1) inclusive pixel ranges, x0 > x1 when empty."""
    F = faces.shape[0]
    for f in prange(F):
        bbox[f, 0, 0] = 1
        bbox[f, 0, 1] = 0
        bbox[f, 1, 0] = 1
        bbox[f, 1, 1] = 0
        # Sutherland-Hodgman against z >= near: at most 4 vertices.
        px = np.empty(4)
        py = np.empty(4)
        pz = np.empty(4)
        n = 0
        for k in range(3):
            a = faces[f, k]
            b = faces[f, (k + 1) % 3]
            ax, ay, az = vc[a, 0], vc[a, 1], vc[a, 2]
            bx, by, bz = vc[b, 0], vc[b, 1], vc[b, 2]
            a_in = az >= near
            b_in = bz >= near
            if a_in:
                px[n], py[n], pz[n] = ax, ay, az
                n += 1
            if a_in != b_in:
                t = (near - az) / (bz - az)
                px[n], py[n], pz[n] = ax + t * (bx - ax), ay + t * (by - ay), near
                n += 1
        if n < 3:
            continue
        us = np.empty(4)
        vs = np.empty(4)
        izs = np.empty(4)
        for k in range(n):
            iz = 1.0 / pz[k]
            us[k] = fx * px[k] * iz + cx
            vs[k] = fy * py[k] * iz + cy
            izs[k] = iz
        for s in range(n - 2):  # fan: (0,1,2), (0,2,3)
            i0, i1, i2 = 0, s + 1, s + 2
            area = _edge(us[i0], vs[i0], us[i1], vs[i1], us[i2], vs[i2])
            if not (area != 0.0) or not np.isfinite(area):
                continue
            tri[f, s, 0], tri[f, s, 1], tri[f, s, 2] = us[i0], vs[i0], izs[i0]
            tri[f, s, 3], tri[f, s, 4], tri[f, s, 5] = us[i1], vs[i1], izs[i1]
            tri[f, s, 6], tri[f, s, 7], tri[f, s, 8] = us[i2], vs[i2], izs[i2]
            umin = min(us[i0], min(us[i1], us[i2]))
            umax = max(us[i0], max(us[i1], us[i2]))
            vmin = min(vs[i0], min(vs[i1], vs[i2]))
            vmax = max(vs[i0], max(vs[i1], vs[i2]))
            # pixel i is a candidate if its centre i + 0.5 lies in [min, max]
            x0 = max(np.ceil(umin - 0.5), 0.0)
            x1 = min(np.floor(umax - 0.5), W - 1.0)
            y0 = max(np.ceil(vmin - 0.5), 0.0)
            y1 = min(np.floor(vmax - 0.5), H - 1.0)
            if x0 > x1 or y0 > y1:
                continue
            bbox[f, s, 0], bbox[f, s, 1] = int(x0), int(x1)
            bbox[f, s, 2], bbox[f, s, 3] = int(y0), int(y1)


@njit(cache=True)
def _bin(bbox, n_bands, band_rows):
    F = bbox.shape[0]
    counts = np.zeros(n_bands + 1, np.int64)
    for f in range(F):
        for s in range(2):
            if bbox[f, s, 0] <= bbox[f, s, 1]:
                for b in range(bbox[f, s, 2] // band_rows, bbox[f, s, 3] // band_rows + 1):
                    counts[b + 1] += 1
    offs = np.cumsum(counts)
    items = np.empty(offs[-1], np.int64)
    fill = offs[:-1].copy()
    for f in range(F):
        for s in range(2):
            if bbox[f, s, 0] <= bbox[f, s, 1]:
                for b in range(bbox[f, s, 2] // band_rows, bbox[f, s, 3] // band_rows + 1):
                    items[fill[b]] = 2 * f + s
                    fill[b] += 1
    return offs, items


@njit(parallel=prange_only(), cache=True)
def _raster(tri, bbox, offs, items, far, W, H, band_rows, zbuf, fid):
    n_bands = offs.shape[0] - 1
    for b in prange(n_bands):
        r0 = b * band_rows
        r1 = min(r0 + band_rows, H) - 1
        for it in range(offs[b], offs[b + 1]):
            code = items[it]
            f = code // 2
            s = code % 2
            u0, v0, iz0 = tri[f, s, 0], tri[f, s, 1], tri[f, s, 2]
            u1, v1, iz1 = tri[f, s, 3], tri[f, s, 4], tri[f, s, 5]
            u2, v2, iz2 = tri[f, s, 6], tri[f, s, 7], tri[f, s, 8]
            area = _edge(u0, v0, u1, v1, u2, v2)
            inv_area = 1.0 / area
            y0 = max(bbox[f, s, 2], r0)
            y1 = min(bbox[f, s, 3], r1)
            for j in range(y0, y1 + 1):
                py = j + 0.5
                for i in range(bbox[f, s, 0], bbox[f, s, 1] + 1):
                    px = i + 0.5
                    b0 = _edge(u1, v1, u2, v2, px, py) * inv_area
                    b1 = _edge(u2, v2, u0, v0, px, py) * inv_area
                    b2 = _edge(u0, v0, u1, v1, px, py) * inv_area
                    if b0 < 0.0 or b1 < 0.0 or b2 < 0.0:
                        continue
                    z = 1.0 / (b0 * iz0 + b1 * iz1 + b2 * iz2)
                    if z < zbuf[j, i] and z <= far:
                        zbuf[j, i] = z
                        fid[j, i] = f


def render_depth(vertices, faces, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(zbuf (H,W) float64 camera z, inf where empty; face (H,W) int64, -1 where empty): the
    rasteriser alone, without render_gbuffer's per-pixel normals and positions (a 2048²
    shadow map needs only the depth, and the rest would be ~400 MB of temporaries)."""
    V = np.asarray(vertices, dtype=np.float64)
    Fc = np.ascontiguousarray(np.asarray(faces), dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise InputError(f"gbuffer: vertices must have shape (V, 3), got {V.shape}")
    if Fc.ndim != 2 or Fc.shape[1] != 3:
        raise InputError(f"gbuffer: faces must have shape (F, 3), got {Fc.shape}")
    if Fc.size and (Fc.min() < 0 or Fc.max() >= len(V)):
        raise InputError(f"gbuffer: face indices out of range [0, {len(V)})")
    if not np.all(np.isfinite(V)):
        raise InputError("gbuffer: vertices contain NaN or Inf")
    W, H = camera.width, camera.height
    vm = camera.viewmat
    # Camera-relative: subtract the camera centre before rotating (precision far from the origin).
    vc = np.ascontiguousarray((V - camera.center) @ vm[:3, :3].T)
    nF = len(Fc)
    tri = np.empty((nF, 2, 9))
    bbox = np.empty((nF, 2, 4), np.int64)
    zbuf = np.full((H, W), np.inf)
    fid = np.full((H, W), -1, np.int64)
    if nF:
        _setup(vc, Fc, camera.fx, camera.fy, camera.cx, camera.cy, camera.near, W, H, tri, bbox)
        n_bands = (H + BAND_ROWS - 1) // BAND_ROWS
        offs, items = _bin(bbox, n_bands, BAND_ROWS)
        _raster(tri, bbox, offs, items, camera.far, W, H, BAND_ROWS, zbuf, fid)
    return zbuf, fid


def render_gbuffer(vertices, faces, camera: Camera, face_semantic_ids=None) -> GBuffer:
    """Rasterise a triangle mesh (vertices (V,3) world, faces (F,3) int) for ``camera``."""
    V = np.asarray(vertices, dtype=np.float64)
    Fc = np.ascontiguousarray(np.asarray(faces), dtype=np.int64)
    zbuf, fid = render_depth(V, Fc, camera)
    W, H = camera.width, camera.height
    nF = len(Fc)
    hit = fid >= 0
    f = fid[hit]
    normal = np.zeros((H, W, 3), np.float32)
    normal[hit] = face_normals(V, Fc[f])
    sem = np.full((H, W), -1, np.int32)
    if face_semantic_ids is not None:
        ids = np.asarray(face_semantic_ids)
        if ids.shape != (nF,):
            raise InputError(f"gbuffer: face_semantic_ids must have shape ({nF},), got {ids.shape}")
        sem[hit] = ids[f]
    return GBuffer(zbuf.astype(np.float32), normal, sem, pixel_positions(camera, zbuf, fid),
                   fid.astype(np.int32))


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,3) float32 unit normals (p1 - p0) x (p2 - p0) of faces (F,3) (0 for degenerate ones)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    n = np.cross(p1 - p0, p2 - p0)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n.astype(np.float32)


def pixel_positions(camera: Camera, zbuf: np.ndarray, fid: np.ndarray) -> np.ndarray:
    """(H,W,3) float64 world positions of render_depth's pixels (nan where empty): the pixel
    ray at the depth, exact for the planar face."""
    hit = fid >= 0
    jj, ii = np.nonzero(hit)
    z = zbuf[hit]
    d_cam = np.stack([(ii + 0.5 - camera.cx) / camera.fx * z, (jj + 0.5 - camera.cy) / camera.fy * z, z], 1)
    pos = np.full(zbuf.shape + (3,), np.nan)
    pos[hit] = d_cam @ camera.pose[:3, :3].T + camera.center
    return pos
