#!/usr/bin/env python
"""Import a scene into Blender (the ``bpy`` module, ``pip install -e ".[interop]"``) as a user of
Blender's USD importer would, and report what it made; optionally render a Workbench image
from one of the scene's cameras.

Runs with bpy alone: it never imports lsd3d_usd or usd-core (bpy bundles its own USD, and two
USD libraries in one process do not mix). Prints (or writes with --json) a JSON report:

    blender         Blender's version
    objects         object count per type
    proxy           {chunk: meshes} under /World/Proxy
    preview         {chunk: {points, mean_color, mean_radius}}: the Points previews (point
                    cloud objects) under /World/SurfelPreview
    surfels         ParticleField prims (/World/Surfels/Chunk_*) that became more than an empty
    actors          {actor: {role, animated, meshes: {name: {displayColor, material}}}}: the
                    mean displayColor attribute and the material's base colour (or null)
    cameras, lights [(name, type)]
    render          {path, covered}: the fraction of pixels an object covers (alpha > 0)

    python tools/blender_import.py SCENE [--json out.json] [--render out.png --camera Train_000
        [--resolution 480x270] [--only-preview]]
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from pathlib import Path

import bpy
import numpy as np


def _base(name: str) -> str:
    """An object's name without Blender's ``.001`` duplicate suffix (prims of the same name
    under /World/Proxy, /World/Surfels and /World/SurfelPreview)."""
    return re.sub(r"\.\d{3}$", "", name)


def _ancestors(obj) -> list[str]:
    out = []
    while obj.parent is not None:
        obj = obj.parent
        out.append(_base(obj.name))
    return out


def _colour(mesh_data):
    attr = mesh_data.attributes.get("displayColor")
    if attr is None or not len(attr.data):
        return None
    vals = np.zeros(len(attr.data) * 4, np.float32)
    attr.data.foreach_get("color", vals)
    return vals.reshape(-1, 4)[:, :3].mean(0).round(4).tolist()


def _material_colour(mesh_data):
    """Base colour of the mesh's first material (its Principled BSDF, as the importer makes
    one of a UsdPreviewSurface), or None."""
    for mat in mesh_data.materials:
        if mat and mat.use_nodes:
            for node in mat.node_tree.nodes:
                if node.type == "BSDF_PRINCIPLED":
                    return [round(float(c), 4) for c in node.inputs["Base Color"].default_value[:3]]
    return None


def report(scene_path: str) -> dict:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    # proxy purpose included: the surfel preview is the ParticleField's proxy (Blender's
    # importer skips proxy prims unless asked)
    bpy.ops.wm.usd_import(filepath=str(scene_path), import_proxy=True)
    sc = bpy.context.scene
    objs = list(bpy.data.objects)
    out = {"blender": bpy.app.version_string,
           "objects": dict(Counter(o.type for o in objs)),
           "proxy": {}, "preview": {}, "surfels": 0, "actors": {}, "cameras": [], "lights": []}
    for o in objs:
        up = _ancestors(o)
        if o.type == "MESH" and len(up) >= 2 and up[1] == "Proxy":
            out["proxy"][up[0]] = out["proxy"].get(up[0], 0) + 1
        elif o.type == "POINTCLOUD" and up and up[0] == "SurfelPreview":
            d = o.data
            n = len(d.points)
            col = np.zeros(n * 4, np.float32)
            d.attributes["displayColor"].data.foreach_get("color", col)
            rad = np.zeros(n, np.float32)
            d.attributes["radius"].data.foreach_get("value", rad)
            out["preview"][_base(o.name)] = {"points": n,
                                             "mean_color": col.reshape(-1, 4)[:, :3].mean(0).tolist(),
                                             "mean_radius": float(rad.mean()) if n else 0.0}
        elif up and up[0] == "Surfels" and o.children:
            out["surfels"] += 1
        elif o.type == "CAMERA":
            out["cameras"].append(_base(o.name))
        elif o.type == "LIGHT":
            out["lights"].append([_base(o.name), o.data.type])
    start, end = sc.frame_start, sc.frame_end
    actors = [o for o in objs if o.parent is not None and _base(o.parent.name) in ("Moving", "Parked")]
    sc.frame_set(start)
    first = {o.name: np.array(o.matrix_world) for o in actors}
    sc.frame_set(end)
    for o in actors:
        moved = float(np.abs(np.array(o.matrix_world) - first[o.name]).max())
        meshes = {_base(c.name): {"displayColor": _colour(c.data), "material": _material_colour(c.data)}
                  for c in o.children_recursive if c.type == "MESH"}
        out["actors"][_base(o.name)] = {"role": _base(o.parent.name), "animated": moved > 1e-3,
                                        "meshes": meshes}
    sc.frame_set(start)
    return out


def _attribute_material():
    """A material showing the displayColor attribute (Workbench draws point clouds in one
    colour; EEVEE reads attributes through the node tree)."""
    mat = bpy.data.materials.new("lsd3dDisplayColor")
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_name = "displayColor"
    emit = nodes.new("ShaderNodeEmission")
    mat.node_tree.links.new(attr.outputs["Color"], emit.inputs["Color"])
    mat.node_tree.links.new(emit.outputs["Emission"], nodes["Material Output"].inputs["Surface"])
    return mat


def render(path: str, camera: str, resolution: tuple[int, int], only_preview: bool,
           engine: str = "workbench") -> dict:
    sc = bpy.context.scene
    cams = [o for o in bpy.data.objects if o.type == "CAMERA" and _base(o.name) == camera]
    if not cams:
        raise SystemExit(f"blender_import: no camera {camera!r} in the imported scene")
    sc.camera = cams[0]
    for o in bpy.data.objects:
        if only_preview and o.type not in ("POINTCLOUD", "EMPTY", "CAMERA"):
            o.hide_render = True
        if only_preview and o.type == "POINTCLOUD" and "SurfelPreview" not in _ancestors(o):
            o.hide_render = True
    if engine == "eevee":   # colours as authored (emission of displayColor on the points)
        sc.render.engine = "BLENDER_EEVEE_NEXT"
        sc.eevee.taa_render_samples = 16
        mat = _attribute_material()
        for o in bpy.data.objects:
            if o.type == "POINTCLOUD":
                o.data.materials.clear()
                o.data.materials.append(mat)
        sc.view_settings.view_transform = "Standard"
    else:
        sc.render.engine = "BLENDER_WORKBENCH"
        sc.display.shading.light = "FLAT"
        sc.display.shading.color_type = "VERTEX"   # meshes' displayColor; points are grey
    sc.render.film_transparent = True
    sc.render.resolution_x, sc.render.resolution_y = resolution
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "PNG"
    sc.render.image_settings.color_mode = "RGBA"
    sc.render.filepath = str(Path(path).absolute())
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(Path(path).absolute()))
    px = np.array(img.pixels[:], np.float32).reshape(-1, 4)
    return {"path": str(path), "camera": camera, "covered": float((px[:, 3] > 0).mean())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="scene folder (its scene.usda) or a USD file")
    ap.add_argument("--json", help="write the report here (default: print it)")
    ap.add_argument("--render", help="also render a Workbench PNG here")
    ap.add_argument("--camera", default="Train_000", help="camera prim name (default Train_000)")
    ap.add_argument("--resolution", default="480x270", help="render size WxH")
    ap.add_argument("--engine", choices=("workbench", "eevee"), default="workbench",
                    help="workbench (fast; point clouds in one colour) or eevee (displayColor)")
    ap.add_argument("--only-preview", action="store_true",
                    help="render the surfel preview alone (meshes hidden)")
    args = ap.parse_args(argv)
    p = Path(args.scene)
    out = report(str(p / "scene.usda" if p.is_dir() else p))
    if args.render:
        w, h = (int(v) for v in args.resolution.lower().split("x"))
        out["render"] = render(args.render, args.camera, (w, h), args.only_preview,
                               args.engine)
    text = json.dumps(out, indent=1)
    if args.json:
        Path(args.json).write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
