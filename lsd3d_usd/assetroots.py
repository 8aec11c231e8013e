"""Composition stays inside the scene: every file a stage composes or names.

A scene is self-contained: its sublayers, references, payloads and asset-valued attributes
(env textures, ...) resolve inside its folder. A shared asset library elsewhere is allowed
only when the user names it: ``LSD3D_ASSET_ROOTS`` (folders, separated by ``:``) — a
setting of the user, never of the scene, since the scene is the untrusted input.

``outside_paths`` lists what a stage's layers name outside the allowed folders, without
loading payloads (each layer's composition arcs are read as written); ``check_inside``
refuses with one line (``render``, ``eval``, ``generate``, layout readers), ``validate``
reports each one (``lsd3d:OutsideScene``).
"""
from __future__ import annotations

import os
from pathlib import Path

from pxr import Sdf

from lsd3d_usd.errors import InputError

ASSET_ROOTS_ENV = "LSD3D_ASSET_ROOTS"


def allowed_roots(*roots) -> list[Path]:
    """Real paths of ``roots`` plus the folders named by LSD3D_ASSET_ROOTS."""
    out = [Path(r).resolve() for r in roots]
    for r in os.environ.get(ASSET_ROOTS_ENV, "").split(os.pathsep):
        if r.strip():
            out.append(Path(r.strip()).expanduser().resolve())
    return out


def _inside(path: str, roots: list[Path]) -> bool:
    real = Path(path).resolve()
    return any(real.is_relative_to(r) for r in roots)


def _assets(v) -> list:
    if isinstance(v, Sdf.AssetPath):
        return [v]
    try:
        return [a for a in v if isinstance(a, Sdf.AssetPath)]
    except TypeError:
        return []


def _asset_values(layer: Sdf.Layer) -> list[tuple[str, str]]:
    """(property path, asset path as written) of every asset value authored in ``layer``."""
    found: list[tuple[str, str]] = []

    def visit(path):
        if not path.IsPropertyPath():
            return
        spec = layer.GetAttributeAtPath(path)
        if spec is None or spec.typeName not in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
            return
        values = [spec.default] if spec.HasDefaultValue() else []
        values += [layer.QueryTimeSample(path, t) for t in layer.ListTimeSamplesForPath(path)]
        for v in values:
            found.extend((str(path), a.path) for a in _assets(v) if a.path)
    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return found


def outside_paths(stage, roots: list[Path], limit: int = 100) -> list[tuple[str, str]]:
    """[(where, path)] of layers and named files outside ``roots`` (real paths): where is
    the layer (and property) naming it."""
    out: list[tuple[str, str]] = []
    for layer in stage.GetUsedLayers():
        if layer.anonymous:
            for dep in layer.GetCompositionAssetDependencies():
                if not os.path.isabs(dep) or _inside(dep, roots):
                    continue
                out.append((layer.identifier, dep))
            continue
        real = layer.realPath
        if real and not _inside(real, roots):
            out.append(("layer stack", real))
            continue
        for dep in layer.GetCompositionAssetDependencies():
            if not _inside(layer.ComputeAbsolutePath(dep), roots):
                out.append((real, dep))
        for prop, asset in _asset_values(layer):
            if not _inside(layer.ComputeAbsolutePath(asset), roots):
                out.append((f"{real}: {prop}", asset))
        if len(out) >= limit:
            break
    # name the layer that composes an outside file before the outside layer itself
    out.sort(key=lambda e: e[0] == "layer stack")
    return out[:limit]


def check_inside(stage, roots: list[Path], what: str) -> None:
    """Refuse (one line) a stage that composes or names a file outside ``roots``."""
    bad = outside_paths(stage, roots, limit=10)
    if bad:
        where, path = bad[0]
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise InputError(f"{where}: names {path!r}, outside {what}{more}; a scene is "
                         f"self-contained unless {ASSET_ROOTS_ENV} names the folder "
                         "(docs/limits.md)")


def folder_of(path) -> Path:
    """The folder a scene path (scene folder or a USD file) is self-contained in."""
    p = Path(path).absolute()
    return p if p.is_dir() else p.parent


SCENE_ROOT_FILE = "scene.usda"   # scene.ROOT_FILE (this module sits below scene.py)


def scene_roots(stage, path) -> list[Path]:
    """The folders the stage at ``path`` may read: its own, and for a file composed over
    scenes (a rig layer of `render --rig`, sublayering ../scene/scene.usda) the folders of
    those scenes, which are then held to the same rule."""
    folders = [folder_of(path)]
    p = Path(path)
    if p.is_file() and p.name != SCENE_ROOT_FILE:
        root = stage.GetRootLayer()
        for sub in root.subLayerPaths:
            q = Path(root.ComputeAbsolutePath(sub))
            if q.name == SCENE_ROOT_FILE and q.is_file():
                folders.append(q.parent)
    return folders


def check_scene(stage, path, *extra) -> None:
    """``check_inside`` for the scene (or file) at ``path`` (see ``scene_roots``); ``extra``
    folders also allowed."""
    check_inside(stage, allowed_roots(*scene_roots(stage, path), *extra),
                 f"the scene folder {folder_of(path)}")
