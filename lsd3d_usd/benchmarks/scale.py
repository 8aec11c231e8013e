"""`lsd3d-usd bench scale`: chunk-wise generation at growing extent — time, memory, density and
seams per configuration, so "linear time, bounded memory, constant density" is a measured
claim.

Each configuration generates a procedural layout (corridor or grid of chunks) and runs
`generate` in a child process with GGDS in chunk regions at fixed, small settings; the child's
peak memory is read from the operating system (wait4), the workers' from their own reports.
With --full: 16-chunk corridor and grid, rig renders along a 200 m and a 2 km route of a 2 km
corridor with chunk streaming (peak memory of each), and a 10 km corridor through layout,
proxy and surfel initialisation (`--steps 0`).
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.view_sampling import sample_views
from lsd3d_usd.eval.render import render_view
from lsd3d_usd.eval.seams import paired_matched_drop
from lsd3d_usd.eval.seams_eval import pooled_psnr, seam_stats, view_errors
from lsd3d_usd.layout import generator
from lsd3d_usd.layout.usdio import read_layout, write_layout
from lsd3d_usd.proxy.usdio import proxy_arrays
from lsd3d_usd.scene import atomic_write_text
from lsd3d_usd.views.stage_data import SceneReader

CONFIGS = [("corridor", 1), ("corridor", 4), ("grid", 4)]
FULL_CONFIGS = [("corridor", 16), ("grid", 16)]
# also run as one region (no chunk seams): the seam measure's baseline
BASELINE_CONFIGS = [("corridor", 4), ("grid", 4)]


def _extent(shape: str, chunks: int) -> tuple[int, int]:
    if shape == "corridor":
        return 100 * chunks, 100
    side = int(round(chunks ** 0.5))
    return 100 * side, 100 * side


def _tree_hwm_mb(pid: int) -> float:
    """The largest VmHWM (peak RSS, MB) among process ``pid`` and its descendants now."""
    def status(p):
        try:
            with open(f"/proc/{p}/status", encoding="ascii") as fh:
                return fh.read()
        except OSError:
            return ""
    children: dict = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            for line in status(entry).splitlines():
                if line.startswith("PPid:"):
                    children.setdefault(int(line.split()[1]), []).append(int(entry))
                    break
    best, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        for line in status(p).splitlines():
            if line.startswith("VmHWM:"):
                best = max(best, int(line.split()[1]) / 1024.0)
    return best


def _child(cmd: list, log_path: Path, poll: float = 0.5) -> tuple[int, float, float]:
    """Run a command; (exit code, wall seconds, peak RSS MB of the largest process among it
    and its descendants). The peak is polled from /proc (VmHWM, monotonic per process): the
    rusage of wait4 would carry this benchmark's own peak into the child (Linux keeps
    ru_maxrss across exec)."""
    t0 = time.perf_counter()
    peak = 0.0
    with open(log_path, "w") as fh:
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
        while p.poll() is None:
            peak = max(peak, _tree_hwm_mb(p.pid))
            time.sleep(poll)
    return p.returncode, time.perf_counter() - t0, peak


def _cli(*args) -> list:
    return [sys.executable, "-m", "lsd3d_usd", *map(str, args)]


def _layout(path: Path, extent, seed: int) -> Path:
    write_layout(generator.generate(seed, extent, "urban"), path)
    return path


def _view_measures(scene: Path, views: int, same_cameras, size=(240, 135),
                   seed: int = 0) -> tuple[dict | None, list | None, object]:
    """(the seam measure on held-out-style views over the whole scene, the PSNR of each of
    ``same_cameras`` over the pixels showing chunk 0_0: views from the same positions in
    every configuration, scored on the same surface; the seam views' eval.seams.SeamStats,
    for pairing with another scene of the same layout, or None)."""
    sc = S.Scene.open(scene)
    layout = read_layout(sc.layer_path("layout"))
    proxy = proxy_arrays(sc.layer_path("proxy"))
    cams = [v.camera for v in sample_views(layout, views, *size, seed=seed + 4242,
                                           novel_frac=0.25)]
    reader = SceneReader(sc.open_stage(), actors=False)
    surfels, env = reader.surfels(), reader.env()
    runs = sc.runs()
    run = runs[0].name if runs else None
    # rendered as the measure asks (none for a scene of one chunk, which has no seams)
    stats, why = seam_stats(sc, run, layout, proxy, cams,
                            (render_view(surfels, env, cam) for cam in cams))
    stats = stats[0] if stats is not None else None
    res = stats.result() if stats is not None else None
    chunk = float(layout.chunk_size)
    same, _ = view_errors(sc, run, proxy, same_cameras,
                          (render_view(surfels, env, cam) for cam in same_cameras),
                          region=(0.0, 0.0, chunk, chunk))
    return (res if res is not None else {"unavailable": why}), same, stats


def same_view_cameras(seed: int, views: int, size=(240, 135)) -> list:
    """Held-out-style cameras on the lanes of chunk 0_0 alone (the one-chunk corridor's
    layout; the generator makes a chunk's content the same at every extent), so that every
    configuration's PSNR is measured from the same positions."""
    layout = generator.generate(seed, _extent("corridor", 1), "urban")
    return [v.camera for v in sample_views(layout, views, *size, seed=seed + 777,
                                           novel_frac=0.25)]


def paired(a: list, b: list, draws: int = 1000) -> tuple[float, list]:
    """PSNR of the per-view errors ``a`` (pairs of sum of squared errors, values; pooled
    over the views, each weighted by its pixels) minus that of ``b`` from the same views, and
    its 95 % bootstrap interval over the views."""
    return paired_seeds([(a, b)], draws)


def paired_seeds(pairs: list, draws: int = 1000) -> tuple[float, list]:
    """``paired`` over several runs: (a, b) per GGDS seed, both from the same views. The
    mean of the per-seed differences and its 95 % interval from a two-level bootstrap (seeds,
    then views within each): a run's training views are a random draw too, and with 24 per
    chunk the same configuration scores ±0.5 dB from one seed to the next."""
    pairs = [(np.asarray(a, float).reshape(-1, 2), np.asarray(b, float).reshape(-1, 2))
             for a, b in pairs]

    def diff(a, b, idx):
        return pooled_psnr(a[idx]) - pooled_psnr(b[idx])
    rng = np.random.default_rng(0)
    boots = []
    for _ in range(draws):
        picks = rng.integers(0, len(pairs), len(pairs)) if len(pairs) > 1 else [0]
        vals = [diff(*pairs[s], rng.integers(0, len(pairs[s][0]), len(pairs[s][0])))
                for s in picks]
        boots.append(float(np.mean(vals)))
    boots = np.asarray([x for x in boots if np.isfinite(x)])
    point = float(np.mean([diff(a, b, np.arange(len(a))) for a, b in pairs]))
    return (round(point, 3), [round(float(x), 3) for x in np.percentile(boots, [2.5, 97.5])])


def run_config(shape: str, chunks: int, work: Path, *, steps: int, workers: int, seed: int,
               views_per_chunk: int, mode: str = "chunk", seams_views: int = 48,
               same_cameras=(), ggds_seed: int | None = None, seam_stats: dict | None = None,
               log=print) -> dict:
    """One configuration: the layout of ``seed``, `generate` with ``ggds_seed`` (default
    ``seed``: the training views, surfel start and GGDS's noise), then the measures.
    ``seam_stats`` (a dict), where given, keeps the seam views' statistics by config name."""
    extent = _extent(shape, chunks)
    ggds_seed = seed if ggds_seed is None else int(ggds_seed)
    name = (f"{shape}{chunks}" + ("" if mode == "chunk" else f"_{mode}")
            + ("" if ggds_seed == seed else f"_s{ggds_seed}"))
    lay = _layout(work / f"{name}.usda", extent, seed)
    out = work / name
    summary = work / f"{name}.json"
    code, wall, rss = _child(_cli(
        "generate", "--layout", lay, "-o", out, "--steps", steps, "--resolution", "240x135",
        "--env-resolution", "256x128", "--no-actors", "--no-progress", "--regions", mode,
        "--workers", workers, "--seed", ggds_seed, "--json", summary,
        "--set", f"ggds.regions.views_per_chunk={views_per_chunk}", "--set", "ggds.held_out=4",
        "--set", "ggds.checkpoint_every=1000"), work / f"{name}.log")
    if code != 0:
        raise RuntimeError(f"bench scale: {name} failed (see {work / (name + '.log')})")
    s = json.loads(summary.read_text())
    g = s.get("ggds", {})
    per = g.get("per_region") or {}
    # per-chunk time over the chunks that hold a full share of surfels (not the few surfels
    # of a building overhanging into an otherwise empty neighbour)
    big = max((r.get("surfels") or 0 for r in per.values()), default=0)
    full = [r for r in per.values() if r.get("wall_s") and (r.get("surfels") or 0) >= 0.25 * big]
    walls = [r["wall_s"] for r in full] or [g.get("wall_s", 0.0)]
    cpus = [r["cpu_s"] for r in full if r.get("cpu_s")]
    seams, same, stats = _view_measures(out, seams_views, list(same_cameras), seed=seed)
    if seam_stats is not None and stats is not None:
        seam_stats[name] = stats
    surf = s["surfels"]
    row = {"config": name, "shape": shape, "chunks": int(surf["chunks"]), "ggds_seed": ggds_seed,
           "extent_m": list(extent), "regions": g.get("regions"), "mode": mode,
           "surfels": int(surf["count"]),
           "surfels_per_m2": round(surf["count"] / max(surf["viewWeightedArea_m2"], 1e-9), 3),
           "surfels_per_m2_footprint": round(surf["count"] / (extent[0] * extent[1]), 3),
           "per_chunk_s": round(statistics.median(walls), 2), "total_s": round(wall, 1),
           # CPU seconds do not depend on how many regions run at once (wall seconds do)
           "per_chunk_cpu_s": round(statistics.median(cpus), 2) if cpus else None,
           "ggds_s": s["timings"].get("ggds_s"),
           # the largest process of the tree (driver or a worker), polled and as reported
           "peak_rss_mb": round(max(rss, g.get("worker_peak_rss_mb") or 0.0), 1),
           "driver_rss_mb": s.get("peak_rss_mb"), "worker_rss_mb": g.get("worker_peak_rss_mb"),
           "psnr_heldout": g.get("psnr_novel"),
           # the same chunk in every configuration (the generator seeds chunk by chunk)
           "psnr_chunk_0_0": ((per.get("chunk_0_0") or {}).get("metrics") or {}).get("psnr_novel"),
           # PSNR from the same positions in chunk 0_0 in every configuration (per view)
           "same_views_errors": [list(e) for e in same] if same else None,
           "psnr_same_views_db": round(pooled_psnr(same), 3) if same else None,
           "seam_psnr_drop_db": seams.get("psnr_drop_db") if seams else None,
           "seam_psnr_drop_class_matched_db": (seams.get("psnr_drop_class_matched_db")
                                               if seams else None),
           # class and distance matched, with its 95 % interval over the seam views
           "seam_psnr_drop_matched_db": seams.get("psnr_drop_matched_db") if seams else None,
           "seam_psnr_drop_matched_ci95_db": (seams.get("psnr_drop_matched_ci95_db")
                                              if seams else None),
           "border_coverage": seams.get("border_coverage") if seams else None,
           "seams": seams, "steps": steps, "workers": workers}
    log(f"{name:>14s}: {row['chunks']:3d} chunks {row['surfels']:>9,} surfels "
        f"({row['surfels_per_m2']:.1f}/m² weighted) per chunk {row['per_chunk_s']:7.1f} s, total "
        f"{row['total_s']:7.1f} s, peak {row['peak_rss_mb']:7.0f} MB (driver "
        f"{row['driver_rss_mb'] or 0:.0f}), held-out {row['psnr_heldout'] or float('nan'):.2f} dB, "
        f"chunk 0_0 same views {row['psnr_same_views_db']} dB, "
        f"seam views: border {_get(seams, 'border', 'psnr_db')} / interior "
        f"{_get(seams, 'interior', 'psnr_db')} dB (class-matched drop "
        f"{row['seam_psnr_drop_class_matched_db']}, class and distance matched "
        f"{row['seam_psnr_drop_matched_db']} in {row['seam_psnr_drop_matched_ci95_db']}), "
        f"border coverage {row['border_coverage']}")
    return row


def _get(d, *keys):
    for k in keys:
        d = (d or {}).get(k)
    return d


def _trajectory(layout, length_m: float, path: Path, speed: float = 10.0) -> Path:
    """Poses along the lane that runs farthest in x, at constant speed."""
    best = max(layout.drivable_lanes(),
               key=lambda ln: np.ptp(ln.points[:, 0]))
    y = float(np.median(best.points[:, 1]))
    x0 = float(best.points[:, 0].min()) + 5.0
    n = int(length_m / speed) + 1
    poses = [{"t": float(k), "x": x0 + speed * k, "y": y, "z": 0.0, "yaw": 0.0} for k in range(n)]
    path.write_text(json.dumps(poses))
    return path


def stream_test(work: Path, seed: int, log=print) -> dict:
    """Rig render peak memory along a 200 m and a 2 km route of a 2 km corridor."""
    lay = _layout(work / "stream.usda", (2100, 100), seed)
    out = work / "stream"
    code, wall, rss = _child(_cli("generate", "--layout", lay, "-o", out, "--steps", 0,
                                  "--env-resolution", "256x128", "--no-actors", "--no-progress"),
                             work / "stream_gen.log")
    if code != 0:
        raise RuntimeError(f"bench scale: the 2 km corridor failed (see {work / 'stream_gen.log'})")
    layout = generator.generate(seed, (2100, 100), "urban")
    res = {"scene_generate_s": round(wall, 1), "scene_generate_rss_mb": round(rss, 1)}
    for length in (200, 2000):
        traj = _trajectory(layout, length, work / f"traj_{length}.json")
        code, wall, rss = _child(_cli("render", out, "--rig", "waymo5", "--trajectory", traj,
                                      "--fps", 1, "--seconds", length / 10.0, "--resolution", 64,
                                      "--no-video", "--no-overview", "--no-progress", "-o",
                                      work / f"rig_{length}"), work / f"rig_{length}.log")
        if code != 0:
            raise RuntimeError(f"bench scale: rig render over {length} m failed "
                               f"(see {work / f'rig_{length}.log'})")
        res[f"rig_{length}m_rss_mb"] = round(rss, 1)
        res[f"rig_{length}m_s"] = round(wall, 1)
    res["rss_ratio_2km_over_200m"] = round(res["rig_2000m_rss_mb"] / res["rig_200m_rss_mb"], 3)
    log(f"streaming rig render: 200 m {res['rig_200m_rss_mb']:.0f} MB, 2 km "
        f"{res['rig_2000m_rss_mb']:.0f} MB (ratio {res['rss_ratio_2km_over_200m']})")
    return res


def corridor_10km(work: Path, seed: int, log=print) -> dict:
    lay = _layout(work / "c10k.usda", (10_000, 100), seed)
    code, wall, rss = _child(_cli("generate", "--layout", lay, "-o", work / "c10k", "--steps", 0,
                                  "--env-resolution", "256x128", "--no-actors", "--no-progress",
                                  "--json", work / "c10k.json"), work / "c10k.log")
    if code != 0:
        raise RuntimeError(f"bench scale: the 10 km corridor failed (see {work / 'c10k.log'})")
    s = json.loads((work / "c10k.json").read_text())
    res = {"chunks": s["surfels"]["chunks"], "surfels": s["surfels"]["count"],
           "total_s": round(wall, 1), "peak_rss_mb": round(rss, 1), "timings": s["timings"]}
    log(f"10 km corridor, --steps 0: {res['chunks']} chunks, {res['surfels']:,} surfels, "
        f"{res['total_s']:.0f} s, peak {res['peak_rss_mb']:.0f} MB")
    return res


def plot(rows: list, path) -> None:
    matplotlib.use("Agg")
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.4))
    for shape, marker in (("corridor", "o"), ("grid", "s")):
        r = sorted((x for x in rows if x["shape"] == shape and x["mode"] == "chunk"),
                   key=lambda x: x["chunks"])
        if not r:
            continue
        n = [x["chunks"] for x in r]
        ax[0].plot(n, [x["total_s"] for x in r], marker + "-", label=f"{shape}: total")
        ax[0].plot(n, [x["per_chunk_s"] for x in r], marker + "--", label=f"{shape}: per chunk")
        ax[1].plot(n, [x["peak_rss_mb"] for x in r], marker + "-", label=f"{shape}: largest process")
        ax[1].plot(n, [x["driver_rss_mb"] for x in r], marker + ":", label=f"{shape}: driver")
    for a, t in zip(ax, ("time (s)", "peak memory (MB)")):
        a.set_xlabel("chunks"); a.set_ylabel(t); a.set_xscale("log", base=2); a.legend(fontsize=7)
    fig.suptitle("chunk-wise generate: time and memory against extent")
    fig.tight_layout(); fig.savefig(path, dpi=100); plt.close(fig)


def seams_vs_one_region(stats: dict, seed: int, seeds: list) -> dict:
    """Per GGDS seed and baseline layout: the chunk-wise scene's matched seam drop against the
    same layout's one-region scene from the same views (eval.seams.paired_matched_drop)."""
    out = {}
    for s_ in seeds:
        tag = "" if s_ == seed else f"_s{s_}"
        row = out[str(s_)] = {}
        for shape, n in BASELINE_CONFIGS:
            a, b = stats.get(f"{shape}{n}{tag}"), stats.get(f"{shape}{n}_scene{tag}")
            row[f"{shape}{n}"] = (paired_matched_drop(a, b) if a is not None
                                      and b is not None else {"difference_db": None,
                                                              "ci95_db": None})
    return out


def _log_seams_vs_one_region(added: dict, log) -> None:
    for s_, row in added.items():
        for k, v in row.items():
            log(f"{k} seed {s_}: seam drop {v.get('scene_db')} dB chunk-wise, "
                f"{v.get('reference_db')} dB as one region: chunk-wise adds "
                f"{v['difference_db']} dB {v['ci95_db']}")


def _mean(vals):
    vals = [v for v in vals if v is not None]
    return round(float(np.mean(vals)), 3) if vals else None


def main(json_path=None, *, full=False, steps=30, workers=None, seed=11, views_per_chunk=24,
         work=None, png_path=None, seam_views=48, same_views=32, repeats=1, log=print) -> dict:
    workers = workers or os.cpu_count() or 1
    same = same_view_cameras(seed, same_views) if same_views else []
    configs = CONFIGS + (FULL_CONFIGS if full else [])
    with tempfile.TemporaryDirectory(prefix="lsd3d-bench-scale-") as tmp:
        wdir = Path(work) if work else Path(tmp)
        wdir.mkdir(parents=True, exist_ok=True)

        stats: dict = {}

        def run(shape, n, ggds_seed=None, **kw):
            return run_config(shape, n, wdir, steps=steps, workers=workers, seed=seed,
                              views_per_chunk=views_per_chunk, seams_views=seam_views,
                              same_cameras=same, ggds_seed=ggds_seed, seam_stats=stats,
                              log=log, **kw)
        seeds = [seed + k for k in range(max(int(repeats), 1))]
        rows = [run(shape, n) for shape, n in configs]
        # the 4-chunk corridor and grid as one region (no chunk seams), per GGDS seed: the
        # seam measure's baseline for what a layout's border bands hold
        bases = {s_: {f"{shape}{n}": run(shape, n, ggds_seed=s_, mode="scene")
                      for shape, n in BASELINE_CONFIGS} for s_ in seeds}
        result = {"configs": rows, **{f"scene_region_{k}": v for k, v in bases[seed].items()}}
        base = bases[seed]["grid4"]
        one = min(rows, key=lambda r: r["chunks"])
        big = max(rows, key=lambda r: r["chunks"])
        # the same layouts again with other GGDS seeds: the spread of a run's training views
        again = [[run(shape, n, ggds_seed=s_) for shape, n in configs] for s_ in seeds[1:]]
        if again:
            result["repeats"] = again
            result["scene_region_repeats"] = [bases[s_] for s_ in seeds[1:]]
        result["seam_vs_one_region"] = added = seams_vs_one_region(stats, seed, seeds)
        _log_seams_vs_one_region(added, log)
        here = added[str(seed)]
        by_seed = {k: [added[str(s_)][k]["difference_db"] for s_ in seeds] for k in here}
        ib, io = rows.index(big), rows.index(one)    # the same configurations, other seeds
        runs = [(big, one)] + [(rr[ib], rr[io]) for rr in again]
        pairs = [(b["same_views_errors"], o["same_views_errors"]) for b, o in runs
                 if b["same_views_errors"] and o["same_views_errors"]]
        paired = paired_seeds(pairs) if pairs else (None, None)
        per_seed = [paired(*p)[0] for p in pairs]
        result["summary"] = {
            "largest_chunks": big["chunks"],
            "density_ratio": round(big["surfels_per_m2"] / one["surfels_per_m2"], 4),
            "per_chunk_time_ratio": round(big["per_chunk_s"] / one["per_chunk_s"], 3),
            "per_chunk_cpu_ratio": (round(big["per_chunk_cpu_s"] / one["per_chunk_cpu_s"], 3)
                                    if big["per_chunk_cpu_s"] and one["per_chunk_cpu_s"] else None),
            "psnr_chunk_0_0_delta_db": (round(big["psnr_chunk_0_0"] - one["psnr_chunk_0_0"], 3)
                                        if big["psnr_chunk_0_0"] and one["psnr_chunk_0_0"] else None),
            # the same views in chunk 0_0, paired per view: largest minus one-chunk scene
            # (with --repeats: the mean over GGDS seeds, the interval over seeds and views)
            "psnr_same_views_delta_db": paired[0],
            "psnr_same_views_delta_ci95_db": paired[1],
            "psnr_same_views_delta_seeds_db": per_seed,
            "ggds_seeds": [seed + k for k in range(len(pairs))],
            "peak_rss_ratio": round(big["peak_rss_mb"] / one["peak_rss_mb"], 3),
            "max_peak_rss_mb": max(r["peak_rss_mb"] for r in rows),
            "seam_psnr_drop_db": big["seam_psnr_drop_db"],
            "seam_psnr_drop_class_matched_db": big["seam_psnr_drop_class_matched_db"],
            "seam_psnr_drop_matched_db": big["seam_psnr_drop_matched_db"],
            "seam_psnr_drop_matched_ci95_db": big["seam_psnr_drop_matched_ci95_db"],
            "seam_psnr_drop_scene_region_db": base["seam_psnr_drop_db"],
            # what chunk-wise GGDS adds to the matched drop, paired per view against the same
            # layout as one region (4-chunk corridor and grid; per GGDS seed and their mean)
            "seam_drop_vs_one_region_db": {k: v["difference_db"] for k, v in here.items()},
            "seam_drop_vs_one_region_ci95_db": {k: v["ci95_db"] for k, v in here.items()},
            "seam_drop_vs_one_region_seeds_db": {k: by_seed[k] for k in here},
            "seam_drop_vs_one_region_mean_db": {k: _mean(by_seed[k]) for k in here},
            "border_coverage": big["border_coverage"]}
        if full:
            result["streaming"] = stream_test(wdir, seed, log=log)
            result["corridor_10km_steps0"] = corridor_10km(wdir, seed, log=log)
        png = png_path or (str(json_path).rsplit(".", 1)[0] + ".png" if json_path else
                           "bench_scale.png")
        plot(rows, png)
        result["plot"] = str(png)
    log(json.dumps(result["summary"], indent=1))
    if json_path:
        atomic_write_text(json_path, json.dumps(result, indent=2))
        log(f"wrote {json_path}")
    return result
