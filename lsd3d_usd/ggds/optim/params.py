"""SurfelField ↔ the raw, unconstrained tensors GGDS optimises (as 3DGS/gsplat do):
means (metres), quats (unnormalised xyzw), log-scales, logit-opacities, SH."""
from __future__ import annotations

import numpy as np
import torch

from lsd3d_usd.splats.field import SurfelField

KEYS = ("means", "quats", "scales", "opacities", "sh")
_EPS = 1e-6


def to_params(field: SurfelField) -> dict[str, torch.Tensor]:
    op = np.clip(field.opacities.astype(np.float64), _EPS, 1 - _EPS)
    return {
        "means": torch.tensor(field.positions, dtype=torch.float32),
        "quats": torch.tensor(field.orientations, dtype=torch.float32),
        "scales": torch.tensor(np.log(np.maximum(field.scales, 1e-8)), dtype=torch.float32),
        "opacities": torch.tensor(np.log(op / (1 - op)), dtype=torch.float32),
        "sh": torch.tensor(field.sh, dtype=torch.float32),
    }


def activated(params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Constrained values the renderer takes (differentiable)."""
    q = params["quats"]
    return {"means": params["means"], "quats": q / q.norm(dim=1, keepdim=True).clamp_min(1e-12),
            "scales": params["scales"].exp(), "opacities": torch.sigmoid(params["opacities"]),
            "sh": params["sh"]}


def to_field(params: dict[str, torch.Tensor], semantic_ids=None, semantic_classes=(),
             activate=activated) -> SurfelField:
    """Back to a SurfelField with the given semantic ids and class table; ``activate`` maps
    the raw tensors to the renderer's values (default: activated)."""
    with torch.no_grad():
        a = activate(params)
        op = a["opacities"].numpy().astype(np.float32)
        return SurfelField(a["means"].numpy().copy(), a["quats"].numpy().copy(),
                           np.maximum(a["scales"].numpy(), 1e-12), np.clip(op, 0.0, 1.0),
                           a["sh"].numpy().copy(), semantic_ids, semantic_classes)
