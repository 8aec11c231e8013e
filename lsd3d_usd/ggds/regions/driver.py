"""The driver of a chunk-wise run: every unfinished region phase by phase, in this process or
on an executor (a local process pool or Ray), the run layer refreshed as regions finish, and
the run's summary. The driver holds no surfel arrays."""
from __future__ import annotations

import time

from tqdm import tqdm

from lsd3d_usd import registry
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.env.config import EnvConfig
from lsd3d_usd.execution import ERROR, OK, SUSPECT, make_executor
from lsd3d_usd.ggds.priors.registry import PriorConfig
from lsd3d_usd.ggds.regions.task import RegionJob, run_region
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.ggds.run.store import (read_plan, refresh_run_layer, region_progress,
                                      region_task, run_summary, write_plan,
                                      write_region_task, write_json)
from lsd3d_usd.memtune import peak_rss_mb


def run_regions(sc: S.Scene, run: str, *, phases: list, ggds: GGDSConfig, prior: PriorConfig,
                env: EnvConfig, seed: int, stop_at: int | None = None,
                keep_checkpoint: bool = False, workers: int = 1, executor: str = "local",
                address: str | None = None, retries: int = 2, term_state=None,
                progress: bool = True, log=print) -> dict:
    """Run every unfinished region of ``phases`` (regions.plan) phase by phase (in this
    process when one worker or one region; else on a local pool or Ray), updating the run
    layer as regions finish; a region with a checkpoint resumes from it. ``ggds`` / ``prior``
    / ``env``: the run's configuration trees (serialised only for a worker process). Returns the run summary (also
    ggds/<run>/summary.json)."""
    plan = read_plan(sc, run)
    t0 = time.perf_counter()
    finished = {tuple(k) for name in plan["regions"] if region_progress(sc, run, name)
                .get("complete") for k in plan["regions"][name]}
    summaries = {}
    base = dict(scene=str(sc.root), run=run, ggds=ggds, prior=prior, env=env, seed=seed,
                stop_at=stop_at, keep_checkpoint=keep_checkpoint,
                registrations=registry.portable())
    n_regions = sum(len(p) for p in phases)
    in_process = workers <= 1 or n_regions == 1
    pool = None
    bar = None
    if not in_process:
        # A fresh process per region: its peak memory is its own, not the largest region's
        # that the same worker ran before (freed arenas are not returned to the system).
        pool = make_executor(executor, workers, address, tasks_per_worker=1)
        if progress:
            bar = tqdm(total=n_regions, desc="GGDS chunks", unit="chunk")
    try:
        for phase in phases:
            todo = [r for r in phase if not region_progress(sc, run, r.name).get("complete")]
            jobs = {r.name: RegionJob(**base, region=r.name, keys=[list(k) for k in r.keys],
                                      finished=[list(k) for k in sorted(finished)],
                                      log=str(sc.run_files(run).dir / "logs" /
                                              f"{r.name or 'scene'}.log")) for r in todo}
            if in_process:
                for r in todo:
                    summaries[r.name] = run_region(jobs[r.name], term_state=term_state,
                                                   progress=progress, log=log)
                    _record_task(sc, run, r.name, summaries[r.name])
                    finished.update(r.keys)
            else:
                summaries.update(_run_pool(pool, jobs, retries, sc, run, bar, log))
                finished.update(k for r in todo for k in r.keys)
    finally:
        if pool is not None:
            pool.close()
        if bar is not None:
            bar.close()
    regions_done = {name: region_progress(sc, run, name) for name in plan["regions"]}
    totals = run_summary(regions_done)
    plan["complete"] = totals["complete"]
    write_plan(sc, run, plan)
    refresh_run_layer(sc, run)
    summary = {"run": run, "regions": len(plan["regions"]), "complete": totals["complete"],
               "steps": totals["steps"], "seconds": round(totals["seconds"], 1),
               "s_per_step": round(totals["s_per_step"], 3), "surfels": totals["surfels"],
               "wall_s": round(time.perf_counter() - t0, 1), **totals["metrics"]}
    tasks = {k: _task_figures(sc, run, k, summaries.get(k)) for k in regions_done}
    rss = [t["peak_rss_mb"] for t in tasks.values() if t.get("peak_rss_mb")]
    if in_process:
        rss.append(peak_rss_mb())
    summary["worker_peak_rss_mb"] = max(rss) if rss else None
    # seconds outside the steps (run_ggds' phases_s) summed over the regions: CPU-side
    # totals, which exceed the wall time when regions ran side by side or in earlier calls
    spent = {}
    for t in tasks.values():
        for k, v in (t.get("phases_s") or {}).items():
            spent[k] = round(spent.get(k, 0.0) + v, 2)
    if spent:
        summary["phases_s"] = spent
    if any(plan["regions"]):   # chunk regions (a whole-scene region is the summary itself)
        summary["per_region"] = {
            k: {**{kk: v.get(kk) for kk in ("stepsDone", "complete", "surfels", "seconds",
                                            "metrics")},
                **tasks[k]}
            for k, v in regions_done.items()}
    write_json(sc.run_files(run).dir / "summary.json", summary)
    return summary


TASK_FIGURES = ("wall_s", "cpu_s", "context", "context_colour_start", "views",
                "neighbour_views", "fit_views", "peak_rss_mb", "phases_s")


def _record_task(sc, run: str, region: str, summary: dict) -> None:
    """Keep a finished region's task figures in its task.json as soon as it returns, so a
    later (resumed) invocation reports them too (``summary``: run_region's, which says
    whether the region completed)."""
    if region and summary.get("complete"):
        write_region_task(sc, run, region, {k: summary.get(k) for k in TASK_FIGURES})


def _task_figures(sc, run: str, region: str, summary: dict | None) -> dict:
    """A region's task figures: this invocation's, else those an earlier one recorded."""
    return {k: (summary if summary is not None else region_task(sc, run, region)).get(k)
            for k in TASK_FIGURES}


def _run_pool(pool, jobs: dict, retries: int, sc, run, bar, log) -> dict:
    """One phase's regions on an executor; a region that fails after its retries stops the
    run with one line naming it (the scene stays valid; --resume continues)."""
    attempts = {name: 0 for name in jobs}
    waiting = list(jobs)
    running = set()
    out = {}
    # A phase of fewer regions than workers (a 2×2 grid has one region per phase) gives
    # each region the idle workers' cores.
    share = getattr(pool, "threads", None)
    threads = (max(share, share * pool.capacity // len(jobs))
               if share and 0 < len(jobs) < pool.capacity else None)
    while waiting or running:
        while waiting and len(running) < pool.capacity:
            name = waiting.pop(0)
            attempts[name] += 1
            pool.submit(name, jobs[name].payload(), isolated=attempts[name] > 1, threads=threads)
            running.add(name)
        for name, status, value in pool.poll(timeout=0.5):
            running.discard(name)
            if status == OK:
                out[name] = value
                _record_task(sc, run, name, value)
                refresh_run_layer(sc, run)
                if bar is not None:
                    bar.update(1)
                continue
            if status == SUSPECT:
                attempts[name] -= 1
                waiting.insert(0, name)
                continue
            deterministic = status == ERROR and str(value).startswith("InputError")
            if attempts[name] <= retries and not deterministic:
                log(f"ggds: retry {attempts[name]}/{retries}: {name}: {value}")
                waiting.insert(0, name)
                continue
            raise InputError(f"GGDS chunk {name or 'scene'} failed"
                             f"{' after %d attempts' % attempts[name] if attempts[name] > 1 else ''}"
                             f": {value} (the scene is valid; continue with --resume; log: "
                             f"{jobs[name].log})")
    return out
