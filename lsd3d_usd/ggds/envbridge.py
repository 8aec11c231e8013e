"""Environment → what GGDS and its prior need: sun, sky irradiance without the sun disk (the
sun is handled separately, with proxy shadows, so it must not be counted twice), fog, hints,
the background lookup, and an exposure that maps scene luminance to display range.

Exposure: a white Lambertian surface facing up reflects L_up = (E_sun max(0, s_z) + E_sky(up))/π;
we scale so it displays at EXPOSURE_KEY, with a floor so night scenes stay dark rather than
being brightened to daylight.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from lsd3d_usd.env import EnvParams
from lsd3d_usd.env.sh import eval_sh_irradiance, sh_irradiance
from lsd3d_usd.env.sky import SkyModel, render_sky
from lsd3d_usd.ggds.prior_base import PriorEnv

EXPOSURE_KEY = 0.8
MIN_UP_LUMINANCE = 0.3      # kcd/m^2: about 1 % of a clear midday; below this scenes darken
_REC709_Y = np.array([0.2126, 0.7152, 0.0722])


@dataclasses.dataclass
class SceneLight:
    prior_env: PriorEnv
    exposure: float                 # multiply map radiance (kcd/m^2) by this for display
    sky_sh: np.ndarray              # (9,3) irradiance SH of the sky without the sun disk
    sun_direction: np.ndarray       # (3,)
    sun_illuminance: np.ndarray     # (3,) klx at normal incidence (after clouds)
    envmap: object | None           # lsd3d_usd.env.EnvMap of the scene's EXR (unscaled)

    def background(self, camera) -> torch.Tensor:
        """(H,W,3) display-scaled env radiance behind every pixel of `camera`."""
        from lsd3d_usd.render.camera import pixel_rays
        _, d = pixel_rays(camera)
        if self.envmap is None:
            return torch.zeros(camera.height, camera.width, 3)
        return self.envmap(torch.from_numpy(d.astype(np.float32))) * self.exposure

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
        from lsd3d_usd.env.lookup import EnvMap
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
    from lsd3d_usd.env import build_params
    e = env_settings
    params, unknown = build_params(e.get("prompt"), when=e.get("when"), lat=e.get("lat"),
                                   lon=e.get("lon"), weather=e.get("weather"),
                                   season=e.get("season"), seed=seed)
    if e.get("prompt"):
        params.extras["prompt"] = e["prompt"]
    if unknown and log is not None:
        log(f"warning: prompt words not understood (ignored): {', '.join(unknown)}")
    return params
