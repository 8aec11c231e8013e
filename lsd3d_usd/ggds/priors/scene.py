"""The prior of a scene: the one a GGDS run of the scene recorded (or an override), with the
scene's conditioning (conditioning.scene.Conditioning). What deferral, eval's prior baseline,
its seam targets and the benchmarks score a scene's renders against.

    sp = load_scene_prior("out/crossing")          # the newest active run's prior
    gb = sp.gbuffer(camera)                        # its proxy G-buffer of a view
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from pxr import Sdf

from lsd3d_usd import configtree
from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.priors.base import Prior, heldout_target
from lsd3d_usd.ggds.priors.registry import (PRIORS, PriorConfig, check_device, check_prior_name,
                                            make_prior)


@dataclass
class ScenePrior:
    """A scene's prior and what conditions it."""
    prior: Prior
    conditioning: Conditioning
    spec: str                     # the prior as configured: "procedural", "diffusers:DIR", ...
    source: str                   # where the choice came from
    seed: int                     # the scene's seed (the prior's material seed)
    setup_s: float = 0.0
    info: dict = field(default_factory=dict)

    @property
    def env(self):
        return self.conditioning.env

    @property
    def proxy(self) -> tuple:
        return self.conditioning.proxy

    @property
    def shadow(self):
        return self.conditioning.shadow

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
        return self.conditioning.gbuffer(camera, fine=fine)

    def heldout_target(self, camera, rgb: np.ndarray, j: int, *, t: float = 1.0, key=None):
        """(target (H, W, 3) array, the G-buffer it conditioned on): what held-out view ``j``
        of a run is scored against (priors.base.heldout_target) for the render ``rgb``.
        ``key``: the G-buffer's key (a caller that forgets the prior's per-view cache)."""
        gb = self.conditioning.gbuffer(camera, key=key)
        x = torch.from_numpy(np.ascontiguousarray(rgb, np.float32))
        return heldout_target(self.prior, x, gb, self.env, j, t=t).numpy(), gb


def scene_root(path) -> Path:
    """The scene folder behind ``path``: a scene folder, its scene.usda, or a USD file that
    sublayers one (a rig's OUT/rig.usda). One InputError line otherwise."""
    p = Path(path)
    if p.is_dir():
        if (p / S.ROOT_FILE).is_file():
            return p.absolute()
        raise InputError(f"{path}: the scene's prior needs a scene folder (holding "
                         f"{S.ROOT_FILE})")
    if p.name == S.ROOT_FILE and p.is_file():
        return p.parent.absolute()
    layer = Sdf.Layer.FindOrOpen(str(p)) if p.is_file() else None
    if layer is not None:
        for sub in layer.subLayerPaths:
            q = Path(sub) if Path(sub).is_absolute() else p.parent / sub
            if q.name == S.ROOT_FILE and q.is_file():
                return q.parent.resolve()
    raise InputError(f"{path}: the scene's prior needs a scene folder, its {S.ROOT_FILE}, or a "
                     "file that sublayers one (the proxy, env and GGDS layers condition the "
                     "prior)")


def recorded_config(sc: S.Scene, run: str | None = None):
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


def recorded_prior_config(sc: S.Scene, run: str | None = None):
    """(PriorConfig, seed, prompt, where they came from, run): what the GGDS run ``run``
    (default: the newest unmuted one) recorded, else the default prior with the scene's seed."""
    recorded, run = recorded_config(sc, run)
    if recorded is not None:
        cfg = configtree.from_dict(PriorConfig, recorded.get("prior", {}))
        seed = int(recorded.get("seed", 0))
        prompt = (recorded.get("env") or {}).get("prompt") or ""
        return cfg, seed, prompt, f"recorded by GGDS run {run}", run
    source = (f"default (GGDS run {run} records no configuration)" if run
              else "default (the scene has no GGDS run)")
    return PriorConfig(), _scene_seed(sc), "", source, run


def recorded_prior_name(scene_path, run: str | None = None) -> str:
    """The registered name of the prior the scene's GGDS run ``run`` (default: the newest
    unmuted one) recorded (the default prior's when none is recorded, as load_scene_prior
    falls back to it)."""
    recorded, _ = recorded_config(S.Scene.open(scene_root(scene_path)), run)
    spec = ((recorded or {}).get("prior") or {}).get("name") or PriorConfig().name
    return str(spec).split(":", 1)[0]


def recorded_prior_is_cheap(scene_path, run: str | None = None) -> tuple[bool, str]:
    """(whether the prior the run recorded is cheap on a CPU, its name)."""
    name = recorded_prior_name(scene_path, run)
    return PRIORS.get(name).cheap_on_cpu, name


def _scene_seed(sc: S.Scene) -> int:
    prov = S.read_provenance(Sdf.Layer.FindOrOpen(str(sc.root_layer_path)))
    return int(prov.get("seed", 0))


def load_scene_prior(scene_path, prior: str | None = None, controlnet=None, *,
                     device: str | None = None, run: str | None = None, proxy=None,
                     purpose: str = "deferral", override: str = "--deferred-prior") -> ScenePrior:
    """The prior the scene's GGDS run ``run`` (default: the newest unmuted one) was made with
    (its recorded `generate` configuration), or ``prior`` ("procedural", "diffusers:DIR",
    another registered name) to override it; ``controlnet`` / ``device`` override those
    settings. With the scene's conditioning (its env layer and ``proxy``, default the scene's,
    as GGDS saw them).
    ``purpose`` / ``override``: what the error lines name as needing the scene, and the flag
    that chooses another prior. Reads only."""
    t0 = time.perf_counter()
    sc = S.Scene.open(scene_root(scene_path))
    cfg, seed, prompt, source, run = recorded_prior_config(sc, run)
    if prior is not None:
        cfg.name = check_prior_name(prior, override)
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
    cond = Conditioning.of_scene(sc, proxy=proxy, prompt=prompt, purpose=purpose)
    return ScenePrior(p, cond, cfg.name, source, seed, time.perf_counter() - t0,
                      {"run": run, "exposure": cond.light.exposure})
