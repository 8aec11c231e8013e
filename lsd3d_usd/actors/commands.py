"""`lsd3d-usd actors ...`: add parked and moving actors to a scene; write the asset library."""
from __future__ import annotations

import argparse

from lsd3d_usd import configtree as ct
from lsd3d_usd.actors.config import ADD_FLAGS, AddConfig, AssetsConfig
from lsd3d_usd.scene import Scene


def _add(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.actors.compose import add_actors, layout_of_scene

    cfg, _ = ct.from_command_line(args, AddConfig, ct.flag_names(AddConfig) | ADD_FLAGS)
    a = cfg.actors
    scene = Scene.open(args.scene)
    layout = layout_of_scene(scene)
    res = add_actors(scene, layout, a.parked, a.moving, cfg.seed, seconds=a.seconds,
                     fps=a.fps, assets_dir=args.assets, pedestrians=a.pedestrians,
                     cyclists=a.cyclists)
    people = ""
    if a.pedestrians != 0 or a.cyclists != 0:       # None: the default number of them
        people = f", {len(res.pedestrian_kinds)} pedestrians, {len(res.cyclist_kinds)} cyclists"
    print(f"{res.layer}: {len(res.parked)} parked, {len(res.moving_kinds)} moving actors{people} "
          f"({res.seconds:g} s at {a.fps:g} samples/s, {res.tcps:g} time codes/s)")
    for n in res.notes:
        print(f"note: {n}")
    return 0


def _assets(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.actors.assets import ply_to_asset, write_library
    fmt = ct.from_command_line(args, AssetsConfig)[0].format
    if args.ply:
        print(ply_to_asset(args.ply, args.output))
        return 0
    from lsd3d_usd.actors.people import write_people_library
    for kind, path in {**write_library(args.output, fmt=fmt),
                       **write_people_library(args.output, fmt=fmt)}.items():
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
    ct.add_arguments(a, AddConfig, flags=ADD_FLAGS)
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
    ct.add_arguments(b, AssetsConfig)
    b.set_defaults(func=_assets)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
