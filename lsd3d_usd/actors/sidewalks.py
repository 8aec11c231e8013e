"""Where pedestrians may be: the walkable area of a layout, walking tracks and crosswalk links.

The walkable area is the proxy's own sidewalk area (`proxy.ground.ground_areas` over the
whole layout: the layout's sidewalk polygons and sidewalk lanes, or where it has none the
band the proxy derives along the roads), minus tree trunks and poles standing on it.
Crosswalks are the layout's crosswalk polygons; the curb strip between a sidewalk and a
crosswalk is stepped over.

Walking tracks are the rings of the walkable area shrunk by ``track_offset`` (round
joins, so a track keeps that distance from every edge of the area, kerb and façade side
alike); every walker on a ring goes the same way round, so walkers only ever follow each
other. Each crosswalk links the two tracks nearest its ends: a walker leaves its track at
the point nearest the crosswalk end, crosses along the crosswalk's axis (on the right-hand
half for its direction) and joins the other track at the point nearest the far end.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Point, Polygon
from shapely.geometry.polygon import orient

from lsd3d_usd.proxy.ground import GroundStyle, ground_areas
from lsd3d_usd.proxy.planar import area_from_points

TRUNK_RADIUS = 0.45      # m kept clear around a tree on the sidewalk
POLE_RADIUS = 0.25


@dataclass
class Track:
    """A closed walking line (K+1, 2), first point repeated, with its arc lengths."""
    points: np.ndarray
    cum: np.ndarray

    @property
    def length(self) -> float:
        return float(self.cum[-1])

    def point(self, s) -> np.ndarray:
        s = np.mod(np.asarray(s, np.float64), self.length)
        return np.stack([np.interp(s, self.cum, self.points[:, k]) for k in range(2)], axis=-1)

    def heading(self, s, half: float = 0.4) -> np.ndarray:
        a, b = self.point(np.asarray(s) - half), self.point(np.asarray(s) + half)
        d = b - a
        return np.arctan2(d[..., 1], d[..., 0])

    def pose2d(self, s: float, half: float = 0.4) -> tuple[np.ndarray, float]:
        """(xy (2,), yaw) at one arc length: the scalar fast path of `point` / `heading`."""
        if not hasattr(self, "_cum_list"):
            self._cum_list = self.cum.tolist()
            self._xy_list = self.points.tolist()
        x, y = self._xy2(s)
        ax, ay = self._xy2(s - half)
        bx, by = self._xy2(s + half)
        return np.array([x, y]), math.atan2(by - ay, bx - ax)

    def _xy2(self, s: float) -> tuple[float, float]:
        cum, xy = self._cum_list, self._xy_list
        s = s % self.length
        j = min(max(bisect.bisect_right(cum, s) - 1, 0), len(cum) - 2)
        d = cum[j + 1] - cum[j]
        f = (s - cum[j]) / d if d > 0 else 0.0
        return xy[j][0] + f * (xy[j + 1][0] - xy[j][0]), xy[j][1] + f * (xy[j + 1][1] - xy[j][1])

    def project(self, xy) -> float:
        return float(LineString(self.points).project(Point(float(xy[0]), float(xy[1]))))


@dataclass
class CrosswalkLink:
    """One crosswalk as a way across: its polygon, the ends of its axis (a, b), its width
    across the axis, and for each end the track and arc length where walkers leave / join."""
    id: str
    polygon: Polygon
    a: np.ndarray
    b: np.ndarray
    width: float
    track_a: int
    s_a: float
    track_b: int
    s_b: float


@dataclass
class Walkable:
    area: object                 # shapely (Multi)Polygon: sidewalks, obstacles removed
    crosswalks: list             # CrosswalkLink
    tracks: list                 # Track
    stand_spots: np.ndarray      # (n, 2) candidate standing points, corners first
    curb_width: float
    road: object = None          # shapely: road surface and curbs (where mid-block crossings go)

    def allowed(self, pad: float = 0.0):
        """Sidewalks, crosswalks and the curb strips between them (shapely), grown by ``pad``."""
        parts = [self.area] + [c.polygon for c in self.crosswalks]
        u = shapely.union_all(np.array(parts, dtype=object))
        return u.buffer(self.curb_width + 0.05 + pad, quad_segs=4)


def _rings(geom) -> list[np.ndarray]:
    """Exterior and interior rings, the area always on their left (exteriors anticlockwise)."""
    out = []
    for poly in getattr(geom, "geoms", [geom]):
        if poly.is_empty or poly.geom_type != "Polygon":
            continue
        poly = orient(poly, 1.0)
        for ring in [poly.exterior, *poly.interiors]:
            xy = np.asarray(ring.coords, np.float64)[:, :2]
            if len(xy) >= 4 and LineString(xy).length > 4.0:
                out.append(xy)
    return out


def _track(xy: np.ndarray, step: float = 0.5) -> Track:
    line = LineString(xy)
    n = max(8, int(np.ceil(line.length / step)))
    pts = np.array([line.interpolate(d).coords[0][:2] for d in np.linspace(0, line.length, n + 1)])
    pts[-1] = pts[0]
    # the ring's orientation is kept: the walkable area on the left of the walking direction
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    return Track(pts, np.concatenate([[0.0], np.cumsum(seg)]))


def walkable_area(layout, style: GroundStyle = GroundStyle(), with_road: bool = False):
    """The sidewalk area of ``layout`` as the proxy builds it (shapely), obstacles removed
    (and with ``with_road`` the road surface with its curbs as a second value)."""
    (x0, y0), (x1, y1) = layout.area_box()
    pad = style.curb_width + style.sidewalk_width + 5.0
    b = (x0 - pad, y0 - pad, x1 + pad, y1 + pad)
    ext = layout.extent
    areas = ground_areas(
        b, 0.0, lanes=[(ln.points, ln.widths, ln.lane_type) for ln in layout.lanes],
        road_areas=[r.polygon for r in layout.road_areas],
        sidewalks=[s.polygon for s in layout.sidewalks],
        vegetation=[z.polygon for z in layout.vegetation_zones],
        buildings=[bd.footprint for bd in layout.buildings], style=style,
        extent=None if ext is None else (ext[0][0], ext[0][1], ext[1][0], ext[1][1]))
    W = areas["sidewalk"]
    obstacles = [Point(*t.position[:2]).buffer(TRUNK_RADIUS, quad_segs=3) for t in layout.trees]
    obstacles += [Point(*p.position[:2]).buffer(POLE_RADIUS, quad_segs=3) for p in layout.poles]
    if obstacles and not W.is_empty:
        W = W.difference(shapely.union_all(np.array(obstacles, dtype=object)))
    if with_road:
        return W, shapely.union(areas["road"], areas["curb"])
    return W


def _crosswalk_axis(poly: Polygon, W) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(a, b, width): the axis of the crosswalk whose ends lie nearest the sidewalks."""
    rect = poly.minimum_rotated_rectangle
    c = np.asarray(rect.exterior.coords, np.float64)[:4, :2]
    best = None
    for k in (0, 1):
        # axis through the midpoints of edges k and k+2
        a = (c[k] + c[(k + 1) % 4]) / 2
        b = (c[(k + 2) % 4] + c[(k + 3) % 4]) / 2
        width = float(np.linalg.norm(c[(k + 1) % 4] - c[k]))
        d = W.distance(Point(*a)) + W.distance(Point(*b)) if not W.is_empty else 0.0
        if best is None or d < best[0]:
            best = (d, a, b, width)
    if best is None or np.linalg.norm(best[2] - best[1]) < 1.0:
        return None
    return best[1], best[2], best[3]


def build_walkable(layout, track_offset: float = 0.6, stand_offset: float = 1.5,
                   style: GroundStyle = GroundStyle()) -> Walkable:
    """Walkable area, walking tracks, crosswalk links and standing spots of ``layout``."""
    W, road = walkable_area(layout, style, with_road=True)
    tracks = [] if W.is_empty else [_track(r) for r in _rings(W.buffer(-track_offset, quad_segs=6))]
    links = []
    for cw in layout.crosswalks:
        poly = area_from_points(cw.polygon)
        if poly.is_empty or not tracks:
            continue
        axis = _crosswalk_axis(poly, W)
        if axis is None:
            continue
        a, b, width = axis
        ends = []
        for e in (a, b):
            d = [LineString(t.points).distance(Point(*e)) for t in tracks]
            k = int(np.argmin(d))
            ends.append((k, tracks[k].project(e), d[k]))
        # both ends must reach a track within a few metres (a sidewalk on each side)
        if ends[0][2] > 4.0 or ends[1][2] > 4.0 or (ends[0][0] == ends[1][0] and
                                                     abs(ends[0][1] - ends[1][1]) < 2.0):
            continue
        links.append(CrosswalkLink(cw.id, poly, a, b, width, ends[0][0], ends[0][1], ends[1][0], ends[1][1]))
    stand = np.zeros((0, 2))
    if not W.is_empty:
        deep = W.buffer(-stand_offset, quad_segs=4)
        pts = []
        for r in _rings(deep):
            t = _track(r, 1.0)
            pts.append(t.points[:-1])
        if pts:
            stand = np.concatenate(pts)
            # corners first: nearest to a junction lane or a crosswalk
            anchors = [ln.points[:, :2] for ln in layout.lanes if ln.is_junction]
            anchors += [np.asarray(cw.polygon, np.float64)[:, :2] for cw in layout.crosswalks]
            if anchors:
                A = np.concatenate(anchors)
                d = np.min(np.linalg.norm(stand[:, None, :] - A[None, ::max(1, len(A) // 400), :], axis=2), axis=1)
                stand = stand[np.argsort(d, kind="stable")]
    return Walkable(W, links, tracks, stand, style.curb_width, road)


def midblock_line(w: Walkable, track: int, s: float, max_length: float = 25.0,
                  crosswalk_distance: float = 8.0):
    """A way straight across the road from arc length ``s`` of ``track``, to the right of
    the walking direction (away from the sidewalk): (the point, the far track, its arc
    length there, the crossing corridor polygon), or None where there is no road to cross
    there (a façade, a hole, no track within ``max_length``, a crosswalk within
    ``crosswalk_distance``: cross there instead)."""
    if w.road is None or w.road.is_empty:
        return None
    t = w.tracks[track]
    p, yaw = t.pose2d(s)
    n = np.array([np.sin(yaw), -np.cos(yaw)])
    ray = LineString([p + 0.3 * n, p + max_length * n])
    best = None
    for k, other in enumerate(w.tracks):
        hit = ray.intersection(LineString(other.points))
        for g in getattr(hit, "geoms", [hit]):
            if g.is_empty or g.geom_type != "Point":
                continue
            d = float(np.dot(np.asarray(g.coords[0]) - p, n))
            if best is None or d < best[0]:
                best = (d, k, np.asarray(g.coords[0]))
    if best is None or best[0] < 4.0:
        return None
    d, k, q = best
    seg = LineString([p, q])
    off_walk = seg.difference(w.area.buffer(w.curb_width + 0.05))
    if off_walk.length < 3.0 or not w.road.buffer(0.05).contains(off_walk):
        return None
    corridor = seg.buffer(0.8, cap_style="flat")
    if any(corridor.distance(c.polygon) < crosswalk_distance for c in w.crosswalks):
        return None
    return p, k, w.tracks[k].project(q), corridor
