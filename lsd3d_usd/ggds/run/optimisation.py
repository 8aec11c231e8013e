"""One GGDS optimisation (geometry-grounded distillation sampling), put together from parts
with one job each: the optimisation state (run/state.py), the training views and their
G-buffers (run/training_views.py), the frozen context (run/context.py), the step (run/step.py), the
colour start (colour_start/start.py) and the held-out evaluation (run/evaluate.py). The run's
lifecycle — loop, checkpoints, resume, plots — is run/lifecycle.py.
"""
from __future__ import annotations

import torch

from lsd3d_usd.conditioning.view_sampling import View
from lsd3d_usd.ggds.colour_start.start import colour_start
from lsd3d_usd.ggds.losses.terms import active_terms
from lsd3d_usd.ggds.priors.base import Prior
from lsd3d_usd.ggds.run import evaluate as E
from lsd3d_usd.ggds.run.context import FrozenContext
from lsd3d_usd.ggds.run.inputs import GGDSInputs
from lsd3d_usd.ggds.run.state import RunState
from lsd3d_usd.ggds.run.step import LossSet, render, take_step
from lsd3d_usd.ggds.run.training_views import TrainingViews, ViewData
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.render.raster_types import RasterResult
from lsd3d_usd.splats.field import SurfelField


class GGDSRun:
    """A run over ``inputs`` (run/inputs.py) against ``prior`` with ``config``.

    ``terms``: (LossTerm, weight) pairs (default: losses.terms.active_terms(config, prior));
    per-term state (e.g. the perceptual network) is built once here by each term's setup,
    unless ``term_state`` already holds it. The run reads ``inputs.field`` and
    ``inputs.context`` once (its tensors hold them afterwards)."""

    def __init__(self, inputs: GGDSInputs, prior: Prior, config: GGDSConfig, *, terms=None,
                 term_state: dict | None = None):
        self.cfg = config
        self.prior = prior
        self.conditioning = inputs.conditioning
        self.focus = inputs.focus
        field = inputs.field
        ctx = inputs.context
        self.context = (FrozenContext(ctx, field.sh_degree, inputs.context_start)
                        if ctx is not None and ctx.n else None)
        self.state = RunState(field, config, [v.camera for v in inputs.views], inputs.face_index)
        terms = active_terms(config, prior) if terms is None else list(terms)
        state = dict(term_state or {})
        for term, _ in terms:
            if term.setup is not None and term.name not in state:
                state[term.name] = term.setup(config, prior)
        self.losses = LossSet(terms, state)
        self.views = TrainingViews(inputs.views, self.conditioning, prior, inputs.focus)
        self.fit_views = list(inputs.fit_views)

    # ------------------------------------------------------------ what callers read
    @property
    def env(self):
        return self.conditioning.env

    @property
    def step_index(self) -> int:
        return self.state.step_index

    @property
    def history(self) -> list[dict]:
        return self.state.history

    @property
    def seconds(self) -> float:
        return self.state.seconds

    @property
    def params(self) -> dict:
        return self.state.params

    @property
    def context_started(self) -> int:
        return 0 if self.context is None else self.context.started

    # ------------------------------------------------------------ the parts
    def view_data(self, i: int) -> ViewData:
        """Training view ``i`` with its G-buffer, background and focus mask."""
        return self.views.get(i)

    def release_views(self) -> None:
        self.views.release()

    def render(self, camera, params=None, *, background=None, **settings) -> RasterResult:
        """The run's surfels (``params``, default its own) and context for ``camera``."""
        return render(self.state, self.context, camera, params, background=background,
                      backend=self.cfg.backend, **settings)

    def step(self) -> dict:
        return take_step(self.state, self.views, self.context, self.prior, self.env,
                         self.losses, backend=self.cfg.backend)

    def world_init(self) -> bool:
        """The colour start (colour_start/start.py); returns whether it ran."""
        return colour_start(self.state, self.views, self.context, self.prior,
                            self.conditioning, self.fit_views)

    def field(self) -> SurfelField:
        return self.state.field()

    def checkpoint(self, optimizer: bool = True) -> tuple[dict, dict]:
        """(tensors, meta): everything a resume needs, as flat named tensors (safetensors) and
        plain JSON data."""
        tensors, meta = self.state.checkpoint(optimizer)
        if self.context is not None:
            tensors.update(self.context.checkpoint())
        meta["context_started"] = self.context_started
        return tensors, meta

    def restore(self, tensors: dict, meta: dict) -> None:
        self.state.restore(tensors, meta)
        if self.context is not None:
            self.context.restore(tensors, meta)

    @torch.no_grad()
    def evaluate(self, views: list[View], t_eval: float = 1.0) -> dict:
        """Held-out metrics (run/evaluate.py) of the run as it stands, and the fraction of
        surfels more than 0.2 m from their seed proxy face."""
        res = E.evaluate_views(self.render, views, self.prior, self.conditioning, t_eval=t_eval,
                               n_denoise=self.cfg.n_denoise, focus=self.focus)
        res.pop("psnr_per_view")
        res["off_surface_frac"] = self.off_surface_fraction()
        return res

    def off_surface_fraction(self, threshold: float = 0.2) -> float:
        V, F, _ = self.conditioning.proxy
        return E.off_surface_fraction(self.state.params["means"].detach().numpy(),
                                      self.state.face_index, V, F, threshold)
