"""OpenDRIVE lane addresses on an imported layout: `lane_position` maps (road id, lane id,
s, offset) to a world pose through the lane index the OpenDRIVE importer keeps in the
layout's metadata ("opendrive_lanes": per layout lane its road, lane id, direction and the
road's s at each vertex). Between vertices the lane centre is interpolated on the circle
through three neighbouring vertices, which is exact for lines and arcs."""
from __future__ import annotations

import bisect
import math

import numpy as np

from lsd3d_usd.errors import InputError


class LaneIndex:
    """(road id, lane id) -> the layout lanes made from it, each with its s range."""

    def __init__(self, layout):
        meta = layout.metadata.get("opendrive_lanes") or {}
        feats = {ln.id: ln for ln in layout.lanes}
        self.by_lane: dict[tuple[str, int], list] = {}
        self.of_layout_lane: dict[str, tuple[str, int]] = {}
        for lid, info in meta.items():
            ln = feats.get(lid)
            if ln is None:
                continue
            pts = np.asarray(ln.points, np.float64)
            if not info["forward"]:
                pts = pts[::-1]
            s = np.asarray(info["s"], np.float64)
            if len(s) != len(pts):
                continue
            key = (str(info["road"]), int(info["lane"]))
            self.by_lane.setdefault(key, []).append((float(s[0]), float(s[-1]), s, pts, lid, info["forward"]))
            self.of_layout_lane[lid] = key
        for v in self.by_lane.values():
            v.sort(key=lambda r: r[0])

    def find(self, road_id: str, lane_id: int, s: float):
        parts = self.by_lane.get((str(road_id), int(lane_id)))
        if not parts:
            if not self.by_lane:
                raise InputError("the layout keeps no OpenDRIVE lane index (import the OpenDRIVE "
                                 "file with this version: lsd3d-usd layout import / scenario build)")
            roads = sorted({r for r, _ in self.by_lane})
            lanes = sorted(l for r, l in self.by_lane if r == str(road_id))
            hint = f"road {road_id} has lanes {lanes}" if lanes else f"roads: {', '.join(roads[:12])}"
            raise InputError(f"LanePosition road {road_id} lane {lane_id}: no such lane ({hint})")
        for p in parts:
            if p[0] - 1e-6 <= s <= p[1] + 1e-6:
                return p
        lo, hi = parts[0][0], parts[-1][1]
        raise InputError(f"LanePosition road {road_id} lane {lane_id}: s={s:g} is outside the "
                         f"lane's [{lo:g}, {hi:g}]")


def _index(layout) -> LaneIndex:
    idx = getattr(layout, "_scenario_lane_index", None)
    if idx is None:
        idx = LaneIndex(layout)
        layout._scenario_lane_index = idx
    return idx


def _circle_point(a, b, c, which: int, u: float):
    """Point a fraction u along the arc from vertex ``which`` (0: a->b, 1: b->c) of the circle
    through a, b, c (2D), and its tangent angle; None when the three are collinear."""
    ax, ay = a
    bx, by = b
    cx, cy = c
    d = 2 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    span = max(math.hypot(bx - ax, by - ay), math.hypot(cx - bx, cy - by))
    if abs(d) < 1e-9 * span * span:
        return None
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    ox = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
    oy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    r = math.hypot(ax - ox, ay - oy)
    if r > 1e7:
        return None
    p, q = (a, b) if which == 0 else (b, c)
    t0 = math.atan2(p[1] - oy, p[0] - ox)
    t1 = math.atan2(q[1] - oy, q[0] - ox)
    dt = (t1 - t0 + math.pi) % (2 * math.pi) - math.pi
    t = t0 + u * dt
    x, y = ox + r * math.cos(t), oy + r * math.sin(t)
    yaw = t + (math.pi / 2 if dt > 0 else -math.pi / 2)
    return x, y, yaw


def lane_position(layout, road_id, lane_id: int, s: float, offset: float = 0.0):
    """(x, y, z, heading) of OpenSCENARIO's LanePosition on a layout imported from OpenDRIVE:
    the lane centre at the road's ``s``, ``offset`` m to the left of the road's s direction
    (OpenSCENARIO's t sense); heading along the lane's driving direction."""
    s_lo, s_hi, sv, pts, _, forward = _index(layout).find(road_id, lane_id, float(s))
    j = min(max(bisect.bisect_right(sv.tolist(), s) - 1, 0), len(sv) - 2)
    ds = sv[j + 1] - sv[j]
    u = (s - sv[j]) / ds if ds > 0 else 0.0
    z = float(pts[j, 2] + u * (pts[j + 1, 2] - pts[j, 2]))
    res = None
    if len(pts) >= 3:
        if j + 2 < len(pts):
            res = _circle_point(pts[j, :2], pts[j + 1, :2], pts[j + 2, :2], 0, u)
        else:
            res = _circle_point(pts[j - 1, :2], pts[j, :2], pts[j + 1, :2], 1, u)
    if res is None:
        x = float(pts[j, 0] + u * (pts[j + 1, 0] - pts[j, 0]))
        y = float(pts[j, 1] + u * (pts[j + 1, 1] - pts[j, 1]))
        yaw = math.atan2(pts[j + 1, 1] - pts[j, 1], pts[j + 1, 0] - pts[j, 0])
    else:
        x, y, yaw = res
    x, y = x - math.sin(yaw) * offset, y + math.cos(yaw) * offset
    if not forward:
        yaw += math.pi
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    return x, y, z, yaw


def layout_lane(layout, road_id, lane_id: int, s: float) -> tuple[str, float]:
    """The layout lane id holding (road, lane, s) and the arc length along it in its
    direction of travel (for the lane graph)."""
    s_lo, s_hi, sv, pts, lid, forward = _index(layout).find(road_id, lane_id, float(s))
    seg = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    a = float(np.interp(s, sv, cum))
    return lid, (a if forward else float(cum[-1] - a))


def opendrive_lane_of(layout, lane: str) -> tuple[str, int] | None:
    """(road id, OpenDRIVE lane id) a layout lane was made from, None when not imported."""
    return _index(layout).of_layout_lane.get(lane)


def road_s(layout, lane: str, arc: float) -> tuple[str, int, float] | None:
    """(road id, OpenDRIVE lane id, road s) at arc length ``arc`` (direction of travel)
    along layout lane ``lane``; None when the lane was not imported from OpenDRIVE."""
    idx = _index(layout)
    key = idx.of_layout_lane.get(lane)
    if key is None:
        return None
    for s0, s1, sv, pts, lid, forward in idx.by_lane[key]:
        if lid == lane:
            seg = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
            cum = np.concatenate([[0.0], np.cumsum(seg)])
            a = arc if forward else float(cum[-1]) - arc
            return key[0], key[1], float(np.interp(a, cum, sv))
    return None
