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

import torch
from tqdm import tqdm

from lsd3d_usd.ggds.run.inputs import GGDSInputs
from lsd3d_usd.ggds.run.optimisation import GGDSRun
from lsd3d_usd.ggds.run.plots import BEFORE_AFTER_VIEWS, render_rgb, write_plots
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.memtune import release_free_memory


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
    Returns the run summary (also written by the store); its ``phases_s`` gives the seconds
    spent outside the steps: ``init`` (the run's state, loss terms, the "before" renders),
    ``colour_start`` (on a resume: restoring the checkpoint), ``eval`` (held-out views),
    ``plots`` and ``write`` (the final layer; measured after the store wrote the summary, so
    only the returned one has it).

    The run takes over ``inputs.field`` and ``inputs.context``: once its parameters hold them
    they are set to None here, so a caller that keeps no other reference frees them (a
    region's initial surfels and band are ~0.2 GB each per million)."""
    n_surfels = int(inputs.field.n)
    phases = {}        # seconds of each part outside the steps (summary "phases_s")
    t = time.perf_counter()
    run = GGDSRun(inputs, prior, config, term_state=term_state)
    inputs.field = inputs.context = None
    store.write_views(inputs.views)
    # "before" = the initial surfels as authored; rendered before a checkpoint is restored
    # too, so a resumed run's before_after.png still shows where it started
    with torch.no_grad():
        before = [render_rgb(run, v) for v in inputs.held_out[:BEFORE_AFTER_VIEWS]]
    phases["init"] = time.perf_counter() - t
    t = time.perf_counter()
    if resume:
        tensors, meta = store.load_checkpoint()
        run.restore(tensors, meta)
        log(f"ggds: resuming {store.name} at step {run.step_index} of {config.steps}")
    else:
        if config.world_init and run.world_init():
            log("ggds: surfel colours initialised from the world-space prior")
            # its least-squares temporaries (hundreds of MB) would otherwise stay resident
            # as free heap beside the steps' own buffers (memtune keeps up to 1 GiB)
            release_free_memory()
    phases["colour_start"] = time.perf_counter() - t
    target = config.steps if stop_at is None else min(int(stop_at), config.steps)
    interrupted = False
    bar = None
    if progress:
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
               "context_colour_start": run.context_started,
               "phases_s": {k: round(v, 2) for k, v in phases.items()}}
    if not summary["complete"]:
        _save(store, run, prior, inputs)
        log(f"ggds: stopped at step {run.step_index} of {config.steps}; continue with --resume")
        return summary
    # the per-view caches (~6 MB a view) are done with: not held through evaluation and writing
    run.release_views()
    release_free_memory()
    t = time.perf_counter()
    metrics = run.evaluate(inputs.held_out) if inputs.held_out else {}
    summary.update(metrics)
    summary["eval_s"] = phases["eval"] = time.perf_counter() - t
    t = time.perf_counter()
    # the figures and the summary before the final save that marks the run complete: a run
    # killed in between is still unfinished (its checkpoint stays) and --resume redoes them
    write_plots(run, inputs.held_out, before, store.plot_dir)
    phases["plots"] = time.perf_counter() - t
    summary["eval_s"] = round(summary["eval_s"], 2)
    summary["phases_s"] = {k: round(v, 2) for k, v in phases.items()}
    store.write_summary(summary)
    t = time.perf_counter()
    _save(store, run, prior, inputs, metrics=metrics, final=True, keep_checkpoint=keep_checkpoint)
    summary["phases_s"]["write"] = round(time.perf_counter() - t, 2)
    return summary
