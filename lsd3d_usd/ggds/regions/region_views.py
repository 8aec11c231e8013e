"""The views of a region: its training and held-out views, its neighbours' views near it, and
the extra views of its colour start."""
from __future__ import annotations

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.elevated_sampling import sample_elevated_views
from lsd3d_usd.conditioning.view_sampling import lane_length_inside, sample_views
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.regions.plan import Region, region_seed


def region_views(layout, g, seed: int, region: Region) -> tuple[list, list]:
    """(training views, held-out views) GGDS samples for ``region`` of a run with config ``g``
    and scene seed ``seed``: ``g.views`` over the whole scene for a whole-scene region, else
    ``views_per_chunk`` per chunk standing on lanes inside the region or up to
    ``view_margin_m`` outside it (so border surfels are seen from both sides), held-out views
    inside it (InputError when it holds no lane). The scene's cameras layer
    (views.scene_cameras) authors the same views; run_region then trains a chunk region on
    those that see any of its surfels (sampling.views_seeing), with ``share_views`` also on
    its neighbours' that stand near it (neighbour_views)."""
    rseed = region_seed(seed, region)
    w, h = g.resolution
    whole = not region.name
    n_views = g.views if whole else g.regions.views_per_chunk * len(region.keys)
    bounds = around = None
    if not whole:
        bounds = region.bounds(float(layout.chunk_size))
        m = g.regions.view_margin_m
        around = (bounds[0] - m, bounds[1] - m, bounds[2] + m, bounds[3] + m)
    views = sample_views(layout, n_views, w, h, seed=rseed, novel_frac=g.novel_frac,
                         fov_deg=g.fov_deg, region=around, clip=not whole,
                         novel_style=g.novel_style, stratified=g.stratified_views)
    if g.elevated_train:
        views += training_elevated(layout, g, rseed, n_views, around, whole)
    held = sample_views(layout, g.held_out, w, h, seed=rseed + 7919, novel_frac=0.5,
                        fov_deg=g.fov_deg, region=bounds, clip=not whole)
    return views, held


def training_elevated(layout, g, rseed: int, n_views: int, around, whole: bool) -> list:
    """The ``elevated_frac × n_views`` elevated views of a region (seed ``rseed``): trained on
    with ``elevated_train``, else fitted to by the colour start only (region_fit_views)."""
    return elevated(layout, g, int(round(g.elevated_frac * n_views)), rseed + 31337, around,
                    whole)


def elevated(layout, g, n: int, seed: int, around, whole: bool) -> list:
    """``n`` elevated views of config ``g`` (conditioning.elevated_sampling): over lanes inside
    ``around`` (clipped to it for a chunk region), and for a whole-scene region a share
    framing the layout."""
    w, h = g.resolution
    return sample_elevated_views(layout, n, w, h, seed=seed, fov_deg=g.fov_deg,
                                 heights=g.elevated_heights, region=around, clip=not whole,
                                 overview_frac=g.elevated_overview_frac if whole else 0.0)


def neighbour_views(layout, g, seed: int, region: Region, chunks) -> list:
    """The views the chunk regions next to ``region`` (those of ``chunks``, the scene's
    surfel chunks) sample for training (region_views) that stand inside it or within
    ``view_margin_m`` of it. Each region samples its views over itself and that margin, so a
    surfel near a border is seen from beyond it only by views reaching ``view_margin_m``
    across, and at half the density of a whole-scene sampling; training a region also on its
    neighbours' views there gives its border surfels about the views its interior has
    (docs/large_scale.md, "Seams"). A neighbour whose views stand denser than the region's own
    (a chunk holding only the end of a lane) is thinned to the region's density, so no
    neighbour floods it with views."""
    size, m = float(layout.chunk_size), g.regions.view_margin_m

    def grown(r):
        x0, y0, x1, y1 = r.bounds(size)
        return x0 - m, y0 - m, x1 + m, y1 + m
    x0, y0, x1, y1 = box = grown(region)
    own = lane_length_inside(layout, box) / len(region.keys)    # lane metres per own view set
    out = []
    for key in sorted(region.neighbourhood() - set(region.keys)):
        if key not in chunks:
            continue
        other = Region((key,), S.chunk_prim_name(*key).lower())
        try:
            views, _ = region_views(layout, g, seed, other)
        except InputError:      # no lane in that chunk: it has no views
            continue
        keep = min(1.0, lane_length_inside(layout, grown(other)) / max(own, 1e-9))
        draw = np.random.default_rng(region_seed(seed, other) + 7_368_787).uniform(size=len(views))
        out += [v for v, u in zip(views, draw) if u < keep
                and x0 <= v.camera.center[0] <= x1 and y0 <= v.camera.center[1] <= y1]
    return out


def region_fit_views(layout, g, seed: int, region: Region) -> list:
    """Extra views for a region's world-space colour start (never trained on). A whole-scene
    region: ``world_init_views`` × its training views, sampled like them (more directions per
    surfel for the fit). A chunk region: the same, and of ``fit_view_frac × views_per_chunk``
    per chunk sampled on lanes up to ``fit_margin_m`` outside it, those standing beyond the
    training views' margin (a surfel near a border is seen by a whole-scene fit from both
    sides and from afar; the region's training views reach only ``view_margin_m`` across, so
    without these its colour would be fitted from one side). Either kind also gets elevated
    views (conditioning.elevated_sampling): with ``elevated_train`` off, the ones region_views would
    otherwise train on (so the colour start alone sees them), and in any case
    ``world_init_views × elevated_frac`` × its training views more."""
    r = g.regions
    w, h = g.resolution
    rseed = region_seed(seed, region)

    def sample(n, seed_, around=None):
        if n <= 0:
            return []
        try:
            return sample_views(layout, n, w, h, seed=seed_, novel_frac=g.novel_frac,
                                fov_deg=g.fov_deg, region=around, clip=around is not None,
                                novel_style=g.novel_style, stratified=g.stratified_views)
        except InputError:      # no lane within ``around``
            return []
    whole = not region.name
    n_train = g.views if whole else r.views_per_chunk * len(region.keys)   # region_views'
    n_elev = int(round(g.world_init_views * g.elevated_frac * n_train))
    if whole:
        views = sample(int(round(g.world_init_views * n_train)), rseed + 104729)
        if not g.elevated_train:
            views += training_elevated(layout, g, rseed, n_train, None, True)
        return views + elevated(layout, g, n_elev, rseed + 27644437, None, True)
    x0, y0, x1, y1 = region.bounds(float(layout.chunk_size))
    m, inner = r.fit_margin_m, r.view_margin_m
    box = (x0 - inner, y0 - inner, x1 + inner, y1 + inner)   # region_views' ``around``
    views = sample(int(round(g.world_init_views * n_train)), rseed + 15485863, box)
    try:
        if not g.elevated_train:
            views += training_elevated(layout, g, rseed, n_train, box, False)
        views += elevated(layout, g, n_elev, rseed + 27644437, box, False)
    except InputError:      # no lane within the box
        pass
    if m <= inner:
        return views
    outer = sample(int(round(r.fit_view_frac * n_train)),
                   rseed + 104729, (x0 - m, y0 - m, x1 + m, y1 + m))
    return views + [v for v in outer if not (x0 - inner <= v.camera.center[0] <= x1 + inner
                                             and y0 - inner <= v.camera.center[1] <= y1 + inner)]
