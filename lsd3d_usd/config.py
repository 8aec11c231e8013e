"""`generate`'s configuration: one typed tree (lsd3d_usd.configtree). The CLI flags of
`generate`, the keys of `generate --config FILE.toml` and of batch specs, `--set KEY=VALUE`
overrides, the defaults shown in `--help` and the provenance of every layer all derive from
it. `lsd3d-usd generate --list-options` prints every key with its default.

Run control (output folder, --resume, --force, progress) is not configuration: it says how to
run, not what to make, and lives in pipeline.RunOptions.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lsd3d_usd import configtree as ct
from lsd3d_usd.configtree import option
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.ggds.priors.registry import PriorConfig
from lsd3d_usd.limits import CYCLISTS, PEDESTRIANS
from lsd3d_usd.proxy.chunks import ProxyParams
from lsd3d_usd.splats.preview import DEFAULT_FRACTION as DEFAULT_PREVIEW_FRACTION

STYLES = ("urban", "suburban", "highway")
WEATHERS = ("clear", "partly-cloudy", "overcast", "fog", "rain", "snow")   # env.params.WEATHERS
SEASONS = ("spring", "summer", "autumn", "winter")                          # env.params.SEASONS
MAX_SURFELS = 4_000_000         # per scene (the paper's cap)
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


@dataclass
class SurfelConfig:
    count: int | None = option(None, help="initial surfel count (default: density × the proxy "
                                          "surface weighted by nearness to the lanes, at most "
                                          "max_count)", flag="--surfels", alias="surfels",
                               lo=1, hi=MAX_SURFELS)
    density: float = option(80.0, help="initial surfels per m² of view-weighted proxy surface",
                            lo=0.0, hi=1e5)
    max_count: int = option(MAX_SURFELS, help="upper bound of the default count", lo=1,
                            hi=MAX_SURFELS)
    sh_degree: int = option(1, help="spherical-harmonics degree of the surfel colours", lo=0,
                            hi=3)


@dataclass
class SplatsConfig:
    preview_fraction: float = option(
        DEFAULT_PREVIEW_FRACTION, help="fraction of the surfels in the UsdGeom.Points preview "
        "written beside each chunk's ParticleField, for USD tools without ParticleField "
        "(Blender, usdview, USD < 26.03; docs/usd.md); 0 = no preview", lo=0.0, hi=1.0,
        recorded=0.0)


@dataclass
class ActorsConfig:
    enabled: bool = option(True, help="the actors layer (parked and moving vehicles)",
                           negate="--no-actors", alias="actors")
    parked: int = option(12, help="parked actors along the curbs", flag="--parked",
                         alias="parked", lo=0, hi=100_000)
    moving: int = option(8, help="moving actors driven by IDM traffic over the lane graph",
                         flag="--moving", alias="moving", lo=0, hi=100_000)
    pedestrians: int = option(0, help="pedestrians on the sidewalks and crosswalks",
                              flag="--pedestrians", alias="pedestrians", lo=0,
                              hi=int(PEDESTRIANS.value))
    cyclists: int = option(0, help="cyclists on bike lanes or the right of driving lanes",
                           flag="--cyclists", alias="cyclists", lo=0,
                           hi=int(CYCLISTS.value))
    seconds: float = option(8.0, help="traffic duration in seconds", flag="--actor-seconds",
                            alias="actor_seconds", lo=0.1, hi=3600.0)
    fps: float = option(10.0, help="traffic samples per second", flag="--actor-fps",
                        alias="actor_fps", lo=0.1, hi=240.0)


@dataclass
class GenerateConfig:
    layout: Path | None = option(None, help="layout layer (.usda/.usdc; docs/layout.md); "
                                            "without it one is generated from seed, extent "
                                            "and style", flag="--layout", alias="layout",
                                 metavar="LAYOUT")
    seed: int = option(0, help="random seed of every step", flag="--seed", alias="seed")
    extent: tuple[float, float] = option((200.0, 200.0), help="generated layout size WxH "
                                                              "(metres; no --layout)",
                                         flag="--extent", alias="extent", lo=1.0, hi=100_000.0,
                                         metavar="WxH")
    style: str = option("urban", help="generated layout style (no --layout)", flag="--style",
                        alias="style", choices=STYLES)
    proxy: ProxyParams = field(default_factory=ProxyParams)
    env: EnvConfig = field(default_factory=EnvConfig)
    surfels: SurfelConfig = field(default_factory=SurfelConfig)
    splats: SplatsConfig = field(default_factory=SplatsConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    ggds: GGDSConfig = field(default_factory=GGDSConfig)
    actors: ActorsConfig = field(default_factory=ActorsConfig)


# Values given by flags are named by their flag in errors; this one is a dict-leaf entry.
FLAG_NAMES = {"ggds.weights.perceptual": "--perceptual-weight"}


def generate_config(**settings) -> GenerateConfig:
    """A GenerateConfig from flat keys and subtree tables, as in a batch spec or config file:
    ``generate_config(layout=..., steps=0, surfels=4000, ggds={"lr": {"sh_dc": 0.01}})``."""
    values = ct.flatten(settings, GenerateConfig, "")
    return ct.apply(GenerateConfig(), values, "", ct.flag_names(GenerateConfig))
