"""Reading a composed stage into arrays for rendering: the one place every view (render
command, rig, eval, usdview) gets its surfels, env map and actors from.

    scene_surfels(stage, time)   every visible ParticleField prim outside /World/Actors and
                                 /World/Cameras (our Lsd3dSurfelField and the official
                                 ParticleField3DGaussianSplat, flattened to surfels by
                                 splats.usdio.read_surfels), in world space, as one SurfelField
    read_dome(stage, time)       the first visible DomeLight's latlong texture (EnvMap)
    camera_prim(stage, path)     a UsdGeom.Camera prim, or one clear error listing the cameras
    SceneReader                  the above for one stage, plus the actors placed and relit at
                                 a time (`actors_at`); reads what cannot change only once
    ChunkStreamer                with a stage opened with Usd.Stage.LoadNone: loads the surfel
                                 and proxy chunk payloads within a radius of the cameras and
                                 unloads those left behind, so memory follows the radius, not
                                 the length of a route

The proxy mesh and the layout are read by their own packages (proxy.usdio.proxy_arrays,
layout.usdio.read_layout / layout_from_stage). Times are USD time codes; None means the
stage's earliest time (the default values where nothing is animated), so animated actors and
cameras are placed where their animation starts.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
from pxr import Sdf, Usd, UsdGeom, UsdLux

from lsd3d_usd.actors.relight import (
    actor_sample_points,
    lighting_from_stage,
    proxy_occluder,
)
from lsd3d_usd.actors.usdio import ActorSet
from lsd3d_usd.env.farfield import FarField
from lsd3d_usd.env.lookup import env_lookup, env_lookup_pinhole
from lsd3d_usd.env.usdlayer import read_far_field
from lsd3d_usd.render.checks import SH_MAX, first_bad
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import (
    ACTORS_PATH,
    CAMERAS_PATH,
    ENV_PATH,
    PROXY_PATH,
    SURFELS_PATH,
    WORLD,
    parse_chunk_prim_name,
)
from lsd3d_usd.splats.field import SH_C0, SurfelField
from lsd3d_usd.splats.init import transform_surfels
from lsd3d_usd.splats.lod import LodTree, build_lod, gather_cuts
from lsd3d_usd.splats.usdio import is_particle_field, read_surfels, surfel_prims
from lsd3d_usd.views.images import read_image


def usd_time(time):
    """A Usd.TimeCode for a time code (float) or None (the earliest time)."""
    return Usd.TimeCode.EarliestTime() if time is None else Usd.TimeCode(time)


def _world(prim, t) -> np.ndarray:
    return np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), np.float64).T


# ------------------------------------------------------------------------------ surfels
def scene_surfel_prims(stage) -> list:
    """ParticleField prims of the scene itself: outside /World/Actors (actors are drawn, relit,
    from their assets) and /World/Cameras."""
    skip = (ACTORS_PATH + "/", CAMERAS_PATH + "/")
    return [p for p in surfel_prims(stage) if not str(p.GetPath()).startswith(skip)]


SUN_SEEN_MAX = 4096  # actor poses whose sun visibility SceneReader keeps
ENV_PIXELS_KEPT = 8  # env backgrounds an EnvMap keeps: every camera of a rig
OPACITY_TOL = 1e-3   # as validation's OpacityRange: linear opacity in [0, 1]


def _layer_of(prim, name: str, t) -> str:
    """The file holding the strongest opinion of attribute ``name`` (or its half variant)."""
    for n in (name, name + "h"):
        attr = prim.GetAttribute(n)
        if attr and attr.HasValue():
            stack = attr.GetPropertyStack(t)
            if stack:
                return stack[0].layer.realPath or stack[0].layer.identifier
    return prim.GetStage().GetRootLayer().realPath


def renderable_problem(f: SurfelField, names=None):
    """(attribute, first bad particle, how many, what) of the first kind of value in ``f``
    that the rasteriser cannot draw or that validate reports as an error, or None: non-finite
    positions, scales or orientations, zero quaternions, negative scales, opacity outside
    [0, 1], SH coefficients non-finite or beyond render.checks.SH_MAX. Every value rasterize
    scans is covered, so a field that passes is marked checked and not scanned per frame.
    ``names``: only these attributes (None: all)."""
    with np.errstate(all="ignore"):
        q = np.asarray(f.orientations, np.float64)
        tests = (
            ("positions", lambda: ~np.isfinite(f.positions).all(1), "a non-finite position"),
            ("orientations", lambda: ~np.isfinite(q).all(1), "a non-finite quaternion"),
            ("orientations", lambda: (q * q).sum(1) < 1e-20, "a zero quaternion"),
            ("scales", lambda: ~np.isfinite(f.scales).all(1) | (f.scales < 0).any(1),
             "a non-finite or negative scale"),
            ("opacities", lambda: ~((f.opacities >= -OPACITY_TOL) & (f.opacities <= 1 + OPACITY_TOL)),
             "an opacity outside [0, 1] (linear, not logit)"),
            ("sh", lambda: _bad_sh_rows(f), f"an SH coefficient non-finite or beyond ±{SH_MAX:g}"),
        )
        for name, bad, what in tests:
            if names is not None and name not in names:
                continue
            hit = np.flatnonzero(bad())
            if hit.size:
                return name, int(hit[0]), int(hit.size), what
    return None


def _bad_sh_rows(f: SurfelField) -> np.ndarray:
    # the rasteriser's own scan (numba, no (N, K, 3) temporaries) finds whether any is bad
    flat = np.ascontiguousarray(f.sh, np.float32).reshape(-1)
    if not flat.size or first_bad(flat, np.float32(-SH_MAX), np.float32(SH_MAX)) < 0:
        return np.zeros(f.n, bool)
    return ~(np.abs(f.sh.reshape(f.n, -1)) <= SH_MAX).all(1)


def check_renderable(prim, f: SurfelField, t, transformed: bool = False) -> None:
    """Refuse (one line naming the layer file, prim, attribute and particle) surfels that
    the rasteriser cannot draw or that validate reports as errors (renderable_problem).
    ``transformed``: ``f`` is the prim's surfels in world space, whose stored values passed:
    the error then names the world transform, which validate (local values) does not see."""
    # a transform moves positions, turns orientations and stretches scales: only those change
    p = renderable_problem(f, ("positions", "orientations", "scales") if transformed else None)
    if p is not None:
        name, i, count, what = p
        hint = ("after the prim's world transform (its own or an ancestor's xformOps take it "
                "beyond float32)" if transformed else
                "`lsd3d-usd validate` lists the problems")
        raise InputError(f"{_layer_of(prim, name, t)}: {prim.GetPath()}.{name}: {what} at "
                         f"particle {i} ({count} bad of {f.n}); {hint}")


def scene_surfels(stage, time=None, prims=None, check: bool = True):
    """The scene's visible surfels in world space as one SurfelField (semantics dropped when
    the prims' class tables differ), or None when there are none. ``check``: refuse surfels
    the rasteriser cannot draw (check_renderable; the field is then marked checked); the
    viewer, which lists a scene's problems and still shows what it can, reads them unchecked."""

    t = usd_time(time)
    fields = []
    for prim in scene_surfel_prims(stage) if prims is None else prims:
        if UsdGeom.Imageable(prim).ComputeVisibility(t) == UsdGeom.Tokens.invisible:
            continue
        f = read_surfels(prim, t)
        if f.n:
            if check:
                check_renderable(prim, f, t)
            w = transform_surfels(f, _world(prim, t))
            if check:
                if w is not f:
                    check_renderable(prim, w, t, transformed=True)  # float32 overflow
                w.mark_checked()
            fields.append(w)
    return SurfelField.concat(fields, drop_mismatched_semantics=True) if fields else None


def lod_tree(field: SurfelField, where: str) -> LodTree:
    """build_lod of ``field``; of a checked field, its merged nodes checked too (once per
    load: a frame then draws the cut without scanning it). ``where`` names it in errors."""
    tree = build_lod(field)
    if field.checked:
        nodes = tree.nodes.rows(tree.n_leaves, tree.nodes.n)
        p = renderable_problem(nodes)
        if p is not None:
            name, i, _, what = p
            raise InputError(f"{where}: level-of-detail node {i} of surfels valid on their own "
                             f"has {what} ({name}); their values are too large to merge")
        tree.nodes.mark_checked()
    return tree


def _might_vary(prim) -> bool:
    """Whether anything that places or shows ``prim``'s surfels may change with time: its own
    attributes, or an ancestor's transform or visibility."""
    if any(a.ValueMightBeTimeVarying() for a in prim.GetAttributes()):
        return True
    p = prim.GetParent()
    while p and not p.IsPseudoRoot():
        x = UsdGeom.Xformable(p)
        if x and x.TransformMightBeTimeVarying():
            return True
        vis = UsdGeom.Imageable(p).GetVisibilityAttr() if UsdGeom.Imageable(p) else None
        if vis and vis.ValueMightBeTimeVarying():
            return True
        p = p.GetParent()
    return False


# ------------------------------------------------------------------------------ env map
@dataclass
class EnvMap:
    """A latlong env texture (scene-linear RGB, float32) with its dome orientation."""
    image: np.ndarray            # (h, w, 3)
    world_from_dome: np.ndarray  # (3,3) rotation of the DomeLight
    pole_axis: str = "Z"         # "Z" (our convention) or "Y" (OpenEXR latlong, Y up)
    source: str = ""
    far_field: FarField | None = None   # the ground beyond the scene, in the image's units

    def lookup(self, dirs: np.ndarray) -> np.ndarray:
        """Radiance (…,3) for world directions (…,3): into the dome's frame (and from a Y pole
        axis to ours), then env.lookup.env_lookup — the one latlong lookup of the project
        (bilinear, wrapping in longitude, continuous at the poles)."""

        d = np.asarray(dirs, np.float64) @ self.world_from_dome  # = R^T d: into the dome frame
        if self.pole_axis == "Y":
            d = np.stack([d[..., 0], -d[..., 2], d[..., 1]], axis=-1)
        image = torch.from_numpy(np.ascontiguousarray(self.image, np.float32))
        return env_lookup(image, torch.from_numpy(d.astype(np.float32))).numpy()

    def pixels(self, camera) -> np.ndarray:
        """(H, W, 3) float32 radiance along each pixel's ray of a render.camera.Camera: what
        lookup(pixel_directions(camera)) gives (within float32 rounding), with the ground beyond
        the scene (``far_field``) over it, in one pass. A new
        array each call (callers draw into it); the last ENV_PIXELS_KEPT lookups are kept, by
        camera rotation and intrinsics, and copied when a camera repeats one (a rig on a car
        driving straight or standing still: the sky does not move with the camera's position)."""
        R = np.ascontiguousarray(camera.pose[:3, :3], np.float64)
        # with a ground beyond the scene the camera's height matters too (not where it is)
        key = ((self.far_field, float(camera.pose[2, 3])) if self.far_field is not None else None,
               int(camera.width), int(camera.height), float(camera.fx), float(camera.fy),
               float(camera.cx), float(camera.cy), R.tobytes(),
               np.asarray(self.world_from_dome, np.float64).tobytes(), self.pole_axis)
        kept = self.__dict__.setdefault("_kept_pixels", OrderedDict())
        hit = kept.get(key)
        if hit is not None and hit[1] is self.image:
            kept.move_to_end(key)
            return hit[0].copy()
        out = env_lookup_pinhole(np.asarray(self.image, np.float32), camera.width, camera.height,
                                 camera.fx, camera.fy, camera.cx, camera.cy, R,
                                 self.world_from_dome, self.pole_axis == "Y", self.far_field,
                                 float(camera.pose[2, 3]))
        kept[key] = (out.copy(), self.image)
        kept.move_to_end(key)
        while len(kept) > ENV_PIXELS_KEPT:
            kept.popitem(last=False)
        return out


class TextureCache:
    """Decoded env textures by (path, modification time), the most recent ``size`` kept: a
    frame range or a usdview session decodes its EXR once."""

    def __init__(self, size: int = 1):
        self.size = int(size)
        self._images: dict = {}

    def image(self, path: str) -> np.ndarray:
        key = (path, os.path.getmtime(path))
        img = self._images.pop(key, None)
        if img is None:
            img = read_image(path)
        self._images[key] = img  # most recent last
        while len(self._images) > self.size:
            self._images.pop(next(iter(self._images)))
        return img


def read_dome(stage, time=None, textures: TextureCache | None = None) -> EnvMap | None:
    """The first visible DomeLight with a texture (intensity, exposure and colour applied),
    or None (black background). ``textures`` caches decoded images across calls."""

    t = usd_time(time)
    textures = TextureCache() if textures is None else textures
    dome_types = [UsdLux.DomeLight] + ([UsdLux.DomeLight_1] if hasattr(UsdLux, "DomeLight_1") else [])
    for prim in Usd.PrimRange(stage.GetPseudoRoot()):
        kind = next((k for k in dome_types if prim.IsA(k)), None)
        if kind is None:
            continue
        if UsdGeom.Imageable(prim).ComputeVisibility(t) == UsdGeom.Tokens.invisible:
            continue
        light = kind(prim)
        asset = light.GetTextureFileAttr().Get(t)
        if not asset or not asset.path:
            continue
        path = asset.resolvedPath or asset.path
        if not os.path.isfile(path):
            raise InputError(f"{prim.GetPath()}.inputs:texture:file: texture {asset.path!r} not found")
        fmt = light.GetTextureFormatAttr().Get(t)
        if fmt not in (None, "automatic", "latlong"):
            raise InputError(f"{prim.GetPath()}: texture format {fmt!r} not supported (latlong only)")
        img = textures.image(path)
        rgb = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
        lx = UsdLux.LightAPI(prim)
        gain = float(lx.GetIntensityAttr().Get(t) or 1.0) * 2.0 ** float(lx.GetExposureAttr().Get(t) or 0.0)
        col = np.asarray(lx.GetColorAttr().Get(t) or (1, 1, 1), np.float32)
        U, _, Vt = np.linalg.svd(_world(prim, t)[:3, :3])
        pole = light.GetPoleAxisAttr().Get() if hasattr(light, "GetPoleAxisAttr") else None
        up = UsdGeom.GetStageUpAxis(stage)
        pole_axis = "Y" if (pole == "Y" or (pole in (None, "scene") and up == "Y")) else "Z"
        env = EnvMap((rgb * (gain * col)).astype(np.float32), U @ Vt, pole_axis, str(prim.GetPath()))
        # /World/Env's far field belongs to its own dome, not to another tool's
        far = read_far_field(stage) if prim.GetParent().GetPath() == ENV_PATH else None
        if far is not None:     # in the map's units, over the map as this dome turns it
            env.far_field = far.scaled(gain * col).over(env.lookup)
        return env
    return None


# ------------------------------------------------------------------------------ cameras
def camera_prim(stage, camera_path: str):
    """The UsdGeom.Camera prim at ``camera_path``; one InputError naming the cameras the stage
    has otherwise."""

    if not Sdf.Path.IsValidPathString(camera_path) or not camera_path.startswith("/"):
        raise InputError(f"--camera {camera_path!r}: not an absolute prim path (e.g. /World/Cameras/Front)")
    prim = stage.GetPrimAtPath(camera_path)
    if not prim or not prim.IsA(UsdGeom.Camera):
        cams = [str(p.GetPath()) for p in Usd.PrimRange(stage.GetPseudoRoot()) if p.IsA(UsdGeom.Camera)]
        what = "no prim" if not prim else f"prim of type {prim.GetTypeName() or 'none'}, not a Camera,"
        raise InputError(f"{stage.GetRootLayer().identifier}: {what} at {camera_path}; cameras in the stage: "
                         f"{', '.join(cams[:10]) if cams else 'none'}")
    return prim


# ------------------------------------------------------------------------------ actors
@dataclass
class ActorFrame:
    """Actors placed and lit at one time: one merged mesh and the surfel actors, each face and
    surfel with the index of its actor in the reader's ActorSet (ground truth labels)."""
    vertices: np.ndarray            # (V,3) world
    faces: np.ndarray               # (F,3)
    colors: np.ndarray              # (F,3) lit linear colour per face
    surfels: object | None          # SurfelField (world, lit) or None
    face_actor: np.ndarray = None   # (F,) int
    surfel_actor: np.ndarray = None  # (n,) int, with surfels

    @staticmethod
    def empty() -> "ActorFrame":
        return ActorFrame(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32),
                          None, np.zeros(0, np.int64), np.zeros(0, np.int64))


class ChunkStreamer:
    """Payload chunks (/World/Surfels/Chunk_<i>_<j>, /World/Proxy/Chunk_<i>_<j>) loaded within
    ``radius`` metres of the cameras and unloaded beyond ``radius`` + one chunk (hysteresis:
    a chunk at the edge does not flicker in and out). Chunk (i, j) covers [i s, (i+1) s) ×
    [j s, (j+1) s) with s the scene's chunk size. Surfels of a loaded chunk are read once."""

    def __init__(self, stage, radius: float, chunk_size: float | None = None,
                 lod: bool = False):
        self.stage = stage
        self.radius = float(radius)
        self.lod = bool(lod)            # a level-of-detail tree per chunk, built as it loads
        self._trees: dict = {}          # key -> LodTree of its field (its leaves are the field)
        self.size = float(chunk_size or _scene_chunk_size(stage))
        self.chunks: dict = {}          # key -> [prim paths] (surfels and proxy)
        for root in (SURFELS_PATH, PROXY_PATH):
            prim = stage.GetPrimAtPath(root)
            if not prim:
                continue
            for child in prim.GetFilteredChildren(_all_defined()):
                try:
                    key = parse_chunk_prim_name(child.GetName())
                except ValueError:
                    continue
                self.chunks.setdefault(key, []).append(child.GetPath())
        self.loaded: set = set()
        self.version = 0                # bumped whenever the loaded set changes
        self._fields: dict = {}         # key -> world-space SurfelField of its surfel prims

    def _distance(self, key, points: np.ndarray) -> float:
        lo = np.array([key[0], key[1]], np.float64) * self.size
        d = np.maximum(np.maximum(lo - points[:, :2], points[:, :2] - (lo + self.size)), 0.0)
        return float(np.min(np.hypot(d[:, 0], d[:, 1])))

    def update(self, points) -> None:
        """Load the chunks within the radius of any of ``points`` (cameras, (n, 3))."""
        pts = np.atleast_2d(np.asarray(points, np.float64))
        dist = {k: self._distance(k, pts) for k in self.chunks}
        want = {k for k, d in dist.items() if d <= self.radius}
        drop = {k for k in self.loaded if dist[k] > self.radius + self.size}
        add = want - self.loaded
        if not add and not drop:
            return
        load = [p for k in add for p in self.chunks[k]]
        unload = [p for k in drop for p in self.chunks[k]]
        self.stage.LoadAndUnload(load, unload)
        self.loaded = (self.loaded | add) - drop
        for k in drop:
            self._fields.pop(k, None)
            self._trees.pop(k, None)
        self.version += 1

    def _read(self, time):
        """Loaded chunks' fields (and trees with lod), each read once, in scene order."""
        keys = sorted(self.loaded, key=lambda k: str(self.chunks[k][0]))
        for key in keys:
            if key not in self._fields:
                prims = [self.stage.GetPrimAtPath(p) for p in self.chunks[key]]
                prims = [p for p in prims if p and p.IsLoaded()]
                self._fields[key] = scene_surfels(self.stage, time,
                                                  [p for p in prims if is_particle_field(p)])
            f = self._fields[key]
            if self.lod and f is not None and key not in self._trees:
                # also for a chunk read before level of detail was asked for
                self._trees[key] = lod_tree(f, f"chunk {key}")
                self._fields[key] = self._trees[key].leaves   # the same surfels, reordered
        return keys

    def trees(self, time=None) -> list[LodTree]:
        """Level-of-detail trees of the loaded chunks (lod=True)."""
        return [self._trees[k] for k in self._read(time) if k in self._trees]

    def surfels(self, time=None):
        """Surfels of the loaded chunks (in scene order), or None; joined once per loaded
        set (a rig's frames between two loads share it)."""
        if getattr(self, "_joined", None) is not None and self._joined[0] == self.version:
            return self._joined[1]
        parts = [self._fields[k] for k in self._read(time) if self._fields[k] is not None]
        joined = SurfelField.concat(parts, drop_mismatched_semantics=True) if parts else None
        self._joined = (self.version, joined)
        return joined


def _scene_chunk_size(stage) -> float:
    world = stage.GetPrimAtPath(WORLD)
    attr = world.GetAttribute("lsd3d:scene:chunkSize") if world else None
    v = attr.Get() if attr and attr.HasValue() else None
    return float(v) if v else 100.0


def _all_defined():
    return Usd.PrimIsActive & Usd.PrimIsDefined & ~Usd.PrimIsAbstract


class SceneReader:
    """One composed stage read for rendering frames at any time: scene surfels (read once
    unless something about them is animated), the env map (textures decoded once), and the
    actors (asset geometry read once, placed and relit per time). Every frame is a pure
    function of (stage, time, camera): nothing carries over between frames.

    ``stream_radius``: the stage was opened with Usd.Stage.LoadNone and chunk payloads are
    loaded around the cameras given to ``surfels(time, near=...)`` (ChunkStreamer); a frame
    is the same as with everything loaded when the radius covers what the camera sees."""

    def __init__(self, stage, *, use_env: bool = True, actors: bool = True,
                 textures: TextureCache | None = None, stream_radius: float | None = None,
                 lod_px: float = 0.0):
        self.stage = stage
        self.lod_px = float(lod_px)     # > 0: surfels_seen draws a level-of-detail cut
        self.use_env = use_env
        self.textures = TextureCache() if textures is None else textures
        self.actors = ActorSet(stage) if actors else None
        self.stream = (ChunkStreamer(stage, stream_radius, lod=self.lod_px > 0)
                       if stream_radius else None)
        self._tree = None
        self._prims = scene_surfel_prims(stage)
        self._static = not any(_might_vary(p) for p in self._prims)
        self._field = None
        self._field_read = False
        self._lighting = None
        self._occluder = None
        self._occluder_version = -1
        self._meshes = {}  # actor index -> (actor, its meshes joined): see _actor_mesh
        self._last = {}  # per kind, (time, value) of the last call: a rig's cameras share a time

    def surfels(self, time=None, near=None):
        """The scene's surfels (world space) at ``time``, or None. ``near``: camera positions
        (n, 3), with streaming: the chunks around them are loaded first."""
        if self.stream is not None:
            if near is not None:
                self.stream.update(near)
            return self.stream.surfels(time)
        if not self._static:
            return scene_surfels(self.stage, time, self._prims)
        if not self._field_read:
            self._field = scene_surfels(self.stage, time, self._prims)
            self._field_read = True
        return self._field

    def surfels_seen(self, camera, time=None):
        """The surfels to draw for ``camera`` (a render.camera.Camera) at ``time``: with
        ``lod_px`` > 0 the level-of-detail cut of every loaded chunk (splats.lod: nodes whose
        bounding sphere covers at most lod_px pixels stand for their children, nothing
        outside the frustum), else all of them (`surfels`)."""
        if self.lod_px <= 0 or (self.stream is None and not self._static):
            # animated surfels are a new field at every time: a tree per frame would cost
            # more than it saves, so they are drawn in full
            return self.surfels(time, near=camera.center[None, :])
        if self.stream is not None:
            self.stream.lod = True              # lod_px may be set after the reader was made
            self.stream.update(camera.center[None, :])
            trees = self.stream.trees(time)
        else:
            field = self.surfels(time)
            if field is None:
                return None
            if self._tree is None or self._tree[0] is not field:
                tree = lod_tree(field, "scene surfels")
                field = tree.leaves             # the same surfels in the tree's order
                if self._static:
                    self._field = field         # kept once, not beside a copy
                self._tree = (field, tree)
            trees = [self._tree[1]]
        if not trees:
            return None
        cuts = [t.cut(camera.viewmat, camera.K, camera.width, camera.height, camera.near,
                      camera.far, self.lod_px) for t in trees]
        return gather_cuts(trees, cuts)

    def _memo(self, kind, time, make):
        hit = self._last.get(kind)
        if hit is None or hit[0] != time:
            hit = self._last[kind] = (time, make(time))
        return hit[1]

    def env(self, time=None) -> EnvMap | None:
        """The env map at ``time`` (None without one, or with use_env=False)."""
        if not self.use_env:
            return None
        return self._memo("env", time, lambda t: read_dome(self.stage, t, self.textures))

    def actors_at(self, time=None) -> ActorFrame:
        """Actor geometry in world space at ``time``, relit by the scene's lighting."""
        return self._memo("actors", time, self._place_actors)

    def _actor_mesh(self, q, a):
        """Actor ``a``'s meshes as one (asset frame): vertices, faces, albedo per face, and
        where each mesh's vertices start (read once per actor, not per frame)."""
        hit = self._meshes.get(q)
        if hit is None or hit[0] is not a:
            sizes = [len(m.vertices) for m in a.meshes]
            ranges = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
            if a.meshes:
                geo = (np.concatenate([m.vertices for m in a.meshes]).astype(np.float64),
                       np.concatenate([m.faces + int(r) for m, r in zip(a.meshes, ranges)]),
                       np.concatenate([m.colors for m in a.meshes]), ranges)
            else:
                geo = (np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32), ranges)
            hit = self._meshes[q] = (a, geo)
        return hit[1]

    def _place_actors(self, time) -> ActorFrame:
        if self.actors is None or not len(self.actors):
            return ActorFrame.empty()
        t = usd_time(time)
        shown = [(q, a, M) for q, (a, M, v) in enumerate(zip(
            self.actors.actors, self.actors.transforms(t), self.actors.visible(t))) if v]
        if not shown:
            return ActorFrame.empty()
        version = self.stream.version if self.stream is not None else 0
        if self._lighting is None or self._occluder_version != version:
            # built when an actor shows, and again when streaming changed the loaded proxy
            self._lighting = lighting_from_stage(self.stage)
            self._occluder = proxy_occluder(self.stage)
            self._occluder_version = version
            self._sun_seen = {}
        light = self._lighting
        # sun visibility: an actor that has not moved sees the sun as before (parked cars, a
        # waiting queue); the others' shadow rays in one pass
        keys = [(q, np.asarray(M, np.float64).tobytes()) for q, _, M in shown]
        todo = [i for i, k in enumerate(keys) if k not in self._sun_seen]
        if todo and len(self._sun_seen) + len(todo) > SUN_SEEN_MAX:
            # full (a long episode): forget all, cast for every shown actor again (the still
            # ones' answers went too; keeping only the new ones raised KeyError below)
            self._sun_seen.clear()
            todo = list(range(len(keys)))
        if todo:
            seen = self._occluder.visibility_many(
                np.stack([actor_sample_points(shown[i][2], shown[i][1].dims) for i in todo]),
                light.sun_dir)
            self._sun_seen.update((keys[i], float(v)) for i, v in zip(todo, seen))
        vis = [self._sun_seen[k] for k in keys]
        vs, fs, cs, fv, surf, fa, sa = [], [], [], [], [], [], []
        n = 0
        for (q, a, M), V in zip(shown, vis):
            local, a_faces, a_colors, ranges = self._actor_mesh(q, a)
            if len(local):
                v = local @ M[:3, :3].T + M[:3, 3]
                if a.animated:      # limbs and wheels in their pose at this time
                    for (mi, _, part), W in zip(a.animated, self.actors.part_transforms(q, t)):
                        v[ranges[mi]:ranges[mi + 1]] = part @ W[:3, :3].T + W[:3, 3]
                vs.append(v)
                fs.append(a_faces + n)
                cs.append(a_colors)
                fv.append(np.full(len(a_faces), V))
                fa.append(np.full(len(a_faces), q, np.int64))
                n += len(v)
            if a.surfels is not None:
                f = transform_surfels(a.surfels, M)
                k = light.factor(f.normals().astype(np.float64), V)
                rgb = np.maximum(0.5 + SH_C0 * f.sh[:, 0, :], 0.0) * k
                sh = f.sh * k[:, None, :]
                sh[:, 0, :] = (rgb - 0.5) / SH_C0
                surf.append(SurfelField(f.positions, f.orientations, f.scales, f.opacities, sh,
                                        f.semantic_ids, f.semantic_classes))
                sa.append(np.full(f.n, q, np.int64))
        empty = ActorFrame.empty()
        verts, faces, colors = empty.vertices, empty.faces, empty.colors
        if vs:
            # every face's normal and light factor in one pass
            verts, faces = np.concatenate(vs), np.concatenate(fs)
            tri = verts[faces]
            nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            colors = np.concatenate(cs) * light.factor(nrm, np.concatenate(fv))
        return ActorFrame(verts, faces, colors.astype(np.float32),
                          SurfelField.concat(surf, drop_mismatched_semantics=True) if surf else None,
                          np.concatenate(fa) if fa else empty.face_actor,
                          np.concatenate(sa) if sa else empty.surfel_actor)
