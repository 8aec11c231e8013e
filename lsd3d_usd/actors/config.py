"""The actors step's configuration (a subtree of `generate`'s, lsd3d_usd.configtree)."""
from __future__ import annotations

from dataclasses import dataclass, field

from lsd3d_usd.configtree import option
from lsd3d_usd.limits import CYCLISTS, PEDESTRIANS


@dataclass
class ActorsConfig:
    enabled: bool = option(True, help="the actors layer (parked and moving vehicles)",
                           negate="--no-actors", alias="actors")
    parked: int = option(12, help="parked actors along the curbs", flag="--parked",
                         alias="parked", lo=0, hi=100_000)
    moving: int = option(8, help="moving actors driven by IDM traffic over the lane graph",
                         flag="--moving", alias="moving", lo=0, hi=100_000)
    # a street has people: by default as many as the layout takes (None: 12 pedestrians and
    # 2 cyclists where the asset folder has such assets and the layout sidewalks / lanes;
    # fewer where there is no room, none without); a number asks for exactly that many
    pedestrians: int | None = option(None, help="pedestrians walking the sidewalks, crossing at "
                                     "crosswalks and standing at corners (default: 12 where the "
                                     "assets and the layout's sidewalks allow)",
                                     flag="--pedestrians", alias="pedestrians", lo=0,
                                     hi=int(PEDESTRIANS.value))
    cyclists: int | None = option(None, help="cyclists on bike lanes, or the right part of "
                                  "driving lanes, in the IDM traffic (default: 2 where the "
                                  "assets allow)", flag="--cyclists", alias="cyclists", lo=0,
                                  hi=int(CYCLISTS.value))
    seconds: float = option(8.0, help="traffic duration in seconds", flag="--actor-seconds",
                            alias="actor_seconds", lo=0.1, hi=3600.0)
    fps: float = option(10.0, help="traffic samples per second, written as time samples",
                        flag="--actor-fps", alias="actor_fps", lo=0.1, hi=240.0)


@dataclass
class AddConfig:
    """`lsd3d-usd actors add`: generate's actor settings (--seconds and --fps without the actor-
    prefix, no --no-actors) and the seed generate shares with every step."""
    actors: ActorsConfig = field(default_factory=ActorsConfig)
    seed: int = option(0, help="random seed", flag="--seed")


ADD_FLAGS = {"actors.enabled": "", "actors.seconds": "--seconds", "actors.fps": "--fps"}


@dataclass
class AssetsConfig:
    """`lsd3d-usd actors assets`."""
    format: str = option("usda", help="library file format", flag="--format",
                         choices=("usda", "usdc"))
