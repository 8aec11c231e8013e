"""Fit OpenDRIVE plan-view primitives (line, arc, paramPoly3) to a 2D polyline.

``fit_polyline(points, tol)`` cuts the polyline into spans, greedily as long as possible, and
fits each span with the simplest primitive such that every point of the curve lies within
``tol`` of the polyline and every polyline vertex within ``tol / 2`` of the curve. The
asymmetry is deliberate: our polylines are themselves chord approximations of curves (the
generator samples arcs with 1 cm chords), so the curve may stand off the polyline's chords by
that much while passing through its vertices; and a reader that samples the curve within
``tol / 2`` then reproduces every vertex within ``tol``. Span ends are polyline vertices, kept exactly, so consecutive primitives join
without a gap and a lane's first and last points stay where they were. Headings are the
primitives' own: continuous wherever the polyline is smooth within ``tol``, and a real corner
of the polyline stays a corner.

Arrays in, arrays out, float64 throughout.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from lsd3d_usd.geometry.polyline import distance_to_segments

DENSE_SPACING = 0.2      # m between curve samples in the two-way distance check
MAX_DENSE = 20000        # samples per check (a 4 km span at 0.2 m)
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)


@dataclass(frozen=True)
class Primitive:
    """One ``<geometry>`` record: start (x, y), heading, length and its shape.

    ``kind`` is "line", "arc" (``curvature``, signed, 1/m) or "paramPoly3" (``coeffs`` =
    aU, bU, cU, dU, aV, bV, cV, dV with pRange "normalized": p = ds / length).
    """
    kind: str
    x: float
    y: float
    hdg: float
    length: float
    curvature: float = 0.0
    coeffs: tuple = ()

    def eval(self, ds) -> np.ndarray:
        """Positions (N, 2) at distances ``ds`` from the start, as an OpenDRIVE reader maps them."""
        ds = np.asarray(ds, dtype=np.float64)
        c, s = np.cos(self.hdg), np.sin(self.hdg)
        if self.kind == "line":
            return np.stack([self.x + ds * c, self.y + ds * s], axis=1)
        if self.kind == "arc":
            k = self.curvature
            if abs(k) < 1e-15:
                return np.stack([self.x + ds * c, self.y + ds * s], axis=1)
            h = self.hdg + k * ds
            return np.stack([self.x + (np.sin(h) - s) / k, self.y - (np.cos(h) - c) / k], axis=1)
        aU, bU, cU, dU, aV, bV, cV, dV = self.coeffs
        p = ds / self.length
        u = aU + bU * p + cU * p**2 + dU * p**3
        v = aV + bV * p + cV * p**2 + dV * p**3
        return np.stack([self.x + c * u - s * v, self.y + s * u + c * v], axis=1)

    def end(self) -> np.ndarray:
        return self.eval(np.array([self.length]))[0]


# ================================================================== distances

def deviation(prim: Primitive, pts: np.ndarray) -> tuple[float, float]:
    """(max distance of the curve to the polyline ``pts``, max distance of its vertices to the
    curve); the curve is sampled every DENSE_SPACING m."""
    n = int(min(MAX_DENSE, max(32, 4 * len(pts), np.ceil(prim.length / DENSE_SPACING) + 1)))
    curve = prim.eval(np.linspace(0.0, prim.length, n))
    d1 = distance_to_segments(curve, pts[:-1], pts[1:]).max()
    d2 = distance_to_segments(pts, curve[:-1], curve[1:]).max()
    return float(d1), float(d2)


# ================================================================== primitives

def _line(pts: np.ndarray) -> Primitive:
    d = pts[-1] - pts[0]
    return Primitive("line", float(pts[0, 0]), float(pts[0, 1]), float(np.arctan2(d[1], d[0])),
                     float(np.hypot(*d)))


def _turn(pts: np.ndarray) -> float:
    """Total signed turning of the polyline (sum of heading changes)."""
    d = np.diff(pts, axis=0)
    h = np.arctan2(d[:, 1], d[:, 0])
    return float(np.sum((np.diff(h) + np.pi) % (2 * np.pi) - np.pi)) if len(h) > 1 else 0.0


def _arc_through(a: np.ndarray, b: np.ndarray, k: float, major: bool) -> Primitive:
    """The arc from a to b with signed curvature k (|k| L / 2 <= 1), minor or major."""
    d = b - a
    L = float(np.hypot(*d))
    theta = float(np.arctan2(d[1], d[0]))
    phi = float(np.arcsin(np.clip(k * L / 2, -1.0, 1.0)))       # half the minor sweep, signed
    half = (np.sign(k) * np.pi - phi) if major else phi
    if abs(k) < 1e-12:
        return Primitive("arc", float(a[0]), float(a[1]), theta, L, 0.0)
    return Primitive("arc", float(a[0]), float(a[1]), theta - half, float(abs(2 * half / k)), float(k))


def _arc(pts: np.ndarray, tol: float) -> Primitive | None:
    a, b = pts[0], pts[-1]
    L = float(np.hypot(*(b - a)))
    inner = pts[1:-1]
    if L < 1e-9 or len(inner) == 0:
        return None
    # signed curvature of the path a → q → b for each inner point q (a left turn bows right
    # of the chord, hence the minus)
    qa, qb = inner - a, inner - b
    cross = (b - a)[0] * qa[:, 1] - (b - a)[1] * qa[:, 0]
    den = L * np.hypot(qa[:, 0], qa[:, 1]) * np.hypot(qb[:, 0], qb[:, 1])
    ks = -2 * cross / np.where(den > 0, den, np.inf)
    kmax = 2.0 / L
    lo, hi = float(np.clip(ks.min(), -kmax, kmax)), float(np.clip(ks.max(), -kmax, kmax))
    major = abs(_turn(pts)) > np.pi

    def resid(k):
        if abs(k) < 1e-12:
            return float(np.abs(cross / L).max())
        prim = _arc_through(a, b, k, major)
        c = np.array([prim.x, prim.y]) + np.array([-np.sin(prim.hdg), np.cos(prim.hdg)]) / k
        return float(np.abs(np.hypot(*(inner - c).T) - 1 / abs(k)).max())

    k = float(np.median(np.clip(ks, -kmax, kmax)))
    if resid(k) > tol and hi > lo:
        r = minimize_scalar(resid, bounds=(lo, hi), method="bounded", options={"xatol": 1e-10})
        k = float(r.x)
    if resid(k) > tol:
        return None
    if abs(k) < 1e-12:
        return None   # a line does it
    return _arc_through(a, b, k, major)


def _poly3_point(cu, cv, t):
    u = cu[0] * t + cu[1] * t**2 + cu[2] * t**3
    v = cv[0] * t + cv[1] * t**2 + cv[2] * t**3
    return u, v


def _poly3_ls(U, V, L, t, iters: int = 8):
    """Least-squares cubic through (0, 0) and (L, 0) in the chord frame for points (U, V) at
    parameters t, alternating with a Newton step of each point's projection on the curve.
    Returns (cu, cv, max point error)."""
    for it in range(iters + 1):
        A = np.stack([t - t**3, t**2 - t**3], axis=1)
        (bU, cU), *_ = np.linalg.lstsq(A, U - L * t**3, rcond=None)
        (bV, cV), *_ = np.linalg.lstsq(A, V, rcond=None)
        cu, cv = (bU, cU, L - bU - cU), (bV, cV, -bV - cV)
        u, v = _poly3_point(cu, cv, t)
        eu, ev = u - U, v - V
        if it == iters:
            break
        du = cu[0] + 2 * cu[1] * t + 3 * cu[2] * t**2
        dv = cv[0] + 2 * cv[1] * t + 3 * cv[2] * t**2
        ddu, ddv = 2 * cu[1] + 6 * cu[2] * t, 2 * cv[1] + 6 * cv[2] * t
        den = du**2 + dv**2 + eu * ddu + ev * ddv
        step = np.where(np.abs(den) > 1e-12, (eu * du + ev * dv) / np.where(den != 0, den, 1), 0.0)
        t_new = np.clip(t - step, 0.0, 1.0)
        t_new[0], t_new[-1] = 0.0, 1.0
        t = np.maximum.accumulate(t_new)
    return cu, cv, float(np.hypot(eu, ev).max())


def _paramPoly3(pts: np.ndarray) -> Primitive | None:
    """Cubic u(p), v(p), p in [0, 1], in the frame of the chord, through both end points.
    Parameters start from chord length and from the vertex index (exact for polylines sampled
    uniformly in a cubic's parameter, like the generator's Hermite connectors); the better of
    the two fits is kept."""
    a, b = pts[0], pts[-1]
    d = b - a
    L = float(np.hypot(*d))
    if L < 1e-9 or len(pts) < 4:
        return None
    hdg = float(np.arctan2(d[1], d[0]))
    c, s = np.cos(hdg), np.sin(hdg)
    rel = pts - a
    U, V = rel @ np.array([c, s]), rel @ np.array([-s, c])
    seg = np.hypot(*np.diff(pts, axis=0).T)
    t_chord = np.concatenate([[0.0], np.cumsum(seg)]) / seg.sum()
    t_index = np.linspace(0.0, 1.0, len(pts))
    cu, cv, _ = min((_poly3_ls(U, V, L, t) for t in (t_chord, t_index)), key=lambda r: r[2])
    # arc length of the cubic (16-point Gauss-Legendre on 8 pieces)
    e = np.linspace(0.0, 1.0, 9)
    x = ((e[:-1, None] + e[1:, None]) / 2 + (e[1:, None] - e[:-1, None]) / 2 * _GL_X[None, :]).ravel()
    w = np.broadcast_to((np.diff(e)[:, None] / 2) * _GL_W[None, :], (8, 16)).ravel()
    du = cu[0] + 2 * cu[1] * x + 3 * cu[2] * x**2
    dv = cv[0] + 2 * cv[1] * x + 3 * cv[2] * x**2
    length = float(np.sum(w * np.hypot(du, dv)))
    if not (np.isfinite(length) and length > 0):
        return None
    coeffs = (0.0, float(cu[0]), float(cu[1]), float(cu[2]), 0.0, float(cv[0]), float(cv[1]), float(cv[2]))
    return Primitive("paramPoly3", float(a[0]), float(a[1]), hdg, length, 0.0, coeffs)


def fit_span(pts: np.ndarray, tol: float) -> Primitive | None:
    """The simplest primitive (line, arc, paramPoly3) fitting the span (see module doc), or None."""
    def ok(prim):
        d_curve, d_vertex = deviation(prim, pts)
        return d_curve <= tol and d_vertex <= tol / 2

    line = _line(pts)
    if line.length < 1e-9:
        return None
    if len(pts) == 2 or ok(line):
        return line
    arc = _arc(pts, tol / 2)
    if arc is not None and ok(arc):
        return arc
    poly = _paramPoly3(pts)
    if poly is not None and ok(poly):
        return poly
    return None


def dedupe(points: np.ndarray, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Points without consecutive duplicates (XY), and the indices kept."""
    p = np.asarray(points, dtype=np.float64)
    keep = np.ones(len(p), bool)
    keep[1:] = np.hypot(*np.diff(p[:, :2], axis=0).T) > eps
    return p[keep], np.flatnonzero(keep)


def fit_polyline(points, tol: float = 0.02) -> tuple[list[Primitive], list[int]]:
    """Primitives covering the polyline (curve within ``tol``, vertices within ``tol / 2``), and the vertex index where each starts
    (plus the last vertex index). ``points`` is (N, 2+) with no consecutive duplicates; a
    polyline of fewer than two distinct points has no primitives."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64)[:, :2])
    n = len(pts)
    if n < 2:
        return [], [0]
    if not (tol > 0):
        raise ValueError(f"fit tolerance must be > 0, got {tol}")
    prims, starts = [], [0]
    i = 0
    while i < n - 1:
        best_j, best = i + 1, fit_span(pts[i:i + 2], tol)
        if best is None:
            raise ValueError(f"zero-length segment at vertex {i}")
        # grow the span geometrically while it fits, then bisect between the last fit and the
        # first failure (a fit is not monotone in the span, so this finds a long one, not
        # always the longest)
        step, fail = 2, None
        while True:
            j = min(i + step, n - 1)
            if j <= best_j:
                break
            f = fit_span(pts[i:j + 1], tol)
            if f is None:
                fail = j
                break
            best_j, best = j, f
            if j == n - 1:
                break
            step *= 2
        if fail is not None:
            lo, hi = best_j, fail
            while hi - lo > 1:
                mid = (lo + hi) // 2
                f = fit_span(pts[i:mid + 1], tol)
                if f is None:
                    hi = mid
                else:
                    lo, best_j, best = mid, mid, f
        prims.append(best)
        starts.append(best_j)
        i = best_j
    return prims, starts
