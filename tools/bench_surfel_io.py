#!/usr/bin/env python
"""Benchmark: save N surfels to .usdc and read them back into numpy.

Prints seconds for save, open, and read-to-numpy (plus touching every byte, so a
lazy memory-mapped read is charged for its page faults), file size and peak RSS.
Targets (issue 2): 2 M surfels save < 10 s, read < 1 s on a 2-core machine.

    python tools/bench_surfel_io.py [--n 2000000] [--sh-degree 3] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import lsd3d_usd  # noqa: F401  (schema registration)
from lsd3d_usd.splats import usdio
from lsd3d_usd.splats.field import SurfelField, sh_coeff_count


def make_field(n: int, sh_degree: int, seed: int = 0) -> SurfelField:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return SurfelField(rng.uniform(-500, 500, (n, 3)).astype(np.float32), q,
                       rng.uniform(0.02, 0.5, (n, 2)).astype(np.float32),
                       rng.uniform(0, 1, n).astype(np.float32),
                       (rng.normal(size=(n, sh_coeff_count(sh_degree), 3)) * 0.2).astype(np.float32),
                       rng.integers(0, 12, n).astype(np.int32))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2_000_000)
    ap.add_argument("--sh-degree", type=int, nargs="+", default=[0, 3])
    ap.add_argument("--repeat", type=int, default=3, help="runs per setting; the median is reported")
    ap.add_argument("--json", help="write results here")
    args = ap.parse_args()
    results = []
    for deg in args.sh_degree:
        field = make_field(args.n, deg)
        saves, reads, opens = [], [], []
        with tempfile.TemporaryDirectory() as tmp:
            for r in range(args.repeat):
                path = Path(tmp) / f"surfels_{r}.usdc"
                t0 = time.perf_counter()
                usdio.write_surfel_file(str(path), field)
                saves.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                from lsd3d_usd import scene
                stage = scene.open_stage(path)
                prim = stage.GetPrimAtPath("/World/Surfels")
                opens.append(time.perf_counter() - t0)
                back = usdio.read_surfels(prim)
                checksum = sum(float(np.add.reduce(a, axis=None, dtype=np.float64)) for a in
                               (back.positions, back.orientations, back.scales, back.opacities, back.sh))
                reads.append(time.perf_counter() - t0)
                assert back.positions.tobytes() == field.positions.tobytes()
                size_mb = path.stat().st_size / 2**20
                del stage, prim, back
        res = {"n": args.n, "sh_degree": deg, "save_s": float(np.median(saves)),
               "open_s": float(np.median(opens)), "read_s": float(np.median(reads)),
               "file_mb": round(size_mb, 1), "checksum": checksum,
               "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
        results.append(res)
        print(f"n={args.n:,} sh_degree={deg}: save {res['save_s']:.2f} s, open {res['open_s'] * 1e3:.1f} ms, "
              f"open+read+touch {res['read_s']:.2f} s, file {res['file_mb']:.0f} MB, "
              f"peak RSS {res['peak_rss_mb']:.0f} MB (median of {args.repeat})")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
