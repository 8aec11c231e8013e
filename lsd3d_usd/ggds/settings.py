"""GGDS configuration: one typed tree (lsd3d_usd.configtree) from which `generate`'s flags,
config-file and batch keys, `--set ggds.…` overrides and run provenance derive.

Defaults were chosen by measured held-out PSNR on the README sample (docs/ggds.md)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from lsd3d_usd.configtree import option
from lsd3d_usd.errors import InputError
from lsd3d_usd.semantics import CLASSES
from lsd3d_usd.ggds.losses.terms import LOSSES
from lsd3d_usd.render.backends import check_backend_name

OMEGA_KINDS = ("uniform", "sds", "signal")   # ggds/losses/image.py: omega(t)
MAX_RESOLUTION = 8192                        # GGDS render side limit (pixels)


GROUND_CLASSES = "road,lane_marking,crosswalk,sidewalk,curb"


def check_ground_classes(value: str, where: str) -> str:
    """A comma-separated list of semantic class names (lsd3d_usd.semantics), or empty."""
    names = [n.strip() for n in str(value).split(",") if n.strip()]
    bad = [n for n in names if n not in CLASSES]
    if bad:
        raise InputError(f"{where}: unknown class {bad[0]!r} (known: {', '.join(CLASSES)})")
    return ",".join(names)


def _loss_weights() -> dict:
    return {name: LOSSES.get(name).default_weight for name in LOSSES.names()}


@dataclass
class LearningRates:
    means: float = option(2e-3, help="surfel position learning rate at the start (metres)", lo=0.0)
    means_end: float = option(2e-5, help="position learning rate at the end (log-linear decay)",
                              lo=0.0)
    quats: float = option(2e-3, help="orientation learning rate", lo=0.0)
    scales: float = option(5e-3, help="log-scale learning rate", lo=0.0)
    opacities: float = option(5e-2, help="logit-opacity learning rate", lo=0.0)
    sh_dc: float = option(1.5e-2, help="SH DC (base colour) learning rate (higher values "
                                       "random-walk rarely seen colours into blotches)", lo=0.0)
    sh_dc_end: float | None = option(None, help="if set, the SH learning rate decays "
                                                "log-linearly to this", lo=0.0)
    sh_rest_factor: float = option(0.05, help="higher-order SH learning rate = sh_dc × this "
                                              "(as 3DGS: 1/20)", lo=0.0)
    sh_relative: float = option(0.25, help="a colour channel's SH steps scale with sqrt(its "
                                           "base colour / this), at most 1: fixed-size steps "
                                           "random-walk dark colours (shadows, façades) into "
                                           "speckle (0 = every colour alike)", lo=0.0,
                                recorded=0.0)
    sh_relative_min: float = option(0.1, help="least factor of sh_relative", lo=0.0, hi=1.0)
    adam_eps_sh: float = option(1e-7, help="Adam epsilon of the SH coefficients (a surfel "
                                           "whose colour gradient is far below it, seen "
                                           "only through many others, moves less than a "
                                           "full step)", lo=0.0)


@dataclass
class StrategyConfig:
    """MCMC strategy (ggds/optim/strategy.py): tangent-plane SGLD noise and dead-surfel relocation."""
    noise_scale: float = option(0.5, help="SGLD noise in units of the surfel's std-dev (0 = off)",
                                lo=0.0)
    gate_sharpness: float = option(100.0, help="k of the noise gate sigmoid(-k (opacity - t))",
                                   lo=0.0)
    gate_threshold: float = option(0.005, help="t of the noise gate: only near-dead surfels move",
                                   lo=0.0, hi=1.0)
    relocate_every: int = option(50, help="steps between relocations of dead surfels (0 = never)",
                                 lo=0)
    dead_opacity: float = option(0.005, help="surfels below this opacity are relocated",
                                 lo=0.0, hi=1.0)
    max_relocate_frac: float = option(0.05, help="at most this fraction relocated at once",
                                      lo=0.0, hi=1.0)
    densify_frac: float = option(0.0, help="error-driven densification: at each relocation "
                                           "move up to this fraction of the surfels, the most "
                                           "redundant ones (see redundant_coef), onto surfels "
                                           "with high residual and split those (needs "
                                           "filter_3d > 0; 0 = off)", lo=0.0, hi=1.0)
    redundant_coef: float = option(0.25, help="a surfel is redundant when the 3D smoothing "
                                              "filter keeps less than this fraction of its "
                                              "opacity (it is much smaller than the finest "
                                              "training pixel)", lo=0.0, hi=1.0)


REGION_MODES = ("auto", "scene", "chunk")


@dataclass
class RegionConfig:
    """How GGDS splits a scene into regions optimised one after another (ggds/regions/)."""
    # keys stored configurations may hold that are no longer options: fit_inner_frac is
    # ggds.world_init_views for every region now (a stored value is dropped)
    RETIRED: ClassVar[tuple] = ("fit_inner_frac",)
    mode: str = option("auto", help="'scene' (one region), 'chunk' (one region per chunk, in "
                                    "parallel phases, each conditioned on its neighbours) or "
                                    "'auto' (scene when it spans at most max_scene_chunks "
                                    "chunks and holds at most max_scene_surfels surfels)",
                       choices=REGION_MODES, flag="--regions")
    max_scene_chunks: int = option(4, help="auto: scenes spanning at most this many chunks "
                                           "may run as one region", lo=1, hi=10_000)
    max_scene_surfels: int = option(1_000_000, help="auto: ... and holding at most this many "
                                                   "surfels (one region's memory grows with "
                                                   "its surfels: ~1 GB per million)",
                                    lo=1, hi=100_000_000)
    views_per_chunk: int = option(128, help="training views of a one-chunk region", lo=1,
                                  hi=100_000)
    band_m: float = option(30.0, help="frozen neighbour surfels within this distance of a "
                                      "region condition it (metres)", lo=0.0, hi=1000.0)
    view_margin_m: float = option(20.0, help="a region's training views stand on lanes inside "
                                             "it or up to this far outside, so surfels at its "
                                             "border are seen from both sides (metres)",
                                  lo=0.0, hi=1000.0)
    fit_margin_m: float = option(50.0, help="the world-space colour start of a chunk region "
                                            "also fits to views standing up to this far "
                                            "outside it, as the whole-scene fit would (0 = "
                                            "none beyond the training views' margin; "
                                            "metres)", lo=0.0, hi=1000.0)
    fit_view_frac: float = option(0.5, help="views sampled per chunk for that fit, as a "
                                            "fraction of views_per_chunk; those beyond "
                                            "view_margin_m that see the region's surfels are "
                                            "used", lo=0.0, hi=10.0)
    fit_context: bool = option(False, help="the colour start of a chunk region also "
                                           "colours its unfinished neighbours' frozen band "
                                           "surfels (initial surfels carry flat class "
                                           "colours); measured: no change to the composed "
                                           "scene at the defaults, docs/large_scale.md",
                               recorded=False)
    share_views: bool = option(False, help="a chunk region also trains on its neighbours' "
                                           "training views that stand within view_margin_m "
                                           "of it (its border surfels are otherwise seen by "
                                           "about half the views its interior is; pays off "
                                           "with view_margin_m=40 at few views per chunk, "
                                           "docs/large_scale.md)", recorded=False)


@dataclass
class GGDSConfig:
    steps: int = option(250, help="GGDS steps (0 = no optimisation)", flag="--steps",
                        alias="steps", lo=0, hi=10_000_000)
    resolution: tuple[int, int] = option((480, 270), help="GGDS render size WxH",
                                         flag="--resolution", alias="resolution", lo=1,
                                         hi=MAX_RESOLUTION, metavar="WxH")
    views: int = option(128, help="training views sampled along and off the lanes",
                        flag="--views", alias="views", lo=1, hi=100_000)
    novel_frac: float = option(0.25, help="fraction of training views placed off the lanes",
                               lo=0.0, hi=1.0)
    novel_style: str = option("lane_offset", help="off-lane training views: 'lane_offset' "
                                                  "(0.5-5 m beyond the lane edge, free heading, "
                                                  "1.2-3 m high) or 'displaced' (a lane view "
                                                  "moved 0.5-8 m as eval's novel views are)",
                              choices=("lane_offset", "displaced"))
    elevated_frac: float = option(0.25, help="elevated views (above the road, looking "
                                              "down: conditioning.elevated_sampling) as a fraction "
                                              "of --views: the colour start fits to them "
                                              "(GGDS trains on them too with "
                                              "elevated_train), and to as many more per "
                                              "world_init_views; of views_per_chunk × its "
                                              "chunks in a chunk region; nothing without the "
                                              "colour start (world_init) unless trained on "
                                              "(0 = none)", lo=0.0, hi=10.0, recorded=0.0)
    elevated_train: bool = option(False, help="train on the elevated views (else the colour "
                                             "start alone fits to them)")
    elevated_fit_weight: float = option(0.5, help="weight of the elevated views' samples in "
                                                  "the colour start against the eye-height "
                                                  "views' (below 1 a surfel both see keeps "
                                                  "more of the colour seen from the road; "
                                                  "docs/ggds.md, views from above)",
                                        lo=1e-3, hi=1.0)
    elevated_heights: tuple[float, float] = option((4.0, 40.0), help="heights of the "
                                                   "elevated views over a lane, log-uniform "
                                                   "between these (metres)", lo=0.1,
                                                   hi=10_000.0, metavar="LOxHI")
    elevated_overview_frac: float = option(0.5, help="share of the elevated views of a "
                                                      "whole-scene run that frame the layout "
                                                      "from above, as its Overview cameras "
                                                      "do", lo=0.0, hi=1.0)
    stratified_views: bool = option(True, help="training views placed one per equal part of "
                                                "the lanes' length (else drawn independently)",
                                    recorded=False)
    fov_deg: float = option(70.0, help="horizontal field of view of the training views (deg)",
                            lo=1.0, hi=170.0)
    held_out: int = option(8, help="held-out views evaluated at the end of a run", lo=0,
                           hi=10_000)
    t_max: float = option(0.98, help="largest prior noise level t", lo=0.0, hi=1.0)
    t_min_start: float = option(0.9, help="t_min at the first step (annealed linearly ...)",
                                lo=0.0, hi=1.0)
    t_min_end: float = option(0.2, help="... to this at the last step", lo=0.0, hi=1.0)
    n_denoise: int = option(5, help="prior denoising steps per target (the paper's N)",
                            lo=1, hi=1000)
    omega: str = option("uniform", help="weighting ω(t) of the image terms (ggds/losses/image.py; "
                                        "'sds' suits a diffusion prior)", choices=OMEGA_KINDS,
                        flag="--omega")
    checkpoint_every: int = option(50, help="steps between checkpoints",
                                   flag="--checkpoint-every", alias="checkpoint_every", lo=1)
    colour_floor: float = option(0.002, help="least base colour (0.5 + C0 · SH DC) per channel "
                                             "after each update and the colour start: below 0 "
                                             "the renderer passes a colour no gradient, so a "
                                             "channel pushed there stays black (0 = no floor)",
                                 lo=0.0, hi=0.5, recorded=0.0)
    untrained_opacity: float = option(0.99, help="colour start: opacity at least this for "
                                                 "surfels no training view sees (roofs, backs), "
                                                 "which the steps never reach; at the initial "
                                                 "0.8 a surface of them is see-through (0 = off)",
                                      lo=0.0, hi=0.999, recorded=0.0)
    world_init: bool = option(True, help="start surfel colours from the prior evaluated in 3D "
                                         "(when the prior can)")
    filter_3d: float = option(0.0, help="3D smoothing filter (anti-aliasing, Mip-Splatting): "
                                         "each disk is convolved with σ = this × the pixel "
                                         "footprint of the finest training view that sees it "
                                         "(0 = off)", lo=0.0, hi=10.0)
    world_init_views: float = option(1.0, help="world-space start: the colour fit also uses "
                                               "this many views per training view, sampled "
                                               "like them (never trained on; a chunk region "
                                               "also fits to views beyond its margin, "
                                               "ggds.regions.fit_*)", lo=0.0, hi=100.0)
    world_init_samples: int = option(16, help="world-space start: points per surfel, each seen "
                                             "from a training camera that has it in view, to "
                                             "which its view-dependent SH colour is fitted",
                                     lo=1, hi=64)
    world_init_ridge: float = option(0.003, help="world-space start: ridge on the SH terms that "
                                                 "depend on the angle to the surfel's normal "
                                                 "(relative to the DC term's weight)", lo=0.0)
    world_init_ridge_tangent: float = option(1.0, help="world-space start: ridge on the SH "
                                                       "terms that depend on the azimuth around "
                                                       "the normal", lo=0.0)
    world_init_zonal_prior: bool = option(False, help="world-space start: the ridge on the "
                                                      "terms that depend on the angle to the "
                                                      "normal pulls towards the median of the "
                                                      "well-seen surfels of the same class and "
                                                      "facing, not towards zero")
    ground_classes: str = option(GROUND_CLASSES,
                                 help="surfels of these classes (comma-separated; empty = "
                                      "none) stay on the plane of the proxy face they were "
                                      "seeded on and face its normal: the map's flat ground "
                                      "is exact geometry, so depth, LiDAR ranges and normals "
                                      "on it stay the proxy's (ggds/optim/grounding.py)",
                                 check=check_ground_classes)
    backend: str = option("numba", help="renderer backend of the run (render/backends.py: "
                                        "numba, torch, or a registered one)",
                          check=lambda v, where: check_backend_name(v, where), recorded="numba")
    perceptual: bool = option(True, help="the perceptual loss term", alias="perceptual",
                              negate="--no-perceptual")
    lpips: Path | None = option(None, help="use LPIPS as the perceptual term: a local "
                                           "torchvision AlexNet or VGG16 state dict (never "
                                           "downloaded; needs a perceptual weight > 0)",
                                flag="--lpips", alias="lpips", metavar="BACKBONE.pth")
    lpips_lin: Path | None = option(None, help="LPIPS linear weights (default: found in an "
                                               "installed lpips package)",
                                    flag="--lpips-lin", alias="lpips_lin", metavar="LIN.pth")
    weights: dict[str, float | None] = option(
        help="loss term weights by name (ggds/losses/terms.py; perceptual: none = the prior's "
             "default)", default_factory=_loss_weights, keys=_loss_weights, lo=0.0)
    lr: LearningRates = field(default_factory=LearningRates)
    strategy: StrategyConfig = field(default_factory=StrategyConfig)
    regions: RegionConfig = field(default_factory=RegionConfig)
    # Not options: set by the caller for each run.
    seed: int = 0

    @property
    def width(self) -> int:
        return int(self.resolution[0])

    @property
    def height(self) -> int:
        return int(self.resolution[1])

    def weight(self, name: str, default: float | None = None) -> float:
        v = self.weights.get(name)
        return float(default if v is None else v) if (v is not None or default is not None) else 0.0
