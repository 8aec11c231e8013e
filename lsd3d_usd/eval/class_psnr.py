"""PSNR of rendered views against the GGDS run's held-out targets, per view and per semantic
class, for every view family eval renders.

A view's error is the squared difference of the linear render and the target, both clipped
to [0, 1], summed over pixels and channels (as eval.seams_eval.view_errors); per class over
the pixels whose label in the proxy G-buffer the prior conditioned on (the target's own
G-buffer, `ScenePrior.heldout_target`) is that class. A family's PSNR pools its views
(views weighted by their pixels), so a class seen in few pixels of a view counts by its pixels.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from lsd3d_usd.eval.seams_eval import pooled_psnr, run_prior
from lsd3d_usd.views.labels import class_of_names

CLASSES = ("road", "sidewalk", "building", "vegetation", "terrain")
CLASS_IDS = dict(zip(CLASSES, class_of_names(CLASSES).tolist()))


@dataclass
class ViewError:
    """(sum of squared errors, values) of one view over all its pixels and per class."""
    sse: float
    n: int
    per_class: dict = field(default_factory=dict)   # class name -> (sse, values)


def view_error(rgb: np.ndarray, target: np.ndarray, semantic: np.ndarray) -> ViewError:
    """The error of one rendered view (H, W, 3) against its target, with the target's class
    labels (H, W)."""
    err = (np.clip(np.asarray(rgb, np.float64), 0, 1)
           - np.clip(np.asarray(target, np.float64), 0, 1)) ** 2
    per_pixel = err.sum(axis=-1)
    sem = np.asarray(semantic)
    per_class = {}
    for name, cid in CLASS_IDS.items():
        m = sem == cid
        per_class[name] = (float(per_pixel[m].sum()), 3 * int(m.sum()))
    return ViewError(float(err.sum()), int(err.size), per_class)


def psnr_stats(errors: list) -> dict:
    """{mean, median, min, max, views} of the views' own PSNRs (empty without views)."""
    if not errors:
        return {}
    a = np.array([pooled_psnr([(e.sse, e.n)]) for e in errors], np.float64)
    return {"mean": round(float(a.mean()), 3), "median": round(float(np.median(a)), 3),
            "min": round(float(a.min()), 3), "max": round(float(a.max()), 3), "views": len(a)}


def pooled(errors: list) -> float | None:
    """PSNR in dB of the views pooled; None without values."""
    v = pooled_psnr([(e.sse, e.n) for e in errors])
    return None if np.isnan(v) else round(v, 3)


def per_class(errors: list) -> dict:
    """{class: pooled PSNR in dB, or None where no view shows it}."""
    out = {}
    for name in CLASSES:
        v = pooled_psnr([e.per_class[name] for e in errors])
        out[name] = None if np.isnan(v) else round(v, 3)
    return out


class Scorer:
    """The run's held-out targets of eval's views, scored as they are rendered. ``why`` says
    why there is no score (no run, or a prior that is slow on the CPU)."""

    def __init__(self, sc, run: str | None, proxy, keep=()):
        t = time.perf_counter()
        self.keep = set(keep)          # families whose targets are kept (the seam measure's)
        self.targets: dict[str, list] = {}
        self.sp, self.why = run_prior(sc, run, proxy)
        self.errors: dict[str, list] = {}
        self._j = 0
        self.seconds = time.perf_counter() - t

    @property
    def ok(self) -> bool:
        return self.sp is not None

    def add(self, family: str, camera, rgb: np.ndarray) -> np.ndarray | None:
        """Score the render ``rgb`` of ``camera`` in ``family``; returns the target (linear),
        or None without a prior. Views are numbered in call order (the held-out seed)."""
        if self.sp is None:
            return None
        t = time.perf_counter()
        key = object()      # the prior's per-view cache entry, dropped below: never scored again
        target, gb = self.sp.heldout_target(camera, rgb, self._j, key=key)
        self._j += 1
        forget = getattr(self.sp.prior, "forget", None)
        if forget is not None:
            forget([key])
        self.errors.setdefault(family, []).append(
            view_error(rgb, target, gb.semantic.cpu().numpy()))
        if family in self.keep:
            self.targets.setdefault(family, []).append(target)
        self.seconds += time.perf_counter() - t
        return target

    def family(self, family: str, idx=None) -> list:
        errs = self.errors.get(family, [])
        return errs if idx is None else [errs[i] for i in idx]
