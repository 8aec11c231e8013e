"""`lsd3d-usd validate`: usd-core's UsdValidation validators plus our own checks.

Works on any USD file (our scenes, official ParticleField3DGaussianSplat files
from other tools, plain meshes). Each problem names the prim, the attribute and
what is wrong; errors fail validation, warnings are reported only.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from pxr import Tf, Sdf, Usd, UsdGeom, UsdValidation, UsdVol

import lsd3d_usd
from lsd3d_usd import assetroots, safepaths, scene
from lsd3d_usd.diagnostics import captured_stderr
from lsd3d_usd.limits import USDA_PARTICLES
from lsd3d_usd.splats.field import kernel_bounds, sh_coeff_count
from lsd3d_usd.splats.usdio import is_surflet

QUAT_TOL = 1e-3
EXTENT_TOL = 1e-4          # relative to the extent's size
BULK_TEXT_LIMIT = int(USDA_PARTICLES.value)  # particles in a .usda layer: bulk data beyond


@dataclass
class Problem:
    severity: str            # "error" | "warning"
    prim: str                # prim path, or "/" for stage/layer-level problems
    attribute: str | None
    message: str
    check: str               # our check name or the UsdValidation validator name

    def line(self) -> str:
        where = self.prim + (f".{self.attribute}" if self.attribute else "")
        prefix = "" if self.severity == "error" else "warning: "
        return f"{prefix}{where}: {self.message}"


# ------------------------------------------------------------------ usd-core
def _usd_validators(stage: Usd.Stage) -> list[Problem]:
    reg = UsdValidation.ValidationRegistry()
    ctx = UsdValidation.ValidationContext(reg.GetOrLoadAllValidators())
    out = []
    for err in ctx.Validate(stage):
        if err.HasNoError():
            continue
        sev = {UsdValidation.ValidationErrorType.Error: "error",
               UsdValidation.ValidationErrorType.Warn: "warning"}.get(err.GetType())
        if sev is None:
            continue
        prim, attr = "/", None
        for site in err.GetSites():
            if site.IsProperty():
                p = site.GetProperty().GetPath()
                prim, attr = str(p.GetPrimPath()), p.name
                break
            if site.IsPrim():
                prim = str(site.GetPrim().GetPath())
                break
        name = err.GetValidator().GetMetadata().name if err.GetValidator() else err.GetName()
        out.append(Problem(sev, prim, attr, " ".join(err.GetMessage().split()), name))
    return out


def _composition_errors(stage: Usd.Stage) -> list[Problem]:
    """Layers, payloads and references that could not be composed (missing or corrupt files):
    usd-core only prints them."""
    out = []
    for err in stage.GetCompositionErrors():
        site = err.rootSite if hasattr(err, "rootSite") else None
        prim = str(site.path) if site is not None and hasattr(site, "path") else "/"
        out.append(Problem("error", prim or "/", None, " ".join(str(err).split())[:400],
                           "lsd3d:Composition"))
    return out


# --------------------------------------------------------------- our checks
def _unknown_types(stage: Usd.Stage) -> list[Problem]:
    reg = Usd.SchemaRegistry()
    out = []
    for prim in stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        t = prim.GetTypeName()
        if t and not reg.FindConcretePrimDefinition(t) and not reg.IsAbstract(t) \
                and prim.GetPrimTypeInfo().GetSchemaType().isUnknown:
            out.append(Problem("error", str(prim.GetPath()), None,
                               f"unknown prim type {t!r} (schema not registered)", "lsd3d:UnknownPrimType"))
        api_list = prim.GetMetadata("apiSchemas")
        for api in (api_list.GetAddedOrExplicitItems() if api_list else []):
            base = api.split(":")[0]
            if not reg.FindAppliedAPIPrimDefinition(base) and not reg.GetTypeFromSchemaTypeName(base):
                out.append(Problem("error", str(prim.GetPath()), None,
                                   f"unknown applied API schema {api!r}", "lsd3d:UnknownAPISchema"))
    return out


def _array(prim: Usd.Prim, name: str, time=Usd.TimeCode.Default()) -> np.ndarray | None:
    for n in (name, name + "h"):
        a = prim.GetAttribute(n)
        if a and a.HasValue():
            v = a.Get(time)
            if v is not None:
                return np.asarray(v)
    return None


def _text_layers(attr: Usd.Attribute) -> list[Sdf.Layer]:
    return [spec.layer for spec in attr.GetPropertyStack(Usd.TimeCode.Default())
            if spec.layer.GetFileFormat().formatId == "usda" and not spec.layer.anonymous]


SH_DEGREE = "radiance:sphericalHarmonicsDegree"
SH_COEFFS = "radiance:sphericalHarmonicsCoefficients"
SEM_IDS = "lsd3d:semanticIds"
PER_PARTICLE = (("orientations", 4), ("scales", 3), ("opacities", 1))
_SAMPLED = ("positions", "orientations", "scales", "opacities", SH_COEFFS, SEM_IDS, "extent")


def _sample_times(prim: Usd.Prim) -> list[Usd.TimeCode]:
    """Every time sample of the particle arrays, or the default time when none is animated
    (at a sample time an unanimated attribute yields its default value)."""
    times: set[float] = set()
    for name in _SAMPLED:
        for n in (name, name + "h"):
            a = prim.GetAttribute(n)
            if a:
                times.update(a.GetTimeSamples())
    return [Usd.TimeCode(t) for t in sorted(times)] or [Usd.TimeCode.Default()]


def _written_by_us(prim: Usd.Prim, attr_name: str, time) -> bool:
    """Our surfel type, or the strongest opinion of the attribute sits in a layer that
    carries lsd3d provenance."""
    if prim.GetTypeName() == lsd3d_usd.SURFEL_TYPE:
        return True
    attr = prim.GetAttribute(attr_name)
    stack = attr.GetPropertyStack(time) if attr else []
    return bool(stack) and bool(scene.read_provenance(stack[0].layer))


def _check_particle_field(prim: Usd.Prim) -> list[Problem]:
    """Checks at the default time, or at every time sample when the arrays are animated;
    a problem found at several times is reported once, with the first time."""
    out: list[Problem] = []
    seen: set = set()
    for t in _sample_times(prim):
        for p in _check_particle_field_at(prim, t):
            key = (p.severity, p.attribute, p.message, p.check)
            if key in seen:
                continue
            seen.add(key)
            if not t.IsDefault():
                p.message += f" (at time {t.GetValue():g})"
            out.append(p)
    n = _array(prim, "positions")
    n = 0 if n is None else n.size // 3
    if n > BULK_TEXT_LIMIT:
        for layer in _text_layers(prim.GetAttribute("positions")):
            out.append(Problem("error", str(prim.GetPath()), "positions",
                               f"{n} particles stored in text layer {layer.identifier}; "
                               "bulk data belongs in .usdc", "lsd3d:BulkDataInUsda"))
    return out


def _check_particle_field_at(prim: Usd.Prim, time) -> list[Problem]:
    path, out = str(prim.GetPath()), []

    def err(attr, msg, check, severity="error"):
        out.append(Problem(severity, path, attr, msg, check))

    def first(mask):
        idx = np.flatnonzero(mask)
        return f"{len(idx)} particle(s), first index {idx[0]}"

    pos = _array(prim, "positions", time)
    coeffs = _array(prim, SH_COEFFS, time)
    sem = _array(prim, SEM_IDS, time)
    if pos is None:
        # no positions means no particles (valid per the schema) only if nothing else is sized
        for name, a, width in [(nm, _array(prim, nm, time), w) for nm, w in PER_PARTICLE] + [
                (SH_COEFFS, coeffs, 3), (SEM_IDS, sem, 1)]:
            if a is not None and a.size:
                err("positions", f"missing, but {name} has {a.size // width} values "
                                 "(the particle count comes from positions)", "lsd3d:ArrayLength")
                break
        return out
    if pos.size % 3:
        err("positions", f"{pos.size} values are not (x, y, z) triples", "lsd3d:ArrayLength")
        return out
    pos = pos.reshape(-1, 3).astype(np.float64)
    n = len(pos)
    surflet = is_surflet(prim)
    arrays = {"positions": pos}
    for name, width in PER_PARTICLE:
        a = _array(prim, name, time)
        if a is None:
            continue
        if a.size != n * width:
            err(name, f"{a.size // width} values for {n} positions", "lsd3d:ArrayLength")
            continue
        arrays[name] = a.reshape(n, width).astype(np.float64) if width > 1 else a.reshape(n).astype(np.float64)
    for name, a in list(arrays.items()):
        if n == 0:
            break
        bad = ~np.isfinite(a.reshape(n, -1)).all(axis=1)
        if bad.any():
            err(name, f"non-finite values in {first(bad)}", "lsd3d:Finite")
            arrays[name] = np.where(np.isfinite(a), a, 0.0)
    if "opacities" in arrays and n:
        o = arrays["opacities"]
        bad = (o < 0) | (o > 1)
        if bad.any():
            err("opacities", f"outside [0, 1] in {first(bad)} (linear opacity, not logit)", "lsd3d:OpacityRange")
    if "scales" in arrays and n:
        s = arrays["scales"]
        bad = ~(s[:, :2] > 0).all(axis=1) | (s[:, 2] < 0 if surflet else ~(s[:, 2] > 0))
        if bad.any():
            what = "x, y not > 0 (or z < 0)" if surflet else "not > 0"
            err("scales", f"{what} in {first(bad)} (linear scales, not log)", "lsd3d:ScalePositive")
    if "orientations" in arrays and n:
        norm = np.linalg.norm(arrays["orientations"], axis=1)
        bad = np.abs(norm - 1) > QUAT_TOL
        if bad.any():
            err("orientations", f"not unit quaternions (tolerance {QUAT_TOL}) in {first(bad)}",
                "lsd3d:UnitQuaternion")
    deg_attr = prim.GetAttribute(SH_DEGREE)
    if coeffs is not None:
        deg = deg_attr.Get() if deg_attr else 3
        if deg is None or not 0 <= int(deg) <= 8:
            err(SH_DEGREE, f"invalid degree {deg}", "lsd3d:SHDegree")
        else:
            k = sh_coeff_count(int(deg))
            if coeffs.size != n * k * 3:
                err(SH_COEFFS, f"{coeffs.size // 3} coefficients for {n} particles, but degree {deg} "
                               f"needs {k} per particle ({n * k})", "lsd3d:SHDegree")
            elif n and not np.isfinite(coeffs).all():
                bad = ~np.isfinite(coeffs.reshape(n, -1)).all(axis=1)
                err(SH_COEFFS, f"non-finite values in {first(bad)}", "lsd3d:Finite")
    if sem is not None:
        if sem.size != n:
            err(SEM_IDS, f"{sem.size} values for {n} positions", "lsd3d:ArrayLength")
        elif n:
            classes = prim.GetAttribute("lsd3d:semanticClasses")
            k = len(classes.Get() or ()) if classes and classes.HasValue() else None
            if k is not None:
                bad = (sem < -1) | (sem >= k)
                if bad.any():
                    err(SEM_IDS, f"ids outside [-1, {k}) in {first(bad)}", "lsd3d:SemanticRange")
    # Extent must cover every kernel's support (3 sigma).
    extent = _array(prim, "extent", time)
    if extent is None or extent.size != 6:
        err("extent", "missing (usd-core does not compute ParticleField extents; author it)",
            "lsd3d:Extent")
    elif not np.isfinite(extent.astype(np.float64)).all():
        err("extent", f"non-finite values {extent.reshape(2, 3).tolist()}", "lsd3d:Finite")
    elif n:
        q = arrays.get("orientations", np.tile([0.0, 0, 0, 1], (n, 1)))
        q = np.where(np.linalg.norm(q, axis=1, keepdims=True) > 0, q, [0, 0, 0, 1])
        lo, hi = kernel_bounds(arrays["positions"], q, arrays.get("scales", np.ones((n, 3))),
                               surflet=surflet)
        ext = extent.reshape(2, 3).astype(np.float64)
        tol = EXTENT_TOL * max(1.0, float(np.max(hi - lo)))
        if (ext[0] > lo + tol).any() or (ext[1] < hi - tol).any():
            msg = (f"{ext.tolist()} does not cover the particles' 3-sigma bounds "
                   f"{[lo.round(4).tolist(), hi.round(4).tolist()]}")
            if _written_by_us(prim, "extent", time):
                err("extent", msg, "lsd3d:Extent")
            else:
                err("extent", msg + " (not written by lsd3d-usd: other converters author the "
                                    "bounds of the positions only)", "lsd3d:Extent", "warning")
    return out


def _check_mesh(prim: Usd.Prim) -> list[Problem]:
    path, out = str(prim.GetPath()), []
    mesh = UsdGeom.Mesh(prim)
    pts = mesh.GetPointsAttr().Get()
    counts = mesh.GetFaceVertexCountsAttr().Get()
    idx = mesh.GetFaceVertexIndicesAttr().Get()
    if pts is None:
        return out
    pts = np.asarray(pts)
    if not np.isfinite(pts).all():
        bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
        out.append(Problem("error", path, "points", f"non-finite values at {len(bad)} point(s), "
                                                    f"first index {bad[0]}", "lsd3d:Finite"))
    if counts is not None and idx is not None:
        counts, idx = np.asarray(counts), np.asarray(idx)
        if counts.sum() != len(idx):
            out.append(Problem("error", path, "faceVertexIndices",
                               f"{len(idx)} indices but faceVertexCounts sum to {counts.sum()}",
                               "lsd3d:ArrayLength"))
        if len(idx) and (idx.min() < 0 or idx.max() >= len(pts)):
            out.append(Problem("error", path, "faceVertexIndices",
                               f"indices outside [0, {len(pts)})", "lsd3d:IndexRange"))
    return out


def _curve_rule(kind: str, basis: str, wrap: str) -> tuple[int, int, int, str]:
    """(minimum vertices, step, offset, wording) of one curve: a count is valid when it is
    >= minimum and (count - offset) % step == 0 (UsdGeom.BasisCurves' segment rules)."""
    if kind == "linear":
        return (3, 1, 0, "at least 3") if wrap == "periodic" else (2, 1, 0, "at least 2")
    if basis == "bezier":
        return (3, 3, 0, "a multiple of 3") if wrap == "periodic" else (4, 3, 4, "4 + 3k")
    if wrap == "pinned":
        return 2, 1, 0, "at least 2"
    return (3, 1, 0, "at least 3") if wrap == "periodic" else (4, 1, 0, "at least 4")


def _check_curves(prim: Usd.Prim) -> list[Problem]:
    """A BasisCurves prim that USD tools can draw: curveVertexCounts authored, adding up to
    the points, each curve long enough for its type / basis / wrap (type defaults to cubic
    bezier, which a two-point polyline is not)."""
    path, out = str(prim.GetPath()), []
    curves = UsdGeom.BasisCurves(prim)
    pts = curves.GetPointsAttr().Get()
    if pts is None or len(pts) == 0:
        return out
    n = len(pts)
    counts = curves.GetCurveVertexCountsAttr().Get()
    if counts is None or len(counts) == 0:
        return [Problem("error", path, "curveVertexCounts",
                        f"missing for {n} points, so USD tools draw no curve (author [{n}] for one "
                        "curve through all points)", "lsd3d:BasisCurves")]
    counts = np.asarray(counts, np.int64)
    if counts.sum() != n or (counts < 1).any():
        return [Problem("error", path, "curveVertexCounts",
                        f"{counts.tolist()[:8]}{'...' if len(counts) > 8 else ''} do not add up to the "
                        f"{n} points", "lsd3d:BasisCurves")]
    kind = curves.GetTypeAttr().Get() or "cubic"
    basis = curves.GetBasisAttr().Get() or "bezier"
    wrap = curves.GetWrapAttr().Get() or "nonperiodic"
    lo, step, offset, words = _curve_rule(str(kind), str(basis), str(wrap))
    bad = np.flatnonzero((counts < lo) | ((counts - offset) % step != 0))
    if len(bad):
        authored = curves.GetTypeAttr().HasAuthoredValue()
        what = f"type {kind}" + ("" if kind == "linear" else f", basis {basis}")
        hint = "" if authored else " (type is not authored: USD's fallback is cubic bezier; " \
                                   "author type = \"linear\" for polylines)"
        out.append(Problem("error", path, "curveVertexCounts",
                           f"curve {bad[0]} has {counts[bad[0]]} vertices; {what}, wrap {wrap} needs "
                           f"{words}{hint}", "lsd3d:BasisCurves"))
    return out


def _check_assets(stage: Usd.Stage) -> list[Problem]:
    out = []
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            if attr.GetTypeName() not in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
                continue
            value = attr.Get()
            values = value if isinstance(value, (list, tuple)) or hasattr(value, "__len__") \
                and not isinstance(value, Sdf.AssetPath) else [value]
            for v in values or []:
                if isinstance(v, Sdf.AssetPath) and v.path and not v.resolvedPath:
                    out.append(Problem("error", str(prim.GetPath()), attr.GetName(),
                                       f"unresolvable asset path @{v.path}@", "lsd3d:AssetPath"))
    return out


def _check_outside(stage: Usd.Stage, path: str | Path) -> list[Problem]:
    """Layers, arcs and asset paths outside the scene folder (and LSD3D_ASSET_ROOTS):
    render, eval and generate refuse them."""
    folder = assetroots.folder_of(path)
    return [Problem("error", "/", None, f"{where} names {p!r}, outside the scene folder "
                    f"{folder} (allowed roots: {assetroots.ASSET_ROOTS_ENV})", "lsd3d:OutsideScene")
            for where, p in assetroots.outside_paths(
                stage, assetroots.allowed_roots(*assetroots.scene_roots(stage, path)))]


def _check_links(path: str | Path) -> list[Problem]:
    """Symbolic links in a scene folder's written folders: a re-run would write and delete
    through them (scene.Scene.check_writable refuses such a scene)."""
    p = Path(path)
    root = p if p.is_dir() else p.parent
    if not (root / scene.ROOT_FILE).is_file() or (p.is_file() and p.name != scene.ROOT_FILE):
        return []
    out = []
    for d in scene.WRITTEN_DIRS:
        for link in safepaths.links_in_tree(root / d):
            out.append(Problem("error", "/", None,
                               f"{link.relative_to(root)} is a symbolic link (to "
                               f"{os.readlink(link)}); steps that rewrite the scene refuse to "
                               "write or delete through it", "lsd3d:SymbolicLink"))
    return out


def validate(path: str | Path) -> list[Problem]:
    """All problems of the USD file (or scene folder) at `path`. Raises InputError when
    the file cannot be opened at all."""
    with captured_stderr():
        stage = scene.open_stage(path)
        problems = _composition_errors(stage)
        try:
            problems += _usd_validators(stage)
        except Tf.ErrorException as e:   # e.g. a corrupt payload file the validators touch
            problems.append(Problem("error", "/", None, "usd-core's validators could not run: "
                                    + scene.first_error_line(e), "usdValidation"))
        problems += _unknown_types(stage)
        for prim in stage.Traverse():
            if prim.IsA(UsdVol.ParticleField):
                problems += _check_particle_field(prim)
            elif prim.IsA(UsdGeom.Mesh):
                problems += _check_mesh(prim)
            elif prim.IsA(UsdGeom.BasisCurves):
                problems += _check_curves(prim)
        problems += _check_assets(stage)
        problems += _check_outside(stage, path)
    problems += _check_links(path)
    # usd-core's MissingReference validator may also name a missing texture we report per attribute.
    ours = {Path(p.message.split("@")[1]).name for p in problems if p.check == "lsd3d:AssetPath"}
    return [p for p in problems
            if not (p.check.startswith("usdUtilsValidators:MissingReference")
                    and any(a in p.message for a in ours))]


def report(path: str | Path, problems: list[Problem], as_json: bool) -> str:
    errors = [p for p in problems if p.severity == "error"]
    if as_json:
        return json.dumps({"path": str(path), "valid": not errors,
                           "errors": len(errors), "warnings": len(problems) - len(errors),
                           "problems": [asdict(p) for p in problems]}, indent=2)
    lines = [p.line() for p in problems]
    lines.append(f"{path}: {'valid' if not errors else 'invalid'} "
                 f"({len(errors)} error(s), {len(problems) - len(errors)} warning(s))")
    return "\n".join(lines)
