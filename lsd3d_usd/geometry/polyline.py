"""Polylines and rings as float64 numpy arrays (N, 2) or (N, 3); distances, offsets and
areas use XY, interpolation carries every column.

- cleaning: `clean_polyline` (XY, repeats dropped), `arc_table` (repeats dropped, every
  column, with cumulative arc length)
- arc length: `point_at`, `heading_at`, `resample`, `resample_step`
- nearest point and distance: `nearest_point`, `distance_to_segments`, `distance_to_polyline`
- offset: `mitre_normals`, `offset_polyline` (one mitre rule, limited to MITRE_LIMIT)
- rings: `signed_area`, `orient_ccw`, `clean_ring`
"""
from __future__ import annotations

import numpy as np

MITRE_LIMIT = 4.0     # a mitre reaches at most this many offsets from its vertex
BRUTE_PAIRS = 200_000     # below this many point-segment pairs, try them all


# ------------------------------------------------------------------ cleaning
def clean_polyline(points: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """XY of a polyline without repeated points (a vertex within ``tol`` of the kept one
    before it is dropped)."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    if len(xy) < 2:
        return xy
    keep = np.ones(len(xy), bool)
    keep[1:] = np.linalg.norm(np.diff(xy, axis=0), axis=1) > tol
    return xy[keep]


def _segments(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kept points, their segments' vectors, lengths): a segment of at most ``tol`` is
    dropped with its end point (the next segment then starts at the point before it)."""
    pts = np.asarray(points, dtype=np.float64)
    seg = np.diff(pts, axis=0)
    length = np.linalg.norm(seg, axis=1)
    keep = length > tol
    return pts[np.concatenate([[True], keep])], seg[keep], length[keep]


def arc_table(points: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """(points without zero-length segments, cumulative arc length at each), over every
    column: the table `point_at` and lane geometry interpolate in."""
    pts, _, length = _segments(points, tol)
    return pts, np.concatenate([[0.0], np.cumsum(length)])


# ------------------------------------------------------------------ arc length
def point_at(points: np.ndarray, s) -> np.ndarray:
    """Points at arc lengths ``s`` (clamped to the polyline), every column interpolated."""
    pts, seg, length = _segments(points, 1e-9)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, cum[-1])
    if not len(seg):         # no length: every s is the one point
        return np.broadcast_to(pts[0], s.shape + pts.shape[1:]).copy()
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    f = ((s - cum[k]) / length[k])[..., None]
    return pts[k] + f * seg[k]


def heading_at(points: np.ndarray, s, half: float = 1.0) -> np.ndarray:
    """Yaw (radians) of the chord over s ± ``half`` (clamped to the ends): smooth through
    vertices, where the tangent jumps."""
    s = np.asarray(s, dtype=np.float64)
    length = arc_table(points)[1][-1]
    d = point_at(points, np.minimum(s + half, length)) - point_at(points, np.maximum(s - half, 0.0))
    return np.arctan2(d[..., 1], d[..., 0])


def resample(points: np.ndarray, t) -> np.ndarray:
    """Points at fractions ``t`` in [0, 1] of the XY arc length, every column interpolated;
    a polyline without length gives its first point."""
    pts = np.asarray(points, dtype=np.float64)
    seg = np.hypot(*np.diff(pts[:, :2], axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s = s / s[-1] if s[-1] > 0 else s
    return np.column_stack([np.interp(t, s, pts[:, k]) for k in range(pts.shape[1])])


def resample_step(points: np.ndarray, step: float) -> np.ndarray:
    """Evenly spaced points at most ``step`` apart along the XY arc length, both ends kept."""
    pts = np.asarray(points, dtype=np.float64)
    length = float(np.hypot(*np.diff(pts[:, :2], axis=0).T).sum())
    return resample(pts, np.linspace(0.0, 1.0, max(2, int(np.ceil(length / step)) + 1)))


# --------------------------------------------------------- nearest point, distance
def nearest_point(points: np.ndarray, q) -> tuple[float, float, np.ndarray, np.ndarray]:
    """(distance from q, arc length at the nearest point, that point, unit direction of its
    segment) on a polyline, in XY; the first nearest segment wins a tie."""
    a, b = points[:-1, :2], points[1:, :2]
    d = b - a
    sq = np.einsum("ij,ij->i", d, d)
    L2 = np.maximum(sq, 1e-18)              # a zero-length segment: t = 0, direction 0
    t = np.clip(np.einsum("ij,ij->i", q - a, d) / L2, 0.0, 1.0)
    c = a + t[:, None] * d
    dist = np.hypot(*(c - q).T)
    k = int(np.argmin(dist))
    seg = np.sqrt(sq)                        # unfloored: zero-length segments add no length
    s = float(seg[:k].sum() + t[k] * seg[k])
    return float(dist[k]), s, c[k], d[k] / np.sqrt(L2[k])


def distance_to_segments_brute(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of each point q (M, 2) to the nearest of the segments a[k]→b[k] (K, 2), every
    pair tried (O(M·K))."""
    ab = b - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    out = np.full(len(q), np.inf)
    block = max(1, 2_000_000 // max(len(a), 1))          # bound the M×K temporaries
    for r0 in range(0, len(q), block):
        qq = q[r0:r0 + block]
        aq = qq[:, None, :] - a[None, :, :]
        t = np.einsum("mkj,kj->mk", aq, ab) / np.where(L2 > 0, L2, 1.0)[None, :]
        t = np.clip(t, 0.0, 1.0)
        d = aq - t[:, :, None] * ab[None, :, :]
        out[r0:r0 + block] = np.sqrt(np.einsum("mkj,mkj->mk", d, d).min(axis=1))
    return out


def distance_to_segments(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of each point q (M, 2) to the nearest of the segments a[k]→b[k] (K, 2): the
    same as ``distance_to_segments_brute``, in O((M + K) log K) for polylines of evenly sized
    segments. The nearest endpoint bounds the answer (d0); a segment within d0 of q has its
    midpoint within d0 + its half-length, so only those midpoints are tried."""
    q = np.asarray(q, np.float64)
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if len(q) * len(a) <= BRUTE_PAIRS or len(a) == 0:
        return distance_to_segments_brute(q, a, b)
    from scipy.spatial import cKDTree    # local import: scipy.spatial is slow to import
    ends = np.vstack([a, b])
    d0, _ = cKDTree(ends).query(q)
    mid = 0.5 * (a + b)
    half = 0.5 * np.hypot(*(b - a).T)
    cand = cKDTree(mid).query_ball_point(q, d0 + half.max() + 1e-9, return_sorted=False)
    counts = np.fromiter((len(c) for c in cand), np.int64, len(q))
    seg = np.fromiter((k for c in cand for k in c), np.int64, int(counts.sum()))
    row = np.repeat(np.arange(len(q)), counts)
    ab = b[seg] - a[seg]
    L2 = np.einsum("ij,ij->i", ab, ab)
    aq = q[row] - a[seg]
    t = np.clip(np.einsum("ij,ij->i", aq, ab) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    d = aq - t[:, None] * ab
    dist = np.sqrt(np.einsum("ij,ij->i", d, d))
    out = d0.copy()                      # every point has at least the segments of its endpoint
    np.minimum.at(out, row, dist)
    return out


def distance_to_polyline(q: np.ndarray, line: np.ndarray) -> np.ndarray:
    """XY distance of each point q (M, ≥2) to a polyline (a single point is a polyline)."""
    q, line = np.asarray(q, np.float64), np.asarray(line, np.float64)
    if len(line) == 1:
        return np.hypot(*(q[:, :2] - line[0, :2]).T)
    return distance_to_segments(q[:, :2], line[:-1, :2], line[1:, :2])


# ------------------------------------------------------------------ offset
def mitre_normals(xy: np.ndarray, limit: float = MITRE_LIMIT) -> tuple[np.ndarray, np.ndarray]:
    """Left unit normals per vertex (the mitre direction) and the mitre scale
    1 / cos(half the turn), at most ``limit`` (a hairpin is cut off, not a spike).
    ``xy`` must have no repeated points (`clean_polyline`)."""
    d = np.diff(xy, axis=0)
    seg_len = np.linalg.norm(d, axis=1, keepdims=True)
    seg_n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(seg_len, 1e-12)
    vn = np.empty_like(xy)
    vn[0], vn[-1] = seg_n[0], seg_n[-1]
    vn[1:-1] = seg_n[:-1] + seg_n[1:]
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    # a 180-degree reversal has no mitre; fall back to the incoming segment's normal
    bad = ln[:, 0] < 1e-9
    if bad.any():
        vn[bad] = np.concatenate([seg_n[:1], seg_n])[bad]
        ln[bad] = 1.0
    vn = vn / ln
    cos_half = np.ones(len(xy))
    cos_half[1:-1] = np.einsum("ij,ij->i", vn[1:-1], seg_n[:-1])
    scale = 1.0 / np.clip(cos_half, 1.0 / limit, 1.0)
    return vn, scale


def offset_polyline(points: np.ndarray, dist: float) -> np.ndarray:
    """XY of a polyline offset ``dist`` to the left (negative: right), mitred at vertices
    (`mitre_normals`); repeated points are dropped first."""
    xy = clean_polyline(points)
    if len(xy) < 2:
        return xy
    vn, sc = mitre_normals(xy)
    return xy + vn * (dist * sc)[:, None]


# ------------------------------------------------------------------ rings
def signed_area(polygon: np.ndarray) -> float:
    """Signed area of an implicitly closed polygon's XY projection (> 0 if CCW)."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def orient_ccw(polygon: np.ndarray) -> np.ndarray:
    """The ring counter-clockwise (reversed if its signed area is not positive)."""
    return polygon if signed_area(polygon) > 0 else polygon[::-1].copy()


def clean_ring(poly: np.ndarray, tol: float = 1e-9, min_area: float = 1e-6) -> np.ndarray | None:
    """A ring without repeated points (XY within ``tol``) or closing point, counter-clockwise;
    None when fewer than 3 vertices or less than ``min_area`` m² are left."""
    poly = np.asarray(poly)
    keep = np.ones(len(poly), bool)
    keep[1:] = np.hypot(*np.diff(poly[:, :2], axis=0).T) > tol
    poly = poly[keep]
    if len(poly) > 3 and np.allclose(poly[0, :2], poly[-1, :2]):
        poly = poly[:-1]
    if len(poly) < 3 or abs(signed_area(poly)) < min_area:
        return None
    return orient_ccw(poly)
