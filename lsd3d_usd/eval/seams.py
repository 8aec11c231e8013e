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
band's own error. Distance confounds it as much: along a corridor the borders ahead are seen
from far away (median 30-200 m) where the interiors around the camera are near (8-17 m), and
error grows with distance. ``psnr_drop_matched_db`` matches both, per (class, depth bin).
A seam shows in all three. A few close-up views of a border can carry most of its band's
pixels, so the matched drop comes with a 95 % bootstrap interval over the views.

A grid line separates two chunks only where both hold surfels along it: with chunk bounds
given, a chunk holding a few hundred surfels of a building that overhangs the layout's edge
makes a border only beside that building, not along the whole edge of the scene.
"""
from __future__ import annotations

import math

import numpy as np

from lsd3d_usd.semantics import CLASSES

BAND_M = 5.0
ALPHA_MIN = 0.5
DEPTH_BINS_M = (10.0, 20.0, 40.0, 80.0)   # upper edges; the last bin is open
BOOTSTRAP = 1000


def _code(i, j):
    return (np.asarray(i, np.int64) + (1 << 24)) * (1 << 25) + (np.asarray(j, np.int64) + (1 << 24))


def border_distance(points: np.ndarray, chunk_size: float, keys, bounds=None,
                    reach: float = BAND_M) -> np.ndarray:
    """Horizontal distance of points (..., 3) to the nearest chunk border that separates two
    of ``keys`` (chunks holding surfels); inf where no such border is near. ``bounds``
    (key -> (xmin, ymin, xmax, ymax) of the chunk's surfels), where given, limits a border to
    where both chunks' surfels extend along it, to within ``reach``."""
    p = np.asarray(points, np.float64)
    if not keys:
        return np.full(p.shape[:-1], np.inf)
    keys = sorted(map(tuple, keys), key=lambda k: int(_code(*k)))
    codes = np.array([int(_code(*k)) for k in keys], np.int64)
    box = np.array([[-np.inf, -np.inf, np.inf, np.inf] if bounds is None or k not in bounds
                    else [bounds[k][0] - reach, bounds[k][1] - reach,
                          bounds[k][2] + reach, bounds[k][3] + reach] for k in keys],
                   np.float64).reshape(-1, 4)
    i = np.floor(p[..., 0] / chunk_size).astype(np.int64)
    j = np.floor(p[..., 1] / chunk_size).astype(np.int64)
    out = np.full(p.shape[:-1], np.inf)
    for axis, (di, dj) in ((0, (1, 0)), (1, (0, 1))):
        along = p[..., 1 - axis]             # the coordinate along this axis's grid lines
        for step in (0, 1):     # the cell's lower and upper grid line on this axis
            sep = np.ones(p.shape[:-1], bool)
            for cell in ((i + di * step, j + dj * step), (i + di * (step - 1), j + dj * (step - 1))):
                c = _code(*cell)
                k = np.clip(np.searchsorted(codes, c), 0, len(codes) - 1)
                b = box[k]
                sep &= (codes[k] == c) & (along >= b[..., 1 - axis]) & (along <= b[..., 3 - axis])
            line = ((i if axis == 0 else j) + step) * chunk_size
            d = np.abs(p[..., axis] - line)
            out = np.where(sep & (d < out), d, out)
    return out


class SeamStats:
    """Accumulates per-pixel errors of views split into border band and interior."""

    def __init__(self, chunk_size: float, keys, band_m: float = BAND_M, bounds=None):
        self.size, self.keys, self.band = float(chunk_size), set(map(tuple, keys)), band_m
        self.bounds = bounds
        self.per_view = []          # per view and part: {(class, depth bin): [sq err, pixels]}
        self.covered = {"border": 0, "interior": 0}
        self.depth = {"border": [], "interior": []}
        self.angle = {"border": [], "interior": []}
        self.by_class = {"border": {}, "interior": {}}   # class id -> [squared error, pixels]

    def add(self, rgb, target, alpha, depth, normal, gbuf) -> None:
        """One view: render rgb (H,W,3) display range, prior target (H,W,3), alpha (H,W),
        surfel depth (H,W), world normals (H,W,3); gbuf: render.gbuffer.GBuffer (proxy)."""
        valid = gbuf.mask & np.isfinite(gbuf.depth)
        d = border_distance(np.where(valid[..., None], gbuf.position, 0.0), self.size, self.keys,
                            self.bounds, self.band)
        parts = {"border": valid & (d <= self.band), "interior": valid & (d > self.band)}
        err = ((np.clip(rgb, 0, 1) - np.clip(target, 0, 1)) ** 2).mean(axis=-1)
        ok = alpha > ALPHA_MIN
        n = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        cos = np.abs((n * gbuf.normal).sum(-1))
        sem = np.asarray(gbuf.semantic).astype(np.int64)
        cell = sem * (len(DEPTH_BINS_M) + 1) + np.searchsorted(DEPTH_BINS_M, gbuf.depth)
        view = {}
        for k, m in parts.items():
            _accumulate(self.by_class[k], sem[m], err[m])
            view[k] = _accumulate({}, cell[m], err[m])
            self.covered[k] += int((m & ok).sum())
            g = m & ok & (depth > 0)
            if g.any():
                self.depth[k].append(np.abs(depth[g] - gbuf.depth[g]) / gbuf.depth[g])
                self.angle[k].append(np.degrees(np.arccos(np.clip(cos[g], 0.0, 1.0))))
        self.per_view.append(view)

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
        out["psnr_drop_class_matched_db"] = _matched_drop(self.by_class)[0]
        drop, ci, frac = self._matched()
        out["psnr_drop_matched_db"], out["matched_border_frac"] = drop, frac
        out["psnr_drop_matched_ci95_db"] = ci
        out["border_coverage"] = out["border"]["coverage"]
        return out

    def view_cells(self, cells=None) -> tuple[list, np.ndarray]:
        """(the (class, depth bin) cells, (views, part, (squared error, pixels), cell) sums;
        part 0 the border band, 1 the interiors). ``cells`` fixes the columns (absent: 0)."""
        if cells is None:
            cells = sorted({c for v in self.per_view for k in v for c in v[k]})
        col = {c: i for i, c in enumerate(cells)}
        arr = np.zeros((len(self.per_view), 2, 2, len(cells)))
        for v, view in enumerate(self.per_view):
            for p, k in enumerate(("border", "interior")):
                for c, (e, n_px) in view[k].items():
                    if c in col:
                        arr[v, p, :, col[c]] = e, n_px
        return cells, arr

    def _matched(self, seed: int = 0) -> tuple:
        """(matched drop, its 95 % interval over views resampled with replacement, the
        fraction of border pixels whose (class, depth bin) the interiors hold)."""
        cells, arr = self.view_cells()
        if not cells:
            return None, None, None
        total = arr.sum(0)
        if not total[0, 1].sum():
            return None, None, None
        drop = _drop_db(total[None])[0]
        both = (total[0, 1] > 0) & (total[1, 1] > 0)
        frac = round(float(total[0, 1][both].sum() / total[0, 1].sum()), 4)
        if not np.isfinite(drop):
            return None, None, frac
        ci = _bootstrap_ci([arr], _drop_db, seed)
        return round(float(drop), 3), ci, frac

    def _class_table(self) -> dict:
        """Per semantic class name: pixels and PSNR in the border band and the interiors."""
        table = {}
        for c in sorted(set(self.by_class["border"]) | set(self.by_class["interior"])):
            name = CLASSES[c] if 0 <= c < len(CLASSES) else "unlabelled"
            row = {}
            for k in ("border", "interior"):
                e, n = self.by_class[k].get(c, (0.0, 0))
                row[k] = {"pixels": n, "psnr_db": _psnr(e, n)}
            table[name] = row
        return table


def paired_matched_drop(scene: SeamStats, reference: SeamStats, seed: int = 0) -> dict:
    """The seam a scene's chunking adds: its matched drop minus that of a reference scene of
    the same layout without chunk seams (e.g. the same scene optimised as one region), from
    the same cameras. Where a border band holds content that is harder to fit than the
    interiors (a corridor's borders fall between its junctions), both scenes show it; the
    difference leaves what the chunk-wise optimisation adds. The 95 % interval resamples the
    views, the same ones in both (ValueError when the two saw different numbers of views)."""
    if len(scene.per_view) != len(reference.per_view):
        raise ValueError(f"paired seam drop: {len(scene.per_view)} views against "
                         f"{len(reference.per_view)}; the two need the same cameras")
    cells = sorted({c for st in (scene, reference) for v in st.per_view for k in v for c in v[k]})
    _, a = scene.view_cells(cells)
    _, b = reference.view_cells(cells)

    def diff(x, y):
        return _drop_db(x) - _drop_db(y)
    da, db = (float(_drop_db(x.sum(0)[None])[0]) for x in (a, b))
    d = da - db

    def rounded(v):
        return round(v, 3) if np.isfinite(v) else None
    out = {"scene_db": rounded(da), "reference_db": rounded(db), "difference_db": rounded(d),
           "ci95_db": None, "views": len(scene.per_view)}
    if np.isfinite(d):
        out["ci95_db"] = _bootstrap_ci([a, b], diff, seed)
    return out


def _bootstrap_ci(arrays, stat, seed: int) -> list | None:
    """95 % interval of ``stat`` over the views (axis 0 of every array, resampled together)."""
    n = len(arrays[0])
    if n < 2:
        return None
    idx = np.random.default_rng(seed).integers(0, n, (BOOTSTRAP, n))
    d = stat(*[a[idx].sum(1) for a in arrays])
    d = d[np.isfinite(d)]
    if not len(d):
        return None
    lo, hi = np.percentile(d, [2.5, 97.5])
    return [round(float(lo), 3), round(float(hi), 3)]


def _accumulate(acc: dict, labels: np.ndarray, err: np.ndarray) -> dict:
    """Add squared errors and pixel counts per label; returns ``acc``."""
    values, inv = np.unique(labels, return_inverse=True)
    sq = np.bincount(inv, weights=err, minlength=len(values))
    n = np.bincount(inv, minlength=len(values))
    for c, e, n_px in zip(values.tolist(), sq.tolist(), n.tolist()):
        a = acc.setdefault(int(c), [0.0, 0])
        a[0] += e
        a[1] += n_px
    return acc


def _drop_db(tot: np.ndarray) -> np.ndarray:
    """Matched drops of (B, part, (sq, n), cells) sums: the interiors' error per cell at the
    border band's mix of cells against the band's, over the cells both hold (nan: none)."""
    sb, nb, si, ni = tot[:, 0, 0], tot[:, 0, 1], tot[:, 1, 0], tot[:, 1, 1]
    both = (nb > 0) & (ni > 0)
    n = np.where(both, nb, 0).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        mse_b = np.where(both, sb, 0).sum(1) / n
        mse_i = np.where(both, nb * si / np.where(ni > 0, ni, 1), 0).sum(1) / n
        return 10 * np.log10(np.maximum(mse_b, 1e-10) / np.maximum(mse_i, 1e-10))


def _matched_drop(acc: dict) -> tuple[float | None, float | None]:
    """(Interior PSNR at the border band's mix of labels minus the border band's PSNR, the
    fraction of border pixels whose label the interiors hold): over the labels both hold."""
    b, i = acc["border"], acc["interior"]
    common = [c for c in b if c in i and i[c][1] > 0]
    nb = sum(b[c][1] for c in common)
    if not nb:
        return None, None
    mse_b = sum(b[c][0] for c in common) / nb
    mse_i = sum(b[c][1] / nb * i[c][0] / i[c][1] for c in common)
    return (round(_psnr(mse_i, 1) - _psnr(mse_b, 1), 3),
            round(nb / sum(n for _, n in b.values()), 4))


def _psnr(sq: float, n: int) -> float | None:
    if not n:
        return None
    mse = sq / n
    return round(99.0 if mse <= 1e-10 else -10.0 * math.log10(mse), 3)
