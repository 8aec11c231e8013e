"""`lsd3d-usd actors ...`: add parked and moving actors to a scene; write the asset library."""
from __future__ import annotations

import argparse

from lsd3d_usd.scene import Scene


def _add(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.actors.compose import add_actors, layout_of_scene

    scene = Scene.open(args.scene)
    layout = layout_of_scene(scene)
    res = add_actors(scene, layout, args.parked, args.moving, args.seed, seconds=args.seconds,
                     fps=args.fps, assets_dir=args.assets, pedestrians=args.pedestrians,
                     cyclists=args.cyclists)
    people = ""
    if args.pedestrians or args.cyclists:
        people = f", {len(res.pedestrian_kinds)} pedestrians, {len(res.cyclist_kinds)} cyclists"
    print(f"{res.layer}: {len(res.parked)} parked, {len(res.moving_kinds)} moving actors{people} "
          f"({res.seconds:g} s at {args.fps:g} samples/s, {res.tcps:g} time codes/s)")
    for n in res.notes:
        print(f"note: {n}")
    return 0


def _assets(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.actors.assets import ply_to_asset, write_library
    if args.ply:
        print(ply_to_asset(args.ply, args.output))
        return 0
    from lsd3d_usd.actors.people import write_people_library
    for kind, path in {**write_library(args.output, fmt=args.format),
                       **write_people_library(args.output, fmt=args.format)}.items():
        print(f"{kind}: {path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("actors", help="actors: referenced vehicle, pedestrian and cyclist assets, "
                                      "parked and moving (IDM traffic, sidewalk walkers)",
                       description="Compose actors into a scene by reference: vehicles parked in free "
                                   "parking slots, vehicles and cyclists driving the lane graph (seeded "
                                   "IDM car following), pedestrians on the sidewalks and crosswalks, "
                                   "written to the scene's actors layer.")
    s = p.add_subparsers(dest="actors_command", metavar="SUBCOMMAND")
    a = s.add_parser("add", help="(re)write the actors layer of a scene",
                     description="Place parked actors at free parking spots / along parking lanes and "
                                 "moving actors on the lanes; moving ones get xform time samples "
                                 "(translate + rotateZ) at the scene's timeCodesPerSecond. The asset "
                                 "files are referenced, never copied. Deterministic per --seed.")
    a.add_argument("scene", help="scene folder (holding scene.usda with a layout layer)")
    a.add_argument("--parked", type=int, default=12, help="number of parked actors (default 12)")
    a.add_argument("--moving", type=int, default=8, help="number of moving actors (default 8)")
    a.add_argument("--pedestrians", type=int, default=0,
                   help="pedestrians walking the sidewalks, crossing at crosswalks and standing at "
                        "corners (default 0)")
    a.add_argument("--cyclists", type=int, default=0,
                   help="cyclists on bike lanes, or the right part of driving lanes, in the IDM "
                        "traffic (default 0)")
    a.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    a.add_argument("--seconds", type=float, default=8.0, help="length of the traffic run (default 8)")
    a.add_argument("--fps", type=float, default=10.0,
                   help="traffic samples per second written as time samples (default 10)")
    a.add_argument("--assets", help="folder of asset files named <kind>.usda|usdc|usd (default: "
                                    "SCENE/assets, the procedural library written there where "
                                    "missing)")
    a.set_defaults(func=_add)
    b = s.add_parser("assets", help="write the procedural library, or convert a splat .ply",
                     description="Write car/van/truck/bus, adult/adult_broad/child (pedestrians) and "
                                 "cyclist asset files into OUTPUT (a folder), or with --ply convert a "
                                 "3DGS/2DGS .ply into a surfel asset file OUTPUT.")
    b.add_argument("output", help="output folder (library) or asset file (with --ply)")
    b.add_argument("--ply", help="a 3DGS/2DGS .ply to convert into a referenced surfel asset")
    b.add_argument("--format", choices=("usda", "usdc"), default="usda", help="library file format")
    b.set_defaults(func=_assets)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
