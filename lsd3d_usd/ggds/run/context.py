"""Frozen context surfels of a run (a chunk region's neighbours within its band), rendered with
the trainable ones but never optimised; culled to what can reach each view."""
from __future__ import annotations

import numpy as np
import torch

from lsd3d_usd.conditioning.visibility import spheres_in_view
from lsd3d_usd.splats.field import SurfelField, quat_normals

# world radius beyond which a disk's alpha stays under the rasteriser's alpha_min
# (opacity <= 1: sqrt(2 ln 255) = 3.33 sigma): the frustum cull of a render
CONTEXT_SIGMAS = 3.5


class FrozenContext:
    """``surfels`` (converted to ``sh_degree``) as float32 tensors, SH in half precision;
    ``start`` (len,) bool: rows whose colours the colour start fits too."""

    def __init__(self, surfels: SurfelField, sh_degree: int, start: np.ndarray | None = None):
        c = surfels if surfels.sh_degree == sh_degree else surfels.with_sh_degree(sh_degree)
        self.tensors = {k: torch.from_numpy(np.ascontiguousarray(v, np.float32)) for k, v in
                        (("means", c.positions), ("quats", c.orientations),
                         ("scales", c.scales), ("opacities", c.opacities))}
        # Frozen colours in half precision (relative error 5e-4, under a display step): a
        # region's band holds ~1 M surfels; SH are over half their bytes (degree 1) and 4/5
        # at degree 3.
        self.tensors["sh"] = torch.from_numpy(c.sh.astype(np.float16))
        self.radii = CONTEXT_SIGMAS * c.scales.max(axis=1).astype(np.float64)
        self.fit_rows = np.zeros(0, np.int64)
        if start is not None:
            start = np.asarray(start, bool)
            if start.shape != (self.n,):
                raise ValueError(f"context_start has shape {start.shape}, the context holds "
                                 f"{self.n} surfels")
            self.fit_rows = np.flatnonzero(start)
        # classes of the rows the colour start fits (their group slopes)
        self.fit_classes = (surfels.semantic_ids[self.fit_rows]
                            if len(self.fit_rows) and surfels.semantic_ids is not None else None)
        self.started = 0    # rows whose colours the start fitted (or a checkpoint restored)

    @property
    def n(self) -> int:
        return int(self.tensors["means"].shape[0])

    def __getitem__(self, key: str) -> torch.Tensor:
        return self.tensors[key]

    def in_view(self, camera) -> torch.Tensor:
        """Indices of the rows that can reach ``camera``'s image."""
        return torch.from_numpy(np.flatnonzero(spheres_in_view(
            self.tensors["means"].numpy(), self.radii, camera)))

    def append_to(self, activated: dict, camera) -> dict:
        """``activated`` (the trainable rows, first: visible_index < n are theirs) with the
        rows that can reach ``camera`` appended: the same image as all of them, without
        per-surfel buffers and gradient rows for the rest (~1.5x a chunk's surfels)."""
        keep = self.in_view(camera)
        return {k: torch.cat([activated[k], self.tensors[k].index_select(0, keep)
                              .to(activated[k].dtype)]) for k in activated}

    def fit_inputs(self):
        """(positions, scales, normals) of the rows the colour start fits, or None."""
        if not len(self.fit_rows):
            return None
        rows = torch.from_numpy(self.fit_rows)
        return tuple(self.tensors[k].index_select(0, rows).numpy() for k in ("means", "scales")) \
            + (quat_normals(self.tensors["quats"].index_select(0, rows).numpy()),)

    def set_fitted_sh(self, rows: np.ndarray, sh: np.ndarray) -> None:
        """Colours of fit rows ``rows`` (indices into fit_rows) from the colour start."""
        idx = torch.from_numpy(self.fit_rows[rows])
        self.tensors["sh"][idx] = torch.from_numpy(sh).to(torch.float16)

    # ------------------------------------------------------------ checkpoint
    def checkpoint(self) -> dict:
        if not len(self.fit_rows):
            return {}
        return {"context.sh": self.tensors["sh"].index_select(
            0, torch.from_numpy(self.fit_rows)).contiguous()}

    def restore(self, tensors: dict, meta: dict) -> None:
        csh = tensors.get("context.sh")
        if csh is None or not len(self.fit_rows):
            return
        if csh.shape[0] != len(self.fit_rows):
            raise ValueError(f"checkpoint context.sh holds {csh.shape[0]} rows, the "
                             f"region's unfinished neighbours {len(self.fit_rows)}")
        self.tensors["sh"][torch.from_numpy(self.fit_rows)] = csh.to(torch.float16)
        self.started = int(meta.get("context_started", len(self.fit_rows)))
