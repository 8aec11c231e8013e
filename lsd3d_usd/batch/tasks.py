"""Batch tasks: what runs where, and how each is identified.

A scene becomes either one ``scene`` task (``generate`` end to end) or, when it is split,
one ``chunk`` task per proxy chunk plus a ``scene`` task that depends on them. A chunk task
writes only its own chunk file (``layers/proxy_chunks/chunk_<i>_<j>.usdc``); it never touches
the proxy root layer or scene.usda, so chunk tasks of one scene can run concurrently on
different workers. When a scene's chunks are all done, the driver writes the proxy root layer
(``finalize_chunks``); the scene task then runs ``generate``, which finds every chunk (and the
root) up to date and reuses them.

Every task carries the hash of its inputs: re-running a batch skips a task whose hash is
recorded as done in the batch state (and whose outputs still exist).

``run_task`` is the one function executed on workers (process pool or Ray). It takes and
returns plain dicts, so it pickles anywhere.
"""
from __future__ import annotations

import json
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

import lsd3d_usd
from lsd3d_usd import configtree as ct
from lsd3d_usd import scene as S
from lsd3d_usd.config import GenerateConfig
from lsd3d_usd.errors import InputError
from lsd3d_usd.execution import task_log
from lsd3d_usd.hashing import content_hash, file_hash
from lsd3d_usd.pipeline import RunOptions, check_config, generate
from lsd3d_usd.proxy.chunks import ProxyBuilder
from lsd3d_usd.proxy.usdio import (
    chunk_file_hash,
    chunk_file_name,
    chunks_dir,
    layout_hash,
    write_chunk_layer,
    write_root_layer,
)
from lsd3d_usd.scene import chunk_prim_name

from .spec import BatchSpec, SceneSpec

TASK_VERSION = "batch-task-v2"
# split_chunks = "auto" splits a scene whose layout spans at least this many proxy chunks:
# below it, building the chunks in one task costs less than starting more workers.
AUTO_SPLIT_MIN_CHUNKS = 8


@dataclass(frozen=True)
class Task:
    id: str                         # "<scene>/scene" or "<scene>/chunk_<i>_<j>"
    kind: str                       # "scene" | "chunk"
    scene: str
    inputs_hash: str
    payload: dict                   # plain data for run_task
    deps: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()   # files that must exist for the task to count as done

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ScenePlan:
    scene: SceneSpec
    layout_hash: str
    chunk_keys: list[tuple[int, int]] = field(default_factory=list)
    chunk_hashes: dict = field(default_factory=dict)       # key -> chunk inputs hash
    tasks: list[Task] = field(default_factory=list)


def scene_config(options: dict):
    """The GenerateConfig of a scene's settings ({key: value}, JSON-able or checked)."""
    return ct.apply(GenerateConfig(), options, "")


def run_options(out, force: bool = False, log=None, workers: int = 1, executor: str = "local",
                address: str | None = None):
    return RunOptions(out=Path(out), force=force, progress=False, log=log or (lambda *a: None),
                      workers=workers, executor=executor, address=address)


def _json_options(options: dict) -> dict:
    return {k: (str(v) if isinstance(v, Path) else list(v) if isinstance(v, tuple) else v)
            for k, v in options.items()}


def read_layout_for(cfg):
    # local import: heavy, or only on this path
    from lsd3d_usd.pipeline import read_layout_for
    return read_layout_for(cfg)[0]


def chunk_file(scene_out: Path, key) -> Path:
    return chunks_dir(Path(scene_out) / S.LAYERS_DIR / S.STEP_LAYERS["proxy"]) / chunk_file_name(*key)


def plan_scene(sc: SceneSpec, logs_dir: Path, executor: str = "local",
               address: str | None = None, layouts: dict | None = None) -> ScenePlan:
    """Tasks of one scene. Reads (or generates) the layout and checks the options, so bad
    input is refused here, before any task runs. ``layouts`` memoises layouts between the
    scenes of one batch (many scenes share a layout file or generator settings)."""

    try:
        cfg = sc.config()
        check_config(cfg)
        key = (str(cfg.layout), cfg.seed, tuple(cfg.extent), cfg.style) if cfg.layout is None \
            else (str(cfg.layout), file_hash(cfg.layout))
        memo = layouts.get(key) if layouts is not None else None
        if memo is None:
            layout = read_layout_for(cfg)
            memo = {"layout": layout, "hash": layout_hash(layout)}
            if layouts is not None:
                layouts[key] = memo
        layout = memo["layout"]
    except InputError as e:
        raise InputError(f"{sc.where}: {e}") from None
    lhash = memo["hash"]
    plan = ScenePlan(sc, lhash)
    jopts = _json_options(sc.options)
    layout_file = sc.options.get("layout")
    layout_id = file_hash(layout_file) if layout_file else None
    base = {"target": "lsd3d_usd.batch.tasks:run_task", "scene": sc.name,
            "out": str(sc.output), "options": jopts, "force": sc.force,
            "region_workers": sc.region_workers, "executor": executor, "address": address}
    pkey = repr(cfg.proxy)
    if pkey not in memo:   # the proxy plan of one layout and proxy settings, built once
        builder = ProxyBuilder(layout, cfg.proxy)
        memo[pkey] = (builder, sorted(builder.chunks()))
    builder, keys = memo[pkey]
    split = sc.split_chunks == "always" or (sc.split_chunks == "auto"
                                                and len(keys) >= AUTO_SPLIT_MIN_CHUNKS)
    deps = []
    if split:
        for key in keys:
            h = builder.inputs(key).hash
            plan.chunk_keys.append(key)
            plan.chunk_hashes[key] = h
            cid = f"{sc.name}/{chunk_prim_name(*key).lower()}"
            cfile = chunk_file(sc.output, key)
            plan.tasks.append(Task(
                cid, "chunk", sc.name, content_hash(TASK_VERSION, "chunk", h, str(cfile)),
                {**base, "kind": "chunk", "chunk": list(key), "id": cid,
                 "log": str(logs_dir / f"{sc.name}.{chunk_prim_name(*key).lower()}.log")},
                outputs=(str(cfile),)))
            deps.append(cid)
    sid = f"{sc.name}/scene"
    plan.tasks.append(Task(
        sid, "scene", sc.name,
        content_hash(TASK_VERSION, "scene", jopts, sc.force, layout_id, lhash, str(sc.output),
              lsd3d_usd.__version__),
        {**base, "kind": "scene", "id": sid, "log": str(logs_dir / f"{sc.name}.scene.log")},
        deps=tuple(deps), outputs=(str(Path(sc.output) / S.ROOT_FILE),)))
    return plan


def plan_batch(spec: BatchSpec) -> list:
    """The scenes' plans, then (with a [dataset] table) the dataset's (batch.dataset), then
    (with a [scenarios] table) the scenario runs' (batch.scenarios)."""
    logs = spec.output / ".batch"
    layouts: dict = {}
    plans = [plan_scene(sc, logs, spec.executor, spec.address, layouts) for sc in spec.scenes]
    if spec.dataset is not None:
        from lsd3d_usd.batch.dataset import plan_dataset
        plans.append(plan_dataset(spec, plans, Task, logs, read_layout_for))
    if spec.scenarios is not None:
        from lsd3d_usd.batch.scenarios import plan_scenarios
        plans.append(plan_scenarios(spec, [p for p in plans if isinstance(p, ScenePlan)], Task, logs))
    return plans


def prepare_scene(plan: ScenePlan) -> None:
    """Create (or check) the scene folder before its tasks run: a split scene's chunk tasks
    write into it, and generate refuses a non-empty folder that is not a scene."""
    # local import: heavy, or only on this path
    from lsd3d_usd.pipeline import prepare_scene
    sc = plan.scene
    try:
        prepare_scene(sc.config(), run_options(sc.output, sc.force), plan.layout_hash)
    except InputError as e:
        raise InputError(f"{plan.scene.where}: {e}") from None


def finalize_chunks(plan: ScenePlan) -> None:
    """Driver side, after every chunk task of the scene: write the proxy root layer listing
    the chunks (one writer, no race) and put it in the scene's stack."""
    sc = S.Scene.open(plan.scene.output)
    write_root_layer(sc.layer_path("proxy"), dict(plan.chunk_hashes),
                     plan.scene.config().proxy.as_dict(),
                     plan.layout_hash)
    sc.add_layer("proxy")


# ----------------------------------------------------------------------- on workers
def _run_chunk(p: dict, log) -> dict:
    cfg = scene_config(p["options"])
    layout = read_layout_for(cfg)
    params = cfg.proxy
    builder = ProxyBuilder(layout, params)
    key = tuple(p["chunk"])
    inp = builder.inputs(key)
    cfile = chunk_file(p["out"], key)
    if chunk_file_hash(cfile) == inp.hash:
        log(f"{p['id']}: chunk file up to date")
        return {"chunk": list(key), "hash": inp.hash, "built": False}
    parts = builder.build(key, inp)
    write_chunk_layer(parts, key, cfile, inp.hash, params.as_dict())
    tris = sum(part.n_faces for part in parts)
    log(f"{p['id']}: wrote {cfile} ({tris} triangles)")
    return {"chunk": list(key), "hash": inp.hash, "built": True, "triangles": tris}


def _run_scene(p: dict, log) -> dict:
    return generate(scene_config(p["options"]),
                    run_options(p["out"], p.get("force", False), log, p.get("region_workers", 1),
                                p.get("executor", "local"), p.get("address")))


def _run_dataset_log(p: dict, log) -> dict:
    from lsd3d_usd.batch.dataset import run_log_task
    return run_log_task(p, log)


def _run_dataset_merge(p: dict, log) -> dict:
    from lsd3d_usd.batch.dataset import run_merge_task
    return run_merge_task(p, log)


def _run_scenarios(p: dict, log) -> dict:
    from lsd3d_usd.batch.scenarios import run_scenarios_task
    return run_scenarios_task(p, log)


RUNS = {"chunk": _run_chunk, "scene": _run_scene, "dataset_log": _run_dataset_log,
        "dataset_merge": _run_dataset_merge, "sim_scenarios": _run_scenarios}


def run_task(payload: dict) -> dict:
    """Execute one task (on a worker). Returns {"result": ..., "seconds": ...}; raises on
    failure with the error as the exception's message."""
    t0 = time.perf_counter()
    with task_log(payload["log"], payload["id"]) as log:
        try:
            run = RUNS[payload["kind"]]
            result = run(payload, log)
        except BaseException:
            log(traceback.format_exc())
            raise
        secs = time.perf_counter() - t0
        log(f"done in {secs:.1f} s")
    return {"result": json.loads(json.dumps(result, default=str)), "seconds": round(secs, 2)}
