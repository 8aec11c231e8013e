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

SAMPLES = Path(__file__).resolve().parents[2] / "samples" / "layouts"


def _chunk_proxy(layout, chunk):
    from lsd3d_usd.proxy import build_proxy
    from lsd3d_usd.proxy.mesh import merge_parts
    from lsd3d_usd.semantics import CLASS_ID
    parts = build_proxy(layout, chunks=[chunk])[chunk]
    vs, fs, ids, base = [], [], [], 0
    for name, cm in sorted(merge_parts(parts).items()):
        vs.append(cm.vertices)
        fs.append(cm.faces.astype(np.int64) + base)
        ids.append(np.full(cm.n_faces, CLASS_ID.get(cm.cls, -1), np.int32))
        base += len(cm.vertices)
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(ids)


def time_steps(layout_path, chunk=(0, 0), counts=(100_000, 500_000), resolutions=((480, 270),),
               steps=5, warmup=2, prompt="sunny afternoon in Madrid", log=print) -> list[dict]:
    from lsd3d_usd.env import build_params
    from lsd3d_usd.ggds.cameras import sample_views
    from lsd3d_usd.ggds.conditioning import shadow_map
    from lsd3d_usd.ggds.envbridge import scene_light
    from lsd3d_usd.ggds.procedural_prior import ProceduralPrior
    from lsd3d_usd.ggds.config import GGDSConfig
    from lsd3d_usd.ggds.run import GGDSRun
    from lsd3d_usd.layout.usdio import read_layout
    from lsd3d_usd.semantics import CLASSES
    from lsd3d_usd.splats.init import mesh_to_surfels

    layout = read_layout(layout_path)
    V, F, ids = _chunk_proxy(layout, tuple(chunk))
    s = layout.chunk_size
    region = (chunk[0] * s, chunk[1] * s, (chunk[0] + 1) * s, (chunk[1] + 1) * s)
    light = scene_light(build_params(prompt)[0])
    shadow = shadow_map(V, F, light.sun_direction)
    out = []
    for n in counts:
        field, face = mesh_to_surfels(V, F, ids, count=n, seed=0, sh_degree=1,
                                      semantic_classes=CLASSES, return_face_index=True)
        for (w, h) in resolutions:
            views = sample_views(layout, 16, w, h, seed=0, region=region)
            cfg = GGDSConfig(steps=warmup + steps, resolution=(w, h), perceptual=False)
            run = GGDSRun(field, (V, F, ids), views, ProceduralPrior(), light.prior_env, cfg,
                          shadow=shadow, face_index=face)
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


def quality(layout_path, steps=None, surfels=None, resolution=(480, 270), prompt="sunny afternoon in Madrid",
            out=None, log=print) -> dict:
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.pipeline import RunOptions, generate
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
        res["total_s"] = round(time.perf_counter() - t0, 1)
    log(f"quality after {res['steps']} steps ({res['surfels']:,} surfels): held-out PSNR "
        f"{res['psnr_novel']:.2f} dB, depth err {100 * res['depth_rel_err']:.2f} %, normal err "
        f"{res['normal_err_deg']:.2f} deg, off-surface {100 * res['off_surface_frac']:.3f} %, "
        f"{res['s_per_step']:.2f} s/step")
    return res


def main(json_path=None, quick=False, layout=None, steps=None, log=print) -> dict:
    """Timing on a 100 m chunk of `layout` (default the generated 200 m sample); quality with
    `generate`'s defaults on `layout`, or by default on the README sample (hand_crossing, whose
    figures are the top-level keys) and the generated 200 m sample."""
    timing_layout = Path(layout) if layout else SAMPLES / "generated_seed7_200x200.usda"
    counts = (50_000,) if quick else (100_000, 500_000)
    res = ((320, 180),) if quick else ((480, 270), (960, 540))
    timing = time_steps(timing_layout, counts=counts, resolutions=res, steps=3 if quick else 5, log=log)
    if quick:
        runs = [quality(SAMPLES / "hand_crossing.usda", steps=steps or 10, surfels=20_000,
                        resolution=(320, 180), log=log)]
    else:
        quality_layouts = [Path(layout)] if layout else [SAMPLES / "hand_crossing.usda",
                                                         SAMPLES / "generated_seed7_200x200.usda"]
        runs = []
        for lay in quality_layouts:
            log(f"quality run on {lay.name} ...")
            runs.append(dict(quality(lay, steps=steps, log=log), layout=lay.name))
    q = runs[0]
    head = next((r for r in timing if r["n"] == 500_000 and (r["width"], r["height"]) == (480, 270)),
                timing[-1])
    result = {"s_per_step": head["s_per_step"], "psnr_novel": q["psnr_novel"],
              "depth_rel_err": q["depth_rel_err"], "normal_err_deg": q["normal_err_deg"],
              "off_surface_frac": q["off_surface_frac"], "timing": timing, "quality": q,
              "quality_runs": runs}
    if json_path:
        Path(json_path).write_text(json.dumps(result, indent=2))
        log(f"wrote {json_path}")
    return result
