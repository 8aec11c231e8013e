"""Per-view conditioning for GGDS: the proxy G-buffer as the prior wants it, with a sun
shadow term from a shadow map of the proxy (rendered by the mesh G-buffer rasteriser from a
distant camera along the sun direction, i.e. a near-orthographic light view)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Hashable

import numpy as np
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.prior_base import GBuffer
from lsd3d_usd.render.camera import Camera, look_at, pixel_directions
from lsd3d_usd.render.gbuffer import render_depth, render_gbuffer


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


def view_gbuffer(camera: Camera, vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray | None,
                 shadow: ShadowMap | None = None) -> GBuffer:
    return pack_view_gbuffer(camera, vertices, faces, shadow).unpack(
        face_normals(vertices, faces), face_ids)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,3) float32 unit normals (p1 - p0) x (p2 - p0), as render_gbuffer writes them."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    n = np.cross(p1 - p0, p2 - p0)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n.astype(np.float32)


@dataclass
class PackedGBuffer:
    """A view's G-buffer as GGDS keeps it for every training view between visits: only what
    cannot be derived again cheaply and exactly (depth, face index, world position, sun
    visibility: 21 B/px against the unpacked 64). Normals and classes come back from the face
    index, view directions from the camera, in about 7 ms at 480x270."""
    camera: Camera
    depth: torch.Tensor            # (H,W) float32, inf where empty
    face: torch.Tensor             # (H,W) int32 proxy face, -1 where empty
    world_pos: torch.Tensor        # (H,W,3) float32, 0 where empty
    sun: torch.Tensor | None       # (H,W) bool lit by the sun (1 where empty), None: all lit

    def unpack(self, normals: np.ndarray, face_ids: np.ndarray | None,
               key: Hashable | None = None) -> GBuffer:
        """normals: face_normals() of the proxy; face_ids: (F,) class ids or None."""
        hit = self.face >= 0
        f = torch.where(hit, self.face, torch.zeros_like(self.face)).long()
        table = torch.from_numpy(np.asarray(normals, np.float32).reshape(-1, 3))
        if not len(table):          # no proxy faces: nothing is hit
            table = torch.zeros(1, 3)
        normal = torch.where(hit[..., None], table[f], 0.0)
        if face_ids is None:
            sem = torch.full(self.face.shape, -1, dtype=torch.int64)
        else:
            if np.shape(face_ids) != (len(normals),):
                raise InputError(f"gbuffer: face_ids must have shape ({len(normals)},), got "
                                 f"{np.shape(face_ids)}")
            ids = torch.from_numpy(np.asarray(face_ids).astype(np.int64))
            sem = torch.where(hit, ids[f], -1) if len(ids) else torch.full(self.face.shape, -1)
        return GBuffer(
            depth=self.depth, normal=normal, semantic=sem, world_pos=self.world_pos,
            view_dirs=torch.from_numpy(pixel_directions(self.camera).astype(np.float32)),
            camera_position=torch.from_numpy(self.camera.center.astype(np.float32)),
            sun_visibility=None if self.sun is None else self.sun.float(), key=key)


def pack_view_gbuffer(camera: Camera, vertices: np.ndarray, faces: np.ndarray,
                      shadow: ShadowMap | None = None) -> PackedGBuffer:
    gb = render_gbuffer(vertices, faces, camera)
    pos = gb.position
    sun = None
    if shadow is not None:
        vis = shadow.visibility(np.where(gb.mask[..., None], pos, np.nan))
        sun = torch.from_numpy(np.where(gb.mask, vis, 1.0) > 0.5)
    return PackedGBuffer(
        camera, depth=torch.from_numpy(gb.depth.astype(np.float32)),
        face=torch.from_numpy(gb.face_index.astype(np.int32)),
        world_pos=torch.from_numpy(np.nan_to_num(pos, nan=0.0).astype(np.float32)), sun=sun)
