"""One frame of a scene: surfels rasterised, mesh actors z-buffered, composited per pixel in
depth order over the env background.

`render_scene(reader, camera, time)` is the one "render this scene from this camera at this
time" function (render --camera, the rig, usdview); `render_surfels` is the one
SurfelField + Camera -> rasterize call (also used alone by eval, which measures the surfels).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from lsd3d_usd.render.camera import Camera, pixel_rays
from lsd3d_usd.render.gbuffer import render_depth
from lsd3d_usd.render.raster_types import RasterSettings
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.views import labels as L


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
    labels: "FrameLabels | None" = None


@dataclass
class FrameLabels:
    """Ground truth of a composited frame, by the one rule that decides what is drawn at a
    pixel: an actor nearer than the surfels' depth; else the surfels where their alpha
    reaches 0.5 (their median depth); else an actor behind faint surfels; else the sky.

    z: camera z-depth (along the optical axis) of that surface, inf for the sky.
    class_id (uint8): views.labels ids (SKY where nothing is drawn). instance_id (uint16): the
    actor's instance id, 0 for stuff. normal: world-space unit normal, 0 for the sky.
    """
    z: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray
    normal: np.ndarray


def env_background(env, camera: Camera) -> np.ndarray | None:
    """(H, W, 3) env radiance along each pixel's ray, or None without an env."""
    if env is None:
        return None
    if hasattr(env, "pixels"):      # views.stage_data.EnvMap: rays and lookup in one pass
        return env.pixels(camera)
    _, d = pixel_rays(camera)
    return env.lookup(d)


def render_surfels(field, camera: Camera, *, background=None, normal_space: str = "camera",
                   sh_degree=None, semantic: bool = False, codes=None, backend: str = "numba"):
    """Rasterise a SurfelField for ``camera`` (no autograd): a render.RasterResult.
    background: None or (H, W, 3) / (3,) numpy radiance behind the surfels. ``semantic``:
    result.semantic holds the largest-weight surfel's class id per pixel; ``codes`` (N,) int:
    the same with these per-surfel labels instead. A field the scene reader validated
    (field.checked) is not scanned value by value again."""

    def t(a):
        a = np.ascontiguousarray(a)
        if a.flags.writeable:
            return torch.from_numpy(a)
        with warnings.catch_warnings():     # a checked field's arrays are read-only; the
            warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
            return torch.from_numpy(a)      # rasteriser only reads its inputs

    with torch.no_grad():
        return rasterize(t(field.positions), t(field.orientations), t(field.scales),
                         t(field.opacities), t(field.sh), t(camera.viewmat), t(camera.K),
                         camera.width, camera.height,
                         settings=RasterSettings.for_camera(camera, sh_degree=sh_degree,
                                                            normal_space=normal_space),
                         background=None if background is None else t(np.asarray(background, np.float32)),
                         semantic_ids=(t(np.asarray(codes, np.int64)) if codes is not None
                                       else t(field.semantic_ids)
                                       if semantic and field.semantic_ids is not None else None),
                         backend=backend, values_checked=getattr(field, "checked", False))


def surfel_codes(field, class_of_row=None, instance_of_row=None) -> np.ndarray:
    """Per-surfel label codes (class + labels.CODE * instance) of a SurfelField: its semantic
    ids through its class table, UNLABELLED where none; ``class_of_row`` / ``instance_of_row``
    (N,) override them (actor surfels)."""
    if class_of_row is not None:
        cls = np.asarray(class_of_row, np.int64)
    elif field.semantic_ids is None:
        cls = np.full(field.n, L.UNLABELLED, np.int64)
    else:
        table = np.append(L.class_of_names(field.semantic_classes), L.UNLABELLED)
        ids = np.asarray(field.semantic_ids, np.int64)
        cls = table[np.where((ids >= 0) & (ids < len(table) - 1), ids, len(table) - 1)]
    inst = np.zeros(field.n, np.int64) if instance_of_row is None else np.asarray(instance_of_row)
    return cls + L.CODE * inst


def composite(surfels, actors, camera: Camera, env=None, sh_degree=None,
              instances=None) -> Frame:
    """Render surfels (the scene's and the surfel actors') and mesh actors (a
    stage_data.ActorFrame) for ``camera`` and composite them per pixel in depth order over the
    env background.

    Mesh actors are opaque: where an actor is nearer than the surfels' depth (the median
    depth, or the expected depth where the surfels' alpha stays below 0.5) the actor wins;
    elsewhere the surfels' premultiplied colour goes over the actor (or over the env).
    ``instances`` (views.labels.Instances of the reader's actors): also the frame's ground
    truth (Frame.labels, FrameLabels) from the same rasterisation."""

    H, W = camera.height, camera.width
    want = instances is not None
    parts = [(f, k) for f, k in ((surfels, "scene"), (actors.surfels, "actor"))
             if f is not None and f.n]
    fields = [f for f, _ in parts]
    s_code = s_normal = None
    if fields:
        codes = None
        if want:
            cls_a = instances.class_ids()
            codes = np.concatenate([
                surfel_codes(f) if k == "scene" else
                surfel_codes(f, cls_a[actors.surfel_actor], instances.ids[actors.surfel_actor])
                for f, k in parts])
        out = render_surfels(SurfelField.concat(fields, drop_mismatched_semantics=True), camera,
                             sh_degree=sh_degree, codes=codes,
                             normal_space="world" if want else "camera")
        s_rgb = out.rgb.numpy()
        s_a = out.alpha.numpy()
        dmed = out.depth_median.numpy()
        dexp = out.depth_expected.numpy()
        s_depth = np.where(dmed > 0, dmed, np.where(s_a > 1e-4, dexp, np.float32(np.inf)))
        if want:
            s_code = out.semantic.numpy()
            s_normal = out.normal.numpy()
    else:
        s_rgb = np.zeros((H, W, 3), np.float32)
        s_a = np.zeros((H, W), np.float32)
        dmed = np.zeros((H, W), np.float32)
        dexp = np.zeros((H, W), np.float32)
        s_depth = np.full((H, W), np.inf, np.float32)
    # whole-image passes only where every pixel needs one; actor pixels by their mask
    bg = env_background(env, camera)     # a fresh array: the actors are drawn into it
    under = np.zeros((H, W, 3), np.float32) if bg is None else np.asarray(bg, np.float32)
    a_depth = np.full((H, W), np.inf, np.float32)
    if len(actors.faces):
        zbuf, a_face = render_depth(actors.vertices, actors.faces, camera)
        a_mask = a_face >= 0
        a_depth[a_mask] = zbuf[a_mask]
        under[a_mask] = actors.colors[a_face[a_mask]]
    else:
        a_mask = np.zeros((H, W), bool)
        a_face = np.full((H, W), -1, np.int64)
    front = a_mask & (a_depth < s_depth)
    rgb = (1.0 - s_a)[..., None] * under
    rgb += s_rgb
    rgb[front] = under[front]
    alpha = s_a.copy()
    alpha[a_mask] = 1.0
    depth_exp = np.where(dexp > 0, dexp, np.float32(0.0))
    at = a_mask & (front | ~(dexp > 0))
    depth_exp[at] = a_depth[at]
    depth = s_depth.copy()
    depth[a_mask] = np.minimum(a_depth[a_mask], s_depth[a_mask])
    frame = Frame(rgb, alpha, depth, depth_exp, front)
    if want:
        frame.labels = _labels(front, a_mask, a_depth, a_face, s_a, dmed, s_code, s_normal,
                               actors, instances, H, W)
    return frame


def _labels(front, a_mask, a_depth, a_face, s_a, dmed, s_code, s_normal, actors, instances,
            H, W) -> FrameLabels:
    # whole-image operations rather than boolean gathers: a rig renders this per frame
    solid = (s_a >= 0.5) & (dmed > 0) & ~front if s_code is not None else np.zeros((H, W), bool)
    actor = front | (a_mask & ~solid)
    z = np.where(solid, dmed, np.float32(np.inf)).astype(np.float32)
    cls = np.full((H, W), L.SKY, np.int64)
    inst = np.zeros((H, W), np.int64)
    nrm = np.zeros((H, W, 3), np.float32)
    if solid.any():
        labelled = solid & (s_code >= 0)
        cls[solid] = L.UNLABELLED
        np.copyto(cls, s_code % L.CODE, where=labelled)
        np.copyto(inst, s_code // L.CODE, where=labelled)
        norm = np.sqrt(np.einsum("ijk,ijk->ij", s_normal, s_normal))
        np.divide(s_normal, np.maximum(norm, 1e-12)[..., None], out=nrm, where=solid[..., None])
    if actor.any():
        f = a_face[actor]
        used, back = np.unique(f, return_inverse=True)     # a face's normal once, not per pixel
        tri = actors.vertices[actors.faces[used]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        q = actors.face_actor[f]
        z[actor] = a_depth[actor]
        cls[actor] = instances.class_ids()[q]
        inst[actor] = instances.ids[q]
        nrm[actor] = n[back]
    return FrameLabels(z, cls.astype(np.uint8), inst.astype(np.uint16), nrm)


def render_scene(reader, camera: Camera, time=None, sh_degree=None, instances=None) -> Frame:
    """The scene of a stage_data.SceneReader seen by ``camera`` at ``time`` (a time code;
    None = the stage's earliest time): surfels + actors over the env. A streaming reader loads
    the chunks around the camera first. ``instances``: with ground truth (composite)."""
    surfels = reader.surfels_seen(camera, time)
    return composite(surfels, reader.actors_at(time), camera, reader.env(time), sh_degree,
                     instances)
