"""Proxy meshes <-> USD: a root proxy layer with one payload per chunk.

Layout on disk (``-o proxy.usdc``)::

    proxy.usdc                      /World/Proxy/Chunk_<i>_<j>  (Xform, payload arc each)
    proxy_chunks/chunk_<i>_<j>.usdc Chunk_<i>_<j> (defaultPrim) / <class> (UsdGeom.Mesh)

The chunk folder is named after the root file's stem (``<stem>_chunks``), so
a scene's ``layers/proxy.usdc`` keeps its chunks in ``layers/proxy_chunks/``.
A stage opened with ``Usd.Stage.LoadNone`` shows the chunk prims but none of
their meshes; ``stage.Load(chunk_path)`` brings in one chunk.

Each mesh: one per chunk and semantic class (parts concatenated), with
``UsdSemantics.LabelsAPI`` instance ``class`` (``semantics:labels:class =
[<class>]``, the Isaac Sim / Replicator convention), a stable id
``lsd3d:proxy:id = "<chunk>/<class>"``, the ids of the parts it holds
(``lsd3d:proxy:partIds``) with a per-face index into them (uniform primvar
``lsd3d:partIndex``), ``primvars:displayColor`` and an authored extent.

Provenance: every chunk layer stores ``inputsHash`` (chunks.chunk_inputs_hash);
the root layer stores the map chunk name -> inputs hash. A chunk whose hash
is unchanged is not rebuilt and its file not rewritten; an unchanged root is
not rewritten either. All writes are atomic (scene.save_layer).
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSemantics, Vt

from lsd3d_usd import safepaths
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import (
    PROXY_PATH,
    WORLD,
    chunk_prim_name,
    open_stage,
    parse_chunk_prim_name,
    provenance,
    save_layer,
)

from .chunks import ProxyBuilder, ProxyParams, _feature_bytes, check_chunk_count
from .mesh import ClassMesh, MeshPart, merge_parts

ID_ATTR = "lsd3d:proxy:id"
PART_IDS_ATTR = "lsd3d:proxy:partIds"
PART_INDEX_PRIMVAR = "lsd3d:partIndex"
SOLID_ATTR = "lsd3d:proxy:solid"
LABELS_API = "SemanticsLabelsAPI"     # UsdSemantics.LabelsAPI, multiple-apply
LABELS_INSTANCE = "class"


def chunk_file_name(i: int, j: int) -> str:
    return chunk_prim_name(i, j).lower() + ".usdc"


def chunks_dir(root_path: str | Path) -> Path:
    p = Path(root_path)
    return p.with_name(f"{p.stem}_chunks")


def _class_color(cls: str) -> np.ndarray:
    # local import: not loaded for --help
    from lsd3d_usd.semantics import CLASS_COLORS, CLASS_ID
    k = CLASS_ID.get(cls)
    return np.asarray(CLASS_COLORS[k] if k is not None else (0.5, 0.5, 0.5), dtype=np.float32)


def _attr(spec, name: str, type_name, value, uniform: bool = False, custom: bool = False,
          interpolation: str | None = None):
    a = Sdf.AttributeSpec(spec, name, type_name,
                          Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying, custom)
    a.default = value
    if interpolation is not None:
        a.SetInfo(UsdGeom.Tokens.interpolation, interpolation)
    return a


def _author_mesh(parent, name: str, cm: ClassMesh, solid: bool):
    """One class mesh as a Mesh prim spec under ``parent``. Authored with Sdf, not through
    a stage (a chunk's meshes are plain opinions in one new layer; the stage API's
    notifications cost more than the data): the same specs UsdGeom.Mesh, LabelsAPI.Apply
    and PrimvarsAPI author (the test compares the two)."""
    spec = Sdf.PrimSpec(parent, name, Sdf.SpecifierDef, "Mesh")
    spec.SetInfo(Usd.Tokens.apiSchemas, Sdf.TokenListOp.Create(
        prependedItems=[f"{LABELS_API}:{LABELS_INSTANCE}"]))
    T = Sdf.ValueTypeNames
    pts = np.ascontiguousarray(cm.vertices, dtype=np.float32)
    lo, hi = pts.min(0), pts.max(0)
    _attr(spec, UsdGeom.Tokens.doubleSided, T.Bool, False, uniform=True)
    _attr(spec, UsdGeom.Tokens.extent, T.Float3Array,
          Vt.Vec3fArray.FromNumpy(np.stack([lo, hi]).astype(np.float32)))
    _attr(spec, UsdGeom.Tokens.faceVertexCounts, T.IntArray,
          Vt.IntArray.FromNumpy(np.full(len(cm.faces), 3, np.int32)))
    _attr(spec, UsdGeom.Tokens.faceVertexIndices, T.IntArray,
          Vt.IntArray.FromNumpy(np.ascontiguousarray(cm.faces.reshape(-1), dtype=np.int32)))
    _attr(spec, ID_ATTR, T.String, cm.name, uniform=True, custom=True)
    _attr(spec, PART_IDS_ATTR, T.StringArray, Vt.StringArray(list(cm.part_ids)), uniform=True,
          custom=True)
    _attr(spec, SOLID_ATTR, T.Bool, bool(solid), uniform=True, custom=True)
    _attr(spec, UsdGeom.Tokens.points, T.Point3fArray, Vt.Vec3fArray.FromNumpy(pts))
    base = _class_color(cm.cls)
    if any(c is not None for c in cm.part_colors):
        cols = np.array([base if c is None else c for c in cm.part_colors], dtype=np.float32)
        _attr(spec, "primvars:displayColor", T.Color3fArray,
              Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(cols[cm.face_part])),
              interpolation=UsdGeom.Tokens.uniform)
    else:
        _attr(spec, "primvars:displayColor", T.Color3fArray, Vt.Vec3fArray.FromNumpy(base[None, :]),
              interpolation=UsdGeom.Tokens.constant)
    _attr(spec, f"primvars:{PART_INDEX_PRIMVAR}", T.IntArray,
          Vt.IntArray.FromNumpy(np.ascontiguousarray(cm.face_part, dtype=np.int32)),
          interpolation=UsdGeom.Tokens.uniform)
    _attr(spec, f"semantics:labels:{LABELS_INSTANCE}", T.TokenArray, Vt.TokenArray([cm.cls]))
    _attr(spec, UsdGeom.Tokens.subdivisionScheme, T.Token, UsdGeom.Tokens.none, uniform=True)
    return spec


def write_chunk_layer(parts: list[MeshPart], key: tuple[int, int], path: str | Path,
                      inputs_hash: str = "", params: dict | None = None) -> Path:
    """Write one chunk's meshes (merged per class) to its own layer, atomically."""

    name = chunk_prim_name(*key)
    layer = Sdf.Layer.CreateAnonymous(".usdc")
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, UsdGeom.Tokens.z)
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
    solid_by_cls: dict[str, bool] = {}
    for p in parts:
        solid_by_cls[p.cls] = solid_by_cls.get(p.cls, True) and p.solid
    merged = merge_parts(parts, prefix=f"{name}/")
    with Sdf.ChangeBlock():        # plain Sdf edits: one notice for the whole chunk
        root = Sdf.PrimSpec(layer, name, Sdf.SpecifierDef, "Xform")
        layer.defaultPrim = name
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for cls, cm in merged.items():
            _author_mesh(root, cls, cm, solid_by_cls[cls])
            lo, hi = np.minimum(lo, cm.vertices.min(0)), np.maximum(hi, cm.vertices.max(0))
        if np.isfinite(lo).all():
            _attr(root, UsdGeom.Tokens.extentsHint, Sdf.ValueTypeNames.Float3Array,
                  Vt.Vec3fArray([tuple(lo), tuple(hi)]))
    prov = provenance("proxy-chunk", params or {}, chunk=[int(key[0]), int(key[1])],
                      inputsHash=inputs_hash,
                      triangles={c: int(cm.n_faces) for c, cm in merged.items()})
    return save_layer(layer, path, prov)


def _root_layer(keys: list[tuple[int, int]], folder_name: str):
    """Root proxy layer built with Sdf (no composition, so payload files need not exist yet)."""

    layer = Sdf.Layer.CreateAnonymous(".usdc")
    layer.defaultPrim = WORLD.strip("/")
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, UsdGeom.Tokens.z)
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
    world = Sdf.CreatePrimInLayer(layer, WORLD)
    world.specifier = Sdf.SpecifierDef
    world.typeName = "Xform"
    proxy = Sdf.CreatePrimInLayer(layer, PROXY_PATH)
    proxy.specifier = Sdf.SpecifierDef
    proxy.typeName = "Xform"
    for key in sorted(keys):
        spec = Sdf.PrimSpec(proxy, chunk_prim_name(*key), Sdf.SpecifierDef, "Xform")
        spec.payloadList.Prepend(Sdf.Payload(f"./{folder_name}/{chunk_file_name(*key)}"))
    return layer


def read_chunk_map(path: str | Path) -> dict[str, str]:
    """Chunk name -> inputs hash stored in a proxy root layer ({} if none or unreadable)."""
    p = Path(path)
    if not p.is_file():
        return {}
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(p))
    except Exception:
        return {}
    if layer is None:
        return {}
    return {str(k): str(v) for k, v in dict(layer.customLayerData.get("lsd3d", {})
                                             .get("chunks", {})).items()}


def chunk_file_hash(path: Path) -> str | None:
    if not path.is_file():
        return None
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path), metadataOnly=True)
    except Exception:
        return None
    if layer is None:
        return None
    return layer.customLayerData.get("lsd3d", {}).get("inputsHash")


def write_root_layer(path: str | Path, chunk_hashes: dict[tuple[int, int], str],
                     params: dict | None = None, layout_hash: str = "",
                     extra: dict | None = None) -> Path:

    path = Path(path)
    layer = _root_layer(list(chunk_hashes), chunks_dir(path).name)
    prov = provenance("proxy", params or {}, layoutHash=layout_hash,
                      chunks={chunk_prim_name(*k): h for k, h in sorted(chunk_hashes.items())},
                      **(extra or {}))
    return save_layer(layer, path, prov)


def write_proxy(parts: dict[tuple[int, int], list[MeshPart]], path: str | Path,
                hashes: dict[tuple[int, int], str] | None = None, layout_hash: str = "",
                params: dict | None = None) -> Path:
    """Write prebuilt parts: every chunk layer, then the root layer listing them."""
    path = Path(path)
    hashes = hashes or {}
    folder = chunks_dir(path)
    for key, ps in parts.items():
        write_chunk_layer(ps, key, folder / chunk_file_name(*key), hashes.get(key, ""), params)
    return write_root_layer(path, {k: hashes.get(k, "") for k in parts}, params, layout_hash)


@dataclass
class BuildReport:
    path: Path
    built: list[tuple[int, int]] = field(default_factory=list)
    skipped: list[tuple[int, int]] = field(default_factory=list)
    root_written: bool = False
    seconds: float = 0.0
    triangles: dict[str, int] = field(default_factory=dict)


def layout_hash(layout, feature_bytes=_feature_bytes) -> str:
    h = hashlib.sha256()
    for f in sorted(layout.features(), key=lambda f: (type(f).__name__, f.id)):
        h.update(feature_bytes(f))
    h.update(repr((layout.extent, layout.chunk_size)).encode())
    return h.hexdigest()


def build_proxy_layer(layout, path: str | Path, chunks=None, params=None, force: bool = False,
                      progress: bool = False, max_chunks: int | None = None) -> BuildReport:
    """Build (only what changed) and write the proxy layer at ``path``.

    ``chunks``: keys to build (default: every chunk of the layout's area). More than
    limits.CHUNKS chunks (or ``max_chunks``) are refused before anything is built.
    Chunks whose inputs hash matches the one stored in their file are skipped.
    With an explicit ``chunks`` list, chunks already listed in an existing root
    layer stay listed; without it the root lists exactly the layout's chunks
    (files of chunks no longer in the layout are removed).
    """

    t0 = time.perf_counter()
    path = Path(path)
    if path.suffix.lower() not in (".usdc", ".usda", ".usd"):
        raise InputError(f"{path}: the proxy layer must be a .usdc, .usda or .usd file")
    if chunks is not None:
        chunks = [tuple(int(v) for v in k) for k in chunks]
    check_chunk_count(layout, None if chunks is None else len(chunks), max_chunks)
    params = params or ProxyParams()
    builder = ProxyBuilder(layout, params)
    keys = builder.chunks(max_chunks) if chunks is None else chunks
    folder = chunks_dir(path)
    # Chunk files are rewritten and pruned below: never through a planted link.
    safepaths.check_tree(folder, path.absolute().parent, "proxy chunk folder")
    old_map = read_chunk_map(path)
    new_map: dict[tuple[int, int], str] = {}
    if chunks is not None:
        for name, h in old_map.items():
            try:
                k = parse_chunk_prim_name(name)
            except ValueError:
                continue
            if (folder / chunk_file_name(*k)).is_file():
                new_map[k] = h
    report = BuildReport(path)
    pdict = params.as_dict()
    it = keys
    if progress:
        # local import: not loaded for --help
        from tqdm import tqdm
        it = tqdm(keys, desc="proxy chunks", unit="chunk")
    for key in it:
        inp = builder.inputs(key)
        cfile = folder / chunk_file_name(*key)
        if not force and chunk_file_hash(cfile) == inp.hash:
            report.skipped.append(key)
        else:
            parts = builder.build(key, inp)
            write_chunk_layer(parts, key, cfile, inp.hash, pdict)
            report.built.append(key)
            for p in parts:
                report.triangles[p.cls] = report.triangles.get(p.cls, 0) + p.n_faces
        new_map[key] = inp.hash
    if chunks is None and folder.is_dir():
        keep = {chunk_file_name(*k) for k in new_map}
        for f in folder.glob("chunk_*.usdc"):
            if f.name not in keep:
                safepaths.unlink(f, folder, "proxy chunk file")
    new_names = {chunk_prim_name(*k): h for k, h in new_map.items()}
    lhash = layout_hash(layout, builder.feature_bytes)
    if force or new_names != old_map or not path.is_file() or _root_layout_hash(path) != lhash:
        write_root_layer(path, new_map, pdict, lhash)
        report.root_written = True
    report.seconds = time.perf_counter() - t0
    return report


def _root_layout_hash(path: Path) -> str | None:
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path), metadataOnly=True)
    except Exception:
        return None
    return None if layer is None else layer.customLayerData.get("lsd3d", {}).get("layoutHash")


# --------------------------------------------------------------------------- reading
def read_proxy(path: str | Path, chunks=None) -> dict[tuple[int, int], dict[str, ClassMesh]]:
    """Meshes of a proxy layer (or any stage with /World/Proxy), per chunk and class.

    Only the requested chunks' payloads are loaded (default: all).
    """

    stage = open_stage(path, load=False)
    root = stage.GetPrimAtPath(PROXY_PATH)
    if not root or not root.IsValid():
        raise InputError(f"{path}: no {PROXY_PATH} prim (not a proxy layer)")
    want = None if chunks is None else {tuple(k) for k in chunks}
    out = {}
    # unloaded payload prims are not "children" under the default predicate
    for child in root.GetFilteredChildren(Usd.PrimIsActive & Usd.PrimIsDefined
                                          & ~Usd.PrimIsAbstract):
        try:
            key = parse_chunk_prim_name(child.GetName())
        except ValueError:
            continue
        if want is not None and key not in want:
            continue
        stage.Load(child.GetPath())
        meshes = {}
        for prim in Usd.PrimRange(stage.GetPrimAtPath(child.GetPath())):
            if not prim.IsA(UsdGeom.Mesh):
                continue
            meshes[prim.GetName()] = class_mesh_from_prim(prim)
        out[key] = meshes
    return out


GROUND_LEVEL_CLASSES = ("road", "sidewalk", "terrain")


def ground_level(path: str | Path) -> float | None:
    """Median height of the proxy's road, sidewalk and terrain vertices, one chunk loaded at a
    time (a 10 km proxy is never held whole): the height at which the ground beyond the scene
    continues it (env.farfield). None when the proxy has none of them."""
    stage = open_stage(path, load=False)
    root = stage.GetPrimAtPath(PROXY_PATH)
    if not root or not root.IsValid():
        raise InputError(f"{path}: no {PROXY_PATH} prim (not a proxy layer)")
    medians, weights = [], []
    for child in root.GetFilteredChildren(Usd.PrimIsActive & Usd.PrimIsDefined
                                          & ~Usd.PrimIsAbstract):
        stage.Load(child.GetPath())
        z = [np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get() or [],
                        np.float64).reshape(-1, 3)[:, 2]
             for prim in Usd.PrimRange(child) if prim.IsA(UsdGeom.Mesh)
             and (UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get() or [""])[0]
             in GROUND_LEVEL_CLASSES]
        stage.Unload(child.GetPath())
        z = np.concatenate(z) if z else np.zeros(0)
        z = z[np.isfinite(z)]
        if len(z):
            medians.append(float(np.median(z)))
            weights.append(len(z))
    if not medians:
        return None
    order = np.argsort(medians)     # the vertex-weighted median of the chunks' medians
    cum = np.cumsum(np.asarray(weights, np.float64)[order])
    return float(np.asarray(medians)[order][np.searchsorted(cum, cum[-1] / 2.0)])


def class_mesh_from_prim(prim) -> ClassMesh:
    mesh = UsdGeom.Mesh(prim)
    where = str(prim.GetPath())
    pts = np.asarray(mesh.GetPointsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if len(counts) and not np.all(counts == 3):
        raise InputError(f"{where}: proxy meshes must be triangles")
    faces = idx.reshape(-1, 3).astype(np.int32)
    labels = UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get()
    cls = str(labels[0]) if labels else prim.GetName()
    pid_attr = prim.GetAttribute(PART_IDS_ATTR)
    part_ids = tuple(pid_attr.Get() or ()) if pid_attr else ()
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(PART_INDEX_PRIMVAR)
    fp = np.asarray(pv.Get(), dtype=np.int32) if pv and pv.HasValue() else np.zeros(len(faces), np.int32)
    id_attr = prim.GetAttribute(ID_ATTR)
    return ClassMesh(pts, faces, cls, part_ids, fp, name=str(id_attr.Get()) if id_attr else where)


def proxy_arrays(path: str | Path, chunks=None):
    """All proxy meshes of a proxy layer concatenated (chunks and classes in sorted order):
    vertices (n,3), faces (m,3) int64, face class ids (m,) int32 (lsd3d_usd.semantics)."""
    # local import: not loaded for --help
    from lsd3d_usd.semantics import CLASS_ID
    vs, fs, ids, base = [], [], [], 0
    for key, meshes in sorted(read_proxy(path, chunks).items()):
        for name in sorted(meshes):
            cm = meshes[name]
            if cm.n_faces == 0:
                continue
            vs.append(cm.vertices)
            fs.append(cm.faces.astype(np.int64) + base)
            ids.append(np.full(cm.n_faces, CLASS_ID.get(cm.cls, -1), np.int32))
            base += len(cm.vertices)
    if not fs:
        raise InputError(f"{path}: the proxy has no geometry")
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(ids)
