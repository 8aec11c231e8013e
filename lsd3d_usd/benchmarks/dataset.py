"""`lsd3d-usd bench dataset`: throughput of `dataset --format nuscenes` on a scene (default:
the README sample generated with generate's defaults) with nuscenes6 and hdl32: a drive of
``seconds`` with cameras at 12 Hz, the LiDAR at 20 Hz and keyframes at 2 Hz. Prints keyframes
(samples) per minute, sensor frames per minute, each part's share of the time (camera
renders, LiDAR sweeps, boxes with their per-camera visibility renders, writing files) and the
peak memory; --json writes the same.
"""
from __future__ import annotations

import json
import resource
import tempfile
import time
from pathlib import Path

from lsd3d_usd.config import generate_config
from lsd3d_usd.datasets.build import DatasetOptions, build_dataset
from lsd3d_usd.pipeline import RunOptions, generate

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "layouts" / "hand_crossing.usda"


def main(*, json_path=None, scene=None, quick=False, seconds=None, width=None, log=print) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        if scene is None:
            scene = Path(tmp) / "scene"
            log(f"generating the README sample{' (no GGDS)' if quick else ''} ...")
            generate(generate_config(layout=SAMPLE, steps=0 if quick else 250,
                                     prompt="sunny afternoon in Madrid"),
                     RunOptions(out=scene, progress=False, log=lambda *a: None))
        seconds = seconds or (1.0 if quick else 20.0)
        width = width or (480 if quick else 1600)
        opt = DatasetOptions(format="nuscenes", rig="nuscenes6", lidar="hdl32", seconds=seconds,
                             camera_hz=12, lidar_hz=20, keyframe_hz=2, width=width)
        t0 = time.perf_counter()
        summary = build_dataset([scene], Path(tmp) / "ds", opt, progress=True, log=log)
        wall = time.perf_counter() - t0
    tm = summary["timing"]
    parts = {k: tm[k] for k in ("cameras_s", "lidar_s", "boxes_s", "write_s")}
    total = sum(parts.values())
    out = {"seconds": seconds, "width": width, "wall_s": round(wall, 2),
           "keyframes": summary["keyframes"], "camera_frames": summary["camera_frames"] * 6,
           "sweeps": summary["sweeps"],
           "keyframes_per_min": round(summary["keyframes"] / wall * 60, 3),
           "sensor_frames_per_min": round((summary["camera_frames"] * 6 + summary["sweeps"])
                                          / wall * 60, 2),
           "share": {k[:-2]: round(v / total, 3) for k, v in parts.items()},
           "seconds_by_part": {k[:-2]: round(v, 2) for k, v in parts.items()},
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}
    log(json.dumps(out, indent=1))
    if json_path:
        Path(json_path).write_text(json.dumps(out, indent=1))
    return out
