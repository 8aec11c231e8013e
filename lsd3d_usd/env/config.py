"""The environment step's configuration (lsd3d_usd.configtree): ``EnvConfig`` is a subtree of
`generate`'s; ``SkyConfig`` is `lsd3d-usd env`'s tree, the same leaves plus the sky's own
tuning, so both commands' shared flags come from one definition."""
from __future__ import annotations

from dataclasses import dataclass, field

from lsd3d_usd.configtree import option
from lsd3d_usd.env.params import SEASONS, WEATHERS

MAX_ENV_SIDE = 16384
COLOR_SPACES = ("lin_rec709", "acescg")


@dataclass
class EnvConfig:
    prompt: str | None = option(None, help='scene description, e.g. "rainy autumn evening in '
                                           'Seattle" (time of day, weather, season, month, '
                                           'place; docs/env.md)', flag="--prompt",
                                alias="prompt", metavar="TEXT")
    when: str | None = option(None, help="local date/time, ISO 8601, e.g. "
                                         "2026-06-21T13:00+02:00 (without an offset: the "
                                         "place's standard time; overrides the prompt)",
                              flag="--when", alias="when")
    lat: float | None = option(None, help="latitude in degrees, north positive (with --lon; "
                                          "overrides the prompt's place)",
                               flag="--lat", alias="lat", lo=-90.0, hi=90.0)
    lon: float | None = option(None, help="longitude in degrees, east positive (with --lat)",
                               flag="--lon", alias="lon", lo=-180.0, hi=180.0)
    weather: str | None = option(None, help="weather (overrides the prompt; without either: "
                                            "clear)", flag="--weather", alias="weather",
                                 choices=WEATHERS)
    season: str | None = option(None, help="season (overrides the prompt): sets the date "
                                           "(hemisphere-aware) unless --when is given, and the "
                                           "ground / vegetation hints", flag="--season",
                                alias="season", choices=SEASONS)
    resolution: tuple[int, int] = option((2048, 1024), help="environment map size WxH (2:1)",
                                         flag="--env-resolution", alias="env_resolution",
                                         lo=2, hi=MAX_ENV_SIDE, metavar="WxH")


@dataclass
class SkyConfig:
    """`lsd3d-usd env`: the scene's env settings (its map size as --resolution) and the sky
    model's own parameters, which `generate` derives from the weather."""
    env: EnvConfig = field(default_factory=EnvConfig)
    time_of_day: str | None = option(None, help="a time word solved for the place and date "
                                                "(dawn, sunrise, morning, noon, afternoon, "
                                                "evening, golden hour, sunset, dusk, night, ...)",
                                     flag="--time-of-day")
    seed: int = option(0, help="seed of the cloud noise", flag="--seed")
    turbidity: float | None = option(None, help="atmospheric turbidity 1.7..10 (default per "
                                                "weather)", flag="--turbidity")
    cloud_coverage: float | None = option(None, help="fraction of the sky covered by clouds, "
                                                     "0..1 (default per weather)",
                                          flag="--cloud-coverage")
    fog_density: float | None = option(None, help="fog extinction in 1/m (visibility = 3.912 / "
                                                  "density; default per weather)",
                                       flag="--fog-density")
    north: float = option(0.0, help="angle (deg, counter-clockwise about +Z) from +Y to north "
                                    "in the stage", flag="--north")
    color_space: str = option("lin_rec709", help="colour space of the EXR (tagged in the file "
                                                 "and on the USD texture)", flag="--color-space",
                              choices=COLOR_SPACES)


# `env` names the map size --resolution (generate's --resolution is the GGDS render size)
SKY_FLAGS = {"env.resolution": "--resolution"}
