"""One region task: optimise one region of a run (in the driver's process or a worker). Its
input is a :class:`RegionJob`, plain data an executor can hand to another process."""
from __future__ import annotations

import resource
import time
from dataclasses import dataclass, field, fields, replace

from lsd3d_usd import configtree as ct
from lsd3d_usd import registry
from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.conditioning.visibility import views_seeing
from lsd3d_usd.env.config import EnvConfig
from lsd3d_usd.errors import InputError
from lsd3d_usd.execution import task_log
from lsd3d_usd.ggds.priors.registry import PriorConfig, make_prior
from lsd3d_usd.ggds.regions.inputs import proxy_neighbourhood, region_context, region_surfels
from lsd3d_usd.ggds.regions.plan import Region, region_seed
from lsd3d_usd.ggds.regions.region_views import neighbour_views, region_fit_views, region_views
from lsd3d_usd.ggds.run.inputs import GGDSInputs
from lsd3d_usd.ggds.run.lifecycle import run_ggds
from lsd3d_usd.ggds.run.store import RegionRunStore, region_dir, write_json
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.layout.usdio import read_layout
from lsd3d_usd.memtune import peak_rss_mb
from lsd3d_usd.splats.chunkio import read_chunk_map

TASK_TARGET = "lsd3d_usd.ggds.regions.task:run_region_task"


@dataclass(kw_only=True)
class RegionJob:
    """A region of run ``run`` of the scene at ``scene``: its chunk ``keys`` and ``region``
    name ("" for a whole-scene region), the run's configuration trees (``ggds``, ``prior``,
    ``env``; plain dicts only in the payload that crosses to a worker), the scene ``seed``,
    the chunks already finished in this run (their optimised surfels condition it), where to
    stop, whether to keep the checkpoint, the log file, and the parent's portable registry
    entries (a backend or prior registered by target)."""
    scene: str
    run: str
    region: str
    keys: list
    ggds: GGDSConfig
    prior: PriorConfig
    env: EnvConfig
    seed: int
    finished: list = field(default_factory=list)
    stop_at: int | None = None
    keep_checkpoint: bool = False
    log: str | None = None
    registrations: dict = field(default_factory=dict)

    TREES = {"ggds": GGDSConfig, "prior": PriorConfig, "env": EnvConfig}

    def payload(self) -> dict:
        """The job as an executor payload (plain data naming the task function): the only
        place its configuration trees become dicts, as they cross to another process."""
        data = {f.name: getattr(self, f.name) for f in fields(self)}
        data.update({k: ct.to_dict(data[k]) for k in self.TREES})
        return {"target": TASK_TARGET, **data}

    @classmethod
    def from_payload(cls, payload: dict) -> "RegionJob":
        data = {k: v for k, v in payload.items() if k != "target"}
        data.update({k: ct.from_dict(tree, data[k]) for k, tree in cls.TREES.items()})
        return cls(**data)


def run_region(job: RegionJob, *, term_state=None, progress: bool = False, log=None,
               refresh: bool = True) -> dict:
    """Optimise one region. Returns its summary. ``refresh``: rewrite the run layer after each
    write (a single process; a pool's driver does it instead)."""
    log = log or (lambda *a: None)
    t_start = time.perf_counter()
    sc = S.Scene(job.scene)
    region = Region(tuple(tuple(k) for k in job.keys), job.region)
    g = job.ggds
    rcfg = g.regions
    seed = int(job.seed)
    layout = read_layout(sc.layer_path("layout"))
    size = float(layout.chunk_size)
    proxy, offsets = proxy_neighbourhood(sc.layer_path("proxy"), region.neighbourhood())
    field_, owners, face = region_surfels(sc, region, offsets)
    if field_ is None:
        return skip_region(sc, job.run, region, "no surfels")
    g = replace(g, seed=region_seed(seed, region))
    whole = not region.name
    bounds = region.bounds(size)
    try:
        views, held = region_views(layout, g, seed, region)
    except InputError:
        if whole:
            raise
        log(f"ggds: {region.name}: no drivable lane inside: its initial surfels are kept")
        return skip_region(sc, job.run, region, "no drivable lane inside")
    shared = 0
    if not whole:
        own = {id(v) for v in views}
        if rcfg.share_views:
            views = views + neighbour_views(layout, g, seed, region,
                                            set(read_chunk_map(sc.layer_path("surfels"))))
        views = views_seeing(views, field_.positions)
        shared = sum(id(v) not in own for v in views)
        if not views:
            log(f"ggds: {region.name}: no training view sees its surfels: they are kept")
            return skip_region(sc, job.run, region, "no training view sees its surfels")
        fit_views = views_seeing(region_fit_views(layout, g, seed, region), field_.positions)
    else:
        fit_views = region_fit_views(layout, g, seed, region)
    cond = Conditioning.of_scene(sc, proxy=proxy, prompt=job.env.prompt or "")
    context = None if whole else region_context(sc, job.run, region,
                                                {tuple(k) for k in job.finished},
                                                rcfg.band_m, size)
    context, context_initial = context if context is not None else (None, None)
    band = rcfg.band_m
    focus = None if whole else (bounds[0] - band, bounds[1] - band, bounds[2] + band,
                                bounds[3] + band)
    inputs = GGDSInputs(field=field_, conditioning=cond, views=views, held_out=held,
                        face_index=face, context=context, focus=focus, fit_views=fit_views,
                        context_start=context_initial if rcfg.fit_context else None)
    n_context = int(context.n) if context is not None else 0
    del field_, context        # run_ggds takes them over (GGDSInputs): not kept alive here
    store = RegionRunStore(sc, job.run, region.name, owners, refresh=refresh,
                           checkpoint_meta={"keys": [list(k) for k in region.keys]})
    resume = store.has_checkpoint()
    prior = make_prior(job.prior, seed=seed)
    t0, c0 = time.perf_counter(), cpu_seconds()
    inputs_s = t0 - t_start
    summary = run_ggds(inputs, prior, g, store, resume=resume, stop_at=job.stop_at,
                       keep_checkpoint=job.keep_checkpoint, term_state=term_state,
                       progress=progress, log=log)
    summary.update(region=region.name, keys=[list(k) for k in region.keys],
                   context=n_context,
                   wall_s=round(time.perf_counter() - t0, 2), views=len(views),
                   neighbour_views=shared, fit_views=len(fit_views),
                   cpu_s=round(cpu_seconds() - c0, 2))
    # the region's inputs (surfels, proxy, views, conditioning) before the run
    summary["phases_s"] = {"inputs": round(inputs_s, 2), **summary.get("phases_s", {})}
    return summary


def skip_region(sc: S.Scene, run: str, region: Region, reason: str) -> dict:
    """A region GGDS cannot optimise (no surfels, or no lane to place views on) keeps its
    initial surfels; recorded as done so the run can complete."""
    progress = {"complete": True, "skipped": reason, "stepsDone": 0,
                "keys": [list(k) for k in region.keys], "surfels": 0}
    write_json(region_dir(sc, run, region.name) / "progress.json", progress)
    return {"region": region.name, **progress}


def run_region_task(payload: dict) -> dict:
    """Executor entry point (a worker process): run one region, log to the job's log file."""
    job = RegionJob.from_payload(payload)
    registry.adopt(job.registrations)
    with task_log(job.log, job.region) as log:
        summary = run_region(job, log=log, refresh=False)
        summary["peak_rss_mb"] = peak_rss_mb()
        log(f"done: {summary}")
    return summary


def cpu_seconds() -> float:
    """CPU time of this process (all threads) so far: comparable across worker counts."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
