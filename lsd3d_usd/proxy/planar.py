"""2D geometry over shapely: ribbons along polylines, dashes, triangulation, prisms.

Everything here takes plain numpy polylines / shapely polygons, so it does not
depend on the layout model.
"""
from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import LineString, MultiPolygon, Polygon, box
from shapely.geometry.base import BaseGeometry

from lsd3d_usd.geometry.polyline import MITRE_LIMIT, clean_polyline, mitre_normals, offset_polyline

from .mesh import MIN_FACE_AREA

EMPTY = Polygon()


def polygons_of(geom: BaseGeometry | None) -> list[Polygon]:
    """The non-empty polygons inside any geometry (collections flattened)."""
    if geom is None or geom.is_empty:
        return []
    if isinstance(geom, Polygon):
        return [geom] if geom.area > 0 else []
    if isinstance(geom, MultiPolygon):      # one vectorised step for its many parts
        parts = shapely.get_parts(geom)
        return list(parts[shapely.area(parts) > 0])
    if hasattr(geom, "geoms"):
        out = []
        for g in geom.geoms:
            out.extend(polygons_of(g))
        return out
    return []


def as_area(geom: BaseGeometry | None) -> BaseGeometry:
    """Only the areal part of a geometry (drops slivers that degenerate to lines/points)."""
    ps = polygons_of(geom)
    if not ps:
        return EMPTY
    return ps[0] if len(ps) == 1 else MultiPolygon(ps)


# Cleaning tolerances: vertices closer than POINT_TOL are one vertex; rings of less area
# than RING_AREA are slivers (a curb "ring" of 1e-7 m made remove_repeated_points fail).
POINT_TOL = 1e-7
RING_AREA = 1e-9
TINY_COORD = 1e-12    # coordinates nearer zero than this (a picometre) are zero
SNAP_GRID = 1e-6      # last resort: snap to this grid (GEOS keeps the result valid)


def _clean_ring(ring, tol: float = POINT_TOL, min_area: float = RING_AREA) -> np.ndarray | None:
    """XY of a ring without repeated points and without its closing point, or None when it
    has fewer than 3 distinct vertices or no area (a degenerate ring)."""
    c = np.asarray(ring.coords, dtype=np.float64)[:, :2]
    if len(c) == 0 or not np.isfinite(c).all():
        return None
    keep = np.ones(len(c), bool)
    keep[1:] = np.linalg.norm(np.diff(c, axis=0), axis=1) > tol
    c = c[keep]
    while len(c) > 1 and np.linalg.norm(c[0] - c[-1]) <= tol:
        c = c[:-1]
    if len(c) < 3:
        return None
    # the shoelace about the first vertex: with raw coordinates of 1e5 m its products cancel
    # to ~1e-5 m², the size of the slivers this test is for
    x, y = c[:, 0] - c[0, 0], c[:, 1] - c[0, 1]
    if 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))) <= min_area:
        return None
    return c


def _rebuilt(poly: Polygon) -> Polygon | None:
    ext = _clean_ring(poly.exterior)
    if ext is None:
        return None
    holes = [h for h in (_clean_ring(r) for r in poly.interiors) if h is not None]
    return Polygon(ext, holes)


def _vertex_gaps(xy: np.ndarray, owner: np.ndarray, n: int) -> np.ndarray:
    """Per polygon, the least distance between two of its distinct vertices (inf: none).

    Consecutive vertices are kept apart by ring cleaning; this sees the others: a hole's
    vertex 4e-9 m from the outer ring's corner leaves a sliver between the rings that the
    cap triangulation drops, and walls of no area over the 4e-9 m edge that remains.
    Rings touching at one point share that vertex exactly (a gap of 0 is not counted)."""
    rows = np.unique(np.column_stack([owner, xy]), axis=0)
    # multipoints wants consecutive indices: the polygons that have vertices, renumbered
    present, idx = np.unique(rows[:, 0].astype(np.intp), return_inverse=True)
    gaps = np.full(n, np.inf)
    gaps[present] = shapely.minimum_clearance(shapely.multipoints(rows[:, 1:], indices=idx))
    return gaps


def _vertex_gap(poly: Polygon) -> float:
    xy = shapely.get_coordinates(poly)
    return float(_vertex_gaps(xy, np.zeros(len(xy), np.intp), 1)[0])


def _sound(poly: Polygon) -> bool:
    """Valid, with every ring non-degenerate as it stands (nothing left to drop)."""
    if not poly.is_valid or poly.area <= RING_AREA:
        return False
    if _vertex_gap(poly) <= POINT_TOL:
        return False
    for r in (poly.exterior, *poly.interiors):
        c = _clean_ring(r)
        if c is None or len(c) != len(r.coords) - 1:
            return False
    return True


def _sound_all(polys: list[Polygon], valid: bool = False) -> np.ndarray:
    """_sound of every polygon at once (vectorised over all rings: many small pieces, such
    as the dashes of a line, cost one call instead of one Python loop each). ``valid``: the
    polygons are known to be valid (the parts of a geometry found valid), not checked again."""
    arr = np.array(polys, dtype=object)
    ok = shapely.area(arr) > RING_AREA
    if not valid:
        ok &= shapely.is_valid(arr)
    rings, part = shapely.get_rings(arr, return_index=True)
    if not len(rings):
        return ok
    xy, ring_of = shapely.get_coordinates(rings, return_index=True)
    n = np.bincount(ring_of, minlength=len(rings))
    same = ring_of[1:] == ring_of[:-1]
    close = same & (np.hypot(*np.diff(xy, axis=0).T) <= POINT_TOL)
    bad = np.bincount(ring_of[1:][close], minlength=len(rings)) > 0
    bad |= n < 4
    bad |= np.bincount(ring_of[~np.isfinite(xy).all(axis=1)], minlength=len(rings)) > 0
    bad |= shapely.area(shapely.polygons(rings)) <= RING_AREA
    ok &= np.bincount(part[bad], minlength=len(polys)) == 0
    ok &= _vertex_gaps(xy, part[ring_of], len(polys)) > POINT_TOL
    return ok


def _clean_pieces(geom: BaseGeometry, valid: bool = False) -> tuple[list[Polygon], bool]:
    """The sound polygons of ``geom`` (see clean_area) and whether they are its own
    polygons, every one kept as it was. ``valid``: ``geom`` is known to be valid."""
    out: list[Polygon] = []
    polys = polygons_of(geom)
    sound = _sound_all(polys, valid) if polys else []
    untouched = True
    for poly, ok in zip(polys, sound):
        if ok:
            out.append(poly)
            continue
        untouched = False
        q = _rebuilt(poly)
        if q is None:
            continue
        if not q.is_valid:
            q = shapely.make_valid(q)
        for piece in polygons_of(q):
            if _sound(piece):
                out.append(piece)
                continue
            piece = _rebuilt(piece)
            if piece is None:
                continue
            snapped = shapely.set_precision(piece, SNAP_GRID)
            out.extend(p for p in polygons_of(snapped) if _sound(p))
    return out, untouched


def _assemble(polys: list[Polygon]) -> BaseGeometry:
    if not polys:
        return EMPTY
    return polys[0] if len(polys) == 1 else MultiPolygon(polys)


def clean_area(geom: BaseGeometry | None) -> BaseGeometry:
    """The areal part of any geometry as valid polygons free of repeated vertices and
    degenerate (sliver) rings: the one cleaning step before polygons become meshes.

    make_valid first, then each polygon's rings are rebuilt without repeated points
    (POINT_TOL) and rings without area are dropped; a polygon that is still not sound goes
    through make_valid again and, as a last resort, is snapped to SNAP_GRID. Pieces that
    overlap once their rings are cleaned are merged and cleaned once more (then snapped).
    """
    if geom is None or geom.is_empty:
        return EMPTY
    valid = geom.is_valid
    if not valid:
        geom = shapely.make_valid(geom)
    pieces, untouched = _clean_pieces(geom, valid)
    result = _assemble(pieces)
    # the polygons of a valid (multi)polygon, all kept: valid as they stand (not so for
    # a collection, whose members may overlap)
    if valid and untouched and isinstance(geom, (Polygon, MultiPolygon)):
        return result
    if result.is_valid:
        return result
    merged = shapely.union_all(np.array(pieces, dtype=object))
    result = _assemble(_clean_pieces(merged)[0])
    if result.is_valid:
        return result
    snapped = shapely.set_precision(merged, SNAP_GRID)   # valid output by construction
    return _assemble([p for p in polygons_of(snapped) if _sound(p)])


def area_from_points(points) -> BaseGeometry:
    """A polygon given as an (N, 2|3) vertex array (implicitly closed; any mess: repeated
    points, self-intersections, zero width), as clean_area of it."""
    xy = np.asarray(points, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2 or len(xy) < 3 or not np.isfinite(xy[:, :2]).all():
        return EMPTY
    xy = xy[:, :2]
    tiny = np.abs(xy) < TINY_COORD
    if tiny.any():      # 1e-29 .. 1e-16 m made GEOS's mitred buffers raise a floating-point
        # divide-by-zero flag, which numpy prints as a RuntimeWarning
        xy = np.where(tiny, 0.0, xy)
    return clean_area(Polygon(xy))


MITER_LIMIT = MITRE_LIMIT     # a mitre reaches at most this many half widths from its vertex


def _near_span(xy: np.ndarray, within, reach: float) -> tuple[int, int] | None:
    """The vertex slice [a, b) of a polyline whose quads are all that can meet ``within``.

    A segment's quad lies inside the segment's bounds grown by ``reach`` (the longest
    mitre), so segments whose grown bounds miss the box are left out; the slice keeps one
    more vertex at each end, so every kept segment's two mitres are computed from the same
    neighbours as in the whole polyline (the quads of the kept segments are the whole
    polyline's, bit for bit). The slice's end segments may be extra: the caller's exact
    bounds test drops them (their quads still lie in their grown bounds). None: no segment
    is near.
    """
    a, b = xy[:-1], xy[1:]
    lo, hi = np.minimum(a, b) - reach, np.maximum(a, b) + reach
    k = np.nonzero((hi[:, 0] >= within[0]) & (lo[:, 0] <= within[2])
                   & (hi[:, 1] >= within[1]) & (lo[:, 1] <= within[3]))[0]
    if not len(k):
        return None
    return max(int(k[0]) - 1, 0), min(int(k[-1]) + 3, len(xy))


def _quads(points: np.ndarray, left, right=None,
           within: tuple[float, float, float, float] | None = None) -> np.ndarray:
    """The mitred per-segment quads (S, 4, 2) of a ribbon (CCW), those meeting ``within``."""
    pts = np.asarray(points, dtype=np.float64)
    keep_idx = _dedupe_index(pts[:, :2])
    xy = pts[keep_idx, :2]
    if len(xy) < 2:
        return np.zeros((0, 4, 2))
    left = np.broadcast_to(np.asarray(left, dtype=np.float64), (len(pts),))[keep_idx]
    right = left if right is None else np.broadcast_to(
        np.asarray(right, dtype=np.float64), (len(pts),))[keep_idx]
    if within is not None:
        reach = MITER_LIMIT * max(float(np.abs(left).max()), float(np.abs(right).max()))
        span = _near_span(xy, within, reach)
        if span is None:
            return np.zeros((0, 4, 2))
        a, b = span
        xy, left, right = xy[a:b], left[a:b], right[a:b]
    vn, sc = mitre_normals(xy)
    L = xy + vn * (left * sc)[:, None]
    R = xy - vn * (right * sc)[:, None]
    quads = np.stack([R[:-1], R[1:], L[1:], L[:-1]], axis=1)
    if within is not None:
        lo, hi = quads.min(axis=1), quads.max(axis=1)
        near = ((hi[:, 0] >= within[0]) & (lo[:, 0] <= within[2])
                & (hi[:, 1] >= within[1]) & (lo[:, 1] <= within[3]))
        quads = quads[near]
    return quads


def _union_quads(quads: np.ndarray) -> BaseGeometry:
    if not len(quads):
        return EMPTY
    polys = shapely.polygons(quads)
    bad = ~shapely.is_valid(polys)
    if bad.any():
        polys[bad] = shapely.make_valid(polys[bad])
    return as_area(shapely.union_all(polys))


def ribbon(points: np.ndarray, left: np.ndarray | float, right: np.ndarray | float | None = None,
           within: tuple[float, float, float, float] | None = None) -> BaseGeometry:
    """Area swept by a polyline with per-vertex half widths to the left and right.

    Built from mitred per-segment quads (so consecutive quads share edges and
    bends leave no wedge gaps) and unioned; self-overlaps on the inside of
    tight bends are resolved by the union.

    ``within`` (xmin, ymin, xmax, ymax): only the quads whose bounds meet this box are
    built and unioned. The quads are those of the whole polyline (the mitre at every
    vertex is computed from its neighbours), so inside the box the area is the same as
    the whole ribbon's; a chunk pays for the part of a long lane near it, not its length.
    """
    return _union_quads(_quads(points, left, right, within))


def _quads_many(lines: list[np.ndarray], half_width: float) -> np.ndarray:
    """The mitred quads of many polylines of one half width, vectorised over all of them:
    per polyline the same quads as ``_quads`` (repeated points dropped, mitre at each
    interior vertex from its two segments, limited as in ``mitre_normals``)."""
    lines = [np.asarray(ln, dtype=np.float64)[:, :2] for ln in lines if len(ln) >= 2]
    if not lines:
        return np.zeros((0, 4, 2))
    xy = np.concatenate(lines)
    lid = np.repeat(np.arange(len(lines)), [len(ln) for ln in lines])
    same = lid[1:] == lid[:-1]
    dup = same & (np.hypot(*np.diff(xy, axis=0).T) <= 1e-6)
    keep = np.concatenate([[True], ~dup])
    xy, lid = xy[keep], lid[keep]
    same = lid[1:] == lid[:-1]                      # segment k joins vertex k and k + 1
    d = np.diff(xy, axis=0)
    seg_len = np.hypot(d[:, 0], d[:, 1])[:, None]
    seg_n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(seg_len, 1e-12)
    seg_n[~same] = 0.0
    has_prev = np.concatenate([[False], same])
    has_next = np.concatenate([same, [False]])
    prev = np.zeros_like(xy)
    prev[1:] = seg_n
    nxt = np.zeros_like(xy)
    nxt[:-1] = seg_n
    vn = prev + nxt
    ln = np.hypot(vn[:, 0], vn[:, 1])
    bad = ln < 1e-9                                  # a reversal: the incoming normal
    vn[bad] = np.where(has_prev[bad, None], prev[bad], nxt[bad])
    ln[bad] = 1.0
    vn = vn / ln[:, None]
    inner = has_prev & has_next
    cos_half = np.ones(len(xy))
    cos_half[inner] = np.einsum("ij,ij->i", vn[inner], prev[inner])
    scale = 1.0 / np.clip(cos_half, 0.25, 1.0)       # miter limit 4, as mitre_normals
    L = xy + vn * (half_width * scale)[:, None]
    R = xy - vn * (half_width * scale)[:, None]
    q = np.stack([R[:-1], R[1:], L[1:], L[:-1]], axis=1)
    return q[same]


def ribbons(lines: list[np.ndarray], half_width: float,
            within: tuple[float, float, float, float] | None = None) -> BaseGeometry:
    """The union of the ribbons of many polylines of one half width, in one vectorised step
    and one union (the dashes of a broken line: one call, not one union per dash).

    ``within``: only the quads meeting this box; each line is first cut to the vertices
    whose quads can meet it (``_near_span``), so a long line costs what lies near the box.
    """
    if within is not None:
        # short lines (dashes, already picked near the box) are taken whole
        lines = [c for c in (ln if len(ln) <= 16 else _near_part(ln, within, MITER_LIMIT
                                                                  * abs(half_width))
                             for ln in lines) if c is not None]
    q = _quads_many(lines, half_width)
    if within is not None and len(q):
        lo, hi = q.min(axis=1), q.max(axis=1)
        q = q[(hi[:, 0] >= within[0]) & (lo[:, 0] <= within[2])
              & (hi[:, 1] >= within[1]) & (lo[:, 1] <= within[3])]
    return _union_quads(q)


def _near_part(line: np.ndarray, within, reach: float) -> np.ndarray | None:
    """The raw vertices of ``line`` (XY) that _quads_many needs for its quads meeting
    ``within``: a slice starting at a vertex _quads_many keeps, so its repeated-point
    removal keeps the same vertices inside it as in the whole line."""
    xy = np.asarray(line, dtype=np.float64)[:, :2]
    if len(xy) < 2:
        return xy
    keep = np.concatenate([[True], ~(np.hypot(*np.diff(xy, axis=0).T) <= 1e-6)])  # as _quads_many
    kept = np.nonzero(keep)[0]
    if len(kept) < 2:
        return xy
    span = _near_span(xy[kept], within, reach)
    if span is None:
        return None
    a, b = span
    return xy[kept[a]:(kept[b] if b < len(kept) else len(xy))]


def grow(bounds: tuple[float, float, float, float], d: float) -> tuple[float, float, float, float]:
    """A box (xmin, ymin, xmax, ymax) grown by ``d`` on every side."""
    return bounds[0] - d, bounds[1] - d, bounds[2] + d, bounds[3] + d


def _dedupe_index(xy: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    if len(xy) < 2:
        return np.arange(len(xy))
    keep = np.ones(len(xy), bool)
    keep[1:] = np.linalg.norm(np.diff(xy, axis=0), axis=1) > tol
    return np.nonzero(keep)[0]


def dashes(points: np.ndarray, dash: float, gap: float, phase: float = 0.0,
           within: tuple[float, float, float, float] | None = None) -> list[np.ndarray]:
    """Sub-polylines of length ``dash`` every ``dash + gap`` metres along a polyline.

    ``phase`` is the arc length at which the pattern starts (pass the
    polyline's absolute start so dashes line up across chunk borders).
    ``within`` (xmin, ymin, xmax, ymax): only the dashes along segments that meet this box
    (the same dashes, at the same arc lengths, as without it).
    """
    xy = clean_polyline(points)
    if len(xy) < 2:
        return []
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    period = dash + gap
    first = -((phase) % period)
    starts = np.arange(first, s[-1], period)
    if within is not None:
        a, b = xy[:-1], xy[1:]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        near = ((hi[:, 0] >= within[0]) & (lo[:, 0] <= within[2])
                & (hi[:, 1] >= within[1]) & (lo[:, 1] <= within[3]))
        k = np.nonzero(near)[0]
        if not len(k):
            return []
        # a dash [a, a + dash] is kept when it overlaps a near segment [s_k, s_k+1]
        seg_of_start = np.searchsorted(s, starts, side="right") - 1
        seg_of_end = np.searchsorted(s, starts + dash, side="left") - 1
        cum = np.concatenate([[0], np.cumsum(near)])
        lo_i = np.clip(seg_of_start, 0, len(seg) - 1)
        hi_i = np.clip(seg_of_end, 0, len(seg) - 1)
        starts = starts[cum[hi_i + 1] - cum[lo_i] > 0]
    # every dash's ends and inner vertices at once; each dash: its start, the polyline's
    # vertices strictly inside it, its end
    a0, a1 = np.maximum(starts, 0.0), np.minimum(starts + dash, s[-1])
    ok = ~(a1 - a0 < 1e-3)
    a0, a1 = a0[ok], a1[ok]
    i0, i1 = np.searchsorted(s, a0, side="right"), np.searchsorted(s, a1, side="left")
    pa = np.column_stack([np.interp(a0, s, xy[:, 0]), np.interp(a0, s, xy[:, 1])])
    pb = np.column_stack([np.interp(a1, s, xy[:, 0]), np.interp(a1, s, xy[:, 1])])
    return [np.vstack([pa[k:k + 1], xy[i0[k]:i1[k]], pb[k:k + 1]]) for k in range(len(a0))]


def triangulate(geom: BaseGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Constrained Delaunay triangulation of a (multi)polygon with holes.

    Returns vertices (N, 2) and CCW faces (M, 3) int32. Vertices are shared
    between triangles (merged on exact coordinates); near-collinear slivers
    (area <= MIN_FACE_AREA) are dropped.
    """
    empty = np.zeros((0, 2)), np.zeros((0, 3), np.int32)
    polys = polygons_of(clean_area(geom))
    if not polys:
        return empty
    tris = shapely.constrained_delaunay_triangles(np.array(polys, dtype=object))
    parts = shapely.get_parts(tris)
    parts = parts[~shapely.is_empty(parts)]
    if not len(parts):
        return empty
    c = shapely.get_coordinates(parts)
    m = len(parts)
    tri = c.reshape(m, 4, 2)[:, :3].reshape(-1, 2)
    uniq, inv = np.unique(tri, axis=0, return_inverse=True)
    faces = inv.reshape(m, 3).astype(np.int32)
    a, b, cc = uniq[faces[:, 0]], uniq[faces[:, 1]], uniq[faces[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (cc[:, 0] - a[:, 0])
    flip = cross < 0
    faces[flip] = faces[flip][:, ::-1]
    faces = faces[np.abs(cross) > 2 * MIN_FACE_AREA]
    return uniq, faces


def flat_mesh(geom: BaseGeometry, z: float) -> tuple[np.ndarray, np.ndarray]:
    """Upward-facing triangulated surface of an area at height z."""
    xy, f = triangulate(geom)
    v = np.column_stack([xy, np.full(len(xy), float(z))])
    return v, f


def prism(geom: BaseGeometry, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed prism over an area between heights z0 < z1 (watertight, outward normals).

    Per polygon: top from a constrained triangulation, bottom its mirror, walls
    one quad per boundary edge of the cap triangulation, so the result is closed
    by construction; a polygon that still does not close (rings touching each
    other) is split in halves and retried.
    """
    if geom is None or geom.is_empty:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    # drop repeated and collinear ring vertices and sliver rings so the caps have no
    # zero-area slivers (clean_area before and after the collinear simplification)
    polys = polygons_of(clean_area(shapely.simplify(clean_area(geom), 0.0)))
    vs, fs, n0 = [], [], 0
    for poly in polys:
        v, f = _prism_split(poly, z0, z1)
        if len(f):
            vs.append(v)
            fs.append(f + n0)
            n0 += len(v)
    if not fs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    return np.vstack(vs), np.vstack(fs).astype(np.int32)


def _prism_split(poly: Polygon, z0: float, z1: float, depth: int = 0):
    """_prism_one, or when that cannot close the polygon (rings touching themselves or
    each other), the prisms of its two halves (recursively, a few levels)."""
    v, f = _prism_one(poly, z0, z1)
    if len(f) or depth >= 6 or poly.area < 1e-4:
        return v, f
    x0, y0, x1, y1 = poly.bounds
    if x1 - x0 >= y1 - y0:
        m = x0 + (x1 - x0) * 0.5 + 1e-4 * (x1 - x0)
        halves = [box(x0 - 1, y0 - 1, m, y1 + 1), box(m, y0 - 1, x1 + 1, y1 + 1)]
    else:
        m = y0 + (y1 - y0) * 0.5 + 1e-4 * (y1 - y0)
        halves = [box(x0 - 1, y0 - 1, x1 + 1, m), box(x0 - 1, m, x1 + 1, y1 + 1)]
    vs, fs, n0 = [], [], 0
    for h in halves:
        for piece in polygons_of(clean_area(shapely.simplify(shapely.intersection(poly, h), 0.0))):
            pv, pf = _prism_split(piece, z0, z1, depth + 1)
            if len(pf):
                vs.append(pv)
                fs.append(pf + n0)
                n0 += len(pv)
    if not fs:
        return v, f
    return np.vstack(vs), np.vstack(fs).astype(np.int32)


def _closed(faces: np.ndarray) -> bool:
    """Every directed edge appears once and has its reverse (closed, consistently wound)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    k = e[:, 0] * (faces.max() + 1) + e[:, 1]
    r = e[:, 1] * (faces.max() + 1) + e[:, 0]
    ks = np.sort(k)
    if (np.diff(ks) == 0).any():
        return False
    return bool(np.isin(r, ks, assume_unique=False).all())


def _prism_one(poly: Polygon, z0: float, z1: float):
    empty = np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    if not poly.is_valid or poly.area < 1e-6:
        return empty
    xy, top = triangulate(poly)
    if len(top) == 0:
        return empty
    # walls along the boundary edges of the cap triangulation itself (edges used by one
    # triangle), so the solid is closed even where near-collinear slivers were dropped
    e = np.concatenate([top[:, [0, 1]], top[:, [1, 2]], top[:, [2, 0]]]).astype(np.int64)
    m = len(xy)
    fwd = e[:, 0] * m + e[:, 1]
    rev = e[:, 1] * m + e[:, 0]
    boundary = e[~np.isin(fwd, rev)]
    n = len(xy)
    verts = np.vstack([np.column_stack([xy, np.full(n, z1)]),
                       np.column_stack([xy, np.full(n, z0)])])
    a, b = boundary[:, 0], boundary[:, 1]
    # edge a->b of a CCW cap triangle has the area on its left: outward is its right
    walls = [np.stack([a + n, b + n, b], axis=1), np.stack([a + n, b, a], axis=1)]
    faces = np.vstack([top, top[:, ::-1] + n] + walls).astype(np.int32)
    return (verts, faces) if _closed(faces) else empty


def box_polygon(bounds) -> Polygon:
    return box(*bounds)


def line(points: np.ndarray) -> LineString:
    return LineString(np.asarray(points, dtype=np.float64)[:, :2])
