"""`evaluate`: render seen / novel / trajectory views of a scene's composed stage and measure
image-feature Fréchet distances, geometry agreement with the proxy, multi-view and temporal
consistency. Writes SCENE/eval/ (report.html, PNGs, eval.json); returns the JSON dict.

Rendering: every unmuted layer of the scene composed (initial surfels + GGDS overs), the
scene's visible ParticleField prims (views.stage_data.scene_surfels: actors are left out, eval
measures the generated scene), the DomeLight env map behind (with its exposure, as `render`
does), then display encoding (tone map, default "clamp" = what GGDS's prior sees, and sRGB).
"""
from __future__ import annotations

import itertools
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from lsd3d_usd.assetroots import check_scene
from lsd3d_usd import configtree as ct
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.conditioning.elevated_sampling import ELEVATED
from lsd3d_usd.eval import elevated_views as E
from lsd3d_usd.eval import geometry as G
from lsd3d_usd.eval import metrics as M
from lsd3d_usd.eval import models, report
from lsd3d_usd.eval import temporal as T
from lsd3d_usd.eval import lane_views as V
from lsd3d_usd.eval.options import EvalConfig
from lsd3d_usd.eval.prior_baseline import baseline_fd, open_baseline
from lsd3d_usd.eval.render import render_view
from lsd3d_usd.eval.seams import paired_matched_drop
from lsd3d_usd.eval.seams_eval import (pooled_psnr, reference_frames, seam_stats,
                                       seams_reference, view_errors)
from lsd3d_usd.ggds.losses.effnet import EffNetFeatureExtractor
from lsd3d_usd.ggds.priors.scene import load_scene_prior
from lsd3d_usd.layout.usdio import read_layout
from lsd3d_usd.proxy.usdio import proxy_arrays
from lsd3d_usd.render.gbuffer import render_gbuffer
from lsd3d_usd.views.deferred import Deferrer
from lsd3d_usd.views.images import read_image, srgb_encode
from lsd3d_usd.views.images import tonemap as tm
from lsd3d_usd.views.stage_data import read_dome, scene_surfels

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
FEATURES = "effnet_lite0"


@dataclass
class EvalOptions:
    """How to run `eval` on ``scene`` (what to measure is ``cfg``, eval.options.EvalConfig)."""
    scene: Path
    cfg: EvalConfig = field(default_factory=EvalConfig)
    out_dir: Path | None = None          # default SCENE/eval
    progress: bool = True
    log: object = print


def eval_options(scene, **settings) -> EvalOptions:
    """EvalOptions with ``settings`` split between run control (out_dir, progress, log) and
    the EvalConfig keys (n_seen=3, bins=(1, 4), deferred={"enabled": True}, ...)."""
    run = {k: settings.pop(k) for k in ("out_dir", "progress", "log") if k in settings}
    for key in ("bins", "heights", "pitch"):
        if isinstance(settings.get(key), (tuple, list)):
            settings[key] = ",".join(f"{b:g}" for b in settings[key])
    cfg = ct.apply(EvalConfig(), ct.flatten(settings, EvalConfig, ""), "",
                   ct.flag_names(EvalConfig))
    return EvalOptions(scene=Path(scene), cfg=cfg, **run)


# ------------------------------------------------------------------ input checks
def _check(c: EvalConfig) -> None:
    """Cross-key checks (each key's own are the tree's)."""
    if c.prior_baseline and c.n_heldout == 0:
        raise InputError("--prior-baseline needs held-out lane views (--heldout > 0)")


def reference_images(ref, limit: int) -> list[Path]:
    """Image files of a reference folder (sorted, at most `limit`); one clear error if unusable."""
    p = Path(ref)
    if not p.is_dir():
        raise InputError(f"--reference {ref}: no such directory")
    files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_EXTS)
    if len(files) < 2:
        raise InputError(f"--reference {ref}: needs at least 2 images ({', '.join(IMAGE_EXTS)}), "
                         f"found {len(files)}")
    return files[:limit]


def load_reference(files: list[Path], size: int = 224) -> list[np.ndarray]:
    """sRGB images in [0, 1] (grey expanded, alpha dropped), each resized at once to the
    feature extractor's size×size exactly as it would resize them (bilinear, antialiased),
    so hundreds of large photos never sit in memory at full size."""

    out = []
    for f in files:
        try:
            img = read_image(f)
        except InputError as e:
            raise InputError(f"--reference: {e}") from None
        if img.ndim == 2:
            img = img[..., None]
        img = np.repeat(img[..., :1], 3, axis=2) if img.shape[2] < 3 else img[..., :3]
        if min(img.shape[:2]) < 8:
            raise InputError(f"--reference: {f}: image too small ({img.shape[1]}x{img.shape[0]})")
        x = torch.from_numpy(np.ascontiguousarray(np.clip(img, 0.0, 1.0), np.float32)).permute(2, 0, 1)[None]
        x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
        out.append(x[0].permute(1, 2, 0).numpy())
    return out


# ------------------------------------------------------------------ rendering
def display(rgb: np.ndarray, tonemap: str, exposure: float) -> np.ndarray:
    return srgb_encode(tm(rgb, exposure, tonemap)).astype(np.float32)


def _bar(total, desc, o: EvalOptions):
    return tqdm(total=total, desc=desc, unit="view", disable=not o.progress)


# ------------------------------------------------------------------ the driver
def evaluate(o: EvalOptions) -> dict:
    t_start = time.perf_counter()
    _check(o.cfg)
    sc = S.Scene.open(o.scene)
    weights = models.check_weights_dir(o.cfg.weights)
    # Reference images are read before any rendering: a bad folder fails at once.
    ref_imgs = (load_reference(reference_images(o.cfg.reference, o.cfg.max_reference))
                if o.cfg.reference is not None else None)
    layout_path = sc.layer_path("layout")
    if not layout_path.is_file():
        raise InputError(f"{layout_path}: the scene has no layout layer (needed for cameras)")
    if not sc.layer_path("proxy").is_file():
        raise InputError(f"{sc.layer_path('proxy')}: the scene has no proxy layer (needed for geometry)")
    out_dir = Path(o.out_dir) if o.out_dir else sc.root / "eval"
    deferrer = _deferrer(o) if o.cfg.deferred.enabled else None
    n_held = o.cfg.n_seen if o.cfg.n_heldout is None else o.cfg.n_heldout
    base, base_why = open_baseline(o.scene, o.cfg.prior_baseline, n_held,
                                   lambda rgb: display(rgb, o.cfg.tonemap, o.cfg.exposure), o.cfg.run)

    timings = {}
    t = time.perf_counter()
    stage = sc.open_stage()
    check_scene(stage, sc.root)
    surfels = scene_surfels(stage)
    if surfels is None:
        raise InputError(f"{sc.root}: no surfels to render (no visible ParticleField prim)")
    env = read_dome(stage)
    layout = read_layout(layout_path)
    PV, PF, PC = proxy_arrays(sc.layer_path("proxy"))
    w, h = o.cfg.resolution
    seen = V.seen_views(sc, layout, o.cfg.run, w, h)
    # the seen family (and the novel and held-out views placed from it) are the views GGDS
    # trained on at eye height; elevated training views (ggds.elevated_train) still count as
    # training cameras for every family's nearest-camera distance. Views the colour start
    # alone fitted to are not recorded in the run, so they count for none.
    ground = [v for v in seen.views if v.kind != ELEVATED]
    pick = V.pick(len(ground), o.cfg.n_seen, o.cfg.seed)
    seen_sel = [ground[i] for i in pick]
    novel = V.novel_views(seen_sel, o.cfg.bin_values(), o.cfg.per_bin, o.cfg.seed + 1, layout,
                          train_centres=[v.camera.center for v in seen.views])
    heldout = V.heldout_lane_views(layout, n_held, w, h, o.cfg.seed, seen_sel)
    centres = [v.camera.center for v in seen.views]
    elev = E.elevated_views(layout, o.cfg.height_values(), o.cfg.per_height, o.cfg.pitch_range(),
                            o.cfg.seed + 2, w, h, V.fov_of(seen_sel), train_centres=centres)
    if o.cfg.overview:
        elev += E.overview_views(stage, layout, w, h, train_centres=centres)
    traj, traj_info = V.lane_trajectory(layout, o.cfg.frames, o.cfg.step_m, w, h)
    seams_ref = None
    if o.cfg.seams_reference is not None:   # checked before any rendering: a bad one fails at once
        seams_ref = seams_reference(o.cfg.seams_reference, sc, seen.run, (PV, PF, PC))
    timings["load_s"] = time.perf_counter() - t
    o.log(f"eval: {surfels.n:,} surfels; seen: {seen.source}; {len(seen_sel)} seen + "
          f"{len(novel)} novel views ({len(o.cfg.bin_values())} bins) + {len(elev)} elevated views + "
          f"{len(traj)} trajectory frames at {w}x{h}")

    # --- seen + novel renders, geometry against the proxy
    t = time.perf_counter()
    agree = {"seen": G.ClassAgreement(o.cfg.seed), "novel": G.ClassAgreement(o.cfg.seed + 1)}
    seen_img, seen_frames, seen_gb, novel_img = [], [], [], []
    mv_err = {b: [] for b in o.cfg.bin_values()}
    mv_shared = {b: [] for b in o.cfg.bin_values()}
    bar = _bar(len(seen_sel) + len(novel) + len(heldout) + len(elev) + len(traj), "eval render", o)
    dfr = DeferredImages()
    for v in seen_sel:
        fr = render_view(surfels, env, v.camera)
        gb = render_gbuffer(PV, PF, v.camera, PC)
        agree["seen"].add(fr, gb, v.camera)
        seen_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        seen_frames.append(fr)
        seen_gb.append(gb)
        if deferrer is not None:
            dfr.add("seen", deferrer, fr["rgb"], v.camera, o)
        if base is not None:
            base.add("seen", fr["rgb"], v.camera)
        bar.update(1)
    for nv in novel:
        fr = render_view(surfels, env, nv.view.camera)
        gb = render_gbuffer(PV, PF, nv.view.camera, PC)
        agree["novel"].add(fr, gb, nv.view.camera)
        novel_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        if deferrer is not None:
            dfr.add("novel", deferrer, fr["rgb"], nv.view.camera, o)
        if base is not None:
            base.add("novel", fr["rgb"], nv.view.camera)
        r = G.reprojection_depth_error(seen_sel[nv.source].camera, seen_frames[nv.source],
                                       seen_gb[nv.source], nv.view.camera, fr, gb)
        if r is not None:
            mv_err[nv.bin_m].append(r["errors"])
            mv_shared[nv.bin_m].append(r["shared_frac"])
        bar.update(1)
    heldout_img, heldout_frames = [], []
    for cam in heldout:
        fr = render_view(surfels, env, cam)
        heldout_frames.append(fr)
        heldout_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        if base is not None:
            base.add("heldout", fr["rgb"], cam)
        bar.update(1)
    elev_img, elev_frames = [], []
    for ev in elev:
        fr = render_view(surfels, env, ev.camera)
        elev_frames.append({"rgb": fr["rgb"]})    # all the PSNR needs
        elev_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        if base is not None:
            base.add("elevated", fr["rgb"], ev.camera)
        bar.update(1)
    timings["render_seen_novel_s"] = time.perf_counter() - t

    # --- trajectory
    t = time.perf_counter()
    traj_frames, traj_img = [], []
    for cam in traj:
        fr = render_view(surfels, env, cam)
        traj_frames.append({k: fr[k] for k in ("alpha", "depth_median", "depth_expected")})
        traj_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        if deferrer is not None:
            dfr.add("traj", deferrer, fr["rgb"], cam, o, target=False)
        bar.update(1)
    bar.close()
    temporal = T.trajectory_warp_errors(traj, traj_img, traj_frames)
    temporal.update(traj_info)
    timings["render_trajectory_s"] = time.perf_counter() - t
    if deferrer is not None:
        timings["deferred_s"] = dfr.seconds
    if base is not None:
        timings["prior_baseline_s"] = base.seconds

    # --- features and Fréchet distances
    t = time.perf_counter()

    ext = EffNetFeatureExtractor()

    def embed(imgs):
        x = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()
        return ext.embed(x, linear=False, size=224).double().numpy()

    f_seen = embed(seen_img)
    f_novel = embed(novel_img)
    bins_arr = np.array([nv.bin_m for nv in novel])
    smallest = []

    def fd(a, b):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", M.FewSamplesWarning)
            r = M.frechet_distance_features(a, b)
        if r.warning:
            smallest.append(min(r.n1, r.n2))
        return r

    fd_out = {"features": "EfficientNet-Lite0 pooled 1280-d (bundled ImageNet weights), 224x224 "
                          "bilinear resize of the sRGB display image",
              "seen_vs_novel": {"overall": fd(f_seen, f_novel).to_json(),
                                "per_bin": {f"{b:g}": fd(f_seen, f_novel[bins_arr == b]).to_json()
                                            for b in o.cfg.bin_values()}}}
    if heldout_img:
        fd_out["seen_vs_heldout_lane"] = fd(f_seen, embed(heldout_img)).to_json()
    groups = list(dict.fromkeys(ev.group for ev in elev))   # heights, then overview
    groups_arr = np.array([ev.group for ev in elev])
    f_elev = embed(elev_img) if elev_img else None
    if base is not None:
        fd_out["prior_baseline"] = baseline_fd(fd, embed, base.images, o.cfg.bin_values(), bins_arr, fd_out,
                                               base.sp, elevated=(groups, groups_arr, f_elev)
                                               if elev else None)
    n_ref = 0
    if ref_imgs is not None:
        f_ref = embed(ref_imgs)
        n_ref = len(f_ref)
        fd_out["vs_reference"] = {
            "seen": fd(f_seen, f_ref).to_json(), "novel": fd(f_novel, f_ref).to_json(),
            "novel_per_bin": {f"{b:g}": fd(f_novel[bins_arr == b], f_ref).to_json() for b in o.cfg.bin_values()}}
        if elev:
            fd_out["vs_reference"]["elevated_per_height"] = {
                g: fd(f_elev[groups_arr == g], f_ref).to_json() for g in groups}
    deferred = None
    if deferrer is not None:
        f_dseen, f_dnovel = embed(dfr.images["seen"]), embed(dfr.images["novel"])
        f_raw = np.concatenate([f_seen, f_novel])
        f_target = embed(dfr.targets["seen"] + dfr.targets["novel"])
        d_temporal = T.trajectory_warp_errors(traj, dfr.images["traj"], traj_frames)
        d_temporal.update(traj_info)
        deferred = {
            **deferrer.describe(),
            "fd_effnet_lite0": {
                "seen_vs_novel": {"overall": fd(f_dseen, f_dnovel).to_json(),
                                  "per_bin": {f"{b:g}": fd(f_dseen, f_dnovel[bins_arr == b]).to_json()
                                              for b in o.cfg.bin_values()}},
                "vs_prior_target": {
                    "views": "seen + novel views against the prior's own image of the same views "
                             "(t = 1)",
                    "raw": fd(f_raw, f_target).to_json(),
                    "deferred": fd(np.concatenate([f_dseen, f_dnovel]), f_target).to_json()}},
            "temporal_warp_err": d_temporal}
    fd_elev = {g: fd(f_seen, f_elev[groups_arr == g]) for g in groups}
    timings["features_fd_s"] = time.perf_counter() - t

    # --- elevated views (and the held-out lane views, for scale) against the run's targets
    t = time.perf_counter()
    errs, psnr_why = (None, None)
    if elev:
        errs, psnr_why = view_errors(sc, seen.run, (PV, PF, PC), list(heldout) + [ev.camera for ev in elev],
                                     heldout_frames + elev_frames)
    novel_elevated = _novel_elevated(elev, groups, errs, len(heldout), fd_elev, fd_out)
    timings["elevated_psnr_s"] = time.perf_counter() - t

    # --- seams between chunks
    t = time.perf_counter()
    frame_sets = [seen_frames + heldout_frames]
    ref_why = None
    if seams_ref is not None and len(heldout) < 2:
        ref_why = "needs at least 2 held-out lane views (--heldout)"
    elif seams_ref is not None:
        # only the held-out lane views count: the seen views are the evaluated run's training
        # cameras, which the reference never trained on
        skip = [None] * len(seen_sel)
        frame_sets += [skip + heldout_frames,
                       itertools.chain(skip, reference_frames(seams_ref[0], heldout))]
    stats, why = seam_stats(sc, seen.run, layout, (PV, PF, PC),
                            [v.camera for v in seen_sel] + list(heldout), *frame_sets)
    seams = stats[0].result() if stats is not None else None
    if seams_ref is not None and not ref_why:
        if seams is None:
            ref_why = f"no seam measure ({why})"
        else:
            seams["vs_reference"] = {"scene": str(o.cfg.seams_reference), "run": seams_ref[1],
                                     **paired_matched_drop(stats[1], stats[2], o.cfg.seed)}
    timings["seams_s"] = time.perf_counter() - t

    # --- multi-view summary
    multiview = {"pairs": "each novel view vs the seen view it was displaced from (seen depth "
                          "reprojected into the novel view; proxy decides mutual visibility)",
                 "per_bin": {}}
    all_err = []
    for b in o.cfg.bin_values():
        e = np.concatenate(mv_err[b]) if mv_err[b] else np.zeros(0)
        all_err.append(e)
        multiview["per_bin"][f"{b:g}"] = {
            "median": round(float(np.median(e)), 5) if e.size else None,
            "frac_over_5pct": round(float((e > 0.05).mean()), 4) if e.size else None,
            "shared_frac": round(float(np.mean(mv_shared[b])), 4) if mv_shared[b] else 0.0,
            "pairs": len(mv_err[b])}
    e = np.concatenate(all_err)
    multiview["median"] = round(float(np.median(e)), 5) if e.size else None
    multiview["frac_over_5pct"] = round(float((e > 0.05).mean()), 4) if e.size else None

    fd_warnings = []
    if smallest:
        fd_warnings.append(
            f"Fréchet distances from fewer samples than feature dimensions ({f_seen.shape[1]}-d; "
            f"smallest set {min(smallest)}): covariances are rank-deficient and values are biased "
            "upwards; compare only values computed with equal sample counts")
    unavailable = models.status(weights)
    if ref_imgs is None:
        unavailable.insert(0, {"metric": "fd_effnet_lite0.vs_reference",
                               "reason": "no --reference DIR of images given"})
    if why:
        unavailable.append({"metric": "seams", "reason": why})
    if ref_why:
        unavailable.append({"metric": "seams.vs_reference", "reason": ref_why})
    if psnr_why:
        unavailable.append({"metric": "novel_elevated.psnr_db", "reason": psnr_why})
    if base_why:
        unavailable.append({"metric": "fd_effnet_lite0.prior_baseline", "reason": base_why})
    timings["total_s"] = time.perf_counter() - t_start
    result = {
        "scene": str(sc.root),
        "run": seen.run,
        "seen_views_source": seen.source,
        "composed_layers": [li.name for li in sc.layers() if not li.muted and li.exists],
        "surfels": int(surfels.n),
        "resolution": [w, h],
        "tonemap": o.cfg.tonemap,
        "seed": o.cfg.seed,
        "bins_m": [float(b) for b in o.cfg.bin_values()],
        "heights_m": [float(x) for x in o.cfg.height_values()],
        "pitch_deg": [float(x) for x in o.cfg.pitch_range()],
        "counts": {"train_views": len(seen.views), "seen": len(seen_sel), "novel": len(novel),
                   "novel_per_bin": o.cfg.per_bin, "heldout_lane": len(heldout),
                   "trajectory_frames": len(traj), "reference": n_ref, "elevated": len(elev),
                   "elevated_per_height": o.cfg.per_height,
                   "overview": sum(ev.group == E.OVERVIEW for ev in elev)},
        "novel_views": {f"{b:g}": _bin_stats([nv for nv in novel if nv.bin_m == b]) for b in o.cfg.bin_values()},
        "novel_elevated": novel_elevated,
        "fd_effnet_lite0": fd_out,
        "geometry": {"seen": agree["seen"].result(), "novel": agree["novel"].result()},
        "multiview_depth_err": multiview,
        "seams": seams,
        "temporal_warp_err": temporal,
        **({"deferred": deferred} if deferred is not None else {}),
        "unavailable": unavailable,
        "warnings": fd_warnings,
        "timings": {k: round(v, 2) for k, v in timings.items()},
    }
    t = time.perf_counter()
    files = report.write_report(out_dir, result, sc, seen_img, novel_img, novel, traj_img,
                                seen_frames=seen_frames, seen_gb=seen_gb,
                                deferred=dfr if deferrer is not None else None,
                                elevated=(elev, elev_img))
    result["timings"]["report_s"] = round(time.perf_counter() - t, 2)
    result["files"] = {k: str(v) for k, v in files.items()}
    report.write_json(out_dir / "eval.json", result)
    return result


def _deferrer(o: EvalOptions):
    d = o.cfg.deferred
    sp = load_scene_prior(o.scene, d.prior, d.controlnet, device=d.device)
    d = Deferrer(sp, d.strength, d.steps, d.seed)
    o.log(f"eval: deferred with prior {sp.spec} ({sp.source}), T {d.strength}, N {d.steps}")
    if sp.note():
        o.log(f"eval: note: {sp.note()}")
    return d


class DeferredImages:
    """Display images of the deferred views (and the prior's own image at t = 1 of the seen
    and novel views), by view set."""

    def __init__(self):
        self.images = {"seen": [], "novel": [], "traj": []}
        self.targets = {"seen": [], "novel": []}
        self.seconds = 0.0

    def add(self, kind: str, deferrer, rgb, camera, o: EvalOptions, target: bool = True):
        t = time.perf_counter()
        levels = (deferrer.strength, 1.0) if target else (deferrer.strength,)
        outs = deferrer.images(rgb, camera, levels)
        self.images[kind].append(display(outs[0], o.cfg.tonemap, o.cfg.exposure))
        if target:
            self.targets[kind].append(display(outs[1], o.cfg.tonemap, o.cfg.exposure))
        self.seconds += time.perf_counter() - t


def _bin_stats(nvs: list) -> dict:
    if not nvs:
        return {}
    near = np.array([nv.nearest_train_m for nv in nvs])
    yaw = np.abs([nv.yaw_deg for nv in nvs])
    return {"count": len(nvs), "nearest_train_m_median": round(float(np.median(near)), 3),
            "abs_yaw_deg_median": round(float(np.median(yaw)), 2)}


def _psnr_stats(vals: list) -> dict:
    if not vals:
        return {}
    a = np.asarray(vals, np.float64)
    return {"mean": round(float(a.mean()), 3), "median": round(float(np.median(a)), 3),
            "min": round(float(a.min()), 3), "max": round(float(a.max()), 3), "views": len(a)}


def _novel_elevated(elev: list, groups: list, errs, n_held: int, fd_elev: dict, fd_out: dict) -> dict:
    """The ``novel_elevated`` entry: per height (and "overview") the pose medians, PSNR
    against the run's held-out targets (errs: (sse, values) of the held-out lane views, then
    the elevated ones; None when there are no targets), FD seen vs elevated and its ratios;
    "heldout_lane": the same PSNR of the lane views, the scale to read them against."""
    psnr = [pooled_psnr([e]) for e in errs] if errs is not None else None
    content = fd_out.get("seen_vs_heldout_lane", {}).get("value")
    pb = fd_out.get("prior_baseline", {}).get("elevated")
    out = {}
    for g in groups:
        idx = [i for i, ev in enumerate(elev) if ev.group == g]
        r = fd_elev[g]
        row = {"views": len(idx), **E.group_stats([elev[i] for i in idx]),
               "fd": round(r.value, 6), "fd_n": [r.n1, r.n2]}
        if psnr is not None:
            vals = [psnr[n_held + i] for i in idx]
            row["psnr_db"] = _psnr_stats(vals)
            if g == E.OVERVIEW:
                row["psnr_db_per_camera"] = {elev[i].name: round(v, 3) for i, v in zip(idx, vals)}
        if content:
            row["fd_over_content"] = round(r.value / max(content, 1e-12), 4)
        if pb is not None:
            prior = pb["prior_elevated_over_content"][g]
            row["prior_fd_over_content"] = prior
            if content:
                row["fd_over_prior"] = round(row["fd_over_content"] / max(prior, 1e-12), 4)
            row["fd_vs_prior_images"] = pb["scene_vs_prior_images"][g]["value"]
        if "elevated_per_height" in fd_out.get("vs_reference", {}):
            row["fd_vs_reference"] = fd_out["vs_reference"]["elevated_per_height"][g]["value"]
        out[g] = row
    if psnr is not None and n_held:
        out["heldout_lane"] = {"psnr_db": _psnr_stats(psnr[:n_held])}
    return out
