"""Foundation commands: validate, inspect, scene (layer stack management)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import lsd3d_usd
from lsd3d_usd import config as C
from lsd3d_usd import configtree as ct
from lsd3d_usd.cliutil import check_output_path
from lsd3d_usd.config import GenerateConfig
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import Scene, atomic_write_text


def _validate(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd import validation

    problems = validation.validate(args.path)
    print(validation.report(args.path, problems, args.json))
    return 1 if any(p.severity == "error" for p in problems) else 0


def _inspect(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd import inspection

    if args.flatten:
        sys.stdout.write(inspection.flatten(args.path))
        return 0
    info = inspection.inspect(args.path, max_depth=args.depth)
    print(inspection.format_json(info) if args.json else inspection.format_text(info))
    return 0


def plugin_path(usdview: bool = False) -> str:
    """The folder to put on PXR_PLUGINPATH_NAME for this install (the package's own folder:
    site-packages for a wheel, the checkout for an editable install): the surfel schema's, or
    the usdview plugin's (which includes the schema)."""
    return str(lsd3d_usd.USDVIEW_PLUGIN_DIR if usdview else lsd3d_usd.SCHEMA_DIR)


def _plugin_path(args) -> int:
    path = plugin_path(args.usdview)
    if args.export:
        print(f'export PXR_PLUGINPATH_NAME="{path}${{PXR_PLUGINPATH_NAME:+:$PXR_PLUGINPATH_NAME}}"')
    else:
        print(path)
    return 0


def _scene(args) -> int:
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
    register_generate(sub)
    p = sub.add_parser(
        "validate", help="check a USD file or scene against USD's validators and the surfel schema",
        description="Run usd-core's UsdValidation validators plus lsd3d checks: unknown prim types; "
                    "missing upAxis/metersPerUnit/defaultPrim; array lengths; finite values; opacity in "
                    "[0,1]; scales > 0; unit quaternions; SH degree vs coefficient count; extent covering "
                    "the particles; BasisCurves that USD tools can draw (curveVertexCounts adding up to the "
                    "points, enough vertices per curve for its type); unresolvable asset paths; bulk "
                    "surfel data in .usda. Works on any USD "
                    "file. Exit 0 when valid, 1 with one line per problem.")
    p.add_argument("path", help="a USD file (.usda/.usdc/.usd) or a scene folder holding scene.usda")
    p.add_argument("--json", action="store_true", help="print a JSON report instead of text")
    p.set_defaults(func=_validate)

    p = sub.add_parser(
        "inspect", help="show layer stack with provenance and sizes, disk use, prim tree, surfel statistics",
        description="Summarise a USD file or scene: its layer stack (strongest first, with each layer's "
                    "size, its per-chunk files included, and provenance), a scene folder's disk use "
                    "per folder, the prim tree with types and counts, statistics per surfel prim, and "
                    "how USD tools without our plugin read the surfels (`lsd3d-usd plugin-path`). "
                    "--flatten prints the composed stage as usda, like `usdcat --flatten`.")
    p.add_argument("path", help="a USD file or a scene folder holding scene.usda")
    p.add_argument("--flatten", action="store_true", help="print the flattened composed stage as usda")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--depth", type=int, default=4, help="prim tree depth to show (default 4)")
    p.set_defaults(func=_inspect)

    p = sub.add_parser(
        "plugin-path", help="print the PXR_PLUGINPATH_NAME that lets other USD tools read our schema",
        description="Print the folder of this install's lsd3d surfel schema (plugInfo.json) to put on "
                    "PXR_PLUGINPATH_NAME, so usdview, usdcat or any USD program that does not import "
                    "lsd3d_usd knows the Lsd3dSurfelField type: "
                    'export PXR_PLUGINPATH_NAME="$(lsd3d-usd plugin-path)", or eval "$(lsd3d-usd '
                    'plugin-path --export)" to prepend it to the current value. Without it such tools '
                    "still read our surfels as ParticleField prims with the official attribute APIs "
                    "(the scene's fallbackPrimTypes metadata), only without our schema's extras.")
    p.add_argument("--usdview", action="store_true",
                   help="the usdview plugin's folder instead (the LSD3D menu; it includes the schema)")
    p.add_argument("--export", action="store_true",
                   help="print a shell line that prepends it to PXR_PLUGINPATH_NAME")
    p.set_defaults(func=_plugin_path)

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


GROUP_TITLES = {"env": "environment (docs/env.md)", "surfels": "initial surfels",
                "splats": "surfel preview for other USD tools (docs/usd.md)",
                "prior": "image prior (docs/priors.md)", "ggds": "GGDS (docs/ggds.md)",
                "actors": "actors (docs/actors.md)"}


def generate_command(args) -> int:
    got = ct.command_config(args, C.GenerateConfig, display=C.FLAG_NAMES,
                            needs={"output": "generate: -o/--output SCENE is required"})
    if got is None:
        return 0
    cfg, explicit = got
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers {args.workers}: must be >= 1")
    if args.address and args.executor != "ray":
        raise InputError("--address is for --executor ray")
    if args.json:   # checked now, not after the whole run
        check_output_path(args.json, "--json", what="summary file")
    # local imports: not loaded for --help. On a fresh install the rasteriser's kernels start
    # compiling on the other core before this process imports the pipeline (render.precompile)
    from lsd3d_usd.render import precompile
    early = None if args.resume else precompile.start_for_ggds(cfg.ggds.steps, cfg.ggds.weights)
    try:
        return _generate(args, cfg, explicit)
    finally:
        precompile.finish(early, timeout=0.0)     # at once if the command failed before GGDS


def _generate(args, cfg, explicit) -> int:
    from lsd3d_usd.pipeline import RunOptions, generate

    run = RunOptions(out=Path(args.output), resume=args.resume, force=args.force,
                     retire_runs=args.retire_runs, keep_checkpoint=args.keep_checkpoint,
                     workers=args.workers, executor=args.executor, address=args.address,
                     progress=not args.no_progress and sys.stderr.isatty(),
                     log=(lambda *a: print(*a, file=sys.stderr)),
                     explicit=explicit)
    try:
        summary = generate(cfg, run)
    except KeyboardInterrupt:
        print("lsd3d-usd: interrupted: the scene is valid; continue with --resume", file=sys.stderr)
        return 130
    text = json.dumps(summary, indent=2, default=str)
    if args.json:
        atomic_write_text(args.json, text)
    print(text)
    return 0


def register_generate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "generate", help="build a scene: layout → proxy → environment → surfels → GGDS",
        description="Generate a driving scene as a USD stage folder. Builds (or reuses, when "
                    "unchanged) the layout, proxy, environment and surfel layers, then runs GGDS "
                    "and writes layers/ggds_<run>.usdc holding overs of the optimised surfel "
                    "attributes (layers/surfels.usdc is never rewritten by it). --steps 0 stops "
                    "before GGDS: a complete scene without optimisation. Ctrl-C leaves a valid "
                    "scene that --resume continues. Every setting has a key (--list-options): "
                    "set it in a TOML file (--config) or with --set KEY=VALUE.")
    add_generate_arguments(p)
    p.set_defaults(func=generate_command, compiles_kernels=True)


def add_generate_arguments(p) -> None:
    """generate's options (also `scenario build`'s)."""
    p.add_argument("-o", "--output", help="scene folder to create or update")
    ct.add_tree_options(p, "generate")
    p.add_argument("--resume", action="store_true",
                   help="continue the newest unfinished GGDS run with its recorded settings "
                        "(--steps N stops it at step N)")
    p.add_argument("--force", action="store_true",
                   help="use an output folder that holds another scene or other files")
    p.add_argument("--retire-runs", action="store_true",
                   help="allow rebuilding surfels / environment that existing GGDS runs were "
                        "optimised on: those runs are muted and marked stale")
    p.add_argument("--keep-checkpoint", action="store_true",
                   help="keep a finished run's optimiser checkpoint (default: dropped; the "
                        "run layer holds the result)")
    p.add_argument("--json", help="also write the summary JSON here")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    x = p.add_argument_group("where GGDS regions run (docs/ggds.md: chunk-wise GGDS)")
    x.add_argument("--workers", type=int, metavar="N",
                   help="regions optimised in parallel (default: one per CPU core; a scene "
                        "that is one region runs in this process)")
    x.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local process pool (default) or a Ray cluster")
    x.add_argument("--address", help="Ray cluster address (with --executor ray; default: a "
                                     "local Ray instance), e.g. ray://head:10001")
    groups = ct.add_arguments(p, GenerateConfig, titles=GROUP_TITLES)
    ct.add_entry_flag(groups["ggds"], "--perceptual-weight", "ggds.weights.perceptual",
                      "weight of the perceptual loss (default: the prior's: 0 for the "
                      "procedural prior, whose targets are exact per pixel; 0.05 for a "
                      "diffusion prior)")
