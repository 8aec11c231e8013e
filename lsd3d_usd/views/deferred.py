"""Deferred rendering, the paper's last step: each rendered frame x0 goes through the scene's
image prior from a low noise level T with N steps, conditioned on the proxy G-buffer of the
same camera, and the result is the frame shown ("deferred", after deferred neural rendering).

    sp = load_scene_prior("out/crossing")            # the prior GGDS used, its env, the proxy
    out = defer_frames(frames, cameras, sp, strength=0.3, steps=5)

What the prior does at T is the prior's own `target` (ggds/prior_base.py), exactly as GGDS
asks it: the diffusion prior VAE-encodes the frame, inverts it with deterministic DDIM to T,
takes N guided DDIM steps back with the disparity ControlNet and decodes; the procedural prior
blends its world-space shading of the G-buffer into a guided filter of the frame.

Temporal consistency: a frame's result is a pure function of (frame, camera, scene). Nothing
random is drawn per frame: the diffusion prior's inversion is deterministic (DDIM, eta 0, the
VAE's posterior mean), and the procedural prior's noise is world-space lattice noise seeded per
surface point (ggds/noise.py), so it is fixed in the world and moves with the surfaces. The
`seed` is handed unchanged to every frame's `target` (priors that draw noise from it get the
same draw each frame); the built-in priors do not use it.

Mesh actors are not in the proxy: the prior has no conditioning for them. Where an actor is in
front, the G-buffer carries the actor's depth (so a ControlNet sees its silhouette) with the
vehicle class, and the deferred frame keeps the raw pixel.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError

# Chosen by the strength sweep on the README sample's rig route (docs/render.md, "Deferred").
DEFAULT_STRENGTH = 0.3
DEFAULT_STEPS = 5
MAX_STEPS = 1000
SUFFIX = "_deferred"


def check_strength(t, where: str = "--deferred-strength") -> float:
    """The noise level T as a float in (0, 1]; one InputError line otherwise."""
    try:
        v = float(t)
    except (TypeError, ValueError):
        raise InputError(f"{where} {t!r}: not a number (a noise level in (0, 1])") from None
    if math.isnan(v) or not 0.0 < v <= 1.0:
        raise InputError(f"{where} {t}: must be in (0, 1] (0 would return the raw frame)")
    return v


def check_steps(n, where: str = "--deferred-steps") -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= int(n) <= MAX_STEPS:
        raise InputError(f"{where} {n!r}: must be an integer from 1 to {MAX_STEPS}")
    return int(n)


def check_prior_name(spec, where: str = "--deferred-prior") -> str:
    """A registered prior's name (with its argument): one InputError line otherwise."""
    from lsd3d_usd.ggds.priors.registry import PRIORS
    name = str(spec).split(":", 1)[0]
    if name not in PRIORS.names():
        known = ", ".join(f"{n}:DIR" if PRIORS.get(n).takes_arg else n for n in PRIORS.names())
        raise InputError(f"{where} {spec!r}: unknown prior; known: {known}")
    return str(spec)


def check_device(device, where: str = "--deferred-device") -> str:
    d = str(device)
    if d != "cpu" and not (d == "cuda" or (d.startswith("cuda:") and d[5:].isdigit())):
        raise InputError(f"{where} {device!r}: expected cpu, cuda or cuda:N")
    return d


def deferred_name(path) -> Path:
    """<stem>_deferred<suffix> beside ``path`` (Front.0003.png -> Front.0003_deferred.png)."""
    p = Path(path)
    return p.with_name(f"{p.stem}{SUFFIX}{p.suffix}")


# ------------------------------------------------------------------------ the scene's prior
@dataclass
class ScenePrior:
    """Everything deferral needs from a scene: its prior and what conditions it."""
    prior: object                 # ggds.prior_base.Prior
    env: object                   # ggds.prior_base.PriorEnv
    proxy: tuple                  # (V (n,3), F (m,3), face class ids (m,))
    shadow: object | None         # ggds.conditioning.ShadowMap of the sun, or None
    spec: str                     # the prior as configured: "procedural", "diffusers:DIR", ...
    source: str                   # where the choice came from
    seed: int                     # the scene's seed (the prior's material seed)
    setup_s: float = 0.0
    info: dict = field(default_factory=dict)

    def note(self) -> str | None:
        """A one-line warning where the prior will be slow (a diffusion model on the CPU)."""
        device = str(getattr(self.prior, "device", "cpu"))
        if hasattr(self.prior, "unet") and device == "cpu":
            return ("the diffusion prior runs on the CPU: an SD-1.5-sized model takes minutes per "
                    "frame here (a GPU path; docs/render.md has the measured figures)")
        return None

    def gbuffer(self, camera, fine: bool = False):
        """The proxy G-buffer of ``camera`` with sun visibility (as GGDS computes it), by
        default without ``fine``: deferral runs once per frame of a video, so a supersampling
        prior samples pixel centres here (4× less work per frame at 2×2), and actors overlaid
        on it would be missing from a finer one. ``fine``: as GGDS's training targets (eval's
        prior baseline)."""
        from lsd3d_usd.conditioning.gbuffer import table_gbuffer
        V, F, _ = self.proxy
        return table_gbuffer(camera, V, F, self.face_table, self.shadow, fine=fine)

    @cached_property
    def face_table(self):
        """The proxy's FaceTable, built once for every frame."""
        from lsd3d_usd.conditioning.gbuffer import FaceTable
        return FaceTable.of(*self.proxy)


def scene_root(path) -> Path:
    """The scene folder behind ``path``: a scene folder, its scene.usda, or a USD file that
    sublayers one (a rig's OUT/rig.usda). One InputError line otherwise."""
    from pxr import Sdf

    from lsd3d_usd import scene as S
    p = Path(path)
    if p.is_dir():
        if (p / S.ROOT_FILE).is_file():
            return p.absolute()
        raise InputError(f"{path}: deferral needs a scene folder (holding {S.ROOT_FILE})")
    if p.name == S.ROOT_FILE and p.is_file():
        return p.parent.absolute()
    layer = Sdf.Layer.FindOrOpen(str(p)) if p.is_file() else None
    if layer is not None:
        for sub in layer.subLayerPaths:
            q = Path(sub) if Path(sub).is_absolute() else p.parent / sub
            if q.name == S.ROOT_FILE and q.is_file():
                return q.parent.resolve()
    raise InputError(f"{path}: deferral needs a scene folder, its {S.ROOT_FILE}, or a file that "
                     f"sublayers one (the proxy, env and GGDS layers condition the prior)")


def _recorded_config(sc, run: str | None = None):
    """(generate configuration dict or None, the run it came from or None): of ``run`` (muted
    or not) when given, else of the newest unmuted run that records one."""
    if run is not None:
        runs = [li for li in sc.runs() if run in (li.name, li.path.name) and li.exists]
    else:
        runs = [li for li in sc.runs() if not li.muted and li.exists]
    for li in runs:
        raw = li.provenance.get("generate")
        if raw:
            try:
                return json.loads(raw), li.name
            except ValueError:
                raise InputError(f"{li.path}: customLayerData lsd3d.generate is not JSON") from None
    return None, (runs[0].name if runs else None)


def recorded_prior_name(scene_path, run: str | None = None) -> str:
    """The registered name of the prior the scene's GGDS run ``run`` (default: the newest
    unmuted one) recorded (the default prior's when none is recorded, as load_scene_prior
    falls back to it)."""
    from lsd3d_usd import scene as S
    from lsd3d_usd.ggds.priors.registry import PriorConfig
    recorded, _ = _recorded_config(S.Scene.open(scene_root(scene_path)), run)
    spec = ((recorded or {}).get("prior") or {}).get("name") or PriorConfig().name
    return str(spec).split(":", 1)[0]


def _scene_seed(sc) -> int:
    from pxr import Sdf

    from lsd3d_usd import scene as S
    prov = S.read_provenance(Sdf.Layer.FindOrOpen(str(sc.root_layer_path)))
    return int(prov.get("seed", 0))


def load_scene_prior(scene_path, prior: str | None = None, controlnet=None,
                     device: str | None = None, run: str | None = None,
                     purpose: str = "deferral", override: str = "--deferred-prior") -> ScenePrior:
    """The prior the scene's GGDS run ``run`` (default: the newest unmuted one) was made with
    (its recorded `generate` configuration), or ``prior`` ("procedural", "diffusers:DIR",
    another registered name) to override it; ``controlnet`` / ``device`` override those
    settings. Also the scene's env (as GGDS saw it: env layer parameters + its EXR), the
    proxy and a sun shadow map. ``purpose`` / ``override``: what the error lines name as
    needing the scene, and the flag that chooses another prior."""
    from lsd3d_usd import configtree
    from lsd3d_usd import scene as S
    from lsd3d_usd.env.params import EnvParams
    from lsd3d_usd.env.usdlayer import read_env_prim
    from lsd3d_usd.conditioning.shadow import shadow_map
    from lsd3d_usd.conditioning.light import scene_light
    from lsd3d_usd.ggds.priors.registry import PriorConfig, make_prior
    from lsd3d_usd.proxy.usdio import proxy_arrays

    t0 = time.perf_counter()
    sc = S.Scene.open(scene_root(scene_path))
    recorded, run = _recorded_config(sc, run)
    if recorded is not None:
        cfg = configtree.from_dict(PriorConfig, recorded.get("prior", {}))
        seed = int(recorded.get("seed", 0))
        prompt = (recorded.get("env") or {}).get("prompt") or ""
        source = f"recorded by GGDS run {run}"
    else:
        cfg, seed, prompt = PriorConfig(), _scene_seed(sc), ""
        source = (f"default (GGDS run {run} records no configuration)" if run
                  else "default (the scene has no GGDS run)")
    if prior is not None:
        cfg.name = check_prior_name(prior)
        source = override
    if controlnet is not None:
        cfg.controlnet = Path(controlnet)
    if device is not None:
        cfg.device = check_device(device)
    try:
        p = make_prior(cfg, seed=seed)
    except InputError as e:
        if prior is not None:
            raise
        raise InputError(f"the scene's prior ({source}): {e}; choose another with "
                         f"{override}") from None

    env_layer = next((li for li in sc.layers() if li.name == "env"), None)
    if env_layer is None or not env_layer.exists or "params" not in env_layer.provenance:
        raise InputError(f"{sc.layer_path('env')}: {purpose} needs the scene's env layer with "
                         "its parameters (customLayerData lsd3d.params)")
    try:
        params = EnvParams.from_dict(dict(env_layer.provenance["params"]))
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{env_layer.path}: unreadable env parameters ({e})") from None
    params.extras["prompt"] = prompt
    stage = sc.open_stage(load=False)
    texture = read_env_prim(stage).get("texture")
    if not texture or not Path(texture).is_file():
        raise InputError(f"{env_layer.path}: the env map texture {texture!r} is missing")
    light = scene_light(params, texture)
    proxy_path = sc.layer_path("proxy")
    if not proxy_path.is_file():
        raise InputError(f"{proxy_path}: {purpose} needs the scene's proxy layer (the prior's "
                         "G-buffer)")
    V, F, ids = proxy_arrays(proxy_path)
    shadow = shadow_map(V, F, light.sun_direction)
    return ScenePrior(p, light.prior_env, (V, F, ids), shadow, cfg.name, source, seed,
                      time.perf_counter() - t0, {"run": run, "exposure": light.exposure})


# ------------------------------------------------------------------------ one frame
def _overlay_actors(gb, camera, actor_mask: np.ndarray, depth: np.ndarray):
    """G-buffer pixels where an actor is in front take the actor's depth, the vehicle class,
    a camera-facing normal and the matching world position."""
    import torch

    from lsd3d_usd.semantics import class_id
    m = torch.from_numpy(np.asarray(actor_mask, bool))
    if not bool(m.any()):
        return gb
    z = torch.from_numpy(np.where(actor_mask, depth, 1.0).astype(np.float32))
    dirs = gb.view_dirs
    fwd = torch.from_numpy(camera.pose[:3, 2].astype(np.float32))
    pos = gb.camera_position + dirs * (z / (dirs @ fwd).clamp_min(1e-6))[..., None]
    gb.depth = torch.where(m, z, gb.depth)
    gb.world_pos = torch.where(m[..., None], pos, gb.world_pos)
    gb.normal = torch.where(m[..., None], -dirs, gb.normal)
    gb.semantic = torch.where(m, torch.full_like(gb.semantic, class_id("vehicle")), gb.semantic)
    if gb.sun_visibility is not None:
        gb.sun_visibility = torch.where(m, torch.ones_like(gb.sun_visibility), gb.sun_visibility)
    return gb


class Deferrer:
    """Defers frames of one scene with one prior, strength and step count."""

    def __init__(self, scene_prior: ScenePrior, strength: float = DEFAULT_STRENGTH,
                 steps: int = DEFAULT_STEPS, seed: int | None = None):
        self.sp = scene_prior
        self.strength = check_strength(strength)
        self.steps = check_steps(steps)
        self.seed = scene_prior.seed if seed is None else int(seed)
        self.frames = 0
        self.seconds = 0.0

    def defer(self, rgb: np.ndarray, camera, actor_mask: np.ndarray | None = None,
              depth: np.ndarray | None = None) -> np.ndarray:
        """The deferred (H, W, 3) float32 scene-linear image of one rendered frame ``rgb``
        (display-scaled radiance, as render_scene and GGDS produce) seen by ``camera``.
        ``actor_mask`` / ``depth``: where mesh actors are in front and their depth."""
        return self.images(rgb, camera, (self.strength,), actor_mask, depth)[0]

    def images(self, rgb: np.ndarray, camera, levels, actor_mask: np.ndarray | None = None,
               depth: np.ndarray | None = None, fine: bool = False) -> list:
        """The prior's images of one frame at each noise level in ``levels`` (one G-buffer for
        all): ``defer`` is levels = (strength,); eval adds t = 1, the prior's own image of the
        view, as the reference distribution."""
        import torch

        rgb = np.asarray(rgb, np.float32)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[:2] != (camera.height, camera.width):
            raise InputError(f"deferral: frame of shape {rgb.shape} does not match the camera's "
                             f"{camera.width}x{camera.height}")
        levels = [check_strength(t, "deferral noise level") for t in levels]
        t0 = time.perf_counter()
        gb = self.sp.gbuffer(camera, fine=fine)
        if actor_mask is not None:
            gb = _overlay_actors(gb, camera, actor_mask, depth)
        # a key of its own, forgotten below: a prior's per-view cache would otherwise keep
        # every frame's derived images (up to its bound) for views never seen again
        gb.key = key = object()
        x = torch.from_numpy(np.clip(np.nan_to_num(rgb, nan=0.0, posinf=0.0), 0.0, None))
        keep = None if actor_mask is None else np.asarray(actor_mask, bool)[..., None]
        outs = []
        for t in levels:
            with torch.no_grad():
                y = self.sp.prior.target(x, gb, self.sp.env, t, n_steps=self.steps, seed=self.seed)
            out = y.detach().cpu().numpy().astype(np.float32)
            outs.append(out if keep is None else np.where(keep, rgb, out))
            if t == self.strength and len(outs) == 1:
                self.frames += 1
                self.seconds += time.perf_counter() - t0
        forget = getattr(self.sp.prior, "forget", None)
        if forget is not None:
            forget([key])
        return outs

    def defer_frame(self, frame, camera):
        """A views.frame.Frame with its colour deferred (alpha and depths are the raw frame's:
        deferral changes colours, not geometry)."""
        from dataclasses import replace
        return replace(frame, rgb=self.defer(frame.rgb, camera, frame.actor_mask, frame.depth))

    def describe(self) -> dict:
        """Provenance: prior, T, N, seed, and how fast it went."""
        d = {"prior": self.sp.spec, "prior_params": self.sp.prior.describe(),
             "prior_source": self.sp.source, "strength": self.strength, "steps": self.steps,
             "seed": self.seed, "scene_seed": self.sp.seed, "frames": self.frames,
             "setup_s": round(self.sp.setup_s, 3)}
        if self.frames:
            d["s_per_frame"] = round(self.seconds / self.frames, 4)
        return d


def defer_frames(frames, cameras, scene_prior: ScenePrior, strength: float = DEFAULT_STRENGTH,
                 steps: int = DEFAULT_STEPS, seed: int | None = None, progress: bool = False) -> list:
    """Deferred images of rendered frames (views.frame.Frame, or (H, W, 3) arrays) seen by
    ``cameras``, in order: a list of (H, W, 3) float32 arrays."""
    from tqdm import tqdm
    frames, cameras = list(frames), list(cameras)
    if len(frames) != len(cameras):
        raise InputError(f"deferral: {len(frames)} frames but {len(cameras)} cameras")
    d = Deferrer(scene_prior, strength, steps, seed)
    out = []
    for f, cam in tqdm(list(zip(frames, cameras)), desc="defer", unit="frame",
                       disable=not progress):
        if hasattr(f, "actor_mask"):
            out.append(d.defer(f.rgb, cam, f.actor_mask, f.depth))
        else:
            out.append(d.defer(f, cam))
    return out


def write_provenance(path, deferrer: Deferrer, **extra) -> Path:
    """OUT/deferred.json: how the deferred frames were made (atomic)."""
    from lsd3d_usd import scene as S
    prov = {**S.provenance("deferred"), **deferrer.describe(), **extra}
    return S.atomic_write_bytes(Path(path), (json.dumps(prov, indent=2, default=str) + "\n").encode())
