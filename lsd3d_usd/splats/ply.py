"""Gaussian-splat PLY files (the 3DGS / 2DGS layout) and 3DGS USD export.

The layout written by the 3DGS and 2DGS reference code and read by gsplat,
SuperSplat and most splat viewers: one ``vertex`` element, binary little-endian
float32 properties

    x y z  nx ny nz (zeros)  f_dc_0..2  f_rest_0..3(K-1)-1  opacity
    scale_0..1 (2DGS) or scale_0..2 (3DGS)  rot_0..3

with opacity stored as a logit, scales as natural logs, rotations as wxyz
quaternions (not necessarily normalised) and f_rest channel-major: all of red's
higher-order coefficients, then green's, then blue's. We add an optional int
``semantic_id`` property (ignored by other tools).

Importing a 3DGS file keeps each Gaussian's two largest axes as the surfel disk
and makes the smallest the normal. Exporting for 3DGS-only consumers adds a thin
third axis: ``thin`` x the smaller disk scale (1e-3 by default: a 10 cm surfel is
0.1 mm thick, invisible as thickness but a valid, invertible covariance).
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
from pxr import Sdf, UsdVol, Vt

from lsd3d_usd import scene
from lsd3d_usd.errors import InputError
from lsd3d_usd.plyio import read_header_comments, read_ply_vertices, write_ply_vertices  # noqa: F401
from lsd3d_usd.splats.field import (
    SurfelField,
    flatten_3d_gaussians,
    kernel_bounds,
    sh_degree_for,
)
from lsd3d_usd.splats.usdio import check_bulk_target

THIN_AXIS = 1e-3
_OPACITY_EPS = 1e-7  # logit of exactly 0 or 1 is infinite: clamp before the logit

# --- Gaussian splats <-> SurfelField ---------------------------------------------------

def _numbered(names, prefix):
    idx = sorted(int(n[len(prefix):]) for n in names if re.fullmatch(re.escape(prefix) + r"\d+", n))
    if idx != list(range(len(idx))):
        raise ValueError(f"{prefix}* properties are not numbered 0..{len(idx) - 1}")
    return [f"{prefix}{i}" for i in idx]


def read_ply(path, max_vertices: int | None = None) -> SurfelField:
    """Read a 3DGS or 2DGS PLY into a SurfelField (3D Gaussians flattened to surfels).
    More than limits.PLY_VERTICES splats (or ``max_vertices``) are refused up front."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        # out-of-range values become inf / NaN and are reported by SurfelField.problems()
        return _read_ply(path, max_vertices)


def _read_ply(path, max_vertices) -> SurfelField:
    v = read_ply_vertices(path, max_vertices)
    names = set(v.dtype.names)
    if "packed_position" in names:
        raise InputError(f"{path}: SuperSplat compressed PLY is not supported; decompress it first")
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in need if n not in names]
    if missing:
        raise InputError(f"{path}: not a Gaussian-splat PLY: missing vertex properties {', '.join(missing)}")
    try:
        scale_names = _numbered(names, "scale_")
        rest_names = _numbered(names, "f_rest_")
    except ValueError as e:
        raise InputError(f"{path}: {e}") from None
    if len(scale_names) not in (2, 3):
        raise InputError(f"{path}: expected 2 (2DGS) or 3 (3DGS) scale_* properties, got {len(scale_names)}")
    n = len(v)
    f64 = lambda k: v[k].astype(np.float64)  # noqa: E731

    pos = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)
    n_rest = len(rest_names)
    if n_rest % 3:
        raise InputError(f"{path}: {n_rest} f_rest_* properties is not a multiple of 3")
    try:
        sh_degree_for(1 + n_rest // 3)
    except ValueError:
        raise InputError(f"{path}: {n_rest} f_rest_* properties do not match an SH degree 0..3") from None
    k = 1 + n_rest // 3
    sh = np.zeros((n, k, 3), np.float32)
    for c in range(3):
        sh[:, 0, c] = v[f"f_dc_{c}"]
        for j in range(k - 1):  # channel-major: f_rest_{c*(K-1)+j}
            sh[:, 1 + j, c] = v[f"f_rest_{c * (k - 1) + j}"]
    opac = (1.0 / (1.0 + np.exp(-f64("opacity")))).astype(np.float32)
    q_wxyz = np.stack([f64(f"rot_{i}") for i in range(4)], 1)
    qn = np.linalg.norm(q_wxyz, axis=1)
    bad = ~(qn > 0) | ~np.isfinite(qn)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} splat(s) have a zero or non-finite rotation "
                         f"(first vertex {int(np.flatnonzero(bad)[0])})")
    q = (q_wxyz / qn[:, None])[:, [1, 2, 3, 0]]
    scales = np.exp(np.stack([f64(s) for s in scale_names], 1))
    if len(scale_names) == 3:
        q, scales2 = flatten_3d_gaussians(q, scales)
    else:
        scales2 = scales
    sem, classes = None, ()
    if "semantic_id" in names:
        classes = read_ply_semantic_classes(path)
        raw = v["semantic_id"].astype(np.float64)
        top = len(classes) if classes else 2 ** 31
        # checked here, before the int32 cast wraps it, so the error names this file and not
        # the prim it would be written to
        bad = ~np.isfinite(raw) | (raw != np.round(raw)) | (raw < -1) | (raw >= top)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"{path}: semantic_id {raw[i]:g} of vertex {i} is not a class id in "
                             f"[-1, {top}) ({int(bad.sum())} vertices)")
        sem = raw.astype(np.int32)
    field = SurfelField(pos, q.astype(np.float32), scales2.astype(np.float32), opac, sh, sem, classes)
    probs = field.problems()
    if probs:
        raise InputError(f"{path}: " + "; ".join(probs))
    return field


def splat_vertex_array(field: SurfelField, layout: str = "2dgs", thin: float = THIN_AXIS) -> np.ndarray:
    """The PLY vertex records of ``field`` in the 2DGS (2 scales) or 3DGS (3 scales) layout."""
    if layout not in ("2dgs", "3dgs"):
        raise InputError(f"PLY layout must be '2dgs' or '3dgs', got {layout!r}")
    n, k = field.n, field.sh.shape[1]
    ns = 2 if layout == "2dgs" else 3
    props = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(3 * (k - 1))] + ["opacity"]
             + [f"scale_{i}" for i in range(ns)] + [f"rot_{i}" for i in range(4)])
    dtype = [(p, "<f4") for p in props]
    if field.semantic_ids is not None:
        dtype.append(("semantic_id", "<i4"))
    out = np.zeros(n, dtype=dtype)
    for i, a in enumerate("xyz"):
        out[a] = field.positions[:, i]
    for c in range(3):
        out[f"f_dc_{c}"] = field.sh[:, 0, c]
        for j in range(k - 1):
            out[f"f_rest_{c * (k - 1) + j}"] = field.sh[:, 1 + j, c]
    p = np.clip(field.opacities.astype(np.float64), _OPACITY_EPS, 1.0 - _OPACITY_EPS)
    out["opacity"] = np.log(p / (1.0 - p))
    s = field.scales.astype(np.float64)
    with np.errstate(divide="ignore"):
        out["scale_0"], out["scale_1"] = np.log(s[:, 0]), np.log(s[:, 1])
        if ns == 3:
            out["scale_2"] = np.log(thin * np.minimum(s[:, 0], s[:, 1]))
    q = field.orientations
    out["rot_0"], out["rot_1"], out["rot_2"], out["rot_3"] = q[:, 3], q[:, 0], q[:, 1], q[:, 2]
    if field.semantic_ids is not None:
        out["semantic_id"] = field.semantic_ids
    return out


def write_ply(path, field: SurfelField, layout: str = "2dgs", thin: float = THIN_AXIS) -> Path:
    """Write ``field`` as a Gaussian-splat PLY (binary little-endian), atomically."""
    probs = field.problems()
    if probs:
        raise InputError(f"{path}: refusing to write invalid surfels: " + "; ".join(probs))
    comments = [f"lsd3d-usd {layout} surfels"]
    if field.semantic_classes:
        comments.append("semantic_classes " + " ".join(field.semantic_classes))
    return write_ply_vertices(path, splat_vertex_array(field, layout, thin), comments)


def read_ply_semantic_classes(path) -> tuple[str, ...]:
    """Class names from our 'comment semantic_classes ...' header line, if present."""
    found = read_header_comments(path, b"comment semantic_classes ")
    return tuple(found[0].split()) if found else ()


# --- official 3DGS ParticleField export ----------------------------------------------------

def write_gaussian_splat_prim(stage, path: str, field: SurfelField, thin: float = THIN_AXIS):
    """Author ``field`` as an official UsdVol ParticleField3DGaussianSplat at ``path``
    (third axis = ``thin`` x the smaller disk scale), for 3DGS-only renderers."""

    probs = field.problems()
    if probs:
        raise InputError(f"{path}: refusing to write invalid surfels: " + "; ".join(probs))
    prim = UsdVol.ParticleField3DGaussianSplat.Define(stage, Sdf.Path(path)).GetPrim()
    T = Sdf.ValueTypeNames
    s3 = np.empty((field.n, 3), np.float32)
    s3[:, :2] = field.scales
    s3[:, 2] = thin * field.scales.min(axis=1)

    def put(name, t, value, uniform=False):
        attr = prim.GetAttribute(name) or prim.CreateAttribute(
            name, t, variability=Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
        attr.Set(value)

    put("positions", T.Point3fArray, Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(field.positions)))
    put("orientations", T.QuatfArray, Vt.QuatfArray.FromNumpy(np.ascontiguousarray(field.orientations)))
    put("scales", T.Float3Array, Vt.Vec3fArray.FromNumpy(s3))
    put("opacities", T.FloatArray, Vt.FloatArray.FromNumpy(np.ascontiguousarray(field.opacities)))
    put("radiance:sphericalHarmonicsDegree", T.Int, int(field.sh_degree), uniform=True)
    put("radiance:sphericalHarmonicsCoefficients", T.Float3Array,
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(field.sh.reshape(-1, 3))))
    ext = kernel_bounds(field.positions, field.orientations, s3, surflet=False)  # thin axis too
    put("extent", T.Float3Array, Vt.Vec3fArray.FromNumpy(ext.astype(np.float32)))
    return prim


def write_gaussian_splat_file(path, field: SurfelField, prim_path: str = "/World/Surfels",
                              thin: float = THIN_AXIS, provenance: dict | None = None) -> Path:
    """Stand-alone USD file holding one ParticleField3DGaussianSplat, written atomically.
    A .usda path is refused above limits.USDA_PARTICLES particles (bulk data)."""

    check_bulk_target(path, field.n)
    stage = scene.new_stage()
    write_gaussian_splat_prim(stage, prim_path, field, thin)
    return scene.save_stage(stage, os.fspath(path), provenance)
