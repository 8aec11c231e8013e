"""`lsd3d-usd bench ...`: benchmarks that print numbers and write JSON (speed is checked here,
never by timed tests).

Each benchmark is a :class:`Benchmark` in the registry ``BENCHMARKS`` (entry-point group
``lsd3d_usd.benchmarks``): a name, a help line, its configuration tree (every flag a leaf, so
``--config FILE.toml`` and ``--set KEY=VALUE`` work) and ``run(config) -> exit code``, which
imports the heavy parts. Another package adds one with an entry point naming its Benchmark.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from lsd3d_usd import configtree as ct
from lsd3d_usd.configtree import option
from lsd3d_usd.errors import InputError
from lsd3d_usd.registry import Registry


@dataclass(frozen=True)
class Benchmark:
    help: str
    config: type                 # a configtree dataclass
    run: Callable                # (config) -> exit code


# ------------------------------------------------------------------ render ---
@dataclass
class RenderBench:
    json: str | None = option(None, help="write per-configuration results as JSON",
                              flag="--json", metavar="OUT.json")
    png: str | None = option(None, help="time-vs-error plot (default: next to --json, or "
                                        "bench_render.png)", flag="--png", metavar="OUT.png")
    quick: bool = option(False, help="small subset, under a minute", flag="--quick")
    seed: int = option(0, help="seed of the synthetic scenes", flag="--seed")


def _render_run(c: RenderBench) -> int:
    from lsd3d_usd.render.benchmark import main   # heavy: torch, numba
    png = c.png
    if png is None:
        png = (c.json.rsplit(".", 1)[0] + ".png") if c.json else "bench_render.png"
    main(json_path=c.json, quick=c.quick, png_path=png, seed=c.seed)
    return 0


RENDER = Benchmark("CPU 2DGS rasteriser: forward/backward time, evaluations/s, memory, error vs "
                   "float64 reference", RenderBench, _render_run)


# ------------------------------------------------------------------- ggds ---
@dataclass
class GGDSBench:
    json: str | None = option(None, help="write results as JSON (keys s_per_step, psnr_heldout, "
                                         "psnr_heldout_2x, fd_novel_over_content, "
                                         "fd_prior_novel_over_content, fd_novel_over_prior, "
                                         "psnr_novel, depth_rel_err, normal_err_deg, "
                                         "off_surface_frac, psnr_overview, "
                                         "elevated_psnr_db_per_height, "
                                         "elevated_fd_over_prior, timing, quality)", flag="--json",
                              metavar="OUT.json")
    quick: bool = option(False, help="small subset (a couple of minutes)", flag="--quick")
    layout: str | None = option(None, help="layout for the timing chunk and the quality run "
                                           "(default: timing on samples/layouts/"
                                           "generated_seed7_200x200.usda, quality on "
                                           "hand_crossing.usda, the README sample, and on it)",
                                flag="--layout")
    steps: int | None = option(None, help="GGDS steps of the quality run (default: generate's, "
                                          "250)", flag="--steps", lo=0)
    strip: str | None = option(None, help="before/after image strip at 1x and 2x (default: "
                                          "next to --json, OUT_before_after.png)",
                               flag="--strip", metavar="OUT.png")
    fd: bool = option(True, help="the eval Fréchet distances (fd_novel_over_content)",
                      negate="--no-fd")
    fd_seeds: int | None = option(None, help="eval seeds the Fréchet distance ratios are "
                                             "averaged over (other seen views and novel offsets "
                                             "each; default 4, --quick 1)", flag="--fd-seeds",
                                  metavar="N")


def _ggds_run(c: GGDSBench) -> int:
    from lsd3d_usd.benchmarks.ggds import main   # heavy: a generate and eval
    main(json_path=c.json, quick=c.quick, layout=c.layout, steps=c.steps, fd=c.fd,
         strip=c.strip, fd_seeds=c.fd_seeds)
    return 0


GGDS = Benchmark("GGDS: seconds per step by surfel count and resolution; held-out PSNR, "
                 "depth/normal error and off-surface fraction after a short run",
                 GGDSBench, _ggds_run)


# ------------------------------------------------------------------ scale ---
@dataclass
class ScaleBench:
    json: str | None = option(None, help="write results as JSON (per configuration: chunks, "
                                         "surfels, surfels_per_m2, per_chunk_s, total_s, "
                                         "peak_rss_mb, driver_rss_mb, seam_psnr_drop_db, "
                                         "seam_psnr_drop_matched_db and its ci95, "
                                         "border_coverage; the 4-chunk corridor and grid also "
                                         "run as one region, and the summary's "
                                         "seam_drop_vs_one_region_db is what chunk-wise GGDS "
                                         "adds to the seam drop, paired per view)",
                              flag="--json", metavar="OUT.json")
    png: str | None = option(None, help="time and memory against chunks (default: next to "
                                        "--json)", flag="--png", metavar="OUT.png")
    full: bool = option(False, help="also 16-chunk corridor and grid, streaming rig renders "
                                    "along 200 m and 2 km, and a 10 km corridor with --steps 0 "
                                    "(an hour or more on 2 cores)", flag="--full")
    steps: int = option(30, help="GGDS steps per chunk", flag="--steps", lo=0)
    workers: int | None = option(None, help="regions in parallel (default: one per core)",
                                 flag="--workers", lo=1)
    views_per_chunk: int = option(24, help="training views per chunk", flag="--views-per-chunk",
                                  lo=1)
    seed: int = option(11, help="seed of the generated layouts", flag="--seed")
    seam_views: int = option(48, help="views of the seam measure per configuration (its 95 % "
                                      "interval narrows with more)", flag="--seam-views", lo=1)
    same_views: int = option(32, help="views from the same positions in chunk 0_0 rendered in "
                                      "every configuration: its PSNR against the one-chunk "
                                      "scene, paired per view (0 = off)", flag="--same-views",
                             lo=0)
    repeats: int = option(1, help="run every configuration with this many GGDS seeds (--seed, "
                                  "--seed+1, ...; the same layouts): the same-view difference "
                                  "becomes the mean over seeds, its interval over seeds and "
                                  "views", flag="--repeats", lo=1)
    work: str | None = option(None, help="keep the generated scenes in this folder (default: a "
                                         "temporary one, removed)", flag="--work")


def _scale_run(c: ScaleBench) -> int:
    from lsd3d_usd.benchmarks.scale import main   # heavy: many generates
    main(json_path=c.json, full=c.full, steps=c.steps, workers=c.workers, seed=c.seed,
         views_per_chunk=c.views_per_chunk, work=c.work, png_path=c.png,
         seam_views=c.seam_views, same_views=c.same_views, repeats=c.repeats)
    return 0


SCALE = Benchmark("chunk-wise generate at growing extent: time, memory, density and seams per "
                  "configuration", ScaleBench, _scale_run)

# ------------------------------------------------------------------ lidar ---
@dataclass
class LidarBench:
    json: str | None = option(None, help="write results as JSON (keys rays, s_per_sweep, camera_s, "
                                         "sweep_over_camera, memory_mb_beyond_scene, "
                                         "range_err_<class>_median_m / _p95_m, "
                                         "vs_reference_max_m, vs_camera_within_1pct)",
                              flag="--json", metavar="OUT.json")
    scene: str | None = option(None, help="scene to sweep (default: the README sample generated "
                                          "with generate's defaults, a few minutes)",
                               flag="--scene", metavar="SCENE")
    quick: bool = option(False, help="without GGDS and with 100 k surfels (under a minute)",
                         flag="--quick")
    sweeps: int | None = option(None, help="sweeps along the default route (default 5, --quick 2)",
                                flag="--sweeps", lo=1, hi=1000)


def _lidar_run(c: LidarBench) -> int:
    from lsd3d_usd.benchmarks.lidar import main   # heavy: numba, a generate
    main(json_path=c.json, scene=c.scene, quick=c.quick, sweeps=c.sweeps)
    return 0


LIDAR = Benchmark("LiDAR sweeps: seconds per waymo_top sweep against a camera render, range error "
                  "against the proxy mesh, the float64 reference and the camera depth",
                  LidarBench, _lidar_run)

@dataclass
class DatasetBench:
    json: str | None = option(None, help="write results as JSON (keys keyframes_per_min, "
                                         "sensor_frames_per_min, share, seconds_by_part, "
                                         "peak_rss_mb)", flag="--json", metavar="OUT.json")
    scene: str | None = option(None, help="scene to drive (default: the README sample "
                                          "generated with generate's defaults, a few minutes)",
                               flag="--scene", metavar="SCENE")
    quick: bool = option(False, help="no GGDS, a 1 s drive at 480 px (a few minutes)",
                         flag="--quick")
    seconds: float | None = option(None, help="drive length (default 20, --quick 1)",
                                   flag="--seconds", lo=0.5, hi=3600.0)
    width: int | None = option(None, help="camera width (default 1600, --quick 480)",
                               flag="--width", lo=8, hi=8192)


def _dataset_run(c: DatasetBench) -> int:
    from lsd3d_usd.benchmarks.dataset import main   # heavy: numba, a generate
    main(json_path=c.json, scene=c.scene, quick=c.quick, seconds=c.seconds, width=c.width)
    return 0


DATASET = Benchmark("dataset throughput: nuScenes samples per minute with nuscenes6 + hdl32 at "
                    "12 / 20 Hz and each sensor's share", DatasetBench, _dataset_run)

@dataclass
class SimBench:
    json: str | None = option(None, help="write results as JSON (keys steps_per_s_world, "
                                         "steps_per_s_front, steps_per_s_full, runs_<name>, "
                                         "peak_rss_mb, rss_mb_per_minute, "
                                         "rss_growth_after_first_minute)",
                              flag="--json", metavar="OUT.json")
    scene: str | None = option(None, help="scene to drive (default: the README sample "
                                          "generated with generate's defaults, a few minutes)",
                               flag="--scene", metavar="SCENE")
    quick: bool = option(False, help="no GGDS, fewer steps (a couple of minutes)", flag="--quick")
    steps: int | None = option(None, help="steps per timed run of the world-only configuration "
                                          "(default 100, --quick 20; sensors run fewer)",
                               flag="--steps", lo=1, hi=100_000)
    repeats: int | None = option(None, help="timed runs per configuration, the median reported "
                                            "(default 3, --quick 1)", flag="--repeats", lo=1, hi=100)
    remote: bool = option(False, help="also the overhead of `sim serve` (gRPC) over the "
                                      "in-process env at nuscenes6 480x270 + hdl32 (keys "
                                      "remote_overhead_pct, remote_codec_pct)", flag="--remote")
    memory_seconds: float | None = option(None, help="also a closed-loop run this long (simulated "
                                                     "seconds, rig none) with RSS each minute",
                                          flag="--memory-seconds", lo=60.0, hi=86_400.0)


def _sim_run(c: SimBench) -> int:
    from lsd3d_usd.benchmarks.sim import main   # heavy: gymnasium, numba, a generate
    main(json_path=c.json, scene=c.scene, quick=c.quick, steps=c.steps, repeats=c.repeats,
         memory_seconds=c.memory_seconds, remote=c.remote)
    return 0


SIM = Benchmark("closed loop: env steps per second with no sensors, one front camera and "
                "nuscenes6 + hdl32 at 480x270; memory over a long episode", SimBench, _sim_run)

@dataclass
class FrameBench:
    json: str | None = option(None, help="write results as JSON (keys frame_480x270_s, "
                                         "frame_960x540_s, full_step_s (nuscenes6 480x270 + "
                                         "hdl32), corridor_over_sample, each also _no_lod; "
                                         "lod_psnr_db (lowest over the rig's frames), "
                                         "lod_psnr_db_overview, lod_psnr_db_lane_views, "
                                         "lod_psnr_db_overview_cameras (the scene's own), "
                                         "drawn_surfels, hidden_fraction: the drawn "
                                         "surfels the frame never shows)",
                              flag="--json", metavar="OUT.json")
    scene: str | None = option(None, help="scene (default: the README sample generated with "
                                          "generate's defaults, a few minutes)",
                               flag="--scene", metavar="SCENE")
    corridor: str | None = option(None, help="a long scene (e.g. the README's 1 km corridor): "
                                             "its middle frame over the scene's",
                                  flag="--corridor", metavar="SCENE")
    quick: bool = option(False, help="no GGDS, 3 poses, 1 repeat", flag="--quick")
    poses: int | None = option(None, help="poses along the longest route (default 5, --quick "
                                          "3)", flag="--poses", lo=1, hi=100)
    repeats: int | None = option(None, help="timed frames per pose and mode (default 3)",
                                 flag="--repeats", lo=1, hi=100)
    lod_px: float = option(4.0, help="level-of-detail budget in pixels", flag="--lod-px",
                           lo=0.5, hi=256.0)


def _frame_run(c: FrameBench) -> int:
    from lsd3d_usd.benchmarks.frame import main   # heavy: numba, a generate
    main(json_path=c.json, scene=c.scene, corridor=c.corridor, quick=c.quick, poses=c.poses,
         repeats=c.repeats, lod_px=c.lod_px)
    return 0


FRAME = Benchmark("one sensor frame: 480x270 / 960x540 camera frames and a nuscenes6 + hdl32 "
                  "sim step with and without level of detail, its PSNR, a long scene's frame "
                  "over the sample's", FrameBench, _frame_run)

BENCHMARKS = Registry("lsd3d_usd.benchmarks", "benchmark", {
    "render": "lsd3d_usd.bench:RENDER",
    "ggds": "lsd3d_usd.bench:GGDS",
    "scale": "lsd3d_usd.bench:SCALE",
    "lidar": "lsd3d_usd.bench:LIDAR",
    "dataset": "lsd3d_usd.bench:DATASET",
    "sim": "lsd3d_usd.bench:SIM",
    "frame": "lsd3d_usd.bench:FRAME",
})


def _runner(bench: Benchmark):
    def run(args) -> int:
        got = ct.command_config(args, bench.config)
        return 0 if got is None else bench.run(got[0])
    return run


def register(subparsers):
    p = subparsers.add_parser(
        "bench", help="run benchmarks (speed and accuracy numbers)",
        description="Benchmarks that print numbers and write JSON. Measured on shared cores, "
                    "timings are noisy.")
    sub = p.add_subparsers(dest="bench_name", metavar="BENCHMARK")
    for name, bench in BENCHMARKS.items():
        if not isinstance(bench, Benchmark):
            raise InputError(f"benchmark {name!r} is not a lsd3d_usd.bench.Benchmark")
        bp = sub.add_parser(name, help=bench.help, description=bench.help)
        ct.add_tree_options(bp, f"bench {name}")
        ct.add_arguments(bp, bench.config)
        bp.set_defaults(func=_runner(bench), compiles_kernels=True)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
