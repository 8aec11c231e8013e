"""What the usdview menu items do, as plain functions of a stage, a camera and prims.

usdview itself is not needed here (usd-core ships none): the plugin module only gathers
the stage, camera, frame and selection from usdview's API and calls these.

Muting GGDS runs uses the stage's own layer muting (``Usd.Stage.MuteLayer``): it works on
any stage (a scene folder or any file whose layer stack holds ``ggds_*`` layers), changes no
file, and is undone by unmuting or reopening the stage. Runs muted *persistently* in a scene
(``lsd3d-usd scene mute``: removed from scene.usda's subLayers) are not in the layer stack;
they are listed as such and stay off until ``lsd3d-usd scene unmute``.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError

GGDS_PREFIX = "ggds_"
DEFAULT_MAX_WIDTH = 640     # CPU render size cap: interactive, not final quality


# ------------------------------------------------------------------------------ cameras
def _time_value(time_code):
    """usdview's frame (a Usd.TimeCode), a number or None -> a number or None (default)."""
    if time_code is None:
        return None
    if hasattr(time_code, "IsDefault"):
        return None if time_code.IsDefault() else float(time_code.GetValue())
    return float(time_code)


def _fit(size, max_width: int | None, aspect: float) -> tuple[int, int]:
    w, h = size if size and size[0] > 0 and size[1] > 0 else (960, round(960 / aspect))
    if max_width and w > max_width:
        h = max(1, round(h * max_width / w))
        w = max_width
    return int(w), int(h)


def view_camera(camera_prim=None, gf_camera=None, time=None, size=None,
                max_width: int | None = DEFAULT_MAX_WIDTH):
    """Our Camera for usdview's view: its camera prim if one is chosen, else the free camera
    (a Gf.Camera). ``size`` is the viewport in pixels (aspect kept, width capped)."""
    # local import: usdview loads the plugin at start: kept lazy
    from pxr import Usd, UsdGeom

    # local import: usdview loads the plugin at start: kept lazy
    from lsd3d_usd.render.camera import from_usd

    t = _time_value(time)
    if camera_prim is not None and camera_prim.IsValid():
        prim = camera_prim
    elif gf_camera is not None:
        # Author the free camera on a scratch stage so one conversion (from_usd) serves both.
        scratch = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageMetersPerUnit(scratch, 1.0)
        cam = UsdGeom.Camera.Define(scratch, "/FreeCamera")
        cam.SetFromCamera(gf_camera, Usd.TimeCode.Default())
        prim, t = cam.GetPrim(), None
    else:
        raise InputError("usdview: no camera (neither a camera prim nor the free camera)")
    cam = UsdGeom.Camera(prim)
    tc = Usd.TimeCode.Default() if t is None else Usd.TimeCode(t)
    aspect = float(cam.GetHorizontalApertureAttr().Get(tc)) / float(cam.GetVerticalApertureAttr().Get(tc))
    w, h = _fit(size, max_width, aspect)
    return from_usd(prim, t, w, h)


# ---------------------------------------------------------------------------- rendering
@dataclass
class RenderResult:
    frame: object             # views.frame.Frame (rgb scene-linear, alpha, depth, ...)
    image: np.ndarray         # (H, W, 3) uint8 sRGB, tone-mapped: what is shown
    surfels: int
    seconds: float


def render_view(stage, camera, time=None, use_env: bool = True, exposure: float = 0.0,
                tonemap: str = "aces", textures=None) -> RenderResult:
    """Render the stage as `lsd3d-usd render` does (surfels, actors at the frame's time, env
    behind) with our CPU rasteriser. Muted layers are respected: the stage is read as
    composed now. textures: a views.stage_data.TextureCache kept across calls (the env
    texture is then decoded once)."""
    # local import: usdview loads the plugin at start: kept lazy
    from lsd3d_usd.views.frame import render_scene
    from lsd3d_usd.views.images import display_uint8
    # local import: usdview loads the plugin at start: kept lazy
    from lsd3d_usd.views.stage_data import SceneReader

    t = _time_value(time)
    t0 = _time.perf_counter()
    reader = SceneReader(stage, use_env=use_env, textures=textures)
    field = reader.surfels(t)
    if field is None:
        raise InputError(f"{stage.GetRootLayer().identifier}: no surfels to render (no visible "
                         "ParticleField prim with particles)")
    frame = render_scene(reader, camera, t)
    image = display_uint8(frame.rgb, exposure, tonemap)
    return RenderResult(frame, np.ascontiguousarray(image), int(field.n), _time.perf_counter() - t0)


def save_png(result: RenderResult, path, exposure: float = 0.0) -> Path:
    """The rendered frame as an 8-bit sRGB PNG (atomic write)."""
    # local import: usdview loads the plugin at start: kept lazy
    from lsd3d_usd.views.images import write_frame
    return write_frame(Path(path), result.frame, "png", exposure)


# ------------------------------------------------------------------------- GGDS layers
@dataclass
class RunLayer:
    name: str                 # "ggds_20261122-101500"
    identifier: str           # layer identifier ("" when only muted in the scene file)
    muted: bool               # muted on this stage (session) or in the scene file
    persistent: bool          # muted in the scene file: not in the layer stack
    steps: int | None
    complete: bool | None

    def label(self) -> str:
        state = "muted in scene file" if self.persistent else ("muted" if self.muted else "active")
        extra = f", {self.steps} steps" if self.steps is not None else ""
        if self.complete is False:
            extra += ", unfinished"
        return f"{self.name} [{state}{extra}]"


def _is_run(identifier: str) -> bool:
    name = Path(identifier.split(":", 1)[-1] if "://" in identifier else identifier).name
    return name.startswith(GGDS_PREFIX) and name.endswith((".usdc", ".usda", ".usd"))


def _run_info(layer) -> tuple[int | None, bool | None]:
    data = dict(layer.customLayerData).get("lsd3d", {}) if layer is not None else {}
    steps = data.get("stepsDone")
    complete = data.get("complete")
    return (int(steps) if steps is not None else None,
            bool(complete) if complete is not None else None)


def ggds_runs(stage) -> list[RunLayer]:
    """GGDS run layers of the stage, newest first: those in its layer stack (muted or not)
    and those a scene's root layer lists as persistently muted."""
    # local import: usdview loads the plugin at start: kept lazy
    from pxr import Sdf

    runs: dict[str, RunLayer] = {}
    muted = {Path(m).name for m in stage.GetMutedLayers()}
    for layer in stage.GetLayerStack(includeSessionLayers=False):
        if _is_run(layer.identifier):
            name = Path(layer.identifier).stem
            steps, complete = _run_info(layer)
            runs[name] = RunLayer(name, layer.identifier, Path(layer.identifier).name in muted,
                                  False, steps, complete)
    # Muted layers are absent from GetLayerStack: find them among the sublayer paths.
    root = stage.GetRootLayer()
    for sub in _sublayer_identifiers(root):
        if _is_run(sub) and Path(sub).stem not in runs:
            layer = Sdf.Layer.FindOrOpen(sub) if Path(sub).is_file() else None
            steps, complete = _run_info(layer)
            runs[Path(sub).stem] = RunLayer(Path(sub).stem, sub, stage.IsLayerMuted(sub), False,
                                            steps, complete)
    for info in _scene_runs(root):
        if info.muted and info.name not in runs:
            layer = Sdf.Layer.FindOrOpen(str(info.path)) if info.exists else None
            steps, complete = _run_info(layer)
            runs[info.name] = RunLayer(info.name, "", True, True, steps, complete)
    return sorted(runs.values(), key=lambda r: r.name, reverse=True)


def _scene_runs(root) -> list:
    """The runs a scene folder lists (persistently muted ones included), when the stage's
    root layer is a scene's scene.usda; [] for any other file."""
    # local import: usdview loads the plugin at start: kept lazy
    from lsd3d_usd import scene as S
    if not root.realPath or Path(root.realPath).name != S.ROOT_FILE:
        return []
    try:
        return S.Scene.open(Path(root.realPath).parent).runs()
    except InputError:
        return []


def _sublayer_identifiers(layer, seen=None) -> list[str]:
    seen = set() if seen is None else seen
    out = []
    for p in layer.subLayerPaths:
        ident = layer.ComputeAbsolutePath(p)
        if ident in seen:
            continue
        seen.add(ident)
        out.append(ident)
        # local import: usdview loads the plugin at start: kept lazy
        from pxr import Sdf
        sub = Sdf.Layer.FindOrOpen(ident) if Path(ident).is_file() else None
        if sub is not None:
            out += _sublayer_identifiers(sub, seen)
    return out


def _find(stage, name: str) -> RunLayer:
    runs = ggds_runs(stage)
    for r in runs:
        if name in (r.name, r.identifier):
            return r
    raise InputError(f"no GGDS run {name!r} in this stage (runs: "
                     f"{', '.join(r.name for r in runs) or 'none'})")


def set_run_muted(stage, name: str, muted: bool) -> RunLayer:
    """Mute or unmute one GGDS run on this stage (session only; no file changes)."""
    run = _find(stage, name)
    if run.persistent:
        raise InputError(f"{run.name}: muted in the scene file; run `lsd3d-usd scene unmute "
                         f"<scene> {run.name}` to bring it back")
    if muted:
        stage.MuteLayer(run.identifier)
    else:
        stage.UnmuteLayer(run.identifier)
    return _find(stage, name)


def unmute_all_runs(stage) -> int:
    """Unmute every session-muted GGDS run; returns how many were unmuted."""
    n = 0
    for r in ggds_runs(stage):
        if r.muted and not r.persistent:
            stage.UnmuteLayer(r.identifier)
            n += 1
    return n


def solo_next_run(stage) -> str:
    """Cycle for A/B comparison: all runs active -> only the newest -> only the next ->
    ... -> no run (initial surfels) -> all runs active. Returns what is shown now."""
    runs = [r for r in ggds_runs(stage) if not r.persistent]
    if not runs:
        return "no GGDS runs to compare"
    active = [r for r in runs if not r.muted]
    if len(active) == len(runs) and len(runs) > 1:
        target = 0                                  # all on -> solo the newest
    elif len(active) == 1:
        k = runs.index(active[0]) + 1
        target = k if k < len(runs) else None       # past the oldest -> none
    elif not active:
        target = "all"
    else:
        target = 0                                  # a hand-made mix -> restart the cycle
    if len(runs) == 1:                              # one run: toggle it
        target = None if not runs[0].muted else "all"
    for i, r in enumerate(runs):
        want_muted = not (target == "all" or target == i)
        if want_muted != r.muted:
            (stage.MuteLayer if want_muted else stage.UnmuteLayer)(r.identifier)
    if target == "all":
        return f"all {len(runs)} GGDS run(s) active"
    if target is None:
        return "no GGDS run: initial surfels"
    return f"only {runs[target].name}"


# --------------------------------------------------------------------------- statistics
def surfel_prims_for(stage, prims) -> list:
    """The surfel (ParticleField) prims among ``prims`` and beneath them; with nothing
    selected, every surfel prim of the stage."""
    # local import: usdview loads the plugin at start: kept lazy
    from lsd3d_usd.splats.usdio import is_particle_field, surfel_prims

    prims = [p for p in (prims or []) if p is not None and p.IsValid()]
    if not prims:
        return surfel_prims(stage)
    out, seen = [], set()
    for p in prims:
        found = [p] if is_particle_field(p) else surfel_prims(stage, str(p.GetPath()))
        for q in found:
            if q.GetPath() not in seen:
                seen.add(q.GetPath())
                out.append(q)
    return out


def selection_stats(stage, prims) -> list[dict]:
    # local import: usdview loads the plugin at start: kept lazy
    from lsd3d_usd.inspection import surfel_stats
    found = surfel_prims_for(stage, prims)
    if not found:
        where = ", ".join(str(p.GetPath()) for p in prims or []) or "the stage"
        raise InputError(f"no surfel (ParticleField) prim in {where}")
    return [surfel_stats(p) for p in found]


def format_stats(stats: list[dict]) -> str:
    lines = []
    for s in stats:
        lines.append(f"{s['path']} ({s['type']}): {s['count']:,} surfels, SH degree {s['sh_degree']}")
        if s["count"]:
            lo, hi = s["extent"]
            lines.append(f"  extent      {lo} .. {hi}")
            for key, label in (("opacity", "opacity"), ("scale_max", "scale max"),
                               ("scale_aspect", "aspect")):
                q = s[key]
                lines.append(f"  {label:11s} min {q['min']:.4g}  median {q['median']:.4g}  "
                             f"p95 {q['p95']:.4g}  max {q['max']:.4g}")
            lines.append(f"  mean colour {s['color_dc_mean']}")
            if s.get("classes"):
                top = sorted(s["classes"].items(), key=lambda kv: -kv[1])
                lines.append("  classes     " + ", ".join(f"{k} {v:,}" for k, v in top))
    return "\n".join(lines)
