"""Deferred rendering, the paper's last step: each rendered frame x0 goes through the scene's
image prior from a low noise level T with N steps, conditioned on the proxy G-buffer of the
same camera, and the result is the frame shown ("deferred", after deferred neural rendering).

    sp = load_scene_prior("out/crossing")            # ggds.priors.scene: the prior GGDS used
    out = defer_frames(frames, cameras, sp, strength=0.3, steps=5)

What the prior does at T is the prior's own `target` (ggds/priors/base.py), exactly as GGDS
asks it: the diffusion prior VAE-encodes the frame, inverts it with deterministic DDIM to T,
takes N guided DDIM steps back with the disparity ControlNet and decodes; the procedural prior
blends its world-space shading of the G-buffer into a guided filter of the frame.

Temporal consistency: a frame's result is a pure function of (frame, camera, scene). Nothing
random is drawn per frame: the diffusion prior's inversion is deterministic (DDIM, eta 0, the
VAE's posterior mean), and the procedural prior's noise is world-space lattice noise seeded per
surface point (ggds/priors/noise.py), so it is fixed in the world and moves with the surfaces. The
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
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError

if TYPE_CHECKING:   # annotations only: the render command's flags need no torch
    from lsd3d_usd.ggds.priors.scene import ScenePrior

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


def deferred_name(path) -> Path:
    """<stem>_deferred<suffix> beside ``path`` (Front.0003.png -> Front.0003_deferred.png)."""
    p = Path(path)
    return p.with_name(f"{p.stem}{SUFFIX}{p.suffix}")


# ------------------------------------------------------------------------ one frame
def overlay_actors(gb, camera, actor_mask: np.ndarray, depth: np.ndarray):
    """G-buffer pixels where an actor is in front take the actor's depth, the vehicle class,
    a camera-facing normal and the matching world position."""
    # local import: not loaded for --help
    import torch

    # local import: not loaded for --help
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
        # local import: not loaded for --help
        import torch

        rgb = np.asarray(rgb, np.float32)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[:2] != (camera.height, camera.width):
            raise InputError(f"deferral: frame of shape {rgb.shape} does not match the camera's "
                             f"{camera.width}x{camera.height}")
        levels = [check_strength(t, "deferral noise level") for t in levels]
        t0 = time.perf_counter()
        gb = self.sp.gbuffer(camera, fine=fine)
        if actor_mask is not None:
            gb = overlay_actors(gb, camera, actor_mask, depth)
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
    # local import: not loaded for --help
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
    prov = {**S.provenance("deferred"), **deferrer.describe(), **extra}
    return S.atomic_write_bytes(Path(path), (json.dumps(prov, indent=2, default=str) + "\n").encode())
