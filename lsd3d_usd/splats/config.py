"""The surfel steps' configuration (lsd3d_usd.configtree): ``SurfelConfig`` and
``SplatsConfig`` are subtrees of `generate`'s; the others are the trees of the `splats`
subcommands, which share SplatsConfig's preview leaf as --preview-fraction."""
from __future__ import annotations

from dataclasses import dataclass, field

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
    sh_degree: int = option(2, help="spherical-harmonics degree of the surfel colours (2: "
                                    "the prior's ground brightens towards grazing angles, "
                                    "which degree 1 extrapolates to black from above)", lo=0,
                            hi=3)


@dataclass
class SplatsConfig:
    preview_fraction: float = option(
        DEFAULT_PREVIEW_FRACTION, help="fraction of the surfels in the UsdGeom.Points preview "
        "written beside each chunk's ParticleField, for USD tools without ParticleField "
        "(Blender, usdview, USD < 26.03; docs/usd.md); 0 = no preview", lo=0.0, hi=1.0,
        recorded=0.0, metavar="F")


@dataclass
class WriteConfig:
    """Where `splats init` and `splats import-ply` write the surfels."""
    prim: str = option("/World/Surfels", help="prim path of the written surfels", flag="--prim",
                       metavar="PRIM")
    splats: SplatsConfig = field(default_factory=SplatsConfig)


WRITE_FLAGS = {"write.splats.preview_fraction": "--preview-fraction"}


@dataclass
class InitConfig:
    """`splats init`: the paper's initialisation on a stage's meshes."""
    count: int = option(2_000_000, help="number of surfels (paper: 1.8-2.2 M per scene, at "
                                        "most 4 M)", flag="--count", metavar="COUNT")
    seed: int = option(0, help="random seed (same seed, same surfels)", flag="--seed",
                       metavar="SEED")
    color: str = option("semantic", help="'semantic' (class colours) or a linear R,G,B triple "
                                         "such as 0.5,0.5,0.5", flag="--color", metavar="COLOR")
    opacity: float = option(0.8, help="initial opacity in [0, 1]", flag="--opacity",
                            metavar="OPACITY")
    sh_degree: int = option(0, help="spherical-harmonics degree of the colour (0: "
                                    "view-independent)", flag="--sh-degree",
                            choices=(0, 1, 2, 3))
    root: str | None = option(None, help="only meshes under this prim path (default "
                                         "/World/Proxy or the whole stage)", flag="--root",
                              metavar="ROOT")
    write: WriteConfig = field(default_factory=WriteConfig)


@dataclass
class ImportConfig:
    """`splats import-ply`."""
    write: WriteConfig = field(default_factory=WriteConfig)


@dataclass
class ExportConfig:
    """`splats export-ply` / `export-3dgs`: what is read, and how thin the third axis is."""
    prim: str | None = option(None, help="read only this ParticleField prim", flag="--prim",
                              metavar="PRIM")
    time: float | None = option(None, help="time code to read (default: the default time)",
                                flag="--time", metavar="TIME")
    thin: float = option(1e-3, help="3DGS third axis as a fraction of the smaller disk scale",
                         flag="--thin", metavar="THIN")


@dataclass
class ExportPlyConfig(ExportConfig):
    layout: str = option("2dgs", help="2dgs: scale_0..1 (2DGS, gsplat 2DGS); 3dgs: scale_0..2 "
                                      "with the thin axis", flag="--layout",
                         choices=("2dgs", "3dgs"))



@dataclass
class Export3dgsConfig(ExportConfig):
    out_prim: str = option("/World/Surfels", help="prim path in the output file",
                           flag="--out-prim", metavar="OUT_PRIM")
