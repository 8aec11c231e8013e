"""The sRGB transfer function (IEC 61966-2-1), for numpy arrays and torch tensors alike: the
one definition used for display images, network inputs and previews. Inputs are clamped to
[0, 1]; the power branch never sees values below its threshold, so its gradient stays finite."""
from __future__ import annotations

import numpy as np

ENCODE_BREAK = 0.0031308
DECODE_BREAK = 0.04045


def _ops(x):
    if hasattr(x, "detach"):
        # local import: torch only for tensors
        import torch
        return torch.where, (lambda a, lo, hi: a.clamp(lo, hi))
    return np.where, np.clip


def srgb_encode(x):
    """Linear [0, 1] -> sRGB-encoded [0, 1]."""
    where, clip = _ops(x)
    x = clip(x, 0.0, 1.0)
    return where(x <= ENCODE_BREAK, 12.92 * x,
                 1.055 * clip(x, ENCODE_BREAK, 1.0) ** (1.0 / 2.4) - 0.055)


def srgb_decode(x):
    """sRGB-encoded [0, 1] -> linear [0, 1]."""
    where, clip = _ops(x)
    x = clip(x, 0.0, 1.0)
    return where(x <= DECODE_BREAK, x / 12.92, ((clip(x, DECODE_BREAK, 1.0) + 0.055) / 1.055) ** 2.4)
