"""Where surfels are worth spending: driving cameras see the street from the lanes at 1-3 m
height, so surface near the lanes fills most pixels and roofs are never seen from the street.
The weights scale the surfel density per proxy face (mesh_to_surfels(face_weights=...))."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def lane_samples(layout, spacing: float = 2.0) -> np.ndarray:
    """Points every `spacing` metres along the drivable lane centrelines (M,2)."""
    pts = []
    for ln in layout.drivable_lanes():
        p = ln.points[:, :2]
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        t = np.arange(0.0, s[-1] + 1e-9, spacing)
        pts.append(np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], axis=1))
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def face_weights(vertices: np.ndarray, faces: np.ndarray, layout, *, falloff_m: float = 15.0,
                 floor: float = 0.05, roof_weight: float = 0.1, roof_height: float = 2.5) -> np.ndarray:
    """Per-face density weight in [floor, 1]: (d0 / (d0 + d))² of the horizontal distance d to
    the nearest lane, with d0 = falloff_m; up-facing faces above roof_height × roof_weight."""
    tri = vertices[faces]
    c = tri.mean(axis=1)
    lanes = lane_samples(layout)
    if len(lanes) == 0:
        w = np.ones(len(faces))
    else:
        d, _ = cKDTree(lanes).query(c[:, :2], k=1)
        w = (falloff_m / (falloff_m + d)) ** 2
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nz = n[:, 2] / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    roof = (nz > 0.7) & (c[:, 2] > roof_height)
    w = np.where(roof, w * roof_weight, w)
    return np.clip(w, floor, 1.0)
