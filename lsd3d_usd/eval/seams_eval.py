"""The seam measure of a scene (eval.seams) and the errors of given views, against the targets
of the prior and light its GGDS run used."""
from __future__ import annotations

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.scene import select_generated_environment
from lsd3d_usd.errors import InputError
from lsd3d_usd.eval.geometry import surfel_depth
from lsd3d_usd.eval.render import render_view
from lsd3d_usd.eval.seams import SeamStats
from lsd3d_usd.ggds.priors.registry import PRIORS
from lsd3d_usd.ggds.priors.scene import load_scene_prior, recorded_config
from lsd3d_usd.ggds.run.store import read_plan
from lsd3d_usd.proxy.usdio import proxy_arrays
from lsd3d_usd.render.gbuffer import render_gbuffer
from lsd3d_usd.splats.chunkio import read_chunk_map
from lsd3d_usd.views.stage_data import read_dome, scene_surfels


def run_prior(sc, run: str | None, proxy):
    """(the ScenePrior of the scene's GGDS run ``run`` over ``proxy``, None), or (None, why
    not): its held-out targets are what the seam measure scores views against."""
    if run is None:
        return None, "no GGDS run: the prior and light of its targets are unknown"
    recorded, _ = recorded_config(sc, run)
    if recorded is None:
        return None, f"run {run} records no configuration"
    name = str((recorded.get("prior") or {}).get("name") or "procedural")
    if not PRIORS.get(name.split(":", 1)[0]).cheap_on_cpu:
        return None, (f"the run's prior ({name}) is a GPU path; seam targets are made with a "
                      "prior that is cheap on the CPU only")
    try:
        return load_scene_prior(sc.root, run=run, proxy=proxy, purpose="the seam measure"), None
    except InputError as e:
        return None, str(e)


def view_errors(sc, run: str | None, proxy, cameras, frames,
                region: tuple | None = None) -> tuple[list | None, str | None]:
    """([(sum of squared errors, values) of each rendered view against its target], None),
    or (None, why not). ``region`` (x0, y0, x1, y1): only the pixels whose proxy surface lies
    inside it (what views from the same positions share when the scenes around differ; a
    view without such pixels gives (0, 0))."""
    sp, why = run_prior(sc, run, proxy)
    if sp is None:
        return None, why
    out = []
    for j, (cam, fr) in enumerate(zip(cameras, frames)):
        x_hat, gb = sp.heldout_target(cam, fr["rgb"], j)
        err = (np.clip(fr["rgb"], 0, 1) - np.clip(x_hat, 0, 1)) ** 2
        if region is not None:   # the target's own G-buffer: no second rasterisation
            p, x0, y0, x1, y1 = gb.world_pos.numpy(), *region
            keep = (gb.valid.numpy() & (p[..., 0] >= x0) & (p[..., 0] < x1)
                    & (p[..., 1] >= y0) & (p[..., 1] < y1))
            err = err[keep]
        out.append((float(np.sum(err, dtype=np.float64)), int(err.size)))
    return out, None


def pooled_psnr(errors) -> float:
    """PSNR in dB of (sum of squared errors, values) pairs pooled (views weighted by their
    pixels); nan when there are no values."""
    sse = sum(e for e, _ in errors)
    n = sum(k for _, k in errors)
    if n == 0:
        return float("nan")
    mse = sse / n
    return 99.0 if mse <= 1e-10 else -10.0 * float(np.log10(mse))


def measure_seams(sc, run: str | None, layout, proxy, cameras, frames) -> tuple[dict | None, str | None]:
    """(seam statistics, None) over the given rendered views, or (None, why not). ``frames``
    may be any iterable: it is consumed only when there is something to measure."""
    stats, why = seam_stats(sc, run, layout, proxy, cameras, frames)
    return (stats[0].result(), None) if stats is not None else (None, why)


def seam_stats(sc, run: str | None, layout, proxy, cameras, *frame_sets, targets=None):
    """([eval.seams.SeamStats per set of rendered frames], None), or (None, why not):
    measure_seams before its summary. Several frame sets (other scenes of the same layout
    rendered from the same cameras) share the border bands, the G-buffers and the run's
    targets (at t = 1 the procedural prior's target is its own render, whatever the frame:
    made once per view), for comparing scenes view by view (eval.seams.paired_matched_drop).
    A set's frame may be None: that set leaves the view out (its first set has them all).
    ``targets``: the run's targets of the cameras already made (eval's scorer), or None."""
    chunks = read_chunk_map(sc.layer_path("surfels"))
    keys = set(chunks)
    if len(keys) < 2:
        return None, "the scene's surfels are not stored in two or more chunks"
    sp, why = run_prior(sc, run, proxy)
    if sp is None:
        return None, why
    V, F, C = proxy
    bounds = {k: (b[0], b[1], b[3], b[4]) for k, v in chunks.items()
              if len(b := v.get("bounds") or []) == 6}
    stats = [SeamStats(float(layout.chunk_size), keys, bounds=bounds) for _ in frame_sets]
    for j, (cam, *frames) in enumerate(zip(cameras, *frame_sets)):
        gb = render_gbuffer(V, F, cam, C)
        tgt = (targets[j] if targets is not None
               else sp.heldout_target(cam, frames[0]["rgb"], j)[0])
        for st, fr in zip(stats, frames):
            if fr is not None:
                st.add(fr["rgb"], tgt, fr["alpha"], surfel_depth(fr), fr["normal_world"], gb)
    return stats, None


def seams_reference(path, sc, run: str | None, proxy) -> tuple:
    """(the reference scene, its run) for the seam measure (``eval --seams-reference``): the
    same layout without chunk seams (generated with ``--regions scene`` and the same seed and
    settings), to be rendered from the evaluated scene's held-out views and scored against the
    same targets. InputError, naming what differs, unless it is another scene with the same
    proxy geometry whose newest active GGDS run optimised the whole scene as one region with
    the same prior, environment and seed as ``run``. Reads only; reference_frames
    loads its surfels when they are needed."""

    what = f"--seams-reference {path}"
    ref = S.Scene.open(path)
    if ref.root.resolve() == sc.root.resolve():
        raise InputError(f"{what}: that is the evaluated scene itself; give the same layout "
                         "generated with --regions scene")
    if not ref.layer_path("proxy").is_file():
        raise InputError(f"{what}: the scene has no proxy layer")
    theirs = proxy_arrays(ref.layer_path("proxy"))
    if any(a.shape != b.shape or not np.array_equal(a, b) for a, b in zip(proxy, theirs)):
        raise InputError(f"{what}: its proxy geometry differs from {sc.root}'s: the reference "
                         "must be generated from the same layout")
    if run is None:
        raise InputError(f"{sc.root}: no GGDS run to compare with {what}")
    runs = [li for li in ref.runs() if not li.muted and li.exists]
    if not runs:
        raise InputError(f"{what}: the scene has no active GGDS run")
    ref_run = runs[0].name

    def plan(scene, name, whose):
        try:
            return read_plan(scene, name)
        except InputError as e:
            raise InputError(f"{what}: {whose} run {name} has no readable plan ({e})") from None
    mp, rp = plan(sc, run, "the evaluated scene's"), plan(ref, ref_run, "the reference's")
    if set(rp.get("regions") or {}) != {""}:
        raise InputError(f"{what}: its run {ref_run} optimised {len(rp.get('regions') or {})} "
                         "chunk regions; a reference without chunk seams is one region "
                         "(generate --regions scene)")
    for key in ("prior", "env"):
        if mp["generate"].get(key) != rp["generate"].get(key):
            raise InputError(f"{what}: its run {ref_run} used another {key} than run "
                             f"{run}: their targets would differ")
    if int(mp.get("seed", 0)) != int(rp.get("seed", 0)):
        raise InputError(f"{what}: its run {ref_run} has seed {rp.get('seed')}, run {run} "
                         f"{mp.get('seed')}: their environments and targets would differ")
    return ref, ref_run


def reference_frames(ref, cameras):
    """Frames of a reference scene checked by seams_reference, rendered lazily: its surfels are
    loaded only when the first frame is asked for (never when there is no seam measure)."""
    stage = ref.open_stage()
    surfels = scene_surfels(stage)
    if surfels is None:
        raise InputError(f"--seams-reference {ref.root}: no surfels to render")
    select_generated_environment(ref, stage)      # as evaluate does for the scene
    env = read_dome(stage)
    for cam in cameras:
        yield render_view(surfels, env, cam)
