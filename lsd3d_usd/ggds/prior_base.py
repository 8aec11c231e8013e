"""The image-prior interface of GGDS and the data a prior is conditioned on.

A prior maps a rendered image x of one view, the proxy G-buffer of the same view and the
environment to a target image x_hat at noise level t in (0, 1]: small t keeps x nearly as
it is, t = 1 re-synthesises it entirely. GGDS pulls the render towards x_hat.

Image convention everywhere in ggds/: (H, W, 3) float32 torch tensors, scene-linear RGB
scaled for display (roughly [0, 1]), row 0 at the top of the image.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Hashable, Optional

import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.shmath import C0 as _SH_C0, C1 as _SH_C1

VEGETATION_HINTS = ("green", "autumn", "bare", "snow")

# Real SH (3DGS ordering, lsd3d_usd.shmath): Y_0 = C0, Y_2 = C1 * z.


@dataclass
class GBuffer:
    """Proxy G-buffer of one view, torch tensors on one device.

    depth:        (H, W) camera z in metres (along the optical axis); inf where empty.
    normal:       (H, W, 3) world-space unit normals; anything where empty.
    semantic:     (H, W) int class ids of lsd3d_usd.semantics; -1 where empty / sky.
    world_pos:    (H, W, 3) world positions (metres); anything finite or nan where empty.
    view_dirs:    (H, W, 3) world-space unit rays from the camera through each pixel.
    camera_position: (3,) world position of the camera centre.
    sun_visibility: optional (H, W) in [0, 1], 1 = lit by the sun (ray cast against the
                  proxy by the caller); None means everything is lit.
    key:          optional hashable identity of the view: equal keys promise equal contents,
                  so a prior may cache what it derives from the G-buffer under it (GGDS
                  rebuilds a training view's G-buffer every time it visits the view).
    fine:         optional callable k -> the same view's G-buffer at k× the resolution (each
                  pixel split into k×k), made on demand, for a prior that integrates over
                  pixels instead of sampling their centres.
    """
    depth: torch.Tensor
    normal: torch.Tensor
    semantic: torch.Tensor
    world_pos: torch.Tensor
    view_dirs: torch.Tensor
    camera_position: torch.Tensor
    sun_visibility: Optional[torch.Tensor] = None
    key: Optional[Hashable] = None
    fine: Optional[Callable[[int], "GBuffer"]] = None

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.depth.shape)

    @property
    def valid(self) -> torch.Tensor:
        """(H, W) bool: pixels covered by proxy geometry."""
        return torch.isfinite(self.depth) & (self.depth > 0)

    def disparity(self) -> torch.Tensor:
        """(H, W) 1 / depth, 0 where empty."""
        d = self.depth
        ok = self.valid
        return torch.where(ok, 1.0 / torch.where(ok, d, torch.ones_like(d)), torch.zeros_like(d))

    def validate(self, height: int | None = None, width: int | None = None) -> None:
        """Raise InputError naming the first field whose shape does not match."""
        if self.depth.ndim != 2:
            raise InputError(f"GBuffer.depth must be (H, W), got {tuple(self.depth.shape)}")
        H, W = self.depth.shape
        if height is not None and (H, W) != (height, width):
            raise InputError(f"GBuffer is {W}x{H} but the image is {width}x{height}")
        expect = {"normal": (H, W, 3), "semantic": (H, W), "world_pos": (H, W, 3),
                  "view_dirs": (H, W, 3), "camera_position": (3,)}
        if self.sun_visibility is not None:
            expect["sun_visibility"] = (H, W)
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise InputError(f"GBuffer.{name} must be {shape}, got {got}")


def default_sky_sh(zenith_rgb=(0.30, 0.42, 0.62), ground_rgb=(0.10, 0.09, 0.08)) -> torch.Tensor:
    """(9, 3) irradiance SH of a simple sky: E(n) = a + b n_z, irradiance zenith_rgb*pi from
    straight up and ground_rgb*pi from straight down (a clear-sky ambient term)."""
    up = torch.tensor(zenith_rgb, dtype=torch.float32) * math.pi
    down = torch.tensor(ground_rgb, dtype=torch.float32) * math.pi
    c = torch.zeros(9, 3)
    c[0] = 0.5 * (up + down) / _SH_C0
    c[2] = 0.5 * (up - down) / _SH_C1
    return c


@dataclass
class PriorEnv:
    """Environment and prompt parameters a prior is conditioned on.

    Lighting is in one radiometric unit of the caller's choice, scaled by `exposure` to the
    display range of the images: a white Lambertian surface facing the sun reflects radiance
    (sun_irradiance * max(0, n.s) * visibility + E_sky(n)) / pi.

    sun_direction:  (3,) world unit vector towards the sun (Z up).
    sun_irradiance: (3,) RGB irradiance of a surface facing the sun.
    sh_irradiance:  (9, 3) sky irradiance SH, E(n) = sum_k c_k Y_k(n) (lsd3d_usd.env.sh basis).
    fog_density:    extinction coefficient 1/m (0 = none); fog_color its in-scattered radiance.
    wetness, snow_cover: hints in [0, 1]; vegetation: one of VEGETATION_HINTS.
    sky_lookup:     callable (..., 3) world directions -> (..., 3) radiance for the background
                    (e.g. lsd3d_usd.env.lookup.EnvMap), or None for a plain sky gradient.
    prompt / negative_prompt: text for text-conditioned priors.
    """
    sun_direction: torch.Tensor = field(
        default_factory=lambda: torch.nn.functional.normalize(torch.tensor([0.35, -0.45, 0.82]), dim=0))
    sun_irradiance: torch.Tensor = field(default_factory=lambda: torch.tensor([2.6, 2.45, 2.2]))
    sh_irradiance: torch.Tensor = field(default_factory=default_sky_sh)
    fog_density: float = 0.0
    fog_color: torch.Tensor = field(default_factory=lambda: torch.tensor([0.62, 0.68, 0.75]))
    wetness: float = 0.0
    snow_cover: float = 0.0
    vegetation: str = "green"
    sky_lookup: Optional[Callable[[torch.Tensor], torch.Tensor]] = None
    exposure: float = 1.0
    prompt: str = ""
    negative_prompt: str = ""

    def __post_init__(self):
        self.sun_direction = torch.as_tensor(self.sun_direction, dtype=torch.float32)
        n = float(self.sun_direction.norm())
        if not math.isfinite(n) or n == 0:
            raise InputError("PriorEnv.sun_direction must be a non-zero 3-vector")
        self.sun_direction = self.sun_direction / n
        self.sun_irradiance = torch.as_tensor(self.sun_irradiance, dtype=torch.float32)
        self.sh_irradiance = torch.as_tensor(self.sh_irradiance, dtype=torch.float32)
        self.fog_color = torch.as_tensor(self.fog_color, dtype=torch.float32)
        if tuple(self.sh_irradiance.shape) != (9, 3):
            raise InputError(f"PriorEnv.sh_irradiance must be (9, 3), got {tuple(self.sh_irradiance.shape)}")
        for name in ("wetness", "snow_cover"):
            v = float(getattr(self, name))
            if not 0.0 <= v <= 1.0:
                raise InputError(f"PriorEnv.{name} must be in [0, 1], got {v}")
        if self.fog_density < 0:
            raise InputError(f"PriorEnv.fog_density must be >= 0, got {self.fog_density}")
        if self.vegetation not in VEGETATION_HINTS:
            raise InputError(f"PriorEnv.vegetation must be one of {VEGETATION_HINTS}, got {self.vegetation!r}")


def check_t(t: float) -> float:
    t = float(t)
    if not (0.0 < t <= 1.0) or math.isnan(t):
        raise InputError(f"prior noise level t must be in (0, 1], got {t}")
    return t


def check_image(x: torch.Tensor) -> None:
    if x.ndim != 3 or x.shape[-1] != 3:
        raise InputError(f"prior input image must be (H, W, 3), got {tuple(x.shape)}")


class Prior:
    """Base class: subclasses implement `target`; `name` goes into provenance."""

    name = "prior"
    # Weights of loss terms configured as None (ggds/terms.py): a diffusion prior's loose
    # targets are where the perceptual term earns its place.
    default_weights = {"perceptual": 0.05}

    def default_weight(self, term: str) -> float:
        return float(self.default_weights.get(term, 0.0))

    def shade_at(self, points, normals, semantic, env: PriorEnv, view_dirs=None,
                 sun_visibility=None) -> torch.Tensor | None:
        """Optional: the prior's radiance at world points (N,3), when it can be evaluated in
        3D (GGDS then starts surfel colours from it). None: image space only."""
        return None

    def target(self, x: torch.Tensor, gbuffer: GBuffer, env: PriorEnv, t: float,
               n_steps: int = 5, seed: int | None = None) -> torch.Tensor:
        """Target image x_hat (H, W, 3) for rendered image x (H, W, 3) at noise level t.

        Deterministic for a given seed; x is treated as detached (no gradient flows)."""
        raise NotImplementedError  # abstract: every prior defines it

    def forget(self, keys) -> None:
        """Optional: drop what was cached under these GBuffer keys (GGDS calls it when a
        run's training views are done with)."""

    def describe(self) -> dict:
        """Parameters for layer provenance."""
        return {"prior": self.name}
