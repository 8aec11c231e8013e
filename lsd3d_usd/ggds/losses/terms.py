"""GGDS loss terms: small named objects in one registry (built-ins here, third-party ones from
the ``lsd3d_usd.losses`` entry-point group). A GGDS step sums ``weight × term(ctx)`` over the
terms whose weight (``ggds.weights.<name>``) is > 0; image terms are also multiplied by ω(t).

A term sees one step's :class:`StepContext`: the render (a RasterResult), the prior's target,
the view's proxy G-buffer and camera, the noise level and the configuration. A term that
needs state built once per run (a network, say) gives a ``setup(config, prior)`` whose
result arrives as ``ctx.state[name]``. See docs/extending.md.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from lsd3d_usd.registry import Registry

# torch and the loss functions are imported inside the terms: the registry (and with it the
# configuration's default weights, needed by `--help`) must load without them.


@dataclass
class StepContext:
    x: Any                          # (H,W,3) torch tensor: rendered colour (differentiable)
    target: Any                     # (H,W,3) the prior's target (detached)
    render: Any                     # the rasteriser's full result for this view
    gbuffer: Any                    # prior_base.GBuffer of the view
    camera: Any                     # render.camera.Camera
    t: float                        # noise level of this step
    config: Any                     # GGDSConfig
    state: dict = field(default_factory=dict)

    def covered(self):
        """(H,W) pixels where both the proxy and the surfels are present."""
        return self.gbuffer.valid & (self.render.alpha > 0.5)


@dataclass(frozen=True)
class LossTerm:
    name: str
    fn: Callable[[StepContext], Any]     # -> scalar torch tensor
    default_weight: float | None = 0.0     # None: decided per prior (see the perceptual term)
    image: bool = False                    # scaled by ω(t): compares the render to the target
    needs: tuple[str, ...] = ()            # extra render outputs, e.g. ("distortion",)
    setup: Callable[[Any, Any], Any] | None = None
    help: str = ""


# ----------------------------------------------------------------------------- built-ins
def _l1(ctx: StepContext):
    # local import: the registry loads without torch (module note)
    from lsd3d_usd.ggds.losses import image as losses
    return losses.l1_loss(ctx.x, ctx.target)


def _l2(ctx: StepContext):
    return ((ctx.x - ctx.target) ** 2).mean()


def _perceptual(ctx: StepContext):
    return ctx.state["perceptual"](ctx.x.clamp(0, 1), ctx.target.clamp(0, 1))


def _perceptual_setup(cfg, prior):
    if cfg.lpips is not None:
        # local import: the registry loads without torch (module note)
        from lsd3d_usd.ggds.losses.lpips import LPIPSLoss
        return LPIPSLoss.from_files(cfg.lpips, cfg.lpips_lin, linear=True)  # renders are linear
    # local import: the registry loads without torch (module note)
    from lsd3d_usd.ggds.losses.perceptual import EffNetPerceptualLoss
    return EffNetPerceptualLoss()


def _normal(ctx: StepContext):
    # local import: the registry loads without torch (module note)
    import torch

    # local import: the registry loads without torch (module note)
    from lsd3d_usd.ggds.losses import image as losses
    R = torch.from_numpy(ctx.camera.viewmat[:3, :3].astype(np.float32))
    proxy_n_cam = ctx.gbuffer.normal @ R.T
    return losses.normal_loss(ctx.render.normal, proxy_n_cam, ctx.covered(), two_sided=True)


def _disparity(ctx: StepContext):
    # local import: the registry loads without torch (module note)
    from lsd3d_usd.ggds.losses import image as losses
    return losses.disparity_loss(ctx.render.depth_expected, ctx.gbuffer.depth, ctx.covered())


def _normal_consistency(ctx: StepContext):
    # local import: the registry loads without torch (module note)
    import torch

    # local import: the registry loads without torch (module note)
    from lsd3d_usd.ggds.losses.regularizers import normal_consistency
    r = ctx.render
    return normal_consistency(r.normal, r.depth_expected, r.alpha,
                              torch.from_numpy(ctx.camera.K))


def _tv(ctx: StepContext):
    # local import: the registry loads without torch (module note)
    from lsd3d_usd.ggds.losses import image as losses
    return losses.tv_loss(ctx.x)


def _distortion(ctx: StepContext):
    return ctx.render.distortion.mean()


L1 = LossTerm("l1", _l1, 1.0, image=True, help="mean |render − target|")
L2 = LossTerm("l2", _l2, 0.0, image=True, help="mean (render − target)²")
PERCEPTUAL = LossTerm("perceptual", _perceptual, None, image=True, setup=_perceptual_setup,
                      help="EfficientNet-Lite0 features (or LPIPS with --lpips); default weight "
                           "by prior: 0 for the procedural prior, 0.05 for a diffusion prior")
NORMAL = LossTerm("normal", _normal, 0.1, help="1 − |cos| between rendered and proxy normals")
DISPARITY = LossTerm("disparity", _disparity, 1.0,
                     help="relative depth error against the proxy")
NORMAL_CONSISTENCY = LossTerm("normal_consistency", _normal_consistency, 0.05,
                              help="2DGS: rendered normals vs normals of the rendered depth")
TV = LossTerm("tv", _tv, 0.01, help="total variation of the render")
DISTORTION = LossTerm("distortion", _distortion, 0.0, needs=("distortion",),
                      help="2DGS depth distortion (measured: no PSNR gain on the README sample)")

LOSSES = Registry("lsd3d_usd.losses", "loss term", {
    t.name: f"lsd3d_usd.ggds.losses.terms:{n}" for n, t in (
        ("L1", L1), ("L2", L2), ("PERCEPTUAL", PERCEPTUAL), ("NORMAL", NORMAL), ("DISPARITY", DISPARITY),
        ("NORMAL_CONSISTENCY", NORMAL_CONSISTENCY), ("TV", TV), ("DISTORTION", DISTORTION))})


def active_terms(cfg, prior) -> list[tuple[LossTerm, float]]:
    """(term, weight) for every registered term with a weight > 0 under ``cfg`` and ``prior``
    (a None weight takes the prior's default for that term)."""
    out = []
    for name in LOSSES.names():
        term = LOSSES.get(name)
        w = cfg.weights.get(name, term.default_weight)
        if w is None:
            w = prior.default_weight(name)
        if name == "perceptual" and not cfg.perceptual:
            w = 0.0
        if w and w > 0:
            out.append((term, float(w)))
    return out
