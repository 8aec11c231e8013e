"""Foundation commands: validate, inspect, scene (layer stack management)."""
from __future__ import annotations

import argparse
import sys


def _validate(args) -> int:
    from lsd3d_usd import validation

    problems = validation.validate(args.path)
    print(validation.report(args.path, problems, args.json))
    return 1 if any(p.severity == "error" for p in problems) else 0


def _inspect(args) -> int:
    from lsd3d_usd import inspection

    if args.flatten:
        sys.stdout.write(inspection.flatten(args.path))
        return 0
    info = inspection.inspect(args.path, max_depth=args.depth)
    print(inspection.format_json(info) if args.json else inspection.format_text(info))
    return 0


def _scene(args) -> int:
    from lsd3d_usd.errors import InputError
    from lsd3d_usd.scene import Scene

    sc = Scene.open(args.scene)
    if args.action == "layers":
        for info in sc.layers():
            prov = info.provenance
            flags = "muted" if info.muted else "active"
            flags += "" if info.exists else ", missing file"
            print(f"{info.name:32s} {flags:8s} {prov.get('step', '')} {prov.get('created', '')}")
        return 0
    if not args.layer:
        raise InputError(f"scene {args.action}: name a layer (see `lsd3d-usd scene layers {args.scene}`)")
    if args.action == "mute":
        sc.mute(args.layer)
    elif args.action == "unmute":
        sc.unmute(args.layer)
    elif args.action == "remove":
        sc.remove_layer(args.layer, delete_file=args.delete)
    print(f"{args.action}d {args.layer}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "validate", help="check a USD file or scene against USD's validators and the surfel schema",
        description="Run usd-core's UsdValidation validators plus lsd3d checks: unknown prim types; "
                    "missing upAxis/metersPerUnit/defaultPrim; array lengths; finite values; opacity in "
                    "[0,1]; scales > 0; unit quaternions; SH degree vs coefficient count; extent covering "
                    "the particles; unresolvable asset paths; bulk surfel data in .usda. Works on any USD "
                    "file. Exit 0 when valid, 1 with one line per problem.")
    p.add_argument("path", help="a USD file (.usda/.usdc/.usd) or a scene folder holding scene.usda")
    p.add_argument("--json", action="store_true", help="print a JSON report instead of text")
    p.set_defaults(func=_validate)

    p = sub.add_parser(
        "inspect", help="show layer stack with provenance, prim tree with counts, surfel statistics",
        description="Summarise a USD file or scene: its layer stack (strongest first, with each layer's "
                    "provenance), the prim tree with types and counts, and statistics per surfel prim. "
                    "--flatten prints the composed stage as usda, like `usdcat --flatten`.")
    p.add_argument("path", help="a USD file or a scene folder holding scene.usda")
    p.add_argument("--flatten", action="store_true", help="print the flattened composed stage as usda")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--depth", type=int, default=4, help="prim tree depth to show (default 4)")
    p.set_defaults(func=_inspect)

    p = sub.add_parser(
        "scene", help="list, mute, unmute or remove the layers of a scene",
        description="Manage a scene folder's layer stack. Muting is persistent: the layer leaves the "
                    "root layer's subLayers (every USD tool then sees it muted) and is remembered in the "
                    "root's customLayerData so `unmute` restores it in its place.")
    p.add_argument("action", choices=("layers", "mute", "unmute", "remove"))
    p.add_argument("scene", help="scene folder")
    p.add_argument("layer", nargs="?", help="layer name, e.g. surfels or ggds_20261122-101500")
    p.add_argument("--delete", action="store_true", help="with remove: also delete the layer file")
    p.set_defaults(func=_scene)
