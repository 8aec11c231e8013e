"""Benchmark: the step overhead of `sim serve` (gRPC) over the in-process `DriveEnv`.

    python tools/bench_sim_remote.py SCENE [--rigs none,nuscenes6] [--width 160] [--steps 20]

Per rig: median step time of the same seed and actions in-process and through
`RemoteDriveEnv` against `lsd3d-usd sim serve` in a subprocess (so client and server do not
share a GIL), stepped alternately, and the overhead (remote - in-process) in ms and %.
Resets are not timed.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time

import numpy as np

ACTION = np.array([1.0, 0.0], np.float32)


def _paired(local, remote, n: int, seed: int) -> tuple[float, float]:
    """Median step times (s), local and remote stepped alternately so that both see the
    same load (a shared machine's load drifts over seconds)."""
    tl, tr = [], []
    for env in (local, remote):
        env.reset(seed=seed)
        env.step(ACTION)              # the first step warms caches on both sides
    while len(tl) < n:
        for env, ts in ((local, tl), (remote, tr)):
            t0 = time.perf_counter()
            _, _, term, trunc, _ = env.step(ACTION)
            ts.append(time.perf_counter() - t0)
            if term or trunc:
                env.reset(seed=seed)
    return float(np.median(tl)), float(np.median(tr))


def _codec(obs, space, n: int = 20) -> tuple[float, int]:
    """Seconds to encode + serialise + parse + decode one observation (the service's own work
    per step beside the RPC), and its size in bytes."""
    from lsd3d_usd.sim.proto import sim_pb2
    from lsd3d_usd.sim.remote import decode_obs, encode_obs
    t0 = time.perf_counter()
    for _ in range(n):
        data = encode_obs(space, obs).SerializeToString()
        decode_obs(space, sim_pb2.Observation.FromString(data))
    return (time.perf_counter() - t0) / n, len(data)


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
        srv = subprocess.Popen([sys.executable, "-m", "lsd3d_usd.cli", "sim", "serve", args.scene,
                                "--port", "0", "--no-reference", "--rig", rig, "--lidar",
                                args.lidar, "--width", str(args.width), "--seconds", "3600"],
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            target = srv.stdout.readline().split(" on ")[1].split()[0]
            remote = RemoteDriveEnv(target)
            t_local, t_remote = _paired(local, remote, args.steps, args.seed)
            local_obs = local.reset(seed=args.seed)
            remote.close()
        finally:
            srv.terminate()
            srv.wait(30)
            local.close()
        d = t_remote - t_local
        codec, size = _codec(local_obs[0], remote.observation_space)
        print(f"rig {rig} (lidar {args.lidar}, width {args.width}): in-process "
              f"{t_local * 1e3:.1f} ms/step, remote {t_remote * 1e3:.1f} ms/step, overhead "
              f"{d * 1e3:+.1f} ms ({100 * d / t_local:+.1f} %); an observation of {size / 1e6:.2f} MB "
              f"encodes, serialises, parses and decodes in {codec * 1e3:.2f} ms", flush=True)


if __name__ == "__main__":
    main()
