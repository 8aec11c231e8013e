"""`lsd3d-usd dataset`: scenes driven by a sensor rig, written in the formats perception code
reads (nuScenes, KITTI, MCAP; docs/datasets.md)."""
from __future__ import annotations

import argparse
import json
import sys
import time

from lsd3d_usd import configtree as ct
from lsd3d_usd.datasets.options import DatasetOptions

# --format is given every time; a log drives one of --route or --routes; a dataset folder is
# either continued or replaced
REQUIRED = ("format",)
EXCLUSIVE = (("route", "routes"), ("resume", "overwrite"))


def _dataset(args) -> int:
    from lsd3d_usd.datasets.build import build_dataset, prepare
    opt, _ = ct.from_command_line(args, DatasetOptions)
    progress = not args.no_progress and sys.stderr.isatty()
    log = (lambda m: print(m, file=sys.stderr))
    deferrer_for = None
    if opt.deferred:
        prepare(args.scene, args.output, opt)     # bad input fails before the prior loads
        from lsd3d_usd.views.commands import make_deferrer
        from lsd3d_usd.views.options import DeferredConfig

        def deferrer_for(scene):
            return make_deferrer(scene, DeferredConfig(enabled=True), log)
    t0 = time.perf_counter()
    summary = build_dataset(args.scene, args.output, opt, progress=progress, log=log,
                            deferrer_for=deferrer_for)
    wall = time.perf_counter() - t0
    keyframes = summary["keyframes"] * summary["logs"]
    print(f"{args.output}: {opt.format}, {summary['logs']} log(s) "
          f"({summary['resumed_logs']} resumed), {keyframes} keyframes, "
          f"{summary['camera_frames'] * summary['logs']} camera ticks, "
          f"{summary['sweeps'] * summary['logs']} sweeps per LiDAR in {wall:.1f} s")
    for k, tick in sorted(summary["resumed_at_tick"].items()):
        print(f"log {k}: resumed at tick {tick} (after its last finished keyframe)")
    for r in summary["routes"]:
        print(f"route {','.join(r)}")
    if args.json:
        from pathlib import Path
        Path(args.json).write_text(json.dumps({**summary, "wall_s": wall}, indent=1))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "dataset", help="drive scenes with a sensor rig and write a nuScenes, KITTI or MCAP "
                        "dataset",
        description="Drive each SCENE along one or more routes with a sensor rig (cameras at "
                    "--camera-hz, the LiDAR at --lidar-hz, keyframes at --keyframe-hz) and "
                    "write what the sensors see, with ground truth, in a dataset format: "
                    "nuscenes (v1.0 tables, lidarseg, map masks; loads with nuscenes-devkit), "
                    "kitti (3D object: training/image_2, velodyne, label_2, calib) or mcap "
                    "(Foxglove schemas). One log (a nuScenes scene) per scene and route. "
                    "See docs/datasets.md.")
    p.add_argument("scene", nargs="+", metavar="SCENE", help="scene folders")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="dataset folder")
    ct.add_arguments(p, DatasetOptions, required=REQUIRED, exclusive=EXCLUSIVE)
    p.add_argument("--json", metavar="FILE", help="write a summary (counts, timings) as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_dataset, compiles_kernels=True)
