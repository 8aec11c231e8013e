"""Benchmark: the step overhead of `sim serve` (gRPC) over the in-process `DriveEnv`
(lsd3d_usd.benchmarks.sim_remote; `lsd3d-usd bench sim --remote` runs it at nuscenes6 480x270
+ hdl32).

    python tools/bench_sim_remote.py SCENE [--rigs none,nuscenes6] [--width 160] [--steps 20]
"""
from __future__ import annotations

import argparse

from lsd3d_usd.benchmarks.sim_remote import overhead


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--rigs", default="none,nuscenes6")
    ap.add_argument("--lidar", default="auto")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for rig in args.rigs.split(","):
        r = overhead(args.scene, rig, args.lidar, args.width, args.steps, args.seed)
        print(f"rig {rig} (lidar {args.lidar}, width {args.width}): in-process "
              f"{r['local_s_per_step'] * 1e3:.1f} ms/step, remote {r['remote_s_per_step'] * 1e3:.1f} "
              f"ms/step, overhead {r['overhead_pct']:+.1f} %; an observation of "
              f"{r['observation_bytes'] / 1e6:.2f} MB encodes, serialises, parses and decodes in "
              f"{r['codec_s'] * 1e3:.2f} ms", flush=True)


if __name__ == "__main__":
    main()
