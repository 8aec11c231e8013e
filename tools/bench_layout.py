#!/usr/bin/env python
"""Benchmark `layout generate`: seconds (plan, build, write) and feature counts.

    python tools/bench_layout.py [--extent 1000x1000] [--seed 0] [--style urban] [--repeat 3]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from lsd3d_usd.layout import generator, usdio


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--extent", default="1000x1000")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--style", default="urban", choices=generator.STYLES)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--format", default="usda", choices=("usda", "usdc"))
    args = ap.parse_args()
    extent = generator.parse_extent(args.extent)
    best = None
    for r in range(args.repeat):
        t0 = time.perf_counter()
        desc = generator.plan(args.seed + r, extent, args.style)
        t1 = time.perf_counter()
        layout = generator.build(desc)
        t2 = time.perf_counter()
        with tempfile.TemporaryDirectory() as d:
            path = usdio.write_layout(layout, Path(d) / f"layout.{args.format}")
            size = path.stat().st_size
            t3 = time.perf_counter()
            usdio.read_layout(path)
            t4 = time.perf_counter()
        row = dict(plan=t1 - t0, build=t2 - t1, write=t3 - t2, total=t3 - t0, read=t4 - t3)
        print(f"seed {args.seed + r} {args.style} {args.extent}: "
              + " ".join(f"{k} {v:.2f}s" for k, v in row.items()) + f" size {size / 1e6:.1f} MB")
        best = row if best is None or row["total"] < best["total"] else best
    counts = ", ".join(f"{v} {k}" for k, v in layout.counts().items() if v)
    print(f"features (last run): {counts}")
    print(f"best total (plan+build+write): {best['total']:.2f} s")


if __name__ == "__main__":
    main()
