"""Deferred rendering on a rig route: strength sweep, temporal warp error, Fréchet distance to
the prior's own images, and seconds per frame.

Renders the rig cameras along the route exactly as `render --rig` does (views.rig_stage +
views.frame.render_scene, actors included), defers every frame at each strength of the sweep
(views.deferred.Deferrer.images: one G-buffer per frame for all levels), then per strength:

  temporal warp error   eval.temporal.trajectory_warp_errors along each camera's frames (display
                        images as eval makes them: clamp tone map + sRGB), the pixel-weighted
                        mean over cameras; raw frames and the prior's own images (t = 1) too;
  fd_effnet_lite0       every frame of every camera against the prior's image (t = 1) of the
                        same view, raw vs deferred (same sample counts, so comparable);
  s/frame               `Deferrer.defer` at the default strength (G-buffer + prior), timed
                        separately on the front camera at --time-resolution.

usage: python tools/bench_deferred.py SCENE --route w_in,j_we,e_out [--seconds 2] [--fps 10]
           [--width 480] [--cameras Front,...] [--strengths 0.1,0.2,...] [--prior SPEC]
           [--time-resolution 480x270] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings

import numpy as np


def _display(rgb):
    from lsd3d_usd.views.images import srgb_encode, tonemap
    return srgb_encode(tonemap(rgb, 0.0, "clamp")).astype(np.float32)


def _warp_mean(per_camera: dict) -> dict:
    """Pixel-weighted mean warp error over cameras (each a trajectory_warp_errors result)."""
    num = sum(r["warp_err"] * r["_pixels"] for r in per_camera.values() if r["warp_err"] is not None)
    den = sum(r["_pixels"] for r in per_camera.values() if r["warp_err"] is not None)
    return {"warp_err": round(num / den, 5) if den else None,
            "naive_err": round(float(np.mean([r["naive_err"] for r in per_camera.values()])), 5),
            "per_camera": {k: r["warp_err"] for k, r in per_camera.items()}}


def _warp(cams, imgs, frames):
    from lsd3d_usd.eval.temporal import trajectory_warp_errors, warp_error
    r = trajectory_warp_errors(cams, imgs, frames)
    r["_pixels"] = sum(warp_error(cams[t - 1], imgs[t - 1], frames[t - 1], cams[t], imgs[t],
                                  frames[t])["pixels"] for t in range(1, len(cams)))
    return r


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--route", required=True)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--cameras", default="Front,FrontLeft,FrontRight,SideLeft,SideRight")
    ap.add_argument("--strengths", default="0.1,0.2,0.3,0.4,0.5,0.6")
    ap.add_argument("--prior", help="override the scene's recorded prior")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--time-resolution", default="480x270")
    ap.add_argument("--time-frames", type=int, default=10)
    ap.add_argument("--time-only", action="store_true", help="only the seconds per frame")
    ap.add_argument("--json")
    a = ap.parse_args(argv)

    from lsd3d_usd.render.camera import from_usd
    from lsd3d_usd.ggds.priors.scene import load_scene_prior
    from lsd3d_usd.views.deferred import Deferrer
    from lsd3d_usd.views.frame import render_scene
    from lsd3d_usd.views.rig_stage import build_rig_stage
    from lsd3d_usd.sensors.rigs import load_rig
    from lsd3d_usd.views.stage_data import SceneReader

    strengths = [float(s) for s in a.strengths.split(",")]
    names = a.cameras.split(",")
    specs = {c.name: c for c in load_rig("waymo5").cameras}
    out_dir = tempfile.mkdtemp(prefix="bench_deferred_")
    stage, paths, track, tcps, _ = build_rig_stage(a.scene, out_dir, "waymo5", a.route, None, a.fps,
                                                   a.seconds)
    reader = SceneReader(stage)
    t0 = time.perf_counter()
    sp = load_scene_prior(a.scene, a.prior)
    print(f"prior {sp.spec} ({sp.source}); setup {time.perf_counter() - t0:.1f} s")
    levels = sorted(set(strengths)) + [1.0]
    d = Deferrer(sp, levels[0], a.steps)
    raw, per_level, cams, frames = {}, {}, {}, {}
    t_render = 0.0
    result = {"scene": a.scene, "route": a.route, "seconds": a.seconds, "fps": a.fps,
              "width": a.width, "cameras": names, "prior": sp.spec, "prior_source": sp.source,
              "steps": a.steps, "setup_s": round(sp.setup_s, 2)}
    for name in ([] if a.time_only else names):
        path = next(p for p in paths if p.endswith("/" + name))
        raw[name], cams[name], frames[name] = [], [], []
        per_level[name] = {t: [] for t in levels}
        for k, t in enumerate(track.times):
            code = round(float(t) * tcps, 6)
            cam = from_usd(stage.GetPrimAtPath(path), code, a.width, specs[name].height_for(a.width))
            t1 = time.perf_counter()
            fr = render_scene(reader, cam, code)
            t_render += time.perf_counter() - t1
            raw[name].append(_display(fr.rgb))
            cams[name].append(cam)
            frames[name].append({"alpha": fr.alpha, "depth_expected": fr.depth_expected,
                                 "depth_median": np.where(np.isfinite(fr.depth), fr.depth, 0.0)})
            for lv, im in zip(levels, d.images(fr.rgb, cam, levels, fr.actor_mask, fr.depth)):
                per_level[name][lv].append(_display(im))
        print(f"{name}: {len(raw[name])} frames")
    if not a.time_only:
        _sweep(a, result, names, raw, per_level, cams, frames, levels, t_render)
    _timing(a, result, sp, reader, stage, paths, track, tcps, specs[names[0]])
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return result


def _sweep(a, result, names, raw, per_level, cams, frames, levels, t_render):
    import torch

    from lsd3d_usd.eval.metrics import FewSamplesWarning, frechet_distance_features
    from lsd3d_usd.ggds.losses.effnet import EffNetFeatureExtractor
    n_frames = sum(len(v) for v in raw.values())
    ext = EffNetFeatureExtractor()

    def embed(imgs):
        """Features of images of any sizes (the rig's side cameras are shorter): per size."""
        out = []
        for shape in dict.fromkeys(im.shape for im in imgs):
            x = torch.from_numpy(np.stack([im for im in imgs if im.shape == shape]))
            out.append(ext.embed(x.permute(0, 3, 1, 2).contiguous(), linear=False,
                                 size=224).double().numpy())
        return np.concatenate(out)

    def fd(f1, f2):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FewSamplesWarning)
            return round(frechet_distance_features(f1, f2).value, 3)

    f_target = embed([im for n in names for im in per_level[n][1.0]])
    f_raw = embed([im for n in names for im in raw[n]])
    result.update(frames=n_frames, render_s_per_frame=round(t_render / n_frames, 4))
    result["raw"] = {"temporal": _warp_mean({n: _warp(cams[n], raw[n], frames[n]) for n in names}),
                     "fd_vs_prior_image": fd(f_raw, f_target)}
    result["sweep"] = {}
    for lv in levels:
        tm = _warp_mean({n: _warp(cams[n], per_level[n][lv], frames[n]) for n in names})
        ratio = tm["warp_err"] / result["raw"]["temporal"]["warp_err"]
        row = {"temporal": tm, "warp_ratio": round(ratio, 3)}
        if lv != 1.0:
            row["fd_vs_prior_image"] = fd(embed([im for n in names for im in per_level[n][lv]]), f_target)
        result["sweep"][f"{lv:g}"] = row
        print(f"T {lv:g}: warp {tm['warp_err']} ({row['warp_ratio']}x raw), fd vs prior image "
              f"{row.get('fd_vs_prior_image', 0.0)}")
    r = result["raw"]
    print(f"raw: warp {r['temporal']['warp_err']} (naive {r['temporal']['naive_err']}), "
          f"fd vs prior image {r['fd_vs_prior_image']}")



def _timing(a, result, sp, reader, stage, paths, track, tcps, spec):
    """Seconds per deferred frame at the timing resolution (square pixels, the first camera's
    poses along the route): wall time, and CPU time of the process (an upper bound of the
    wall time on idle cores when the machine is shared)."""
    import os

    import torch

    from lsd3d_usd.render.camera import Camera, from_usd
    from lsd3d_usd.views.deferred import DEFAULT_STRENGTH, Deferrer
    from lsd3d_usd.views.frame import render_scene
    w, h = (int(v) for v in a.time_resolution.split("x"))
    path = next(p for p in paths if p.endswith("/" + spec.name))
    dt = Deferrer(sp, DEFAULT_STRENGTH, a.steps)
    wall, cpu = [], []
    for k, t in enumerate(track.times[:a.time_frames + 1]):
        code = round(float(t) * tcps, 6)
        cam = from_usd(stage.GetPrimAtPath(path), code, w, spec.height_for(w))
        f = cam.fx
        c2 = Camera(w, h, f, f, w / 2, h / 2, cam.pose, cam.near, cam.far)
        fr = render_scene(reader, c2, code)
        t1, c1 = time.perf_counter(), time.process_time()
        dt.defer(fr.rgb, c2, fr.actor_mask, fr.depth)
        if k:   # the first frame compiles / warms caches
            wall.append(time.perf_counter() - t1)
            cpu.append(time.process_time() - c1)
    result["s_per_frame"] = {"resolution": a.time_resolution, "strength": DEFAULT_STRENGTH,
                             "wall_median": round(float(np.median(wall)), 4),
                             "wall_min": round(float(np.min(wall)), 4),
                             "cpu_median": round(float(np.median(cpu)), 4), "frames": len(wall),
                             "torch_threads": torch.get_num_threads(),
                             "load_average": [round(v, 1) for v in os.getloadavg()]}
    print(f"s/frame at {a.time_resolution}: wall median {np.median(wall):.3f} (min "
          f"{np.min(wall):.3f}), process CPU median {np.median(cpu):.3f}; load {os.getloadavg()}")


if __name__ == "__main__":
    main()
