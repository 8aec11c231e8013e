"""A small preview rasteriser for proxy meshes (docs pictures, quick looks).

Painter's algorithm over matplotlib polygons: triangles are shaded by class
colour (sRGB-encoded from the linear class albedo, brightened for display)
times a Lambert term, culled when facing away, sorted far to near. Good for a
few hundred thousand triangles; the real renderer lives in render/.
"""
from __future__ import annotations

import io
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import PolyCollection

from lsd3d_usd.colour import srgb_encode as _srgb
from lsd3d_usd.scene import atomic_write_bytes
from lsd3d_usd.semantics import CLASS_COLORS, CLASS_ID

from .mesh import ClassMesh
from .usdio import read_proxy


def _face_colors(cm: ClassMesh) -> np.ndarray:
    base = np.asarray(CLASS_COLORS[CLASS_ID[cm.cls]] if cm.cls in CLASS_ID else (0.5, 0.5, 0.5),
                      dtype=np.float64)
    cols = np.tile(base, (len(cm.faces), 1))
    if cm.part_colors and any(c is not None for c in cm.part_colors):
        pc = np.array([base if c is None else c for c in cm.part_colors], dtype=np.float64)
        cols = pc[cm.face_part]
    return cols


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World -> camera rotation rows (x right, y down, z forward: OpenCV axes)."""
    f = np.asarray(target, float) - np.asarray(eye, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return np.stack([r, d, f])


def render(meshes: list[ClassMesh], width: int = 1600, height: int = 1000,
           view: str = "perspective", eye=None, target=None, fov_deg: float = 50.0,
           sun=(0.35, -0.45, 0.82), background=(0.72, 0.80, 0.90)) -> np.ndarray:
    """RGB image (H, W, 3) float in [0, 1]."""
    matplotlib.use("Agg")

    meshes = [m for m in meshes if m.n_faces]
    if not meshes:
        return np.broadcast_to(np.asarray(background), (height, width, 3)).copy()
    V = [m.vertices[m.faces] for m in meshes]                 # (M, 3, 3) per mesh
    tri = np.concatenate(V)
    col = np.concatenate([_face_colors(m) for m in meshes])
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    sun = np.asarray(sun, float) / np.linalg.norm(sun)
    shade = 0.45 + 0.55 * np.clip(n @ sun, 0.0, 1.0)
    rgb = np.clip(_srgb(col * 1.6) * shade[:, None], 0, 1)

    lo = np.concatenate([m.vertices for m in meshes]).min(0)
    hi = np.concatenate([m.vertices for m in meshes]).max(0)
    center = (lo + hi) / 2
    center[2] = 0.0
    ext = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_facecolor(background)
    fig.patch.set_facecolor(background)
    if view == "top":
        keep = n[:, 2] > 1e-6
        order = np.argsort(tri[keep, :, 2].max(1), kind="stable")  # low first, high last
        xy = tri[keep][order][:, :, :2]
        colors = rgb[keep][order]
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
    else:
        target = center if target is None else np.asarray(target, float)
        eye = (center + np.array([-0.45, -0.75, 0.32]) * ext) if eye is None else np.asarray(eye, float)
        R = look_at(eye, target)
        cam = (tri - eye) @ R.T                                 # (M, 3, 3)
        near = 0.5
        keep = (cam[:, :, 2] > near).all(1)
        keep &= ((tri.mean(1) - eye) * n).sum(1) < 0            # back-face culling
        f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
        uv = f * cam[..., :2] / cam[..., 2:3]
        uv[..., 0] += width / 2
        uv[..., 1] = height / 2 - uv[..., 1]                   # image y up for matplotlib
        inside = ((uv[..., 0].max(1) > 0) & (uv[..., 0].min(1) < width)
                  & (uv[..., 1].max(1) > 0) & (uv[..., 1].min(1) < height))
        keep &= inside
        depth = cam[keep, :, 2].mean(1)
        order = np.argsort(-depth, kind="stable")               # far first
        xy = uv[keep][order]
        colors = rgb[keep][order]
        fog = np.clip((depth[order] - 0.3 * ext) / (2.0 * ext), 0, 0.6)[:, None]
        colors = colors * (1 - fog) + np.asarray(background) * fog
        ax.set_xlim(0, width)
        ax.set_ylim(0, height)
    ax.add_collection(PolyCollection(xy, facecolors=colors, edgecolors=colors, linewidths=0.15,
                                     antialiased=False))
    ax.axis("off")
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float64) / 255.0
    plt.close(fig)
    return img


def render_proxy_file(path, output, view: str = "perspective", width: int = 1600,
                      height: int = 1000, chunks=None) -> Path:

    data = read_proxy(path, chunks)
    meshes = [cm for by_cls in data.values() for cm in by_cls.values()]
    img = render(meshes, width, height, view)
    return save_png(img, output)


def save_png(img: np.ndarray, output) -> Path:
    buf = io.BytesIO()
    iio.imwrite(buf, (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), extension=".png")
    return atomic_write_bytes(output, buf.getvalue())
