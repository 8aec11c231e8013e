"""`lsd3d-usd dataset`: plan a dataset (scenes x routes -> logs), check everything before
anything is written, render the logs one sample at a time into a registered writer, then
merge the logs' records into the format's tables.

The output folder holds, besides the format's files, ROOT/.lsd3d/: dataset.json (the settings
and the plan: what --resume checks), logs/<k>.json (a finished log's record: its table rows)
and work/<k>/ (the log's rig.usda). A killed run continues with --resume: finished logs are
kept, the ticks of an unfinished log after its last checkpoint are rendered again (their
files are rewritten, byte for byte the same), and the tables are merged as an uninterrupted
run merges them. A writer that can checkpoint (nuScenes, KITTI, MCAP) continues an unfinished
log after its last keyframe: after every keyframe the writer's delta (what the log gained since
the previous checkpoint) is appended to logs/<k>.journal.jsonl, then logs/<k>.partial.json
(next tick, the journal's valid length) is replaced, so a checkpoint costs what it adds, not
what the log holds; a writer without checkpoints starts the log again.
"""
from __future__ import annotations

import fnmatch
import json
import os
import re
import time
from pathlib import Path

import numpy as np

from lsd3d_usd import safepaths
from lsd3d_usd import scene as S
from lsd3d_usd.datasets.drive import LogPlan
from lsd3d_usd.datasets.options import DEFAULT_VERSION, DatasetOptions  # noqa: F401  (re-exported)
from lsd3d_usd import limits as L
from lsd3d_usd.errors import InputError

STATE = ".lsd3d"
MAX_ROUTES = 1000
STATE_FILE_BYTES = L.DATASET_STATE_BYTES
TMP_NAME = re.compile(r"^\..+\.tmp-\d+-[0-9a-f]{8}(\.[^.]*)?$")   # scene._tmp_sibling


def scene_root(scene) -> Path:
    p = Path(scene)
    if not (p / S.ROOT_FILE).is_file():
        raise InputError(f"{scene}: not a scene folder (no {S.ROOT_FILE})")
    return p.resolve()


def _only_empty_state(o: Path) -> bool:
    """Nothing in ``o`` but, at most, a state folder without files (a start killed before it
    recorded the dataset): as good as empty."""
    entries = list(o.iterdir())
    if not entries:
        return True
    st = o / STATE
    if entries != [st] or st.is_symlink() or not st.is_dir():
        return False
    # a link anywhere (to a folder too: os.walk lists it without entering it) is not ours
    return all(not files and not any(Path(d, n).is_symlink() for n in dirs)
               for d, dirs, files in os.walk(st))


def check_output(out: Path, scenes: list[Path], opt: DatasetOptions) -> None:
    if opt.resume and opt.overwrite:
        raise InputError("--resume and --overwrite exclude each other")
    o = out.resolve()
    for sc in scenes:
        if o == sc or sc in o.parents:
            raise InputError(f"-o {out}: inside the scene folder {sc}; write the dataset "
                             "elsewhere (a scene folder holds only the scene)")
        if o in sc.parents:
            raise InputError(f"-o {out}: the scene {sc} lies inside it; write the dataset "
                             "elsewhere")
    if o.exists() and not o.is_dir():
        raise InputError(f"-o {out}: exists and is not a folder")
    if o.is_dir() and not _only_empty_state(o):
        ours = (o / STATE / "dataset.json").is_file()
        if opt.resume:
            if not ours:
                raise InputError(f"-o {out}: --resume, but it holds no lsd3d-usd dataset "
                                 f"({STATE}/dataset.json)")
            # a resume appends, truncates and deletes inside the folder: a planted link would
            # carry those steps outside it
            safepaths.check_tree(o, o, "dataset folder")
        elif opt.overwrite:
            if not ours:
                raise InputError(f"-o {out}: --overwrite, but it holds files that are not an "
                                 "lsd3d-usd dataset; refusing to delete them")
            owned_files(o, out)
        else:
            raise InputError(f"-o {out}: not empty; give --resume to continue the dataset in "
                             "it or --overwrite to replace it")


def read_record(path: Path, out) -> dict:
    """A JSON state file of the dataset (dataset.json, a log record), refused with one line
    when it is not a JSON object (truncated, garbage, a link, too large)."""
    where = f"-o {out}: {path}"
    if path.is_symlink() or not path.is_file():
        raise InputError(f"{where}: not a regular file; give --overwrite")
    if path.stat().st_size > STATE_FILE_BYTES.value:
        raise InputError(STATE_FILE_BYTES.message(path.stat().st_size, where))
    try:
        data = json.loads(path.read_bytes())
    except (ValueError, RecursionError) as e:
        raise InputError(f"{where}: not valid JSON ({str(e)[:80]}); give --overwrite") from None
    if not isinstance(data, dict):
        raise InputError(f"{where}: not a JSON object; give --overwrite")
    return data


def _matches(rel: tuple, pattern: str) -> bool:
    parts = tuple(pattern.split("/"))
    if parts[-1] == "**":                     # anything below the folder
        return len(rel) > len(parts) - 1 and all(
            fnmatch.fnmatchcase(a, b) for a, b in zip(rel, parts[:-1]))
    return len(rel) == len(parts) and all(fnmatch.fnmatchcase(a, b) for a, b in zip(rel, parts))


def owned_files(o: Path, out) -> list[Path]:
    """The files of the dataset in ``o`` that --overwrite may delete: its state folder and
    the names its format (recorded in dataset.json) writes. Refused (one line naming the
    first) when anything else is there, or a symbolic link anywhere."""
    from lsd3d_usd.datasets.writers import WRITERS
    rec = read_record(o / STATE / "dataset.json", out)
    fmt, version = rec.get("format"), rec.get("version")
    if not isinstance(fmt, str) or not isinstance(version, str) or \
            not isinstance(rec.get("logs"), list):
        raise InputError(f"-o {out}: {STATE}/dataset.json is not an lsd3d-usd dataset record "
                         "(no format, version and logs); refusing to delete anything")
    try:
        patterns = [f.format(version=version) for f in getattr(WRITERS.get(fmt), "files", ())]
    except InputError:
        patterns = []                         # a writer no longer installed: state only
    patterns.append(f"{STATE}/**")
    safepaths.check_tree(o, o, "dataset folder")
    files = []
    for dirpath, _, names in os.walk(o):
        for n in sorted(names):
            p = Path(dirpath) / n
            rel = p.relative_to(o).parts
            if not any(_matches(rel, pat) for pat in patterns):
                raise InputError(f"-o {out}: --overwrite, but {p} is not a file of the "
                                 f"{fmt} dataset there; refusing to delete anything (move it "
                                 "away first)")
            files.append(p)
    return files


def lidar_of(opt: DatasetOptions):
    from lsd3d_usd.sensors.rigs import rig_lidar
    return rig_lidar(opt.rig, opt.lidar)


def _layout(scene: Path):
    from lsd3d_usd.layout.usdio import layout_from_stage
    stage = S.open_stage(scene / S.ROOT_FILE, load=False)
    if not stage.GetPrimAtPath(S.LAYOUT_PATH):
        raise InputError(f"{scene}: the scene has no layout ({S.LAYOUT_PATH}) to drive routes on")
    return layout_from_stage(stage, str(scene))


def check_route(layout, ids: list, where: str) -> list:
    from lsd3d_usd.layout.routes import LaneGraph
    try:
        LaneGraph(layout).route_indices(ids)
    except InputError as e:
        raise InputError(f"{where}: --route {','.join(ids)}: {str(e).removeprefix('route: ')}") \
            from None
    return ids


def draw_routes(layout, n: int, length: float, seed: int, where: str) -> list:
    """``n`` distinct routes (`routes.random_routes`), errors prefixed with ``where``."""
    from lsd3d_usd.layout.routes import random_routes
    try:
        return random_routes(layout, n, length, seed)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None


def plan_logs(scenes: list[Path], opt: DatasetOptions, layouts=None) -> list[LogPlan]:
    """The logs (scene x route) of a dataset; ``layouts``: the scenes' layouts when the
    scenes are not written yet (a batch plans before it generates)."""
    from lsd3d_usd.layout.routes import default_route, parse_route
    names = [s.name for s in scenes]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup:
        raise InputError(f"two scenes are named {dup!r}: a log is named after its scene folder")
    if opt.route is not None and opt.routes is not None:
        raise InputError("--route and --routes exclude each other")
    if opt.routes is not None and not 1 <= opt.routes <= MAX_ROUTES:
        raise InputError(f"--routes {opt.routes}: must be within 1 .. {MAX_ROUTES}")
    plans = []
    for k, sc in enumerate(scenes):
        layout = layouts[k] if layouts is not None else _layout(sc)
        if opt.route is not None:
            routes = [check_route(layout, parse_route(opt.route),
                                  str(sc))]
        elif opt.routes is not None:
            lanes = layout.drivable_lanes()
            v = max((ln.speed_limit_mps for ln in lanes), default=10.0)
            routes = draw_routes(layout, opt.routes, opt.seconds * v, opt.seed, str(sc))
        else:
            ids, _ = default_route(layout, opt.seconds)
            if not ids:
                raise InputError(f"{sc}: the layout has no drivable lanes")
            routes = [ids]
        for r in routes:
            plans.append(LogPlan(len(plans), sc, sc.name, list(r),
                                 f"{sc.name}:{','.join(r)}"))
    return plans


def check_settings(opt: DatasetOptions):
    """The checks of the settings alone: (writer class, LiDAR model or None, timeline)."""
    from lsd3d_usd.datasets.timeline import Timeline
    from lsd3d_usd.datasets.writers import WRITERS
    from lsd3d_usd.sensors.rigs import load_rig
    writer_cls = WRITERS.get(opt.format)
    load_rig(opt.rig)
    if not opt.version or "/" in opt.version or opt.version.startswith("."):
        raise InputError(f"--version {opt.version!r}: a folder name like v1.0-lsd3d")
    if opt.width is not None and not 8 <= opt.width <= 8192:
        raise InputError(f"--width {opt.width}: must be within 8 .. 8192")
    if opt.width is not None:
        from lsd3d_usd.sensors.rigs import check_rig_width
        check_rig_width(opt.rig, opt.width, f"--width {opt.width}")
    lidar = lidar_of(opt)
    if lidar is not None and opt.lidar_hz > lidar.rotation_hz + 1e-9:
        raise InputError(f"--lidar-hz {opt.lidar_hz:g} exceeds the LiDAR's rotation rate "
                         f"{lidar.rotation_hz:g} Hz (one sweep per turn)")
    if getattr(writer_cls, "needs_lidar", False) and lidar is None:
        raise InputError(f"--format {opt.format}: needs a LiDAR (--lidar hdl32, waymo_top or a "
                         "FILE.toml)")
    timeline = Timeline(opt.camera_hz, opt.lidar_hz if lidar is not None else None,
                        opt.keyframe_hz, opt.seconds)
    return writer_cls, lidar, timeline


def prepare(scenes, out, opt: DatasetOptions):
    """Every check before anything is written: (writer class, plans, LiDAR, timeline)."""
    writer_cls, lidar, timeline = check_settings(opt)
    if not scenes:
        raise InputError("dataset: give at least one SCENE")
    roots = [scene_root(s) for s in scenes]
    check_output(Path(out), roots, opt)
    opt.scenes = [str(r) for r in roots]
    return writer_cls, plan_logs(roots, opt), lidar, timeline


def _scene_files(root: Path) -> tuple[list[Path], list[Path]]:
    """(the layers of the scene's root layer stack: the root layer and its sublayers,
    recursively; the files those layers reference or payload, e.g. chunk files)."""
    from pxr import Sdf
    stack, arcs, todo = [], [], [root / S.ROOT_FILE]
    while todo:
        p = todo.pop(0)
        if p in stack:
            continue
        stack.append(p)
        try:
            layer = Sdf.Layer.FindOrOpen(str(p)) if p.is_file() else None
        except Exception:  # noqa: BLE001 -- unreadable: recorded as its bytes, no arcs followed
            layer = None
        if layer is None:
            continue
        subs = [Path(layer.ComputeAbsolutePath(s)) for s in layer.subLayerPaths]
        todo += subs
        arcs += [Path(layer.ComputeAbsolutePath(d))
                 for d in layer.GetCompositionAssetDependencies()
                 if Path(layer.ComputeAbsolutePath(d)) not in subs]
    return stack, sorted(set(arcs) - set(stack))


def input_digests(opt: DatasetOptions) -> dict:
    """What the dataset is made from, by name: the SHA-256 of every layer of each scene's
    root layer stack and of a rig or LiDAR FILE.toml (streamed: bounded memory), the size
    and mtime of the files those layers reference or payload (chunk files: hashing a large
    scene's chunks would cost more than a resume saves), and the LiDAR model itself (a rig's
    own LiDAR file included). --resume refuses other content, naming what changed."""
    from lsd3d_usd.hashing import content_hash, file_hash
    out = {}
    for sc in map(Path, opt.scenes):
        stack, arcs = _scene_files(sc)
        for f in stack + arcs:
            name = f"{sc.name}/{f.relative_to(sc) if f.is_relative_to(sc) else f}"
            if not f.is_file():
                out[name] = "missing"
            elif f in stack:
                out[name] = f"sha256 {file_hash(f)}"
            else:
                st = f.stat()
                out[name] = f"size {st.st_size} mtime_ns {st.st_mtime_ns}"
    for flag, spec in (("--rig", opt.rig), ("--lidar", opt.lidar)):
        if isinstance(spec, str) and spec.lower().endswith(".toml") and Path(spec).is_file():
            out[f"{flag} {spec}"] = f"sha256 {file_hash(spec)}"
    lidar = lidar_of(opt)
    out["the LiDAR model"] = content_hash(lidar.describe() if lidar else None)
    return out


def check_resume(state: Path, sig: dict, out) -> None:
    old = read_record(state / "dataset.json", out)
    # a key missing on either side differs (a dropped "routes": null is not the default)
    diff = sorted(k for k in set(old) | set(sig) if k != "inputs" and
                  (k not in old or k not in sig or old[k] != sig[k]))
    if diff:
        raise InputError(f"-o {out}: --resume, but the dataset was made with other "
                         f"settings ({diff[0]}: {old.get(diff[0])!r} there, "
                         f"{sig.get(diff[0])!r} now)")
    if "inputs" not in sig:                # a batch: its task hashes cover the scenes
        return
    was, now = old.get("inputs"), sig["inputs"]
    if not isinstance(was, dict):
        raise InputError(f"-o {out}: --resume, but {STATE}/dataset.json records no digests of "
                         "what the dataset was made from (an older lsd3d-usd, or edited); "
                         "give --overwrite")
    for k in sorted(set(was) | set(now)):
        if was.get(k) != now.get(k):
            how = ("changed" if k in was and k in now and now[k] != "missing" else
                   "is missing now" if k in was else "is new")
            raise InputError(f"-o {out}: --resume, but {k} {how} since the dataset began; "
                             "restore it, or give --overwrite to start again")


def dataset_record(opt: DatasetOptions, plans, inputs: bool = True) -> dict:
    """What dataset.json holds: the settings, the plan and (``inputs``) input_digests."""
    sig = {**opt.signature(), "logs": [p.key for p in plans]}
    if inputs:
        sig["inputs"] = input_digests(opt)
    return sig


def start_dataset(root: Path, opt: DatasetOptions, plans, inputs: bool = True) -> None:
    """Record the settings, the plan and the digests of the inputs
    (ROOT/.lsd3d/dataset.json); --overwrite deletes the previous dataset's own files (nothing
    else may be there), --resume checks the record. ``inputs`` False: a batch, which records
    the dataset before its scenes exist (its task hashes cover them)."""
    state = root / STATE
    sig = dataset_record(opt, plans, inputs)
    # --resume into a new or empty folder starts the dataset (a batch always resumes);
    # check_output refused a non-empty folder without a record
    if opt.resume and os.path.lexists(state / "dataset.json"):
        check_resume(state, sig, root)
        # temp files of a killed writer (scene.atomic_write_bytes) are no part of the dataset
        o = root.resolve()
        for dirpath, _, names in os.walk(o):
            for n in names:
                if TMP_NAME.match(n):
                    safepaths.unlink(Path(dirpath) / n, o, "temp file")
    if opt.overwrite and root.is_dir() and any(root.iterdir()):
        o = root.resolve()
        for f in owned_files(o, root):
            safepaths.unlink(f, o, "dataset file")
        for dirpath, _, _ in sorted(os.walk(o), key=lambda w: -len(w[0])):
            if Path(dirpath) != o and not any(Path(dirpath).iterdir()):
                Path(dirpath).rmdir()          # emptied above (a folder of ours)
    state.mkdir(parents=True, exist_ok=True)
    S.atomic_write_text(state / "dataset.json", json.dumps(sig, indent=1))
    (state / "logs").mkdir(exist_ok=True)


class Checkpoints:
    """A log's checkpoints: an append-only journal of the writer's deltas
    (logs/<k>.journal.jsonl, one JSON line per keyframe) and logs/<k>.partial.json, replaced
    after each append, naming the next tick and how many journal bytes are valid. A kill
    between the two leaves a tail past that length, which ``load`` cuts off."""

    def __init__(self, logs: Path, index: int):
        self.part = logs / f"{index:04d}.partial.json"
        self.journal = logs / f"{index:04d}.journal.jsonl"
        self.size = 0
        self.bytes_written = 0          # by ``save`` (what the checkpoint benchmark reports)

    def load(self):
        """(next tick, the writer's deltas in order) of the last checkpoint, or None. Every
        field is checked: a tampered or torn state file is one error line, not a traceback."""
        if not self.part.is_file() and not self.part.is_symlink():
            return None
        out = self.part.parents[2]
        part = read_record(self.part, out)
        if "journal_bytes" not in part:     # a checkpoint of another layout: start again
            return None
        size, tick = part["journal_bytes"], part.get("next_tick")
        for key, v in (("journal_bytes", size), ("next_tick", tick)):
            if type(v) is not int or v < 0:
                raise InputError(f"{self.part}: {key} is {v!r}, not a count; give --overwrite")
        if size > STATE_FILE_BYTES.value:
            raise InputError(STATE_FILE_BYTES.message(size, f"{self.part}: journal_bytes"))
        self.size = size
        if self.journal.is_symlink():       # truncating it would cut its target
            raise InputError(f"{self.journal}: a symbolic link; refusing to truncate it "
                             "(give --overwrite)")
        data = self.journal.read_bytes() if self.journal.is_file() else b""
        if len(data) < self.size:
            raise InputError(f"{self.journal}: shorter than its checkpoint "
                             f"({len(data)} < {self.size} bytes); give --overwrite")
        if len(data) > self.size:
            os.truncate(self.journal, self.size)
            data = data[:self.size]
        deltas = []
        for n, ln in enumerate(data.splitlines(), 1):
            try:
                d = json.loads(ln)
            except (ValueError, RecursionError):
                d = None
            if not isinstance(d, dict):
                raise InputError(f"{self.journal}: line {n} is not a JSON object; give "
                                 "--overwrite")
            deltas.append(d)
        return tick, deltas

    def save(self, next_tick: int, delta: dict) -> None:
        line = (json.dumps(delta) + "\n").encode()
        with open(self.journal, "ab") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
        self.size += len(line)
        part = json.dumps({"next_tick": next_tick, "journal_bytes": self.size})
        S.atomic_write_text(self.part, part)
        self.bytes_written += len(line) + len(part)

    def clear(self) -> None:
        root = self.part.parents[2]
        safepaths.unlink(self.part, root, "checkpoint")   # first: without it the journal is not read
        safepaths.unlink(self.journal, root, "journal")
        self.size = 0


def run_log(root: Path, opt: DatasetOptions, plan: LogPlan, writer, lidar, timeline, *,
            progress: bool = False, log=print, deferrer=None, timing=None) -> dict:
    """Render one log into ``writer`` and keep its record (ROOT/.lsd3d/logs/<k>.json); with
    --resume a finished log is read back and an unfinished one continues after its last
    checkpoint. Returns {"record", "resumed_at" (tick or None), "skipped" (bool)}."""
    from tqdm import tqdm

    from lsd3d_usd.datasets.drive import drive
    from lsd3d_usd.sensors.rigs import load_rig
    state = root / STATE
    rec_file = state / "logs" / f"{plan.index:04d}.json"
    if opt.resume and rec_file.is_file():
        return {"record": read_record(rec_file, root), "resumed_at": None, "skipped": True}
    resumable = hasattr(writer, "checkpoint") and hasattr(writer, "restore")
    cps = Checkpoints(state / "logs", plan.index)
    part = cps.load() if opt.resume and resumable else None
    if part is None:
        cps.clear()                             # a stale journal of a run not resumed
    start = part[0] if part else 0
    if part:
        # next_tick follows a keyframe and the journal holds one line per keyframe before it
        kf = timeline._every(timeline.keyframe_hz)
        if not (1 <= start <= timeline.n_ticks and (start - 1) % kf == 0
                and len(part[1]) == (start - 1) // kf + 1):
            raise InputError(f"{cps.part}: next_tick {start} does not follow a keyframe of "
                             f"this log's {timeline.n_ticks} ticks with {len(part[1])} journal "
                             "lines; give --overwrite")
    width = opt.width or load_rig(opt.rig).cameras[0].size[0]
    info, samples = drive(plan, state / "work" / f"{plan.index:04d}", rig=opt.rig,
                          lidar=lidar, timeline=timeline, width=width, seed=opt.seed,
                          exposure=opt.exposure, tonemap=opt.tonemap, deferrer=deferrer,
                          start_tick=start, lod_px=opt.lod_px if opt.lod else 0.0, log=log)
    if part:
        try:
            writer.restore(info, part[1])
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
            # a journal line that parses but is not the writer's delta (tampered)
            raise InputError(f"{cps.journal}: not a checkpoint of the {opt.format} writer "
                             f"({type(e).__name__}: {str(e)[:60]}); give --overwrite") from None
    else:
        writer.begin_log(info)
    timing = timing if timing is not None else {}
    counts = timeline.counts()
    bar = tqdm(total=counts["camera_frames"] + counts["sweeps"], unit="frame",
               desc=f"dataset log {plan.index}", disable=not progress)
    t_render = time.perf_counter()
    for s in samples:
        t0 = time.perf_counter()
        timing["render_s"] = timing.get("render_s", 0.0) + t0 - t_render
        for k, v in s.timing.items():
            timing[k] = timing.get(k, 0.0) + v
        writer.write(s)
        if resumable and s.keyframe:
            cps.save(s.tick.index + 1, writer.checkpoint())
        t_render = time.perf_counter()
        timing["write_s"] = timing.get("write_s", 0.0) + t_render - t0
        bar.update(int(bool(s.cameras)) + int(s.lidar is not None))
    bar.close()
    rec = writer.end_log()
    S.atomic_write_text(rec_file, json.dumps(rec))
    cps.clear()
    return {"record": rec, "resumed_at": start if part else None, "skipped": False}


def record_problem(value, shape, where: str = "") -> str | None:
    """Where ``value`` (JSON read back) departs from ``shape``, or None. A shape is a type
    (int excludes bool), ``[shape]`` (a list of those), ``{str: shape}`` (a mapping of any
    keys) or ``{"key": shape, ...}`` (those keys required, others free)."""
    if isinstance(shape, type):
        ok = isinstance(value, shape) and not (shape is int and isinstance(value, bool))
        return None if ok else f"{where or 'record'} is {type(value).__name__}, not " \
                               f"{shape.__name__}"
    if isinstance(shape, list):
        if not isinstance(value, list):
            return f"{where or 'record'} is {type(value).__name__}, not a list"
        return next((p for i, v in enumerate(value)
                     if (p := record_problem(v, shape[0], f"{where}[{i}]"))), None)
    if not isinstance(value, dict):
        return f"{where or 'record'} is {type(value).__name__}, not an object"
    if list(shape) == [str]:
        return next((p for k, v in value.items()
                     if (p := record_problem(v, shape[str], f"{where}.{k}".lstrip(".")))), None)
    for k, s in shape.items():
        if k not in value:
            return f"{where}.{k}".lstrip(".") + " is missing"
        if (p := record_problem(value[k], s, f"{where}.{k}".lstrip("."))):
            return p
    return None


def merge(root: Path, opt: DatasetOptions, writer, n_logs: int) -> dict:
    """The format's tables from every log's record (all must be finished); each record is
    checked against the writer's ``record_shape`` first (it is data read back from disk)."""
    logs = root / STATE / "logs"
    missing = [k for k in range(n_logs) if not (logs / f"{k:04d}.json").is_file()]
    if missing:
        raise InputError(f"{root}: log {missing[0]} is not finished; run again with --resume")
    records = []
    shape = getattr(writer, "record_shape", None)
    for k in range(n_logs):
        f = logs / f"{k:04d}.json"
        rec = read_record(f, root)
        if shape is not None and (p := record_problem(rec, shape)):
            raise InputError(f"{f}: not a log record of the {opt.format} writer ({p[:100]}); "
                             "give --overwrite")
        records.append(rec)
    try:
        return writer.finish(records)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        # a writer without a shape, or a shape that misses a detail: still one line
        raise InputError(f"{logs}: a log record is not one of the {opt.format} writer "
                         f"({type(e).__name__}: {str(e)[:60]}); give --overwrite") from None


def build_dataset(scenes, out, opt: DatasetOptions, *, progress: bool = True, log=print,
                  deferrer_for=None) -> dict:
    """Write the dataset (module doc); a summary dict (logs, samples, tables, timings).
    ``deferrer_for(scene)``: a views.deferred.Deferrer for --deferred."""
    writer_cls, plans, lidar, timeline = prepare(scenes, out, opt)
    root = Path(out)
    logs = root / STATE / "logs"
    # a run refused before any log or checkpoint was written leaves the folder as it found it
    with safepaths.removed_on_error(root, keep=lambda: logs.is_dir() and any(logs.iterdir())):
        start_dataset(root, opt, plans)
        writer = writer_cls(root, opt)
        timing = {"render_s": 0.0, "cameras_s": 0.0, "lidar_s": 0.0, "boxes_s": 0.0,
                  "write_s": 0.0}
        done_logs, resumed_at = 0, {}
        for plan in plans:
            got = run_log(root, opt, plan, writer, lidar, timeline, progress=progress, log=log,
                          deferrer=deferrer_for(plan.scene) if deferrer_for else None,
                          timing=timing)
            done_logs += got["skipped"]
            if got["resumed_at"] is not None:
                resumed_at[plan.index] = got["resumed_at"]
    tables = merge(root, opt, writer, len(plans))
    counts = timeline.counts()
    return {"logs": len(plans), "resumed_logs": done_logs, "resumed_at_tick": resumed_at,
            "keyframes": counts["keyframes"], "camera_frames": counts["camera_frames"],
            "sweeps": counts["sweeps"], "tables": tables, "timing": timing,
            "routes": [p.route for p in plans]}
