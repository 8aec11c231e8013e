"""The sun's shadow map of the proxy: its depth rendered by the mesh G-buffer rasteriser from a
distant camera along the sun direction (a near-orthographic light view), and the visibility
of world points it gives."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.render.gbuffer import render_depth


@dataclass
class ShadowMap:
    camera: Camera
    depth: np.ndarray     # (S,S) camera z of the nearest proxy surface seen from the sun
    bias: float           # metres

    def visibility(self, points: np.ndarray) -> np.ndarray:
        """1 where `points` (..., 3) see the sun, 0 where the proxy occludes it."""
        shape = points.shape[:-1]
        p = points.reshape(-1, 3)
        ok = np.isfinite(p).all(axis=1)
        uv, z = self.camera.project(np.where(ok[:, None], p, 0.0))
        i = np.floor(uv[:, 0]).astype(np.int64)
        j = np.floor(uv[:, 1]).astype(np.int64)
        inside = ok & (i >= 0) & (j >= 0) & (i < self.depth.shape[1]) & (j < self.depth.shape[0])
        vis = np.ones(len(p), np.float32)
        occ = self.depth[np.clip(j, 0, self.depth.shape[0] - 1), np.clip(i, 0, self.depth.shape[1] - 1)]
        vis[inside & (occ < z - self.bias)] = 0.0
        return vis.reshape(shape)


def shadow_map(vertices: np.ndarray, faces: np.ndarray, sun_dir: np.ndarray,
               resolution: int = 2048) -> ShadowMap | None:
    """Shadow map covering the proxy's bounds; None when the sun is below the horizon."""
    sun = np.asarray(sun_dir, np.float64)
    sun = sun / np.linalg.norm(sun)
    if sun[2] <= 0.02 or len(faces) == 0:
        return None
    lo, hi = vertices.min(0), vertices.max(0)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) + 1.0
    dist = 50.0 * radius  # far enough that the perspective is nearly orthographic
    eye = centre + sun * dist
    up = (0.0, 1.0, 0.0) if abs(sun[2]) > 0.99 else (0.0, 0.0, 1.0)
    fov = 2.0 * np.degrees(np.arctan(radius / (dist - radius)))
    cam = Camera.from_fov(resolution, resolution, fov, pose=look_at(eye, centre, up),
                          near=dist - 2 * radius, far=dist + 2 * radius)
    depth, _ = render_depth(vertices, faces, cam)
    texel = 2.0 * radius / resolution
    # Bias grows with the slope of a texel seen from the sun; 2 texels covers up to ~60 deg.
    return ShadowMap(cam, depth.astype(np.float32), bias=2.0 * texel + 0.02)
