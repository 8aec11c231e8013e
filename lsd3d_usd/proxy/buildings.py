"""Buildings from footprints: manifold3d extrusion, floors, window recesses, roofs.

A building is one closed solid: the footprint extruded to the eave height,
window recesses cut into every façade (one batched boolean per building —
the only place the proxy uses booleans besides roofs) and a roof that is flat
(with a parapet), gable or hip. Booleans run in a local frame centred on the
footprint because manifold3d meshes are float32.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import Polygon

from lsd3d_usd.configtree import option

from .mesh import BUILDING, MeshPart, drop_degenerate
from .planar import area_from_points, polygons_of

ROOFS = ("flat", "gable", "hip")


@dataclass(frozen=True)
class BuildingStyle:
    floor_height: float = option(3.2, help="floor height where the layout gives no floor "
                                           "count (m)", lo=1.0, hi=50.0)
    window_width: float = option(1.2, help="window width (m)", lo=0.0)
    window_height: float = option(1.5, help="window height (m)", lo=0.0)
    window_spacing: float = option(3.0,
                                   help="window spacing, centre to centre along a façade (m)", lo=0.0)
    window_depth: float = option(0.25, help="window recess depth (m)", lo=0.0)
    window_margin: float = option(0.8,
                                  help="windows keep this far from façade corners (m)", lo=0.0)
    parapet_height: float = option(0.6, help="parapet height of flat roofs (m)", lo=0.0)
    parapet_width: float = option(0.3, help="parapet width (m)", lo=0.0)
    max_roof_height: float = option(4.0, help="largest gable / hip roof height (m)", lo=0.0)
    windows: bool = option(True, help="window recesses in the façades (off: plain blocks, faster)")


def stable_unit(key: str, salt: str = "") -> float:
    """A deterministic number in [0, 1) from a string (for per-object variation)."""
    h = hashlib.blake2b(f"{salt}:{key}".encode(), digest_size=8).digest()
    return int.from_bytes(h, "little") / 2.0 ** 64


def choose_roof(building_id: str, footprint: Polygon) -> str:
    """Flat unless the footprint is a rectangle; then a stable choice from the id."""
    if not is_rectangle(footprint):
        return "flat"
    u = stable_unit(building_id, "roof")
    return "flat" if u < 0.5 else ("gable" if u < 0.75 else "hip")


def is_rectangle(poly: Polygon, tol: float = 0.01) -> bool:
    """Footprint fills its minimum rotated rectangle (within ``tol`` of the area)."""
    rect = poly.minimum_rotated_rectangle
    return bool(poly.is_valid and rect.area > 0 and poly.area / rect.area > 1.0 - tol)


def _cross_section(poly: Polygon):
    # local import: not loaded for --help
    import manifold3d as m
    poly = shapely.orient_polygons(poly, exterior_cw=False)
    contours = [np.asarray(poly.exterior.coords)[:-1, :2]]
    contours += [np.asarray(r.coords)[:-1, :2] for r in poly.interiors]
    return m.CrossSection([np.ascontiguousarray(c, dtype=np.float64) for c in contours],
                          m.FillRule.Positive)


def _extrude(cs, z0: float, z1: float):
    # local import: not loaded for --help
    import manifold3d as m
    return m.Manifold.extrude(cs, z1 - z0).translate((0.0, 0.0, z0))


def _rect_frame(poly: Polygon):
    """Centre, unit long axis, half long side, half short side of the min rotated rectangle."""
    r = np.asarray(poly.minimum_rotated_rectangle.exterior.coords)[:4]
    e0, e1 = r[1] - r[0], r[2] - r[1]
    if np.linalg.norm(e0) < np.linalg.norm(e1):
        e0, e1 = e1, e0
    a, b = np.linalg.norm(e0) / 2, np.linalg.norm(e1) / 2
    return r.mean(0), e0 / (2 * a), a, b


def _box(center, axis_u, size_u, size_v, z0, z1):
    """Box with its u side along unit 2D ``axis_u``."""
    # local import: not loaded for --help
    import manifold3d as m
    ang = np.degrees(np.arctan2(axis_u[1], axis_u[0]))
    return (m.Manifold.cube((size_u, size_v, z1 - z0), center=True)
            .rotate((0.0, 0.0, float(ang)))
            .translate((float(center[0]), float(center[1]), 0.5 * (z0 + z1))))


def _windows(poly: Polygon, floors: int, floor_h: float, st: BuildingStyle):
    """One manifold holding every window recess box (unioned in one batch)."""
    # local import: not loaded for --help
    import manifold3d as m
    boxes = []
    wh = min(st.window_height, 0.55 * floor_h)
    rings = [np.asarray(shapely.orient_polygons(poly, exterior_cw=False).exterior.coords)]
    for ring in rings:
        for p, q in zip(ring[:-1], ring[1:]):
            d = q - p
            L = float(np.hypot(*d))
            usable = L - 2 * st.window_margin
            n = int(usable // st.window_spacing) if usable >= st.window_width else 0
            if n <= 0:
                continue
            u = d / L
            out = np.array([u[1], -u[0]])          # CCW ring: outside is to the right
            offs = (np.arange(n) - (n - 1) / 2) * st.window_spacing
            for f in range(floors):
                z0 = f * floor_h + 0.5 * (floor_h - wh)
                for o in offs:
                    c = p + d / 2 + u * o + out * (0.5 * (0.2 - st.window_depth))
                    boxes.append(_box(c, u, st.window_width, st.window_depth + 0.2, z0, z0 + wh))
    if not boxes:
        return None
    return m.Manifold.batch_boolean(boxes, m.OpType.Add)


def _pitched_body(poly: Polygon, kind: str, h: float, st: BuildingStyle):
    """Walls + gable/hip roof of a rectangular footprint as one convex hull (no boolean:
    a hull of the exact corner points is cleaner than intersecting a roof with a prism)."""
    # local import: not loaded for --help
    import manifold3d as m
    c, u, a, b = _rect_frame(poly)
    v = np.array([-u[1], u[0]])
    rh = min(st.max_roof_height, 0.7 * b)
    corners = [c + u * su * a + v * sv * b for su in (-1, 1) for sv in (-1, 1)]
    pts = [(*p, 0.0) for p in corners] + [(*p, h) for p in corners]
    if kind == "gable":
        pts += [(*(c + u * a), h + rh), (*(c - u * a), h + rh)]
    else:  # hip: equal slopes on all four sides, ridge shortened by the half width
        ridge = max(a - b, 0.0)
        pts += ([(*(c + u * ridge), h + rh), (*(c - u * ridge), h + rh)] if ridge > 1e-3
                else [(*c, h + rh)])
    return m.Manifold.hull_points(np.asarray(pts, dtype=np.float64))


def building_mesh(building_id: str, footprint_xy: np.ndarray, height: float, floors: int = 0,
                  roof: str | None = None, style: BuildingStyle = BuildingStyle()
                  ) -> MeshPart | None:
    """Closed building solid from a footprint (N, 2) polygon, eave ``height`` in metres."""
    polys = [g for g in polygons_of(area_from_points(footprint_xy)) if g.area > 0.5]
    if not polys:
        return None
    poly = max(polys, key=lambda g: g.area)        # a self-touching footprint keeps its main part
    origin = np.asarray(poly.centroid.coords[0])
    local = _translate(poly, -origin)
    floors = int(floors) if floors and floors > 0 else max(1, int(round(height / style.floor_height)))
    floor_h = height / floors
    roof = roof or choose_roof(building_id, local)
    if roof != "flat" and not is_rectangle(local):
        roof = "flat"                               # pitched roofs need a rectangle
    cs = _cross_section(local)
    if roof == "flat":
        body = _extrude(cs, 0.0, height + style.parapet_height)
        inner = cs.offset(-style.parapet_width)
        if not inner.is_empty():
            body = body - _extrude(inner, height, height + style.parapet_height + 1.0)
    else:
        body = _pitched_body(local, roof, height, style)
    solid = body
    if style.windows:
        win = _windows(local, floors, floor_h, style)
        if win is not None:
            solid = body - win
    v, f = _to_arrays(solid)
    if style.windows and (len(f) == 0 or len(drop_degenerate(v, f)) < len(f)):
        v, f = _to_arrays(body)                     # rare boolean slivers: keep the plain body
    if len(f) == 0:
        return None
    v = v + np.array([origin[0], origin[1], 0.0])
    return MeshPart(v, f, BUILDING, f"{building_id}", solid=True)


def _to_arrays(solid):
    # booleans can leave needle slivers; simplify collapses most of them and stays manifold
    mesh = solid.simplify(1e-4).to_mesh64()
    return (np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3].copy(),
            np.asarray(mesh.tri_verts, dtype=np.int64).copy())


def _translate(poly: Polygon, d) -> Polygon:
    return affinity.translate(poly, float(d[0]), float(d[1]))
