"""The proxy G-buffer of a view as a prior wants it (GBuffer), with the sun's visibility from a
shadow map (conditioning.shadow); the compact form GGDS keeps per training view
(PackedGBuffer) and the per-face lookup tables that unpack it (FaceTable)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Hashable, Optional

import numpy as np
import torch
from numba import njit, prange

from lsd3d_usd.errors import InputError
from lsd3d_usd.jitopts import prange_only
from lsd3d_usd.conditioning.shadow import ShadowMap
from lsd3d_usd.render.camera import Camera
from lsd3d_usd.render.gbuffer import face_normals, render_depth


@dataclass
class GBuffer:
    """Proxy G-buffer of one view, torch tensors on one device.

    depth:        (H, W) camera z in metres (along the optical axis); inf where empty.
    normal:       (H, W, 3) world-space unit normals; anything where empty.
    semantic:     (H, W) int class ids of lsd3d_usd.semantics; -1 where empty / sky.
    world_pos:    (H, W, 3) world positions (metres); anything finite or nan where empty.
    view_dirs:    (H, W, 3) world-space unit rays from the camera through each pixel.
    camera_position: (3,) world position of the camera centre.
    sun_visibility: optional (H, W) in [0, 1], 1 = lit by the sun (ray cast against the
                  proxy by the caller); None means everything is lit.
    key:          optional hashable identity of the view: equal keys promise equal contents,
                  so a prior may cache what it derives from the G-buffer under it (GGDS
                  rebuilds a training view's G-buffer every time it visits the view).
    fine:         optional callable k -> the same view's G-buffer at k× the resolution (each
                  pixel split into k×k), made on demand, for a prior that integrates over
                  pixels instead of sampling their centres.
    """
    depth: torch.Tensor
    normal: torch.Tensor
    semantic: torch.Tensor
    world_pos: torch.Tensor
    view_dirs: torch.Tensor
    camera_position: torch.Tensor
    sun_visibility: Optional[torch.Tensor] = None
    key: Optional[Hashable] = None
    fine: Optional[Callable[[int], "GBuffer"]] = None

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.depth.shape)

    @property
    def valid(self) -> torch.Tensor:
        """(H, W) bool: pixels covered by proxy geometry."""
        return torch.isfinite(self.depth) & (self.depth > 0)

    def disparity(self) -> torch.Tensor:
        """(H, W) 1 / depth, 0 where empty."""
        d = self.depth
        ok = self.valid
        return torch.where(ok, 1.0 / torch.where(ok, d, torch.ones_like(d)), torch.zeros_like(d))

    def validate(self, height: int | None = None, width: int | None = None) -> None:
        """Raise InputError naming the first field whose shape does not match."""
        if self.depth.ndim != 2:
            raise InputError(f"GBuffer.depth must be (H, W), got {tuple(self.depth.shape)}")
        H, W = self.depth.shape
        if height is not None and (H, W) != (height, width):
            raise InputError(f"GBuffer is {W}x{H} but the image is {width}x{height}")
        expect = {"normal": (H, W, 3), "semantic": (H, W), "world_pos": (H, W, 3),
                  "view_dirs": (H, W, 3), "camera_position": (3,)}
        if self.sun_visibility is not None:
            expect["sun_visibility"] = (H, W)
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise InputError(f"GBuffer.{name} must be {shape}, got {got}")


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
        """``faces``: the proxy's FaceTable; ``key``, ``fine``: GBuffer.key, GBuffer.fine.
        Normals, classes and view directions in one pass (_unpack_pixels: the formulas of
        render.camera.pixel_directions, in float64, each direction rounded to float32)."""
        H, W = self.face.shape
        normal = np.empty((H, W, 3), np.float32)
        semantic = np.empty((H, W), np.int64)
        dirs = np.empty((H, W, 3), np.float32)
        c = self.camera
        _unpack_pixels(self.face.numpy(), faces.normals.numpy(), faces.classes.numpy(),
                       np.array([c.fx, c.fy, c.cx, c.cy]), np.ascontiguousarray(c.pose[:3, :3]),
                       normal, semantic, dirs)
        return GBuffer(
            depth=self.depth, normal=torch.from_numpy(normal),
            semantic=torch.from_numpy(semantic), world_pos=self.world_pos,
            view_dirs=torch.from_numpy(dirs),
            camera_position=torch.from_numpy(self.camera.center.astype(np.float32)),
            sun_visibility=None if self.sun is None else self.sun.float(), key=key, fine=fine)


@njit(parallel=prange_only(), cache=True)
def _unpack_pixels(face, normals, classes, cam, R, normal, semantic, dirs):
    """Per pixel: its face's normal and class (the table's last row where empty) and the unit
    world direction of its ray."""
    H, W = face.shape
    empty = classes.shape[0] - 1
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    for j in prange(H):
        y = (j + 0.5 - cy) / fy
        for i in range(W):
            f = face[j, i]
            if f < 0:
                f = empty
            for a in range(3):
                normal[j, i, a] = normals[f, a]
            semantic[j, i] = classes[f]
            x = (i + 0.5 - cx) / fx
            dx = x * R[0, 0] + y * R[0, 1] + R[0, 2]
            dy = x * R[1, 0] + y * R[1, 1] + R[1, 2]
            dz = x * R[2, 0] + y * R[2, 1] + R[2, 2]
            n = math.sqrt(dx * dx + dy * dy + dz * dz)
            dirs[j, i, 0], dirs[j, i, 1], dirs[j, i, 2] = dx / n, dy / n, dz / n


def pack_view_gbuffer(camera: Camera, vertices: np.ndarray, faces: np.ndarray,
                      shadow: ShadowMap | None = None) -> PackedGBuffer:
    """The view's PackedGBuffer: the proxy rasterised (render.gbuffer.render_depth), then each
    pixel's world position and sun visibility in one pass (_pack_pixels; the same formulas as
    render.gbuffer.pixel_positions and ShadowMap.visibility, which the tests hold it to)."""
    zbuf, fid = render_depth(vertices, faces, camera)
    H, W = zbuf.shape
    depth = np.empty((H, W), np.float32)
    face = np.empty((H, W), np.int32)
    pos = np.empty((H, W, 3), np.float32)
    sun = np.ones((H, W), np.bool_)
    cam = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    if shadow is not None:
        sv = shadow.camera.viewmat
        sc = shadow.camera
        light = np.array([sc.fx, sc.fy, sc.cx, sc.cy, shadow.bias])
        sdepth = np.ascontiguousarray(shadow.depth)
    else:
        sv, light, sdepth = np.eye(4), np.zeros(5), np.zeros((0, 0), np.float32)
    _pack_pixels(zbuf, fid, cam, np.ascontiguousarray(camera.pose, np.float64),
                 np.ascontiguousarray(sv, np.float64), light, sdepth, shadow is not None,
                 depth, face, pos, sun)
    return PackedGBuffer(camera, depth=torch.from_numpy(depth), face=torch.from_numpy(face),
                         world_pos=torch.from_numpy(pos),
                         sun=torch.from_numpy(sun) if shadow is not None else None)


@njit(parallel=prange_only(), cache=True)
def _pack_pixels(zbuf, fid, cam, pose, sv, light, sdepth, shadowed, depth, face, pos, sun):
    """Per pixel: depth and face as float32 / int32; the world position of the pixel ray at
    its depth (float64 inside, 0 where empty); whether the sun's shadow map sees it (texel
    depth not nearer than the point's light-view z less the bias; lit where empty or off
    the map)."""
    H, W = zbuf.shape
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    SH, SW = sdepth.shape[0], sdepth.shape[1]
    for j in prange(H):
        for i in range(W):
            z = zbuf[j, i]
            f = fid[j, i]
            depth[j, i] = z
            face[j, i] = f
            if f < 0:
                pos[j, i, 0] = pos[j, i, 1] = pos[j, i, 2] = 0.0
                continue
            dx = (i + 0.5 - cx) / fx * z
            dy = (j + 0.5 - cy) / fy * z
            px = pose[0, 0] * dx + pose[0, 1] * dy + pose[0, 2] * z + pose[0, 3]
            py = pose[1, 0] * dx + pose[1, 1] * dy + pose[1, 2] * z + pose[1, 3]
            pz = pose[2, 0] * dx + pose[2, 1] * dy + pose[2, 2] * z + pose[2, 3]
            pos[j, i, 0], pos[j, i, 1], pos[j, i, 2] = px, py, pz
            if not shadowed or not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
                continue
            qx = sv[0, 0] * px + sv[0, 1] * py + sv[0, 2] * pz + sv[0, 3]
            qy = sv[1, 0] * px + sv[1, 1] * py + sv[1, 2] * pz + sv[1, 3]
            qz = sv[2, 0] * px + sv[2, 1] * py + sv[2, 2] * pz + sv[2, 3]
            u = light[0] * qx / qz + light[2]
            v = light[1] * qy / qz + light[3]
            # on the map as floats first (nan fails too): no huge float is made an integer
            if not (0.0 <= u < SW and 0.0 <= v < SH):
                continue
            if sdepth[int(math.floor(v)), int(math.floor(u))] < qz - light[4]:
                sun[j, i] = False
