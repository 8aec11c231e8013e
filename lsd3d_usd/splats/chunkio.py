"""Surfels stored per chunk: one payload per chunk of the scene's grid, so a scene of any
extent opens with nothing heavy loaded, and GGDS runs that add per-chunk opinions the same way.

On disk (a scene's layers/ folder)::

    surfels.usdc                              /World/Surfels (Xform)
                                                Chunk_<i>_<j> (Lsd3dSurfelField, payload arc)
    surfels_chunks/<inputs>/chunk_<i>_<j>.usdc  Chunk_<i>_<j> (defaultPrim): initial surfels
    ggds_<run>.usdc                           over /World/Surfels/Chunk_<i>_<j> (prepend
                                              payload), one per chunk the run has written
    ggds_<run>_chunks/chunk_<i>_<j>.usdc      over Chunk_<i>_<j>: the optimised attributes

With a preview (splats.preview, ``splats.preview_fraction`` > 0) each chunk file also holds
``Chunk_<i>_<j>_Preview`` (UsdGeom.Points, purpose proxy), brought in at
``/World/SurfelPreview/Chunk_<i>_<j>`` by a payload to that prim of the same file; a run's
chunk file holds an over of it with the run's own preview, and the run layer an over of
``/World/SurfelPreview/Chunk_<i>_<j>`` with a payload to it.

The initial surfels go to a new folder named by their inputs hash; the root layer, written
last and atomically, switches to it, and then older folders are removed. A crash mid-way
leaves the previous root pointing at its own, intact chunks.

A surfel belongs to the chunk that holds its centre (floor(x / size), floor(y / size)): no
duplicates at seams. The run's payload sits on a stronger sublayer, so its attribute opinions
win over the initial chunk's; muting or removing the run layer reverts every chunk at once;
with ``Usd.Stage.LoadNone`` neither file is read until the chunk is loaded. Nothing is authored
on the chunk prims of the root layers themselves: a local opinion there would beat every
payload. Per-chunk bookkeeping (surfel count, bounds, inputs hash) is in the root layer's
``customLayerData["lsd3d"]["chunks"]``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

import lsd3d_usd
from lsd3d_usd import safepaths
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import (
    SURFEL_PREVIEW_PATH,
    SURFELS_PATH,
    WORLD,
    author_fallback_prim_types,
    chunk_prim_name,
    parse_chunk_prim_name,
    save_layer,
)
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.splats.preview import preview_count, preview_prim_name, write_preview
from lsd3d_usd.splats.usdio import read_surfels, write_surfels

SEED_CHUNK_ATTR = "lsd3d:seedChunk"
SEED_FACE_ATTR = "lsd3d:seedFace"


def chunk_keys(positions: np.ndarray, chunk_size: float) -> np.ndarray:
    """(N, 2) int64 chunk index of each position (floor of x / size, y / size)."""
    p = np.asarray(positions, np.float64)
    return np.floor(p[:, :2] / float(chunk_size)).astype(np.int64)


def split_by_chunk(positions: np.ndarray, chunk_size: float) -> dict[tuple[int, int], np.ndarray]:
    """{chunk key: sorted indices of the positions inside it}."""
    keys = chunk_keys(positions, chunk_size)
    if not len(keys):
        return {}
    order = np.lexsort((keys[:, 1], keys[:, 0]))
    k = keys[order]
    starts = np.flatnonzero(np.r_[True, np.any(k[1:] != k[:-1], axis=1)])
    ends = np.r_[starts[1:], len(k)]
    return {(int(k[s, 0]), int(k[s, 1])): np.sort(order[s:e]) for s, e in zip(starts, ends)}


def chunk_file_name(key) -> str:
    return chunk_prim_name(*key).lower() + ".usdc"


def chunks_base(root_path) -> Path:
    """``<stem>_chunks`` beside a root layer."""
    p = Path(root_path)
    return p.with_name(f"{p.stem}_chunks")


def chunk_folder(root_path) -> Path:
    """The folder a root layer's chunk payloads point into (recorded in it), or the plain
    ``<stem>_chunks`` folder of a run layer."""
    p = Path(root_path)
    if p.is_file():
        layer = Sdf.Layer.OpenAsAnonymous(str(p), metadataOnly=True)
        rel = layer.customLayerData.get("lsd3d", {}).get("chunkFolder") if layer else None
        if rel:
            folder = (p.parent / rel).resolve()
            if not folder.is_relative_to(p.parent.resolve()) or ".." in Path(rel).parts:
                raise InputError(f"{p}: chunk folder {rel!r} lies outside {p.parent}")
            return folder
    return chunks_base(p)


def _stage():
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    return stage


def write_chunk(folder, key, field: SurfelField, provenance: dict | None = None,
                seed_faces: tuple[np.ndarray, np.ndarray] | None = None,
                preview_fraction: float = 0.0) -> Path:
    """The initial surfels of one chunk to ``folder`` (atomic), defaultPrim Chunk_<i>_<j>.
    ``seed_faces``: (proxy chunk (n, 2), face index (n,)) each surfel was seeded on.
    ``preview_fraction`` > 0: also the Points preview of that fraction (splats.preview)."""

    name = chunk_prim_name(*key)
    stage = _stage()
    prim = write_surfels(stage, f"/{name}", field)   # + the official APIs and type fallback
    UsdGeom.Imageable(prim).CreatePurposeAttr(UsdGeom.Tokens.render)
    write_preview(stage, f"/{preview_prim_name(name)}", field, preview_fraction, key)
    if seed_faces is not None:
        chunks, faces = (np.ascontiguousarray(a, np.int32) for a in seed_faces)
        if chunks.shape != (field.n, 2) or faces.shape != (field.n,):
            raise ValueError(f"seed faces of {name}: need ({field.n}, 2) and ({field.n},)")
        prim.CreateAttribute(SEED_CHUNK_ATTR, Sdf.ValueTypeNames.Int2Array).Set(
            Vt.Vec2iArray.FromNumpy(chunks))
        prim.CreateAttribute(SEED_FACE_ATTR, Sdf.ValueTypeNames.IntArray).Set(
            Vt.IntArray.FromNumpy(faces))
    stage.SetDefaultPrim(prim)
    return save_layer(stage.GetRootLayer(), Path(folder) / chunk_file_name(key), provenance)


def write_run_chunk(folder, key, field: SurfelField, attributes: tuple[str, ...],
                    provenance: dict | None = None, preview_fraction: float = 0.0) -> Path:
    """One chunk's optimised attributes of a GGDS run: overs only (atomic); with
    ``preview_fraction`` > 0 also an over of the chunk's preview with the run's surfels."""
    name = chunk_prim_name(*key)
    stage = _stage()
    prim = write_surfels(stage, f"/{name}", field, over=True, attributes=attributes)
    if preview_count(field.n, preview_fraction):
        write_preview(stage, f"/{preview_prim_name(name)}", field, preview_fraction, key, over=True)
    stage.SetDefaultPrim(prim)
    return save_layer(stage.GetRootLayer(), Path(folder) / chunk_file_name(key), provenance)


def _root(chunks: Iterable, folder_rel: str, *, define: bool, previews: Iterable = ()):
    """Root layer (Sdf, no composition): /World/Surfels with a payload per chunk; ``define``
    for the initial surfels (defs), else overs (a run layer). ``previews``: the chunks whose
    files hold a preview, each brought in at /World/SurfelPreview/Chunk_<i>_<j>."""

    layer = Sdf.Layer.CreateAnonymous(".usdc")
    spec_kind = Sdf.SpecifierDef if define else Sdf.SpecifierOver
    if define:
        author_fallback_prim_types(layer)   # its chunk prims are ours, typed by this layer
        layer.defaultPrim = WORLD.strip("/")
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, UsdGeom.Tokens.z)
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
    for path in (WORLD, SURFELS_PATH):
        spec = Sdf.CreatePrimInLayer(layer, path)
        spec.specifier = spec_kind
        if define:
            spec.typeName = "Xform"
    parent = layer.GetPrimAtPath(SURFELS_PATH)
    for key in sorted(chunks):
        spec = Sdf.PrimSpec(parent, chunk_prim_name(*key), spec_kind,
                            lsd3d_usd.SURFEL_TYPE if define else "")
        spec.payloadList.Prepend(Sdf.Payload(f"./{folder_rel}/{chunk_file_name(key)}"))
    previews = sorted(previews)
    if previews:
        group = Sdf.CreatePrimInLayer(layer, SURFEL_PREVIEW_PATH)
        group.specifier = spec_kind
        if define:
            group.typeName = "Xform"
        for key in previews:
            name = chunk_prim_name(*key)
            spec = Sdf.PrimSpec(group, name, spec_kind, "Points" if define else "")
            spec.payloadList.Prepend(Sdf.Payload(f"./{folder_rel}/{chunk_file_name(key)}",
                                                 Sdf.Path(f"/{preview_prim_name(name)}")))
            if define:   # the surfels name their stand-in (UsdGeomImageable proxyPrim)
                rel = Sdf.RelationshipSpec(parent.nameChildren[name], UsdGeom.Tokens.proxyPrim,
                                           custom=False)
                rel.targetPathList.Prepend(spec.path)
    return layer


def chunk_has_preview(path, key) -> bool:
    """Whether a chunk file holds the chunk's preview prim (read afresh: the file may have
    been rewritten since a layer of it was last opened)."""
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    return bool(layer and layer.GetPrimAtPath(f"/{preview_prim_name(chunk_prim_name(*key))}"))


def preview_fraction_of(root_path) -> float:
    """The preview fraction a surfel root layer was written with (0: none, or older)."""
    p = Path(root_path)
    if not p.is_file():
        return 0.0
    layer = Sdf.Layer.OpenAsAnonymous(str(p), metadataOnly=True)
    value = layer.customLayerData.get("lsd3d", {}).get("previewFraction") if layer else None
    try:
        return max(0.0, float(value)) if value is not None else 0.0
    except (TypeError, ValueError):
        raise InputError(f"{p}: previewFraction {value!r} is not a number") from None


def chunk_info(key, field: SurfelField, inputs_hash: str = "", preview_fraction: float = 0.0) -> dict:
    lo = field.positions.min(0) if field.n else np.zeros(3)
    hi = field.positions.max(0) if field.n else np.zeros(3)
    info = {"count": int(field.n), "bounds": [float(v) for v in (*lo, *hi)],
            "inputsHash": inputs_hash}
    if preview_fraction > 0:
        info["preview"] = preview_count(field.n, preview_fraction)
    return info


def write_root(root_path, folder, chunks: dict, provenance: dict | None = None, *,
               define: bool = True) -> Path:
    """The root layer listing ``chunks`` ({key: chunk_info}) with payloads into ``folder``
    (beside or below the root), atomically; a chunk whose info has ``"preview"`` (a point
    count > 0) also gets its preview's payload."""
    path = Path(root_path).absolute()
    rel = Path(folder).absolute().relative_to(path.parent).as_posix()
    previews = [k for k, v in chunks.items() if v.get("preview")]
    layer = _root(chunks, rel, define=define, previews=previews)
    prov = dict(provenance or {})
    prov["chunks"] = json.dumps({chunk_prim_name(*k): v for k, v in sorted(chunks.items())})
    prov["chunkFolder"] = rel
    return save_layer(layer, path, prov)


def prune_chunk_folders(root_path) -> list[Path]:
    """Remove the versioned chunk folders under ``<stem>_chunks`` the root no longer uses."""
    keep = chunk_folder(root_path)
    base = chunks_base(root_path)
    removed = []
    if base.is_dir() and keep != base:
        safepaths.check_tree(base, Path(root_path).absolute().parent, "surfel chunk folder")
        for d in base.iterdir():
            if d.is_dir() and d.resolve() != keep.resolve():
                safepaths.rmtree(d, base, "surfel chunk folder")
                removed.append(d)
    return removed


def read_chunk_map(root_path) -> dict[tuple[int, int], dict]:
    """{key: chunk_info} recorded in a root layer ({} for none, or a monolithic layer)."""

    p = Path(root_path)
    if not p.is_file():
        return {}
    layer = Sdf.Layer.OpenAsAnonymous(str(p), metadataOnly=True)
    raw = layer.customLayerData.get("lsd3d", {}).get("chunks") if layer else None
    if not raw:
        return {}
    try:
        data = json.loads(raw) if isinstance(raw, str) else dict(raw)
        return {parse_chunk_prim_name(k): dict(v) for k, v in data.items()}
    except (ValueError, TypeError) as e:
        raise InputError(f"{p}: unreadable chunk table ({e})") from None


def read_chunk(root_path, key, run_roots: Iterable = ()) -> SurfelField:
    """One chunk's surfels: the initial file with the given run chunk files (strongest first,
    those that exist) composed over it — without opening the scene."""

    base = chunk_folder(root_path) / chunk_file_name(key)
    if not base.is_file():
        raise InputError(f"{base}: no such surfel chunk file")
    runs = [chunk_folder(r) / chunk_file_name(key) for r in run_roots]
    layers = [str(p) for p in runs if p.is_file()]
    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths = layers + [str(base)]
    stage = Usd.Stage.Open(root)
    prim = stage.GetPrimAtPath(f"/{chunk_prim_name(*key)}")
    if not prim:
        raise InputError(f"{base}: no prim /{chunk_prim_name(*key)}")
    return read_surfels(prim)


def read_seed_faces(root_path, key) -> tuple[np.ndarray, np.ndarray] | None:
    """(proxy chunk (n, 2), face (n,)) of a chunk's initial surfels, or None if not recorded."""

    path = chunk_folder(root_path) / chunk_file_name(key)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath(f"/{chunk_prim_name(*key)}")
    a, b = prim.GetAttribute(SEED_CHUNK_ATTR), prim.GetAttribute(SEED_FACE_ATTR)
    if not (a and a.HasValue() and b and b.HasValue()):
        return None
    chunks = np.asarray(a.Get(), np.int64).reshape(-1, 2)
    faces = np.asarray(b.Get(), np.int64).reshape(-1)
    if len(chunks) != len(faces):
        raise InputError(f"{path}: {len(chunks)} seed chunks for {len(faces)} seed faces")
    return chunks, faces
