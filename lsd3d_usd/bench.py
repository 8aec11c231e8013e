"""`lsd3d-usd bench ...`: benchmarks that print numbers and write JSON (speed is checked here,
never by timed tests).

A small registry: each benchmark is BENCHMARKS[name] = (help, add_arguments, run), so another
area adds its own (e.g. `bench ggds`) with one `register_benchmark` call in this module.
"""
from __future__ import annotations

import argparse

BENCHMARKS: dict = {}


def register_benchmark(name, help_text, add_arguments, run):
    """add_arguments(parser) adds flags; run(args) -> exit code. Keep heavy imports in run."""
    BENCHMARKS[name] = (help_text, add_arguments, run)


# ------------------------------------------------------------------ render ---
def _render_args(p: argparse.ArgumentParser):
    p.add_argument("--json", metavar="OUT.json", help="write per-configuration results as JSON")
    p.add_argument("--png", metavar="OUT.png",
                   help="time-vs-error plot (default: next to --json, or bench_render.png)")
    p.add_argument("--quick", action="store_true", help="small subset, under a minute")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic scenes (default 0)")


def _render_run(args) -> int:
    from lsd3d_usd.render.benchmark import main

    png = args.png
    if png is None:
        png = (args.json.rsplit(".", 1)[0] + ".png") if args.json else "bench_render.png"
    main(json_path=args.json, quick=args.quick, png_path=png, seed=args.seed)
    return 0


register_benchmark(
    "render",
    "CPU 2DGS rasteriser: forward/backward time, evaluations/s, memory, error vs float64 reference",
    _render_args, _render_run)


# ------------------------------------------------------------------- ggds ---
def _ggds_args(p: argparse.ArgumentParser):
    p.add_argument("--json", metavar="OUT.json", help="write results as JSON (keys s_per_step, "
                   "psnr_heldout, psnr_heldout_2x, fd_novel_over_content, "
                   "fd_prior_novel_over_content, fd_novel_over_prior, psnr_novel, "
                   "depth_rel_err, normal_err_deg, off_surface_frac, timing, quality)")
    p.add_argument("--quick", action="store_true", help="small subset (a couple of minutes)")
    p.add_argument("--layout", help="layout for the timing chunk and the quality run (default: "
                                    "timing on samples/layouts/generated_seed7_200x200.usda, "
                                    "quality on hand_crossing.usda, the README sample, and on it)")
    p.add_argument("--steps", type=int, help="GGDS steps of the quality run (default: generate's, 250)")
    p.add_argument("--strip", metavar="OUT.png", help="before/after image strip at 1x and 2x "
                   "(default: next to --json, OUT_before_after.png)")
    p.add_argument("--no-fd", action="store_true", help="skip the eval Fréchet distances "
                   "(fd_novel_over_content)")
    p.add_argument("--fd-seeds", type=int, default=None, metavar="N",
                   help="eval seeds the Fréchet distance ratios are averaged over (other seen "
                        "views and novel offsets each; default 4, --quick 1)")


def _ggds_run(args) -> int:
    from lsd3d_usd.benchmarks.ggds import main

    main(json_path=args.json, quick=args.quick, layout=args.layout, steps=args.steps,
         fd=not args.no_fd, strip=args.strip, fd_seeds=args.fd_seeds)
    return 0


register_benchmark(
    "ggds",
    "GGDS: seconds per step by surfel count and resolution; held-out PSNR, depth/normal error and "
    "off-surface fraction after a short run",
    _ggds_args, _ggds_run)


# ------------------------------------------------------------------ scale ---
def _scale_args(p: argparse.ArgumentParser):
    p.add_argument("--json", metavar="OUT.json", help="write results as JSON (per configuration: "
                   "chunks, surfels, surfels_per_m2, per_chunk_s, total_s, peak_rss_mb, "
                   "driver_rss_mb, seam_psnr_drop_db, seam_psnr_drop_matched_db and its "
                   "ci95, border_coverage; the 4-chunk corridor and grid also run as one "
                   "region, and the summary's seam_drop_vs_one_region_db is what chunk-wise "
                   "GGDS adds to the seam drop, paired per view)")
    p.add_argument("--png", metavar="OUT.png", help="time and memory against chunks (default: "
                                                    "next to --json)")
    p.add_argument("--full", action="store_true",
                   help="also 16-chunk corridor and grid, streaming rig renders along 200 m and "
                        "2 km, and a 10 km corridor with --steps 0 (an hour or more on 2 cores)")
    p.add_argument("--steps", type=int, default=30, help="GGDS steps per chunk (default 30)")
    p.add_argument("--workers", type=int, help="regions in parallel (default: one per core)")
    p.add_argument("--views-per-chunk", type=int, default=24, help="training views per chunk "
                                                                   "(default 24)")
    p.add_argument("--seed", type=int, default=11, help="seed of the generated layouts (default 11)")
    p.add_argument("--seam-views", type=int, default=48,
                   help="views of the seam measure per configuration (default 48; its 95 %% "
                        "interval narrows with more)")
    p.add_argument("--same-views", type=int, default=32,
                   help="views from the same positions in chunk 0_0 rendered in every "
                        "configuration: its PSNR against the one-chunk scene, paired per view "
                        "(default 32; 0 = off)")
    p.add_argument("--repeats", type=int, default=1,
                   help="run every configuration with this many GGDS seeds (--seed, --seed+1, "
                        "...; the same layouts): the same-view difference becomes the mean over "
                        "seeds, its interval over seeds and views (a run's training views are a "
                        "random draw: ±0.5 dB from one seed to the next at 24 views per chunk; "
                        "default 1)")
    p.add_argument("--work", help="keep the generated scenes in this folder (default: a temporary "
                                  "one, removed)")


def _scale_run(args) -> int:
    from lsd3d_usd.benchmarks.scale import main

    main(json_path=args.json, full=args.full, steps=args.steps, workers=args.workers,
         seed=args.seed, views_per_chunk=args.views_per_chunk, work=args.work, png_path=args.png,
         seam_views=args.seam_views, same_views=args.same_views, repeats=args.repeats)
    return 0


register_benchmark(
    "scale",
    "chunk-wise generate at growing extent: time, memory, density and seams per configuration",
    _scale_args, _scale_run)


def register(subparsers):
    p = subparsers.add_parser(
        "bench", help="run benchmarks (speed and accuracy numbers)",
        description="Benchmarks that print numbers and write JSON. Measured on shared cores, "
                    "timings are noisy.")
    sub = p.add_subparsers(dest="bench_name", metavar="BENCHMARK")
    for name, (help_text, add_args, run) in BENCHMARKS.items():
        bp = sub.add_parser(name, help=help_text, description=help_text)
        add_args(bp)
        bp.set_defaults(func=run, compiles_kernels=True)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
