"""Seams of chunk-wise generation: is a scene as good at its chunk borders as inside chunks?

Pixels are split by where their proxy surface lies: the border band (horizontal distance
at most ``band_m`` from a grid line that separates two chunks holding surfels) against the
interiors. Per class of pixels: PSNR of the render against the prior's target (t = 1, as
GGDS's held-out evaluation), coverage (proxy pixels the surfels cover, alpha > 0.5), and the
render's agreement with the proxy (median relative depth error, median normal angle), so a
seam shows as a PSNR drop, a coverage gap or a geometry jump at the borders. Arrays in,
numbers out; the caller renders.

Border bands and interiors hold different things (a band may be mostly facades where the
interiors are mostly road), and the classes differ in how well GGDS fits them by several dB.
So the drop is also given class-matched: the interiors' error per semantic class, weighted by
the border band's class mix (classes absent from the interiors left out), against the border
band's own error. That compares like with like; a seam shows in both.
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
        self.covered = {"border": 0, "interior": 0}
        self.depth = {"border": [], "interior": []}
        self.angle = {"border": [], "interior": []}
        self.by_class = {"border": {}, "interior": {}}   # class id -> [squared error, pixels]

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
        sem = np.asarray(gbuf.semantic)
        for k, m in parts.items():
            classes, inv = np.unique(sem[m], return_inverse=True)
            sq_c = np.bincount(inv, weights=err[m], minlength=len(classes))
            n_c = np.bincount(inv, minlength=len(classes))
            for c, e, n_px in zip(classes.tolist(), sq_c.tolist(), n_c.tolist()):
                acc = self.by_class[k].setdefault(int(c), [0.0, 0])
                acc[0] += e
                acc[1] += n_px
            self.covered[k] += int((m & ok).sum())
            g = m & ok & (depth > 0)
            if g.any():
                self.depth[k].append(np.abs(depth[g] - gbuf.depth[g]) / gbuf.depth[g])
                self.angle[k].append(np.degrees(np.arccos(np.clip(cos[g], 0.0, 1.0))))

    def _total(self, k: str) -> tuple[float, int]:
        """(squared error, pixels) of part ``k`` over all classes."""
        acc = self.by_class[k].values()
        return sum(e for e, _ in acc), sum(n for _, n in acc)

    def result(self) -> dict:
        totals = {k: self._total(k) for k in ("border", "interior")}

        def psnr(k):
            return _psnr(*totals[k])

        def med(vals):
            return round(float(np.median(np.concatenate(vals))), 5) if vals else None
        out = {"band_m": self.band, "pixels": {k: n for k, (_, n) in totals.items()}}
        for k in ("border", "interior"):
            out[k] = {"psnr_db": psnr(k),
                      "coverage": (round(self.covered[k] / totals[k][1], 5) if totals[k][1]
                                   else None),
                      "depth_rel_err": med(self.depth[k]), "normal_err_deg": med(self.angle[k])}
        b, i = out["border"]["psnr_db"], out["interior"]["psnr_db"]
        out["psnr_drop_db"] = round(i - b, 3) if b is not None and i is not None else None
        out["classes"] = self._class_table()
        out["psnr_drop_class_matched_db"] = self._class_matched_drop()
        out["border_coverage"] = out["border"]["coverage"]
        return out

    def _class_table(self) -> dict:
        """Per semantic class name: pixels and PSNR in the border band and the interiors."""
        from lsd3d_usd.semantics import CLASSES
        table = {}
        for c in sorted(set(self.by_class["border"]) | set(self.by_class["interior"])):
            name = CLASSES[c] if 0 <= c < len(CLASSES) else "unlabelled"
            row = {}
            for k in ("border", "interior"):
                e, n = self.by_class[k].get(c, (0.0, 0))
                row[k] = {"pixels": n, "psnr_db": _psnr(e, n)}
            table[name] = row
        return table

    def _class_matched_drop(self) -> float | None:
        """Interior PSNR at the border band's class mix minus the border band's PSNR, over
        the classes both hold."""
        b, i = self.by_class["border"], self.by_class["interior"]
        common = [c for c in b if c in i and i[c][1] > 0]
        nb = sum(b[c][1] for c in common)
        if not nb:
            return None
        mse_b = sum(b[c][0] for c in common) / nb
        mse_i = sum(b[c][1] / nb * i[c][0] / i[c][1] for c in common)
        return round(_psnr(mse_i, 1) - _psnr(mse_b, 1), 3)


def _psnr(sq: float, n: int) -> float | None:
    if not n:
        return None
    mse = sq / n
    return round(99.0 if mse <= 1e-10 else -10.0 * math.log10(mse), 3)
