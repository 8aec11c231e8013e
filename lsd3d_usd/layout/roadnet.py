"""The road network the generator's blocks plug into: roads (edges between nodes), the arms
of a node, lane naming, and small geometry helpers shared by the generator and the block types.

A road runs straight from node a to node b; its lanes are cut into pieces at chunk borders.
A block sits at a node and attaches to each road through an *arm* (the road seen from the
node); the arm's ``cut`` is how far from the node the straight road starts (the socket).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from shapely.geometry import box as shp_box
from shapely.geometry.polygon import orient

from lsd3d_usd.layout import blocks as B
from lsd3d_usd.layout import model as m

MAX_BLOCK_REACH = 36.0  # a block stays within this distance of its node (node ≥ 40 m from borders)
CROSSWALK_DEPTH = 3.0
STOP_GAP = 4.5          # from junction boundary to where lane lines start


@dataclass
class Edge:
    """A straight road from node a to node b with one cross-section."""
    key: str
    a: str
    b: str
    section: B.Section
    p_a: np.ndarray            # node positions
    p_b: np.ndarray
    d: np.ndarray              # unit a→b
    s0: float = 0.0            # road starts at p_a + s0*d
    s1: float = 0.0
    pieces: list = field(default_factory=list)   # [(chunk (i, j), s_start, s_end, border_start, border_end)]
    border0: tuple | None = None   # (axis, value) of the extent border at s0, None at a node
    border1: tuple | None = None

    def s_at(self, s: float, border, lateral: float) -> float:
        """Parameter where the line at ``lateral`` meets ``border`` (axis, value); ``s`` at a node.
        Offset lines of a road crossing a border at an angle are cut on the border itself."""
        if border is None:
            return s
        axis, value = border
        return float((value - (self.p_a[axis] + lateral * B.left_normal(self.d)[axis])) / self.d[axis])

    def point(self, s: float, lateral: float = 0.0) -> np.ndarray:
        return self.p_a + s * self.d + lateral * B.left_normal(self.d)


@dataclass
class Arm:
    """A road seen from one of its end nodes."""
    edge: Edge
    direction: np.ndarray      # unit, away from the node
    section: B.Section
    at_a: bool                 # the node is the edge's a end
    cut: float = 0.0           # distance from the node where the straight road starts


def lane_id(e: Edge, piece: int, fwd: bool, k: int) -> str:
    return f"{e.key}_p{piece}_{'f' if fwd else 'b'}{k}"


def end_lanes(e: Edge, at_a: bool, incoming: bool) -> list[tuple[str, np.ndarray, float]]:
    """(lane id, end point, width) of the driving lanes at one end of a road,
    incoming = travelling toward that end. Index 0 = innermost lane."""
    piece = 0 if at_a else len(e.pieces) - 1
    s = e.s0 if at_a else e.s1
    fwd = (not at_a) if incoming else at_a
    out = []
    for k in range(e.section.lanes):
        off = e.section.lane_offset(k)
        out.append((lane_id(e, piece, fwd, k), e.point(s, -off if fwd else off), e.section.lane_width))
    return out


def line_specs(sec: B.Section) -> list[tuple[float, str, str, bool]]:
    """(lateral offset, kind, colour, double) of painted lines, in the a→b frame."""
    specs = []
    if sec.median > 0:
        specs += [(sec.median / 2, "solid", "yellow", False), (-sec.median / 2, "solid", "yellow", False)]
    elif sec.lanes >= 2:
        specs.append((0.0, "solid", "yellow", True))
    else:
        specs.append((0.0, "broken", "yellow", False))
    for k in range(1, sec.lanes):
        off = sec.median / 2 + k * sec.lane_width
        specs += [(off, "broken", "white", False), (-off, "broken", "white", False)]
    if sec.parking > 0:
        off = sec.median / 2 + sec.lanes * sec.lane_width
        specs += [(off, "solid", "white", False), (-off, "solid", "white", False)]
    return specs


def connector(lid, p0, t0, w0, p1, t1, w1, preds, succs, road_id, curve_pts=None) -> m.LaneCenter:
    """A lane inside a block from p0 to p1 (Hermite curve unless ``curve_pts`` is given);
    the width varies linearly with arc length from w0 to w1."""
    pts = curve_pts if curve_pts is not None else B.hermite(p0, t0, p1, t1)
    pts = pts.copy()
    pts[0], pts[-1] = p0, p1
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    frac = s / s[-1] if s[-1] > 0 else np.zeros_like(s)
    widths = w0 + (w1 - w0) * frac
    return m.LaneCenter(lid, points=xyz(pts), widths=widths, lane_type="driving", road_id=road_id,
                        predecessors=preds, successors=succs, is_junction=True)


def curve_or_line(node, d_in, d_out, radius, lateral, p0=None, p1=None) -> np.ndarray:
    """A lane path through a fillet curve block (a straight segment when radius is inf)."""
    if np.isinf(radius):
        u = -d_in
        s = B.left_normal(u) * lateral
        a = node + 5.0 * d_in + s if p0 is None else p0
        b = node + 5.0 * d_out + B.left_normal(d_out) * lateral if p1 is None else p1
        return np.stack([a, b])
    pts = B.curve_path(node, d_in, d_out, radius, lateral)
    if p0 is not None:
        pts[0], pts[-1] = p0, p1
    return pts


def xyz(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return np.concatenate([a, np.zeros((len(a), 1))], axis=1)


def polygons(geom) -> list[np.ndarray]:
    """Hole-free CCW polygons (implicitly closed) covering ``geom``: a polygon
    with holes is cut through each hole's centre (the layout format has no holes)."""
    out = []
    stack = list(getattr(geom, "geoms", [geom]))
    while stack:
        g = stack.pop(0)
        if g.is_empty or g.geom_type not in ("Polygon", "MultiPolygon", "GeometryCollection"):
            continue
        if g.geom_type != "Polygon":
            stack[:0] = list(g.geoms)
            continue
        if g.area < 0.05:
            continue
        if g.interiors:
            cx = g.interiors[0].centroid.x
            minx, miny, maxx, maxy = g.bounds
            left = g.intersection(shp_box(minx - 1, miny - 1, cx, maxy + 1))
            right = g.intersection(shp_box(cx, miny - 1, maxx + 1, maxy + 1))
            stack[:0] = [left, right]
            continue
        g = orient(g.simplify(0.002), 1.0)
        if g.is_empty or g.geom_type != "Polygon":
            continue
        out.append(np.asarray(g.exterior.coords)[:-1, :2])
    return out
