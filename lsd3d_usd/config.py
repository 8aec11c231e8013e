"""`generate`'s configuration: one typed tree (lsd3d_usd.configtree). The CLI flags of
`generate`, the keys of `generate --config FILE.toml` and of batch specs, `--set KEY=VALUE`
overrides, the defaults shown in `--help` and the provenance of every layer all derive from
it. `lsd3d-usd generate --list-options` prints every key with its default. Each step's subtree
lives with its step (env.config, splats.config, actors.config, proxy.chunks, ggds.settings,
ggds.priors.registry); this module only composes them.

Run control (output folder, --resume, --force, progress) is not configuration: it says how to
run, not what to make, and lives in pipeline.RunOptions.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lsd3d_usd import configtree as ct
from lsd3d_usd.configtree import option
from lsd3d_usd.actors.config import ActorsConfig
from lsd3d_usd.env.config import EnvConfig
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.ggds.priors.registry import PriorConfig
from lsd3d_usd.layout.config import STYLES
from lsd3d_usd.proxy.chunks import ProxyParams
from lsd3d_usd.splats.config import SplatsConfig, SurfelConfig

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
