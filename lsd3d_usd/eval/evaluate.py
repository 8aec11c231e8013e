"""`evaluate`: render seen / novel / trajectory views of a scene's composed stage and measure
image-feature Fréchet distances, geometry agreement with the proxy, multi-view and temporal
consistency. Writes SCENE/eval/ (report.html, PNGs, eval.json); returns an eval.result.EvalResult.

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
from lsd3d_usd.conditioning.scene import select_generated_environment
from lsd3d_usd.eval import class_psnr as CP
from lsd3d_usd.eval import elevated_views as E
from lsd3d_usd.eval import geometry as G
from lsd3d_usd.eval import metrics as M
from lsd3d_usd.eval import models, report
from lsd3d_usd.eval import temporal as T
from lsd3d_usd.eval import lane_views as V
from lsd3d_usd.eval import off_path_views as OP
from lsd3d_usd.eval.options import EvalConfig
from lsd3d_usd.eval.prior_baseline import baseline_fd, open_baseline
from lsd3d_usd.eval.render import render_view
from lsd3d_usd.eval.result import (Counts, DeferredResult, Distances, EvalResult, Geometry,
                                   MultiviewDepth, SeenVsNovel)
from lsd3d_usd.eval.seams import paired_matched_drop
from lsd3d_usd.eval.seams_eval import reference_frames, seam_stats, seams_reference
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
# the trajectory's PSNR scores every 3rd frame: frames 0.5 m apart show nearly the same
# pixels, and each target costs a G-buffer and a prior image (~0.3 s at 320x180)
TRAJ_SCORE_EVERY = 3


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


# ------------------------------------------------------------------ the driver
def evaluate(o: EvalOptions) -> EvalResult:
    """Render every view family, measure it, write the report and eval.json (its
    ``to_json()``); the families are rendered in a fixed order (seen, novel, held-out,
    elevated, off-path, trajectory) because the deferrer draws its noise in call order.
    Every view is scored against the run's target as it is rendered (class_psnr.Scorer)."""
    t_start = time.perf_counter()
    timings = {}
    t = time.perf_counter()
    inp = _load(o)
    timings["load_s"] = time.perf_counter() - t
    w, h = o.cfg.resolution
    o.log(f"eval: {inp.surfels.n:,} surfels; seen: {inp.seen.source}; {len(inp.seen_sel)} seen + "
          f"{len(inp.novel)} novel views ({len(o.cfg.bin_values())} bins) + {len(inp.elev)} elevated "
          f"views + {len(inp.off_path.views)} off-path views + {len(inp.traj)} trajectory frames "
          f"at {w}x{h}")

    t = time.perf_counter()
    bar = tqdm(total=len(inp.seen_sel) + len(inp.novel) + len(inp.heldout) + len(inp.elev)
               + len(inp.off_path.views) + len(inp.traj), desc="eval render", unit="view",
               disable=not o.progress)
    dfr = DeferredImages()
    r = Renders()
    _render_seen(inp, o, r, dfr, bar)
    _render_novel(inp, o, r, dfr, bar)
    _render_heldout(inp, o, r, bar)
    _render_elevated(inp, o, r, bar)
    timings["render_seen_novel_s"] = time.perf_counter() - t
    t = time.perf_counter()
    _render_off_path(inp, o, r, bar)
    timings["render_off_path_s"] = time.perf_counter() - t
    t = time.perf_counter()
    temporal = _render_trajectory(inp, o, r, dfr, bar)
    bar.close()
    timings["render_trajectory_s"] = time.perf_counter() - t
    if inp.deferrer is not None:
        timings["deferred_s"] = dfr.seconds
    if inp.base is not None:
        timings["prior_baseline_s"] = inp.base.seconds
    timings["psnr_targets_s"] = inp.scorer.seconds

    t = time.perf_counter()
    fds = _distances(inp, o, r, dfr)
    timings["features_fd_s"] = time.perf_counter() - t
    novel_elevated = _novel_elevated(inp.elev, fds.groups, inp.scorer, fds.fd_elev,
                                     fds.distances)
    novel_off_path = _novel_off_path(inp.off_path, inp.scorer, fds)
    psnr_why = inp.scorer.why
    t = time.perf_counter()
    seams, why, ref_why = _seams(inp, o, r)
    timings["seams_s"] = time.perf_counter() - t

    unavailable = models.status(inp.weights)
    if inp.ref_imgs is None:
        unavailable.insert(0, {"metric": "fd_effnet_lite0.vs_reference",
                               "reason": "no --reference DIR of images given"})
    for metric, reason in (("seams", why), ("seams.vs_reference", ref_why),
                           ("psnr_db", psnr_why),
                           ("fd_effnet_lite0.prior_baseline", inp.base_why)):
        if reason:
            unavailable.append({"metric": metric, "reason": reason})
    timings["total_s"] = time.perf_counter() - t_start
    sc, cfg, elev = inp.sc, o.cfg, inp.elev
    result = EvalResult(
        scene=str(sc.root), run=inp.seen.run, seen_views_source=inp.seen.source,
        composed_layers=[li.name for li in sc.layers() if not li.muted and li.exists],
        surfels=int(inp.surfels.n), resolution=[w, h], tonemap=cfg.tonemap, seed=cfg.seed,
        bins_m=[float(b) for b in cfg.bin_values()],
        heights_m=[float(x) for x in cfg.height_values()],
        pitch_deg=[float(x) for x in cfg.pitch_range()],
        counts=Counts(train_views=len(inp.seen.views), seen=len(inp.seen_sel), novel=len(inp.novel),
                      novel_per_bin=cfg.per_bin, heldout_lane=len(inp.heldout),
                      trajectory_frames=len(inp.traj), reference=fds.n_ref, elevated=len(elev),
                      elevated_per_height=cfg.per_height,
                      overview=sum(ev.group == E.OVERVIEW for ev in elev),
                      off_path=len(inp.off_path.views), off_path_per_bin=cfg.off_path_per_bin),
        seen_views=_psnr_entry(inp.scorer.family("seen")),
        novel_views={f"{b:g}": _bin_stats(inp, b) for b in cfg.bin_values()},
        novel_elevated=novel_elevated, novel_off_path=novel_off_path, distances=fds.distances,
        geometry=Geometry(seen=r.agree["seen"].result(), novel=r.agree["novel"].result()),
        multiview=_multiview(cfg.bin_values(), r), seams=seams,
        temporal={**temporal, **_psnr_entry(inp.scorer.family("trajectory"))},
        deferred=fds.deferred, unavailable=unavailable, warnings=fds.warnings,
        timings={k: round(v, 2) for k, v in timings.items()})
    t = time.perf_counter()
    files = report.write_report(inp.out_dir, result, sc, r.seen_img, r.novel_img, inp.novel,
                                r.traj_img, seen_frames=r.seen_frames, seen_gb=r.seen_gb,
                                deferred=dfr if inp.deferrer is not None else None,
                                elevated=(elev, r.elev_img),
                                off_path=(inp.off_path, r.off_img,
                                          inp.base.images["off_path"] if inp.base else None))
    result.timings["report_s"] = round(time.perf_counter() - t, 2)
    result.files = {k: str(v) for k, v in files.items()}
    report.write_json(inp.out_dir / "eval.json", result.to_json())
    return result


@dataclass
class Inputs:
    """The scene as eval reads it and every camera it renders, placed before any rendering."""
    sc: S.Scene
    weights: object
    ref_imgs: list | None
    out_dir: Path
    deferrer: object
    base: object                 # eval.prior_baseline's collector, or None
    base_why: str | None
    stage: object
    surfels: object
    env: object
    layout: object
    proxy: tuple                 # (PV, PF, PC)
    seen: V.SeenSet
    seen_sel: list
    novel: list
    heldout: list
    elev: list
    off_path: OP.OffPathSet
    traj: list
    traj_info: dict
    seams_ref: tuple | None
    scorer: CP.Scorer            # PSNR per view and class against the run's targets
    reuse_targets: bool          # the prior baseline's images are the scorer's targets


def _load(o: EvalOptions) -> Inputs:
    """Everything that can fail on bad input, before anything is rendered or written."""
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
    stage = sc.open_stage()
    check_scene(stage, sc.root)
    surfels = scene_surfels(stage)
    if surfels is None:
        raise InputError(f"{sc.root}: no surfels to render (no visible ParticleField prim)")
    # the environment its targets are conditioned on, whatever variant the views select
    select_generated_environment(sc, stage)
    env = read_dome(stage)
    layout = read_layout(layout_path)
    proxy = proxy_arrays(sc.layer_path("proxy"))
    w, h = o.cfg.resolution
    seen = V.seen_views(sc, layout, o.cfg.run, w, h)
    # the seen family (and the novel and held-out views placed from it) are the views GGDS
    # trained on at eye height; elevated training views (ggds.elevated_train) still count as
    # training cameras for every family's nearest-camera distance. Views the colour start
    # alone fitted to are not recorded in the run, so they count for none.
    ground = [v for v in seen.views if v.kind != ELEVATED]
    seen_sel = [ground[i] for i in V.pick(len(ground), o.cfg.n_seen, o.cfg.seed)]
    centres = [v.camera.center for v in seen.views]
    novel = V.novel_views(seen_sel, o.cfg.bin_values(), o.cfg.per_bin, o.cfg.seed + 1, layout,
                          train_centres=centres)
    heldout = V.heldout_lane_views(layout, n_held, w, h, o.cfg.seed, seen_sel)
    elev = E.elevated_views(layout, o.cfg.height_values(), o.cfg.per_height, o.cfg.pitch_range(),
                            o.cfg.seed + 2, w, h, V.fov_of(seen_sel), train_centres=centres)
    if o.cfg.overview:
        elev += E.overview_views(stage, layout, w, h, train_centres=centres)
    off_path = OP.off_path_views(layout, o.cfg.off_path_per_bin, w, o.cfg.seed + 3,
                                 OP.run_regions(sc, seen.run))
    traj, traj_info = V.lane_trajectory(layout, o.cfg.frames, o.cfg.step_m, w, h)
    scorer = CP.Scorer(sc, seen.run, proxy, keep=("seen", "heldout"))
    seams_ref = None
    if o.cfg.seams_reference is not None:   # checked before any rendering: a bad one fails at once
        seams_ref = seams_reference(o.cfg.seams_reference, sc, seen.run, proxy)
    return Inputs(sc=sc, weights=weights, ref_imgs=ref_imgs, out_dir=out_dir, deferrer=deferrer,
                  base=base, base_why=base_why, stage=stage, surfels=surfels, env=env,
                  layout=layout, proxy=proxy, seen=seen, seen_sel=seen_sel, novel=novel,
                  heldout=heldout, elev=elev, off_path=off_path, traj=traj, traj_info=traj_info,
                  seams_ref=seams_ref, scorer=scorer,
                  reuse_targets=base is not None and base.same_images(scorer.sp))


@dataclass
class Renders:
    """What the families' renders keep for the measures and the report."""
    seen_img: list = field(default_factory=list)
    seen_frames: list = field(default_factory=list)
    seen_gb: list = field(default_factory=list)
    novel_img: list = field(default_factory=list)
    heldout_img: list = field(default_factory=list)
    heldout_frames: list = field(default_factory=list)
    elev_img: list = field(default_factory=list)
    off_img: list = field(default_factory=list)
    traj_img: list = field(default_factory=list)
    traj_frames: list = field(default_factory=list)
    agree: dict = field(default_factory=dict)       # "seen" / "novel": G.ClassAgreement
    mv_err: dict = field(default_factory=dict)      # bin -> per-pair depth errors
    mv_shared: dict = field(default_factory=dict)   # bin -> per-pair shared fractions


def _render_seen(inp: Inputs, o: EvalOptions, r: Renders, dfr, bar) -> None:
    """The seen views, and their G-buffers against the proxy."""
    PV, PF, PC = inp.proxy
    r.agree["seen"] = G.ClassAgreement(o.cfg.seed)
    for v in inp.seen_sel:
        fr = render_view(inp.surfels, inp.env, v.camera)
        gb = render_gbuffer(PV, PF, v.camera, PC)
        r.agree["seen"].add(fr, gb, v.camera)
        r.seen_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        r.seen_frames.append(fr)
        r.seen_gb.append(gb)
        if inp.deferrer is not None:
            dfr.add("seen", inp.deferrer, fr["rgb"], v.camera, o)
        _score(inp, "seen", v.camera, fr["rgb"])
        bar.update(1)


def _render_novel(inp: Inputs, o: EvalOptions, r: Renders, dfr, bar) -> None:
    """The novel views: against the proxy, and the seen view each was displaced from
    reprojected into it (multi-view depth)."""
    PV, PF, PC = inp.proxy
    r.agree["novel"] = G.ClassAgreement(o.cfg.seed + 1)
    r.mv_err = {b: [] for b in o.cfg.bin_values()}
    r.mv_shared = {b: [] for b in o.cfg.bin_values()}
    for nv in inp.novel:
        fr = render_view(inp.surfels, inp.env, nv.view.camera)
        gb = render_gbuffer(PV, PF, nv.view.camera, PC)
        r.agree["novel"].add(fr, gb, nv.view.camera)
        r.novel_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        if inp.deferrer is not None:
            dfr.add("novel", inp.deferrer, fr["rgb"], nv.view.camera, o)
        _score(inp, "novel", nv.view.camera, fr["rgb"])
        e = G.reprojection_depth_error(inp.seen_sel[nv.source].camera, r.seen_frames[nv.source],
                                       r.seen_gb[nv.source], nv.view.camera, fr, gb)
        if e is not None:
            r.mv_err[nv.bin_m].append(e["errors"])
            r.mv_shared[nv.bin_m].append(e["shared_frac"])
        bar.update(1)


def _render_heldout(inp: Inputs, o: EvalOptions, r: Renders, bar) -> None:
    for cam in inp.heldout:
        fr = render_view(inp.surfels, inp.env, cam)
        r.heldout_frames.append(fr)
        r.heldout_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        _score(inp, "heldout", cam, fr["rgb"])
        bar.update(1)


def _render_elevated(inp: Inputs, o: EvalOptions, r: Renders, bar) -> None:
    for ev in inp.elev:
        fr = render_view(inp.surfels, inp.env, ev.camera)
        r.elev_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        _score(inp, "elevated", ev.camera, fr["rgb"])
        bar.update(1)


def _render_off_path(inp: Inputs, o: EvalOptions, r: Renders, bar) -> None:
    for v in inp.off_path.views:
        fr = render_view(inp.surfels, inp.env, v.camera)
        r.off_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        _score(inp, "off_path", v.camera, fr["rgb"])
        bar.update(1)


def _score(inp: Inputs, family: str, camera, rgb) -> None:
    """PSNR of one render against the run's target, and the prior baseline's image of the
    view (the same target, made once, when the two are the same image)."""
    target = inp.scorer.add(family, camera, rgb)
    if inp.base is not None and family != "trajectory":
        inp.base.add(family, rgb, camera, target=target if inp.reuse_targets else None)


def _render_trajectory(inp: Inputs, o: EvalOptions, r: Renders, dfr, bar) -> dict:
    """The trajectory frames; returns their temporal warp errors (``temporal_warp_err``)."""
    for i, cam in enumerate(inp.traj):
        fr = render_view(inp.surfels, inp.env, cam)
        r.traj_frames.append({k: fr[k] for k in ("alpha", "depth_median", "depth_expected")})
        r.traj_img.append(display(fr["rgb"], o.cfg.tonemap, o.cfg.exposure))
        if inp.deferrer is not None:
            dfr.add("traj", inp.deferrer, fr["rgb"], cam, o, target=False)
        if i % TRAJ_SCORE_EVERY == 0:
            _score(inp, "trajectory", cam, fr["rgb"])
        bar.update(1)
    temporal = T.trajectory_warp_errors(inp.traj, r.traj_img, r.traj_frames)
    temporal.update(inp.traj_info)
    return temporal


@dataclass
class Features:
    """What the feature step gives the rest: the distances, the elevated groups' FD against
    the seen views, the deferred renders' measures and the few-samples warning."""
    distances: Distances
    fd_elev: dict
    groups: list
    fd_off: dict                # off-path bin -> FD of the seen views against its views
    deferred: DeferredResult | None
    warnings: list
    n_ref: int


def _distances(inp: Inputs, o: EvalOptions, r: Renders, dfr) -> Features:
    """EfficientNet-Lite0 features of every family and their Fréchet distances."""
    ext = EffNetFeatureExtractor()
    bins = o.cfg.bin_values()

    def embed(imgs):
        x = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()
        return ext.embed(x, linear=False, size=224).double().numpy()

    smallest = []

    def fd(a, b):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", M.FewSamplesWarning)
            res = M.frechet_distance_features(a, b)
        if res.warning:
            smallest.append(min(res.n1, res.n2))
        return res

    def seen_vs_novel(f_a, f_b) -> SeenVsNovel:
        return SeenVsNovel(overall=fd(f_a, f_b).to_json(),
                           per_bin={f"{b:g}": fd(f_a, f_b[bins_arr == b]).to_json() for b in bins})

    f_seen = embed(r.seen_img)
    f_novel = embed(r.novel_img)
    bins_arr = np.array([nv.bin_m for nv in inp.novel])
    dist = Distances(seen_vs_novel=seen_vs_novel(f_seen, f_novel))
    if r.heldout_img:
        dist.seen_vs_heldout_lane = fd(f_seen, embed(r.heldout_img)).to_json()
    elev = inp.elev
    groups = list(dict.fromkeys(ev.group for ev in elev))   # heights, then overview
    groups_arr = np.array([ev.group for ev in elev])
    f_elev = embed(r.elev_img) if r.elev_img else None
    off_bins = {k: np.asarray(i, int) for k, i in inp.off_path.bins.items() if i}
    f_off = embed(r.off_img) if r.off_img else None
    fd_off = {k: fd(f_seen, f_off[i]) for k, i in off_bins.items()}
    if inp.base is not None:
        dist.prior_baseline = baseline_fd(fd, embed, inp.base.images, bins, bins_arr,
                                          dist.to_json(), inp.base.sp,
                                          elevated=(groups, groups_arr, f_elev) if elev else None,
                                          off_path=(off_bins, f_off) if off_bins else None)
    n_ref = 0
    if inp.ref_imgs is not None:
        f_ref = embed(inp.ref_imgs)
        n_ref = len(f_ref)
        dist.vs_reference = {
            "seen": fd(f_seen, f_ref).to_json(), "novel": fd(f_novel, f_ref).to_json(),
            "novel_per_bin": {f"{b:g}": fd(f_novel[bins_arr == b], f_ref).to_json() for b in bins}}
        if elev:
            dist.vs_reference["elevated_per_height"] = {
                g: fd(f_elev[groups_arr == g], f_ref).to_json() for g in groups}
    deferred = None
    if inp.deferrer is not None:
        f_dseen, f_dnovel = embed(dfr.images["seen"]), embed(dfr.images["novel"])
        f_target = embed(dfr.targets["seen"] + dfr.targets["novel"])
        d_temporal = T.trajectory_warp_errors(inp.traj, dfr.images["traj"], r.traj_frames)
        d_temporal.update(inp.traj_info)
        deferred = DeferredResult(
            provenance=inp.deferrer.describe(), seen_vs_novel=seen_vs_novel(f_dseen, f_dnovel),
            vs_prior_raw=fd(np.concatenate([f_seen, f_novel]), f_target).to_json(),
            vs_prior_deferred=fd(np.concatenate([f_dseen, f_dnovel]), f_target).to_json(),
            temporal=d_temporal)
    fd_elev = {g: fd(f_seen, f_elev[groups_arr == g]) for g in groups}
    notes = []
    if smallest:
        notes.append(
            f"Fréchet distances from fewer samples than feature dimensions ({f_seen.shape[1]}-d; "
            f"smallest set {min(smallest)}): covariances are rank-deficient and values are biased "
            "upwards; compare only values computed with equal sample counts")
    return Features(distances=dist, fd_elev=fd_elev, groups=groups, fd_off=fd_off,
                    deferred=deferred, warnings=notes, n_ref=n_ref)


def _seams(inp: Inputs, o: EvalOptions, r: Renders) -> tuple[dict | None, str | None, str | None]:
    """The seams between chunks (None, with why, when not measured) and why the comparison
    with --seams-reference is missing."""
    frame_sets = [r.seen_frames + r.heldout_frames]
    ref_why = None
    seams_ref, heldout = inp.seams_ref, inp.heldout
    if seams_ref is not None and len(heldout) < 2:
        ref_why = "needs at least 2 held-out lane views (--heldout)"
    elif seams_ref is not None:
        # only the held-out lane views count: the seen views are the evaluated run's training
        # cameras, which the reference never trained on
        skip = [None] * len(inp.seen_sel)
        frame_sets += [skip + r.heldout_frames,
                       itertools.chain(skip, reference_frames(seams_ref[0], heldout))]
    sc_t = inp.scorer.targets
    targets = (sc_t.get("seen", []) + sc_t.get("heldout", [])
               if len(sc_t.get("seen", [])) == len(inp.seen_sel) else None)
    stats, why = seam_stats(inp.sc, inp.seen.run, inp.layout, inp.proxy,
                            [v.camera for v in inp.seen_sel] + list(heldout), *frame_sets,
                            targets=targets)
    seams = stats[0].result() if stats is not None else None
    if seams_ref is not None and not ref_why:
        if seams is None:
            ref_why = f"no seam measure ({why})"
        else:
            seams["vs_reference"] = {"scene": str(o.cfg.seams_reference), "run": seams_ref[1],
                                     **paired_matched_drop(stats[1], stats[2], o.cfg.seed)}
    return seams, why, ref_why


def _multiview(bins, r: Renders) -> MultiviewDepth:
    per_bin, all_err = {}, []
    for b in bins:
        e = np.concatenate(r.mv_err[b]) if r.mv_err[b] else np.zeros(0)
        all_err.append(e)
        per_bin[f"{b:g}"] = {
            "median": round(float(np.median(e)), 5) if e.size else None,
            "frac_over_5pct": round(float((e > 0.05).mean()), 4) if e.size else None,
            "shared_frac": round(float(np.mean(r.mv_shared[b])), 4) if r.mv_shared[b] else 0.0,
            "pairs": len(r.mv_err[b])}
    e = np.concatenate(all_err)
    return MultiviewDepth(per_bin=per_bin,
                          median=round(float(np.median(e)), 5) if e.size else None,
                          frac_over_5pct=round(float((e > 0.05).mean()), 4) if e.size else None)


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


def _bin_stats(inp: Inputs, b: float) -> dict:
    """A novel bin's ``novel_views`` entry: pose medians and PSNR (all, per class)."""
    idx = [i for i, nv in enumerate(inp.novel) if nv.bin_m == b]
    if not idx:
        return {}
    near = np.array([inp.novel[i].nearest_train_m for i in idx])
    yaw = np.abs([inp.novel[i].yaw_deg for i in idx])
    return {"count": len(idx), "nearest_train_m_median": round(float(np.median(near)), 3),
            "abs_yaw_deg_median": round(float(np.median(yaw)), 2),
            **_psnr_entry(inp.scorer.family("novel", idx) if inp.scorer.ok else [])}


def _psnr_entry(errors: list) -> dict:
    """``psnr_db`` {mean, median, min, max, views} and ``psnr_db_per_class`` of a family's
    views against the run's targets (nothing without targets)."""
    if not errors:
        return {}
    return {"psnr_db": CP.psnr_stats(errors), "psnr_db_per_class": CP.per_class(errors)}


def _novel_elevated(elev: list, groups: list, scorer: CP.Scorer, fd_elev: dict,
                    dist: Distances) -> dict:
    """The ``novel_elevated`` entry: per height (and "overview") the pose medians, PSNR
    against the run's held-out targets (all and per class; missing without targets), FD seen
    vs elevated and its ratios; "heldout_lane": the same PSNR of the lane views, the scale to
    read them against."""
    errs = scorer.family("elevated")
    content = (dist.seen_vs_heldout_lane or {}).get("value")
    pb = (dist.prior_baseline or {}).get("elevated")
    out = {}
    for g in groups:
        idx = [i for i, ev in enumerate(elev) if ev.group == g]
        r = fd_elev[g]
        row = {"views": len(idx), **E.group_stats([elev[i] for i in idx]),
               "fd": round(r.value, 6), "fd_n": [r.n1, r.n2]}
        if errs:
            row.update(_psnr_entry([errs[i] for i in idx]))
            if g == E.OVERVIEW:
                row["psnr_db_per_camera"] = {elev[i].name: CP.pooled([errs[i]]) for i in idx}
        if content:
            row["fd_over_content"] = round(r.value / max(content, 1e-12), 4)
        if pb is not None:
            prior = pb["prior_elevated_over_content"][g]
            row["prior_fd_over_content"] = prior
            if content:
                row["fd_over_prior"] = round(row["fd_over_content"] / max(prior, 1e-12), 4)
            row["fd_vs_prior_images"] = pb["scene_vs_prior_images"][g]["value"]
        if "elevated_per_height" in (dist.vs_reference or {}):
            row["fd_vs_reference"] = dist.vs_reference["elevated_per_height"][g]["value"]
        out[g] = row
    if errs and scorer.family("heldout"):
        out["heldout_lane"] = _psnr_entry(scorer.family("heldout"))
    return out


def _novel_off_path(off: OP.OffPathSet, scorer: CP.Scorer, feats: Features) -> dict:
    """The ``novel_off_path`` entry: per bin PSNR against the run's targets of the same
    cameras (pooled over the bin's views), FD of the seen views against the bin's views over
    the content change, and that over the prior's own ratio for the same cameras
    (``fd_over_prior_per_bin``: 1 = the scene departs from the seen views as its prior's
    images do); the family's PSNR per class."""
    if not off.views:
        return {}
    errs = scorer.family("off_path")
    dist = feats.distances
    content = (dist.seen_vs_heldout_lane or {}).get("value")
    pb = (dist.prior_baseline or {}).get("off_path")
    out = {"views": len(off.views), "stations": off.stations,
           "regions": off.regions, "rig_camera": f"{OP.RIG} {OP.RIG_CAMERA}",
           "bins": {k: {"lateral_m": p[0], "height_m": p[1], "yaw_deg": p[2]}
                    for k, p in OP.bin_poses().items()}}
    if errs:
        out["psnr_db_per_bin"] = {k: CP.pooled([errs[i] for i in idx])
                                  for k, idx in off.bins.items()}
        out["psnr_db_per_class"] = CP.per_class(errs)
        out["psnr_db_per_class_per_bin"] = {k: CP.per_class([errs[i] for i in idx])
                                            for k, idx in off.bins.items()}
    out["fd_per_bin"] = {k: round(r.value, 6) for k, r in feats.fd_off.items()}
    if content:
        out["fd_over_content_per_bin"] = {k: round(r.value / max(content, 1e-12), 4)
                                          for k, r in feats.fd_off.items()}
    if pb is not None and content:
        prior = pb["prior_off_path_over_content"]
        out["prior_fd_over_content_per_bin"] = prior
        out["fd_over_prior_per_bin"] = {
            k: round(out["fd_over_content_per_bin"][k] / max(prior[k], 1e-12), 4) for k in prior}
        out["fd_vs_prior_images_per_bin"] = {k: v["value"] for k, v in
                                             pb["scene_vs_prior_images"].items()}
    return out
