"""A dataset made by a batch (docs/batch.md, docs/datasets.md): the spec's ``[dataset]`` table
turns the batch's scenes into one dataset, one task per scene x route (after the scene's own
task) and one merge task that writes the format's tables from the logs' records.

    [dataset]
    output = "ds"                # relative to [batch].output
    format = "nuscenes"          # nuscenes | kitti | mcap (a registered writer)
    routes = 10                  # or route = "w_in,j_we,e_out"; default: the longest route
    seconds = 20.0
    camera_hz = 12.0             # lidar_hz, keyframe_hz, width, rig, lidar, seed, version
    scenes = ["crossing"]        # default: every scene of the batch

Routes are drawn from the scenes' layouts when the batch is planned, so a bad route is refused
before any task runs. A log task whose inputs changed (its scene was made again, other
settings) renders the log again; an interrupted one continues after its last keyframe.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from lsd3d_usd.datasets.build import (
    STATE,
    DatasetOptions,
    check_output,
    check_settings,
    merge,
    plan_logs,
    run_log,
    start_dataset,
)
from lsd3d_usd.datasets.drive import LogPlan
from lsd3d_usd.errors import InputError
from lsd3d_usd.hashing import content_hash

TASK_VERSION = "batch-dataset-v1"
KEYS = {"output": str, "format": str, "rig": str, "lidar": str, "route": str, "routes": int,
        "seconds": float, "camera_hz": float, "lidar_hz": float, "keyframe_hz": float,
        "width": int, "seed": int, "version": str, "scenes": list}


@dataclass
class DatasetSpec:
    output: Path
    options: DatasetOptions
    scenes: list = field(default_factory=list)      # scene names (empty: all)


def check_table(table, where: str, keys: dict) -> None:
    """A spec table holds only ``keys`` ({name: type}; an int where a float is wanted is
    fine, a bool never is): one error line naming the table and key otherwise."""
    if not isinstance(table, dict):
        raise InputError(f"{where}: expected a table")
    for k, v in table.items():
        want = keys.get(k)
        if want is None:
            raise InputError(f"{where}: unknown key {k!r}; known keys: {', '.join(sorted(keys))}")
        ok = isinstance(v, want) or (want is float and isinstance(v, int))
        if isinstance(v, bool) or not ok:
            raise InputError(f"{where}.{k}: expected {want.__name__}, got {v!r}")


def parse_dataset(table, where: str, base_output: Path) -> DatasetSpec:
    check_table(table, where, KEYS)
    if "format" not in table:
        raise InputError(f"{where}: missing key 'format' (nuscenes, kitti or mcap)")
    out = Path(table.get("output", "dataset")).expanduser()
    out = out if out.is_absolute() else (base_output / out)
    opt = DatasetOptions(**{k: (float(v) if KEYS[k] is float else v) for k, v in table.items()
                            if k not in ("output", "scenes")}, resume=True)
    return DatasetSpec(out.absolute(), opt, [str(s) for s in table.get("scenes", [])])


@dataclass
class DatasetPlan:
    spec: DatasetSpec
    logs: list
    tasks: list

    def check(self) -> None:
        """Driver side, before any scene folder is prepared: the dataset folder checked."""
        try:
            check_output(self.spec.output, [Path(s) for s in self.spec.options.scenes],
                         self.spec.options)
        except InputError as e:       # name the spec's key, not the command's -o
            msg = str(e).removeprefix(f"-o {self.spec.output}: ")
            raise InputError(f"dataset.output {self.spec.output}: {msg}") from None

    def prepare(self) -> None:
        """Driver side, before the tasks: the folder checked and its settings recorded."""
        self.check()
        start_dataset(self.spec.output, self.spec.options, self.logs, inputs=False)


def plan_dataset(spec, scene_plans, task_cls, logs_dir: Path, read_layout) -> DatasetPlan:
    d = spec.dataset
    by_name = {p.scene.name: p for p in scene_plans}
    names = d.scenes or list(by_name)
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise InputError(f"{spec.path.name}: dataset.scenes: no scene named {unknown[0]!r}")
    chosen = [by_name[n] for n in names]
    opt = d.options
    try:
        check_settings(opt)
        scenes = [Path(p.scene.output).absolute() for p in chosen]
        opt.scenes = [str(s) for s in scenes]
        logs = plan_logs(scenes, opt, [read_layout(p.scene.config()) for p in chosen])
    except InputError as e:
        raise InputError(f"{spec.path.name}: dataset: {e}") from None
    sig = opt.signature()
    base = {"target": "lsd3d_usd.batch.tasks:run_task", "out": str(d.output),
            "options": asdict(opt)}
    tasks, ids, hashes = [], [], []
    by_out = {Path(p.scene.output).absolute(): p for p in chosen}
    for lp in logs:
        sp = by_out[Path(lp.scene)]
        scene_task = next(t for t in sp.tasks if t.kind == "scene")
        tid = f"dataset/log_{lp.index:04d}"
        h = content_hash(TASK_VERSION, "log", sig, lp.key, scene_task.inputs_hash)
        tasks.append(task_cls(tid, "dataset_log", "dataset", h, {
            **base, "kind": "dataset_log", "id": tid, "hash": h,
            "plan": {"index": lp.index, "scene": str(lp.scene), "scene_name": lp.scene_name,
                     "route": lp.route, "key": lp.key},
            "log": str(logs_dir / f"dataset.log_{lp.index:04d}.log")},
            deps=(scene_task.id,),
            outputs=(str(d.output / STATE / "logs" / f"{lp.index:04d}.json"),)))
        ids.append(tid)
        hashes.append(h)
    mh = content_hash(TASK_VERSION, "merge", hashes)
    tasks.append(task_cls("dataset/merge", "dataset_merge", "dataset", mh, {
        **base, "kind": "dataset_merge", "id": "dataset/merge", "hash": mh, "n_logs": len(logs),
        "log": str(logs_dir / "dataset.merge.log")}, deps=tuple(ids),
        outputs=(str(d.output / STATE / "merged.json"),)))
    return DatasetPlan(d, logs, tasks)


# ----------------------------------------------------------------------- on workers
def _options(p: dict) -> DatasetOptions:
    return DatasetOptions(**p["options"])


def run_log_task(p: dict, log) -> dict:
    opt = _options(p)
    writer_cls, lidar, timeline = check_settings(opt)
    root = Path(p["out"])
    lp = LogPlan(**{**p["plan"], "scene": Path(p["plan"]["scene"])})
    logs = root / STATE / "logs"
    stamp = logs / f"{lp.index:04d}.inputs"
    if not stamp.is_file() or stamp.read_text() != p["hash"]:
        # other inputs than the log's files were made from: render it from its start
        for f in (logs / f"{lp.index:04d}.json", logs / f"{lp.index:04d}.partial.json",
                  logs / f"{lp.index:04d}.journal.jsonl"):
            f.unlink(missing_ok=True)
        stamp.write_text(p["hash"])
    got = run_log(root, opt, lp, writer_cls(root, opt), lidar, timeline, log=log)
    log(f"{p['id']}: log {lp.index} ({lp.key}) "
        + ("already finished" if got["skipped"] else
           f"resumed at tick {got['resumed_at']}" if got["resumed_at"] is not None else "done"))
    return {"log": lp.index, "resumed_at": got["resumed_at"], "skipped": got["skipped"]}


def run_merge_task(p: dict, log) -> dict:
    opt = _options(p)
    writer_cls, _, _ = check_settings(opt)
    root = Path(p["out"])
    tables = merge(root, opt, writer_cls(root, opt), p["n_logs"])
    (root / STATE / "merged.json").write_text(json.dumps({"hash": p["hash"], "tables": tables}))
    log(f"{p['id']}: {tables}")
    return {"tables": tables}
