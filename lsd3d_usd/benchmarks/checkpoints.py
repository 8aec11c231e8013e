"""The cost of a dataset log's checkpoints against its length: the nuScenes writer fed a
synthetic log (nothing rendered) with the row volume of a real one — nuscenes6 at 12 Hz, a
LiDAR at 20 Hz, keyframes at 2 Hz (46 sample_data rows and their ego poses per keyframe),
``actors`` annotated actors with a 2D box in two cameras each — and a checkpoint after every
keyframe, as `dataset` takes them (datasets.build.Checkpoints). Prints, per log length, the
bytes and seconds all the log's checkpoints wrote and took, and the last one's share.

    python -m lsd3d_usd.benchmarks.checkpoints [--keyframes 25,100,400] [--actors 20]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from lsd3d_usd.datasets.build import Checkpoints, DatasetOptions
from lsd3d_usd.datasets.drive import CameraShot, LidarShot, LogInfo, LogPlan, Sample
from lsd3d_usd.datasets.nuscenes import NuScenesWriter
from lsd3d_usd.datasets.timeline import Timeline
from lsd3d_usd.sensors.camera import camera_in_ego
from lsd3d_usd.sensors.rigs import load_rig
from lsd3d_usd.views.boxes import Box, CameraBox

WIDTH, POINTS = 8, 64            # tiny files: only the tables' rows matter here


def _info(keyframes: int, actors: int, tmp: Path) -> LogInfo:
    specs = list(load_rig("nuscenes6").cameras)
    tl = Timeline(12.0, 20.0, 2.0, keyframes / 2.0)
    rows = [{"id": i + 1, "prim": f"/World/Actors/a{i}", "class": "vehicle", "kind": "car",
             "role": "traffic"} for i in range(actors)]
    return LogInfo(LogPlan(0, tmp, "bench", ["a", "b"], "bench:a,b"), "nuscenes6", specs,
                   object(), WIDTH, tl, SimpleNamespace(rows=rows), None,
                   {c.name: camera_in_ego(c) for c in specs}, np.eye(4), ["a", "b"])


def _samples(info: LogInfo, actors: int):
    rng = np.random.default_rng(0)
    img = np.zeros((info.cameras[0].height_for(WIDTH), WIDTH, 3), np.uint8)
    K = np.array([[4.0, 0, 4], [0, 4.0, 2], [0, 0, 1]])
    sweep = SimpleNamespace(xyz=rng.normal(size=(POINTS, 3)).astype(np.float32),
                            intensity=np.full(POINTS, 0.5, np.float32),
                            ring=np.zeros(POINTS, np.uint16), range=np.ones(POINTS),
                            class_id=np.zeros(POINTS, np.uint8),
                            instance_id=np.zeros(POINTS, np.int32))
    names = [c.name for c in info.cameras]
    for tick in info.timeline.ticks():
        ego = np.eye(4)
        ego[0, 3] = 10.0 * tick.time
        s = Sample(tick, tick.time, ego)
        if tick.cameras:
            s.cameras = [CameraShot(n, img, K, info.ego_from_camera[n], None) for n in names]
        if tick.lidar:
            s.lidar = LidarShot("LIDAR_TOP", sweep, np.eye(4))
        if tick.keyframe:
            entry = CameraBox((1.0, 1.0, 5.0, 3.0), 12, 13, 0.9, 0.0, (1, 1, 5, 3))
            s.boxes = [Box(f"/World/Actors/a{i}", "vehicle", 7, "car", (20.0 + 3 * i, 3.0, 0.8),
                           (4.5, 1.9, 1.6), (0, 0, 0, 1), (5.0, 0.0, 0.0), instance_id=i + 1,
                           role="traffic", cameras={names[i % 6]: entry, names[(i + 1) % 6]: entry},
                           num_lidar_pts=5, pixels=12)
                       for i in range(actors)]
        yield s


def measure(keyframes: int, actors: int = 20) -> dict:
    """{keyframes, bytes, seconds, last_bytes, last_seconds} of one log's checkpoints."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        info = _info(keyframes, actors, root)
        writer = NuScenesWriter(root / "ds", DatasetOptions(format="nuscenes"))
        writer.begin_log(info)
        logs = root / "ds" / ".lsd3d" / "logs"
        logs.mkdir(parents=True)
        cps = Checkpoints(logs, 0)
        seconds = last_s = 0.0
        last_b = 0
        for s in _samples(info, actors):
            writer.write(s)
            if s.keyframe:
                b0, t0 = cps.bytes_written, time.perf_counter()
                cps.save(s.tick.index + 1, writer.checkpoint())
                last_s = time.perf_counter() - t0
                last_b = cps.bytes_written - b0
                seconds += last_s
        return {"keyframes": keyframes, "bytes": cps.bytes_written, "seconds": seconds,
                "last_bytes": last_b, "last_seconds": last_s}


def main(argv=None) -> list:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--keyframes", default="25,100,400")
    p.add_argument("--actors", type=int, default=20)
    p.add_argument("--json")
    a = p.parse_args(argv)
    got = []
    print(f"{'keyframes':>9} {'all checkpoints':>16} {'time':>8} {'last one':>10} {'time':>8}")
    for n in (int(v) for v in a.keyframes.split(",")):
        r = measure(n, a.actors)
        got.append(r)
        print(f"{n:>9} {r['bytes'] / 1e6:>13.2f} MB {r['seconds']:>7.3f}s "
              f"{r['last_bytes'] / 1e3:>7.1f} kB {r['last_seconds'] * 1e3:>6.2f}ms")
    if a.json:
        Path(a.json).write_text(json.dumps(got, indent=1))
    return got


if __name__ == "__main__":
    main()
