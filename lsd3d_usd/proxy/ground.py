"""The ground of a chunk as a planar partition: road, curb, sidewalk, vegetation, terrain.

Within a chunk box the five areas are disjoint and their union is the whole
box, so neighbouring chunks meet without gaps or double cover: every area is
computed from the features around the chunk (box + margin) and only then cut
at the box, exactly on the border line.

Heights (flat ground; layout z is not used): terrain and vegetation patches at
0, the road surface at ``road_z`` (slightly above, an open surface), curbs
and sidewalks as closed prisms up to ``road_z + curb_height``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon, box
from shapely.geometry.base import BaseGeometry

from lsd3d_usd.configtree import option
from .mesh import CURB, ROAD, SIDEWALK, TERRAIN, VEGETATION, MeshPart
from .planar import area_from_points, as_area, flat_mesh, polygons_of, prism, ribbon

NOT_ROAD_LANES = ("sidewalk", "border")


@dataclass(frozen=True)
class GroundStyle:
    road_z: float = option(0.02, help="road surface height above the terrain (m)", lo=0.0)
    curb_height: float = option(0.15,
                                help="curb / sidewalk top above the road surface (m)", lo=0.0)
    curb_width: float = option(0.3, help="curb width (m)", lo=0.0)
    sidewalk_width: float = option(3.0, help="width of the sidewalks derived where the layout "
                                             "has none (m)", lo=0.0)
    derive_sidewalks: bool = option(True,
                                    help="derive sidewalks along roads where the layout has none")
    terrain_cell: float = option(10.0, help="terrain cell size: the ground grid that keeps "
                                            "triangles even (m)", lo=0.5, hi=1000.0)


def _union(geoms) -> Polygon:
    geoms = [g for g in geoms if g is not None and not g.is_empty]
    if not geoms:
        return Polygon()
    return as_area(shapely.union_all(np.array(geoms, dtype=object)))


def _grown(area, distance: float, **style) -> BaseGeometry:
    """``area``.buffer(distance, **style); an area whose GEOS buffer meets an invalid or
    zero division (a valid sliver ribbon 4e-6 m thick with two vertices 1e-21 m apart: NaN
    coordinates and a RuntimeWarning) is grown again from its copy on a 1 nm grid."""
    with np.errstate(invalid="raise", divide="raise"):
        try:
            return area.buffer(distance, **style)
        except FloatingPointError:
            return shapely.set_precision(area, 1e-9).buffer(distance, **style)


def ground_areas(chunk_box: tuple[float, float, float, float], margin: float,
                 lanes: list[tuple[np.ndarray, np.ndarray, str]],
                 road_areas: list[np.ndarray] = (), sidewalks: list[np.ndarray] = (),
                 vegetation: list[np.ndarray] = (), buildings: list[np.ndarray] = (),
                 style: GroundStyle = GroundStyle(),
                 extent: tuple[float, float, float, float] | None = None) -> dict[str, Polygon]:
    """Disjoint areas {road, curb, sidewalk, vegetation, terrain} covering ``chunk_box``.

    lanes: (points (N, 2|3), full widths (N,), lane_type). Polygons are (N, 2|3)
    arrays, or areas already cleaned by ``planar.area_from_points``. Everything may extend beyond the box; pass all features within
    ``margin`` of it so the result near the border does not depend on the chunk.
    ``extent`` (the layout's area): roads leaving it get no curb across their cut end.
    """
    x0, y0, x1, y1 = chunk_box
    cbox = box(x0, y0, x1, y1)
    big = box(x0 - margin, y0 - margin, x1 + margin, y1 + margin)
    road_parts, walk_parts = [], []
    for pts, widths, lane_type in lanes:
        rib = ribbon(pts, np.asarray(widths, dtype=np.float64) / 2, within=big.bounds)
        (walk_parts if lane_type == "sidewalk" else
         road_parts if lane_type not in NOT_ROAD_LANES else []).append(rib)
    road_parts += [_poly(p) for p in road_areas]
    R = shapely.intersection(_union(road_parts), big)
    # the curb rings every road boundary (junction mouths are inside the union, so none there)
    C = as_area(shapely.difference(_grown(R, style.curb_width, quad_segs=2, join_style="mitre"), R))
    if extent is not None:
        # a road cut at the layout's edge continues beyond it: no curb across its end
        inner = box(*extent).buffer(-1.5 * style.curb_width, join_style="mitre")
        C = as_area(shapely.intersection(C, inner))
    blocked = _union([R, C])
    walk = [_poly(p) for p in sidewalks] + walk_parts
    if not sidewalks and style.derive_sidewalks and not R.is_empty:
        derived = _grown(R, style.curb_width + style.sidewalk_width, quad_segs=4)
        if extent is not None:   # a road cut at the extent continues: no walk around its end
            derived = shapely.intersection(derived, box(*extent))
        walk.append(derived)
    houses = _union([_poly(p) for p in buildings])
    S = as_area(shapely.difference(_union(walk), _union([blocked, houses])))
    blocked = _union([blocked, S])
    V = as_area(shapely.difference(_union([_poly(p) for p in vegetation]), blocked))
    out = {ROAD: R, CURB: C, SIDEWALK: S, VEGETATION: V}
    out = {k: as_area(shapely.intersection(g, cbox)) for k, g in out.items()}
    out[TERRAIN] = as_area(shapely.difference(cbox, _union(list(out.values()))))
    return out


def _poly(p) -> Polygon:
    # an already cleaned area (the chunk builder cleans a feature's polygon once) as it is
    return p if isinstance(p, BaseGeometry) else area_from_points(p)


def _grid_cells(geom: Polygon, cell: float) -> list[Polygon]:
    if geom.is_empty or cell <= 0:
        return polygons_of(geom)
    x0, y0, x1, y1 = geom.bounds
    gx = np.arange(np.floor(x0 / cell), np.ceil(x1 / cell)) * cell
    gy = np.arange(np.floor(y0 / cell), np.ceil(y1 / cell)) * cell
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    cells = shapely.box(X.ravel(), Y.ravel(), X.ravel() + cell, Y.ravel() + cell)
    return polygons_of(shapely.GeometryCollection(list(shapely.intersection(cells, geom))))


def ground_parts(areas: dict[str, Polygon], chunk_name: str,
                 style: GroundStyle = GroundStyle()) -> list[MeshPart]:
    """Meshes of the ground areas; ids ``ground/<class>/<chunk>``."""
    top = style.road_z + style.curb_height
    parts = []
    for cls, geom in areas.items():
        if geom.is_empty:
            continue
        pid = f"ground/{cls}/{chunk_name}"
        if cls in (CURB, SIDEWALK):
            v, f = prism(geom, 0.0, top)
            solid = True
        elif cls == TERRAIN:
            v, f = flat_mesh(shapely.GeometryCollection(_grid_cells(geom, style.terrain_cell)), 0.0)
            solid = False
        else:
            v, f = flat_mesh(geom, style.road_z if cls == ROAD else 0.0)
            solid = False
        if len(f):
            parts.append(MeshPart(v, f, cls, pid, solid=solid))
    return parts
