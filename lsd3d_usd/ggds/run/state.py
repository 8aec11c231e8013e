"""The optimisation state of a run: the surfel parameters, selective Adam, the MCMC strategy,
the schedules, the random generator and the history, and how they checkpoint (flat named
tensors for safetensors plus plain JSON)."""
from __future__ import annotations

import numpy as np
import torch

from lsd3d_usd.configtree import to_dict
from lsd3d_usd.ggds.optim import params as P
from lsd3d_usd.ggds.optim.adam import SelectiveAdam, lr_at
from lsd3d_usd.ggds.optim.antialias import filter_sigma, smooth
from lsd3d_usd.ggds.optim.grounding import Grounding
from lsd3d_usd.ggds.optim.strategy import MCMCStrategy
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.splats.field import SurfelField, rgb_to_sh_dc


class RunState:
    """``field``: the initial surfels (read once: the state keeps its own tensors).
    ``cameras``: the training cameras (the 3D smoothing filter's sampling rates)."""

    def __init__(self, field: SurfelField, config: GGDSConfig, cameras, face_index=None):
        self.cfg = config
        # what the result keeps of the initial field; the rest lives in the parameters (the
        # ids are the run's own: a relocated surfel takes its source's class)
        ids = None if field.semantic_ids is None else np.array(field.semantic_ids, copy=True)
        self.semantics = (ids, field.semantic_classes)
        self.params = P.to_params(field)
        # flat classes held on their seed planes (optim/grounding.py), None when none is
        self.grounding = Grounding.of(self.params, ids, field.semantic_classes,
                                      config.ground_classes)
        for p in self.params.values():
            p.requires_grad_(True)
        k = self.params["sh"].shape[1]
        sh_scale = torch.full((k, 1), float(config.lr.sh_rest_factor))
        sh_scale[0] = 1.0
        rel = config.lr.sh_relative
        self.optimizer = SelectiveAdam(self.params, self.lrs(0), lr_scales={"sh": sh_scale},
                                       eps_by_key={"sh": config.lr.adam_eps_sh},
                                       relative={"sh": (rel, config.lr.sh_relative_min)}
                                       if rel > 0 else {})
        self.strategy = MCMCStrategy.of(config.strategy, config.seed)
        self.face_index = None if face_index is None else np.asarray(face_index, np.int64).copy()
        # Per-surfel σ of the 3D smoothing filter (optim/antialias.py), or None when off.
        self.filter3d = (torch.from_numpy(filter_sigma(field.positions, list(cameras),
                                                       config.filter_3d))
                         if config.filter_3d > 0 else None)
        self.rng = np.random.default_rng(config.seed)
        self.step_index = 0
        self.history: list[dict] = []
        self.seconds = 0.0

    @property
    def n(self) -> int:
        return int(self.params["means"].shape[0])

    # ------------------------------------------------------------ schedules
    def lrs(self, step: int) -> dict:
        c, lr = self.cfg, self.cfg.lr
        return {"means": lr_at(step, c.steps, lr.means, lr.means_end), "quats": lr.quats,
                "scales": lr.scales, "opacities": lr.opacities,
                "sh": lr.sh_dc if lr.sh_dc_end is None else lr_at(step, c.steps, lr.sh_dc,
                                                                  lr.sh_dc_end)}

    def t_min(self, step: int) -> float:
        c = self.cfg
        f = min(step / max(c.steps - 1, 1), 1.0)
        return c.t_min_start + (c.t_min_end - c.t_min_start) * f

    # ------------------------------------------------------------ the renderer's values
    def activated(self, params: dict | None = None) -> dict:
        """The renderer's values of ``params`` (default: the state's): constrained
        (params.activated) and, with the 3D smoothing filter on, each disk convolved with its
        frequency limit."""
        a = P.activated(self.params if params is None else params)
        if self.filter3d is not None:
            a["scales"], a["opacities"] = smooth(a["scales"], a["opacities"], self.filter3d)
        return a

    @torch.no_grad()
    def filter_coef(self) -> torch.Tensor | None:
        """(N,) fraction of each surfel's opacity the 3D filter keeps (None without it)."""
        if self.filter3d is None:
            return None
        s = self.params["scales"].exp()
        return smooth(s, torch.ones(len(s)), self.filter3d)[1]

    def field(self) -> SurfelField:
        """The surfels as the renderer sees them (the 3D filter baked in)."""
        ids, classes = self.semantics
        return P.to_field(self.params, None if ids is None else ids.copy(), classes,
                          activate=self.activated)

    def ground(self, rows: torch.Tensor) -> None:
        """Put the updated ``rows`` of grounded classes back on their planes."""
        if self.grounding is not None:
            self.grounding.project(self.params, rows)

    @torch.no_grad()
    def floor_colour(self, rows: torch.Tensor | None = None) -> None:
        """Hold the base colour (0.5 + C0 · SH DC) of ``rows`` (default all) at least
        ``cfg.colour_floor`` per channel. The renderer draws a colour below 0 as 0 and passes
        it no gradient, so a channel that one noisy step pushes there — in shadows, where
        the targets sit near 0 — stays black for the rest of the run."""
        floor = self.cfg.colour_floor
        if floor <= 0:
            return
        dc = self.params["sh"].data[:, 0]
        lo = float(rgb_to_sh_dc(floor))
        if rows is None:
            dc.clamp_(min=lo)
        elif rows.numel():
            dc[rows] = dc[rows].clamp(min=lo)

    def track_relocation(self) -> None:
        """A relocated surfel sits on its source's disk: it inherits the source's class, seed
        face and plane, and, seen by the same views, its frequency limit."""
        dead, src = self.strategy.last_relocation
        ids = self.semantics[0]
        if ids is not None:
            ids[dead.numpy()] = ids[src.numpy()]
        if self.grounding is not None:
            self.grounding.relocated(dead, src)
            self.grounding.project(self.params, dead)
        if self.face_index is not None:
            self.face_index[dead.numpy()] = self.face_index[src.numpy()]
        if self.filter3d is not None:
            self.filter3d[dead] = self.filter3d[src]

    # ------------------------------------------------------------ checkpoint
    def checkpoint(self, optimizer: bool = True) -> tuple[dict, dict]:
        """(tensors, meta): everything a resume needs of the state, as views of the run's own
        tensors (write them before the next step). Without ``optimizer`` the Adam moments are
        left out (a resume then restarts them at zero)."""
        tensors = {f"params.{k}": v.detach().contiguous() for k, v in self.params.items()}
        if optimizer:
            # the moments themselves, not state_dict()'s clones: written out at once
            opt = self.optimizer
            tensors.update({f"adam.m.{k}": v.contiguous() for k, v in opt.m.items()})
            tensors.update({f"adam.v.{k}": v.contiguous() for k, v in opt.v.items()})
            tensors["adam.t"] = opt.t.contiguous()
        tensors.update(self.strategy.state_tensors())
        if self.face_index is not None:
            tensors["face_index"] = torch.from_numpy(np.ascontiguousarray(self.face_index))
        if self.filter3d is not None:
            tensors["filter3d"] = self.filter3d.contiguous()
        if self.semantics[0] is not None:
            tensors["semantic_ids"] = torch.from_numpy(
                np.ascontiguousarray(self.semantics[0], dtype=np.int32))
        if self.grounding is not None:
            tensors.update(self.grounding.state_tensors())
        meta = {"step": self.step_index, "rng": self.rng.bit_generator.state,
                "history": list(self.history), "seconds": self.seconds,
                "config": to_dict(self.cfg), "optimizer": bool(optimizer)}
        return tensors, meta

    def restore(self, tensors: dict, meta: dict) -> None:
        """Inverse of :meth:`checkpoint`. Shapes must match the run's surfels."""
        with torch.no_grad():
            for k, p in self.params.items():
                v = tensors.get(f"params.{k}")
                if v is None or v.shape != p.shape:
                    got = "missing" if v is None else f"shape {tuple(v.shape)}"
                    raise ValueError(f"checkpoint params.{k} is {got}, the scene's surfels give "
                                     f"{tuple(p.shape)}")
                p.copy_(v)
        if meta.get("optimizer", True) and "adam.t" in tensors:
            self.optimizer.load_state_dict({
                "m": {k: tensors[f"adam.m.{k}"] for k in self.params},
                "v": {k: tensors[f"adam.v.{k}"] for k in self.params}, "t": tensors["adam.t"]})
        self.step_index = int(meta["step"])
        self.rng.bit_generator.state = meta["rng"]
        self.strategy.load_state_tensors(tensors)
        self.history = list(meta["history"])
        self.seconds = float(meta.get("seconds", 0.0))
        if "face_index" in tensors:
            self.face_index = tensors["face_index"].numpy().astype(np.int64).copy()
        if self.filter3d is not None and "filter3d" in tensors:
            self.filter3d = tensors["filter3d"].clone()
        if self.semantics[0] is not None and "semantic_ids" in tensors:
            ids = tensors["semantic_ids"].numpy()
            if ids.shape == self.semantics[0].shape:
                self.semantics[0][:] = ids
        if self.grounding is not None:
            self.grounding.load_state_tensors(tensors)
