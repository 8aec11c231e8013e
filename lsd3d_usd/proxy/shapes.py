"""Small closed primitives (numpy only): boxes, cylinders, spheres, profile prisms.

Each returns (vertices (N, 3) float64, faces (M, 3) int32), watertight with
outward normals, in a local frame; callers place them with transform_points.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np


def ngon_prism(xy: np.ndarray, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """Prism over a convex CCW polygon (K, 2): fan-triangulated caps and quad walls."""
    xy = np.asarray(xy, dtype=np.float64)
    k = len(xy)
    v = np.vstack([np.column_stack([xy, np.full(k, z0)]), np.column_stack([xy, np.full(k, z1)])])
    i = np.arange(k)
    j = (i + 1) % k
    fan = np.arange(1, k - 1)
    bottom = np.stack([np.zeros(k - 2, int), fan + 1, fan], axis=1)       # faces down
    top = np.stack([np.full(k - 2, k), fan + k, fan + 1 + k], axis=1)     # faces up
    walls = np.vstack([np.stack([i, j, j + k], 1), np.stack([i, j + k, i + k], 1)])
    return v, np.vstack([bottom, top, walls]).astype(np.int32)


def box(sx: float, sy: float, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box centred on the local origin in XY."""
    hx, hy = sx / 2, sy / 2
    return ngon_prism(np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]), z0, z1)


def cylinder(radius: float, z0: float, z1: float, segments: int = 8
             ) -> tuple[np.ndarray, np.ndarray]:
    a = np.arange(segments) * (2 * np.pi / segments)
    return ngon_prism(radius * np.column_stack([np.cos(a), np.sin(a)]), z0, z1)


@lru_cache(maxsize=4)
def _unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        # split every edge once (shared midpoints keep the mesh closed)
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        ue, inv = np.unique(e, axis=0, return_inverse=True)
        mid = v[ue].mean(1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)          # midpoints of edges 01, 12, 20
        v = np.vstack([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        f = np.vstack([np.stack([a, m[:, 0], m[:, 2]], 1), np.stack([b, m[:, 1], m[:, 0]], 1),
                       np.stack([c, m[:, 2], m[:, 1]], 1), np.stack([m[:, 0], m[:, 1], m[:, 2]], 1)])
    v.setflags(write=False)
    f = f.astype(np.int32)
    f.setflags(write=False)
    return v, f


def ellipsoid(rx: float, ry: float, rz: float, subdivisions: int = 1
              ) -> tuple[np.ndarray, np.ndarray]:
    v, f = _unit_icosphere(subdivisions)
    return v * np.array([rx, ry, rz]), f.copy()


def profile_prism(profile_xz: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """A side profile (K, 2) in the (x, z) plane (convex, any winding) extruded across y.

    Used for coarse vehicles: one closed solid per vehicle, no booleans.
    """
    p = np.asarray(profile_xz, dtype=np.float64)
    area2 = np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(np.roll(p[:, 0], -1), p[:, 1])
    if area2 < 0:
        p = p[::-1]
    v, f = ngon_prism(p, -width / 2, width / 2)     # built in (x, z, y) ...
    v = v[:, [0, 2, 1]]                             # ... swapped to (x, y, z): a mirror,
    return v, f[:, ::-1].copy()                     # so the winding flips back outward
