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
    register_generate(sub)
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


def _extent(text: str) -> tuple[float, float]:
    from lsd3d_usd.errors import InputError
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--extent {text!r}: expected WxH in metres, e.g. 200x200") from None
    return w, h


def _generate(args) -> int:
    import json
    from pathlib import Path

    from lsd3d_usd.cliutil import parse_size
    from lsd3d_usd.pipeline import GenerateOptions, generate

    opts = GenerateOptions(
        out=Path(args.output), layout=Path(args.layout) if args.layout else None, seed=args.seed,
        extent=_extent(args.extent), style=args.style, prompt=args.prompt, when=args.when,
        lat=args.lat, lon=args.lon, weather=args.weather, season=args.season,
        env_resolution=parse_size(args.env_resolution, "--env-resolution"), surfels=args.surfels,
        steps=args.steps, prior=args.prior, resolution=parse_size(args.resolution, "--resolution"),
        views=args.views, checkpoint_every=args.checkpoint_every, perceptual=not args.no_perceptual,
        perceptual_weight=args.perceptual_weight,
        lpips=Path(args.lpips) if args.lpips else None,
        lpips_lin=Path(args.lpips_lin) if args.lpips_lin else None,
        parked=0 if args.no_actors else args.parked, moving=0 if args.no_actors else args.moving,
        actor_seconds=args.actor_seconds,
        resume=args.resume, force=args.force, progress=not args.no_progress and sys.stderr.isatty(),
        log=(lambda *a: print(*a, file=sys.stderr)))
    try:
        summary = generate(opts)
    except KeyboardInterrupt:
        print("lsd3d-usd: interrupted: the scene is valid; continue with --resume", file=sys.stderr)
        return 130
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2, default=str))
    print(json.dumps(summary, indent=2, default=str))
    return 0


def register_generate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "generate", help="build a scene: layout → proxy → environment → surfels → GGDS",
        description="Generate a driving scene as a USD stage folder. Builds (or reuses, when "
                    "unchanged) the layout, proxy, environment and surfel layers, then runs GGDS "
                    "and writes layers/ggds_<run>.usdc holding only overs of the optimised "
                    "surfel attributes (layers/surfels.usdc is never rewritten). --steps 0 stops "
                    "before GGDS: a complete scene without optimisation. Ctrl-C leaves a valid "
                    "scene that --resume continues.")
    p.add_argument("--layout", help="layout layer (.usda/.usdc; see docs/layout.md). Without it a "
                                    "layout is generated from --seed, --extent and --style")
    p.add_argument("-o", "--output", required=True, help="scene folder to create or update")
    p.add_argument("--prompt", help='scene description, e.g. "rainy autumn evening in Seattle" '
                                    "(time of day, weather, season, place; see docs/env.md)")
    p.add_argument("--steps", type=int, default=250, help="GGDS steps (0 = no optimisation; default 250)")
    p.add_argument("--prior", default="procedural",
                   help="image prior: 'procedural' (default, runs on CPU) or 'diffusers:DIR' "
                        "(a local latent-diffusion + depth ControlNet directory; never downloads)")
    p.add_argument("--resolution", default="480x270", help="GGDS render size WxH (default 480x270)")
    p.add_argument("--seed", type=int, default=0, help="random seed of every step (default 0)")
    p.add_argument("--resume", action="store_true", help="continue the newest GGDS run from its checkpoint")
    p.add_argument("--force", action="store_true",
                   help="use an output folder that holds another scene or other files")
    p.add_argument("--surfels", type=int, help="initial surfel count (default: 80 per m² of proxy "
                                               "surface weighted by nearness to the lanes, "
                                               "at most 4 M)")
    p.add_argument("--views", type=int, default=128, help="training views sampled along and off the lanes (default 128)")
    p.add_argument("--checkpoint-every", type=int, default=50, help="steps between checkpoints (default 50)")
    p.add_argument("--no-perceptual", action="store_true", help="skip the EfficientNet perceptual loss")
    p.add_argument("--perceptual-weight", type=float,
                   help="weight of the EfficientNet-Lite0 perceptual loss (default: 0 with the "
                        "procedural prior, whose targets are exact per pixel; 0.05 with a diffusion prior)")
    p.add_argument("--lpips", metavar="BACKBONE.pth",
                   help="use LPIPS as the perceptual term instead of EfficientNet-Lite0: a local "
                        "torchvision AlexNet or VGG16 state dict (never downloaded; needs "
                        "--perceptual-weight > 0)")
    p.add_argument("--lpips-lin", metavar="LIN.pth",
                   help="LPIPS linear weights (the lpips package's weights/v0.1/alex.pth or vgg.pth; "
                        "default: found in an installed lpips package)")
    p.add_argument("--parked", type=int, default=12, help="parked actors along the curbs (default 12)")
    p.add_argument("--moving", type=int, default=8,
                   help="moving actors driven by IDM traffic over the lane graph (default 8)")
    p.add_argument("--actor-seconds", type=float, default=8.0, help="traffic duration in seconds (default 8)")
    p.add_argument("--no-actors", action="store_true", help="no actors layer")
    p.add_argument("--extent", default="200x200", help="generated layout size WxH m (no --layout)")
    p.add_argument("--style", default="urban", choices=("urban", "suburban", "highway"),
                   help="generated layout style (no --layout)")
    p.add_argument("--when", help="local date/time, e.g. 2026-06-21T13:00+02:00 (overrides the prompt)")
    p.add_argument("--lat", type=float, help="latitude (with --lon; overrides the prompt's place)")
    p.add_argument("--lon", type=float, help="longitude")
    p.add_argument("--weather", help="clear|partly-cloudy|overcast|fog|rain|snow (overrides the prompt)")
    p.add_argument("--season", help="spring|summer|autumn|winter (overrides the prompt)")
    p.add_argument("--env-resolution", default="2048x1024", help="environment map size (default 2048x1024)")
    p.add_argument("--json", help="also write the summary JSON here")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_generate)
