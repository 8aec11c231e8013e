"""What the viewer serves, independent of HTTP: scene description, per-chunk surfel buffers,
env maps, proxy and layout overlays, actors, scene files.

Surfel buffers depend on which GGDS runs are enabled (a "configuration"). A configuration's
id is a content hash: of the packing version, the chunk size and the bytes of every file its
composed stage reads. Its chunk buffers are built once (the surfels binned into the scene's
chunk grid) and cached under SCENE/viewer_cache/surfels_<id>/, so a second start, or a page
reload, reads no USD for them. A folder without write permission caches in a temp folder.

Scene reading goes through `data.SceneSource` only.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

import numpy as np

from lsd3d_usd import safepaths
from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import VIEWER_PROBLEMS
from lsd3d_usd.scene import atomic_write_bytes
from lsd3d_usd.semantics import CLASS_COLORS, CLASS_ID
from lsd3d_usd.viewer import pack
from lsd3d_usd.viewer.data import GGDS, SceneSource

CACHE_DIR = "viewer_cache"
KEEP_CONFIGS = 6              # surfel caches kept per scene (the oldest are removed)
MAX_PROBLEMS = int(VIEWER_PROBLEMS.value)   # problems listed (memory and page size bounded)
MAX_RUNS_ASKED = 1000         # run names in one /api/config request
SCENE_FILE_SUFFIXES = (".png", ".jpg", ".json", ".txt", ".md", ".usda", ".csv", ".html")


@dataclass
class ChunkEntry:
    i: int
    j: int
    n: int
    lo: list
    hi: list
    bytes: int


@dataclass
class Config:
    id: str
    layers: list                       # layer files, strongest first
    runs: list                         # enabled GGDS run names
    folder: Path
    chunks: dict = field(default_factory=dict)   # (i, j) -> ChunkEntry
    sh_degree: int = 0
    semantic_classes: list = field(default_factory=list)
    seconds: float = 0.0
    cached: bool = False

    def describe(self) -> dict:
        n = sum(c.n for c in self.chunks.values())
        size = sum(c.bytes for c in self.chunks.values())
        return {"id": self.id, "runs": self.runs, "layers": self.layers, "surfels": n,
                "bytes": size, "bytesPerSurfel": round(size / n, 2) if n else 0.0,
                "shDegree": self.sh_degree, "semanticClasses": self.semantic_classes,
                "semanticColors": _class_colors(self.semantic_classes),
                "buildSeconds": round(self.seconds, 3), "cached": self.cached,
                "chunks": [{"i": c.i, "j": c.j, "n": c.n, "lo": c.lo, "hi": c.hi, "bytes": c.bytes,
                            "url": f"/api/chunk/{self.id}/{c.i}_{c.j}"}
                           for c in sorted(self.chunks.values(), key=lambda c: (c.i, c.j))]}


class ViewerService:
    """One scene folder, read-only, for the browser viewer. Thread-safe: USD access is
    serialised by one lock; built buffers are immutable."""

    def __init__(self, root, *, validate: bool = True, log=None):
        self.src = SceneSource(root)
        self.root = self.src.root
        self.log = log or (lambda msg: None)
        self.lock = threading.RLock()
        self.problems: list[dict] = []
        self._problems_dropped = 0
        self.configs: dict[str, Config] = {}
        self._digests: dict = {}
        self._stages: dict = {}
        self._env: dict = {}
        self._proxy: dict = {}
        self._json: dict = {}
        self.cache_root = self._cache_root()
        self.layers = self._read("layer stack", self.src.layers, default=[])
        self.default_runs = [e.name for e in self.layers if e.kind == GGDS and e.active and e.exists]
        self.validation_done = threading.Event()
        if validate:
            threading.Thread(target=self._validate, name="validate", daemon=True).start()
        else:
            self.validation_done.set()

    # ------------------------------------------------------------------------ helpers
    def _problem(self, where: str, message: str, severity: str = "error") -> None:
        entry = {"severity": severity, "where": where[:200], "message": message[:1000]}
        with self.lock:
            if entry in self.problems or self._problems_dropped:
                self._problems_dropped += entry not in self.problems
                return
            if len(self.problems) >= MAX_PROBLEMS:   # bounded: the page shows the first ones
                self._problems_dropped = 1
                self.problems.append({"severity": "warning", "where": "viewer",
                                      "message": f"more than {MAX_PROBLEMS} problems; "
                                                 "the rest are not listed"})
                return
            self.problems.append(entry)
        self.log(f"{severity}: {where}: {message}")

    def _read(self, what: str, fn, *args, default=None):
        """Run a scene read; a failure becomes a listed problem (the page still opens)."""
        try:
            with self.lock:
                return fn(*args)
        except InputError as e:
            self._problem(what, str(e))
        except Exception as e:  # Tf / OIIO errors of damaged files: one line, listed in the UI
            self._problem(what, f"{type(e).__name__}: {' '.join(str(e).split())[:400]}")
        return default

    def _validate(self) -> None:
        try:
            found = self.src.validate()
        except InputError as e:
            found = [{"severity": "error", "where": "validate", "message": str(e)}]
        except Exception as e:
            found = [{"severity": "error", "where": "validate",
                      "message": f"{type(e).__name__}: {' '.join(str(e).split())[:400]}"}]
        for p in found:
            self._problem(p["where"], p["message"], p["severity"])
        self.validation_done.set()

    def _cache_root(self) -> Path:
        folder = self.root / CACHE_DIR
        try:
            # A planted link (viewer_cache -> elsewhere) would make the cache write and
            # evict there: never follow one, cache in a temp folder instead.
            safepaths.check_tree(folder, self.root, "viewer cache")
        except InputError as e:
            tmp = Path(tempfile.mkdtemp(prefix="lsd3d-viewer-"))
            self._problem("cache", f"{e}; caching buffers in {tmp} for this run", "warning")
            return tmp
        try:
            folder.mkdir(exist_ok=True)
            probe = folder / f".probe-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
            return folder
        except OSError:
            tmp = Path(tempfile.mkdtemp(prefix="lsd3d-viewer-"))
            self._problem("cache", f"{folder} is not writable; caching buffers in {tmp} for this run",
                          "warning")
            return tmp

    def _digest(self, path: Path) -> str:
        st = path.stat()
        key = (str(path), st.st_size, st.st_mtime_ns)
        if key not in self._digests:
            h = hashlib.sha256()
            with open(path, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
            self._digests[key] = h.hexdigest()
        return self._digests[key]

    def _layer_files(self, runs: list[str]) -> list[str]:
        """The stack to compose: the scene's active step layers plus the chosen runs."""
        known = {e.name: e for e in self.layers}
        unknown = [r for r in runs if r not in known or known[r].kind != GGDS]
        if unknown:
            raise InputError(f"no GGDS run {unknown[0]!r} in the scene "
                             f"(runs: {', '.join(e.name for e in self.layers if e.kind == GGDS) or 'none'})")
        chosen = set(runs)
        return [e.file for e in self.layers if e.exists
                and ((e.kind == GGDS and e.name in chosen) or (e.kind != GGDS and e.active))]

    def stage(self, runs: list[str] | None = None, env_variant: str | None = None):
        runs = self.default_runs if runs is None else runs
        files = self._layer_files(runs)
        key = (tuple(files), env_variant)
        with self.lock:
            if key not in self._stages:
                if len(self._stages) > 8:
                    self._stages.clear()
                self._stages[key] = self.src.open_stage(files, env_variant)
                self._unreadable()
            return self._stages[key]

    def _unreadable(self) -> None:
        for f, msg in self.src.unreadable.items():
            self._problem(f, f"{msg}; left out of the view")

    # ------------------------------------------------------------------- configuration
    def config(self, runs: list[str] | None = None) -> Config:
        """The configuration with these GGDS runs enabled (default: the scene's own), its
        chunk buffers built or found in the cache."""
        runs = list(self.default_runs if runs is None else runs)
        with self.lock:
            files = self._layer_files(runs)
            stage = self.src.surfel_stage(files)
            self._unreadable()
            size = self.src.chunk_size(stage)
            h = hashlib.sha256(f"LSDV{pack.CHUNK_VERSION}|{size!r}|".encode())
            for p in self.src.used_files(stage):
                rel = os.path.relpath(p, self.root)
                h.update(f"{rel}|{self._digest(p)}|".encode())
            cid = h.hexdigest()[:20]
            if cid in self.configs:
                return self.configs[cid]
            folder = self.cache_root / f"surfels_{cid}"
            cfg = Config(cid, files, sorted(runs), folder)
            if not self._load_index(cfg):
                self._build(cfg, stage, size)
            self.configs[cid] = cfg
            self._evict()
            return cfg

    def _load_index(self, cfg: Config) -> bool:
        index = cfg.folder / "index.json"
        try:
            data = json.loads(index.read_text())
            if not isinstance(data, dict) or data.get("version") != pack.CHUNK_VERSION:
                return False                   # another packing version: rebuilt, not misread
            chunks = {}
            for c in data["chunks"]:
                e = ChunkEntry(int(c["i"]), int(c["j"]), int(c["n"]), c["lo"], c["hi"], int(c["bytes"]))
                f = cfg.folder / f"chunk_{e.i}_{e.j}.bin"
                if f.stat().st_size != e.bytes:
                    return False
                chunks[(e.i, e.j)] = e
        except (OSError, ValueError, KeyError, TypeError):
            return False
        cfg.chunks, cfg.sh_degree = chunks, int(data.get("shDegree", 0))
        cfg.semantic_classes = list(data.get("semanticClasses", []))
        cfg.cached = True
        os.utime(cfg.folder)  # most recently used: kept by _evict
        return True

    def _build(self, cfg: Config, stage, size: float) -> None:
        t0 = time.perf_counter()
        groups: dict = {}
        classes: list = []
        deg = 0
        for f in self.src.surfel_fields(stage):
            if f.semantic_classes and not classes:
                classes = list(f.semantic_classes)
            deg = max(deg, min(f.sh_degree, pack.MAX_SH_DEGREE))   # higher bands not sent
            for key, idx in pack.bin_by_chunk(f.positions, size).items():
                groups.setdefault(key, []).append((f, idx))
        tmp = cfg.folder.with_name(cfg.folder.name + f".tmp{os.getpid()}")
        safepaths.rmtree(tmp, self.cache_root, "viewer cache folder")
        tmp.mkdir(parents=True)
        chunks = {}
        for key, parts in groups.items():
            pos = np.concatenate([f.positions[i] for f, i in parts])
            quat = np.concatenate([f.orientations[i] for f, i in parts])
            scl = np.concatenate([f.scales[i] for f, i in parts])
            opa = np.concatenate([f.opacities[i] for f, i in parts])
            sh = np.concatenate([_sh_deg(f.sh[i], deg) for f, i in parts])
            sem = None
            if classes and all(f.semantic_ids is not None and list(f.semantic_classes) == classes
                               for f, _ in parts):
                sem = np.concatenate([f.semantic_ids[i] for f, i in parts])
            buf = pack.pack_chunk(key, pos, quat, scl, opa, sh, sem)
            atomic_write_bytes(tmp / f"chunk_{key[0]}_{key[1]}.bin", buf)
            chunks[key] = ChunkEntry(int(key[0]), int(key[1]), len(pos), pos.min(0).tolist(),
                                     pos.max(0).tolist(), len(buf))
        cfg.chunks, cfg.sh_degree, cfg.semantic_classes = chunks, deg, classes
        cfg.seconds = time.perf_counter() - t0
        index = {"version": pack.CHUNK_VERSION, "layers": cfg.layers, "runs": cfg.runs,
                 "chunkSize": size, "shDegree": deg, "semanticClasses": classes,
                 "chunks": [vars(c) for c in chunks.values()]}
        atomic_write_bytes(tmp / "index.json", json.dumps(index).encode())
        safepaths.rmtree(cfg.folder, self.cache_root, "viewer cache folder")
        safepaths.replace(tmp, cfg.folder, self.cache_root, "viewer cache folder")
        n = sum(c.n for c in chunks.values())
        self.log(f"built {n} surfels in {len(chunks)} chunks for layers {', '.join(cfg.layers)} "
                 f"in {cfg.seconds:.2f} s")

    def _evict(self) -> None:
        olds = sorted((p for p in self.cache_root.glob("surfels_*")
                       if p.is_dir() and not p.is_symlink()),
                      key=lambda p: p.stat().st_mtime, reverse=True)
        live = {c.folder for c in self.configs.values()}
        for p in olds[KEEP_CONFIGS:]:
            if p not in live and p.parent == self.cache_root:
                try:
                    safepaths.rmtree(p, self.cache_root, "viewer cache folder")
                except (InputError, OSError) as e:
                    self._problem("cache", f"{p}: not removed: {e}", "warning")

    def chunk_bytes(self, cid: str, key: tuple[int, int]) -> bytes | None:
        cfg = self.configs.get(cid)
        if cfg is None or key not in cfg.chunks:
            return None
        return (cfg.folder / f"chunk_{key[0]}_{key[1]}.bin").read_bytes()

    # -------------------------------------------------------------------------- scene
    def scene_info(self) -> dict:
        stage = self._read("stage", self.stage)
        info: dict = {"name": self.root.name, "chunkSize": 100.0,
                      "layers": [], "env": {"variants": [], "selected": None}, "cameras": [],
                      "time": {"start": 0.0, "end": 0.0, "codesPerSecond": 24.0}}
        for e in self.layers:
            info["layers"].append({"name": e.name, "file": e.file, "kind": e.kind, "active": e.active,
                                   "exists": e.exists, "provenance": _summary(e.provenance),
                                   "files": self.src.run_files(e.name) if e.kind == GGDS else []})
        if stage is not None:
            size = self._read("chunk size", self.src.chunk_size, stage)
            if size:
                info["chunkSize"] = size
            names, sel = self._read("environment", self.src.env_variants, stage, default=([], None))
            info["env"] = {"variants": names, "selected": sel}
            tr = self._read("time range", self.src.time_range, stage)
            if tr:
                info["time"] = {"start": tr.start, "end": tr.end, "codesPerSecond": tr.codes_per_second}
            cams = self._read("cameras", self.src.cameras, stage, default=[])
            info["cameras"] = [{"path": c.path, "focalLength": c.focal_length, "hAperture": c.h_aperture,
                                "vAperture": c.v_aperture, "hOffset": c.h_offset, "vOffset": c.v_offset,
                                "near": c.near, "far": c.far,
                                "times": [t for t in c.times] if c.times != [None] else [],
                                "poses": [_mat(p) for p in c.poses]} for c in cams]
            info["proxyChunks"] = [list(k) for k in self._read("proxy", self.src.proxy_chunk_keys, default=[])]
        info["defaultRuns"] = self.default_runs
        info["problems"] = list(self.problems)
        info["validating"] = not self.validation_done.is_set()
        return info

    def config_info(self, runs: list[str] | None) -> dict:
        if runs is not None:   # a request naming unknown runs is a bad request, no scene problem
            if len(runs) > MAX_RUNS_ASKED:
                raise InputError(f"{len(runs)} runs asked for; at most {MAX_RUNS_ASKED}")
            with self.lock:
                self._layer_files(runs)
        try:
            cfg = self.config(runs)
        except InputError as e:
            self._problem("surfels", str(e))
            raise
        except Exception as e:
            msg = f"{type(e).__name__}: {' '.join(str(e).split())[:400]}"
            self._problem("surfels", msg)
            raise InputError(msg) from None
        return cfg.describe()

    def problem_list(self) -> dict:
        return {"problems": list(self.problems), "validating": not self.validation_done.is_set()}

    # ---------------------------------------------------------------------------- env
    def env_info(self, variant: str | None) -> dict:
        """Metadata of one environment variant (its map URL, dome frame, actor lighting)."""
        key = variant or ""
        if key in self._env:
            return self._env[key][0]
        with self.lock:
            stage = self.stage(None, variant)
            env = self.src.env(stage)
            light = self.src.lighting(stage)
        info = {"variant": variant, "map": None,
                "lighting": {"sh": light.sh.tolist(), "sunDir": light.sun_dir.tolist(),
                             "sunMap": light.sun_map.tolist(), "sunResidual": light.sun_residual.tolist(),
                             "reference": light.reference}}
        data = None
        if env is not None:
            data = pack.pack_env(env.image)
            w, h = pack.ENV_HEADER.unpack_from(data, 0)[3:5]
            info["map"] = {"url": "/api/envmap/" + _quote(key or "_"), "width": w, "height": h,
                           "worldFromDome": env.world_from_dome.tolist(), "poleAxis": env.pole_axis,
                           "source": env.source}
            if env.far_field is not None:
                # the ground beyond the scene (env/farfield.py), its radiance in the map's units:
                # pack_env sends the map's values unscaled (half floats), the gain already in both
                ff = env.far_field
                info["map"]["farField"] = {
                    "height": float(ff.height),
                    "radiance": [float(v) for v in ff.radiance],
                    "ground": [float(v) for v in ff.ground],
                    "fogDensity": float(ff.fog_density)}
        self._env[key] = (info, data)
        return info

    def env_bytes(self, variant: str) -> bytes | None:
        key = "" if variant == "_" else variant
        if key not in self._env:
            return None
        return self._env[key][1]

    # -------------------------------------------------------------------- overlays
    def layout_info(self) -> dict:
        if "layout" not in self._json:
            stage = self.stage()
            lay = self._read("layout", self.src.layout, stage) if stage is not None else None
            self._json["layout"] = _layout_json(lay)
        return self._json["layout"]

    def actors_info(self) -> dict:
        if "actors" not in self._json:
            stage = self.stage()
            codes, actors = self._read("actors", self.src.actors, stage, default=([], []))
            meshes, index = [], {}
            out = []
            for a in actors:
                key = hashlib.sha1(b"".join(np.ascontiguousarray(x).tobytes()
                                            for m in a.meshes for x in m)).hexdigest()
                if key not in index:
                    index[key] = len(meshes)
                    meshes.append(_actor_mesh(a.meshes))
                out.append({"path": a.path, "role": a.role, "mesh": index[key],
                            "transforms": [_mat(m) for m in a.transforms], "visible": a.visible})
            self._json["actors"] = {"times": codes, "meshes": meshes, "actors": out}
        return self._json["actors"]

    def proxy_bytes(self, key: tuple[int, int]) -> bytes | None:
        if key not in self._proxy:
            parts = self._read("proxy", self.src.proxy_chunk, key, default=None)
            if parts is None:
                return None
            self._proxy[key] = pack.pack_mesh([(v, f, rgb) for _, v, f, rgb in parts])
        return self._proxy[key]

    # ------------------------------------------------------------------------ files
    def scene_file(self, rel: str) -> Path | None:
        """A file of the scene folder by its relative path, or None. ``rel`` must already be
        a plain relative path (the server refuses '..', absolute and encoded ones); this checks
        again after resolving symlinks, and serves only documents and images."""
        path = self.root / rel
        if not self.src.inside(path) or not path.is_file():
            return None
        if path.suffix.lower() not in SCENE_FILE_SUFFIXES:
            return None
        if Path(os.path.realpath(path)).is_relative_to(Path(os.path.realpath(self.cache_root))):
            return None
        return path


def _class_colors(classes) -> list:
    return [[float(v) for v in (CLASS_COLORS[CLASS_ID[c]] if c in CLASS_ID else (0.5, 0.5, 0.5))]
            for c in classes]


def _sh_deg(sh: np.ndarray, deg: int) -> np.ndarray:
    """(N,K,3) coefficients as (N,(deg+1)^2,3): higher bands dropped, missing ones zero."""
    k = (deg + 1) ** 2
    if sh.shape[1] >= k:
        return sh[:, :k]
    out = np.zeros((len(sh), k, 3), np.float32)
    out[:, :sh.shape[1]] = sh
    return out


def _mat(m) -> list:
    """4x4 column-vector matrix as 16 numbers, column-major (WebGL's order)."""
    return [round(float(v), 6) for v in np.asarray(m, np.float64).T.reshape(-1)]


def _quote(s: str) -> str:
    return quote(s, safe="")


def _summary(prov: dict) -> dict:
    """The provenance fields worth showing in the layer list."""
    keep = ("step", "created", "seed", "prompt", "stepsDone", "complete", "timings", "metrics")
    return {k: prov[k] for k in keep if k in prov}


def _actor_mesh(meshes) -> dict:
    """One actor's meshes as flat arrays, one colour per face (vertices not shared)."""
    pos, col = [], []
    for v, f, c in meshes:
        tri = np.asarray(v, np.float64)[np.asarray(f, np.int64)]          # (F,3,3)
        pos.append(tri.reshape(-1, 3))
        col.append(np.repeat(np.asarray(c, np.float64).reshape(-1, 3), 3, axis=0))
    p = np.concatenate(pos) if pos else np.zeros((0, 3))
    c = np.concatenate(col) if col else np.zeros((0, 3))
    return {"positions": np.round(p, 4).reshape(-1).tolist(), "colors": np.round(c, 4).reshape(-1).tolist()}


def _pts(a) -> list:
    a = np.asarray(a, np.float64)
    if a.ndim == 2 and a.shape[1] == 2:
        a = np.concatenate([a, np.zeros((len(a), 1))], 1)
    return np.round(a, 3).reshape(-1).tolist()


def _layout_json(layout) -> dict:
    if layout is None:
        return {"lanes": [], "lines": []}
    lanes, lines = [], []
    for f in layout.features():
        kind = type(f).__name__
        if kind == "LaneCenter":
            lanes.append({"id": f.id, "points": _pts(f.points), "successors": list(f.successors),
                          "predecessors": list(f.predecessors), "type": f.lane_type,
                          "speedLimit": float(f.speed_limit_mps), "junction": bool(f.is_junction)})
            continue
        try:
            coords = f.coords()
        except Exception:
            continue
        c = np.asarray(coords, np.float64)
        if c.ndim != 2 or len(c) < 2:
            continue
        closed = kind in ("Crosswalk", "Sidewalk", "RoadArea", "VegetationZone", "Building", "ParkingSpot")
        lines.append({"id": f.id, "kind": kind, "points": _pts(c), "closed": closed})
    return {"lanes": lanes, "lines": lines}
