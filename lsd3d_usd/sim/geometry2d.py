"""Oriented boxes on the ground plane, as arrays: corners, overlap, containment.

A box is (centre xy, yaw, length, width): length along the heading (yaw, radians from +X,
counter-clockwise), width across it, metres. Corners come in the order front-right,
front-left, rear-left, rear-right (counter-clockwise; corners 0-1 are the front edge).

`boxes_overlap` is the separating axis theorem on the two boxes' own axes (the heading and
its normal), vectorised over broadcast arrays. The boxes are closed sets, as shapely's
``intersects``: touching boxes overlap. A box of zero length and/or width (a segment or a
point) is handled exactly, because the axes come from the yaw and not from edge vectors.
Containment and polygon tests go through shapely (GEOS), with the boundary counted inside.
"""
from __future__ import annotations

import numpy as np
import shapely

#: Gap (m) under which two boxes count as touching: absorbs float64 rounding of the
#: projections, so boxes built to share an edge overlap as they do in shapely.
TOUCH_EPS = 1e-9

_SIGNS = np.array([[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]])


def box_corners(xy, yaw, length, width) -> np.ndarray:
    """Corners (..., 4, 2) of boxes broadcast over xy (..., 2), yaw, length, width (...)."""
    xy = np.asarray(xy, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    hl = 0.5 * np.asarray(length, dtype=np.float64)
    hw = 0.5 * np.asarray(width, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    shape = np.broadcast_shapes(xy.shape[:-1], yaw.shape, hl.shape, hw.shape)
    lx = _SIGNS[:, 0] * np.broadcast_to(hl, shape)[..., None]       # (..., 4) local x
    ly = _SIGNS[:, 1] * np.broadcast_to(hw, shape)[..., None]       # local y
    c = np.broadcast_to(c, shape)[..., None]
    s = np.broadcast_to(s, shape)[..., None]
    xy = np.broadcast_to(xy, shape + (2,))
    x = xy[..., 0:1] + c * lx - s * ly
    y = xy[..., 1:2] + s * lx + c * ly
    return np.stack([x, y], axis=-1)


def boxes_overlap(xy_a, yaw_a, length_a, width_a, xy_b, yaw_b, length_b, width_b,
                  eps: float = TOUCH_EPS) -> np.ndarray:
    """Whether boxes a and b overlap or touch (separating axis theorem), broadcast.

    One against many: a scalar box a and arrays (N, 2), (N,) for b give (N,) booleans.
    """
    xy_a = np.asarray(xy_a, dtype=np.float64)
    xy_b = np.asarray(xy_b, dtype=np.float64)
    ya = np.asarray(yaw_a, dtype=np.float64)
    yb = np.asarray(yaw_b, dtype=np.float64)
    hla, hwa = 0.5 * np.asarray(length_a, np.float64), 0.5 * np.asarray(width_a, np.float64)
    hlb, hwb = 0.5 * np.asarray(length_b, np.float64), 0.5 * np.asarray(width_b, np.float64)
    d = xy_b - xy_a
    dx, dy = d[..., 0], d[..., 1]
    ca, sa, cb, sb = np.cos(ya), np.sin(ya), np.cos(yb), np.sin(yb)
    # |cos| and |sin| of the relative yaw: the projections of b's axes on a's and vice versa
    cr = np.abs(ca * cb + sa * sb)
    sr = np.abs(ca * sb - sa * cb)
    ok = np.ones(np.broadcast_shapes(dx.shape, ya.shape, yb.shape, hla.shape, hwa.shape,
                                     hlb.shape, hwb.shape), dtype=bool)
    # a's heading, a's normal, b's heading, b's normal
    for ux, uy, ra, rb in ((ca, sa, hla, hlb * cr + hwb * sr),
                           (-sa, ca, hwa, hlb * sr + hwb * cr),
                           (cb, sb, hla * cr + hwa * sr, hlb),
                           (-sb, cb, hla * sr + hwa * cr, hwb)):
        ok &= np.abs(dx * ux + dy * uy) <= ra + rb + eps
    return ok


def box_geometry(xy, yaw, length, width):
    """One box as a shapely geometry: a Polygon, or a LineString / Point when degenerate."""
    corners = box_corners(xy, yaw, length, width)
    if length > 0 and width > 0:
        return shapely.Polygon(corners)
    if length > 0 or width > 0:
        a, b = ((corners[0], corners[3]) if length > 0 else (corners[0], corners[1]))
        return shapely.LineString([a, b])
    return shapely.Point(np.asarray(xy, dtype=np.float64))


def box_polygons(xy, yaw, length, width) -> np.ndarray:
    """Shapely polygons (object array) of non-degenerate boxes broadcast over the inputs."""
    return shapely.polygons(box_corners(xy, yaw, length, width))


def points_in(geometry, xy) -> np.ndarray:
    """Whether each point (..., 2) lies in the geometry, its boundary included."""
    xy = np.asarray(xy, dtype=np.float64)
    return shapely.intersects_xy(geometry, xy[..., 0], xy[..., 1])


def box_inside(geometry, xy, yaw, length, width) -> np.ndarray:
    """Whether all four corners of each box lie in the geometry (NAVSIM's corner rule)."""
    return points_in(geometry, box_corners(xy, yaw, length, width)).all(axis=-1)


def relative_angle(xy, yaw, points) -> np.ndarray:
    """Angle in [0, pi] between the heading at xy and the direction to each point (..., 2).

    A point at xy itself is at angle 0 (ahead), as nuPlan's helpers treat full overlap.
    """
    d = np.asarray(points, dtype=np.float64) - np.asarray(xy, dtype=np.float64)
    ang = np.arctan2(d[..., 1], d[..., 0]) - float(yaw)
    ang = np.abs((ang + np.pi) % (2.0 * np.pi) - np.pi)
    return np.where((d[..., 0] == 0) & (d[..., 1] == 0), 0.0, ang)


def polygon_tree(polygons) -> shapely.STRtree:
    """An STRtree over static polygons, for `hits`."""
    return shapely.STRtree(list(polygons))


def hits(tree: shapely.STRtree, geometries) -> np.ndarray:
    """Pairs (2, K) [geometry index, tree index] of intersecting geometries (one or many)."""
    geoms = np.atleast_1d(np.asarray(geometries, dtype=object))
    return tree.query(geoms, predicate="intersects")
