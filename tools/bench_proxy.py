"""Benchmark: generated layout -> proxy layer (seconds, peak memory, triangles per class).

    python tools/bench_proxy.py [--extent 1000] [--style urban] [--seed 0] [--synthetic]

Target (issue 4): a 1 km x 1 km layout in under 60 s and under 4 GB.
"""
from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import lsd3d_usd  # noqa: F401  (registers the schema first)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--extent", type=float, default=1000.0, help="square side in metres (default 1000)")
    ap.add_argument("--style", default="urban", help="generator style (urban, suburban, highway)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--synthetic", action="store_true",
                    help="use the proxy's synthetic grid layout instead of the layout generator")
    ap.add_argument("--out", default=None, help="folder for the proxy layer (default: a temp dir)")
    args = ap.parse_args()

    from lsd3d_usd.proxy.usdio import build_proxy_layer

    t0 = time.perf_counter()
    if args.synthetic:
        from lsd3d_usd.proxy.synthetic import grid_layout
        n = max(1, int(round(args.extent / 100)))
        layout = grid_layout(n, n)
    else:
        from lsd3d_usd.layout.generator import generate
        layout = generate(args.seed, (args.extent, args.extent), args.style)
    t_layout = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or tmp) / "proxy.usdc"
        c0 = time.process_time()
        rep = build_proxy_layer(layout, out)
        cpu = time.process_time() - c0
        t_rebuild0 = time.perf_counter()
        again = build_proxy_layer(layout, out)
        t_rebuild = time.perf_counter() - t_rebuild0
        size = sum(f.stat().st_size for f in out.parent.rglob("*.usdc"))
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    counts = layout.counts()
    print(f"layout: {args.extent:.0f} m x {args.extent:.0f} m "
          f"{'synthetic grid' if args.synthetic else f'{args.style} seed {args.seed}'}, "
          f"{sum(counts.values())} features ({counts['Building']} buildings, "
          f"{counts['LaneCenter']} lanes, {counts['Tree']} trees), {t_layout:.2f} s to make")
    print(f"proxy build: {rep.seconds:.2f} s wall, {cpu:.2f} s CPU for {len(rep.built)} chunks "
          f"({rep.seconds / max(len(rep.built), 1):.3f} s/chunk), files {size / 1e6:.1f} MB")
    print(f"unchanged rebuild: {t_rebuild:.2f} s, {len(again.built)} chunks rebuilt")
    print(f"peak RSS: {peak_gb:.2f} GB")
    total = sum(rep.triangles.values())
    print(f"triangles: {total}")
    for cls, n in sorted(rep.triangles.items(), key=lambda kv: -kv[1]):
        print(f"  {cls:14s} {n:10d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
