"""The environment step's configuration (a subtree of `generate`'s, lsd3d_usd.configtree)."""
from __future__ import annotations

from dataclasses import dataclass

from lsd3d_usd.configtree import option
from lsd3d_usd.env.params import SEASONS, WEATHERS

MAX_ENV_SIDE = 16384


@dataclass
class EnvConfig:
    prompt: str | None = option(None, help='scene description, e.g. "rainy autumn evening in '
                                           'Seattle" (time of day, weather, season, place; '
                                           'docs/env.md)', flag="--prompt", alias="prompt",
                                metavar="TEXT")
    when: str | None = option(None, help="local date/time, e.g. 2026-06-21T13:00+02:00 "
                                         "(overrides the prompt)", flag="--when", alias="when")
    lat: float | None = option(None, help="latitude (with --lon; overrides the prompt's place)",
                               flag="--lat", alias="lat", lo=-90.0, hi=90.0)
    lon: float | None = option(None, help="longitude", flag="--lon", alias="lon",
                               lo=-180.0, hi=180.0)
    weather: str | None = option(None, help="weather (overrides the prompt)", flag="--weather",
                                 alias="weather", choices=WEATHERS)
    season: str | None = option(None, help="season (overrides the prompt)", flag="--season",
                                alias="season", choices=SEASONS)
    resolution: tuple[int, int] = option((2048, 1024), help="environment map size WxH",
                                         flag="--env-resolution", alias="env_resolution",
                                         lo=2, hi=MAX_ENV_SIDE, metavar="WxH")
