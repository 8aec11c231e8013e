"""Map signals and furniture as proxy solids: traffic lights, signs, poles, barriers.

These are the features a map gives (OpenDRIVE objects and signals, Lanelet2 regulatory
elements, OSM nodes); ``furniture`` holds the ones the proxy derives where the map is
silent. All compact parts are closed solids placed by ``transform_points``; a barrier is a
prism along its polyline cut at the chunk like a hedge.
"""
from __future__ import annotations

import numpy as np
import shapely

from .furniture import _placed, street_light_parts
from .mesh import BUILDING, CURB, POLE, SIGN, TRAFFIC_LIGHT, MeshPart, transform_points
from .planar import prism, ribbon
from .shapes import box, cylinder, ngon_prism

PLATE = 0.7            # m across a sign plate
MAX_ARM = 15.0         # m: a signal head farther from the roadside keeps its own mast


def _polygon(kind: str) -> np.ndarray:
    """A sign plate's outline (convex, CCW) in the plate's local (y, z) plane."""
    r = PLATE / 2
    if kind == "yield":              # triangle, point down
        a = np.radians([90.0, 210.0, 330.0]) + np.pi
    elif kind == "warning":          # triangle, point up
        a = np.radians([90.0, 210.0, 330.0])
    elif kind == "priority":         # diamond
        a = np.radians([0.0, 90.0, 180.0, 270.0])
    elif kind in ("speed_limit", "no_entry", "mandatory", "prohibition"):
        a = np.arange(16) * (2 * np.pi / 16)
    elif kind == "stop":
        a = (np.arange(8) + 0.5) * (np.pi / 4)
    else:                            # information / other: a rectangle
        return np.array([[-r, -0.6 * r], [r, -0.6 * r], [r, 0.6 * r], [-r, 0.6 * r]])
    return r * np.column_stack([np.cos(a), np.sin(a)])


def sign_parts(sign_id: str, position, facing_yaw: float, kind: str = "other",
               height: float = 2.5) -> list[MeshPart]:
    """A pole and a plate (shape by ``kind``) whose top is ``height`` above the ground,
    facing ``facing_yaw``."""
    height = max(float(height), PLATE + 0.3)
    centre = height - PLATE / 2
    pv, pf = cylinder(0.04, 0.0, centre, segments=6)
    sv, sf = ngon_prism(_polygon(kind), -0.015, 0.015)       # (y, z, x) before the swap
    sv = sv[:, [2, 0, 1]] + np.array([0.06, 0.0, centre])    # a rotation (even permutation)
    return [_placed(pv, pf, POLE, f"{sign_id}/pole", facing_yaw, position),
            _placed(sv, sf, SIGN, f"{sign_id}/plate", facing_yaw, position)]


def signal_parts(light_id: str, mast_xy, head_xy, facing_yaw: float, height: float = 5.5
                 ) -> list[MeshPart]:
    """A traffic light: a mast at ``mast_xy`` and a 1 m head whose top is ``height`` above
    the ground at ``head_xy``, facing ``facing_yaw``; an arm joins the mast to a head that
    hangs away from it (over the road)."""
    height = max(float(height), 2.5)
    mast = np.asarray(mast_xy, dtype=np.float64)[:2]
    head = np.asarray(head_xy, dtype=np.float64)[:2]
    d = head - mast
    reach = float(np.hypot(*d))
    hv, hf = box(0.3, 0.35, height - 1.0, height)
    parts = [MeshPart(transform_points(hv, facing_yaw, (head[0], head[1], 0.0)), hf,
                      TRAFFIC_LIGHT, f"{light_id}/head", solid=True)]
    if reach < 0.3:                  # the head on top of its mast, just behind it
        mv, mf = cylinder(0.09, 0.0, height - 1.0, segments=8)
        parts.append(_placed(mv, mf, POLE, f"{light_id}/mast", facing_yaw, head))
        return parts
    mv, mf = cylinder(0.09, 0.0, height + 0.1, segments=8)
    av, af = box(reach, 0.12, height - 0.05, height + 0.1)
    av = av + np.array([reach / 2, 0.0, 0.0])
    arm_yaw = float(np.arctan2(d[1], d[0]))
    parts += [_placed(mv, mf, POLE, f"{light_id}/mast", 0.0, mast),
              _placed(av, af, POLE, f"{light_id}/arm", arm_yaw, mast)]
    return parts


def pole_parts(pole_id: str, position, kind: str = "pole", height: float = 6.0,
               yaw: float = 0.0) -> list[MeshPart]:
    """A plain pole (8-sided, 7 cm), a street lamp (``furniture.street_light_parts`` scaled
    to ``height``, its arm towards ``yaw``) or a bollard (1 m or ``height``, 10 cm)."""
    if kind == "street_lamp":
        parts = street_light_parts(pole_id, position, yaw)
        s = float(height) / 7.0
        if abs(s - 1.0) > 1e-9:
            p0 = np.array([position[0], position[1], 0.0])
            for p in parts:
                p.vertices = p0 + (p.vertices - p0) * np.array([1.0, 1.0, s])
        return parts
    r = 0.1 if kind == "bollard" else 0.07
    v, f = cylinder(r, 0.0, float(height), segments=8)
    return [_placed(v, f, POLE, pole_id, yaw, position)]


BARRIER_CLASS = {"wall": BUILDING, "jersey": CURB}    # others (fence, guard rail, railing): pole


def barrier_part(barrier_id: str, points: np.ndarray, kind: str, height: float, width: float,
                 clip=None) -> MeshPart | None:
    """A barrier as a closed prism of its thickness along its polyline, cut at ``clip``
    (the chunk box) like a hedge: walls are ``building``, jersey barriers ``curb``, fences,
    guard rails and railings ``pole`` (the metal street furniture class)."""
    area = ribbon(points, max(float(width), 0.02) / 2,
                  within=None if clip is None else clip.bounds)
    if clip is not None:
        area = shapely.intersection(area, clip)
    v, f = prism(area, 0.0, float(height))
    if len(f) == 0:
        return None
    return MeshPart(v, f, BARRIER_CLASS.get(kind, POLE), barrier_id, solid=True)
