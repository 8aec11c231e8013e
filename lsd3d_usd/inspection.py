"""`lsd3d-usd inspect`: layer stack with provenance, prim tree with counts, surfel statistics,
disk use (per layer, and per folder of a scene), and how other USD tools read our schema."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdVol

import lsd3d_usd
from lsd3d_usd import scene
from lsd3d_usd.assetroots import check_scene
from lsd3d_usd.diagnostics import captured_stderr
from lsd3d_usd.errors import InputError
from lsd3d_usd.splats.usdio import particle_bounds, read_surfels


def human_size(n: int) -> str:
    """Bytes as people read them: 512 B, 3.4 kB, 159.2 MB, 1.1 GB (powers of 1000)."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def _tree_bytes(path: Path) -> int:
    """Bytes of the files under ``path`` (symbolic links not followed)."""
    if path.is_file():
        return path.stat().st_size
    total = 0
    for p in path.rglob("*"):
        if p.is_file() and not p.is_symlink():
            total += p.stat().st_size
    return total


def layer_bytes(path: Path) -> int:
    """A layer file's bytes plus its per-chunk files (``<stem>_chunks/``, brought in by
    payloads), which belong to it."""
    chunks = path.with_name(f"{path.stem}_chunks")
    return path.stat().st_size + (_tree_bytes(chunks) if chunks.is_dir() else 0)


def disk_use(root_file: Path) -> dict:
    """Disk use of a scene folder (``root_file`` its scene.usda): the total and every folder
    (two levels: layers/proxy_chunks, ggds/<run>) and file at the top, largest first. For
    another USD file: the file alone."""
    root = root_file.parent
    if root_file.name != scene.ROOT_FILE or not (root / scene.LAYERS_DIR).is_dir():
        return {"total_bytes": root_file.stat().st_size, "folders": {}}
    folders, total = {}, 0
    for p in sorted(root.iterdir()):
        if p.is_symlink():
            continue
        n = _tree_bytes(p)
        total += n
        folders[p.name + ("/" if p.is_dir() else "")] = n
        if p.is_dir() and p.name in (scene.LAYERS_DIR, scene.RUNS_DIR):
            for q in sorted(p.iterdir()):
                if q.is_dir() and not q.is_symlink():
                    folders[f"{p.name}/{q.name}/"] = _tree_bytes(q)
    return {"total_bytes": total, "folders": folders}


def _layer_summary(layer: Sdf.Layer, muted: bool = False) -> dict:
    prov = scene.read_provenance(layer)
    path = Path(layer.realPath) if layer.realPath else None
    return {"identifier": layer.realPath or layer.identifier,
            "format": layer.GetFileFormat().formatId, "muted": muted,
            "bytes": layer_bytes(path) if path and path.is_file() else None,
            "provenance": {k: (v if isinstance(v, (str, int, float, bool)) else str(v))
                           for k, v in prov.items()}}


def layer_stack(stage: Usd.Stage) -> list[dict]:
    root = stage.GetRootLayer()
    out = [_layer_summary(layer) for layer in stage.GetLayerStack(includeSessionLayers=False)]
    for muted in root.customLayerData.get("lsd3d", {}).get("mutedLayers", []):
        p = Path(root.realPath).parent / scene.LAYERS_DIR / muted
        if p.is_file():
            out.append(_layer_summary(Sdf.Layer.FindOrOpen(str(p)), muted=True))
    return out


def _prim_counts(prim: Usd.Prim) -> dict:
    info: dict = {}
    if prim.IsA(UsdVol.ParticleField):
        a = prim.GetAttribute("positions")
        v = a.Get() if a else None
        info["particles"] = len(v) if v is not None else 0
    elif prim.IsA(UsdGeom.Mesh):
        m = UsdGeom.Mesh(prim)
        pts, counts = m.GetPointsAttr().Get(), m.GetFaceVertexCountsAttr().Get()
        info["points"] = len(pts) if pts is not None else 0
        info["faces"] = len(counts) if counts is not None else 0
    elif prim.IsA(UsdGeom.BasisCurves):
        c = UsdGeom.BasisCurves(prim).GetCurveVertexCountsAttr().Get()
        info["curves"] = len(c) if c is not None else 0
    if prim.HasAuthoredPayloads():
        info["payload"] = "loaded" if prim.IsLoaded() else "unloaded"
    if prim.GetVariantSets().GetNames():
        info["variants"] = {n: prim.GetVariantSets().GetVariantSet(n).GetVariantSelection()
                            for n in prim.GetVariantSets().GetNames()}
    return info


def prim_tree(stage: Usd.Stage, max_depth: int = 4) -> list[dict]:
    rows = []
    it = iter(Usd.PrimRange.Stage(stage, Usd.PrimAllPrimsPredicate))
    for prim in it:
        depth = prim.GetPath().pathElementCount - 1
        if depth >= max_depth:
            it.PruneChildren()
            continue
        kids = len(prim.GetAllChildren())
        rows.append({"path": str(prim.GetPath()), "depth": depth, "type": prim.GetTypeName() or "",
                     "children": kids, **_prim_counts(prim)})
        if depth == max_depth - 1 and kids:
            rows[-1]["pruned"] = True
    return rows


def _pct(a: np.ndarray) -> dict:
    if a.size == 0:
        return {}
    q = np.percentile(a, [0, 5, 50, 95, 100])
    return dict(zip(("min", "p5", "median", "p95", "max"), [round(float(x), 6) for x in q]))


def surfel_stats(prim: Usd.Prim) -> dict:
    """Count, bounds and distributions of a ParticleField prim. A prim that cannot be read
    as surfels (arrays that do not fit the positions) is reported, not fatal: validate
    names the defect."""
    stats = {"path": str(prim.GetPath()), "type": prim.GetTypeName()}
    try:
        with np.errstate(all="ignore"):
            f = read_surfels(prim)
    except (InputError, ValueError) as e:
        stats.update(count=None, sh_degree=None, problem=str(e))
        return stats
    stats.update(count=f.n, sh_degree=f.sh_degree)
    if f.n:
        ext = particle_bounds(prim)       # the bounds validate checks (3D Gaussians keep 3 axes)
        if ext is not None:
            stats["extent"] = [ext[0].round(3).tolist(), ext[1].round(3).tolist()]
        with np.errstate(all="ignore"):
            stats["opacity"] = _pct(f.opacities)
            stats["scale_max"] = _pct(f.scales.max(axis=1))
            stats["scale_aspect"] = _pct(f.scales.max(axis=1) / np.maximum(f.scales.min(axis=1), 1e-12))
            stats["color_dc_mean"] = f.colors().mean(axis=0).round(4).tolist()
        if f.semantic_ids is not None:
            ids, counts = np.unique(f.semantic_ids, return_counts=True)
            names = f.semantic_classes
            stats["classes"] = {(names[i] if 0 <= i < len(names) else str(int(i))): int(c)
                                for i, c in zip(ids, counts)}
    return stats


def schema_note(stage: Usd.Stage) -> dict | None:
    """How a USD tool that does not import lsd3d_usd reads the stage's Lsd3dSurfelField
    prims: the plugin path that registers the schema, and whether the root layer names a
    fallback type for it. None when the stage has none of our prims."""
    if not any(p.GetTypeName() == lsd3d_usd.SURFEL_TYPE for p in stage.Traverse()):
        return None
    root = stage.GetRootLayer()
    info = root.pseudoRoot.GetInfo("fallbackPrimTypes") if root.pseudoRoot.HasInfo("fallbackPrimTypes") else {}
    fallback = list(dict(info).get(lsd3d_usd.SURFEL_TYPE, []))
    return {"type": lsd3d_usd.SURFEL_TYPE, "plugin_path": str(lsd3d_usd.SCHEMA_DIR),
            "fallback": fallback}


def preview_stats(stage: Usd.Stage) -> dict | None:
    """The surfel previews (UsdGeom.Points under /World/SurfelPreview, splats.preview) of the
    loaded chunks: how many prims and points, or None when the stage has none."""
    root = stage.GetPrimAtPath(scene.SURFEL_PREVIEW_PATH)
    if not root:
        return None
    prims = [p for p in root.GetChildren() if p.IsA(UsdGeom.Points)]
    points = 0
    for p in prims:
        pts = UsdGeom.Points(p).GetPointsAttr().Get()
        points += len(pts) if pts is not None else 0
    return {"path": scene.SURFEL_PREVIEW_PATH, "prims": len(prims), "points": points}


def inspect(path: str | Path, max_depth: int = 4) -> dict:
    with captured_stderr():
        stage = scene.open_stage(path)
        check_scene(stage, path)    # as render and eval: a scene reads only its own folder
        meta = {"upAxis": UsdGeom.GetStageUpAxis(stage),
                "metersPerUnit": UsdGeom.GetStageMetersPerUnit(stage),
                "defaultPrim": stage.GetRootLayer().defaultPrim or None}
        return {"path": str(path), "stage": meta, "layers": layer_stack(stage),
                "size": disk_use(Path(stage.GetRootLayer().realPath)),
                "prims": prim_tree(stage, max_depth),
                "surfels": [surfel_stats(p) for p in stage.Traverse() if p.IsA(UsdVol.ParticleField)],
                "preview": preview_stats(stage),
                "schema": schema_note(stage)}


def flatten(path: str | Path) -> str:
    with captured_stderr():
        stage = scene.open_stage(path)
        check_scene(stage, path)
        return stage.Flatten().ExportToString()


def format_text(info: dict) -> str:
    out = [f"{info['path']}", f"  upAxis={info['stage']['upAxis']} metersPerUnit="
           f"{info['stage']['metersPerUnit']} defaultPrim={info['stage']['defaultPrim']}", "", "Layers (strongest first):"]
    for layer in info["layers"]:
        prov = layer["provenance"]
        bits = [f"{k}={prov[k]}" for k in ("step", "created", "seed", "version") if k in prov]
        size = f", {human_size(layer['bytes'])}" if layer.get("bytes") is not None else ""
        out.append(f"  {'[muted] ' if layer['muted'] else ''}{layer['identifier']} ({layer['format']}{size})"
                   + (f"  {' '.join(bits)}" if bits else ""))
    size = info.get("size")
    if size and size["folders"]:
        out += ["", f"Disk use: {human_size(size['total_bytes'])}"]
        rows = [(f"{'  ' * name.rstrip('/').count('/')}{name}", n)
                for name, n in _folder_order(size["folders"])]
        width = max(len(label) for label, _ in rows)
        out += [f"  {label:{width}s} {human_size(n):>9s}" for label, n in rows]
    out += ["", "Prims:"]
    for row in info["prims"]:
        extra = {k: v for k, v in row.items() if k not in ("path", "depth", "type", "children")}
        name = row["path"].rsplit("/", 1)[-1] or "/"
        desc = " ".join(f"{k}={v}" for k, v in extra.items())
        out.append(f"  {'  ' * row['depth']}{name} [{row['type'] or '-'}]"
                   + (f" children={row['children']}" if row["children"] else "") + (f" {desc}" if desc else ""))
    if info["surfels"]:
        out += ["", "Surfel fields:"]
        for s in info["surfels"]:
            if s.get("problem"):
                out.append(f"  {s['path']} ({s['type']}): cannot be read: {s['problem']}")
                continue
            out.append(f"  {s['path']} ({s['type']}): {s['count']} surfels, SH degree {s['sh_degree']}")
            for k in ("extent", "opacity", "scale_max", "scale_aspect", "color_dc_mean", "classes"):
                if k in s:
                    out.append(f"    {k}: {s[k]}")
    pv = info.get("preview")
    if pv:
        out += ["", f"Surfel preview for tools without ParticleField: {pv['path']}: {pv['points']} "
                    f"points in {pv['prims']} UsdGeom.Points prim(s) (purpose proxy; docs/usd.md)"]
    note = info.get("schema")
    if note:
        how = (f"read the surfel prims as {', '.join(note['fallback'])} with the official attribute "
               "APIs (the root layer's fallbackPrimTypes)" if note["fallback"] else
               "see the surfel prims as an unknown type (the root layer names no fallbackPrimTypes)")
        out += ["", f"Schema: USD tools that do not import lsd3d_usd {how}; to give them "
                    f"{note['type']}: export PXR_PLUGINPATH_NAME={note['plugin_path']} "
                    "(`lsd3d-usd plugin-path`)"]
    return "\n".join(out)


def _folder_order(folders: dict) -> list:
    """Top-level entries largest first, each followed by its sub-folders largest first."""
    tops = sorted((k for k in folders if not k.rstrip("/").count("/")), key=lambda k: -folders[k])
    rows = []
    for t in tops:
        rows.append((t, folders[t]))
        subs = [k for k in folders if k != t and k.startswith(t) and k.rstrip("/").count("/") == 1]
        rows += sorted(((k, folders[k]) for k in subs), key=lambda kv: -kv[1])
    return rows


def format_json(info: dict) -> str:
    return json.dumps(info, indent=2, default=str)
