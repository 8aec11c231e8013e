#!/usr/bin/env python
"""Benchmark: what the Points preview (splats.preview) adds to a scene's surfel chunk files.

For every surfel chunk of a generated scene, the chunk's initial surfels (with their seed
faces, as `generate` writes them) are written again to a temporary folder with no preview and
with the preview at each fraction given, alternating, ``--repeat`` times; prints the file
sizes and the medians of the write times, summed over the chunks, and the preview's share of
both (issue 37's target: at most 15 % of the surfel layer at the default fraction). With
``--runs``, the same for every GGDS run layer's chunk files (the run's own preview).

    python tools/bench_preview.py SCENE [--fraction 0.1 0.25] [--repeat 5] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import lsd3d_usd  # noqa: F401  (schema registration)
from lsd3d_usd.scene import Scene
from lsd3d_usd.splats import chunkio
from lsd3d_usd.splats.preview import DEFAULT_FRACTION, preview_count


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="a generated scene folder")
    ap.add_argument("--fraction", type=float, nargs="+", default=[DEFAULT_FRACTION])
    ap.add_argument("--repeat", type=int, default=5, help="writes per setting; medians reported")
    ap.add_argument("--runs", action="store_true", help="also measure the GGDS run layers")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    root = Scene.open(args.scene).layer_path("surfels")
    keys = sorted(chunkio.read_chunk_map(root))
    chunks = [(k, chunkio.read_chunk(root, k), chunkio.read_seed_faces(root, k)) for k in keys]
    n = sum(f.n for _, f, _ in chunks)
    settings = [0.0, *args.fraction]
    times = {s: [] for s in settings}
    sizes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            for s in settings:
                folder = Path(tmp) / f"f{s}"
                t0 = time.perf_counter()
                for key, field, seeds in chunks:
                    chunkio.write_chunk(folder, key, field, seed_faces=seeds, preview_fraction=s)
                times[s].append(time.perf_counter() - t0)
                sizes[s] = sum(p.stat().st_size for p in folder.glob("*.usdc"))
    base_t, base_b = statistics.median(times[0.0]), sizes[0.0]
    out = {"scene": str(args.scene), "surfels": n, "chunks": len(keys),
           "surfel_layer": {"bytes": base_b, "write_s": round(base_t, 4)}, "previews": []}
    print(f"{n:,} surfels in {len(keys)} chunk(s); surfel chunk files without a preview: "
          f"{base_b / 1e6:.2f} MB, written in {base_t:.3f} s (median of {args.repeat})")
    for s in args.fraction:
        t, b = statistics.median(times[s]), sizes[s]
        pts = sum(preview_count(f.n, s) for _, f, _ in chunks)
        row = {"fraction": s, "points": pts, "bytes": b - base_b, "write_s": round(t - base_t, 4),
               "size_share": round((b - base_b) / base_b, 4),
               "time_share": round((t - base_t) / base_t, 4)}
        out["previews"].append(row)
        print(f"fraction {s:g}: {pts:,} points, +{(b - base_b) / 1e6:.2f} MB "
              f"({100 * row['size_share']:.1f} % of the surfel layer), +{t - base_t:.3f} s "
              f"({100 * row['time_share']:.1f} % of its write time)")
    if args.runs:
        out["runs"] = [_bench_run(root, run, args) for run in
                       sorted(Path(root).parent.glob("ggds_*.usdc"))]
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


def _bench_run(root: Path, run: Path, args) -> dict:
    """A run's chunk files written again without and with its preview (medians)."""
    from lsd3d_usd.ggds.run.store import RUN_ATTRIBUTES

    folder = chunkio.chunk_folder(run)
    keys = [k for k in sorted(chunkio.read_chunk_map(root))
            if (folder / chunkio.chunk_file_name(k)).is_file()]
    fields = [(k, chunkio.read_chunk(root, k, [run])) for k in keys]
    fraction = chunkio.preview_fraction_of(root)
    times, sizes = {0.0: [], fraction: []}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            for s in (0.0, fraction):
                f = Path(tmp) / f"f{s}"
                t0 = time.perf_counter()
                for key, field in fields:
                    chunkio.write_run_chunk(f, key, field, RUN_ATTRIBUTES, preview_fraction=s)
                times[s].append(time.perf_counter() - t0)
                sizes[s] = sum(p.stat().st_size for p in f.glob("*.usdc"))
    t0, t1 = statistics.median(times[0.0]), statistics.median(times[fraction])
    row = {"run": run.stem, "chunks": len(keys), "fraction": fraction,
           "bytes": sizes[0.0], "preview_bytes": sizes[fraction] - sizes[0.0],
           "write_s": round(t0, 4), "preview_write_s": round(t1 - t0, 4)}
    print(f"{run.stem}: run chunk files {sizes[0.0] / 1e6:.2f} MB written in {t0:.3f} s; its "
          f"preview +{row['preview_bytes'] / 1e6:.2f} MB "
          f"({100 * row['preview_bytes'] / max(sizes[0.0], 1):.1f} %), +{t1 - t0:.3f} s "
          f"({100 * (t1 - t0) / t0:.1f} %)")
    return row


if __name__ == "__main__":
    sys.exit(main())
