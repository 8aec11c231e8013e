"""`bench sim --remote`: the step overhead of `sim serve` (gRPC) over the in-process env.

The same seed and actions in-process and through `RemoteDriveEnv` against `lsd3d-usd sim
serve` in a subprocess (so client and server do not share a GIL), stepped alternately so
that both see the same load; medians; resets not timed. The codec time is the service's own
work per step beside the RPC (encode, serialise, parse, decode one observation).
"""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np

ACTION = np.array([1.0, 0.0], np.float32)


def paired(local, remote, n: int, seed: int) -> tuple[float, float]:
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


def codec(obs, space, n: int = 20) -> tuple[float, int]:
    """Seconds to encode + serialise + parse + decode one observation (the service's own work
    per step beside the RPC), and its size in bytes."""
    from lsd3d_usd.sim.proto import sim_pb2
    from lsd3d_usd.sim.remote import decode_obs, encode_obs
    t0 = time.perf_counter()
    for _ in range(n):
        data = encode_obs(space, obs).SerializeToString()
        decode_obs(space, sim_pb2.Observation.FromString(data))
    return (time.perf_counter() - t0) / n, len(data)


def overhead(scene, rig: str, lidar: str = "auto", width: int = 480, steps: int = 20,
             seed: int = 0) -> dict:
    """In-process and remote median step times (s), the overhead, and the codec's share."""
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.remote import RemoteDriveEnv
    local = DriveEnv(scene, rig=rig, lidar=lidar, width=width, seconds=3600.0)
    srv = subprocess.Popen([sys.executable, "-m", "lsd3d_usd.cli", "sim", "serve", str(scene),
                            "--port", "0", "--no-reference", "--rig", rig, "--lidar", lidar,
                            "--width", str(width), "--seconds", "3600"],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        target = srv.stdout.readline().split(" on ")[1].split()[0]
        remote = RemoteDriveEnv(target)
        t_local, t_remote = paired(local, remote, steps, seed)
        obs, _ = local.reset(seed=seed)
        space = remote.observation_space
        remote.close()
    finally:
        srv.terminate()
        srv.wait(30)
        local.close()
    c, size = codec(obs, space)
    return {"rig": rig, "lidar": lidar, "width": width, "local_s_per_step": t_local,
            "remote_s_per_step": t_remote, "overhead_pct": 100.0 * (t_remote - t_local) / t_local,
            "codec_s": c, "codec_pct": 100.0 * c / t_local, "observation_bytes": size}
