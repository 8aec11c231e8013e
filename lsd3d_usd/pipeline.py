"""`generate`: layout → proxy → env → surfels → actors → cameras → GGDS, each step writing its own layer.
It composes the steps and nothing else: what a step computes lives in its package.

Steps whose inputs did not change are reused (proxy chunks by content hash, the env EXR and
layer by parameter hash, the surfel layer by the hash of its inputs), so re-running `generate`
on a scene only does the work that is new. Every check that can fail on bad input runs before
anything is written. A step that would change a layer that active GGDS runs were optimised on
refuses (or, with RunOptions.retire_runs, mutes those runs and marks them stale) — see
scene.py. GGDS writes a new run layer, or with --resume continues the newest unfinished run
with its own recorded configuration.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from pxr import UsdLux

from lsd3d_usd import configtree as ct
from lsd3d_usd import scene as S
from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors import people as P
from lsd3d_usd.actors.compose import add_actors
from lsd3d_usd.conditioning.light import colour_by_light, env_params, scene_light
from lsd3d_usd.config import GenerateConfig
from lsd3d_usd.env import write_env, write_env_layer
from lsd3d_usd.env.usdlayer import author_far_field
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.losses.terms import LOSSES
from lsd3d_usd.ggds.priors.base import Prior
from lsd3d_usd.ggds.priors.registry import PRIORS, check_prior, make_prior
from lsd3d_usd.ggds.regions.driver import run_regions
from lsd3d_usd.ggds.regions.plan import phases_from_plan, plan_regions
from lsd3d_usd.ggds.run.store import read_plan, region_progress, write_plan
from lsd3d_usd.hashing import content_hash
from lsd3d_usd.layout import generator
from lsd3d_usd.layout.model import DRIVABLE_TYPES
from lsd3d_usd.layout.usdio import read_layout, write_layout
from lsd3d_usd.memtune import peak_rss_mb, release_free_memory
from lsd3d_usd.proxy.usdio import build_proxy_layer, ground_level, layout_hash
from lsd3d_usd.render import precompile
from lsd3d_usd.splats import chunkio
from lsd3d_usd.splats.chunkio import read_chunk_map
from lsd3d_usd.splats.initial import write_initial_surfels
from lsd3d_usd.views.scene_cameras import write_scene_cameras

SURFELS_VERSION = "surfels-v7"   # v7: Points preview in the chunk files (splats.preview); v6: density weights on faces split to 2 m² (splats.initial); v5: drivable lanes only
FAR_FIELD_VERSION = "far-field-v1"   # the env layer records the ground beyond the scene (env.farfield)


@dataclass
class RunOptions:
    """How to run `generate` (not what to make: that is GenerateConfig)."""
    out: Path
    resume: bool = False
    force: bool = False
    retire_runs: bool = False
    keep_checkpoint: bool = False
    progress: bool = True
    log: Callable = print
    workers: int | None = None          # GGDS regions in parallel (None: one per core)
    executor: str = "local"             # "local" process pool or "ray"
    address: str | None = None          # Ray cluster address (executor "ray")
    # Configuration keys the user gave explicitly (flags, --set, config file). With --resume,
    # any of them that differs from the run's recorded configuration is refused; None (a
    # library call): the keys whose value differs from the default.
    explicit: frozenset | None = None


@dataclass
class Plan:
    """What `generate` will do, worked out before anything is written."""
    cfg: GenerateConfig
    layout: object
    source: Path | None
    layout_hash: str
    env_params: object
    env_hash: str
    surfels_hash: str
    resume_run: str | None = None
    stop_at: int | None = None
    term_state: dict | None = None


# ------------------------------------------------------------------ checks before writing
def read_layout_for(cfg: GenerateConfig):
    """The layout the configuration names (read) or describes (generated)."""
    if cfg.layout is not None:
        if not Path(cfg.layout).is_file():
            raise InputError(f"--layout {cfg.layout}: no such file")
        layout, source = read_layout(cfg.layout), Path(cfg.layout)
    else:
        layout, source = generator.generate(cfg.seed, cfg.extent, cfg.style), None
    if not layout.drivable_lanes():
        where = cfg.layout or "generated layout"
        raise InputError(f"{where}: the layout has no drivable lanes (of type "
                         f"{', '.join(DRIVABLE_TYPES)}; GGDS places its cameras along them, and "
                         "the proxy needs roads)")
    return layout, source


def check_config(cfg: GenerateConfig, run: RunOptions | None = None) -> dict | None:
    """Cross-key checks and the prior / loss files, before anything is written. Returns the
    loss terms' prepared state (e.g. LPIPS weights read once), or None without GGDS."""
    g = cfg.ggds
    if run is not None and run.resume and run.force:
        raise InputError("--resume and --force exclude each other")
    if g.lpips_lin is not None and g.lpips is None:
        raise InputError("--lpips-lin needs --lpips BACKBONE.pth")
    for flag, f in (("--lpips", g.lpips), ("--lpips-lin", g.lpips_lin)):
        if f is not None and not Path(f).is_file():
            raise InputError(f"{flag} {f}: no such file (LPIPS loads local weights only; "
                             "nothing is downloaded)")
    lo, hi = g.elevated_heights
    if lo > hi:
        raise InputError(f"ggds.elevated_heights {lo:g}x{hi:g}: the lower height exceeds the "
                         "upper")
    if g.steps == 0 and not (run and run.resume):
        return None
    check_prior(cfg.prior)
    weight = g.weights.get("perceptual")
    if weight is None:   # the prior's default, known without loading it
        weight = PRIORS.get(cfg.prior.kind).default_weight("perceptual")
    if g.lpips is not None and (not g.perceptual or not weight > 0):
        raise InputError(f"--lpips {g.lpips}: the perceptual weight is 0 (--no-perceptual, or "
                         "the procedural prior's default), so LPIPS would not be used; "
                         "pass --perceptual-weight W")
    state = {}
    if g.lpips is not None:   # keys, shapes, lin weights checked now; loaded once
        state["perceptual"] = LOSSES.get("perceptual").setup(g, None)
    return state


def _surfels_hash(layout_hash: str, env_hash: str, cfg: GenerateConfig) -> str:
    return content_hash(SURFELS_VERSION, layout_hash, cfg.proxy.as_dict(), env_hash, cfg.seed,
                 ct.to_dict(cfg.surfels), ct.to_dict(cfg.splats))


def _prior_knows_ground(prior_cfg) -> bool:
    """Whether the configured prior (a PriorConfig) says what its open ground looks like
    (Prior.ground_albedo), known without loading it."""
    return PRIORS.get(prior_cfg.kind).prior_type().ground_albedo is not Prior.ground_albedo


def _env_layer_hash(params_hash: str, layout_hash: str, cfg: GenerateConfig) -> str:
    """The env layer's inputs: the environment, and what its far field is made of (the
    proxy's ground level: the layout and proxy settings; the terrain colour of a prior that
    says what it is, with its seed)."""
    colour = (cfg.prior.name, cfg.seed) if _prior_knows_ground(cfg.prior) else "env ground colour"
    return content_hash(FAR_FIELD_VERSION, params_hash, layout_hash, cfg.proxy.as_dict(), colour)


def plan(cfg: GenerateConfig, run: RunOptions) -> Plan:
    """Read and check everything; decide resume; nothing written."""
    sc = S.Scene.open(run.out) if (Path(run.out) / S.ROOT_FILE).is_file() else None
    resume_run, stop_at = None, None
    if run.resume:
        if sc is None:
            raise InputError(f"{run.out}: no scene to resume (no {S.ROOT_FILE})")
        cfg, resume_run, stop_at = _resume_config(sc, cfg, run)
    term_state = check_config(cfg, run)
    layout, source = read_layout_for(cfg)
    lhash = layout_hash(layout)
    params = env_params(ct.to_dict(cfg.env), cfg.seed, run.log)
    w, h = cfg.env.resolution
    ehash = params.content_hash(w, h)
    shash = _surfels_hash(lhash, ehash, cfg)
    return Plan(cfg, layout, source, lhash, params, _env_layer_hash(ehash, lhash, cfg), shash,
                resume_run, stop_at, term_state)


def _resume_config(sc: S.Scene, cfg: GenerateConfig, run: RunOptions):
    """The newest unfinished run's recorded configuration; explicit conflicting keys refused."""
    names = sc.unfinished_runs()
    if not names and not sc.runs():
        # killed before GGDS started: what there is to continue is the plain re-run, which
        # reuses every finished step
        run.log("resume: no GGDS run was started; continuing generate from the finished steps")
        return cfg, None, None
    if not names:
        raise InputError(f"{sc.root}: no unfinished GGDS run to resume")
    name = names[0]
    plan = read_plan(sc, name)
    recorded = ct.from_dict(GenerateConfig, plan["generate"])
    at = min((int(region_progress(sc, name, r).get("stepsDone", 0)) for r in plan["regions"]),
             default=0)
    stop_at = None
    explicit = run.explicit
    if explicit is None:
        explicit = frozenset(ct.diff(GenerateConfig(), cfg))
    conflicts = []
    for key, (old, new) in ct.diff(recorded, cfg).items():
        if key not in explicit:
            continue
        if key == "ggds.steps":
            if not at < new <= recorded.ggds.steps:
                raise InputError(f"--resume --steps {new}: {name} is at step {at} of "
                                 f"{recorded.ggds.steps}; give a step in between")
            stop_at = new
            continue
        conflicts.append(f"{key} {new!r} (run: {old!r})")
    if conflicts:
        raise InputError(f"--resume continues {name} with its recorded settings; conflicting: "
                         f"{', '.join(conflicts)} (drop them, or start a new run without "
                         "--resume)")
    run.log(f"resume: {name} at step {at} of {recorded.ggds.steps}, with its recorded settings")
    return recorded, name, stop_at


def prepare_scene(cfg: GenerateConfig, run: RunOptions, layout_hash: str) -> S.Scene:
    """Open or create the scene folder (refusing one that holds something else)."""
    out = Path(run.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out}: exists and is not a folder")
    for parent in out.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"-o {out}: {parent} is a file, not a folder")
            break
    if (out / S.ROOT_FILE).is_file():
        sc = S.Scene.open(out)
        sc.check_writable()
        root = S.Sdf.Layer.FindOrOpen(str(sc.root_layer_path))
        stored = S.read_provenance(root).get("layoutHash")
        if stored and stored != layout_hash and not run.force:
            raise InputError(f"{out}: holds a different scene (another layout); use --force to "
                             "rebuild it here or choose another output folder")
        return sc
    if out.exists() and any(out.iterdir()) and not run.force:
        raise InputError(f"{out}: exists and is not empty (and not a scene); use --force or "
                         "choose another output folder")
    return S.Scene.create(out, seed=cfg.seed, exist_ok=True)


def _preflight(sc: S.Scene) -> None:
    """What later steps would refuse, checked before anything changes (so a run is not
    retired, nor a layer rewritten, by a generate that then fails): the surfels layer's
    recorded chunk folder must lie inside the scene."""
    path = sc.layer_path("surfels")
    if path.is_file():
        chunkio.chunk_folder(path)


def _check_dependents(sc: S.Scene, p: Plan, run: RunOptions) -> None:
    """Refuse (or retire) active runs made on surfels / light this run would change."""
    changes = {"surfels": p.surfels_hash, "env": p.env_hash}
    stale = sc.dependent_runs(changes)
    if not stale:
        return
    changed = [k for k, v in changes.items() if sc.layer_inputs_hash(k) not in (None, v)]
    what = " and ".join(changed) or "surfels"
    if not run.retire_runs:
        raise InputError(f"{sc.root}: these settings change the scene's {what}, which GGDS "
                         f"run(s) {', '.join(stale)} were optimised on; pass --retire-runs to "
                         "rebuild them (the runs are muted and marked stale), or use another "
                         "output folder")
    sc.retire_runs(stale, f"{what} rebuilt with other inputs")
    run.log(f"retired (muted, marked stale): {', '.join(stale)}")


# ------------------------------------------------------------------------- the steps
def _layout_step(sc: S.Scene, p: Plan) -> None:
    """The layout layer is the input exactly as given (bytes copied when it is usda)."""
    dst = sc.layer_path("layout")
    if p.source is not None and p.source.suffix.lower() == ".usda" and not _composes(p.source):
        data = p.source.read_bytes()
        if not dst.is_file() or dst.read_bytes() != data:
            S.atomic_write_bytes(dst, data)
    else:
        write_layout(p.layout, dst, provenance=S.provenance(
            "layout", {"source": str(p.source) if p.source else "generator",
                       "extent": list(p.cfg.extent), "style": p.cfg.style}, seed=p.cfg.seed))
    sc.add_layer("layout")
    root = S.Sdf.Layer.FindOrOpen(str(sc.root_layer_path))
    if S.read_provenance(root).get("layoutHash") != p.layout_hash:
        S.save_layer(root, sc.root_layer_path, {"layoutHash": p.layout_hash})


def _composes(path: Path) -> bool:
    """Whether a layer names other files (sublayers, references, payloads): copied as
    bytes, those paths would resolve from layers/ instead; such a layout is flattened."""
    layer = S.Sdf.Layer.FindOrOpen(str(path))
    return layer is None or bool(layer.GetCompositionAssetDependencies())


def _proxy_step(sc: S.Scene, p: Plan, run: RunOptions) -> dict:
    rep = build_proxy_layer(p.layout, sc.layer_path("proxy"), params=p.cfg.proxy,
                            progress=run.progress)
    sc.add_layer("proxy")
    return {"built": len(rep.built), "skipped": len(rep.skipped), "seconds": round(rep.seconds, 2),
            "triangles": rep.triangles}


def _env_step(sc: S.Scene, p: Plan):
    """The EXR (cached by parameter hash) and the env layer, and the light GGDS sees."""

    w, h = p.cfg.env.resolution
    exr = write_env(p.env_params, sc.textures_dir, w, h)
    light = scene_light(p.env_params, exr)
    if sc.layer_inputs_hash("env") == p.env_hash:
        sc.add_layer("env")
        return light
    stage = S.new_stage()
    write_env_layer(stage, [p.env_params], texture_dir=sc.textures_dir, width=w, height=h,
                    layer_dir=sc.root / S.LAYERS_DIR,
                    variant_extras=lambda st, _name, _exr: author_scene_variant(
                        st, sc, p.cfg.prior, p.cfg.seed, p.env_params, light))
    sc.write_layer("env", stage, S.provenance("env", p.env_params.to_dict(), seed=p.cfg.seed,
                                               exposure=light.exposure, inputsHash=p.env_hash))
    return light


def author_scene_variant(stage, sc: S.Scene, prior_cfg, seed: int, params, light) -> None:
    """What an environment variant of a scene's env layer holds beside the map, authored where
    the stage's edit target is (the variant's edit context): the display scale the surfels
    are authored in (``light.exposure``) as the dome's standard exposure, so USD renderers and
    our views show the sky at the surfels' level, and the ground beyond the scene
    (env.farfield). `generate` authors its own variant so; `lsd3d-usd env --usd` into a
    scene's env layer authors an added variant alike (env_commands)."""
    env = stage.GetPrimAtPath(S.ENV_PATH)
    UsdLux.DomeLight_1(env.GetChild("Dome")).GetExposureAttr().Set(float(math.log2(light.exposure)))
    env.CreateAttribute("lsd3d:env:displayExposure", S.Sdf.ValueTypeNames.Float,
                        custom=True).Set(float(light.exposure))
    height, albedo = _far_field(sc, prior_cfg, seed, params, light)
    author_far_field(stage, height, albedo)


def _far_field(sc: S.Scene, prior_cfg, seed: int, params, light) -> tuple[float, np.ndarray]:
    """Height and albedo of the ground beyond the scene (env.farfield): at the proxy's ground
    level, continuing the prior's terrain where the prior says what that is (its
    ground_albedo), else in the env's ground colour."""
    proxy = sc.layer_path("proxy")
    height = ground_level(proxy) if proxy.is_file() else None
    albedo = None
    if _prior_knows_ground(prior_cfg):
        albedo = make_prior(prior_cfg, seed).ground_albedo(light.prior_env)
    if albedo is None:
        albedo = params.resolved().ground_albedo
    return (0.0 if height is None else height), np.asarray(albedo, np.float64)


def _surfel_step(sc: S.Scene, p: Plan, light, run: RunOptions) -> dict:
    """The initial surfels, chunk by chunk (splats.initial), unless they are up to date."""
    path = sc.layer_path("surfels")
    chunks = chunkio.read_chunk_map(path) if path.is_file() else {}
    folder = chunkio.chunk_folder(path) if chunks else None
    if (sc.layer_inputs_hash("surfels") == p.surfels_hash and chunks and
            all((folder / chunkio.chunk_file_name(k)).is_file() for k in chunks)):
        sc.add_layer("surfels")
        return {"reused": True, "count": int(sum(c["count"] for c in chunks.values())),
                "chunks": len(chunks)}
    t0 = time.perf_counter()
    sc.guard_step_layer("surfels", p.surfels_hash)   # (runs were retired up front if allowed)
    c = p.cfg.surfels
    info = write_initial_surfels(
        sc.layer_path("proxy"), p.layout, path,
        colour=lambda field, V, F: colour_by_light(field, light, V, F), count=c.count, density=c.density,
        max_count=c.max_count, sh_degree=c.sh_degree, seed=p.cfg.seed,
        inputs_hash=p.surfels_hash, progress=run.progress,
        preview_fraction=p.cfg.splats.preview_fraction,
        provenance=S.provenance("surfels", {**ct.to_dict(c), "splats": ct.to_dict(p.cfg.splats)},
                                seed=p.cfg.seed))
    release_free_memory()   # the chunks' temporaries; GGDS workers run beside this process
    sc.add_layer("surfels")
    return {"reused": False, **info, "init_s": round(time.perf_counter() - t0, 2)}


def _actors_step(sc: S.Scene, p: Plan, run: RunOptions) -> dict:
    """Parked and moving actors as references to the scene's own procedural vehicle assets
    (written once into assets/, so the scene folder is self-contained)."""
    folder = sc.assets_dir
    A.ensure_library(folder)
    a = p.cfg.actors
    if a.pedestrians != 0 or a.cyclists != 0:      # None: the default number of them
        kinds = P.PEDESTRIAN_KINDS + P.CYCLIST_KINDS
        missing = [k for k in kinds if not (folder / f"{k}.usda").is_file()]
        if missing:
            P.write_people_library(folder, missing)
    res = add_actors(sc, p.layout, parked=a.parked, moving=a.moving, seed=p.cfg.seed,
                     seconds=a.seconds, fps=a.fps, assets_dir=folder, pedestrians=a.pedestrians,
                     cyclists=a.cyclists)
    for note in res.notes:
        run.log(f"actors: {note}")
    return {"parked": len(res.parked), "moving": len(res.moving_kinds),
            "pedestrians": len(res.pedestrian_kinds), "cyclists": len(res.cyclist_kinds),
            "seconds": res.seconds}


def _ggds_step(sc: S.Scene, p: Plan, run: RunOptions) -> dict:
    """GGDS region by region (ggds.regions.driver): a new run, or the unfinished one resumed."""

    cfg = p.cfg
    if p.resume_run:
        name = p.resume_run
        phases = phases_from_plan(read_plan(sc, name))
    else:
        name = sc.new_run_name()
        phases = plan_regions(read_chunk_map(sc.layer_path("surfels")), cfg.ggds.regions)
        write_plan(sc, name, {
            "generate": ct.to_dict(cfg), "seed": cfg.seed, "prompt": cfg.env.prompt or "",
            "params": {**ct.to_dict(cfg.ggds), "prior": cfg.prior.name},
            "dependsOn": {"surfels": p.surfels_hash, "env": p.env_hash},
            "regions": {r.name: [list(k) for k in r.keys] for ph in phases for r in ph},
            "phases": [[r.name for r in ph] for ph in phases], "complete": False})
    n = sum(len(ph) for ph in phases)
    run.log(f"ggds: {name}: {n} region(s) in {len(phases)} phase(s)")
    return run_regions(sc, name, phases=phases, ggds=cfg.ggds, prior=cfg.prior, env=cfg.env,
                       seed=cfg.seed,
                       stop_at=p.stop_at,
                       keep_checkpoint=run.keep_checkpoint,
                       workers=run.workers or os.cpu_count() or 1, executor=run.executor,
                       address=run.address, term_state=p.term_state, progress=run.progress,
                       log=run.log)


# --------------------------------------------------------------------------- driver
def generate(cfg: GenerateConfig, run: RunOptions) -> dict:
    """Run the whole pipeline; returns a summary dict (the GGDS part also written to
    ggds/<run>/summary.json)."""
    t0 = time.perf_counter()
    p = plan(cfg, run)
    cfg = p.cfg
    sc = prepare_scene(cfg, run, p.layout_hash)
    _preflight(sc)
    if p.resume_run is None:
        _check_dependents(sc, p, run)
    timings = {}
    run.log(f"scene: {sc.root}")
    # on a fresh install, the rasteriser's kernels compile on the other core meanwhile
    background = precompile.start_for_ggds(cfg.ggds.steps, cfg.ggds.weights)
    try:
        return _generate_steps(cfg, run, p, sc, timings, t0)
    finally:
        precompile.finish(background)
        if background is not None:
            run.log(f"kernels: the rasteriser's compiled alongside in a second process "
                    f"(waited {precompile.waited_s():.1f} s for them)")


def _generate_steps(cfg, run, p, sc, timings, t0) -> dict:
    """generate's steps, layout to GGDS, on the planned scene."""
    def timed(key, fn, *a):
        t = time.perf_counter()
        out = fn(*a)
        timings[key] = time.perf_counter() - t
        return out

    timed("layout_s", _layout_step, sc, p)
    run.log(f"layout: {sum(p.layout.counts().values())} features ({len(p.layout.lanes)} lanes)")
    prep = timed("proxy_s", _proxy_step, sc, p, run)
    run.log(f"proxy: {prep['built']} chunk(s) built, {prep['skipped']} reused")
    light = timed("env_s", _env_step, sc, p)
    run.log(f"env: {p.env_params.resolved().variant_name()} (display exposure {light.exposure:.4g})")
    sinfo = timed("surfels_s", _surfel_step, sc, p, light, run)
    run.log(f"surfels: {sinfo['count']:,} in {sinfo['chunks']} chunk(s) "
            f"({'reused' if sinfo['reused'] else 'initialised'})")
    summary = {"scene": str(sc.root), "proxy": prep, "surfels": sinfo}
    a = cfg.actors
    if a.enabled and (a.parked or a.moving or a.pedestrians != 0 or a.cyclists != 0):
        summary["actors"] = timed("actors_s", _actors_step, sc, p, run)
        run.log(f"actors: {summary['actors']['parked']} parked, "
                f"{summary['actors']['moving']} moving, {summary['actors']['pedestrians']} "
                f"pedestrians, {summary['actors']['cyclists']} cyclists")
    summary["cameras"] = timed("cameras_s", write_scene_cameras, sc, p.layout, cfg, run.log)
    if cfg.ggds.steps > 0 or p.resume_run:
        summary["ggds"] = g = timed("ggds_s", _ggds_step, sc, p, run)
        if g.get("complete") and "psnr_novel" in g:
            run.log(f"ggds: {g['run']}: {g['steps']} steps, {g['s_per_step']} s/step, held-out "
                    f"PSNR {g['psnr_novel']:.2f} dB, depth err {100 * g['depth_rel_err']:.2f} %, "
                    f"normal err {g['normal_err_deg']:.2f} deg, off-surface "
                    f"{100 * g['off_surface_frac']:.2f} %")
    timings["total_s"] = time.perf_counter() - t0
    summary["timings"] = {k: round(v, 2) for k, v in timings.items()}
    summary["peak_rss_mb"] = peak_rss_mb()
    return summary
