"""`lsd3d-usd splats ...`: mesh -> surfel initialisation and interchange with splat tools."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom, UsdSemantics

from lsd3d_usd import configtree as ct
from lsd3d_usd import limits, scene
from lsd3d_usd.cliutil import add_limit_option, check_output_path
from lsd3d_usd.errors import InputError
from lsd3d_usd.splats.config import (WRITE_FLAGS, Export3dgsConfig, ExportPlyConfig,
                                     ImportConfig, InitConfig)
from lsd3d_usd.splats.preview import DEFAULT_FRACTION

SCENE_ROOT = "scene.usda"


def _is_scene(path) -> bool:
    p = Path(path)
    return p.is_dir() and (p / SCENE_ROOT).is_file()


def _read_stage_surfels(path, prim_path=None, time_code=None):
    """The surfels of a USD file or scene folder (composed, so GGDS edits apply), in world
    space: the prim at ``prim_path`` or all ParticleField prims concatenated."""

    # local import: not loaded for --help
    from lsd3d_usd.splats.field import SurfelField
    from lsd3d_usd.splats.init import transform_surfels
    # local import: not loaded for --help
    from lsd3d_usd.splats.usdio import read_surfels, surfel_prims

    from lsd3d_usd.assetroots import check_scene
    stage = scene.open_stage(path)
    check_scene(stage, path)        # as render and eval: a scene reads only its own folder
    t = Usd.TimeCode.Default() if time_code is None else Usd.TimeCode(time_code)
    if prim_path:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim:
            raise InputError(f"{path}: no prim at {prim_path}")
        prims = [prim]
    else:
        prims = surfel_prims(stage)
        if not prims:
            raise InputError(f"{path}: no ParticleField prim (no surfels)")
    fields = []
    for prim in prims:
        f = read_surfels(prim, t)
        M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), dtype=np.float64).T
        fields.append(transform_surfels(f, M))
    return SurfelField.concat(fields)


USD_SUFFIXES = (".usdc", ".usda", ".usd")


def _check_output(out, suffixes=USD_SUFFIXES, scene_ok: bool = True) -> None:
    """Before any work: the output is a scene folder (where allowed) or a file path that can
    be written (not a folder, not below a file, a known extension)."""

    if scene_ok and _is_scene(out):
        return
    what = "output file" + (" (or a scene folder)" if scene_ok else "")
    check_output_path(out, "-o", suffixes=suffixes, what=what)


def _write_surfels(field, out, prim_path, prov, retire_runs=False,
                   preview_fraction=DEFAULT_FRACTION):
    """To a stand-alone USD file, or as the surfels layer of a scene folder (refused when GGDS
    runs were optimised on the scene's current surfels, unless retire_runs); with the Points
    preview of ``preview_fraction`` of the surfels (0 = none; docs/usd.md)."""
    # local import: not loaded for --help
    from lsd3d_usd.splats.usdio import write_surfel_file, write_surfels_with_preview

    if _is_scene(out):
        stage = scene.new_stage()
        write_surfels_with_preview(stage, prim_path, field, preview_fraction)
        return scene.Scene.open(out).write_layer("surfels", stage, prov, retire_runs=retire_runs)
    write_surfel_file(str(out), field, prim_path, prov, preview_fraction)
    return Path(out)


# --- mesh -> surfels ------------------------------------------------------------------------

def _stage_meshes(stage, root, t):
    """Triangulated world-space meshes under ``root``: (vertices, faces, face class ids)."""

    # local import: not loaded for --help
    from lsd3d_usd import semantics

    def label_id(prim):
        for tax in UsdSemantics.LabelsAPI.GetDirectTaxonomies(prim):
            for lab in UsdSemantics.LabelsAPI(prim, tax).GetLabelsAttr().Get(t) or []:
                if str(lab) in semantics.CLASS_ID:
                    return semantics.CLASS_ID[str(lab)]
        return None

    start = stage.GetPrimAtPath(root)
    Vs, Fs, Ss, nv = [], [], [], 0
    for prim in Usd.PrimRange(start, Usd.TraverseInstanceProxies()):
        if not prim.IsA(UsdGeom.Mesh):
            continue
        if UsdGeom.Imageable(prim).ComputeVisibility(t) == UsdGeom.Tokens.invisible:
            continue
        mesh = UsdGeom.Mesh(prim)
        pts = np.asarray(mesh.GetPointsAttr().Get(t), np.float64).reshape(-1, 3)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(t) or [], np.int64)
        idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(t) or [], np.int64)
        if len(pts) == 0 or len(counts) == 0:
            continue
        # Fan-triangulate polygons; remember the source face of each triangle.
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        tri_src = np.repeat(np.arange(len(counts)), np.maximum(counts - 2, 0))
        k = np.arange(len(tri_src)) - np.repeat(np.cumsum(np.maximum(counts - 2, 0)) - np.maximum(counts - 2, 0),
                                                np.maximum(counts - 2, 0))
        s0 = starts[tri_src]
        tris = np.stack([idx[s0], idx[s0 + k + 1], idx[s0 + k + 2]], 1)
        if mesh.GetOrientationAttr().Get(t) == UsdGeom.Tokens.leftHanded:
            tris = tris[:, [0, 2, 1]]
        M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), dtype=np.float64).T
        pw = pts @ M[:3, :3].T + M[:3, 3]
        if np.linalg.det(M[:3, :3]) < 0:
            tris = tris[:, [0, 2, 1]]
        face_ids = np.full(len(counts), -1 if label_id(prim) is None else label_id(prim), np.int32)
        for sub in UsdGeom.Subset.GetAllGeomSubsets(mesh):
            lid = label_id(sub.GetPrim())
            if lid is not None and sub.GetElementTypeAttr().Get() == UsdGeom.Tokens.face:
                ind = np.asarray(sub.GetIndicesAttr().Get(t) or [], np.int64)
                face_ids[ind[(ind >= 0) & (ind < len(counts))]] = lid
        Vs.append(pw)
        Fs.append(tris + nv)
        Ss.append(face_ids[tri_src])
        nv += len(pw)
    if not Vs:
        return None
    return np.vstack(Vs), np.vstack(Fs), np.concatenate(Ss)


def _init(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.splats.init import mesh_to_surfels

    c, _ = ct.from_command_line(args, InitConfig, ct.flag_names(InitConfig) | WRITE_FLAGS)
    if args.output is not None:
        _check_output(args.output)
    stage = scene.open_stage(args.input)
    root = c.root or (scene.PROXY_PATH if stage.GetPrimAtPath(scene.PROXY_PATH) else "/")
    if not stage.GetPrimAtPath(root):
        raise InputError(f"{args.input}: no prim at {root}")
    meshes = _stage_meshes(stage, root, Usd.TimeCode.Default())
    if meshes is None:
        raise InputError(f"{args.input}: no Mesh prims under {root}")
    V, F, ids = meshes
    color = "semantic"
    if c.color != "semantic":
        try:
            color = tuple(float(x) for x in c.color.split(","))
            assert len(color) == 3
        except (ValueError, AssertionError):
            raise InputError(f"--color {c.color!r}: use 'semantic' or R,G,B (linear, e.g. 0.5,0.5,0.5)") from None
    t0 = time.perf_counter()
    field = mesh_to_surfels(V, F, ids, count=c.count, seed=c.seed, color=color,
                            opacity=c.opacity, sh_degree=c.sh_degree)
    dt = time.perf_counter() - t0
    out = args.output or (args.input if _is_scene(args.input) else None)
    if out is None:
        raise InputError("splats init: give -o OUT (a .usdc file or a scene folder)")
    prov = scene.provenance("splats.init", {"count": c.count, "color": c.color, "opacity": c.opacity,
                                            "sh_degree": c.sh_degree, "root": root,
                                            "triangles": int(len(F))}, seed=c.seed,
                            timings={"init_s": round(dt, 3)})
    path = _write_surfels(field, out, c.write.prim, prov, args.retire_runs,
                          c.write.splats.preview_fraction)
    area = float(np.pi * np.sum(field.scales[:, 0].astype(np.float64) * field.scales[:, 1]))
    print(f"{field.n} surfels on {len(F)} triangles ({area:.1f} m^2) in {dt:.2f} s -> {path}")
    return 0


# --- interchange ----------------------------------------------------------------------------

def _import_ply(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.hashing import file_hash
    from lsd3d_usd.splats.ply import read_ply

    c, _ = ct.from_command_line(args, ImportConfig, ct.flag_names(ImportConfig) | WRITE_FLAGS)
    _check_output(args.output)
    field = read_ply(args.input, max_vertices=args.max_vertices)
    digest = file_hash(args.input)
    prov = scene.provenance("splats.import-ply", {"source": str(Path(args.input).name)},
                            inputsHash=f"ply-{digest}")
    path = _write_surfels(field, args.output, c.write.prim, prov, args.retire_runs,
                          c.write.splats.preview_fraction)
    print(f"{field.n} surfels (SH degree {field.sh_degree}) -> {path}")
    return 0


def _export_ply(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.splats.ply import write_ply

    c, _ = ct.from_command_line(args, ExportPlyConfig)
    _check_output(args.output, (".ply",), scene_ok=False)
    field = _read_stage_surfels(args.input, c.prim, c.time)
    path = write_ply(args.output, field, layout=c.layout, thin=c.thin)
    print(f"{field.n} surfels -> {path} ({c.layout} layout)")
    return 0


def _export_3dgs(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.splats.ply import write_gaussian_splat_file

    c, _ = ct.from_command_line(args, Export3dgsConfig)
    _check_output(args.output, scene_ok=False)
    field = _read_stage_surfels(args.input, c.prim, c.time)
    prov = scene.provenance("splats.export-3dgs", {"thin": c.thin})
    path = write_gaussian_splat_file(args.output, field, c.out_prim, c.thin, prov)
    print(f"{field.n} surfels -> {path} (ParticleField3DGaussianSplat, thin axis {c.thin} x smaller scale)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("splats", help="surfels: initialise from meshes, import/export PLY and 3DGS",
                       description="2D Gaussian surfels: initialise them on the proxy meshes, and move "
                                   "them to and from other splat tools (gsplat, 2DGS, 3DGS, SuperSplat).")
    ss = p.add_subparsers(dest="splats_command", metavar="ACTION")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])

    q = ss.add_parser("init", help="mesh -> surfels (the paper's initialisation)",
                      description="Place COUNT surfels on the Mesh prims of a scene or USD file (by default "
                                  "under /World/Proxy), distributed by area, each with the face normal "
                                  "t_u x t_v and a 1-sigma disk of area (mesh area / COUNT). Colour from "
                                  "the semantic label (UsdSemantics labels on the mesh or its face subsets) "
                                  "or a fixed colour. Writes the scene's surfels layer, or a .usdc file.")
    q.add_argument("input", help="scene folder or USD file holding the meshes")
    q.add_argument("-o", "--output", help="output .usdc file or scene folder (default: the input scene)")
    q.add_argument("--retire-runs", action="store_true",
                   help="replace a scene's surfels even though GGDS runs were optimised on them "
                        "(the runs are muted and marked stale)")
    ct.add_arguments(q, InitConfig, flags=WRITE_FLAGS)
    q.set_defaults(func=_init)

    q = ss.add_parser("import-ply", help="3DGS/2DGS PLY -> surfel USD",
                      description="Read a Gaussian-splat PLY as written by 3DGS, 2DGS, gsplat or SuperSplat "
                                  "(uncompressed; logit opacity, log scales, wxyz rotations, channel-major "
                                  "f_rest). 3D Gaussians become surfels: the two largest axes are the disk, "
                                  "the smallest the normal. Writes a .usdc file or a scene's surfels layer.")
    q.add_argument("input", help="input .ply file")
    q.add_argument("-o", "--output", required=True, help="output .usdc file or scene folder")
    q.add_argument("--retire-runs", action="store_true",
                   help="replace a scene's surfels even though GGDS runs were optimised on them "
                        "(the runs are muted and marked stale)")
    ct.add_arguments(q, ImportConfig, flags=WRITE_FLAGS)
    add_limit_option(q, limits.PLY_VERTICES)
    q.set_defaults(func=_import_ply)

    for name, fn, helptext in (
            ("export-ply", _export_ply, "surfels -> 2DGS or 3DGS PLY"),
            ("export-3dgs", _export_3dgs, "surfels -> official ParticleField3DGaussianSplat USD")):
        q = ss.add_parser(name, help=helptext,
                          description=helptext + ". Reads the composed stage (GGDS edits included); all "
                          "ParticleField prims are concatenated in world space unless --prim names one. "
                          "3DGS output gets a thin third axis (--thin x the smaller disk scale) so that "
                          "renderers that only know 3D Gaussians draw the surfels as flat ellipsoids.")
        q.add_argument("input", help="scene folder or USD file")
        q.add_argument("-o", "--output", required=True,
                       help="output .ply file" if name == "export-ply" else "output .usdc/.usda file")
        ct.add_arguments(q, ExportPlyConfig if name == "export-ply" else Export3dgsConfig)
        q.set_defaults(func=fn)
