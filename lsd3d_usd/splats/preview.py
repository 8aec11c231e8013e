"""A surfel preview every USD tool draws: a decimated ``UsdGeom.Points`` beside each chunk's
ParticleField.

USD before 26.03 has no ParticleField, and usdview's Storm does not draw one; such tools (Blender
4.2's importer, older pipelines) would show nothing of a scene's main content. So each surfel
chunk file also holds a Points prim (``/Chunk_<i>_<j>_Preview``, brought into the stage at
``/World/SurfelPreview/Chunk_<i>_<j>`` by its own payload arc) with, for a deterministic subset
of the surfels:

    points          the surfel centres
    widths          the diameter of a disk of the same area as the surfel's ellipse at
                    sqrt(2) sigma (where the Gaussian falls to 1/e of its peak: about what a
                    splat renderer shows of it), enlarged by 1/sqrt(fraction) so the subset
                    covers what the whole field covers (each point stands in for 1/fraction
                    surfels)
    normals         the disk normals (local +Z rotated by the orientation)
    displayColor    the view-independent colour of the SH DC term (0.5 + C0 dc, clamped)
    displayOpacity  the surfel opacity
    purpose         "proxy" (the ParticleField says "render"), so a tool showing both
                    purposes can hide one, and the ParticleField names it as its proxyPrim

The subset is a seeded uniform sample without replacement (the seed is the chunk key): the
same surfels give the same preview on every run, and the mean colour of the preview is an
unbiased estimate of the field's. A GGDS run writes its own preview of its optimised surfels
into its run chunk files (an ``over`` of the same prim), so muting a run mutes its preview too.
"""
from __future__ import annotations

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from lsd3d_usd.shmath import C0 as SH_C0
from lsd3d_usd.splats.field import SurfelField, quat_normals

# Default fraction of the surfels in the preview: 10 % keeps the preview at ~4 % of the chunk
# files' size (40 of ~110 bytes per surfel, at a tenth of the count) while the README sample's
# 0.9 M surfels still give ~90 k points (about 8 per m² of road near the lanes), which Blender
# and usdview draw interactively. docs/usd.md has the measurements.
DEFAULT_FRACTION = 0.1
PREVIEW_SUFFIX = "_Preview"


def preview_prim_name(chunk_name: str) -> str:
    """Name of the Points prim in a chunk file: ``Chunk_<i>_<j>_Preview``."""
    return chunk_name + PREVIEW_SUFFIX


def preview_count(n: int, fraction: float) -> int:
    """Points of the preview of ``n`` surfels (at least one of a non-empty field when
    fraction > 0)."""
    if fraction <= 0 or n <= 0:
        return 0
    return int(min(n, max(1, round(n * float(fraction)))))


def preview_indices(n: int, fraction: float, key=(0, 0)) -> np.ndarray:
    """Sorted indices of the surfels in the preview: a uniform sample without replacement,
    seeded by the chunk ``key`` (deterministic)."""
    m = preview_count(n, fraction)
    if m == 0:
        return np.zeros(0, np.int64)
    seed = np.random.SeedSequence([0x5EED, int(key[0]) & 0xFFFFFFFF, int(key[1]) & 0xFFFFFFFF])
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=m, replace=False))


def preview_arrays(field: SurfelField, fraction: float, key=(0, 0)) -> dict[str, np.ndarray]:
    """The preview's arrays (float32): points, widths, normals, colors, opacities. Only the
    sampled rows are gathered (no copy of the whole field)."""
    idx = preview_indices(field.n, fraction, key)
    s = np.abs(np.asarray(field.scales[idx], np.float32))
    widths = 2.0 * np.sqrt(2.0 * s[:, 0] * s[:, 1] / np.float32(max(float(fraction), 1e-12)))
    dc = np.asarray(field.sh[idx, 0, :], np.float32)
    return {"points": np.ascontiguousarray(field.positions[idx], np.float32),
            "widths": np.ascontiguousarray(widths, np.float32),
            "normals": quat_normals(field.orientations[idx]),
            "colors": np.ascontiguousarray(np.clip(0.5 + np.float32(SH_C0) * dc, 0.0, 1.0),
                                           np.float32),
            "opacities": np.ascontiguousarray(np.clip(field.opacities[idx], 0.0, 1.0),
                                              np.float32)}


def _extent(points: np.ndarray, widths: np.ndarray) -> Vt.Vec3fArray:
    if not len(points):
        return Vt.Vec3fArray.FromNumpy(np.zeros((2, 3), np.float32))
    r = (widths * 0.5)[:, None]
    ext = np.stack([(points - r).min(0), (points + r).max(0)]).astype(np.float32)
    return Vt.Vec3fArray.FromNumpy(ext)


def write_preview(stage: Usd.Stage, path: str, field: SurfelField, fraction: float,
                  key=(0, 0), *, over: bool = False) -> Usd.Prim | None:
    """Author the preview of ``field`` as a Points prim at ``path`` (an ``over`` for a run's
    edit layer). Nothing is written for fraction 0; returns the prim or None."""
    if preview_count(field.n, fraction) == 0 and not over:
        return None
    a = preview_arrays(field, fraction, key)
    if over:
        prim = stage.OverridePrim(path)
        points = UsdGeom.Points(prim)
    else:
        points = UsdGeom.Points.Define(stage, path)
        prim = points.GetPrim()
        points.CreatePurposeAttr(UsdGeom.Tokens.proxy)
    T = Sdf.ValueTypeNames

    def put(name, type_name, value):
        attr = prim.GetAttribute(name) or prim.CreateAttribute(name, type_name, custom=False)
        attr.Set(value)
        return attr

    put("points", T.Point3fArray, Vt.Vec3fArray.FromNumpy(a["points"]))
    put("widths", T.FloatArray, Vt.FloatArray.FromNumpy(a["widths"])).SetMetadata(
        "interpolation", UsdGeom.Tokens.vertex)
    put("normals", T.Normal3fArray, Vt.Vec3fArray.FromNumpy(a["normals"])).SetMetadata(
        "interpolation", UsdGeom.Tokens.vertex)
    pv = UsdGeom.PrimvarsAPI(prim)
    pv.CreatePrimvar("displayColor", T.Color3fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(a["colors"]))
    pv.CreatePrimvar("displayOpacity", T.FloatArray, UsdGeom.Tokens.vertex).Set(
        Vt.FloatArray.FromNumpy(a["opacities"]))
    put("extent", T.Float3Array, _extent(a["points"], a["widths"]))
    return prim


def read_preview_colors(prim: Usd.Prim) -> np.ndarray:
    """(n, 3) displayColor of a preview Points prim (empty when none is authored)."""
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    value = pv.Get() if pv else None
    return np.asarray(value if value is not None else [], np.float32).reshape(-1, 3)
