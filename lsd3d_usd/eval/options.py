"""The configuration tree of `eval` (lsd3d_usd.configtree): every flag is a leaf, so
`eval --config FILE.toml --set KEY=VALUE` work as for `generate`; the deferred subtree is
`render`'s."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lsd3d_usd.configtree import option
from lsd3d_usd.errors import InputError
from lsd3d_usd.eval.elevated_views import DEFAULT_HEIGHTS, DEFAULT_PITCH, parse_heights, parse_pitch
from lsd3d_usd.eval.lane_views import DEFAULT_BINS
from lsd3d_usd.views.images import TONEMAPS
from lsd3d_usd.views.options import DeferredConfig


def parse_bins(text: str, where: str = "--bins") -> tuple[float, ...]:
    """'0.5,1,2' → (0.5, 1.0, 2.0): positive distances in metres."""
    try:
        vals = tuple(float(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise InputError(f"{where} {text!r}: expected comma-separated metres, e.g. "
                         "0.5,1,2,4,8") from None
    if not vals:
        raise InputError(f"{where}: give at least one distance")
    if any(not b > 0 for b in vals):
        raise InputError(f"{where} {text}: need positive distances")
    return vals


def _check_bins(v: str, where: str) -> str:
    parse_bins(v, where)
    return v


def _check_heights(v: str, where: str) -> str:
    parse_heights(v, where)
    return v


def _check_pitch(v: str, where: str) -> str:
    parse_pitch(v, where)
    return v


@dataclass
class EvalConfig:
    """`eval`: what is rendered and measured (run control — scene, output, progress — is not
    configuration)."""
    run: str | None = option(None, help="GGDS run whose training cameras are the seen views "
                                        "(default: the newest unmuted run)", flag="--run",
                             metavar="NAME")
    reference: Path | None = option(None, help="folder of reference images (png/jpg/...; at "
                                               "least 2) to compare against",
                                    flag="--reference", metavar="DIR")
    weights: Path | None = option(None, help="folder of local weight files for Inception FID "
                                             "/ FD-DINOv2 / CLIP score / FVD (expected names "
                                             "in docs/eval.md); nothing is downloaded",
                                  flag="--weights", metavar="DIR")
    n_seen: int = option(16, help="seen views to render", flag="--seen", lo=1, hi=100_000)
    n_heldout: int | None = option(None, help="fresh on-lane views (not trained on) rendered "
                                              "as the FD reference for a change of content "
                                              "(default: as many as --seen; 0 = none)",
                                   flag="--heldout", lo=0, hi=100_000)
    per_bin: int = option(16, help="novel views per distance bin", flag="--per-bin", lo=1,
                          hi=100_000)
    bins: str = option(",".join(f"{b:g}" for b in DEFAULT_BINS),
                       help="novel-view distances from the training cameras in metres",
                       flag="--bins", check=_check_bins)
    heights: str = option(",".join(f"{h:g}" for h in DEFAULT_HEIGHTS),
                          help="heights in metres of the elevated novel views (above the road "
                               "point each looks at; novel_elevated in the JSON)",
                          flag="--heights", check=_check_heights)
    per_height: int = option(4, help="elevated views per height (0 = none; the Overview "
                                     "cameras still count unless --no-overview)",
                             flag="--per-height", lo=0, hi=100_000)
    pitch: str = option(",".join(f"{p:g}" for p in DEFAULT_PITCH),
                        help="MIN,MAX degrees below the horizon of the elevated views",
                        flag="--pitch", check=_check_pitch, metavar="MIN,MAX")
    overview: bool = option(True, help="score the scene's Overview cameras (/World/Cameras/"
                                       "Overview/*) with the elevated views",
                            negate="--no-overview")
    off_path_per_bin: int = option(3, help="off-path views per bin (stations on the lanes; "
                                           "0 = none): lateral offsets, camera heights and "
                                           "yaws a driving stack's cameras take "
                                           "(novel_off_path in the JSON)",
                                   flag="--off-path-per-bin", lo=0, hi=100_000)
    resolution: tuple[int, int] = option((320, 180), help="render size WxH", flag="--resolution",
                                         lo=16, hi=8192, metavar="WxH")
    frames: int = option(24, help="trajectory frames for the temporal check", flag="--frames",
                         lo=2, hi=100_000)
    step_m: float = option(0.5, help="trajectory spacing in metres", flag="--step",
                           lo=1e-3, hi=1000.0)
    seed: int = option(0, help="seed of view selection and novel offsets", flag="--seed")
    tonemap: str = option("clamp", help="display encoding before features (clamp: what GGDS's "
                                        "prior sees)", flag="--tonemap", choices=TONEMAPS)
    exposure: float = option(0.0, help="exposure in stops before tone mapping",
                             flag="--exposure", lo=-64.0, hi=64.0)
    max_reference: int = option(500, help="use at most this many reference images",
                                flag="--max-reference", lo=2, hi=1_000_000)
    prior_baseline: bool | None = option(None, help="also render the scene's prior at t = 1 "
                                                    "from the same seen, novel and held-out "
                                                    "views: the Fréchet distances a scene "
                                                    "reproducing its prior exactly would give "
                                                    "(default: on for a prior that is cheap on "
                                                    "the CPU, as the procedural one)",
                                         flag="--prior-baseline", negate="--no-prior-baseline")
    seams_reference: Path | None = option(None, help="a scene of the same layout without chunk "
                                                     "seams (generated with --regions scene and "
                                                     "the same seed and settings): rendered "
                                                     "from the held-out views, it gives what the "
                                                     "chunk-wise optimisation adds to the seam "
                                                     "drop (seams.vs_reference in the JSON)",
                                          flag="--seams-reference", metavar="SCENE")
    deferred: DeferredConfig = field(default_factory=DeferredConfig)

    def bin_values(self) -> tuple[float, ...]:
        return parse_bins(self.bins)

    def height_values(self) -> tuple[float, ...]:
        return parse_heights(self.heights)

    def pitch_range(self) -> tuple[float, float]:
        return parse_pitch(self.pitch)
