"""`lsd3d-usd bench ggds`: seconds per GGDS step by surfel count and resolution on one 100 m
chunk of a sample layout, and the quality of a short run on a whole sample layout (held-out
PSNR against the prior, depth / normal agreement with the proxy, off-surface fraction)."""
from __future__ import annotations

import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from pxr import Usd

from lsd3d_usd import scene as S
from lsd3d_usd.colour import srgb_encode
from lsd3d_usd.conditioning.light import scene_light
from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.conditioning.view_sampling import sample_views
from lsd3d_usd.config import generate_config
from lsd3d_usd.env import build_params
from lsd3d_usd.errors import InputError
from lsd3d_usd.eval.evaluate import eval_options, evaluate
from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
from lsd3d_usd.ggds.priors.scene import load_scene_prior
from lsd3d_usd.ggds.regions.plan import Region
from lsd3d_usd.ggds.regions.region_views import region_views
from lsd3d_usd.ggds.run.evaluate import field_renderer, heldout_psnr, render_and_target, scaled
from lsd3d_usd.ggds.run.inputs import GGDSInputs
from lsd3d_usd.ggds.run.optimisation import GGDSRun
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.layout.usdio import read_layout
from lsd3d_usd.pipeline import RunOptions, generate, read_layout_for
from lsd3d_usd.proxy import build_proxy
from lsd3d_usd.proxy.mesh import merge_parts
from lsd3d_usd.semantics import CLASS_ID, CLASSES
from lsd3d_usd.splats import chunkio
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.splats.init import mesh_to_surfels
from lsd3d_usd.views.stage_data import scene_surfels

SAMPLES = Path(__file__).resolve().parents[2] / "samples" / "layouts"


def _chunk_proxy(layout, chunk):
    parts = build_proxy(layout, chunks=[chunk])[chunk]
    vs, fs, ids, base = [], [], [], 0
    for name, cm in sorted(merge_parts(parts).items()):
        vs.append(cm.vertices)
        fs.append(cm.faces.astype(np.int64) + base)
        ids.append(np.full(cm.n_faces, CLASS_ID.get(cm.cls, -1), np.int32))
        base += len(cm.vertices)
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(ids)


def time_steps(layout_path, *, chunk=(0, 0), counts=(100_000, 500_000), resolutions=((480, 270),),
               steps=5, warmup=2, prompt="sunny afternoon in Madrid", log=print) -> list[dict]:

    layout = read_layout(layout_path)
    V, F, ids = _chunk_proxy(layout, tuple(chunk))
    s = layout.chunk_size
    region = (chunk[0] * s, chunk[1] * s, (chunk[0] + 1) * s, (chunk[1] + 1) * s)
    cond = Conditioning.build((V, F, ids), scene_light(build_params(prompt)[0]))
    out = []
    for n in counts:
        field, face = mesh_to_surfels(V, F, ids, count=n, seed=0, sh_degree=1,
                                      semantic_classes=CLASSES, return_face_index=True)
        for (w, h) in resolutions:
            views = sample_views(layout, 16, w, h, seed=0, region=region)
            cfg = GGDSConfig(steps=warmup + steps, resolution=(w, h), perceptual=False)
            run = GGDSRun(GGDSInputs(field=field, conditioning=cond, views=views,
                                     face_index=face), ProceduralPrior(), cfg)
            for i in range(len(views)):  # G-buffers are cached per view: not part of a step
                run.view_data(i)
            for _ in range(warmup):
                run.step()
            recs = [run.step() for _ in range(steps)]
            row = {"n": int(n), "width": w, "height": h, "chunk": list(chunk),
                   "proxy_triangles": int(len(F)),
                   "s_per_step": statistics.median(r["seconds"] for r in recs),
                   "visible_median": int(statistics.median(r["visible"] for r in recs))}
            for key in ("render_s", "prior_s", "loss_s", "backward_s", "update_s"):
                row[key] = round(statistics.median(r[key] for r in recs), 4)
            out.append(row)
            log(f"n={n:>9,} {w}x{h}: {row['s_per_step']:.3f} s/step (render {row['render_s']:.3f}, "
                f"prior {row['prior_s']:.3f}, loss {row['loss_s']:.3f}, backward {row['backward_s']:.3f}, "
                f"update {row['update_s']:.3f}; {row['visible_median']:,} visible)")
    return out


def quality(layout_path, *, steps=None, surfels=None, resolution=(480, 270), prompt="sunny afternoon in Madrid",
            out=None, fd=True, strip=None, log=print, fd_seeds=1) -> dict:
    """A `generate` with its defaults (or the given steps / surfels / resolution) on
    ``layout_path``, then: held-out PSNR against the prior at 1× and at 2× the training
    resolution, depth / normal / off-surface figures, and with ``fd`` the `eval` Fréchet
    distances (seen vs novel per distance bin, over the content-change baseline). ``strip``:
    a PNG path for the before/after image strip (initial surfels, after GGDS, prior target;
    at 1× and 2×)."""
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(out) if out else Path(tmp) / "scene"
        kw = {} if steps is None else {"steps": steps}  # None: generate's default
        cfg = generate_config(layout=Path(layout_path), surfels=surfels, **kw,
                              resolution=tuple(resolution), prompt=prompt, perceptual=False,
                              actors=False, env_resolution=(512, 256))
        t0 = time.perf_counter()
        summary = generate(cfg, RunOptions(out=target, progress=False, log=lambda *a: None,
                                           force=bool(out)))
        g = summary["ggds"]
        res = {k: g[k] for k in ("s_per_step", "psnr_novel", "depth_rel_err", "normal_err_deg",
                                 "off_surface_frac", "steps", "surfels")}
        res["generate_s"] = round(time.perf_counter() - t0, 1)
        t = time.perf_counter()
        res.update(_heldout(target, cfg, strip))
        res["heldout_s"] = round(time.perf_counter() - t, 1)
        if fd:
            t = time.perf_counter()
            res.update(fd_ratios(target, fd_seeds))
            res["eval_s"] = round(time.perf_counter() - t, 1)
        res["total_s"] = round(time.perf_counter() - t0, 1)
    log(f"quality after {res['steps']} steps ({res['surfels']:,} surfels): held-out PSNR "
        f"{res['psnr_heldout']:.2f} dB (2x: {res['psnr_heldout_2x']:.2f} dB), depth err "
        f"{100 * res['depth_rel_err']:.2f} %, normal err {res['normal_err_deg']:.2f} deg, "
        f"off-surface {100 * res['off_surface_frac']:.3f} %, {res['s_per_step']:.2f} s/step"
        + (f", fd novel/content max {res['fd_novel_over_content']:.2f}" if fd else "")
        + (f" (the prior's own images: {res['fd_prior_novel_over_content']:.2f})"
           if "fd_prior_novel_over_content" in res else "")
        + (f", Overview cameras PSNR {res['psnr_overview']:.2f} dB" if "psnr_overview" in res else "")
        + (f", elevated fd / the prior's max {res['elevated_fd_over_prior']:.2f}"
           if "elevated_fd_over_prior" in res else ""))
    if "off_path_psnr_db_per_bin" in res:
        ratio = res.get("off_path_fd_over_prior_per_bin", {})
        log("off-path bins: " + "; ".join(
            f"{k} {v:.2f} dB" + (f", fd / the prior's {ratio[k]:.2f}" if k in ratio else "")
            for k, v in res["off_path_psnr_db_per_bin"].items()))
    for fam, cls in (res.get("psnr_db_per_class") or {}).items():
        log(f"PSNR per class, {fam}: " + ", ".join(f"{c} {v:.2f}" for c, v in cls.items()
                                                   if v is not None))
    return res


def _heldout(scene_dir: Path, cfg, strip) -> dict:
    """Held-out PSNR of the scene as written (composed stage) at 1× and 2×, the views GGDS
    held out (a whole-scene region's: regions.region_views.region_views), and the image strip."""
    sc = S.Scene.open(scene_dir)
    layout, _ = read_layout_for(cfg)
    g = cfg.ggds
    _, views = region_views(layout, g, cfg.seed, Region((), ""))
    sp = load_scene_prior(scene_dir, purpose="bench ggds")
    cond = sp.conditioning
    after = scene_surfels(Usd.Stage.Open(str(sc.root_layer_path)))
    kw = dict(n_denoise=g.n_denoise)
    p1 = heldout_psnr(after, views, sp.prior, cond, **kw)
    p2 = heldout_psnr(after, scaled(views, 2.0), sp.prior, cond, **kw)
    out = {"psnr_heldout": float(np.mean(p1)), "psnr_heldout_2x": float(np.mean(p2)),
           "psnr_heldout_lane": _mean_kind(p1, views, "lane"),
           "psnr_heldout_offlane": _mean_kind(p1, views, "novel")}
    if strip:
        root = sc.layer_path("surfels")
        before = SurfelField.concat([chunkio.read_chunk(root, k)
                                     for k in sorted(chunkio.read_chunk_map(root))])
        rows = []
        for j, v in enumerate(views[:2]):
            for vv in (v, scaled([v], 2.0)[0]):
                x0, _, _ = render_and_target(field_renderer(before), vv, sp.prior, cond, j, **kw)
                x1, tgt, _ = render_and_target(field_renderer(after), vv, sp.prior, cond, j, **kw)
                rows.append((f"{vv.camera.width}x{vv.camera.height}", x0.rgb, x1.rgb, tgt))
        write_strip(Path(strip), rows)
        out["strip"] = str(strip)
    return out


def _mean_kind(psnrs, views, kind) -> float | None:
    vals = [p for p, v in zip(psnrs, views) if v.kind == kind]
    return float(np.mean(vals)) if vals else None


def write_strip(path: Path, rows) -> None:
    """rows of (label, initial, after GGDS, target) images (H,W,3) linear → one PNG."""

    fig = Figure(figsize=(13.5, 2.6 * len(rows)))
    ax = fig.subplots(len(rows), 3, squeeze=False)
    for i, (label, *imgs) in enumerate(rows):
        for j, (img, title) in enumerate(zip(imgs, ("initial surfels", "after GGDS",
                                                     "prior target"))):
            ax[i, j].imshow(srgb_encode(img.clamp(0, 1)).numpy(), interpolation="none")
            ax[i, j].set_xticks([]); ax[i, j].set_yticks([])
            if i == 0:
                ax[i, j].set_title(title)
        ax[i, 0].set_ylabel(label)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def fd_ratios(scene_dir: Path, seeds: int = 1) -> dict:
    """`eval` with its defaults at eval seeds 0 .. seeds-1 (other seen views and novel
    offsets each): Fréchet distance seen vs novel per bin over the content-change baseline
    (seen vs fresh on-lane views), averaged over the seeds (one seed's ratio moves by ~0.15);
    ≤ 1 at every bin means moving the camera off the training views changes the images less
    than a change of place does. The same ratio of the prior's own images of the same views
    (eval's prior baseline) says what a scene reproducing its prior exactly would score;
    fd_novel_over_prior is the largest over the bins of scene / prior (both seed means).
    fd_novel_per_bin, fd_content and eval_geometry_seen are eval seed 0's. The elevated
    family (eval's novel_elevated) likewise: elevated_* (elevated_psnr_db_per_height,
    elevated_fd_over_content_per_height, elevated_prior_fd_over_content_per_height and
    elevated_fd_over_prior, largest over the heights and the Overview group); the Overview
    cameras' PSNR (the same cameras at every seed) is seed 0's."""
    runs = []
    for seed in range(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            runs.append(evaluate(eval_options(scene=scene_dir, out_dir=Path(tmp), seed=seed,
                                             progress=False, log=lambda *a: None)))
    fds = [r.distances.to_json() for r in runs]
    bins = list(fds[0]["seen_vs_novel"]["per_bin"])
    scene = {b: [f["seen_vs_novel"]["per_bin"][b]["value"] / f["seen_vs_heldout_lane"]["value"]
                 for f in fds] for b in bins}
    mean = {b: float(np.mean(v)) for b, v in scene.items()}
    out = {"fd_novel_over_content": max(mean.values()),
           "fd_novel_over_content_per_bin": {b: round(v, 3) for b, v in mean.items()},
           "fd_novel_over_content_per_seed": {b: [round(x, 3) for x in v] for b, v in scene.items()},
           "fd_seeds": seeds,
           "fd_novel_per_bin": {b: round(fds[0]["seen_vs_novel"]["per_bin"][b]["value"], 2)
                                for b in bins},
           "fd_content": round(fds[0]["seen_vs_heldout_lane"]["value"], 2),
           "eval_geometry_seen": runs[0].geometry.seen["all"]}
    if all("prior_baseline" in f for f in fds):
        per_seed = {b: [f["prior_baseline"]["prior_novel_over_content"][b] for f in fds]
                    for b in bins}
        prior = {b: float(np.mean(v)) for b, v in per_seed.items()}
        out["fd_prior_novel_over_content_per_bin"] = {b: round(v, 3) for b, v in prior.items()}
        out["fd_prior_novel_over_content_per_seed"] = {b: [round(x, 3) for x in v]
                                                       for b, v in per_seed.items()}
        out["fd_prior_novel_over_content"] = max(prior.values())
        out["fd_novel_over_prior"] = max(mean[b] / max(prior[b], 1e-12) for b in bins)
    out.update(_elevated_keys([r.novel_elevated for r in runs]))
    out.update(_off_path_keys(runs))
    return out


def _off_path_keys(runs: list) -> dict:
    """bench ggds's keys of eval's novel_off_path and per-class PSNR over the eval seeds
    (fd_ratios): off_path_psnr_db_per_bin and off_path_fd_over_prior_per_bin (seed means),
    off_path_fd_over_prior (largest over the bins), off_path_psnr_db_per_class (seed mean),
    and seed 0's psnr_db_per_class of every family."""
    ops = [r.novel_off_path for r in runs]
    out = {}

    def mean(key):
        if not all(op.get(key) for op in ops):
            return None
        keys = list(ops[0][key])
        vals = {k: [op[key][k] for op in ops] for k in keys}
        return {k: round(float(np.mean(v)), 3) for k, v in vals.items() if None not in v}
    if ops[0]:
        out["novel_off_path"] = ops[0]
    for key, name in (("psnr_db_per_bin", "off_path_psnr_db_per_bin"),
                      ("fd_over_prior_per_bin", "off_path_fd_over_prior_per_bin"),
                      ("psnr_db_per_class", "off_path_psnr_db_per_class")):
        m = mean(key)
        if m:
            out[name] = m
    if "off_path_fd_over_prior_per_bin" in out:
        out["off_path_fd_over_prior"] = max(out["off_path_fd_over_prior_per_bin"].values())
    r = runs[0]
    fams = {"seen": r.seen_views, **{f"novel_{b}": v for b, v in r.novel_views.items()},
            **{("heldout_lane" if g == "heldout_lane" else f"elevated_{g}"): v
               for g, v in r.novel_elevated.items()},
            "off_path": r.novel_off_path, "trajectory": r.temporal}
    per_class = {k: v["psnr_db_per_class"] for k, v in fams.items() if v.get("psnr_db_per_class")}
    if per_class:
        out["psnr_db_per_class"] = per_class
    return out


def _elevated_keys(elev: list) -> dict:
    """bench ggds's keys of eval's novel_elevated over the eval seeds (fd_ratios)."""
    groups = [g for g in elev[0] if g != "heldout_lane"]
    if not groups:
        return {}

    def mean(key, sub=None):
        vals = {g: [e[g][key] if sub is None else e[g].get(key, {}).get(sub) for e in elev]
                for g in groups}
        return {g: float(np.mean(v)) for g, v in vals.items() if v and None not in v}
    out = {"novel_elevated": elev[0]}
    psnr = mean("psnr_db", "mean")
    if psnr:
        out["elevated_psnr_db_per_height"] = {g: round(v, 3) for g, v in psnr.items()}
    lane = elev[0].get("heldout_lane", {}).get("psnr_db", {}).get("mean")
    if lane is not None:
        out["elevated_psnr_heldout_lane"] = lane
    ov = elev[0].get("overview", {}).get("psnr_db_per_camera")
    if ov:
        out["psnr_overview_per_camera"] = ov
        out["psnr_overview"] = round(float(np.mean(list(ov.values()))), 3)
    if all("fd_over_content" in e[g] for e in elev for g in groups):
        scene = mean("fd_over_content")
        out["elevated_fd_over_content_per_height"] = {g: round(v, 3) for g, v in scene.items()}
        if all("prior_fd_over_content" in e[g] for e in elev for g in groups):
            prior = mean("prior_fd_over_content")
            out["elevated_prior_fd_over_content_per_height"] = {g: round(v, 3)
                                                                for g, v in prior.items()}
            ratio = {g: scene[g] / max(prior[g], 1e-12) for g in groups}
            out["elevated_fd_over_prior_per_height"] = {g: round(v, 3) for g, v in ratio.items()}
            out["elevated_fd_over_prior"] = max(ratio.values())
    return out


def main(json_path=None, *, quick=False, layout=None, steps=None, fd=True, strip=None,
         log=print, fd_seeds=None) -> dict:
    """Timing on a 100 m chunk of `layout` (default the generated 200 m sample); quality with
    `generate`'s defaults on `layout`, or by default on the README sample (hand_crossing, whose
    figures are the top-level keys) and the generated 200 m sample."""
    fd_seeds = (1 if quick else 4) if fd_seeds is None else fd_seeds
    if fd and fd_seeds < 1:
        raise InputError(f"--fd-seeds {fd_seeds}: must be >= 1 (or --no-fd)")
    timing_layout = Path(layout) if layout else SAMPLES / "generated_seed7_200x200.usda"
    counts = (50_000,) if quick else (100_000, 500_000)
    res = ((320, 180),) if quick else ((480, 270), (960, 540))
    timing = time_steps(timing_layout, counts=counts, resolutions=res, steps=3 if quick else 5, log=log)
    if strip is None and json_path:
        strip = str(Path(json_path).with_suffix("")) + "_before_after.png"
    if quick:
        runs = [quality(SAMPLES / "hand_crossing.usda", steps=steps or 10, surfels=20_000,
                        resolution=(320, 180), fd=fd, strip=strip, log=log, fd_seeds=fd_seeds)]
    else:
        quality_layouts = [Path(layout)] if layout else [SAMPLES / "hand_crossing.usda",
                                                         SAMPLES / "generated_seed7_200x200.usda"]
        runs = []
        for i, lay in enumerate(quality_layouts):
            log(f"quality run on {lay.name} ...")
            runs.append(dict(quality(lay, steps=steps, fd=fd, strip=strip if i == 0 else None,
                                     log=log, fd_seeds=fd_seeds), layout=lay.name))
    q = runs[0]
    head = next((r for r in timing if r["n"] == 500_000 and (r["width"], r["height"]) == (480, 270)),
                timing[-1])
    result = {"s_per_step": head["s_per_step"], "psnr_novel": q["psnr_novel"],
              "psnr_heldout": q["psnr_heldout"], "psnr_heldout_2x": q["psnr_heldout_2x"],
              "fd_novel_over_content": q.get("fd_novel_over_content"),
              "fd_prior_novel_over_content": q.get("fd_prior_novel_over_content"),
              "fd_novel_over_prior": q.get("fd_novel_over_prior"),
              "psnr_overview": q.get("psnr_overview"),
              "elevated_psnr_db_per_height": q.get("elevated_psnr_db_per_height"),
              "elevated_fd_over_prior": q.get("elevated_fd_over_prior"),
              "off_path_psnr_db_per_bin": q.get("off_path_psnr_db_per_bin"),
              "off_path_fd_over_prior": q.get("off_path_fd_over_prior"),
              "psnr_db_per_class": q.get("psnr_db_per_class"),
              "depth_rel_err": q["depth_rel_err"], "normal_err_deg": q["normal_err_deg"],
              "off_surface_frac": q["off_surface_frac"], "timing": timing, "quality": q,
              "quality_runs": runs}
    if json_path:
        Path(json_path).write_text(json.dumps(result, indent=2))
        log(f"wrote {json_path}")
    return result
