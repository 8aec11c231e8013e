"""The surfel steps' configuration (subtrees of `generate`'s, lsd3d_usd.configtree)."""
from __future__ import annotations

from dataclasses import dataclass

from lsd3d_usd.configtree import option
from lsd3d_usd.splats.init import MAX_SURFELS
from lsd3d_usd.splats.preview import DEFAULT_FRACTION as DEFAULT_PREVIEW_FRACTION


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
