"""The actors layer (``layers/actors.usda``) and reading placed actors back for rendering.

Layer content (authored with Sdf, so nothing needs to resolve while writing)::

    /World/Actors                 Xform, lsd3d:actors:seed / fps / seconds
      Parked/<Kind>_<k>           Xform, references = @<asset, relative to the layer>@
                                  xformOp:translate + xformOp:rotateZ (degrees), static
      Moving/<Kind>_<k>           the same, both ops time-sampled (one sample per traffic
                                  step at the scene's timeCodesPerSecond), plus
                                  lsd3d:actor:speed (m/s) samples; primvars:displayColor
                                  (constant) = per-instance paint, inherited by every mesh
                                  of the asset that has no displayColor of its own; the
                                  same paint as a material bound here (PAINT_MATERIAL):
        lsd3dPaint                Material (UsdPreviewSurface), for renderers that shade by
                                  material; bound weakerThanDescendants when the asset has a
                                  paint slot (parts with materials of their own keep them),
                                  strongerThanDescendants otherwise (the whole asset painted,
                                  as the inherited displayColor paints it)

The asset files stay where they are (a library folder); the layer only points at them.
Every actor prim carries ``lsd3d:actor:role`` (parked | moving | ego) and
``lsd3d:actor:asset`` (the path as given, for error messages).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

import lsd3d_usd  # noqa: F401
from lsd3d_usd.actors.assets import DIMS_ATTR, KIND_ATTR, asset_label, mesh_data_from_prim
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import ACTORS_PATH, new_stage, save_layer
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.splats.init import transform_surfels
from lsd3d_usd.splats.usdio import is_particle_field, read_surfels

PAINT_MATERIAL = "lsd3dPaint"
ROLE_ATTR = "lsd3d:actor:role"
ASSET_ATTR = "lsd3d:actor:asset"
SPEED_ATTR = "lsd3d:actor:speed"
DEFAULT_TCPS = 24.0


# ------------------------------------------------------------------ writing
@dataclass
class ActorSpec:
    """One actor to author: name, role, asset reference (relative string), paint colour
    (or None) and its transform: static (position, yaw) or sampled (times, positions, yaws)."""
    name: str
    role: str
    asset: str
    position: np.ndarray                      # (3,) or (n,3)
    yaw: np.ndarray | float                   # radians, scalar or (n,)
    times: np.ndarray | None = None           # seconds (n,) when time-sampled
    speed: np.ndarray | None = None
    paint: tuple | None = None
    extra: dict = field(default_factory=dict)
    colors: dict = field(default_factory=dict)   # part path under the actor -> displayColor over
    joints: dict = field(default_factory=dict)   # joint Xform path -> rotateY degrees (per time)
    group: str | None = None                     # /World/Actors/<group>; default from the role
    paint_slot: bool = True     # the asset declares a paint slot (assets.AssetInfo.paint_slot)


def _spec_attr(prim_spec, name: str, type_name, value=None, uniform=False, custom=True):
    a = Sdf.AttributeSpec(prim_spec, name, type_name,
                          Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying, custom)
    if value is not None:
        a.default = value
    return a


def author_actor(layer, parent_path: str, a: ActorSpec, tcps: float):
    """Author one actor prim spec under ``parent_path`` in ``layer`` (Sdf level)."""
    T = Sdf.ValueTypeNames
    path = Sdf.Path(parent_path).AppendChild(a.name)
    spec = Sdf.CreatePrimInLayer(layer, path)
    spec.specifier = Sdf.SpecifierDef
    spec.typeName = "Xform"
    spec.referenceList.Prepend(Sdf.Reference(a.asset))
    _spec_attr(spec, ROLE_ATTR, T.Token, a.role, uniform=True)
    _spec_attr(spec, ASSET_ATTR, T.String, a.asset, uniform=True)
    for k, v in a.extra.items():
        _spec_attr(spec, f"lsd3d:actor:{k}", T.String, str(v), uniform=True)
    tr = _spec_attr(spec, "xformOp:translate", T.Double3, custom=False)
    rz = _spec_attr(spec, "xformOp:rotateZ", T.Float, custom=False)
    _spec_attr(spec, "xformOpOrder", T.TokenArray, Vt.TokenArray(["xformOp:translate", "xformOp:rotateZ"]),
               uniform=True, custom=False)
    if a.times is None:
        p = np.asarray(a.position, np.float64).reshape(3)
        tr.default = Gf.Vec3d(*map(float, p))
        rz.default = float(np.degrees(float(a.yaw)))
    else:
        P = np.asarray(a.position, np.float64).reshape(-1, 3)
        Y = np.degrees(np.asarray(a.yaw, np.float64).reshape(-1))
        sp = _spec_attr(spec, SPEED_ATTR, T.Float) if a.speed is not None else None
        for k, t in enumerate(np.asarray(a.times, np.float64)):
            code = round(float(t) * tcps, 6)  # 0.1 s * 24 must be 2.4, not 2.4000000000000004
            layer.SetTimeSample(tr.path, code, Gf.Vec3d(*map(float, P[k])))
            layer.SetTimeSample(rz.path, code, float(Y[k]))
            if sp is not None:
                layer.SetTimeSample(sp.path, code, float(a.speed[k]))
    if a.paint is not None:   # on the reference root: no asset prim name assumed
        pv = _spec_attr(spec, "primvars:displayColor", T.Color3fArray,
                        Vt.Vec3fArray([Gf.Vec3f(*map(float, a.paint))]), custom=False)
        pv.SetInfo("interpolation", "constant")
        _paint_material(layer, spec, a.paint, a.paint_slot)
    # parts of our own procedural people (compose keeps only parts the asset has)
    for part, rgb in a.colors.items():
        over = Sdf.CreatePrimInLayer(layer, path.AppendPath(Sdf.Path(part)))
        over.specifier = Sdf.SpecifierOver
        for anc in over.path.GetAncestorsRange():     # the parts between, as overs too
            if anc.HasPrefix(path) and anc != path:
                layer.GetPrimAtPath(anc).specifier = Sdf.SpecifierOver
        pv = _spec_attr(over, "primvars:displayColor", T.Color3fArray,
                        Vt.Vec3fArray([Gf.Vec3f(*map(float, rgb))]), custom=False)
        pv.SetInfo("interpolation", "constant")
    for joint, angles in a.joints.items():
        over = Sdf.CreatePrimInLayer(layer, path.AppendPath(Sdf.Path(joint)))
        over.specifier = Sdf.SpecifierOver
        rot = _spec_attr(over, "xformOp:rotateY", T.Float, custom=False)
        ang = np.asarray(angles, np.float64).reshape(-1)
        if a.times is None or len(ang) == 1:
            rot.default = float(ang[0])
        else:
            for k, t in enumerate(np.asarray(a.times, np.float64)):
                layer.SetTimeSample(rot.path, round(float(t) * tcps, 6), float(ang[k]))
    return spec


def _paint_material(layer, spec, rgb, slot: bool) -> None:
    """A UsdPreviewSurface of colour ``rgb`` defined under the actor prim ``spec`` (ours, not
    a prim of the asset) and bound to it (Sdf level)."""
    T = Sdf.ValueTypeNames
    mat = Sdf.PrimSpec(spec, PAINT_MATERIAL, Sdf.SpecifierDef, "Material")
    shader = Sdf.PrimSpec(mat, "Surface", Sdf.SpecifierDef, "Shader")
    _spec_attr(shader, "info:id", T.Token, "UsdPreviewSurface", uniform=True, custom=False)
    _spec_attr(shader, "inputs:diffuseColor", T.Color3f, Gf.Vec3f(*map(float, rgb)), custom=False)
    _spec_attr(shader, "inputs:roughness", T.Float, 0.5, custom=False)
    _spec_attr(shader, "outputs:surface", T.Token, custom=False)
    out = _spec_attr(mat, "outputs:surface", T.Token, custom=False)
    out.connectionPathList.Prepend(shader.path.AppendProperty("outputs:surface"))
    api = spec.GetInfo("apiSchemas") if spec.HasInfo("apiSchemas") else Sdf.TokenListOp()
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(
        prependedItems=list(api.prependedItems) + ["MaterialBindingAPI"]))
    rel = Sdf.RelationshipSpec(spec, "material:binding", custom=False)
    rel.targetPathList.explicitItems = [mat.path]   # replaces the asset's own binding here
    rel.SetInfo("bindMaterialAs", "weakerThanDescendants" if slot else "strongerThanDescendants")


def scene_time_codes_per_second(scene) -> float:
    """The scene root layer's timeCodesPerSecond (USD's default, 24, when unauthored)."""
    root = Sdf.Layer.FindOrOpen(str(scene.root_layer_path))
    return float(root.timeCodesPerSecond) if root.HasTimeCodesPerSecond() else DEFAULT_TCPS


def actors_layer(actors: list[ActorSpec], tcps: float, seconds: float, info: dict):
    """An anonymous layer holding /World/Actors with ``actors`` (keep a reference to it)."""

    # A detached layer: on a stage, each reference would try to resolve while we author.
    stage = new_stage()
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(stage.GetRootLayer())
    layer.timeCodesPerSecond = tcps
    layer.framesPerSecond = tcps
    layer.startTimeCode = 0.0
    layer.endTimeCode = float(seconds * tcps)
    with Sdf.ChangeBlock():
        root = Sdf.CreatePrimInLayer(layer, ACTORS_PATH)
        root.specifier = Sdf.SpecifierDef
        root.typeName = "Xform"
        for k, v in info.items():
            _spec_attr(root, f"lsd3d:actors:{k}", Sdf.ValueTypeNames.String, str(v), uniform=True)
        groups = set()
        for a in actors:
            g = a.group or {"parked": "Parked", "moving": "Moving", "ego": "Ego"}.get(a.role, "Other")
            gp = f"{ACTORS_PATH}/{g}"
            if g not in groups:
                gs = Sdf.CreatePrimInLayer(layer, gp)
                gs.specifier = Sdf.SpecifierDef
                gs.typeName = "Xform"
                groups.add(g)
            author_actor(layer, gp, a, tcps)
    return layer


def extend_root_time_range(scene, end_code: float, tcps: float) -> None:
    """Make the scene root's playback range cover [0, end_code] at ``tcps`` (usdview and
    other tools read start/endTimeCode from the root layer only)."""

    root = Sdf.Layer.FindOrOpen(str(scene.root_layer_path))
    root.Reload()
    changed = False
    if not root.HasTimeCodesPerSecond() or root.timeCodesPerSecond != tcps:
        root.timeCodesPerSecond = tcps
        root.framesPerSecond = tcps
        changed = True
    if not root.HasStartTimeCode():
        root.startTimeCode = 0.0
        changed = True
    if not root.HasEndTimeCode() or root.endTimeCode < end_code:
        root.endTimeCode = float(end_code)
        changed = True
    if changed:
        save_layer(root, scene.root_layer_path)


# ------------------------------------------------------------------ reading
def check_references(stage, root_path: str) -> None:
    """Every reference under ``root_path`` points at an existing file (InputError naming the
    actor prim, the asset path as written and the layer it was written in otherwise)."""
    start = stage.GetPrimAtPath(root_path)
    if not start:
        return
    for prim in Usd.PrimRange(start):
        for spec in prim.GetPrimStack():
            refs = spec.referenceList
            for ref in list(refs.prependedItems) + list(refs.explicitItems) + list(refs.appendedItems):
                if not ref.assetPath:
                    continue
                path = spec.layer.ComputeAbsolutePath(ref.assetPath)
                if not os.path.isfile(path):
                    raise InputError(f"{spec.layer.realPath or spec.layer.identifier}: actor {prim.GetPath()} "
                                     f"references missing asset {ref.assetPath!r} (resolved to {path})")


@dataclass
class PlacedActor:
    path: str
    role: str
    meshes: list            # MeshData in the actor-root frame
    surfels: object | None  # SurfelField in the actor-root frame, or None
    dims: np.ndarray
    kind: str = ""          # lsd3d:actor:kind (car, van, ...; "" when not authored)
    label: str = "vehicle"  # its UsdSemantics class label (semantics.CLASSES)
    # meshes moving within the actor (limbs, wheels): (index into meshes, prim path, vertices
    # in the mesh prim's own frame); `meshes` holds them in the pose of the first time
    animated: list = field(default_factory=list)


def actor_label(prim) -> str:
    """The class of an actor: the UsdSemantics ``class`` label on its root (or the first
    prim below that has one), "vehicle" when none is authored."""
    return asset_label(prim)


def _moves_within(sub, root) -> bool:
    """Does prim ``sub`` move relative to the actor ``root`` over time (an animated joint)?"""
    p = sub
    while p and p != root:
        if p.IsA(UsdGeom.Xformable) and UsdGeom.Xformable(p).TransformMightBeTimeVarying():
            return True
        p = p.GetParent()
    return False


class ActorSet:
    """The actors of a composed stage: geometry read once (in each actor's own frame);
    `transforms(t)` / `visible(t)` place and show them at time t. Stateless per call."""

    def __init__(self, stage, root_path: str | None = None):
        self.stage = stage
        root_path = root_path or ACTORS_PATH
        check_references(stage, root_path)
        self.actors: list[PlacedActor] = []
        start = stage.GetPrimAtPath(root_path)
        if not start:
            return
        t0 = Usd.TimeCode.EarliestTime()
        for prim in Usd.PrimRange(start):
            role = prim.GetAttribute(ROLE_ATTR)
            if not role or not role.HasValue():
                continue
            Minv = np.linalg.inv(self._world(prim, t0))
            meshes, fields, animated = [], [], []
            for sub in Usd.PrimRange(prim):
                if sub.IsA(UsdGeom.Mesh):
                    meshes.append(mesh_data_from_prim(sub, Minv @ self._world(sub, t0)))
                    if _moves_within(sub, prim):
                        animated.append((len(meshes) - 1, str(sub.GetPath()),
                                         mesh_data_from_prim(sub).vertices))
                elif is_particle_field(sub):
                    f = read_surfels(sub, t0)
                    if f.n:
                        fields.append(transform_surfels(f, Minv @ self._world(sub, t0)))
            surf = SurfelField.concat(fields, drop_mismatched_semantics=True) if fields else None
            da = prim.GetAttribute(DIMS_ATTR)
            dims = np.array(da.Get(), np.float64) if da and da.HasValue() else np.array([4.5, 1.8, 1.5])
            ka = prim.GetAttribute(KIND_ATTR)
            kind = str(ka.Get()) if ka and ka.HasValue() else ""
            self.actors.append(PlacedActor(str(prim.GetPath()), str(role.Get()), meshes, surf, dims,
                                           kind, actor_label(prim), animated))

    @staticmethod
    def _world(prim, t) -> np.ndarray:
        return np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), np.float64).T

    def __len__(self) -> int:
        return len(self.actors)

    def part_transforms(self, q: int, time_code) -> list[np.ndarray]:
        """World-from-mesh matrices of actor q's animated meshes (as `PlacedActor.animated`)."""
        t = Usd.TimeCode(time_code)
        return [self._world(self.stage.GetPrimAtPath(p), t) for _, p, _ in self.actors[q].animated]

    def transforms(self, time_code) -> list[np.ndarray]:
        t = Usd.TimeCode(time_code)
        return [self._world(self.stage.GetPrimAtPath(a.path), t) for a in self.actors]

    def visible(self, time_code) -> list[bool]:
        t = Usd.TimeCode(time_code)
        return [UsdGeom.Imageable(self.stage.GetPrimAtPath(a.path)).ComputeVisibility(t)
                != UsdGeom.Tokens.invisible for a in self.actors]
