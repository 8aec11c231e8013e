"""What one GGDS run optimises against, as arrays (no USD): the contract between the callers
that prepare a run (a region of a scene, a benchmark, a test) and the run itself."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.splats.field import SurfelField


@dataclass(kw_only=True)
class GGDSInputs:
    """field: the initial surfels (trainable). conditioning: the proxy, light, shadow map and
    G-buffers the prior sees. views / held_out: training and held-out views
    (conditioning.view_sampling.View). face_index: the seed proxy face of every surfel (rows of the
    conditioning's proxy, -1 unknown). context: frozen neighbour surfels rendered with the
    trainable ones (a chunk region's band); focus (x0, y0, x1, y1): where the loaded surfels
    cover the scene (image terms and held-out PSNR compare only pixels whose proxy surface
    lies there). fit_views: more views for the colour start only. context_start (len(context),)
    bool: context rows whose colours the colour start fits too (a neighbour's initial
    surfels, which still carry class colours); None: the context keeps its colours."""
    field: SurfelField | None
    conditioning: Conditioning
    views: list
    held_out: list = field(default_factory=list)
    face_index: np.ndarray | None = None
    context: SurfelField | None = None
    focus: tuple | None = None
    fit_views: list = field(default_factory=list)
    context_start: np.ndarray | None = None
