"""Chunk-wise GGDS: a scene of any extent optimised region by region, each region conditioned
on its neighbours (the paper's chunk-wise outpainting, p(V_e | M_e, V_{e-1}), carried through
surfels and GGDS).

A region is a set of chunks optimised together: the whole scene when it is small (mode
"auto" with at most ``max_scene_chunks`` chunks: as fast and at least as good), else one chunk.
A region trains its own surfels and renders, frozen, its neighbours' surfels within ``band_m``
of it — the neighbour's optimised surfels when the neighbour has finished in this run, its
initial ones otherwise — so views near a border see a complete scene and the new chunk
continues its finished neighbours. Its views lie on the lanes inside it (``views_per_chunk``
per chunk), its proxy G-buffers come from the 3×3 proxy neighbourhood, and image losses
compare only pixels whose proxy surface lies within the loaded surfels. So the views,
surfels and memory of a region do not depend on the size of the scene.

Regions run in phases: the chunks of one phase share no overlap band (2×2 parity classes of
the grid; two phases along a corridor), so a phase's regions run in parallel (a local process
pool or Ray, lsd3d_usd.execution) and each region runs after the neighbours it conditions on.
A region task is idempotent and resumable (its checkpoint), so a killed run resumes with
finished regions untouched. The driver holds no surfel arrays.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from lsd3d_usd import configtree as ct
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.settings import RegionConfig
from lsd3d_usd.memtune import peak_rss_mb

TASK_TARGET = "lsd3d_usd.ggds.regions.driver:run_region_task"


@dataclass(frozen=True)
class Region:
    keys: tuple       # sorted chunk keys
    name: str         # "" for a whole-scene region (files in the run folder), chunk_<i>_<j>

    def bounds(self, chunk_size: float) -> tuple[float, float, float, float]:
        k = np.asarray(self.keys, np.float64)
        return (float(k[:, 0].min() * chunk_size), float(k[:, 1].min() * chunk_size),
                float((k[:, 0].max() + 1) * chunk_size), float((k[:, 1].max() + 1) * chunk_size))

    def neighbourhood(self) -> set:
        return {(i + di, j + dj) for i, j in self.keys for di in (-1, 0, 1) for dj in (-1, 0, 1)}


def phases_from_plan(plan: dict) -> list[list[Region]]:
    """The phases a run recorded in its plan (run.json)."""
    return [[Region(tuple(tuple(k) for k in plan["regions"][name]), name) for name in phase]
            for phase in plan["phases"]]


def plan_regions(chunks, cfg: RegionConfig) -> list[list[Region]]:
    """Phases of regions over the scene's chunks ({key: info with "count"}, or keys; see the
    module doc)."""
    counts = chunks if isinstance(chunks, dict) else {k: {} for k in chunks}
    keys = sorted(tuple(int(v) for v in k) for k in counts)
    if not keys:
        raise InputError("GGDS: the scene has no surfel chunks")
    mode = cfg.mode
    if mode == "auto":
        total = sum(int((v or {}).get("count", 0)) for v in counts.values())
        small = len(keys) <= cfg.max_scene_chunks and total <= cfg.max_scene_surfels
        mode = "scene" if small else "chunk"
    if mode == "scene":
        return [[Region(tuple(keys), "")]]
    phases = {}
    for k in keys:
        phases.setdefault((k[0] % 2, k[1] % 2), []).append(
            Region((k,), S.chunk_prim_name(*k).lower()))
    return [phases[p] for p in sorted(phases, key=lambda p: (p[1], p[0]))]


def region_seed(seed: int, region: Region) -> int:
    if not region.name:
        return int(seed)
    ss = np.random.SeedSequence([int(seed)] + [int(v) & 0xFFFFFFFF for k in region.keys for v in k])
    return int(ss.generate_state(1)[0] % (2**31))


def region_views(layout, g, seed: int, region: Region) -> tuple[list, list]:
    """(training views, held-out views) GGDS samples for ``region`` of a run with config ``g``
    and scene seed ``seed``: ``g.views`` over the whole scene for a whole-scene region, else
    ``views_per_chunk`` per chunk standing on lanes inside the region or up to
    ``view_margin_m`` outside it (so border surfels are seen from both sides), held-out views
    inside it (InputError when it holds no lane). The scene's cameras layer
    (views.scene_cameras) authors the same views; run_region then trains a chunk region on
    those that see any of its surfels (sampling.views_seeing), with ``share_views`` also on
    its neighbours' that stand near it (neighbour_views)."""
    from lsd3d_usd.conditioning.views import sample_views
    rseed = region_seed(seed, region)
    w, h = g.resolution
    whole = not region.name
    n_views = g.views if whole else g.regions.views_per_chunk * len(region.keys)
    bounds = around = None
    if not whole:
        bounds = region.bounds(float(layout.chunk_size))
        m = g.regions.view_margin_m
        around = (bounds[0] - m, bounds[1] - m, bounds[2] + m, bounds[3] + m)
    views = sample_views(layout, n_views, w, h, seed=rseed, novel_frac=g.novel_frac,
                         fov_deg=g.fov_deg, region=around, clip=not whole,
                         novel_style=g.novel_style, stratified=g.stratified_views)
    held = sample_views(layout, g.held_out, w, h, seed=rseed + 7919, novel_frac=0.5,
                        fov_deg=g.fov_deg, region=bounds, clip=not whole)
    return views, held


def neighbour_views(layout, g, seed: int, region: Region, chunks) -> list:
    """The views the chunk regions next to ``region`` (those of ``chunks``, the scene's
    surfel chunks) sample for training (region_views) that stand inside it or within
    ``view_margin_m`` of it. Each region samples its views over itself and that margin, so a
    surfel near a border is seen from beyond it only by views reaching ``view_margin_m``
    across, and at half the density of a whole-scene sampling; training a region also on its
    neighbours' views there gives its border surfels about the views its interior has
    (docs/large_scale.md, "Seams"). A neighbour whose views stand denser than the region's own
    (a chunk holding only the end of a lane) is thinned to the region's density, so no
    neighbour floods it with views."""
    from lsd3d_usd.conditioning.views import lane_length_inside
    size, m = float(layout.chunk_size), g.regions.view_margin_m

    def grown(r):
        x0, y0, x1, y1 = r.bounds(size)
        return x0 - m, y0 - m, x1 + m, y1 + m
    x0, y0, x1, y1 = box = grown(region)
    own = lane_length_inside(layout, box) / len(region.keys)    # lane metres per own view set
    out = []
    for key in sorted(region.neighbourhood() - set(region.keys)):
        if key not in chunks:
            continue
        other = Region((key,), S.chunk_prim_name(*key).lower())
        try:
            views, _ = region_views(layout, g, seed, other)
        except InputError:      # no lane in that chunk: it has no views
            continue
        keep = min(1.0, lane_length_inside(layout, grown(other)) / max(own, 1e-9))
        draw = np.random.default_rng(region_seed(seed, other) + 7_368_787).uniform(size=len(views))
        out += [v for v, u in zip(views, draw) if u < keep
                and x0 <= v.camera.center[0] <= x1 and y0 <= v.camera.center[1] <= y1]
    return out


def region_fit_views(layout, g, seed: int, region: Region) -> list:
    """Extra views for a region's world-space colour start (never trained on). A whole-scene
    region: ``world_init_views`` × its training views, sampled like them (more directions per
    surfel for the fit). A chunk region: ``fit_inner_frac`` × its training views, sampled like
    them, and of ``fit_view_frac × views_per_chunk`` per chunk sampled on lanes up to
    ``fit_margin_m`` outside it, those standing beyond the training views' margin (a surfel
    near a border is seen by a whole-scene fit from both sides and from afar; the region's
    training views reach only ``view_margin_m`` across, so without these its colour would be
    fitted from one side)."""
    from lsd3d_usd.conditioning.views import sample_views
    r = g.regions
    w, h = g.resolution
    rseed = region_seed(seed, region)

    def sample(n, seed_, around=None):
        if n <= 0:
            return []
        try:
            return sample_views(layout, n, w, h, seed=seed_, novel_frac=g.novel_frac,
                                fov_deg=g.fov_deg, region=around, clip=around is not None,
                                novel_style=g.novel_style, stratified=g.stratified_views)
        except InputError:      # no lane within ``around``
            return []
    if not region.name:
        return sample(int(round(g.world_init_views * g.views)), rseed + 104729)
    x0, y0, x1, y1 = region.bounds(float(layout.chunk_size))
    m, inner = r.fit_margin_m, r.view_margin_m
    views = sample(int(round(r.fit_inner_frac * r.views_per_chunk * len(region.keys))),
                   rseed + 15485863, (x0 - inner, y0 - inner, x1 + inner, y1 + inner))
    if m <= inner:
        return views
    outer = sample(int(round(r.fit_view_frac * r.views_per_chunk * len(region.keys))),
                   rseed + 104729, (x0 - m, y0 - m, x1 + m, y1 + m))
    return views + [v for v in outer if not (x0 - inner <= v.camera.center[0] <= x1 + inner
                                             and y0 - inner <= v.camera.center[1] <= y1 + inner)]


# ---------------------------------------------------------------------------- inputs
def _proxy_neighbourhood(proxy_path, keys):
    """Proxy arrays of ``keys`` (those that exist) concatenated, and each chunk's face offset."""
    from lsd3d_usd.proxy.usdio import proxy_arrays, read_chunk_map
    have = {S.parse_chunk_prim_name(n) for n in read_chunk_map(proxy_path)}
    V, F, ids, offsets, vb, fb = [], [], [], {}, 0, 0
    for key in sorted(k for k in keys if k in have):
        v, f, c = proxy_arrays(proxy_path, [key])
        offsets[key] = fb
        V.append(v)
        F.append(f + vb)
        ids.append(c)
        vb += len(v)
        fb += len(f)
    if not F:
        raise InputError(f"{proxy_path}: no proxy geometry around chunks {sorted(keys)}")
    return (np.concatenate(V), np.concatenate(F), np.concatenate(ids)), offsets


def region_surfels(sc: S.Scene, region: Region, offsets: dict):
    """The region's initial surfels (chunks in order), their owner ranges, and their seed
    faces as indices into the neighbourhood's proxy arrays (-1 where unknown)."""
    from lsd3d_usd.splats import chunkio
    from lsd3d_usd.splats.field import SurfelField
    root = sc.layer_path("surfels")
    have = chunkio.read_chunk_map(root)
    fields, owners, faces, n = [], [], [], 0
    for key in region.keys:
        if key not in have:
            continue
        f = chunkio.read_chunk(root, key)
        seed = chunkio.read_seed_faces(root, key)
        if seed is None:
            face = np.full(f.n, -1, np.int64)
        else:
            chunks, local = seed
            base = np.array([offsets.get((int(a), int(b)), -1) for a, b in chunks], np.int64)
            face = np.where(base >= 0, base + local, -1)
        fields.append(f)
        faces.append(face)
        owners.append((key, n, n + f.n))
        n += f.n
    if not fields:
        return None, [], None
    return SurfelField.concat(fields), owners, np.concatenate(faces)


def region_context(sc: S.Scene, run: str, region: Region, finished: set, band_m: float,
                   chunk_size: float):
    """(frozen surfels of the neighbours within ``band_m`` of the region: this run's result
    for finished neighbours, the initial surfels otherwise; (n,) bool: which rows are
    initial), or None when there are none."""
    from lsd3d_usd.ggds.run.store import run_layer_path
    from lsd3d_usd.splats import chunkio
    from lsd3d_usd.splats.field import SurfelField
    if band_m <= 0:
        return None
    root = sc.layer_path("surfels")
    have = chunkio.read_chunk_map(root)
    x0, y0, x1, y1 = region.bounds(chunk_size)
    parts, initial = [], []
    for key in sorted(region.neighbourhood() - set(region.keys)):
        if key not in have:
            continue
        runs = [run_layer_path(sc, run)] if key in finished else []
        f = chunkio.read_chunk(root, key, runs)
        p = f.positions
        near = ((p[:, 0] >= x0 - band_m) & (p[:, 0] <= x1 + band_m) &
                (p[:, 1] >= y0 - band_m) & (p[:, 1] <= y1 + band_m))
        if near.any():
            parts.append(f.subset(np.flatnonzero(near)))
            initial.append(np.full(parts[-1].n, key not in finished))
    if not parts:
        return None
    return SurfelField.concat(parts, drop_mismatched_semantics=True), np.concatenate(initial)


# ---------------------------------------------------------------------------- a region task
def run_region(job: dict, *, term_state=None, progress: bool = False, log=None,
               refresh: bool = True) -> dict:
    """Optimise one region (``job``: the plain data run_regions builds). Returns its summary."""
    from lsd3d_usd.env.exr import write_env
    from lsd3d_usd.conditioning.shadow import shadow_map
    from lsd3d_usd.ggds.settings import GGDSConfig
    from lsd3d_usd.conditioning.light import env_params, scene_light
    from lsd3d_usd.ggds.priors.registry import PriorConfig, make_prior
    from lsd3d_usd.ggds.run.lifecycle import GGDSInputs, run_ggds
    from lsd3d_usd.ggds.run.store import RegionRunStore
    from lsd3d_usd.layout.usdio import read_layout
    log = log or (lambda *a: None)
    sc = S.Scene(job["scene"])
    region = Region(tuple(tuple(k) for k in job["keys"]), job["region"])
    g = ct.from_dict(GGDSConfig, job["ggds"])
    rcfg = g.regions
    seed = int(job["seed"])
    layout = read_layout(sc.layer_path("layout"))
    size = float(layout.chunk_size)
    proxy, offsets = _proxy_neighbourhood(sc.layer_path("proxy"), region.neighbourhood())
    field, owners, face = region_surfels(sc, region, offsets)
    if field is None:
        return skip_region(sc, job["run"], region, "no surfels")
    g = replace(g, seed=region_seed(seed, region))
    whole = not region.name
    bounds = region.bounds(size)
    try:
        views, held = region_views(layout, g, seed, region)
    except InputError:
        if whole:
            raise
        log(f"ggds: {region.name}: no drivable lane inside: its initial surfels are kept")
        return skip_region(sc, job["run"], region, "no drivable lane inside")
    if not whole:
        from lsd3d_usd.conditioning.visibility import views_seeing
        own = {id(v) for v in views}
        if rcfg.share_views:
            from lsd3d_usd.splats.chunkio import read_chunk_map
            views = views + neighbour_views(layout, g, seed, region,
                                            set(read_chunk_map(sc.layer_path("surfels"))))
        views = views_seeing(views, field.positions)
        shared = sum(id(v) not in own for v in views)
        if not views:
            log(f"ggds: {region.name}: no training view sees its surfels: they are kept")
            return skip_region(sc, job["run"], region, "no training view sees its surfels")
        fit_views = views_seeing(region_fit_views(layout, g, seed, region),
                                 field.positions)
    else:
        fit_views = region_fit_views(layout, g, seed, region)
    params = env_params(job["env"], seed)
    ew, eh = job["env"]["resolution"]
    light = scene_light(params, write_env(params, sc.textures_dir, int(ew), int(eh)))
    context = None if whole else region_context(sc, job["run"], region,
                                                {tuple(k) for k in job["finished"]},
                                                rcfg.band_m, size)
    context, context_initial = context if context is not None else (None, None)
    band = rcfg.band_m
    focus = None if whole else (bounds[0] - band, bounds[1] - band, bounds[2] + band,
                                bounds[3] + band)
    inputs = GGDSInputs(field, proxy, views, held, light.prior_env, light.background,
                        shadow_map(proxy[0], proxy[1], light.sun_direction), face,
                        context=context, focus=focus, fit_views=fit_views,
                        context_start=context_initial if rcfg.fit_context else None)
    n_context = int(context.n) if context is not None else 0
    del field, context        # run_ggds takes them over (GGDSInputs): not kept alive here
    store = RegionRunStore(sc, job["run"], region.name, owners, refresh=refresh,
                           checkpoint_meta={"keys": [list(k) for k in region.keys]})
    resume = store.has_checkpoint()
    prior = make_prior(ct.from_dict(PriorConfig, job["prior"]), seed=seed)
    t0, c0 = time.perf_counter(), _cpu_seconds()
    summary = run_ggds(inputs, prior, g, store, resume=resume, stop_at=job.get("stop_at"),
                       keep_checkpoint=job.get("keep_checkpoint", False), term_state=term_state,
                       progress=progress, log=log)
    summary.update(region=region.name, keys=[list(k) for k in region.keys],
                   context=n_context,
                   wall_s=round(time.perf_counter() - t0, 2), views=len(views),
                   neighbour_views=0 if whole else shared,
                   fit_views=len(fit_views),
                   cpu_s=round(_cpu_seconds() - c0, 2))
    return summary


def skip_region(sc: S.Scene, run: str, region: Region, reason: str) -> dict:
    """A region GGDS cannot optimise (no surfels, or no lane to place views on) keeps its
    initial surfels; recorded as done so the run can complete."""
    from lsd3d_usd.ggds.run.store import region_dir, write_json
    progress = {"complete": True, "skipped": reason, "stepsDone": 0,
                "keys": [list(k) for k in region.keys], "surfels": 0}
    write_json(region_dir(sc, run, region.name) / "progress.json", progress)
    return {"region": region.name, **progress}


def run_region_task(payload: dict) -> dict:
    """Executor entry point (a worker process): run one region, log to the job's log file."""
    import lsd3d_usd  # noqa: F401  registers the schema before any stage is opened
    from lsd3d_usd.execution import task_log
    with task_log(payload["log"], payload["region"]) as log:
        summary = run_region(payload, log=log, refresh=False)
        summary["peak_rss_mb"] = peak_rss_mb()
        log(f"done: {summary}")
    return summary


def _cpu_seconds() -> float:
    """CPU time of this process (all threads) so far: comparable across worker counts."""
    import resource
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


# ---------------------------------------------------------------------------- the driver
def run_regions(sc: S.Scene, run: str, *, phases: list, ggds: dict, prior: dict,
                env: dict, seed: int, resume: bool = False, stop_at: int | None = None,
                keep_checkpoint: bool = False, workers: int = 1, executor: str = "local",
                address: str | None = None, retries: int = 2, term_state=None,
                progress: bool = True, log=print) -> dict:
    """Run every unfinished region phase by phase (in this process when one worker or one
    region; else on a local pool or Ray), updating the run layer as regions finish. Returns
    the run summary (also ggds/<run>/summary.json)."""
    from lsd3d_usd.ggds.run.store import (aggregate_metrics, read_plan, refresh_run_layer, region_progress, write_plan)
    plan = read_plan(sc, run)
    t0 = time.perf_counter()
    finished = {tuple(k) for name in plan["regions"] if region_progress(sc, run, name)
                .get("complete") for k in plan["regions"][name]}
    summaries = {}
    base = {"target": TASK_TARGET, "scene": str(sc.root), "run": run, "ggds": ggds,
            "prior": prior, "env": env, "seed": seed, "stop_at": stop_at,
            "keep_checkpoint": keep_checkpoint}
    n_regions = sum(len(p) for p in phases)
    in_process = workers <= 1 or n_regions == 1
    pool = None
    bar = None
    if not in_process:
        from lsd3d_usd.execution import make_executor
        # A fresh process per region: its peak memory is its own, not the largest region's
        # that the same worker ran before (freed arenas are not returned to the system).
        pool = make_executor(executor, workers, address, tasks_per_worker=1)
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=n_regions, desc="GGDS chunks", unit="chunk")
    try:
        for phase in phases:
            todo = [r for r in phase if not region_progress(sc, run, r.name).get("complete")]
            jobs = {r.name: {**base, "region": r.name, "keys": [list(k) for k in r.keys],
                             "finished": [list(k) for k in sorted(finished)],
                             "log": str(sc.run_files(run).dir / "logs" /
                                        f"{r.name or 'scene'}.log")} for r in todo}
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
    complete = all(p.get("complete") for p in regions_done.values())
    plan["complete"] = complete
    write_plan(sc, run, plan)
    refresh_run_layer(sc, run)
    done = [p for p in regions_done.values() if p.get("complete")]
    steps = [int(p.get("stepsDone", 0)) for p in regions_done.values() if not p.get("skipped")]
    seconds = sum(float(p.get("seconds", 0.0)) for p in regions_done.values())
    summary = {"run": run, "regions": len(plan["regions"]), "complete": complete,
               "steps": min(steps) if steps else 0, "seconds": round(seconds, 1),
               "s_per_step": round(seconds / max(sum(steps), 1), 3),
               "surfels": int(sum(p.get("surfels", 0) for p in regions_done.values())),
               "wall_s": round(time.perf_counter() - t0, 1),
               **aggregate_metrics([p.get("metrics") or {} for p in done],
                                   [p.get("surfels", 0) for p in done])}
    tasks = {k: _task_figures(sc, run, k, summaries.get(k)) for k in regions_done}
    rss = [t["peak_rss_mb"] for t in tasks.values() if t.get("peak_rss_mb")]
    if in_process:
        rss.append(peak_rss_mb())
    summary["worker_peak_rss_mb"] = max(rss) if rss else None
    if any(plan["regions"]):   # chunk regions (a whole-scene region is the summary itself)
        summary["per_region"] = {
            k: {**{kk: v.get(kk) for kk in ("stepsDone", "complete", "surfels", "seconds",
                                            "metrics")},
                **tasks[k]}
            for k, v in regions_done.items()}
    from lsd3d_usd.ggds.run.store import write_json
    write_json(sc.run_files(run).dir / "summary.json", summary)
    return summary


TASK_FIGURES = ("wall_s", "cpu_s", "context", "context_colour_start", "views",
                "neighbour_views", "fit_views", "peak_rss_mb")


def _record_task(sc, run: str, region: str, summary: dict) -> None:
    """Keep a finished region's task figures in its task.json as soon as it returns, so a
    later (resumed) invocation reports them too (``summary``: run_region's, which says
    whether the region completed)."""
    from lsd3d_usd.ggds.run.store import write_region_task
    if region and summary.get("complete"):
        write_region_task(sc, run, region, {k: summary.get(k) for k in TASK_FIGURES})


def _task_figures(sc, run: str, region: str, summary: dict | None) -> dict:
    """A region's task figures: this invocation's, else those an earlier one recorded."""
    from lsd3d_usd.ggds.run.store import region_task
    return {k: (summary if summary is not None else region_task(sc, run, region)).get(k)
            for k in TASK_FIGURES}


def _run_pool(pool, jobs: dict, retries: int, sc, run, bar, log) -> dict:
    """One phase's regions on an executor; a region that fails after its retries stops the
    run with one line naming it (the scene stays valid; --resume continues)."""
    from lsd3d_usd.execution import ERROR, OK, SUSPECT
    from lsd3d_usd.ggds.run.store import refresh_run_layer
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
            pool.submit(name, jobs[name], isolated=attempts[name] > 1, threads=threads)
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
                             f"{jobs[name]['log']})")
    return out
