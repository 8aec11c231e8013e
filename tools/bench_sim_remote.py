"""Benchmark: the step overhead of `sim serve` (gRPC) over the in-process `DriveEnv`.

    python tools/bench_sim_remote.py SCENE [--rigs none,nuscenes6] [--width 160] [--steps 20]

Per rig: mean step time of the same seed and actions in-process, then through
`RemoteDriveEnv` against `lsd3d-usd sim serve` in a subprocess (so client and server do not
share a GIL), and the overhead (remote - in-process) in ms and %. Resets are not timed.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time

import numpy as np

ACTION = np.array([1.0, 0.0], np.float32)


def _steps(env, n: int, seed: int) -> float:
    env.reset(seed=seed)
    env.step(ACTION)                  # the first step warms caches on both sides
    t, k = 0.0, 0
    while k < n:
        t0 = time.perf_counter()
        _, _, term, trunc, _ = env.step(ACTION)
        t += time.perf_counter() - t0
        k += 1
        if term or trunc:
            env.reset(seed=seed)
    return t / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--rigs", default="none,nuscenes6")
    ap.add_argument("--lidar", default="auto")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.remote import RemoteDriveEnv
    for rig in args.rigs.split(","):
        kw = dict(rig=rig, lidar=args.lidar, width=args.width, seconds=3600.0)
        local = DriveEnv(args.scene, **kw)
        t_local = _steps(local, args.steps, args.seed)
        local.close()
        srv = subprocess.Popen([sys.executable, "-m", "lsd3d_usd.cli", "sim", "serve", args.scene,
                                "--port", "0", "--no-reference", "--rig", rig, "--lidar",
                                args.lidar, "--width", str(args.width), "--seconds", "3600"],
                               stdout=subprocess.PIPE, text=True)
        try:
            target = srv.stdout.readline().split(" on ")[1].split()[0]
            remote = RemoteDriveEnv(target)
            t_remote = _steps(remote, args.steps, args.seed)
            remote.close()
        finally:
            srv.terminate()
            srv.wait(30)
        d = t_remote - t_local
        print(f"rig {rig} (lidar {args.lidar}, width {args.width}): in-process "
              f"{t_local * 1e3:.1f} ms/step, remote {t_remote * 1e3:.1f} ms/step, overhead "
              f"{d * 1e3:+.1f} ms ({100 * d / t_local:+.1f} %)", flush=True)


if __name__ == "__main__":
    main()
