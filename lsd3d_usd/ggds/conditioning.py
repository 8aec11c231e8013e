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
from lsd3d_usd.render.gbuffer import face_normals, pixel_positions, render_depth


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
                 shadow: ShadowMap | None = None, fine: bool = True) -> GBuffer:
    """The proxy G-buffer of ``camera``; with ``fine``, GBuffer.fine makes it again at k× the
    resolution."""
    return table_gbuffer(camera, vertices, faces, FaceTable.of(vertices, faces, face_ids),
                         shadow, fine)


def table_gbuffer(camera: Camera, vertices: np.ndarray, faces: np.ndarray, table: "FaceTable",
                  shadow: ShadowMap | None = None, fine: bool = True) -> GBuffer:
    """view_gbuffer with the proxy's FaceTable built once by the caller."""
    return pack_view_gbuffer(camera, vertices, faces, shadow).unpack(
        table, fine=finer(camera, vertices, faces, table, shadow) if fine else None)


def finer(camera: Camera, vertices, faces, table: "FaceTable", shadow=None):
    """GBuffer.fine of a view: k -> its G-buffer at k× the resolution."""
    def make(k: int) -> GBuffer:
        return table_gbuffer(camera.with_resolution(camera.width * k, camera.height * k),
                             vertices, faces, table, shadow)
    return make


@dataclass
class FaceTable:
    """What a pixel's proxy face gives it: unit normal and class, as lookup tables built
    once per proxy (row F is the empty pixel's: normal 0, class -1)."""
    normals: torch.Tensor          # (F+1,3) float32
    classes: torch.Tensor          # (F+1,) int64

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray | None) -> "FaceTable":
        n = face_normals(vertices, faces)
        if face_ids is None:
            ids = np.full(len(n), -1, np.int64)
        elif np.shape(face_ids) != (len(n),):
            raise InputError(f"gbuffer: face_ids must have shape ({len(n)},), got "
                             f"{np.shape(face_ids)}")
        else:
            ids = np.asarray(face_ids).astype(np.int64)
        return cls(torch.from_numpy(np.concatenate([n, np.zeros((1, 3), np.float32)])),
                   torch.from_numpy(np.append(ids, -1)))


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

    def unpack(self, faces: FaceTable, key: Hashable | None = None, fine=None) -> GBuffer:
        """``faces``: the proxy's FaceTable; ``key``, ``fine``: GBuffer.key, GBuffer.fine."""
        empty = len(faces.classes) - 1
        f = torch.where(self.face >= 0, self.face, empty).long()
        return GBuffer(
            depth=self.depth, normal=faces.normals[f], semantic=faces.classes[f],
            world_pos=self.world_pos,
            view_dirs=torch.from_numpy(pixel_directions(self.camera).astype(np.float32)),
            camera_position=torch.from_numpy(self.camera.center.astype(np.float32)),
            sun_visibility=None if self.sun is None else self.sun.float(), key=key, fine=fine)


def pack_view_gbuffer(camera: Camera, vertices: np.ndarray, faces: np.ndarray,
                      shadow: ShadowMap | None = None) -> PackedGBuffer:
    zbuf, fid = render_depth(vertices, faces, camera)
    hit = fid >= 0
    pos = pixel_positions(camera, zbuf, fid)
    sun = None
    if shadow is not None:
        vis = shadow.visibility(pos)            # nan where empty: lit there
        sun = torch.from_numpy(np.where(hit, vis, 1.0) > 0.5)
    return PackedGBuffer(
        camera, depth=torch.from_numpy(zbuf.astype(np.float32)),
        face=torch.from_numpy(fid.astype(np.int32)),
        world_pos=torch.from_numpy(np.nan_to_num(pos, nan=0.0).astype(np.float32)), sun=sun)
