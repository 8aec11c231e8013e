"""lsd3d_usd.env: the environment at infinity and the light of the scene.

Sun/moon position (NOAA), analytic sky (Preetham + CIE overcast + clouds, twilight, night),
weather / season hints, prompt control, half-float EXR with a DomeLight_1 layer, order-2 SH
irradiance and a torch lookup for the renderer. Direction convention: see `mapping`.

The names below are importable from ``lsd3d_usd.env`` and load their module when first used,
so reading environment parameters never imports the sky renderer (numba) or torch.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "direction_to_uv": "mapping", "env_direction_to_uv": "mapping",
    "pixel_directions": "mapping", "pixel_solid_angles": "mapping", "uv_to_direction": "mapping",
    "COLOR_SPACES": "params", "SEASONS": "params", "VEGETATION": "params", "WEATHERS": "params",
    "EnvParams": "params", "FogParams": "params",
    "CITIES": "prompt", "build_params": "prompt", "parse_prompt": "prompt",
    "eval_sh_irradiance": "sh", "sh_basis": "sh", "sh_irradiance": "sh",
    "SkyModel": "sky", "render_sky": "sky",
    "lunar_position": "sun", "solar_position": "sun", "sun_direction": "sun",
    "write_env": "exr", "read_env": "exr",
    "write_env_layer": "usdlayer", "read_env_prim": "usdlayer",
    "EnvMap": "lookup", "env_lookup": "lookup",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'lsd3d_usd.env' has no attribute {name!r}")
    return getattr(importlib.import_module(f"lsd3d_usd.env.{module}"), name)


def __dir__():
    return __all__
