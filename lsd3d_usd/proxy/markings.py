"""Paint on the road: lane lines (solid / broken / double, white / yellow), stop lines,
crosswalk stripes. Thin open meshes 1 cm above the road surface, cut at the chunk box."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon

from lsd3d_usd.configtree import option
from lsd3d_usd.geometry.polyline import offset_polyline

from .mesh import CROSSWALK, LANE_MARKING, MeshPart
from .planar import area_from_points, as_area, dashes, flat_mesh, grow, ribbon, ribbons

PAINT = {"white": (0.80, 0.80, 0.78), "yellow": (0.75, 0.55, 0.08)}


@dataclass(frozen=True)
class MarkingStyle:
    line_width: float = option(0.15, help="road line width (m)", lo=0.0)
    double_gap: float = option(0.12, help="gap between the two lines of a double line (m)", lo=0.0)
    dash: float = option(3.0, help="dash length of broken lines (m)", lo=0.1)
    gap: float = option(6.0, help="gap between dashes (m)", lo=0.0)
    stop_line_width: float = option(0.4, help="stop line width (m)", lo=0.0)
    stripe_width: float = option(0.5, help="crosswalk bar width (m)", lo=0.0)
    stripe_gap: float = option(0.6, help="gap between crosswalk bars (m)", lo=0.0)
    lift: float = option(0.01, help="markings' height above the road surface (m)", lo=0.0)


def road_line_area(points: np.ndarray, kind: str, double: bool,
                   st: MarkingStyle = MarkingStyle(), within=None):
    """Painted area of one road line (the dash pattern starts at the line's first point,
    so it is the same whichever chunk asks). ``within`` (xmin, ymin, xmax, ymax): only
    the paint near this box is built (the same paint there as without it)."""
    offsets = [0.0]
    if double:
        d = (st.line_width + st.double_gap) / 2
        offsets = [-d, d]
    near = None if within is None else grow(within, st.line_width)
    pieces = []
    for o in offsets:
        pl = offset_polyline(points, o) if o else np.asarray(points)[:, :2]
        segs = dashes(pl, st.dash, st.gap, within=near) if kind == "broken" else [pl]
        pieces.append(ribbons(segs, st.line_width / 2, within=near))
    pieces = [p for p in pieces if not p.is_empty]
    return as_area(shapely.union_all(np.array(pieces, dtype=object))) if pieces else Polygon()


def crosswalk_area(polygon: np.ndarray, st: MarkingStyle = MarkingStyle()):
    """Zebra bars inside a crosswalk polygon: bars run along its short side (the
    direction of traffic), repeated along its long side (across the road)."""
    poly = area_from_points(polygon)
    if poly.is_empty:
        return Polygon()
    r = np.asarray(poly.minimum_rotated_rectangle.exterior.coords)[:4]
    e0, e1 = r[1] - r[0], r[2] - r[1]
    if np.linalg.norm(e0) < np.linalg.norm(e1):
        e0, e1 = e1, e0
        origin = r[1]
    else:
        origin = r[0]
    L, W = np.linalg.norm(e0), np.linalg.norm(e1)
    u, v = e0 / L, e1 / W
    period = st.stripe_width + st.stripe_gap
    n = int((L + st.stripe_gap) // period)
    start = (L - (n * period - st.stripe_gap)) / 2
    bars = []
    for k in range(n):
        a = origin + u * (start + k * period)
        bars.append(Polygon([a, a + u * st.stripe_width, a + u * st.stripe_width + v * W, a + v * W]))
    if not bars:
        return Polygon()
    return as_area(shapely.intersection(shapely.union_all(np.array(bars, dtype=object)), poly))


def paint_part(area, clip: Polygon, cls: str, part_id: str, z: float,
               color=None) -> MeshPart | None:
    area = as_area(shapely.intersection(area, clip))
    if area.is_empty:
        return None
    v, f = flat_mesh(area, z)
    if len(f) == 0:
        return None
    return MeshPart(v, f, cls, part_id, color=color)


def road_line_part(line_id, points, kind, color, double, clip, road_z,
                   st: MarkingStyle = MarkingStyle()):
    return paint_part(road_line_area(points, kind, double, st, within=clip.bounds), clip,
                      LANE_MARKING, line_id, road_z + st.lift, PAINT.get(color))


def stop_line_part(line_id, points, clip, road_z, st: MarkingStyle = MarkingStyle()):
    return paint_part(ribbon(points, st.stop_line_width / 2,
                             within=grow(clip.bounds, st.stop_line_width)),
                      clip, LANE_MARKING, line_id, road_z + st.lift, PAINT["white"])


def crosswalk_part(cw_id, polygon, clip, road_z, st: MarkingStyle = MarkingStyle()):
    return paint_part(crosswalk_area(polygon, st), clip, CROSSWALK, cw_id, road_z + st.lift)
