"""Vegetation: trees (trunk + crown), hedges (clipped prisms), zone patches with shrubs."""
from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon

from .buildings import stable_unit
from .mesh import VEGETATION, MeshPart, transform_points
from .planar import prism, ribbon
from .shapes import cylinder, ellipsoid


def tree_parts(tree_id: str, position, height: float = 8.0, crown_radius: float = 2.5
               ) -> list[MeshPart]:
    """A tree as two closed solids: an 8-sided trunk and an ellipsoidal crown."""
    height = max(float(height), 1.5)
    r = max(min(float(crown_radius), 0.45 * height), 0.3)
    crown_h = min(2.4 * r, 0.75 * height)           # crown height (ellipsoid z extent)
    trunk_top = height - crown_h * 0.85             # the crown overlaps the trunk top
    pos = np.array([position[0], position[1], 0.0])
    yaw = 2 * np.pi * stable_unit(tree_id, "yaw")
    tv, tf = cylinder(max(0.06 * r + 0.08, 0.1), 0.0, trunk_top, segments=8)
    cv, cf = ellipsoid(r, r, crown_h / 2, subdivisions=1)
    cv = cv + np.array([0.0, 0.0, height - crown_h / 2])
    return [MeshPart(transform_points(tv, yaw, pos), tf, VEGETATION, f"{tree_id}/trunk", solid=True),
            MeshPart(transform_points(cv, yaw, pos), cf, VEGETATION, f"{tree_id}/crown", solid=True)]


def hedge_part(hedge_id: str, points: np.ndarray, height: float, width: float,
               clip: Polygon | None = None) -> MeshPart | None:
    """A hedge as a closed prism along its polyline, cut at ``clip`` (the chunk box)."""
    area = ribbon(points, width / 2, within=None if clip is None else clip.bounds)
    if clip is not None:
        area = shapely.intersection(area, clip)
    v, f = prism(area, 0.0, height)
    if len(f) == 0:
        return None
    return MeshPart(v, f, VEGETATION, f"{hedge_id}", solid=True)


def zone_shrubs(zone_id: str, polygon: Polygon, kind: str, owner: Polygon) -> list[MeshPart]:
    """Shrubs / trees scattered in a vegetation zone on a jittered grid (stable per zone).

    Only positions inside ``owner`` (the chunk box) are emitted, so each plant
    belongs to exactly one chunk.
    """
    spacing = {"grass": 0.0, "park": 14.0, "shrub": 6.0, "forest": 7.0}.get(kind, 0.0)
    if spacing <= 0 or polygon.is_empty:
        return []
    region = shapely.intersection(polygon.buffer(-1.0), owner)
    if region.is_empty:
        return []
    x0, y0, x1, y1 = region.bounds
    # the grid is anchored at the world origin so it does not depend on the chunk
    gx = np.arange(np.floor(x0 / spacing), np.ceil(x1 / spacing) + 1) * spacing
    gy = np.arange(np.floor(y0 / spacing), np.ceil(y1 / spacing) + 1) * spacing
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    out = []
    for x, y in zip(X.ravel(), Y.ravel()):
        key = f"{zone_id}/{int(round(x / spacing))}_{int(round(y / spacing))}"
        p = np.array([x + (stable_unit(key, "jx") - 0.5) * spacing * 0.7,
                      y + (stable_unit(key, "jy") - 0.5) * spacing * 0.7])
        if not shapely.contains_xy(region, p[0], p[1]):
            continue
        u = stable_unit(key, "size")
        if kind == "shrub":
            v, f = ellipsoid(0.8 + 0.8 * u, 0.8 + 0.8 * u, 0.6 + 0.5 * u)
            v = v + np.array([p[0], p[1], 0.5 + 0.4 * u])
            out.append(MeshPart(v, f, VEGETATION, f"{key}/shrub", solid=True))
        else:
            out += tree_parts(key, p, 6.0 + 8.0 * u, 2.0 + 1.5 * u)
    return out
