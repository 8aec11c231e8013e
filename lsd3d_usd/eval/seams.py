"""Seams of chunk-wise generation: is a scene as good at its chunk borders as inside chunks?

Pixels are split by where their proxy surface lies: the border band (horizontal distance
at most ``band_m`` from a grid line that separates two chunks holding surfels) against the
interiors. Per class of pixels: PSNR of the render against the prior's target (t = 1, as
GGDS's held-out evaluation), coverage (proxy pixels the surfels cover, alpha > 0.5), and the
render's agreement with the proxy (median relative depth error, median normal angle), so a
seam shows as a PSNR drop, a coverage gap or a geometry jump at the borders. Arrays in,
numbers out; the caller renders.
"""
from __future__ import annotations

import math

import numpy as np

BAND_M = 5.0
ALPHA_MIN = 0.5


def _code(i, j):
    return (np.asarray(i, np.int64) + (1 << 24)) * (1 << 25) + (np.asarray(j, np.int64) + (1 << 24))


def border_distance(points: np.ndarray, chunk_size: float, keys) -> np.ndarray:
    """Horizontal distance of points (..., 3) to the nearest chunk border that separates two
    of ``keys`` (chunks holding surfels); inf where no such border is near."""
    p = np.asarray(points, np.float64)
    codes = np.array(sorted(int(_code(a, b)) for a, b in keys), np.int64)
    i = np.floor(p[..., 0] / chunk_size).astype(np.int64)
    j = np.floor(p[..., 1] / chunk_size).astype(np.int64)
    out = np.full(p.shape[:-1], np.inf)
    for axis, (di, dj) in ((0, (1, 0)), (1, (0, 1))):
        for step in (0, 1):     # the cell's lower and upper grid line on this axis
            a = (i + di * step, j + dj * step)
            b = (i + di * (step - 1), j + dj * (step - 1))
            sep = np.isin(_code(*a), codes) & np.isin(_code(*b), codes)
            line = ((i if axis == 0 else j) + step) * chunk_size
            d = np.abs(p[..., axis] - line)
            out = np.where(sep & (d < out), d, out)
    return out


class SeamStats:
    """Accumulates per-pixel errors of views split into border band and interior."""

    def __init__(self, chunk_size: float, keys, band_m: float = BAND_M):
        self.size, self.keys, self.band = float(chunk_size), set(map(tuple, keys)), band_m
        self.sq = {"border": 0.0, "interior": 0.0}
        self.n = {"border": 0, "interior": 0}
        self.proxy = {"border": 0, "interior": 0}
        self.covered = {"border": 0, "interior": 0}
        self.depth = {"border": [], "interior": []}
        self.angle = {"border": [], "interior": []}

    def add(self, rgb, target, alpha, depth, normal, gbuf) -> None:
        """One view: render rgb (H,W,3) display range, prior target (H,W,3), alpha (H,W),
        surfel depth (H,W), world normals (H,W,3); gbuf: render.gbuffer.GBuffer (proxy)."""
        valid = gbuf.mask & np.isfinite(gbuf.depth)
        d = border_distance(np.where(valid[..., None], gbuf.position, 0.0), self.size, self.keys)
        parts = {"border": valid & (d <= self.band), "interior": valid & (d > self.band)}
        err = ((np.clip(rgb, 0, 1) - np.clip(target, 0, 1)) ** 2).mean(axis=-1)
        ok = alpha > ALPHA_MIN
        n = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        cos = np.abs((n * gbuf.normal).sum(-1))
        for k, m in parts.items():
            self.sq[k] += float(err[m].sum())
            self.n[k] += int(m.sum())
            self.proxy[k] += int(m.sum())
            self.covered[k] += int((m & ok).sum())
            g = m & ok & (depth > 0)
            if g.any():
                self.depth[k].append(np.abs(depth[g] - gbuf.depth[g]) / gbuf.depth[g])
                self.angle[k].append(np.degrees(np.arccos(np.clip(cos[g], 0.0, 1.0))))

    def result(self) -> dict:
        def psnr(k):
            if not self.n[k]:
                return None
            mse = self.sq[k] / self.n[k]
            return round(99.0 if mse <= 1e-10 else -10.0 * math.log10(mse), 3)

        def med(vals):
            return round(float(np.median(np.concatenate(vals))), 5) if vals else None
        out = {"band_m": self.band, "pixels": dict(self.n)}
        for k in ("border", "interior"):
            out[k] = {"psnr_db": psnr(k),
                      "coverage": round(self.covered[k] / self.proxy[k], 5) if self.proxy[k] else None,
                      "depth_rel_err": med(self.depth[k]), "normal_err_deg": med(self.angle[k])}
        b, i = out["border"]["psnr_db"], out["interior"]["psnr_db"]
        out["psnr_drop_db"] = round(i - b, 3) if b is not None and i is not None else None
        out["border_coverage"] = out["border"]["coverage"]
        return out
