"""What `evaluate` returns: one typed part per family of measures, read by attribute (the report,
the CLI, the benchmarks). ``EvalResult.to_json()`` is eval.json's layout (docs/eval.md), which
users and checks rely on: its keys and their order are fixed; the parts that other modules
already produce as JSON-ready dicts (FD results, geometry, temporal, seams) stay dicts."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

FEATURES_NOTE = ("EfficientNet-Lite0 pooled 1280-d (bundled ImageNet weights), 224x224 "
                 "bilinear resize of the sRGB display image")
PAIRS_NOTE = ("each novel view vs the seen view it was displaced from (seen depth reprojected "
              "into the novel view; proxy decides mutual visibility)")
PRIOR_TARGET_NOTE = "seen + novel views against the prior's own image of the same views (t = 1)"


@dataclass
class Counts:
    """How many views of each family were rendered (``counts``)."""
    train_views: int
    seen: int
    novel: int
    novel_per_bin: int
    heldout_lane: int
    trajectory_frames: int
    reference: int
    elevated: int
    elevated_per_height: int
    overview: int
    off_path: int = 0
    off_path_per_bin: int = 0


@dataclass
class SeenVsNovel:
    """FD of the seen views' features against the novel views', all and per distance bin
    (keyed by the bin's "%g")."""
    overall: dict
    per_bin: dict[str, dict]

    def to_json(self) -> dict:
        return {"overall": self.overall, "per_bin": self.per_bin}


@dataclass
class Distances:
    """The Fréchet distances (``fd_effnet_lite0``); an optional family is None when not measured."""
    seen_vs_novel: SeenVsNovel
    seen_vs_heldout_lane: dict | None = None
    prior_baseline: dict | None = None       # eval.prior_baseline.baseline_fd
    vs_reference: dict | None = None

    def to_json(self) -> dict:
        out = {"features": FEATURES_NOTE, "seen_vs_novel": self.seen_vs_novel.to_json()}
        for key in ("seen_vs_heldout_lane", "prior_baseline", "vs_reference"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out


@dataclass
class Geometry:
    """Surfels against the proxy (eval.geometry.ClassAgreement.result) for the two families."""
    seen: dict
    novel: dict


@dataclass
class MultiviewDepth:
    """Seen depth reprojected into the novel views displaced from them (``multiview_depth_err``)."""
    per_bin: dict[str, dict]
    median: float | None
    frac_over_5pct: float | None

    def to_json(self) -> dict:
        return {"pairs": PAIRS_NOTE, "per_bin": self.per_bin, "median": self.median,
                "frac_over_5pct": self.frac_over_5pct}


@dataclass
class DeferredResult:
    """The deferred renders' measures; ``provenance`` is views.deferred.Deferrer.describe()."""
    provenance: dict
    seen_vs_novel: SeenVsNovel
    vs_prior_raw: dict
    vs_prior_deferred: dict
    temporal: dict

    def to_json(self) -> dict:
        return {**self.provenance,
                "fd_effnet_lite0": {"seen_vs_novel": self.seen_vs_novel.to_json(),
                                    "vs_prior_target": {"views": PRIOR_TARGET_NOTE,
                                                        "raw": self.vs_prior_raw,
                                                        "deferred": self.vs_prior_deferred}},
                "temporal_warp_err": self.temporal}


@dataclass
class EvalResult:
    scene: str
    run: str | None
    seen_views_source: str
    composed_layers: list[str]
    surfels: int
    resolution: list[int]
    tonemap: str
    seed: int
    bins_m: list[float]
    heights_m: list[float]
    pitch_deg: list[float]
    counts: Counts
    seen_views: dict                     # PSNR vs the run's targets, all and per class
    novel_views: dict[str, dict]         # per bin: count, pose medians, PSNR
    novel_elevated: dict[str, dict]      # per height, "overview", "heldout_lane"
    novel_off_path: dict                 # per lateral / height / yaw bin (eval.off_path_views)
    distances: Distances
    geometry: Geometry
    multiview: MultiviewDepth
    seams: dict | None
    temporal: dict
    deferred: DeferredResult | None
    unavailable: list[dict]
    warnings: list[str]
    timings: dict[str, float]
    files: dict[str, str] = field(default_factory=dict)   # set once the report is written

    def to_json(self) -> dict:
        out = {"scene": self.scene, "run": self.run, "seen_views_source": self.seen_views_source,
               "composed_layers": self.composed_layers, "surfels": self.surfels,
               "resolution": self.resolution, "tonemap": self.tonemap, "seed": self.seed,
               "bins_m": self.bins_m, "heights_m": self.heights_m, "pitch_deg": self.pitch_deg,
               "counts": asdict(self.counts), "seen_views": self.seen_views,
               "novel_views": self.novel_views, "novel_elevated": self.novel_elevated,
               "novel_off_path": self.novel_off_path, "fd_effnet_lite0": self.distances.to_json(),
               "geometry": asdict(self.geometry), "multiview_depth_err": self.multiview.to_json(),
               "seams": self.seams, "temporal_warp_err": self.temporal}
        if self.deferred is not None:
            out["deferred"] = self.deferred.to_json()
        out.update(unavailable=self.unavailable, warnings=self.warnings, timings=self.timings)
        if self.files:
            out["files"] = self.files
        return out
