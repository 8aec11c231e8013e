"""One frame of a scene: surfels rasterised, mesh actors z-buffered, composited per pixel in
depth order over the env background.

`render_scene(reader, camera, time)` is the one "render this scene from this camera at this
time" function (render --camera, the rig, usdview); `render_surfels` is the one
SurfelField + Camera -> rasterize call (also used alone by eval, which measures the surfels).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from lsd3d_usd.render.camera import Camera, pixel_rays
from lsd3d_usd.render.gbuffer import render_gbuffer
from lsd3d_usd.render.raster_types import RasterSettings
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.splats.field import SurfelField


@dataclass
class Frame:
    """A composited frame (numpy, (H, W[, 3]), float32 unless noted).

    rgb: scene-linear colour, env behind. alpha: coverage by surfels and actors.
    depth: camera depth of the nearest drawn surface (actor, or the surfels' median depth,
    or their expected depth where their alpha stays below 0.5), inf where nothing is drawn.
    depth_expected: the surfels' expected depth, the actor's where an actor is in front, 0
    where nothing is drawn (the EXR Z channel). actor_mask (bool): an actor is in front.
    """
    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    depth_expected: np.ndarray
    actor_mask: np.ndarray


def env_background(env, camera: Camera) -> np.ndarray | None:
    """(H, W, 3) env radiance along each pixel's ray, or None without an env."""
    if env is None:
        return None
    _, d = pixel_rays(camera)
    return env.lookup(d)


def render_surfels(field, camera: Camera, *, background=None, normal_space: str = "camera",
                   sh_degree=None, semantic: bool = False, backend: str = "numba"):
    """Rasterise a SurfelField for ``camera`` (no autograd): a render.RasterResult.
    background: None or (H, W, 3) / (3,) numpy radiance behind the surfels."""

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a))

    with torch.no_grad():
        return rasterize(t(field.positions), t(field.orientations), t(field.scales),
                         t(field.opacities), t(field.sh), t(camera.viewmat), t(camera.K),
                         camera.width, camera.height,
                         settings=RasterSettings.for_camera(camera, sh_degree=sh_degree,
                                                            normal_space=normal_space),
                         background=None if background is None else t(np.asarray(background, np.float32)),
                         semantic_ids=(t(field.semantic_ids) if semantic and field.semantic_ids is not None
                                       else None),
                         backend=backend)


def composite(surfels, actors, camera: Camera, env=None, sh_degree=None) -> Frame:
    """Render surfels (the scene's and the surfel actors') and mesh actors (a
    stage_data.ActorFrame) for ``camera`` and composite them per pixel in depth order over the
    env background.

    Mesh actors are opaque: where an actor is nearer than the surfels' depth (the median
    depth, or the expected depth where the surfels' alpha stays below 0.5) the actor wins;
    elsewhere the surfels' premultiplied colour goes over the actor (or over the env)."""

    H, W = camera.height, camera.width
    fields = [f for f in (surfels, actors.surfels) if f is not None and f.n]
    if fields:
        out = render_surfels(SurfelField.concat(fields, drop_mismatched_semantics=True), camera,
                             sh_degree=sh_degree)
        s_rgb = out.rgb.numpy()
        s_a = out.alpha.numpy()
        dmed = out.depth_median.numpy()
        dexp = out.depth_expected.numpy()
        s_depth = np.where(dmed > 0, dmed, np.where(s_a > 1e-4, dexp, np.inf)).astype(np.float32)
    else:
        s_rgb = np.zeros((H, W, 3), np.float32)
        s_a = np.zeros((H, W), np.float32)
        dexp = np.zeros((H, W), np.float32)
        s_depth = np.full((H, W), np.inf, np.float32)
    bg = env_background(env, camera)
    under = np.zeros((H, W, 3), np.float32) if bg is None else bg.astype(np.float32)
    a_mask = np.zeros((H, W), bool)
    a_depth = np.full((H, W), np.inf, np.float32)
    if len(actors.faces):
        g = render_gbuffer(actors.vertices, actors.faces, camera)
        a_mask = g.face_index >= 0
        a_depth = np.where(a_mask, g.depth, np.inf).astype(np.float32)
        a_rgb = np.zeros((H, W, 3), np.float32)
        a_rgb[a_mask] = actors.colors[g.face_index[a_mask]]
        under = np.where(a_mask[..., None], a_rgb, under)
    front = a_mask & (a_depth < s_depth)
    rgb = np.where(front[..., None], under, s_rgb + (1.0 - s_a)[..., None] * under)
    alpha = np.where(front | a_mask, 1.0, s_a).astype(np.float32)
    depth_exp = np.where(front, a_depth, np.where(dexp > 0, dexp, np.where(a_mask, a_depth, 0.0)))
    return Frame(rgb.astype(np.float32), alpha, np.minimum(a_depth, s_depth),
                 depth_exp.astype(np.float32), front)


def render_scene(reader, camera: Camera, time=None, sh_degree=None) -> Frame:
    """The scene of a stage_data.SceneReader seen by ``camera`` at ``time`` (a time code;
    None = the stage's earliest time): surfels + actors over the env. A streaming reader loads
    the chunks around the camera first."""
    surfels = reader.surfels(time, near=camera.center[None, :])
    return composite(surfels, reader.actors_at(time), camera, reader.env(time), sh_degree)
