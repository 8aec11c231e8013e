"""Actor assets: separate USD files referenced into a scene, never copied into it.

An asset file holds one model under its defaultPrim (Z up, metres, origin on the
ground at the centre of the footprint, +X forward), with an authored
``extentsHint``, the semantic label ``vehicle`` (UsdSemantics ``LabelsAPI``
instance ``class``, as the proxy meshes) and our attributes

    lsd3d:actor:kind        token   car | van | truck | bus | user
    lsd3d:actor:dimensions  float3  length, width, height (m)

The procedural library (car, van, truck, bus) is a few closed prisms per
vehicle: ``Body`` (paint), ``Cabin`` (glass) and ``Wheels``. The paint is a constant
``primvars:displayColor`` on the asset's root, inherited by every mesh below it that has no
displayColor of its own (the Body); an actor's per-instance colour is the same primvar on its
reference root, stronger than the asset's, so it fits any asset whatever its prim names
(``set_paint``; the actors layer also binds a material of it, actors.usdio). A user asset
is any USD file with a
defaultPrim (meshes and/or ParticleField surfels), or a 3DGS/2DGS .ply that
``ply_to_asset`` converts to a surfel asset in our schema.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdSemantics, UsdShade, Vt

import lsd3d_usd  # noqa: F401  (schema registration before any stage)
from lsd3d_usd import semantics
from lsd3d_usd.errors import InputError
from lsd3d_usd.proxy.shapes import cylinder, profile_prism
from lsd3d_usd.scene import provenance, save_stage
from lsd3d_usd.splats.ply import read_ply
from lsd3d_usd.splats.usdio import is_particle_field, write_surfels

# 2: the paint as an inherited constant primvar on the root and a material bound to it, the
# other parts with materials of their own (1: a displayColor on Body)
ASSET_VERSION = 2
KIND_ATTR = "lsd3d:actor:kind"
DIMS_ATTR = "lsd3d:actor:dimensions"
VEHICLE_CLASS = "vehicle"
LIBRARY_KINDS = ("car", "van", "truck", "bus")

GLASS = (0.04, 0.05, 0.06)
TYRE = (0.03, 0.03, 0.03)
# Linear paint colours drawn per instance (white, silver, black, red, blue, ...).
PAINTS = np.array([(0.80, 0.80, 0.78), (0.45, 0.46, 0.48), (0.03, 0.03, 0.035),
                   (0.55, 0.04, 0.03), (0.04, 0.12, 0.40), (0.20, 0.22, 0.25),
                   (0.60, 0.50, 0.25), (0.08, 0.25, 0.10)], dtype=np.float32)


@dataclass(frozen=True)
class VehicleSpec:
    """Side profiles (x forward, z up) of the lower hull and the cabin, widths, wheels."""
    hull: tuple
    cabin: tuple
    width: float
    wheel_radius: float
    axles: tuple          # x of the axles
    paint: tuple
    cabin_color: tuple = GLASS


SPECS: dict[str, VehicleSpec] = {
    "car": VehicleSpec(
        hull=((-2.25, 0.28), (2.25, 0.28), (2.30, 0.72), (1.90, 0.90), (-2.20, 0.95)),
        cabin=((1.25, 0.90), (0.45, 1.42), (-1.20, 1.42), (-1.95, 0.95)),
        width=1.80, wheel_radius=0.33, axles=(1.40, -1.35), paint=(0.55, 0.04, 0.03)),
    "van": VehicleSpec(
        hull=((-2.60, 0.30), (2.60, 0.30), (2.65, 0.95), (2.20, 1.05), (-2.55, 1.10)),
        cabin=((2.20, 1.05), (1.75, 1.90), (-2.55, 1.95), (-2.55, 1.10)),
        width=2.00, wheel_radius=0.36, axles=(1.75, -1.70), paint=(0.80, 0.80, 0.78)),
    "truck": VehicleSpec(
        hull=((-4.00, 0.40), (4.00, 0.40), (4.05, 1.20), (-4.00, 1.20)),
        cabin=((4.05, 1.20), (4.00, 2.95), (-4.00, 3.00), (-4.00, 1.20)),
        width=2.40, wheel_radius=0.50, axles=(2.80, -1.80, -3.00), paint=(0.60, 0.50, 0.25),
        cabin_color=(0.70, 0.70, 0.68)),   # a cargo box, not glass
    "bus": VehicleSpec(
        hull=((-5.90, 0.35), (5.90, 0.35), (6.00, 1.15), (-5.95, 1.15)),
        cabin=((6.00, 1.15), (5.95, 3.05), (-5.90, 3.10), (-5.95, 1.15)),
        width=2.50, wheel_radius=0.50, axles=(4.10, -3.60), paint=(0.04, 0.12, 0.40)),
}


@dataclass
class MeshData:
    """One mesh of an asset in the asset's frame (or world, once placed)."""
    name: str
    vertices: np.ndarray           # (V,3) float64
    faces: np.ndarray              # (F,3) int32
    colors: np.ndarray             # (F,3) float32 linear albedo per face


@dataclass
class AssetInfo:
    """What a renderer or placer needs to know about an asset file."""
    path: Path
    prim_name: str
    kind: str
    dimensions: np.ndarray         # (3,) length, width, height
    meshes: list[MeshData] = field(default_factory=list)
    has_surfels: bool = False
    label: str = VEHICLE_CLASS     # its UsdSemantics class (vehicle, pedestrian, cyclist, ...)
    # the asset declares its paint as a constant displayColor on its root (inherited by the
    # parts without a colour of their own): an actor's paint replaces only that
    paint_slot: bool = False


# ------------------------------------------------------------------ geometry
def _profile_solid(profile, width: float):
    return profile_prism(np.asarray(profile, np.float64), width)


def _wheels(spec: VehicleSpec):
    vs, fs, n = [], [], 0
    r, tw = spec.wheel_radius, 0.24
    for x in spec.axles:
        for side in (-1.0, 1.0):
            # A cylinder along z, turned so its axis is y: (x, y, z) <- (x, z, -y) keeps it right-handed.
            v, f = cylinder(r, -tw / 2, tw / 2, segments=12)
            v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
            v += np.array([x, side * (spec.width / 2 - tw / 2 + 0.02), r])
            vs.append(v)
            fs.append(f + n)
            n += len(v)
    return np.concatenate(vs), np.concatenate(fs).astype(np.int32)


def vehicle_meshes(kind: str) -> list[MeshData]:
    """The meshes of a procedural vehicle (asset frame: ground at z=0, +X forward)."""
    if kind not in SPECS:
        raise InputError(f"unknown vehicle kind {kind!r}; choose from {', '.join(LIBRARY_KINDS)}")
    s = SPECS[kind]
    hv, hf = _profile_solid(s.hull, s.width)
    cv, cf = _profile_solid(s.cabin, s.width - 0.12)
    wv, wf = _wheels(s)
    col = lambda c, f: np.tile(np.asarray(c, np.float32), (len(f), 1))  # noqa: E731
    return [MeshData("Body", hv, hf, col(s.paint, hf)),
            MeshData("Cabin", cv, cf, col(s.cabin_color, cf)),
            MeshData("Wheels", wv, wf, col(TYRE, wf))]


def dimensions_of(meshes: list[MeshData]) -> np.ndarray:
    v = np.concatenate([m.vertices for m in meshes])
    lo, hi = v.min(0), v.max(0)
    return np.array([hi[0] - lo[0], hi[1] - lo[1], hi[2]], np.float64)


# ------------------------------------------------------------------ writing
def _prim_name(kind: str) -> str:
    return kind[:1].upper() + kind[1:]


def _label(prim, cls: str = VEHICLE_CLASS) -> None:
    UsdSemantics.LabelsAPI.Apply(prim, "class").CreateLabelsAttr(Vt.TokenArray([cls]))


def _root_attrs(prim, kind: str, dims, cls: str = VEHICLE_CLASS) -> None:
    prim.CreateAttribute(KIND_ATTR, Sdf.ValueTypeNames.Token, variability=Sdf.VariabilityUniform).Set(kind)
    prim.CreateAttribute(DIMS_ATTR, Sdf.ValueTypeNames.Float3, variability=Sdf.VariabilityUniform).Set(
        Gf.Vec3f(*map(float, dims)))
    _label(prim, cls)


def _new_asset_stage(name: str, kind: str):
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, f"/{name}")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    return stage, root


def author_mesh(stage, path: str, m: MeshData, cls: str = VEHICLE_CLASS, colour: bool = True):
    """A Mesh prim of ``m`` labelled ``cls``; ``colour=False`` leaves its displayColor
    unauthored (it inherits the paint of an ancestor)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    pts = np.ascontiguousarray(m.vertices, np.float32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(m.faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(m.faces.reshape(-1), np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(0), pts.max(0)])))
    cols = np.ascontiguousarray(m.colors, np.float32)
    if not colour:
        pass
    elif np.all(cols == cols[:1]):
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray.FromNumpy(cols[:1]))
    else:
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform).Set(Vt.Vec3fArray.FromNumpy(cols))
    _label(mesh.GetPrim(), cls)
    return mesh


def write_vehicle_asset(kind: str, path) -> Path:
    """Write the procedural vehicle ``kind`` as a standalone asset file (atomic)."""

    meshes = vehicle_meshes(kind)
    name = _prim_name(kind)
    stage, root = _new_asset_stage(name, kind)
    for m in meshes:
        mesh = author_mesh(stage, f"/{name}/{m.name}", m, colour=m.name != "Body")
        if m.name != "Body":   # for renderers that shade by material (Blender, RTX)
            bind_preview_material(mesh.GetPrim(), f"/{name}/Materials/{m.name}", m.colors[0])
    set_paint(root.GetPrim(), SPECS[kind].paint)   # inherited by Body
    bind_preview_material(root.GetPrim(), f"/{name}/Materials/Paint", SPECS[kind].paint)
    dims = dimensions_of(meshes)
    _root_attrs(root.GetPrim(), kind, dims)
    v = np.concatenate([m.vertices for m in meshes])
    UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint([tuple(v.min(0)), tuple(v.max(0))])
    stage.GetRootLayer().documentation = f"lsd3d-usd procedural {kind} (Z up, metres, +X forward)"
    return save_stage(stage, path, provenance("actor-asset", {"kind": kind},
                                              assetVersion=ASSET_VERSION))


def set_paint(prim, rgb) -> None:
    """A constant displayColor primvar on ``prim``: inherited by every gprim below it that has
    none of its own (UsdGeomPrimvarsAPI inheritance, as Hydra renders it)."""
    UsdGeom.PrimvarsAPI(prim).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                                            UsdGeom.Tokens.constant).Set(
        Vt.Vec3fArray([Gf.Vec3f(*map(float, rgb))]))


def bind_preview_material(prim, path: str, rgb, strength=UsdShade.Tokens.weakerThanDescendants):
    """Define a UsdPreviewSurface material of diffuse colour ``rgb`` at ``path`` and bind it to
    ``prim`` (with ``strength`` over the bindings of its descendants)."""
    stage = prim.GetStage()
    mat = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, rgb)))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.5)
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat, strength)
    return mat


def library_asset_current(path) -> bool:
    """Whether a procedural library asset file was written by this asset version (older
    ones are rewritten: their paint sat on a prim named Body)."""
    if not Path(path).is_file():
        return False
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path), metadataOnly=True)
    except Exception:   # Tf errors for a corrupt file: rewrite it
        return False
    prov = layer.customLayerData.get("lsd3d", {}) if layer else {}
    return prov.get("assetVersion") == ASSET_VERSION


def ensure_library(folder) -> list[str]:
    """Write the procedural vehicles into ``folder`` where missing or of an older asset
    version; returns the kinds written."""
    folder = Path(folder)
    stale = [k for k in LIBRARY_KINDS if not library_asset_current(folder / f"{k}.usda")]
    if stale:
        write_library(folder, stale)
    return stale


def write_library(folder, kinds=LIBRARY_KINDS, fmt: str = "usda") -> dict[str, Path]:
    """Write the procedural vehicles to ``folder/<kind>.<fmt>``; returns kind -> path."""
    folder = Path(folder)
    return {k: write_vehicle_asset(k, folder / f"{k}.{fmt}") for k in kinds}


def ply_to_asset(ply_path, out_path, kind: str = "user", semantic: str = VEHICLE_CLASS) -> Path:
    """Convert a 3DGS/2DGS .ply into a surfel asset (our Lsd3dSurfelField schema), atomic.

    The splats are taken as given: Z up, metres, +X forward, origin on the ground."""

    field_ = read_ply(ply_path)
    if field_.n == 0:
        raise InputError(f"{ply_path}: no splats in the file")
    field_ = replace(field_, semantic_ids=np.full(field_.n, semantics.class_id(semantic), np.int32),
                     semantic_classes=tuple(semantics.CLASSES))
    name = "Asset"
    stage, root = _new_asset_stage(name, kind)
    write_surfels(stage, f"/{name}/Surfels", field_)
    lo, hi = field_.extent()
    dims = np.array([hi[0] - lo[0], hi[1] - lo[1], hi[2]])
    _root_attrs(root.GetPrim(), kind, dims)
    UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint([tuple(lo), tuple(hi)])
    return save_stage(stage, out_path, provenance("actor-asset", {"source": str(ply_path)}))


# ------------------------------------------------------------------ reading / validation
def relative_asset_path(asset, layer_dir) -> str:
    """``asset`` relative to the folder of the layer that references it ('./x' or '../x')."""
    rel = os.path.relpath(Path(asset).absolute(), Path(layer_dir).absolute()).replace(os.sep, "/")
    return rel if rel.startswith("../") else f"./{rel}"


def check_asset(path) -> Path:
    """The asset file, validated: exists, opens as USD, has a defaultPrim. InputError otherwise."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"actor asset {path}: no such file")
    try:
        layer = Sdf.Layer.FindOrOpen(str(p.absolute()))
    except Exception as e:  # Tf errors for corrupt files
        raise InputError(f"actor asset {path}: cannot be read as USD ({' '.join(str(e).split())[:200]})") from None
    if layer is None:
        raise InputError(f"actor asset {path}: cannot be read as USD")
    if not layer.defaultPrim:
        raise InputError(f"actor asset {path}: no defaultPrim (a referenced asset needs one)")
    return p.absolute()


def mesh_data_from_prim(prim, M: np.ndarray | None = None) -> MeshData:
    """A UsdGeom.Mesh (triangulated fans for n-gons) with per-face displayColor,
    transformed by the 4x4 column-vector matrix ``M`` if given."""
    mesh = UsdGeom.Mesh(prim)
    pts = np.asarray(mesh.GetPointsAttr().Get() or [], np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
    if counts.sum() != len(idx) or (len(idx) and (idx.min() < 0 or idx.max() >= len(pts))):
        raise InputError(f"{prim.GetPath()}: inconsistent mesh topology")
    tris, owner = [], []
    start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    for k in np.unique(counts):
        if k < 3:
            continue
        sel = np.flatnonzero(counts == k)
        base = start[sel]
        for j in range(1, k - 1):  # fan
            tris.append(np.stack([idx[base], idx[base + j], idx[base + j + 1]], 1))
            owner.append(sel)
    faces = np.concatenate(tris).astype(np.int32) if tris else np.zeros((0, 3), np.int32)
    owner = np.concatenate(owner) if owner else np.zeros(0, np.int64)
    cols, interp = mesh_colour(prim)
    if interp == "uniform" and len(cols) == len(counts):
        face_cols = cols[owner]
    elif interp in ("vertex", "varying") and len(cols) == len(pts):
        face_cols = cols[faces].mean(1)
    else:
        face_cols = np.tile(cols[:1], (len(faces), 1))
    if M is not None:
        pts = pts @ M[:3, :3].T + M[:3, 3]
        if np.linalg.det(M[:3, :3]) < 0:
            faces = faces[:, ::-1].copy()
    return MeshData(prim.GetName(), pts, faces, face_cols.astype(np.float32))


def material_colour(prim) -> np.ndarray | None:
    """diffuseColor of the UsdPreviewSurface of the material bound to ``prim`` (its input's
    value; a texture connection is not sampled), or None."""
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if not material:
        return None
    shader = material.ComputeSurfaceSource()[0]
    if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
        return None
    inp = shader.GetInput("diffuseColor")
    value = inp.Get() if inp else None
    if value is None and inp:
        src = inp.GetValueProducingAttributes()
        value = src[0].Get() if src else None
    return None if value is None else np.asarray(value, np.float32).reshape(1, 3)


def mesh_colour(prim) -> tuple[np.ndarray, str]:
    """(colours, interpolation) of a gprim, as a USD renderer resolves them: its own
    displayColor; else a constant displayColor inherited from an ancestor (an actor's
    per-instance paint on its reference root, an asset's paint on its root); else the
    diffuseColor of its bound UsdPreviewSurface; else grey 0.5."""
    api = UsdGeom.PrimvarsAPI(prim)
    pv = api.FindPrimvarWithInheritance(UsdGeom.Tokens.primvarsDisplayColor)
    if pv and pv.HasValue():
        cols = np.asarray(pv.ComputeFlattened(), np.float32).reshape(-1, 3)
        own = pv.GetAttr().GetPrim() == prim
        if len(cols):
            return cols, pv.GetInterpolation() if own else UsdGeom.Tokens.constant
    mat = material_colour(prim)
    if mat is not None:
        return mat, UsdGeom.Tokens.constant
    return np.full((1, 3), 0.5, np.float32), UsdGeom.Tokens.constant


def read_asset(path) -> AssetInfo:
    """Open an asset file and describe it (kind, dimensions, meshes in the asset frame)."""

    p = check_asset(path)
    stage = Usd.Stage.Open(str(p))
    root = stage.GetDefaultPrim()
    if not root or not root.IsValid():
        raise InputError(f"actor asset {path}: its defaultPrim does not exist")
    cache = UsdGeom.XformCache()
    Minv = np.linalg.inv(np.array(cache.GetLocalToWorldTransform(root), np.float64).T)
    meshes, surfels = [], False
    for prim in Usd.PrimRange(root):
        if prim.IsA(UsdGeom.Mesh):
            M = Minv @ np.array(cache.GetLocalToWorldTransform(prim), np.float64).T
            meshes.append(mesh_data_from_prim(prim, M))
        elif is_particle_field(prim):
            surfels = True
    if not meshes and not surfels:
        raise InputError(f"actor asset {path}: no Mesh or ParticleField under {root.GetPath()}")
    kind_attr = root.GetAttribute(KIND_ATTR)
    kind = str(kind_attr.Get()) if kind_attr and kind_attr.HasValue() else "user"
    dims_attr = root.GetAttribute(DIMS_ATTR)
    if dims_attr and dims_attr.HasValue():
        dims = np.array(dims_attr.Get(), np.float64)
    else:
        bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"]).ComputeLocalBound(root)
        r = bbox.ComputeAlignedRange()
        if r.IsEmpty():
            raise InputError(f"actor asset {path}: cannot compute its size (no extent); "
                             f"author {DIMS_ATTR} on {root.GetPath()}")
        lo, hi = np.array(r.GetMin()), np.array(r.GetMax())
        dims = np.array([hi[0] - lo[0], hi[1] - lo[1], hi[2]])
    pv = UsdGeom.PrimvarsAPI(root).GetPrimvar(UsdGeom.Tokens.primvarsDisplayColor)
    slot = bool(pv and pv.HasAuthoredValue() and pv.GetInterpolation() == UsdGeom.Tokens.constant)
    return AssetInfo(p, root.GetName(), kind, dims, meshes, surfels, label=asset_label(root),
                     paint_slot=slot)


def asset_label(root) -> str:
    """The class of an asset: the UsdSemantics ``class`` label on its root prim (or the
    first prim below with one), "vehicle" when none is authored."""
    for p in Usd.PrimRange(root):
        api = UsdSemantics.LabelsAPI(p, "class")
        attr = api.GetLabelsAttr() if api else None
        labels = attr.Get() if attr and attr.HasValue() else None
        if labels:
            return str(labels[0])
    return VEHICLE_CLASS


def library_assets(folder) -> dict[str, Path]:
    """kind -> asset file of a library folder (``<kind>.usd[a|c]``), validated."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"--assets {folder}: no such folder")
    out = {}
    for f in sorted(folder.iterdir()):
        if f.suffix in (".usda", ".usdc", ".usd") and not f.name.startswith("."):
            out.setdefault(f.stem, check_asset(f))
    if not out:
        raise InputError(f"--assets {folder}: no .usda/.usdc/.usd asset files in the folder")
    return out
