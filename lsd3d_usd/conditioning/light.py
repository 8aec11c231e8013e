"""The scene's light as a prior and an evaluation need it (PriorEnv, SceneLight): sun, sky irradiance without the sun disk (the
sun is handled separately, with proxy shadows, so it must not be counted twice), fog, hints,
the background lookup, and an exposure that maps scene luminance to display range.

Exposure: a white Lambertian surface facing up reflects L_up = (E_sun max(0, s_z) + E_sky(up))/π;
we scale so it displays at EXPOSURE_KEY, with a floor so night scenes stay dark rather than
being brightened to daylight.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import field
from typing import Callable, Optional

import numpy as np
import torch

from lsd3d_usd.conditioning.shadow import shadow_map
from lsd3d_usd.env import EnvParams, build_params
from lsd3d_usd.env.prompt import unknown_words
from lsd3d_usd.env.farfield import FarField
from lsd3d_usd.env.lookup import EnvMap
from lsd3d_usd.env.sh import eval_sh_irradiance, sh_irradiance
from lsd3d_usd.env.sky import SkyModel, render_sky
from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import pixel_rays
from lsd3d_usd.semantics import CLASS_COLORS
from lsd3d_usd.shmath import C0 as _SH_C0
from lsd3d_usd.shmath import C1 as _SH_C1
from lsd3d_usd.splats.field import rgb_to_sh_dc

VEGETATION_HINTS = ("green", "autumn", "bare", "snow")
EXPOSURE_KEY = 0.8
MIN_UP_LUMINANCE = 0.3      # kcd/m^2: about 1 % of a clear midday; below this scenes darken
_REC709_Y = np.array([0.2126, 0.7152, 0.0722])


# Real SH (3DGS ordering, lsd3d_usd.shmath): Y_0 = C0, Y_2 = C1 * z.
def default_sky_sh(zenith_rgb=(0.30, 0.42, 0.62), ground_rgb=(0.10, 0.09, 0.08)) -> torch.Tensor:
    """(9, 3) irradiance SH of a simple sky: E(n) = a + b n_z, irradiance zenith_rgb*pi from
    straight up and ground_rgb*pi from straight down (a clear-sky ambient term)."""
    up = torch.tensor(zenith_rgb, dtype=torch.float32) * math.pi
    down = torch.tensor(ground_rgb, dtype=torch.float32) * math.pi
    c = torch.zeros(9, 3)
    c[0] = 0.5 * (up + down) / _SH_C0
    c[2] = 0.5 * (up - down) / _SH_C1
    return c


@dataclasses.dataclass
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
    far_field:      env.farfield.FarField (env units, like sky_lookup): the ground beyond the
                    scene behind the proxy, or None.
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
    far_field: Optional[FarField] = None

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


@dataclasses.dataclass
class SceneLight:
    prior_env: PriorEnv
    exposure: float                 # multiply map radiance (kcd/m^2) by this for display
    sky_sh: np.ndarray              # (9,3) irradiance SH of the sky without the sun disk
    sun_direction: np.ndarray       # (3,)
    sun_illuminance: np.ndarray     # (3,) klx at normal incidence (after clouds)
    envmap: object | None           # lsd3d_usd.env.EnvMap of the scene's EXR (unscaled)

    def background(self, camera) -> torch.Tensor:
        """(H,W,3) display-scaled env radiance behind every pixel of `camera`, with the
        ground beyond the scene where the light has one (prior_env.far_field)."""
        _, d = pixel_rays(camera)
        if self.envmap is None:
            bg = torch.zeros(camera.height, camera.width, 3)
        else:
            bg = self.envmap(torch.from_numpy(d.astype(np.float32))) * self.exposure
        ff = self.prior_env.far_field
        if ff is None:
            return bg
        return torch.from_numpy(ff.scaled(self.exposure).apply(bg.numpy(), camera.pose[:3, 3], d))

    def irradiance(self, normals: np.ndarray, sun_visibility: np.ndarray | None = None) -> np.ndarray:
        """Display-scaled irradiance/π for normals (N,3): what a white surface reflects."""
        n = np.asarray(normals, np.float64)
        sky = eval_sh_irradiance(self.sky_sh, n)
        cos = np.clip(n @ self.sun_direction, 0.0, None)
        vis = 1.0 if sun_visibility is None else sun_visibility[:, None]
        return (sky + self.sun_illuminance[None, :] * cos[:, None] * vis) / math.pi * self.exposure


def scene_light(params: EnvParams, exr_path=None, sh_resolution: int = 128) -> SceneLight:
    r = params.resolved()
    model = SkyModel(r)
    sky = render_sky(dataclasses.replace(r, sun_disk=False), 2 * sh_resolution, sh_resolution)
    sky_sh = sh_irradiance(sky)
    sun_dir = np.asarray(model.sun_dir, np.float64)
    sun_lux = np.asarray(model.sun_direct_lux, np.float64) / 1000.0 if model.sun_up else np.zeros(3)
    up = np.array([[0.0, 0.0, 1.0]])
    L_up = (eval_sh_irradiance(sky_sh, up)[0] + sun_lux * max(sun_dir[2], 0.0)) / math.pi
    lum = float(L_up @ _REC709_Y)
    exposure = EXPOSURE_KEY / max(lum, MIN_UP_LUMINANCE)
    envmap = None
    if exr_path is not None:
        envmap = EnvMap.from_exr(exr_path)
    fog_rgb = np.asarray(model.fog_rgb, np.float64) * exposure
    # The prior applies env.exposure itself: hand it the map in its own units.
    sky_lookup = envmap
    penv = PriorEnv(
        sun_direction=torch.tensor(sun_dir if np.linalg.norm(sun_dir) > 0 else [0, 0, 1.0],
                                   dtype=torch.float32),
        sun_irradiance=torch.tensor(sun_lux, dtype=torch.float32),
        sh_irradiance=torch.tensor(sky_sh, dtype=torch.float32),
        fog_density=float(r.fog_density), fog_color=torch.tensor(fog_rgb, dtype=torch.float32),
        wetness=float(r.wet_ground), snow_cover=float(r.snow_cover), vegetation=r.vegetation,
        sky_lookup=sky_lookup, exposure=float(exposure),
        prompt=str(params.extras.get("prompt", "")))
    return SceneLight(penv, float(exposure), sky_sh, sun_dir, sun_lux, envmap)


def env_params(env_settings: dict, seed: int = 0, log=None) -> EnvParams:
    """EnvParams from a configuration's env settings (prompt, when, lat, lon, weather,
    season), the prompt kept for text-conditioned priors. Unknown prompt words go to ``log``."""
    e = env_settings
    params, unknown = build_params(e.get("prompt"), when=e.get("when"), lat=e.get("lat"),
                                   lon=e.get("lon"), weather=e.get("weather"),
                                   season=e.get("season"), seed=seed)
    if e.get("prompt"):
        params.extras["prompt"] = e["prompt"]
    if unknown and log is not None:
        log(f"warning: prompt words not understood (ignored): {unknown_words(unknown)}")
    return params


def colour_by_light(field, light: "SceneLight", vertices: np.ndarray, faces: np.ndarray) -> None:
    """Initial DC colours of a SurfelField in place: class albedo × (sky + sun where the proxy
    ``vertices``/``faces`` do not shadow it) irradiance of ``light``."""
    shadow = shadow_map(vertices, faces, light.sun_direction)
    vis = shadow.visibility(field.positions.astype(np.float64) + 0.05 * field.normals()) \
        if shadow is not None else None
    albedo = CLASS_COLORS[np.clip(field.semantic_ids, 0, None)]
    rgb = np.clip(albedo * light.irradiance(field.normals(), vis), 0.0, 4.0)
    field.sh[:, 0, :] = rgb_to_sh_dc(rgb)
