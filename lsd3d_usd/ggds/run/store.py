"""Where a GGDS run keeps its results in a scene.

A run is one layer, ``layers/ggds_<run>.usdc``: overs only, one per chunk the run has written,
each adding a payload to the run's chunk file (``layers/ggds_<run>_chunks/chunk_<i>_<j>.usdc``)
that holds the optimised attributes (splats.chunkio). Beside it, ``ggds/<run>/``:

    run.json              the run's plan: configuration, regions and phases, dependencies,
                          whether it is complete (present while the run can be resumed)
    <region>/ or .        per region (a set of chunks optimised together; a one-region run
                          uses the run folder itself): the checkpoint while unfinished
                          (state.json + state-<step>.safetensors: tensors and JSON, never a
                          pickle), progress.json, views.json, summary.json, loss.png,
                          before_after.png, task.json (the driver's record of a finished
                          chunk region's task: wall / CPU seconds, views, peak memory)

Checkpoints of older versions (a pickled ``state.pt``) are refused, never loaded. Only one
process writes the run layer: the driver (or, in a single process, the region's store).
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import parse_chunk_prim_name
from lsd3d_usd.splats import chunkio
from lsd3d_usd.splats.chunkio import chunks_base

RUN_ATTRIBUTES = ("positions", "orientations", "scales", "opacities", "sh")
CHECKPOINT_VERSION = 1
RUN_VERSION = 2


_ST_DTYPES = {torch.float64: "F64", torch.float32: "F32", torch.float16: "F16",
              torch.int64: "I64", torch.int32: "I32", torch.int16: "I16", torch.int8: "I8",
              torch.uint8: "U8", torch.bool: "BOOL"}     # numpy has no bfloat16


def safetensors_parts(tensors: dict):
    """The safetensors file of ``tensors`` (CPU) as its header and then each tensor's own
    memory, for a writer to stream. safetensors.torch.save copies every tensor into bytes and
    joins them: at SH degree 2 a checkpoint (parameters and both Adam moments, ~0.45 GB for
    0.9 M surfels) held twice that beside the run."""
    arrays, header, off = [], {}, 0
    for name in sorted(tensors):
        t = tensors[name].detach()
        if t.dtype not in _ST_DTYPES:
            raise ValueError(f"checkpoint tensor {name}: dtype {t.dtype} has no safetensors name")
        a = t.contiguous().numpy()
        header[name] = {"dtype": _ST_DTYPES[t.dtype], "shape": list(t.shape),
                        "data_offsets": [off, off + a.nbytes]}
        off += a.nbytes
        arrays.append(a)
    head = json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)          # the data starts 8-byte aligned, as save() pads
    yield struct.pack("<Q", len(head)) + head
    for a in arrays:
        if a.nbytes:
            yield memoryview(a.reshape(-1).view(np.uint8))   # contiguous: a view


def _json_default(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


def write_json(path: Path, data) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return S.atomic_write_text(path, json.dumps(data, indent=1, default=_json_default))


def _read_json(path: Path, what: str):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: unreadable {what} ({e})") from None


# ---------------------------------------------------------------------------- run level
def run_layer_path(sc: S.Scene, run: str) -> Path:
    return sc.layer_path(f"{run}.usdc")


def run_chunk_folder(sc: S.Scene, run: str) -> Path:
    return chunks_base(run_layer_path(sc, run))


def region_dir(sc: S.Scene, run: str, region: str) -> Path:
    d = sc.run_files(run).dir
    return d / region if region else d


def region_task(sc: S.Scene, run: str, region: str) -> dict:
    """What the invocation that finished ``region`` measured of its task (wall and CPU
    seconds, views, peak memory; regions.TASK_FIGURES), or {} before then."""
    p = region_dir(sc, run, region) / "task.json"
    try:     # a report's input only: unreadable reads as unknown, never fails a run
        return json.loads(p.read_text(encoding="utf-8")) if p.is_file() else {}
    except (OSError, ValueError, UnicodeDecodeError):
        return {}


def write_region_task(sc: S.Scene, run: str, region: str, figures: dict) -> Path:
    return write_json(region_dir(sc, run, region) / "task.json", figures)


def write_plan(sc: S.Scene, run: str, plan: dict) -> Path:
    return write_json(sc.run_files(run).dir / "run.json", {**plan, "version": RUN_VERSION})


def read_plan(sc: S.Scene, run: str) -> dict:
    f = sc.run_files(run)
    path = f.dir / "run.json"
    if f.legacy_state.is_file() and not path.is_file():
        raise InputError(f"{f.legacy_state}: a pickled checkpoint of an older lsd3d-usd "
                         "version; it is not loaded (unpickling can run code). Start a new "
                         "run without --resume (the scene's layers are kept)")
    if not path.is_file():
        raise InputError(f"{f.dir}: no run plan to resume (no run.json)")
    plan = _read_json(path, "run plan")
    if not isinstance(plan, dict) or plan.get("version") != RUN_VERSION:
        raise InputError(f"{path}: not a version-{RUN_VERSION} lsd3d-usd run plan")
    return plan


def region_progress(sc: S.Scene, run: str, region: str) -> dict:
    p = region_dir(sc, run, region) / "progress.json"
    return _read_json(p, "region progress") if p.is_file() else {}


def refresh_run_layer(sc: S.Scene, run: str) -> Path:
    """(Re)write the run layer from what is on disk: an over with a payload for every chunk
    file the run has written, and provenance gathered from the plan and the regions'
    progress. Atomic; the layer joins the stack if it is not there yet."""
    plan = read_plan(sc, run)
    folder = run_chunk_folder(sc, run)
    infos = {}
    if folder.is_dir():
        for f in sorted(folder.glob("chunk_*.usdc")):
            key = parse_chunk_prim_name(f.stem.replace("chunk_", "Chunk_", 1))
            infos[key] = {"file": f.name, "preview": chunkio.chunk_has_preview(f, key)}
    regions = {name: region_progress(sc, run, name) for name in plan["regions"]}
    totals = run_summary(regions)
    prior = next((r["prior"] for r in regions.values() if r.get("prior")), {})
    prov = S.provenance(
        "ggds", {**plan.get("params", {}), **prior}, seed=plan.get("seed"),
        timings={"optimise_s": round(totals["seconds"], 2),
                 "s_per_step": round(totals["s_per_step"], 4)},
        stepsDone=totals["steps"], complete=bool(plan.get("complete")),
        prompt=plan.get("prompt", ""), dependsOn=plan.get("dependsOn"),
        generate=json.dumps(plan.get("generate", {})), metrics=totals["metrics"] or None,
        regions=json.dumps({k: {kk: v.get(kk) for kk in ("stepsDone", "complete", "keys")}
                            for k, v in regions.items()}))
    path = chunkio.write_root(run_layer_path(sc, run), folder, infos, prov, define=False)
    sc.add_layer(path.name)
    return path


def run_summary(regions: dict) -> dict:
    """A run's totals from its regions' progress ({region: progress.json}): complete, steps
    (the fewest of the optimised regions), seconds, s_per_step, surfels, and the held-out
    metrics of the finished regions weighted by their surfels."""
    done = [r for r in regions.values() if r.get("complete")]
    steps = [int(r.get("stepsDone", 0)) for r in regions.values() if not r.get("skipped")]
    seconds = sum(float(r.get("seconds", 0.0)) for r in regions.values())
    return {"complete": all(r.get("complete") for r in regions.values()),
            "steps": min(steps) if steps else 0, "seconds": seconds,
            "s_per_step": seconds / max(sum(steps), 1),
            "surfels": int(sum(r.get("surfels", 0) for r in regions.values())),
            "metrics": aggregate_metrics([r.get("metrics") or {} for r in done],
                                         [r.get("surfels", 0) for r in done])}


def aggregate_metrics(metrics: list[dict], weights: list[float]) -> dict:
    """Regions' held-out metrics combined (means weighted by each region's surfel count)."""
    out = {}
    w = np.asarray(weights, np.float64)
    for key in ("psnr_novel", "depth_rel_err", "normal_err_deg", "off_surface_frac"):
        vals = np.array([m.get(key, np.nan) for m in metrics], np.float64)
        ok = np.isfinite(vals) & (w > 0) if len(vals) else np.zeros(0, bool)
        if ok.any():
            out[key] = float((vals[ok] * w[ok]).sum() / w[ok].sum())
    return out


def run_views(sc: S.Scene, run: str) -> list[dict] | None:
    """The training views of a run (View.to_json dicts, all regions, each once: a chunk
    region also trains on views of its neighbours), or None if the run recorded none (older
    runs keep them in the layer's provenance: ``trainViews``)."""
    d = sc.run_files(run).dir
    files = sorted(d.glob("views.json")) + sorted(d.glob("*/views.json"))
    if not files:
        return None
    out, seen = [], set()
    for f in files:
        for v in _read_json(f, "training views"):
            key = json.dumps(v, sort_keys=True)
            if key not in seen:
                seen.add(key)
                out.append(v)
    return out


# ---------------------------------------------------------------------------- a region
class RegionRunStore:
    """One region of run ``run``: its checkpoint, summary and plots in ``region_dir``, and its
    surfels written to the run's chunk files, split by the chunk each surfel belongs to
    (``owners``: [(key, start, stop)] ranges of the region's surfel array). ``refresh``:
    rewrite the run layer after each write (single process); a pool's driver does it instead."""

    def __init__(self, sc: S.Scene, run: str, region: str, owners: list, *,
                 checkpoint_meta: dict | None = None, refresh: bool = True):
        self.scene = sc
        self.run = run
        self.region = region
        self.name = f"{run}/{region}" if region else run
        self.dir = region_dir(sc, run, region)
        self.owners = list(owners)
        self.checkpoint_meta = dict(checkpoint_meta or {})
        self.refresh = refresh

    @property
    def plot_dir(self) -> Path:
        return self.dir

    # ------------------------------------------------------------------ checkpoint
    @property
    def _meta(self) -> Path:
        return self.dir / "state.json"

    def has_checkpoint(self) -> bool:
        return self._meta.is_file()

    def load_checkpoint(self) -> tuple[dict, dict]:
        """(tensors, meta); one-line InputError when missing, truncated or inconsistent."""
        if not self._meta.is_file():
            raise InputError(f"{self.dir}: no checkpoint to resume (no state.json)")
        meta = _read_json(self._meta, "checkpoint metadata")
        if not isinstance(meta, dict) or meta.get("version") != CHECKPOINT_VERSION:
            raise InputError(f"{self._meta}: not a version-{CHECKPOINT_VERSION} lsd3d-usd "
                             "checkpoint")
        name = str(meta.get("tensors", ""))
        if not name.startswith("state-") or "/" in name or not name.endswith(".safetensors"):
            raise InputError(f"{self._meta}: bad tensor file name {name!r}")
        path = self.scene.inside(self.dir / name, "checkpoint file")
        try:
            tensors = load_file(str(path))
        except (SafetensorError, OSError, ValueError) as e:
            raise InputError(f"{path}: unreadable checkpoint ({str(e).splitlines()[0]})") from None
        return tensors, meta

    def save_checkpoint(self, tensors: dict, meta: dict) -> None:
        """Crash-consistent: the tensors go to a new file named by step, then the JSON that
        names it replaces the old JSON (atomic), then older tensor files are removed. A crash
        at any point leaves a JSON whose tensor file exists."""
        self.dir.mkdir(parents=True, exist_ok=True)
        name = f"state-{int(meta['step']):08d}.safetensors"
        S.atomic_write_parts(self.dir / name, safetensors_parts(tensors))
        write_json(self._meta, {**self.checkpoint_meta, **meta, "version": CHECKPOINT_VERSION,
                                 "run": self.name, "tensors": name})
        for old in self.dir.glob("state-*.safetensors"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def drop_checkpoint(self) -> None:
        self._meta.unlink(missing_ok=True)
        for old in self.dir.glob("state-*.safetensors"):
            old.unlink(missing_ok=True)

    # ------------------------------------------------------------------ results
    def write_layer(self, field, provenance: dict) -> None:
        """The region's surfels into the run's chunk files, its progress beside them, then
        (single process) the run layer."""
        folder = run_chunk_folder(self.scene, self.run)
        # the run's preview follows the surfel layer's (none when it has none)
        fraction = chunkio.preview_fraction_of(self.scene.layer_path("surfels"))
        for key, a, b in self.owners:
            chunkio.write_run_chunk(folder, key, field.rows(a, b), RUN_ATTRIBUTES,
                                    preview_fraction=fraction)
        write_json(self.dir / "progress.json",
                    {**provenance, "keys": [list(k) for k, _, _ in self.owners],
                     "surfels": int(field.n)})
        if self.refresh:
            refresh_run_layer(self.scene, self.run)

    def write_views(self, views: list) -> Path:
        return write_json(self.dir / "views.json", [v.to_json() for v in views])

    def write_summary(self, summary: dict) -> Path:
        return write_json(self.dir / "summary.json", summary)
