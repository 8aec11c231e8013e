"""A GGDS run from start to finish, as one library call: arrays in, a run store out.

``run_ggds(inputs, prior, config, store)`` owns the lifecycle: the loop with a progress bar,
checkpoints every ``checkpoint_every`` steps, resume from the store's checkpoint,
interruption (Ctrl-C writes the run so far as a valid, resumable layer), held-out evaluation,
and the plots. The caller (pipeline.generate, a batch chunk task, a benchmark) prepares the
arrays — surfels, proxy, views, lighting — and decides where results go (the store).
"""
from __future__ import annotations

import signal
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.ggds.run.optimisation import GGDSRun
from lsd3d_usd.splats.field import SurfelField

BEFORE_AFTER_VIEWS = 2


@dataclass
class GGDSInputs:
    """Everything a run optimises against, as arrays (no USD)."""
    field: SurfelField                      # the initial surfels (trainable)
    proxy: tuple                            # (V (n,3), F (m,3), face class ids (m,))
    views: list                             # training views (ggds.cameras.View)
    held_out: list                          # held-out views (evaluation only)
    env: object                             # prior_base.PriorEnv
    background: Callable | None = None      # camera -> (H,W,3) env radiance behind the surfels
    shadow: object | None = None            # conditioning.ShadowMap of the sun
    face_index: np.ndarray | None = None    # seed proxy face of every surfel
    context: SurfelField | None = None      # frozen neighbour surfels rendered with them
    focus: tuple | None = None              # (x0, y0, x1, y1) the loaded surfels cover
    fit_views: list = ()                    # more views for the world-space colour start only
    # (len(context),) bool: context rows whose colours start with the region's (a neighbour's
    # initial surfels, which still carry class colours); None: the context keeps its colours
    context_start: np.ndarray | None = None


def _log_nothing(*a):
    pass


def _progress(run: GGDSRun, prior, metrics=None, final=False) -> dict:
    return {"stepsDone": run.step_index, "steps": run.cfg.steps, "complete": bool(final),
            "seconds": round(run.seconds, 3), "metrics": metrics, "prior": prior.describe()}


def _save(store, run: GGDSRun, prior, inputs: GGDSInputs, *, metrics=None, final=False,
          keep_checkpoint=False) -> None:
    store.write_layer(run.field(), _progress(run, prior, metrics, final))
    if final and not keep_checkpoint:
        store.drop_checkpoint()
    else:
        tensors, meta = run.checkpoint(optimizer=True)
        store.save_checkpoint(tensors, meta)


def run_ggds(inputs: GGDSInputs, prior, config: GGDSConfig, store, *, resume: bool = False,
             stop_at: int | None = None, keep_checkpoint: bool = False, term_state=None,
             progress: bool = True, log=_log_nothing) -> dict:
    """Optimise ``inputs.field`` against ``prior`` and write the run through ``store``.

    resume: continue from the store's checkpoint (its configuration wins; pass the stored
    one). stop_at: stop after this many steps in all (the run stays resumable).
    keep_checkpoint: keep the resumable state of a finished run (default: dropped, the layer
    holds the result). term_state: already built loss-term state (e.g. a loaded LPIPS net).
    Returns the run summary (also written by the store).

    The run takes over ``inputs.field`` and ``inputs.context``: once its parameters hold them
    they are set to None here, so a caller that keeps no other reference frees them (a
    region's initial surfels and band are ~0.2 GB each per million)."""
    n_surfels = int(inputs.field.n)
    run = GGDSRun(inputs.field, inputs.proxy, inputs.views, prior, inputs.env, config,
                  background_fn=inputs.background, shadow=inputs.shadow,
                  face_index=inputs.face_index, term_state=term_state,
                  context=inputs.context, focus=inputs.focus, fit_views=inputs.fit_views,
                  context_start=inputs.context_start)
    inputs.field = inputs.context = None
    store.write_views(inputs.views)
    before = []
    if resume:
        tensors, meta = store.load_checkpoint()
        run.restore(tensors, meta)
        log(f"ggds: resuming {store.name} at step {run.step_index} of {config.steps}")
    else:
        with torch.no_grad():  # "before" = the initial surfels as authored
            before = [_render(run, v) for v in inputs.held_out[:BEFORE_AFTER_VIEWS]]
        if config.world_init and run.world_init():
            log("ggds: surfel colours initialised from the world-space prior")
            # its least-squares temporaries (hundreds of MB) would otherwise stay resident
            # as free heap beside the steps' own buffers (memtune keeps up to 1 GiB)
            from lsd3d_usd.memtune import release_free_memory
            release_free_memory()
    target = config.steps if stop_at is None else min(int(stop_at), config.steps)
    interrupted = False
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=target, initial=run.step_index, desc="GGDS", unit="step")
    try:
        while run.step_index < target:
            rec = run.step()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr_target']:.1f}")
            if run.step_index % config.checkpoint_every == 0 and run.step_index < target:
                _save(store, run, prior, inputs)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if bar is not None:
            bar.close()
    if interrupted:
        # Ctrl-C leaves a valid scene: the run so far as a layer, resumable.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            _save(store, run, prior, inputs)
        finally:
            signal.signal(signal.SIGINT, previous)
        raise KeyboardInterrupt
    summary = {"run": store.name, "steps": run.step_index, "seconds": round(run.seconds, 1),
               "s_per_step": round(run.seconds / max(run.step_index, 1), 3),
               "surfels": n_surfels, "complete": run.step_index >= config.steps,
               "context_colour_start": run.context_started}
    if not summary["complete"]:
        _save(store, run, prior, inputs)
        log(f"ggds: stopped at step {run.step_index} of {config.steps}; continue with --resume")
        return summary
    # the per-view caches (~6 MB a view) are done with: not held through evaluation and writing
    run.release_views()
    from lsd3d_usd.memtune import release_free_memory
    release_free_memory()
    t = time.perf_counter()
    metrics = run.evaluate(inputs.held_out) if inputs.held_out else {}
    _save(store, run, prior, inputs, metrics=metrics, final=True, keep_checkpoint=keep_checkpoint)
    summary.update(metrics)
    summary["eval_s"] = round(time.perf_counter() - t, 2)
    _plots(run, prior, inputs, before, store.plot_dir)
    store.write_summary(summary)
    return summary


def _render(run: GGDSRun, view) -> torch.Tensor:
    cam = view.camera
    bg = run.background_fn(cam) if run.background_fn else None
    return run.render(cam, background=bg).rgb


@torch.no_grad()
def _plots(run: GGDSRun, prior, inputs: GGDSInputs, before: list, out_dir) -> None:
    """loss.png (losses and PSNR against the prior per step) and before_after.png (initial
    surfels, after GGDS, prior target for the first held-out views)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lsd3d_usd.conditioning.gbuffer import view_gbuffer
    from lsd3d_usd.ggds.losses.effnet import linear_to_srgb
    out_dir.mkdir(parents=True, exist_ok=True)
    h = run.history
    if h:
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.2))
        steps = [r["step"] for r in h]
        for key in ("loss", "l1", "disparity", "normal"):
            ys = np.array([r.get(key, np.nan) for r in h])
            k = max(1, len(ys) // 20)
            ax[0].plot(steps, np.convolve(ys, np.ones(k) / k, mode="same"), label=key)
        ax[0].set_yscale("log"); ax[0].set_xlabel("step"); ax[0].legend(); ax[0].set_title("GGDS losses")
        ax[1].plot(steps, [r["psnr_target"] for r in h], ".", ms=3)
        ax[1].set_xlabel("step"); ax[1].set_ylabel("PSNR render vs prior target (dB)")
        fig.tight_layout(); fig.savefig(out_dir / "loss.png", dpi=100); plt.close(fig)
    rows = []
    for i, v in enumerate(inputs.held_out[:BEFORE_AFTER_VIEWS]):
        x = _render(run, v)
        gb = view_gbuffer(v.camera, run.vertices, run.faces, run.face_ids, run.shadow)
        tgt = prior.target(x.clamp(0, None), gb, run.env, 1.0, seed=i)
        rows.append((before[i] if i < len(before) else x, x, tgt))
    if rows:
        fig, ax = plt.subplots(len(rows), 3, figsize=(12, 2.4 * len(rows)), squeeze=False)
        for i, imgs in enumerate(rows):
            for j, (img, title) in enumerate(zip(imgs, ("initial surfels", "after GGDS",
                                                         "prior target"))):
                ax[i, j].imshow(linear_to_srgb(img.clamp(0, 1)).numpy()); ax[i, j].set_axis_off()
                if i == 0:
                    ax[i, j].set_title(title)
        fig.tight_layout(); fig.savefig(out_dir / "before_after.png", dpi=100); plt.close(fig)
