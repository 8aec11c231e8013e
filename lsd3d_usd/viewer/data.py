"""The viewer's one door into a scene: everything it reads from the composed stage.

Only this module calls the stage-reading functions of the rest of the package (surfels, env
map, layout, actors, proxy, layer stack, cameras, validation); the server and the packing work
on the plain arrays and dicts it returns. When those functions move, only this file changes.

The viewer never writes the scene: the layer toggles compose an in-memory root layer that
copies the scene's root (metadata, /World opinions) and lists only the chosen layer files,
and the environment variant is selected in the stage's session layer.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdLux

from lsd3d_usd import scene as S
from lsd3d_usd.actors.relight import lighting_from_stage
from lsd3d_usd.actors.usdio import ActorSet
from lsd3d_usd.env.farfield import FarField
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.usdio import layout_from_stage
from lsd3d_usd.proxy.usdio import read_proxy
from lsd3d_usd.render.camera import from_usd
from lsd3d_usd.semantics import CLASS_COLORS, CLASS_ID
from lsd3d_usd.views.stage_data import read_dome, scene_surfels

GGDS = "ggds"
ENV_VARIANT_SET = "environment"


@dataclass
class LayerEntry:
    name: str              # "ggds_20261201-164339", "surfels", ...
    file: str              # file name under layers/
    kind: str              # "ggds" (toggleable in the viewer) or "step"
    active: bool           # in the scene's own stack (not muted there)
    exists: bool
    provenance: dict


@dataclass
class EnvData:
    """A DomeLight's latlong map with its gain applied (scene-linear RGB, float32), and the
    far field drawn with it (env.farfield: what read_dome's EnvMap.pixels draws)."""
    image: np.ndarray              # (h, w, 3)
    world_from_dome: np.ndarray    # (3, 3)
    pole_axis: str                 # "Z" or "Y"
    source: str                    # the light's prim path
    far_field: FarField | None = None   # the ground beyond the scene, in the image's units
                                        # (the dome's gain applied), or None


@dataclass
class ActorData:
    path: str
    role: str
    meshes: list                   # [(vertices (V,3) f64 actor frame, faces (F,3), colors (F,3))]
    transforms: list               # one 4x4 world-from-actor per time code
    visible: list                  # one bool per time code


@dataclass
class CameraData:
    path: str
    focal_length: float
    h_aperture: float
    v_aperture: float
    h_offset: float
    v_offset: float
    near: float
    far: float
    times: list                    # time codes of the poses ([None] for a static camera)
    poses: list                    # 4x4 world-from-camera, OpenCV axes (x right, y down, z ahead)


@dataclass
class Lighting:
    sh: np.ndarray                 # (9, 3) irradiance SH
    sun_dir: np.ndarray
    sun_map: np.ndarray
    sun_residual: np.ndarray
    reference: float


@dataclass
class TimeRange:
    start: float
    end: float
    codes_per_second: float
    codes: list = field(default_factory=list)


class SceneSource:
    """A scene folder opened for viewing (read-only)."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).absolute()
        if self.root.name == S.ROOT_FILE and self.root.is_file():
            self.root = self.root.parent          # the scene's root layer names its folder
        if not self.root.is_dir():
            raise InputError(f"{root}: no such scene folder")
        if not (self.root / S.ROOT_FILE).is_file():
            raise InputError(f"{root}: not an lsd3d-usd scene folder (no {S.ROOT_FILE})")
        self._scene = S.Scene(self.root)
        self.unreadable: dict[str, str] = {}    # layer file -> why it was left out

    @property
    def root_file(self) -> Path:
        return self._scene.root_layer_path

    # ---------------------------------------------------------------- layer stack
    def layers(self) -> list[LayerEntry]:
        out = []
        for info in self._scene.layers():
            kind = GGDS if info.name.startswith(S.GGDS_PREFIX) else "step"
            out.append(LayerEntry(info.name, info.path.name, kind, not info.muted, info.exists,
                                  _plain(info.provenance)))
        return out

    def run_files(self, name: str) -> list[str]:
        """Scene-relative paths of a GGDS run's plots and summary (those that exist)."""

        folder = self.root / "ggds" / name
        if not name.startswith(S.GGDS_PREFIX) or not folder.is_dir():
            return []
        return [f"ggds/{name}/{p.name}" for p in sorted(folder.iterdir())
                if p.suffix in (".png", ".json") and p.is_file()]

    def open_stage(self, layer_files: list[str], env_variant: str | None = None, load: bool = True):
        """The scene composed from ``layer_files`` (names under layers/, strongest first) on an
        in-memory copy of the root layer, with ``env_variant`` selected in the session layer."""

        try:
            root = Sdf.Layer.FindOrOpen(str(self.root_file))
        except Exception as e:  # Tf errors of a corrupt root layer
            raise InputError(f"{self.root_file}: cannot be read as USD: {' '.join(str(e).split())[:300]}") from None
        if root is None:
            raise InputError(f"{self.root_file}: cannot be read as USD")
        anon = Sdf.Layer.CreateAnonymous("viewer_root.usda")
        anon.TransferContent(root)
        paths = []
        for f in layer_files:
            p = self.root / S.LAYERS_DIR / f
            if Path(f).name != f or f in (".", "..") or not p.is_file():
                raise InputError(f"{self.root}: layer {f!r} is not a file under {S.LAYERS_DIR}/")
            if self._readable(p):
                paths.append(str(p))
        anon.subLayerPaths = paths
        try:
            stage = Usd.Stage.Open(anon, Usd.Stage.LoadAll if load else Usd.Stage.LoadNone)
        except Exception as e:
            raise InputError(f"{self.root}: cannot compose the stage: {' '.join(str(e).split())[:300]}") from None
        if env_variant:
            self._select_env(stage, env_variant)
        return stage

    def _readable(self, path: Path) -> bool:
        """Open a layer on its own first: a damaged one is left out of the composition (USD would
        skip it with a warning on stderr) and remembered in ``unreadable`` for the problem list."""

        try:
            ok = Sdf.Layer.FindOrOpen(str(path)) is not None
            msg = "cannot be read as USD"
        except Exception as e:  # Tf errors: truncated or foreign files
            ok, msg = False, f"cannot be read as USD: {' '.join(str(e).split())[:300]}"
        if not ok:
            self.unreadable[str(path.relative_to(self.root))] = msg
        return ok

    def surfel_stage(self, layer_files: list[str]):
        """Like open_stage, with only the surfel prims' payloads loaded (not the proxy's)."""

        stage = self.open_stage(layer_files, None, load=False)
        if stage.GetPrimAtPath(S.SURFELS_PATH):
            stage.Load(S.SURFELS_PATH)
        return stage

    def used_files(self, stage) -> list[Path]:
        """Every file the composed stage read (layers, references, payloads)."""
        out = []
        for layer in stage.GetUsedLayers():
            if layer.anonymous or not layer.realPath:
                continue
            out.append(Path(layer.realPath))
        return sorted(set(out))

    # --------------------------------------------------------------------- metadata
    def chunk_size(self, stage) -> float:
        world = stage.GetPrimAtPath(S.WORLD)
        attr = world.GetAttribute("lsd3d:scene:chunkSize") if world else None
        size = float(attr.Get()) if attr and attr.HasValue() else 100.0
        if not np.isfinite(size) or size <= 0:
            raise InputError(f"{self.root_file}: lsd3d:scene:chunkSize = {size} (must be a positive size in metres)")
        return size

    def time_range(self, stage) -> TimeRange:
        tcps = float(stage.GetTimeCodesPerSecond() or 24.0)
        return TimeRange(float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode()), tcps)

    # ------------------------------------------------------------------------ surfels
    def surfel_fields(self, stage):
        """Static surfels in world space (not actors' or cameras'), one SurfelField per read.
        Today the scene holds one monolithic prim, so this yields one field (or nothing)."""

        f = scene_surfels(stage, check=False)    # problems are listed, not refused (validate's)
        if f is not None and f.n:
            yield f

    # ---------------------------------------------------------------------------- env
    def env_variants(self, stage) -> tuple[list[str], str | None]:
        env = stage.GetPrimAtPath(S.ENV_PATH)
        if not env or not env.GetVariantSets().HasVariantSet(ENV_VARIANT_SET):
            return [], None
        vs = env.GetVariantSets().GetVariantSet(ENV_VARIANT_SET)
        return list(vs.GetVariantNames()), vs.GetVariantSelection() or None

    def _select_env(self, stage, name: str) -> None:
        names, _ = self.env_variants(stage)
        if name not in names:
            raise InputError(f"environment variant {name!r} is not among {names or 'none'}")
        with Usd.EditContext(stage, stage.GetSessionLayer()):
            stage.GetPrimAtPath(S.ENV_PATH).GetVariantSets().GetVariantSet(ENV_VARIANT_SET) \
                .SetVariantSelection(name)

    def env(self, stage) -> EnvData | None:
        """The first visible DomeLight's map, or None. The texture must lie in the scene folder."""

        for prim in Usd.PrimRange(stage.GetPseudoRoot()):
            if not (prim.IsA(UsdLux.DomeLight) or prim.IsA(UsdLux.DomeLight_1)):
                continue
            kind = UsdLux.DomeLight if prim.IsA(UsdLux.DomeLight) else UsdLux.DomeLight_1
            asset = kind(prim).GetTextureFileAttr().Get()
            path = (asset.resolvedPath or asset.path) if asset else ""
            if path and not self.inside(path):
                raise InputError(f"{prim.GetPath()}.inputs:texture:file: {asset.path!r} resolves outside "
                                 f"the scene folder; the viewer reads files inside {self.root} only")

        env = read_dome(stage)
        if env is None:
            return None
        return EnvData(env.image, np.asarray(env.world_from_dome, np.float64), env.pole_axis, env.source,
                       env.far_field)

    def lighting(self, stage) -> Lighting:
        light = lighting_from_stage(stage)
        return Lighting(np.asarray(light.sh, np.float64), np.asarray(light.sun_dir, np.float64),
                        np.asarray(light.sun_map, np.float64), np.asarray(light.sun_residual, np.float64),
                        float(light.reference))

    # -------------------------------------------------------------------------- layout
    def layout(self, stage):
        """The scene's Layout (layout.model), or None without /World/Layout."""

        if not stage.GetPrimAtPath(S.LAYOUT_PATH):
            return None
        return layout_from_stage(stage, str(self.root))

    # --------------------------------------------------------------------------- proxy
    def proxy_file(self) -> Path | None:
        p = self._scene.layer_path("proxy")
        return p if p.is_file() else None

    def proxy_chunk(self, key: tuple[int, int]) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
        """The proxy meshes of one chunk: [(class, vertices (V,3), faces (F,3), rgb (3,))]."""

        path = self.proxy_file()
        if path is None:
            return []
        out = []
        for cm in read_proxy(path, chunks=[key]).get(tuple(key), {}).values():
            k = CLASS_ID.get(cm.cls)
            rgb = np.asarray(CLASS_COLORS[k] if k is not None else (0.5, 0.5, 0.5), np.float32)
            out.append((cm.cls, np.asarray(cm.vertices, np.float64), np.asarray(cm.faces, np.int64), rgb))
        return out

    def proxy_chunk_keys(self) -> list[tuple[int, int]]:
        """Chunks present in the proxy layer (their payloads are not loaded)."""

        path = self.proxy_file()
        if path is None:
            return []
        stage = S.open_stage(path, load=False)
        root = stage.GetPrimAtPath(S.PROXY_PATH)
        keys = []
        if root:
            for child in root.GetFilteredChildren(Usd.PrimIsActive & Usd.PrimIsDefined & ~Usd.PrimIsAbstract):
                try:
                    keys.append(S.parse_chunk_prim_name(child.GetName()))
                except ValueError:
                    continue
        return sorted(keys)

    # -------------------------------------------------------------------------- actors
    def actors(self, stage, max_samples: int = 2000) -> tuple[list[float], list[ActorData]]:
        """Actors with their meshes (actor frame) and world transforms at shared time codes."""

        aset = ActorSet(stage)
        if not len(aset):
            return [], []
        times: set[float] = set()
        for a in aset.actors:
            times.update(_xform_times(stage.GetPrimAtPath(a.path)))
        codes = _sample_codes(sorted(times), max_samples) or [float(Usd.TimeCode.EarliestTime().GetValue())]
        mats = [aset.transforms(t) for t in codes]
        vis = [aset.visible(t) for t in codes]
        out = []
        for k, a in enumerate(aset.actors):
            meshes = [(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64),
                       np.asarray(m.colors, np.float32)) for m in a.meshes]
            out.append(ActorData(a.path, a.role, meshes, [mats[i][k] for i in range(len(codes))],
                                 [bool(vis[i][k]) for i in range(len(codes))]))
        return codes, out

    # ------------------------------------------------------------------------- cameras
    def cameras(self, stage, max_samples: int = 2000) -> list[CameraData]:
        out = []
        for prim in Usd.PrimRange(stage.GetPseudoRoot()):
            if not prim.IsA(UsdGeom.Camera):
                continue
            cam = UsdGeom.Camera(prim)
            times = _sample_codes(sorted(_xform_times(prim)), max_samples) or [None]
            try:
                poses = [from_usd(prim, t).pose for t in times]
            except InputError:
                continue  # orthographic / degenerate cameras: nothing the viewer can look through
            clip = cam.GetClippingRangeAttr().Get()
            out.append(CameraData(
                str(prim.GetPath()), float(cam.GetFocalLengthAttr().Get()),
                float(cam.GetHorizontalApertureAttr().Get()), float(cam.GetVerticalApertureAttr().Get()),
                float(cam.GetHorizontalApertureOffsetAttr().Get() or 0.0),
                float(cam.GetVerticalApertureOffsetAttr().Get() or 0.0),
                float(clip[0]), float(clip[1]), times, poses))
        return out

    # ---------------------------------------------------------------------- validation
    def validate(self, timeout: float = 600.0) -> list[dict]:
        """The scene's validation problems as dicts (severity, where, message), from
        `lsd3d-usd validate --json` in a child process: validation captures the process's fd 2
        while it runs, which in the server's own process would swallow its log."""

        try:
            r = subprocess.run([sys.executable, "-m", "lsd3d_usd", "validate", str(self.root), "--json"],
                               capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return [{"severity": "warning", "where": "validate", "message": f"validation took over {timeout:.0f} s; skipped"}]
        try:
            report = json.loads(r.stdout)
        except ValueError:
            msg = (r.stderr.strip().splitlines() or [f"exit status {r.returncode}"])[-1]
            return [{"severity": "error", "where": "validate", "message": msg.removeprefix("lsd3d-usd: error: ")}]
        return [{"severity": p["severity"], "where": p["prim"] + (f".{p['attribute']}" if p.get("attribute") else ""),
                 "message": p["message"]} for p in report.get("problems", [])]

    # -------------------------------------------------------------------------- files
    def inside(self, path: str | os.PathLike) -> bool:
        """True when ``path`` (symlinks resolved) lies inside the scene folder."""
        try:
            real = Path(os.path.realpath(path))
            return real == Path(os.path.realpath(self.root)) or \
                real.is_relative_to(Path(os.path.realpath(self.root)))
        except (OSError, ValueError):
            return False


def _xform_times(prim) -> set[float]:
    """Time samples of the transforms of ``prim`` and its ancestors (what moves it)."""

    times: set[float] = set()
    p = prim
    while p and p.GetPath().pathString != "/":
        if p.IsA(UsdGeom.Xformable):
            times.update(float(t) for t in UsdGeom.Xformable(p).GetTimeSamples())
        p = p.GetParent()
    return times


def _sample_codes(times: list[float], limit: int) -> list[float]:
    if len(times) <= limit:
        return times
    return [float(t) for t in np.linspace(times[0], times[-1], limit)]


def _plain(value):
    """customLayerData values (Vt arrays, nested dicts) as JSON-ready Python values."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    if hasattr(value, "__len__") and not isinstance(value, (bytes, bytearray)):
        try:
            return [_plain(v) for v in value]
        except TypeError:
            pass
    return str(value)
