"""SurfelField ↔ USD ParticleField prims (our Lsd3dSurfelField, and official fields).

Writes use Vt *FromNumpy (one memcpy per attribute); reads wrap the VtArrays
with numpy views, which for .usdc files are backed by the memory-mapped crate.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdVol, Vt

import lsd3d_usd
from lsd3d_usd import scene
from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import USDA_PARTICLES
from lsd3d_usd.scene import author_fallback_prim_types
from lsd3d_usd.splats.field import (
    SurfelField,
    flatten_3d_gaussians,
    kernel_bounds,
    sh_coeff_count,
)
from lsd3d_usd.splats.preview import DEFAULT_FRACTION, write_preview

SH_DEGREE_ATTR = "radiance:sphericalHarmonicsDegree"
SH_COEFFS_ATTR = "radiance:sphericalHarmonicsCoefficients"
SEM_IDS_ATTR = "lsd3d:semanticIds"
SEM_CLASSES_ATTR = "lsd3d:semanticClasses"

# SurfelField field name → what it authors; the keys are what `attributes=` accepts.
FIELD_ATTRS = ("positions", "orientations", "scales", "opacities", "sh", "semantic_ids")


def is_particle_field(prim: Usd.Prim) -> bool:
    return prim.IsA(UsdVol.ParticleField)


def is_surflet(prim: Usd.Prim) -> bool:
    """Whether the prim's kernel is a 2D disk (surflet): its third scale is not an axis."""
    return (prim.HasAPI("ParticleFieldKernelGaussianSurfletAPI")
            or prim.HasAPI("ParticleFieldKernelConstantSurfletAPI"))


def particle_bounds(prim: Usd.Prim, time: Usd.TimeCode = Usd.TimeCode.Default()) -> np.ndarray | None:
    """(2,3) bounds of the prim's kernels (field.kernel_bounds on its own arrays: a 3D
    Gaussian keeps its third axis), or None without particles or with arrays that do not
    fit the positions (validate names those)."""

    pos = _get(prim, "positions", time)
    if pos is None or pos.size == 0 or pos.size % 3:
        return None
    pos = pos.reshape(-1, 3).astype(np.float64)
    n = len(pos)
    quat = _get(prim, "orientations", time)
    scales = _get(prim, "scales", time)
    quat = np.tile([0.0, 0, 0, 1], (n, 1)) if quat is None else quat.astype(np.float64)
    scales = np.ones((n, 3)) if scales is None else scales.astype(np.float64)
    if quat.size != 4 * n or scales.size != 3 * n:
        return None
    quat = quat.reshape(n, 4)
    ok = np.isfinite(quat).all(axis=1) & (np.linalg.norm(np.nan_to_num(quat), axis=1) > 0)
    quat = np.where(ok[:, None], quat, [0.0, 0, 0, 1])
    with np.errstate(invalid="ignore", over="ignore"):
        return kernel_bounds(pos, quat, scales.reshape(n, 3), surflet=is_surflet(prim))


def surfel_prims(stage: Usd.Stage, root: str = "/") -> list[Usd.Prim]:
    """Every ParticleField prim (ours or official) under `root` (loaded prims only)."""
    start = stage.GetPrimAtPath(root) if root != "/" else stage.GetPseudoRoot()
    if not start:
        return []
    return [p for p in Usd.PrimRange(start) if is_particle_field(p)]


def _scales3(scales2: np.ndarray) -> np.ndarray:
    out = np.zeros((len(scales2), 3), np.float32)
    out[:, :2] = scales2
    return out


def write_surfels(stage: Usd.Stage, path: str, field: SurfelField, *, over: bool = False,
                  attributes: tuple[str, ...] | None = None,
                  time: Usd.TimeCode = Usd.TimeCode.Default()) -> Usd.Prim:
    """Author `field` on an Lsd3dSurfelField prim at `path`.

    over=True authors an `over` (for edit layers such as GGDS runs) and only the
    `attributes` named (subset of FIELD_ATTRS); extent is re-authored whenever
    geometry changes. Raises InputError when the field is invalid.
    """
    problems = field.problems()
    if problems:
        raise InputError(f"{path}: refusing to write invalid surfels: " + "; ".join(problems))
    attributes = tuple(attributes or FIELD_ATTRS)
    unknown = set(attributes) - set(FIELD_ATTRS)
    if unknown:
        raise ValueError(f"unknown surfel attributes {sorted(unknown)}; known: {FIELD_ATTRS}")
    prim = stage.OverridePrim(path) if over else stage.DefinePrim(path, lsd3d_usd.SURFEL_TYPE)
    if not over:
        if prim.GetTypeName() != lsd3d_usd.SURFEL_TYPE:
            raise InputError(f"{path}: exists with type {prim.GetTypeName()!r}, not {lsd3d_usd.SURFEL_TYPE}")
        # readers without our plugin: the official APIs explicitly, and ParticleField as the
        # fallback type in the layer (read when it is the root layer of the stage opened)
        prim.SetMetadata("apiSchemas", Sdf.TokenListOp.Create(
            prependedItems=list(lsd3d_usd.SURFEL_API_SCHEMAS)))
        author_fallback_prim_types(stage.GetEditTarget().GetLayer())
    T = Sdf.ValueTypeNames

    def put(name, type_name, value, uniform=False):
        attr = prim.GetAttribute(name)
        if not attr:
            attr = prim.CreateAttribute(name, type_name, custom=False,
                                        variability=Sdf.VariabilityUniform if uniform
                                        else Sdf.VariabilityVarying)
        attr.Set(value, Usd.TimeCode.Default() if uniform else time)

    if "positions" in attributes:
        put("positions", T.Point3fArray, Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(field.positions)))
    if "orientations" in attributes:
        put("orientations", T.QuatfArray, Vt.QuatfArray.FromNumpy(np.ascontiguousarray(field.orientations)))
    if "scales" in attributes:
        put("scales", T.Float3Array, Vt.Vec3fArray.FromNumpy(_scales3(field.scales)))
    if "opacities" in attributes:
        put("opacities", T.FloatArray, Vt.FloatArray.FromNumpy(np.ascontiguousarray(field.opacities)))
    if "sh" in attributes:
        put(SH_DEGREE_ATTR, T.Int, field.sh_degree, uniform=True)
        put(SH_COEFFS_ATTR, T.Float3Array,
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(field.sh.reshape(-1, 3))))
    if "semantic_ids" in attributes and field.semantic_ids is not None:
        put(SEM_IDS_ATTR, T.IntArray, Vt.IntArray.FromNumpy(np.ascontiguousarray(field.semantic_ids)))
        if field.semantic_classes:
            put(SEM_CLASSES_ATTR, T.TokenArray, Vt.TokenArray(list(field.semantic_classes)), uniform=True)
    if {"positions", "orientations", "scales"} & set(attributes):
        ext = field.extent().astype(np.float32)
        put("extent", T.Float3Array, Vt.Vec3fArray.FromNumpy(ext))
    return prim


def _get(prim: Usd.Prim, name: str, time) -> np.ndarray | None:
    """numpy view of an attribute, preferring float over the half-precision variant."""
    for n in (name, name + "h"):
        attr = prim.GetAttribute(n)
        if attr and attr.HasValue():
            value = attr.Get(time)
            if value is not None:
                arr = np.asarray(value)
                return arr.astype(np.float32) if arr.dtype == np.float16 else arr
    return None


def read_surfels(prim: Usd.Prim, time: Usd.TimeCode = Usd.TimeCode.Default()) -> SurfelField:
    """Read any ParticleField prim into a SurfelField.

    Official 3D Gaussian splats are flattened to surfels (two largest axes kept).
    Missing optional attributes take the schema's fallbacks (no rotation, unit
    scale, opaque, DC colour 0.5). Inconsistent lengths raise InputError.
    """
    path = prim.GetPath()
    if not is_particle_field(prim):
        raise InputError(f"{path}: not a ParticleField prim (type {prim.GetTypeName()!r})")
    pos = _get(prim, "positions", time)
    if pos is None:
        pos = np.zeros((0, 3), np.float32)
    n = len(pos)

    def sized(name, arr, width):
        if arr is None:
            return None
        arr = arr.reshape(-1, width) if width else arr.reshape(-1)
        if len(arr) != n:
            raise InputError(f"{path}.{name}: {len(arr)} values for {n} positions")
        return arr

    quat = sized("orientations", _get(prim, "orientations", time), 4)
    scales = sized("scales", _get(prim, "scales", time), 3)
    opac = sized("opacities", _get(prim, "opacities", time), None)
    if quat is None:
        quat = np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1))
    if scales is None:
        scales = np.ones((n, 3), np.float32)
    if opac is None:
        opac = np.ones(n, np.float32)
    deg_attr = prim.GetAttribute(SH_DEGREE_ATTR)
    deg = int(deg_attr.Get()) if deg_attr and deg_attr.Get() is not None else 0
    coeffs = _get(prim, SH_COEFFS_ATTR, time)
    if coeffs is None:
        deg, sh = 0, np.zeros((n, 1, 3), np.float32)
    else:
        k = sh_coeff_count(deg)
        if coeffs.size != n * k * 3:
            raise InputError(f"{path}.{SH_COEFFS_ATTR}: {coeffs.size // 3} coefficients for {n} "
                             f"particles at degree {deg} (expected {n * k})")
        sh = coeffs.reshape(n, k, 3)
    if prim.HasAPI("ParticleFieldKernelGaussianEllipsoidAPI"):
        quat, scales2 = flatten_3d_gaussians(quat, scales)
    else:
        scales2 = scales[:, :2]
    sem = prim.GetAttribute(SEM_IDS_ATTR)
    sem_ids = sized(SEM_IDS_ATTR, np.asarray(sem.Get(time)), None) if sem and sem.HasValue() else None
    classes_attr = prim.GetAttribute(SEM_CLASSES_ATTR)
    classes = tuple(classes_attr.Get() or ()) if classes_attr and classes_attr.HasValue() else ()
    return SurfelField(pos, quat, scales2, opac, sh, sem_ids, classes)


def check_bulk_target(path, n: int) -> None:
    """Bulk data belongs in crate files: refuse a text (.usda) output for more than
    limits.USDA_PARTICLES particles, before anything is written (validate would report
    BulkDataInUsda on the result)."""

    if Path(str(path)).suffix.lower() == ".usda" and not USDA_PARTICLES.ok(n):
        raise InputError(f"{path}: {n} particles exceed the limit of {USDA_PARTICLES.value} "
                         "for a text .usda layer (bulk data belongs in crate files); "
                         "write .usdc (or .usd)")


def preview_path_for(prim_path: str) -> str:
    """Where the Points preview of the surfel prim at ``prim_path`` goes: beside the scene's
    chunk previews for a prim directly under /World (/World/SurfelPreview/<name>), else a
    sibling ``<path>_Preview``."""
    p = Sdf.Path(prim_path)
    if str(p.GetParentPath()) == scene.WORLD:
        return f"{scene.SURFEL_PREVIEW_PATH}/{p.name}"
    return f"{prim_path}_Preview"


def write_surfels_with_preview(stage: Usd.Stage, prim_path: str, field: SurfelField,
                               preview_fraction: float = DEFAULT_FRACTION) -> Usd.Prim:
    """write_surfels, plus (fraction > 0) the Points preview for USD tools without
    ParticleField (splats.preview): the surfel prim gets purpose render and names the
    preview, purpose proxy, as its proxyPrim."""
    prim = write_surfels(stage, prim_path, field)
    if write_preview(stage, preview_path_for(prim_path), field, preview_fraction):
        img = UsdGeom.Imageable(prim)
        img.CreatePurposeAttr(UsdGeom.Tokens.render)
        img.CreateProxyPrimRel().SetTargets([Sdf.Path(preview_path_for(prim_path))])
    return prim


def write_surfel_file(path: str, field: SurfelField, prim_path: str = "/World/Surfels",
                      provenance: dict | None = None,
                      preview_fraction: float = DEFAULT_FRACTION) -> None:
    """Write a stand-alone surfel layer (Z up, metres, defaultPrim /World) with its Points
    preview (``preview_fraction``, 0 = none), atomically. A .usda path is refused above
    limits.USDA_PARTICLES particles (check_bulk_target)."""

    check_bulk_target(path, field.n)
    stage = scene.new_stage()
    write_surfels_with_preview(stage, prim_path, field, preview_fraction)
    scene.save_stage(stage, path, provenance)


def read_surfel_file(path: str, prim_path: str | None = None) -> SurfelField:
    """Read the surfel prim at `prim_path` (default: the only/first ParticleField) of a file."""

    stage = scene.open_stage(path)
    if prim_path:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim:
            raise InputError(f"{path}: no prim at {prim_path}")
        return read_surfels(prim)
    prims = surfel_prims(stage)
    if not prims:
        raise InputError(f"{path}: no ParticleField prim")
    return read_surfels(prims[0])
