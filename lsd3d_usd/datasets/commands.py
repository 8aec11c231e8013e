"""`lsd3d-usd dataset`: scenes driven by a sensor rig, written in the formats perception code
reads (nuScenes, KITTI, MCAP; docs/datasets.md)."""
from __future__ import annotations

import argparse
import json
import sys
import time

from lsd3d_usd.datasets.options import DEFAULT_VERSION, DatasetOptions


def _dataset(args) -> int:
    from lsd3d_usd.datasets.build import build_dataset, prepare
    opt = DatasetOptions(format=args.format, rig=args.rig, lidar=args.lidar, route=args.route,
                         routes=args.routes, seconds=args.seconds, camera_hz=args.camera_hz,
                         lidar_hz=args.lidar_hz, keyframe_hz=args.keyframe_hz,
                         deferred=args.deferred, resume=args.resume, overwrite=args.overwrite,
                         seed=args.seed, version=args.version, width=args.width)
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
    p.add_argument("--format", required=True, metavar="nuscenes|kitti|mcap",
                   help="dataset format (a registered writer, lsd3d_usd.dataset_writers)")
    p.add_argument("--rig", default="nuscenes6", metavar="nuscenes6|waymo5|FILE.toml",
                   help="sensor rig: a rig name or a rig FILE.toml (docs/sensors.md)")
    p.add_argument("--lidar", default="auto", metavar="hdl32|waymo_top|none|FILE.toml",
                   help="the LiDAR (default auto: the rig's own; nuscenes6 carries hdl32)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--route", metavar="IDS", help="lane ids to drive, comma-separated (default: "
                                                  "the longest drivable route)")
    g.add_argument("--routes", type=int, metavar="N", help="N distinct seeded routes per scene")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each log (20)")
    p.add_argument("--camera-hz", type=float, default=12.0, help="camera frame rate (12)")
    p.add_argument("--lidar-hz", type=float, default=20.0, help="LiDAR sweep rate (20)")
    p.add_argument("--keyframe-hz", type=float, default=2.0,
                   help="keyframe (annotated sample) rate, dividing both sensor rates (2)")
    p.add_argument("--width", type=int, default=None,
                   help="camera image width in pixels (default: the rig's native, 1600 for "
                        "nuscenes6); heights follow each camera's aspect")
    p.add_argument("--deferred", action="store_true",
                   help="camera images through the scene's image prior (docs/render.md)")
    m = p.add_mutually_exclusive_group()
    m.add_argument("--resume", action="store_true",
                   help="continue the dataset in DIR: finished logs are kept, an unfinished one "
                        "continues after its last keyframe (nuscenes, kitti)")
    m.add_argument("--overwrite", action="store_true", help="replace the dataset in DIR")
    p.add_argument("--seed", type=int, default=0, help="seed of routes, traffic and LiDAR noise")
    p.add_argument("--version", default=DEFAULT_VERSION,
                   help=f"nuScenes version folder ({DEFAULT_VERSION})")
    p.add_argument("--json", metavar="FILE", help="write a summary (counts, timings) as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_dataset, compiles_kernels=True)
