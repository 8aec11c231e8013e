"""Stage conventions: layer names, prim paths, create/open, provenance, atomic writes.

The one place that knows where things live in a scene folder::

    scene/
      scene.usda          root layer: metadata + subLayers (strongest first)
      layers/ggds_<run>.usdc, surfels.usdc, cameras.usda, actors.usda, env.usda, proxy.usdc,
              layout.usda
      textures/  assets/
      ggds/<run>/         a run's checkpoint (while unfinished), summary.json, plots

A step reads the layers below it and writes its own; it never rewrites another
step's layer. Every write is atomic (temp file in the same folder, fsync, os.replace).
Muting is persistent: a muted layer leaves the root's subLayers (so every USD
tool sees it muted) and is remembered in customLayerData["lsd3d"]["mutedLayers"].

Paths read from a scene (sublayer entries, muted-layer names) are only ever plain file
names inside layers/: anything else is refused before it is written or deleted.

Dependencies: a step layer records the hash of its inputs (provenance ``inputsHash``) and a
GGDS run records the hashes of the layers it was optimised on (``dependsOn``). A step that
would change a layer that active runs depend on refuses, or with permission retires those
runs (muted and marked ``stale`` in their provenance): a run is never silently active on
top of surfels or light it was not made for.
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import re
import stat
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from pxr import Sdf, Usd, UsdGeom, Vt  # noqa: E402  (lsd3d_usd registered the schema first)

import lsd3d_usd
from lsd3d_usd import safepaths
from lsd3d_usd.errors import InputError

WORLD = "/World"
LAYOUT_PATH = "/World/Layout"
PROXY_PATH = "/World/Proxy"
SURFELS_PATH = "/World/Surfels"
SURFEL_PREVIEW_PATH = "/World/SurfelPreview"   # UsdGeom.Points stand-ins (splats.preview)
ENV_PATH = "/World/Env"
ACTORS_PATH = "/World/Actors"
CAMERAS_PATH = "/World/Cameras"

ROOT_FILE = "scene.usda"
LAYERS_DIR = "layers"
TEXTURES_DIR = "textures"
ASSETS_DIR = "assets"
RUNS_DIR = "ggds"
WRITTEN_DIRS = (LAYERS_DIR, RUNS_DIR, TEXTURES_DIR)   # rewritten and pruned by the steps

# Fixed step layers, weakest first. GGDS runs stack above all of them, newest strongest.
STEP_LAYERS: dict[str, str] = {
    "layout": "layout.usda",
    "proxy": "proxy.usdc",
    "env": "env.usda",
    "actors": "actors.usda",
    "cameras": "cameras.usda",
    "surfels": "surfels.usdc",
}
GGDS_PREFIX = "ggds_"
# Step layers GGDS runs are optimised on (a run records their inputs hashes as dependsOn).
DEPENDED_ON = ("surfels", "env")
_RUN_RE = re.compile(r"^ggds_[A-Za-z0-9_.-]+\.usdc$")
_LAYER_FILE_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*\.(usda|usdc|usd)$")
_TMP_RE = re.compile(r"^\..+\.tmp-(\d+)-[0-9a-f]{8}(\.[A-Za-z0-9]+)?$")


def chunk_prim_name(i: int, j: int) -> str:
    """Prim name of chunk (i, j); negative indices are written m<k> (Chunk_m1_0)."""
    def enc(k: int) -> str:
        return f"m{-k}" if k < 0 else str(k)
    return f"Chunk_{enc(int(i))}_{enc(int(j))}"


def parse_chunk_prim_name(name: str) -> tuple[int, int]:
    m = re.fullmatch(r"Chunk_(m?\d+)_(m?\d+)", name)
    if not m:
        raise ValueError(f"not a chunk prim name: {name!r}")
    dec = lambda s: -int(s[1:]) if s.startswith("m") else int(s)  # noqa: E731
    return dec(m.group(1)), dec(m.group(2))


def author_fallback_prim_types(layer: Sdf.Layer) -> None:
    """Merge lsd3d_usd.FALLBACK_PRIM_TYPES into the layer's ``fallbackPrimTypes`` metadata, so
    a USD reader without our plugin opening it as its root layer sees ParticleField prims."""
    info = dict(layer.pseudoRoot.GetInfo("fallbackPrimTypes")) \
        if layer.pseudoRoot.HasInfo("fallbackPrimTypes") else {}
    want = {t: Vt.TokenArray(list(f)) for t, f in lsd3d_usd.FALLBACK_PRIM_TYPES.items()}
    if any(list(info.get(t, ())) != list(v) for t, v in want.items()):
        info.update(want)
        layer.pseudoRoot.SetInfo("fallbackPrimTypes", info)


def new_stage() -> Usd.Stage:
    """In-memory stage with the scene conventions: Z up, metres, defaultPrim /World."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, WORLD)
    stage.SetDefaultPrim(world.GetPrim())
    return stage


# --------------------------------------------------------------------- provenance
def _usd_value(value: Any) -> Any:
    """Map Python values to ones customLayerData can hold (None dropped by caller)."""
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {str(k): _usd_value(v) for k, v in value.items() if v is not None}
    if hasattr(value, "tolist"):  # numpy scalars / arrays
        return _usd_value(value.tolist())
    if isinstance(value, (list, tuple)):
        # Plain Python lists become untyped VtValue vectors that usda cannot parse back.
        if value and all(isinstance(v, str) for v in value):
            return Vt.StringArray(list(value))
        if value and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            return Vt.DoubleArray([float(v) for v in value])
    return json.dumps(value, default=str)  # anything else, losslessly readable


def provenance(step: str, params: dict | None = None, seed: int | None = None,
               timings: dict | None = None, **extra: Any) -> dict:
    """How a layer was made: tool, version, step, time, seed, parameters, timings."""
    prov: dict[str, Any] = {
        "tool": "lsd3d-usd",
        "version": lsd3d_usd.__version__,
        "step": step,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "usd": ".".join(str(v) for v in Usd.GetVersion()),
    }
    if seed is not None:
        prov["seed"] = int(seed)
    if params:
        prov["params"] = params
    if timings:
        prov["timings"] = timings
    prov.update({k: v for k, v in extra.items() if v is not None})
    return _usd_value(prov)


def read_provenance(layer: Sdf.Layer) -> dict:
    return dict(layer.customLayerData.get("lsd3d", {}))


# ------------------------------------------------------------------ atomic writes
def _tmp_sibling(path: Path) -> Path:
    # Same folder (so os.replace is atomic) and same extension (USD picks the format by it).
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")


def save_layer(layer: Sdf.Layer, path: str | os.PathLike, provenance: dict | None = None) -> Path:
    """Write `layer` to `path` atomically; merge `provenance` into customLayerData["lsd3d"]."""
    path = Path(path).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    if provenance:
        data = dict(layer.customLayerData)
        lsd = dict(data.get("lsd3d", {}))
        lsd.update(provenance)
        data["lsd3d"] = lsd
        layer.customLayerData = data
    tmp = _tmp_sibling(path)
    try:
        if not layer.Export(str(tmp)):
            raise OSError(f"USD could not write {path}")
        _fsync(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    # A layer already open at this path in this process would keep serving old data.
    opened = Sdf.Layer.Find(str(path))
    if opened is not None and opened is not layer:
        opened.Reload(force=True)
    return path


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def clean_stale_temp_files(folder: Path) -> list[Path]:
    """Remove our temp files (``.<name>.tmp-<pid>-<hex><ext>``) whose writer process is gone
    (left by a kill -9 between write and rename). Returns what was removed."""
    removed = []
    if not Path(folder).is_dir():
        return removed
    for f in Path(folder).iterdir():
        m = _TMP_RE.match(f.name)
        if not m or not f.is_file():
            continue
        pid = int(m.group(1))
        if pid == os.getpid() or process_alive(pid):
            continue
        f.unlink(missing_ok=True)
        removed.append(f)
    return removed


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (signal 0; another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def save_stage(stage: Usd.Stage, path: str | os.PathLike, provenance: dict | None = None) -> Path:
    """Atomically write the stage's root layer to `path` (format from the extension)."""
    return save_layer(stage.GetRootLayer(), path, provenance)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    return atomic_write_parts(path, (data,))


def atomic_write_parts(path: str | os.PathLike, parts) -> Path:
    """Write the bytes-like ``parts`` one after another to ``path`` atomically (large
    contents written piece by piece, never joined in memory)."""
    path = Path(path).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(path)
    try:
        with open(tmp, "wb") as f:
            for part in parts:
                f.write(part)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


# ------------------------------------------------------------------- USD opening
def open_stage(path: str | os.PathLike, load: bool = True) -> Usd.Stage:
    """Open any USD file with one clear error for missing, non-USD or corrupt files."""
    p = Path(path)
    if p.is_dir() and (p / ROOT_FILE).is_file():
        p = p / ROOT_FILE
    if not p.exists():
        raise InputError(f"{path}: no such file")
    if p.is_dir():
        raise InputError(f"{path}: is a folder without {ROOT_FILE}")
    if not p.suffix or not Sdf.FileFormat.FindByExtension(p.suffix.lstrip(".")):
        raise InputError(f"{path}: not a USD file (unknown extension {p.suffix!r})")
    check_regular(p)
    if p.name == ROOT_FILE:
        check_special_files(p.parent)
    try:
        stage = Usd.Stage.Open(str(p), Usd.Stage.LoadAll if load else Usd.Stage.LoadNone)
    except Exception as e:  # Tf.ErrorException: syntax errors, truncated crate files
        raise InputError(f"{path}: cannot be read as USD: {_first_line(e)}") from None
    if stage is None:
        raise InputError(f"{path}: cannot be read as USD")
    return stage


def check_regular(p: Path, what: str = "file") -> None:
    """Refuse (one line) a FIFO, socket or device where a file is read: opening a FIFO blocks
    until something writes to it, a device reads forever."""
    try:
        mode = os.stat(p).st_mode
    except OSError:
        return                                   # missing: the caller's own message
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise InputError(f"{p}: not a regular {what} (a FIFO, socket or device); refusing to "
                         "read it")


def check_special_files(folder: Path, limit: int = 200_000) -> None:
    """Refuse a scene folder holding a FIFO, socket or device anywhere (a tar archive can carry
    one): a layer, chunk or texture read from it would hang the command."""
    n = 0
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in filenames + [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]:
            check_regular(Path(dirpath) / name)
            n += 1
            if n >= limit:                      # a folder this large is checked elsewhere
                return


def first_error_line(e: Exception) -> str:
    """The message of a USD (Tf) error without its C++ location preamble, one line."""
    return _first_line(e)


def _first_line(e: Exception) -> str:
    text = " ".join(str(e).split())
    # Tf errors read "Error in 'func' at line N in file F : 'message'"; keep the message.
    m = re.search(r" in file \S+ : '(.+?)'(?: Error in |$)", text)
    return (m.group(1) if m else text)[:400]


# ------------------------------------------------------------------------ scene
@dataclass
class LayerInfo:
    name: str           # "surfels", "ggds_20261122-001500", ...
    path: Path
    exists: bool
    muted: bool
    provenance: dict

    @property
    def is_run(self) -> bool:
        return self.name.startswith(GGDS_PREFIX)

    @property
    def stale(self) -> bool:
        return bool(self.provenance.get("stale"))


@dataclass(frozen=True)
class RunFiles:
    """Where one GGDS run keeps its files beside its layer: ggds/<run>/ (see ggds/run/store.py)."""
    dir: Path
    summary: Path           # summary.json of the run
    legacy_state: Path      # state.pt of older versions (pickle: never loaded)


def order_layers(files: Iterable[str]) -> list[str]:
    """Strongest first: GGDS runs (newest first: run names sort by time), then fixed steps
    strong→weak (surfels, cameras, actors, env, proxy, layout), then anything else by name."""
    files = set(files)
    runs = sorted((f for f in files if f.startswith(GGDS_PREFIX)), reverse=True)
    steps = [f for f in reversed(list(STEP_LAYERS.values())) if f in files]
    other = sorted(files - set(runs) - set(steps))
    return runs + steps + other


class Scene:
    """A scene folder: root layer + step layers under layers/."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).absolute()

    # ---- paths
    @property
    def root_layer_path(self) -> Path:
        return self.root / ROOT_FILE

    def layer_path(self, name: str) -> Path:
        """Path of a step layer by step name ("proxy") or file name ("ggds_x.usdc")."""
        file_name = STEP_LAYERS.get(name, name)
        if name not in STEP_LAYERS and not _RUN_RE.match(file_name):
            raise InputError(f"unknown scene layer {name!r}; steps: {', '.join(STEP_LAYERS)} "
                             "or ggds_<run>.usdc")
        return self.root / LAYERS_DIR / file_name

    @staticmethod
    def _rel(file_name: str) -> str:
        return f"./{LAYERS_DIR}/{file_name}"

    def inside(self, path: str | os.PathLike, what: str = "path") -> Path:
        """``path`` resolved, refused with one line unless it lies inside the scene folder."""
        p = Path(path)
        p = (p if p.is_absolute() else self.root / p).resolve()
        if not p.is_relative_to(self.root.resolve()):
            raise InputError(f"{self.root}: {what} {str(path)!r} lies outside the scene folder; "
                             "refusing to read, write or delete it")
        return p

    def check_writable(self) -> None:
        """Refuse (one line) a scene whose folders the steps rewrite and prune (layers/,
        ggds/, textures/) are, or hold, symbolic links: a re-run would write and delete
        through them, outside the scene. Called before a command changes anything."""
        for d in WRITTEN_DIRS:
            safepaths.check_tree(self.root / d, self.root, f"scene folder {d}/")

    def run_files(self, run: str) -> RunFiles:
        run = Path(run).stem if run.endswith(".usdc") else run
        if not _RUN_RE.match(f"{run}.usdc"):
            raise InputError(f"{self.root}: {run!r} is not a GGDS run name (ggds_<name>)")
        d = self.root / RUNS_DIR / run
        return RunFiles(d, d / "summary.json", d / "state.pt")

    @property
    def assets_dir(self) -> Path:
        return self.root / ASSETS_DIR

    @property
    def textures_dir(self) -> Path:
        return self.root / TEXTURES_DIR

    # ---- create / open
    @classmethod
    def create(cls, root: str | os.PathLike, *, seed: int = 0, chunk_size: float = 100.0,
               extent: tuple | None = None, exist_ok: bool = False) -> "Scene":
        scene = cls(root)
        if scene.root_layer_path.exists() and not exist_ok:
            raise InputError(f"{scene.root}: already holds a scene ({ROOT_FILE})")
        for d in (LAYERS_DIR, TEXTURES_DIR, ASSETS_DIR):
            (scene.root / d).mkdir(parents=True, exist_ok=True)
        stage = new_stage()
        world = stage.GetPrimAtPath(WORLD)
        world.AddAppliedSchema(lsd3d_usd.SCENE_API)
        world.CreateAttribute("lsd3d:scene:generator", Sdf.ValueTypeNames.String,
                              variability=Sdf.VariabilityUniform).Set("lsd3d-usd")
        world.CreateAttribute("lsd3d:scene:version", Sdf.ValueTypeNames.String,
                              variability=Sdf.VariabilityUniform).Set(lsd3d_usd.__version__)
        world.CreateAttribute("lsd3d:scene:seed", Sdf.ValueTypeNames.Int,
                              variability=Sdf.VariabilityUniform).Set(int(seed))
        world.CreateAttribute("lsd3d:scene:chunkSize", Sdf.ValueTypeNames.Double,
                              variability=Sdf.VariabilityUniform).Set(float(chunk_size))
        if extent is not None:
            (x0, y0, z0), (x1, y1, z1) = extent
            world.CreateAttribute("lsd3d:scene:extent", Sdf.ValueTypeNames.Double3Array,
                                  variability=Sdf.VariabilityUniform).Set(
                [(x0, y0, z0), (x1, y1, z1)])
        stage.GetRootLayer().documentation = "lsd3d-usd scene: root layer (metadata + subLayers)"
        author_fallback_prim_types(stage.GetRootLayer())
        if scene.root_layer_path.exists():  # exist_ok: keep the existing stack
            old = Sdf.Layer.FindOrOpen(str(scene.root_layer_path))
            stage.GetRootLayer().subLayerPaths = list(old.subLayerPaths)
            data = dict(stage.GetRootLayer().customLayerData)
            if "lsd3d" in old.customLayerData:
                data["lsd3d"] = old.customLayerData["lsd3d"]
            stage.GetRootLayer().customLayerData = data
        save_layer(stage.GetRootLayer(), scene.root_layer_path,
                   provenance("scene", seed=seed, chunkSize=float(chunk_size)))
        return scene

    @classmethod
    def open(cls, root: str | os.PathLike) -> "Scene":
        """The scene in folder ``root``, also given as its root layer (``root/scene.usda``)."""
        p = Path(root)
        if p.name == ROOT_FILE and p.is_file():
            root = p.parent
        elif p.is_file():
            raise InputError(f"{p}: not an lsd3d-usd scene (give the scene folder or its {ROOT_FILE})")
        scene = cls(root)
        if not scene.root_layer_path.is_file():
            raise InputError(f"{scene.root}: not an lsd3d-usd scene folder (no {ROOT_FILE})")
        scene._root_layer()  # fail early and clearly if unreadable
        for d in (scene.root, scene.root / LAYERS_DIR):
            clean_stale_temp_files(d)
        return scene

    def _root_layer(self) -> Sdf.Layer:
        try:
            layer = Sdf.Layer.FindOrOpen(str(self.root_layer_path))
        except Exception as e:
            raise InputError(f"{self.root_layer_path}: cannot be read as USD: {_first_line(e)}") from None
        if layer is None:
            raise InputError(f"{self.root_layer_path}: cannot be read as USD")
        layer.Reload()
        return layer

    # ---- the layer stack
    def _layer_file(self, entry: str, what: str) -> str:
        """A stack entry ("./layers/x.usdc") or muted name ("x.usdc") → its plain file name
        inside layers/; anything pointing elsewhere is refused."""
        e = str(entry)
        for prefix in (f"./{LAYERS_DIR}/", f"{LAYERS_DIR}/"):
            if e.startswith(prefix):
                e = e[len(prefix):]
                break
        if not _LAYER_FILE_RE.match(e):
            raise InputError(f"{self.root_layer_path}: {what} {str(entry)!r} is not a layer file "
                             f"inside {LAYERS_DIR}/; refusing to use it (edit {ROOT_FILE})")
        return e

    def _stack_files(self, layer: Sdf.Layer) -> list[str]:
        return [self._layer_file(p, "sublayer") for p in layer.subLayerPaths]

    def _muted_files(self, layer: Sdf.Layer) -> list[str]:
        muted = layer.customLayerData.get("lsd3d", {}).get("mutedLayers", []) or []
        return [self._layer_file(m, "muted layer") for m in muted]

    def muted_files(self) -> list[str]:
        """File names of the persistently muted layers."""
        return self._muted_files(self._root_layer())

    def _write_root(self, layer: Sdf.Layer, stack: Iterable[str], muted: Iterable[str]) -> None:
        layer.subLayerPaths = [self._rel(f) for f in order_layers(stack)]
        author_fallback_prim_types(layer)   # scenes made before it was authored get it too
        data = dict(layer.customLayerData)
        lsd = dict(data.get("lsd3d", {}))
        muted = order_layers(muted)
        if muted:
            lsd["mutedLayers"] = Vt.StringArray(muted)
        else:
            lsd.pop("mutedLayers", None)
        data["lsd3d"] = lsd
        layer.customLayerData = data
        save_layer(layer, self.root_layer_path)

    def write_layer(self, name: str, stage_or_layer, provenance: dict | None = None, *,
                    retire_runs: bool = False) -> Path:
        """Atomically write a step's layer and put it in the stack (unmuted). A layer that GGDS
        runs depend on (DEPENDED_ON) is guarded: see :meth:`guard_step_layer`."""
        if name in DEPENDED_ON:
            self.guard_step_layer(name, (provenance or {}).get("inputsHash"), retire_runs)
        layer = stage_or_layer.GetRootLayer() if isinstance(stage_or_layer, Usd.Stage) else stage_or_layer
        path = save_layer(layer, self.layer_path(name), provenance)
        root = self._root_layer()
        muted = [m for m in self._muted_files(root) if m != path.name]
        self._write_root(root, self._stack_files(root) + [path.name], muted)
        return path

    def add_layer(self, name: str) -> None:
        """Put an existing layer file into the stack."""
        path = self.layer_path(name)
        if not path.is_file():
            raise InputError(f"{path}: no such layer file")
        root = self._root_layer()
        self._write_root(root, self._stack_files(root) + [path.name],
                         [m for m in self._muted_files(root) if m != path.name])

    def layers(self) -> list[LayerInfo]:
        """Active and muted layers, strongest first."""
        root = self._root_layer()
        active, muted = self._stack_files(root), self._muted_files(root)
        infos = []
        for f in order_layers(set(active) | set(muted)):
            path = self.root / LAYERS_DIR / f
            prov = {}
            if path.is_file():
                try:
                    prov = read_provenance(Sdf.Layer.FindOrOpen(str(path)))
                except Exception:
                    prov = {}
            infos.append(LayerInfo(Path(f).stem, path, path.is_file(), f in muted and f not in active, prov))
        return infos

    def _resolve(self, name: str) -> str:
        root = self._root_layer()
        known = self._stack_files(root) + self._muted_files(root)
        for f in known:
            if name in (f, Path(f).stem) or STEP_LAYERS.get(name) == f:
                return f
        raise InputError(f"{self.root}: no layer {name!r} in the stack "
                         f"(layers: {', '.join(Path(f).stem for f in known) or 'none'})")

    def mute(self, name: str) -> None:
        f = self._resolve(name)
        root = self._root_layer()
        self._write_root(root, [s for s in self._stack_files(root) if s != f],
                         self._muted_files(root) + [f])

    def unmute(self, name: str) -> None:
        f = self._resolve(name)
        root = self._root_layer()
        self._write_root(root, self._stack_files(root) + [f],
                         [m for m in self._muted_files(root) if m != f])

    def remove_layer(self, name: str, delete_file: bool = False) -> None:
        f = self._resolve(name)
        root = self._root_layer()
        layer_file, run_dir = self.root / LAYERS_DIR / f, None
        if delete_file:   # everything checked before the root layer changes
            safepaths.check_inside(layer_file, self.root, "layer")
            if f.startswith(GGDS_PREFIX):
                run_dir = self.run_files(f).dir
                if run_dir.exists() or run_dir.is_symlink():
                    safepaths.check_tree(run_dir, self.root, "run folder")
                else:
                    run_dir = None
        self._write_root(root, [s for s in self._stack_files(root) if s != f],
                         [m for m in self._muted_files(root) if m != f])
        if delete_file:
            layer_file.unlink(missing_ok=True)
            if run_dir is not None:
                safepaths.rmtree(run_dir, self.root, "run folder")

    # ---- GGDS runs and what they depend on
    def runs(self) -> list[LayerInfo]:
        """GGDS run layers (muted ones included), newest first."""
        return [li for li in self.layers() if li.is_run]

    def unfinished_runs(self) -> list[str]:
        """Runs that can be resumed (a plan not marked complete, or an older version's
        checkpoint, which --resume then refuses by name), newest first."""
        d = self.root / RUNS_DIR
        if not d.is_dir():
            return []
        names = []
        for p in d.iterdir():
            if not (p.is_dir() and p.name.startswith(GGDS_PREFIX)):
                continue
            plan = p / "run.json"
            if (p / "state.pt").is_file() and not plan.is_file():
                names.append(p.name)
                continue
            try:
                if plan.is_file() and not json.loads(plan.read_text()).get("complete"):
                    names.append(p.name)
            except (OSError, ValueError):
                names.append(p.name)   # unreadable: --resume names the file
        return sorted(names, reverse=True)

    def layer_inputs_hash(self, name: str) -> str | None:
        path = self.layer_path(name)
        if not path.is_file():
            return None
        return read_provenance(Sdf.Layer.FindOrOpen(str(path))).get("inputsHash")

    def dependent_runs(self, changes: dict[str, str]) -> list[str]:
        """Active, not yet stale GGDS runs that depend on a step layer whose inputs hash would
        change: ``changes`` maps a step name ("surfels", "env", ...) to its new inputs hash.
        A run without a recorded ``dependsOn`` (older versions) is taken to depend on the
        layers as they are now."""
        out = []
        current = {k: self.layer_inputs_hash(k) for k in changes}
        for li in self.runs():
            if li.muted or li.stale or not li.exists:
                continue
            dep = li.provenance.get("dependsOn")
            dep = json.loads(dep) if isinstance(dep, str) else dict(dep or {})
            for step, new in changes.items():
                old = dep.get(step, current.get(step))
                if old is not None and old != new:
                    out.append(li.name)
                    break
        return out

    def guard_step_layer(self, name: str, new_hash: str | None, retire_runs: bool = False) -> None:
        """Before step layer ``name`` is replaced by one made from inputs ``new_hash`` (None:
        unknown, so different): refuse if active GGDS runs were optimised on the current one,
        or with ``retire_runs`` retire them (muted, marked stale)."""
        new = new_hash or f"unhashed-{uuid.uuid4().hex}"
        stale = self.dependent_runs({name: new})
        if not stale:
            return
        if not retire_runs:
            raise InputError(f"{self.root}: this would replace the scene's {name}, which GGDS "
                             f"run(s) {', '.join(stale)} were optimised on; pass --retire-runs "
                             "to do it (the runs are muted and marked stale), or write "
                             "elsewhere")
        self.retire_runs(stale, f"{name} replaced (inputs {new[:16]})")

    def retire_runs(self, names: Iterable[str], reason: str) -> None:
        """Mute runs and mark them stale in their own provenance (kept, visibly, for
        comparison; `scene unmute` brings one back on purpose)."""
        for name in names:
            path = self.layer_path(f"{name}.usdc")
            layer = Sdf.Layer.FindOrOpen(str(path))
            save_layer(layer, path, {"stale": reason})
            self.mute(name)

    def new_run_name(self, prefix: str = "ggds") -> str:
        """A fresh, sortable GGDS run name: ggds_<UTC time>[_<k>]."""
        stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S")
        base, k = f"{prefix}_{stamp}", 1
        name = base
        while (self.root / LAYERS_DIR / f"{name}.usdc").exists():
            k += 1
            name = f"{base}_{k}"
        return name

    def open_stage(self, load: bool = True) -> Usd.Stage:
        return open_stage(self.root_layer_path, load=load)
