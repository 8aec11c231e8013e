"""lsd3d_usd.env: the environment at infinity and the light of the scene.

Sun/moon position (NOAA), analytic sky (Preetham + CIE overcast + clouds, twilight, night),
weather / season hints, prompt control, half-float EXR with a DomeLight_1 layer, order-2 SH
irradiance and a torch lookup for the renderer. Direction convention: see `mapping`.
"""
from __future__ import annotations

import numpy as np

from lsd3d_usd.env.mapping import (direction_to_uv, env_direction_to_uv, pixel_directions,
                                   pixel_solid_angles, uv_to_direction)
from lsd3d_usd.env.params import (COLOR_SPACES, SEASONS, VEGETATION, WEATHERS, EnvParams,
                                  FogParams)
from lsd3d_usd.env.prompt import CITIES, build_params, parse_prompt
from lsd3d_usd.env.sh import eval_sh_irradiance, sh_basis, sh_irradiance
from lsd3d_usd.env.sky import SkyModel, render_sky
from lsd3d_usd.env.sun import lunar_position, solar_position


def sun_direction(params: EnvParams) -> np.ndarray:
    """Unit vector toward the sun (world, Z up, x east / y north unless north_deg is set);
    below the horizon it points down."""
    from lsd3d_usd.env.sun import azel_to_direction
    p = solar_position(params.when, params.latitude, params.longitude)
    return azel_to_direction(p.azimuth, p.elevation, params.north_deg)


def write_env(params: EnvParams, out, width: int = 2048, height: int = 1024, **kw):
    """Render + write the EXR (cached by parameter hash); returns its path."""
    from lsd3d_usd.env.exr import write_env as _write
    return _write(params, out, width, height, **kw)


def read_env(path):
    from lsd3d_usd.env.exr import read_env as _read
    return _read(path)


def write_env_layer(stage_or_path, envs, **kw):
    from lsd3d_usd.env.usdlayer import write_env_layer as _w
    return _w(stage_or_path, envs, **kw)


def read_env_prim(stage):
    from lsd3d_usd.env.usdlayer import read_env_prim as _r
    return _r(stage)


def __getattr__(name):  # torch only when asked for
    if name in ("EnvMap", "env_lookup"):
        from lsd3d_usd.env import lookup
        return getattr(lookup, name)
    raise AttributeError(name)


__all__ = ["EnvParams", "FogParams", "WEATHERS", "SEASONS", "VEGETATION", "COLOR_SPACES",
           "CITIES", "parse_prompt", "build_params", "sun_direction", "solar_position",
           "lunar_position", "render_sky", "SkyModel", "write_env", "read_env", "sh_irradiance",
           "eval_sh_irradiance", "sh_basis", "EnvMap", "env_lookup", "uv_to_direction",
           "direction_to_uv", "env_direction_to_uv", "pixel_directions", "pixel_solid_angles",
           "write_env_layer", "read_env_prim"]
