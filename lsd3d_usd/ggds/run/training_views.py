"""The training views of a run and what a step needs of each: its packed proxy G-buffer and
background, kept between visits (33 B/px; an unpacked view is 65), and the focus mask."""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch

from lsd3d_usd.conditioning.gbuffer import GBuffer, PackedGBuffer
from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.conditioning.view_sampling import View

_RUN_KEYS = itertools.count()   # G-buffer keys unique across the runs of a process


@dataclass
class ViewData:
    view: View
    gbuffer: GBuffer
    background: torch.Tensor | None     # (H,W,3) env radiance behind the surfels
    mask: torch.Tensor | None = None    # (H,W) bool: pixels the image terms compare (None: all)


def focus_mask(gbuffer: GBuffer, focus) -> torch.Tensor | None:
    """Pixels whose proxy surface lies inside ``focus`` (x0, y0, x1, y1), or that show no
    proxy surface (the sky): what a region's render can be compared on. Beyond the focus the
    scene's surfels are not loaded, so the render shows the sky where the prior sees geometry."""
    if focus is None:
        return None
    x0, y0, x1, y1 = focus
    w = gbuffer.world_pos
    inside = (w[..., 0] >= x0) & (w[..., 0] <= x1) & (w[..., 1] >= y0) & (w[..., 1] <= y1)
    return torch.where(gbuffer.valid, inside, torch.ones_like(inside))


class TrainingViews:
    """Training views with their G-buffers made on first visit and kept (keyed by run and
    view, so a prior can cache what it derives per view) until ``release``."""

    def __init__(self, views: list, conditioning: Conditioning, prior, focus=None):
        self.views = list(views)
        self.conditioning = conditioning
        self.prior = prior
        self.focus = focus
        self.key = next(_RUN_KEYS)
        self._cache: dict[int, tuple[PackedGBuffer, torch.Tensor | None]] = {}

    def __len__(self) -> int:
        return len(self.views)

    @property
    def cached(self) -> int:
        """How many views hold a cached G-buffer."""
        return len(self._cache)

    def get(self, i: int) -> ViewData:
        cam = self.views[i].camera
        if i not in self._cache:
            self._cache[i] = (self.conditioning.packed(cam), self.conditioning.background(cam))
        packed, bg = self._cache[i]
        gb = self.conditioning.unpack(packed, key=(self.key, i))
        return ViewData(self.views[i], gb, bg, focus_mask(gb, self.focus))

    def release(self) -> None:
        """Drop what the steps kept per view (packed G-buffers, backgrounds, the prior's cached
        targets: ~6 MB per view at 480x270); ``get`` builds them again."""
        self.prior.forget([(self.key, i) for i in self._cache])
        self._cache.clear()
