"""Read and write the layout layer (``/World/Layout``) — the USD edge of the layout model.

Format (full reference in docs/layout.md):

- Every feature prim carries ``lsd3d:featureType`` (token): LaneCenter, RoadLine,
  RoadEdge, Crosswalk, StopLine, StopSign, Building, Tree, Hedge,
  VegetationZone, ParkingSpot, Sidewalk, RoadArea, TrafficLight, TrafficSign, Pole,
  Barrier. Prims without it are
  ignored (so a layout may hold helper prims); the reader walks everything
  under /World/Layout, the grouping scopes the writer makes are optional.
- Polylines are linear, non-periodic ``BasisCurves``; polygons are linear,
  periodic (closed) ``BasisCurves``; trees, stop signs, traffic lights, traffic
  signs and poles are ``Points``.
- ``points`` is float32 (USD's ``point3f[]``). For a lossless float64 round
  trip the writer adds ``lsd3d:points64`` (``point3d[]``) and, for lanes,
  ``lsd3d:widths64``; the reader uses a float64 copy only while it still
  rounds to the authored float32 ``points``/``widths``, so editing ``points``
  in any USD tool wins over a stale copy.
- The feature id is the prim name, or ``lsd3d:id`` when the id is not a
  valid prim name (OpenDRIVE ids like ``12_0_-1``).
- Layout-wide data (extent, chunk size, generator description, source file)
  lives in the layer's customLayerData under ``lsd3dLayout``; provenance under
  ``lsd3d`` (scene.save_stage).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, Vt

import lsd3d_usd  # noqa: F401  (schema registration before any stage opens)
from lsd3d_usd.assetroots import check_scene
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import model as m
from lsd3d_usd.limits import (CHUNK_SIZE_MAX, CHUNK_SIZE_MIN, COORDINATE, FEATURE_POINTS,
                              LAYOUT_EXTENT, LAYOUT_POINTS)
from lsd3d_usd.scene import LAYOUT_PATH, WORLD, new_stage, open_stage, save_stage

NS = "lsd3d:"
LAYER_DATA_KEY = "lsd3dLayout"

# Scope each feature type is written under (reading ignores scopes).
GROUP = {
    "LaneCenter": "Lanes", "RoadLine": "RoadLines", "RoadEdge": "RoadEdges",
    "Crosswalk": "Crosswalks", "StopLine": "StopLines", "StopSign": "StopSigns",
    "Building": "Buildings", "Tree": "Vegetation", "Hedge": "Vegetation",
    "VegetationZone": "Vegetation", "ParkingSpot": "Parking", "Sidewalk": "Sidewalks",
    "RoadArea": "RoadAreas", "TrafficLight": "Signals", "TrafficSign": "Signals",
    "Pole": "Furniture", "Barrier": "Furniture",
}
POLYGON_TYPES = {"Crosswalk", "Building", "VegetationZone", "ParkingSpot", "Sidewalk", "RoadArea"}
POINT_TYPES = {"Tree", "StopSign", "TrafficLight", "TrafficSign", "Pole"}
SINGLE_POINT_TYPES = POINT_TYPES - {"Tree"}     # exactly one point per prim

# usdview display colours (linear RGB) and display widths of non-lane curves (m).
COLOR = {
    "LaneCenter": (0.25, 0.35, 0.55), "RoadLine": (0.95, 0.95, 0.95), "RoadEdge": (0.8, 0.15, 0.1),
    "Crosswalk": (0.9, 0.9, 0.3), "StopLine": (0.95, 0.95, 0.95), "StopSign": (0.9, 0.05, 0.05),
    "Building": (0.8, 0.5, 0.25), "Tree": (0.1, 0.6, 0.15), "Hedge": (0.15, 0.45, 0.1),
    "VegetationZone": (0.3, 0.7, 0.2), "ParkingSpot": (0.4, 0.4, 0.8), "Sidewalk": (0.6, 0.6, 0.6),
    "RoadArea": (0.3, 0.3, 0.3), "TrafficLight": (0.1, 0.8, 0.2), "TrafficSign": (0.2, 0.3, 0.9),
    "Pole": (0.5, 0.5, 0.5), "Barrier": (0.6, 0.45, 0.3),
}
YELLOW = (0.95, 0.8, 0.1)
DISPLAY_WIDTH = 0.15

T = Sdf.ValueTypeNames


# ======================================================================= write

def layout_to_stage(layout: m.Layout) -> Usd.Stage:
    """An in-memory stage holding ``layout`` under /World/Layout."""
    stage = new_stage()
    layer = stage.GetRootLayer()
    with Sdf.ChangeBlock():
        _write_layer(layer, layout)
    return stage


def write_layout(layout: m.Layout, path: str | Path, provenance: dict | None = None) -> Path:
    """Write ``layout`` as a layout layer at ``path`` (atomic; .usda/.usdc by extension)."""
    stage = layout_to_stage(layout)
    return save_stage(stage, path, provenance)


def _write_layer(layer: Sdf.Layer, layout: m.Layout) -> None:
    world = layer.GetPrimAtPath(WORLD)
    root = Sdf.PrimSpec(world, Sdf.Path(LAYOUT_PATH).name, Sdf.SpecifierDef, "Scope")
    root.documentation = "lsd3d-usd map layout (see docs/layout.md)"
    groups: dict[str, Sdf.PrimSpec] = {}
    used: dict[str, set[str]] = {}

    def group(ftype: str) -> Sdf.PrimSpec:
        g = GROUP[ftype]
        if g not in groups:
            groups[g] = Sdf.PrimSpec(root, g, Sdf.SpecifierDef, "Scope")
            used[g] = set()
        return groups[g]

    for cls in m.FEATURE_CLASSES:
        ftype = cls.FEATURE_TYPE
        feats = getattr(layout, m.LIST_FOR_TYPE[ftype])
        if not feats:
            continue
        parent = group(ftype)
        if ftype == "Tree":
            _write_trees(parent, feats, used[GROUP[ftype]])
            continue
        for f in feats:
            name = _prim_name(f.id, used[GROUP[ftype]])
            _write_feature(parent, name, f)

    data = dict(layer.customLayerData)
    info: dict = {"chunkSize": float(layout.chunk_size),
                  "metadataJson": json.dumps(layout.metadata, sort_keys=True)}
    if layout.extent is not None:
        (x0, y0), (x1, y1) = layout.extent
        info["extent"] = Vt.DoubleArray([float(x0), float(y0), float(x1), float(y1)])
    data[LAYER_DATA_KEY] = info
    layer.customLayerData = data


def _prim_name(fid: str, used: set[str]) -> str:
    name = Tf.MakeValidIdentifier(fid) if fid else "feature"
    base, k = name, 1
    while name in used:
        k += 1
        name = f"{base}_{k}"
    used.add(name)
    return name


def _attr(prim: Sdf.PrimSpec, name: str, type_name, value, uniform: bool = False) -> Sdf.AttributeSpec:
    a = Sdf.AttributeSpec(prim, name, type_name,
                          Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
    a.default = value
    return a


def _vec3f(a: np.ndarray):
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))


def _vec3d(a: np.ndarray):
    return Vt.Vec3dArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float64))


def _extent(points: np.ndarray, pad: float):
    lo, hi = points.min(axis=0) - pad, points.max(axis=0) + pad
    return Vt.Vec3fArray.FromNumpy(np.stack([lo, hi]).astype(np.float32))


def _write_feature(parent: Sdf.PrimSpec, name: str, f) -> None:
    ftype = f.FEATURE_TYPE
    points_type = ftype in POINT_TYPES
    prim = Sdf.PrimSpec(parent, name, Sdf.SpecifierDef, "Points" if points_type else "BasisCurves")
    _attr(prim, NS + "featureType", T.Token, ftype, uniform=True)
    if f.id != name:
        _attr(prim, NS + "id", T.String, f.id, uniform=True)
    color = COLOR[ftype]
    if isinstance(f, m.RoadLine) and f.color == "yellow":
        color = YELLOW
    _attr(prim, "primvars:displayColor", T.Color3fArray, Vt.Vec3fArray([color]))\
        .SetInfo("interpolation", "constant")

    if points_type:
        pts = f.coords()
        _attr(prim, "points", T.Point3fArray, _vec3f(pts))
        _attr(prim, NS + "points64", T.Point3dArray, _vec3d(pts))
        _attr(prim, "widths", T.FloatArray, Vt.FloatArray([1.0])).SetInfo("interpolation", "constant")
        _attr(prim, "extent", T.Float3Array, _extent(pts, 0.5))
    else:
        pts = f.polygon() if isinstance(f, m.ParkingSpot) else f.coords()
        _attr(prim, "type", T.Token, "linear", uniform=True)
        _attr(prim, "wrap", T.Token, "periodic" if ftype in POLYGON_TYPES else "nonperiodic",
              uniform=True)
        _attr(prim, "curveVertexCounts", T.IntArray, Vt.IntArray([len(pts)]))
        _attr(prim, "points", T.Point3fArray, _vec3f(pts))
        if not isinstance(f, m.ParkingSpot):  # a spot's rectangle is derived from its fields
            _attr(prim, NS + "points64", T.Point3dArray, _vec3d(pts))
        if isinstance(f, m.LaneCenter):
            _attr(prim, "widths", T.FloatArray, Vt.FloatArray.FromNumpy(f.widths.astype(np.float32)))\
                .SetInfo("interpolation", "vertex")
            _attr(prim, NS + "widths64", T.DoubleArray, Vt.DoubleArray.FromNumpy(f.widths))
            pad = float(f.widths.max()) / 2
        else:
            w = f.width if isinstance(f, (m.Hedge, m.Barrier)) else DISPLAY_WIDTH
            _attr(prim, "widths", T.FloatArray, Vt.FloatArray([w])).SetInfo("interpolation", "constant")
            pad = w / 2
        _attr(prim, "extent", T.Float3Array, _extent(pts, pad))

    defaults = _defaults(type(f))
    for attr_name, (field_name, type_name) in SCHEMA[ftype].items():
        value = getattr(f, field_name)
        if field_name in defaults and not isinstance(value, np.ndarray) and value == defaults[field_name]:
            continue   # the reader restores model defaults; smaller, faster layers
        if type_name == T.StringArray:
            value = Vt.StringArray(list(value))
        elif type_name == T.Double3:
            value = tuple(float(v) for v in value)
        _attr(prim, NS + attr_name, type_name, value, uniform=True)


_DEFAULTS: dict = {}


def _defaults(cls) -> dict:
    """Model defaults of a feature class (field name -> value)."""
    if cls not in _DEFAULTS:
        out = {}
        for fl in dataclasses.fields(cls):
            if fl.default is not dataclasses.MISSING:
                out[fl.name] = fl.default
            elif fl.default_factory is not dataclasses.MISSING:
                out[fl.name] = fl.default_factory()
        _DEFAULTS[cls] = out
    return _DEFAULTS[cls]


def _write_trees(parent: Sdf.PrimSpec, trees: list[m.Tree], used: set[str]) -> None:
    """All trees in one Points prim: per-point ids and hints (cheap for thousands of trees)."""
    prim = Sdf.PrimSpec(parent, _prim_name("Trees", used), Sdf.SpecifierDef, "Points")
    pts = np.stack([t.position for t in trees])
    crown = np.array([t.crown_radius_hint for t in trees])
    _attr(prim, NS + "featureType", T.Token, "Tree", uniform=True)
    _attr(prim, "primvars:displayColor", T.Color3fArray, Vt.Vec3fArray([COLOR["Tree"]]))\
        .SetInfo("interpolation", "constant")
    _attr(prim, "points", T.Point3fArray, _vec3f(pts))
    _attr(prim, NS + "points64", T.Point3dArray, _vec3d(pts))
    _attr(prim, "widths", T.FloatArray, Vt.FloatArray.FromNumpy((2 * crown).astype(np.float32)))\
        .SetInfo("interpolation", "vertex")
    _attr(prim, "extent", T.Float3Array, _extent(pts, float(crown.max())))
    _attr(prim, NS + "ids", T.StringArray, Vt.StringArray([t.id for t in trees]), uniform=True)
    _attr(prim, NS + "heightHint", T.DoubleArray,
          Vt.DoubleArray.FromNumpy(np.array([t.height_hint for t in trees])), uniform=True)
    _attr(prim, NS + "crownRadiusHint", T.DoubleArray, Vt.DoubleArray.FromNumpy(crown), uniform=True)


# Per feature type: USD attribute (after lsd3d:) -> (model field, USD type). All optional
# on read (model defaults apply) except where REQUIRED says so.
SCHEMA: dict[str, dict[str, tuple[str, object]]] = {
    "LaneCenter": {
        "laneType": ("lane_type", T.Token), "direction": ("direction", T.Token),
        "speedLimit": ("speed_limit_mps", T.Double),
        "predecessors": ("predecessors", T.StringArray), "successors": ("successors", T.StringArray),
        "leftNeighbors": ("left_neighbors", T.StringArray),
        "rightNeighbors": ("right_neighbors", T.StringArray),
        "roadId": ("road_id", T.String), "isJunction": ("is_junction", T.Bool),
    },
    "RoadLine": {"kind": ("kind", T.Token), "color": ("color", T.Token), "double": ("double", T.Bool)},
    "RoadEdge": {"kind": ("kind", T.Token)},
    "Crosswalk": {}, "StopLine": {}, "Sidewalk": {}, "RoadArea": {},
    "StopSign": {"laneIds": ("lane_ids", T.StringArray)},
    "Building": {"heightHint": ("height_hint", T.Double), "floorsHint": ("floors_hint", T.Int)},
    "Hedge": {"height": ("height", T.Double), "width": ("width", T.Double)},
    "VegetationZone": {"kind": ("kind", T.Token)},
    "ParkingSpot": {"center": ("center", T.Double3), "heading": ("heading", T.Double),
                    "length": ("length", T.Double), "width": ("width", T.Double),
                    "occupied": ("occupied", T.Bool)},
    "Tree": {},
    "TrafficLight": {"heading": ("heading", T.Double), "height": ("height", T.Double),
                     "laneIds": ("lane_ids", T.StringArray)},
    "TrafficSign": {"heading": ("heading", T.Double), "kind": ("kind", T.Token),
                    "code": ("code", T.String), "value": ("value", T.Double),
                    "height": ("height", T.Double), "laneIds": ("lane_ids", T.StringArray)},
    "Pole": {"kind": ("kind", T.Token), "height": ("height", T.Double)},
    "Barrier": {"kind": ("kind", T.Token), "height": ("height", T.Double),
                "width": ("width", T.Double)},
}

# Types accepted on read for each written type (hand-authored layers use what is natural).
_ACCEPT = {
    T.Token: {T.Token, T.String},
    T.String: {T.String, T.Token},
    T.Double: {T.Double, T.Float, T.Int, T.Half},
    T.Int: {T.Int, T.Int64, T.UInt},
    T.Bool: {T.Bool},
    T.StringArray: {T.StringArray, T.TokenArray},
    T.Double3: {T.Double3, T.Float3, T.Point3d, T.Point3f, T.Vector3d, T.Vector3f},
    T.DoubleArray: {T.DoubleArray, T.FloatArray},
}


# ======================================================================== read

def read_layout(path: str | Path) -> m.Layout:
    """Read the layout under /World/Layout of the USD file (or scene folder) at ``path``."""
    stage = open_stage(path)
    check_scene(stage, path)   # a layout's sublayers outside its folder are refused
    return layout_from_stage(stage, str(path))


def layout_from_stage(stage: Usd.Stage, where: str = "stage") -> m.Layout:
    """The layout under /World/Layout of a composed stage. ``where`` names it in errors."""
    root = stage.GetPrimAtPath(LAYOUT_PATH)
    if not root or not root.IsValid():
        raise InputError(f"{where}: no {LAYOUT_PATH} prim (a layout layer defines its features "
                         f"under {LAYOUT_PATH})")
    units = _stage_units(stage, where)
    layout = m.Layout()
    _read_layer_data(stage, layout, where, units)
    total = 0
    for prim in Usd.PrimRange(root):
        attr = prim.GetAttribute(NS + "featureType")
        if not attr or not attr.HasAuthoredValue():
            if prim.GetTypeName() in ("BasisCurves", "Points"):
                raise InputError(f"{where}: {prim.GetPath()}: attribute {NS}featureType is missing "
                                 f"(one of {', '.join(m.FEATURE_CLASS_BY_TYPE)})")
            continue
        ftype = str(_get(prim, "featureType", T.Token, where))
        if ftype not in m.FEATURE_CLASS_BY_TYPE:
            raise InputError(f"{where}: {prim.GetPath()}: {NS}featureType {ftype!r} is not one of "
                             f"{', '.join(m.FEATURE_CLASS_BY_TYPE)}")
        try:
            for f in _read_prim(prim, ftype, where, units):
                layout.add(f)
                total += len(f.coords())
                if not LAYOUT_POINTS.ok(total):
                    LAYOUT_POINTS.check(total, f"{where}: {prim.GetPath()}",
                                        what="points of the features read so far")
        except ValueError as e:
            raise InputError(f"{where}: {prim.GetPath()}: {e}") from None
    seen: set[str] = set()
    for f in layout.features():
        if f.id in seen:
            raise InputError(f"{where}: feature id {f.id!r} is used twice (ids must be unique; "
                             f"set {NS}id or rename the prim)")
        seen.add(f.id)
    m.check_size(layout, where)
    layout.reindex()
    return layout


@dataclasses.dataclass(frozen=True)
class _Units:
    """Conversion of a layer's coordinates to the layout's Z-up metres."""
    scale: float = 1.0     # metersPerUnit
    y_up: bool = False

    def points(self, p: np.ndarray) -> np.ndarray:
        if self.y_up:   # rotate +90 deg about X: Y up becomes Z up, (x, y, z) -> (x, -z, y)
            p = np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)
        return p * self.scale if self.scale != 1.0 else p

    def length(self, v):
        return v * self.scale if self.scale != 1.0 else v


def _stage_units(stage: Usd.Stage, where: str) -> _Units:
    """upAxis and metersPerUnit as authored on the stage's root layer. Unauthored means the
    layout convention (Z up, metres), not USD's fallbacks (Y, centimetres)."""

    y_up = False
    if stage.HasAuthoredMetadata(UsdGeom.Tokens.upAxis):
        axis = str(UsdGeom.GetStageUpAxis(stage))
        if axis not in ("Y", "Z"):
            raise InputError(f"{where}: upAxis {axis!r} is not Y or Z")
        y_up = axis == "Y"
    scale = 1.0
    if stage.HasAuthoredMetadata(UsdGeom.Tokens.metersPerUnit):
        scale = float(UsdGeom.GetStageMetersPerUnit(stage))
        if not (np.isfinite(scale) and scale > 0):
            raise InputError(f"{where}: metersPerUnit {scale} is not a positive number")
    return _Units(scale, y_up)


def _read_layer_data(stage: Usd.Stage, layout: m.Layout, where: str,
                     units: _Units = _Units()) -> None:
    """Extent, chunk size and metadata from customLayerData, checked against the limits
    (limits.LAYOUT_EXTENT, CHUNK_SIZE_MIN/MAX) before any consumer sizes work by them.
    Lengths are in the layer's units (scaled by metersPerUnit)."""

    info = None
    for layer in stage.GetLayerStack(includeSessionLayers=False):
        if LAYER_DATA_KEY in layer.customLayerData:
            info = layer.customLayerData[LAYER_DATA_KEY]
            break
    if not info:
        return
    key = f"{where}: customLayerData {LAYER_DATA_KEY}"
    try:
        if not isinstance(info, dict):
            raise ValueError(f"expected a dictionary, got {type(info).__name__}")
        if "extent" in info:
            e = [units.length(float(v)) for v in info["extent"]]
            if len(e) != 4:
                raise ValueError("extent needs 4 numbers")
            if not all(np.isfinite(e)):
                raise ValueError(f"extent {e} has a non-finite value")
            if e[2] < e[0] or e[3] < e[1]:
                raise ValueError(f"extent {e} is not (xmin, ymin, xmax, ymax)")
            LAYOUT_EXTENT.check(max(e[2] - e[0], e[3] - e[1]), key, what=f"extent {e}: side")
            COORDINATE.check(max(abs(v) for v in e), key, what=f"extent {e}: a corner at")
            layout.extent = ((e[0], e[1]), (e[2], e[3]))
        if "chunkSize" in info:
            cs = units.length(float(info["chunkSize"]))
            CHUNK_SIZE_MIN.check(cs, key, what="chunkSize")
            CHUNK_SIZE_MAX.check(cs, key, what="chunkSize")
            layout.chunk_size = cs
        if "metadataJson" in info:
            layout.metadata = json.loads(info["metadataJson"])
    except (ValueError, TypeError, OverflowError) as e:
        raise InputError(f"{key}: {e}") from None


def _get(prim: Usd.Prim, name: str, want, where: str, default=None):
    """Authored value of lsd3d:<name>, type-checked against ``want``; ``default`` if absent."""
    attr = prim.GetAttribute(NS + name)
    if not attr or not attr.HasAuthoredValue():
        return default
    tn = attr.GetTypeName()
    if tn not in _ACCEPT.get(want, {want}):
        raise InputError(f"{where}: {prim.GetPath()}: attribute {NS}{name} has type {tn}, "
                         f"expected {want}")
    return attr.Get()


def _float_points(prim: Usd.Prim, where: str) -> np.ndarray:
    attr = prim.GetAttribute("points")
    if not attr or not attr.HasAuthoredValue():
        raise InputError(f"{where}: {prim.GetPath()}: attribute points is missing")
    if attr.GetTypeName() not in (T.Point3fArray, T.Float3Array, T.Point3dArray, T.Double3Array,
                                  T.Vector3fArray):
        raise InputError(f"{where}: {prim.GetPath()}: attribute points has type "
                         f"{attr.GetTypeName()}, expected point3f[]")
    value = attr.Get()
    if value is not None and not FEATURE_POINTS.ok(len(value)):
        FEATURE_POINTS.check(len(value), f"{where}: {prim.GetPath()}.points")
    return np.asarray(value, dtype=np.float64).reshape(-1, 3)


def _prefer64(prim: Usd.Prim, name: str, approx: np.ndarray, where: str, want) -> np.ndarray:
    """The float64 shadow of an attribute if it still matches the float32 value, else ``approx``."""
    attr = prim.GetAttribute(NS + name)
    if not attr or not attr.HasAuthoredValue():
        return approx
    if attr.GetTypeName() not in (want,):
        raise InputError(f"{where}: {prim.GetPath()}: attribute {NS}{name} has type "
                         f"{attr.GetTypeName()}, expected {want}")
    exact = np.asarray(attr.Get(), dtype=np.float64).reshape(approx.shape if approx.ndim > 1 else -1)
    if exact.shape == approx.shape and np.array_equal(exact.astype(np.float32), approx.astype(np.float32)):
        return exact
    return approx


# Model fields holding lengths (converted by metersPerUnit); "center" is a point.
LENGTH_FIELDS = {"height_hint", "height", "width", "length"}


def _read_prim(prim: Usd.Prim, ftype: str, where: str, units: _Units = _Units()) -> list:
    path = prim.GetPath()
    name = prim.GetName()
    fid = _get(prim, "id", T.String, where, default=None)
    pts32 = _float_points(prim, where)
    pts = units.points(_prefer64(prim, "points64", pts32, where, T.Point3dArray))
    bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if bad.size:    # before any geometry is computed from them (a footprint's orientation)
        raise InputError(f"{where}: {path}: attribute points: a non-finite coordinate at point "
                         f"{int(bad[0])} ({bad.size} of {len(pts)})")

    if ftype == "Tree":
        n = len(pts)
        ids = _get(prim, "ids", T.StringArray, where)
        ids = list(ids) if ids is not None else ([fid or name] if n == 1 else
                                                 [f"{fid or name}_{k}" for k in range(n)])
        heights = units.length(_per_point(prim, "heightHint", n, where, 8.0))
        crowns = units.length(_per_point(prim, "crownRadiusHint", n, where, 2.5))
        if len(ids) != n:
            raise InputError(f"{where}: {path}: attribute {NS}ids has {len(ids)} entries for {n} points")
        return [m.Tree(ids[k], position=pts[k], height_hint=heights[k], crown_radius_hint=crowns[k])
                for k in range(n)]

    kwargs = {}
    for attr_name, (field_name, type_name) in SCHEMA[ftype].items():
        v = _get(prim, attr_name, type_name, where)
        if v is None:
            continue
        if type_name == T.StringArray:
            v = [str(s) for s in v]
        elif type_name in (T.Token, T.String):
            v = str(v)
        elif type_name == T.Double3:
            v = units.points(np.array([float(c) for c in v]))
        if field_name in LENGTH_FIELDS:
            v = units.length(float(v))
        kwargs[field_name] = v

    if ftype in SINGLE_POINT_TYPES:
        if len(pts) != 1:
            raise InputError(f"{where}: {path}: attribute points: a {ftype} has exactly 1 point, "
                             f"got {len(pts)}")
        return [m.FEATURE_CLASS_BY_TYPE[ftype](fid or name, position=pts[0], **kwargs)]

    counts = _curve_counts(prim, len(pts), where)
    polygon = ftype in POLYGON_TYPES
    widths = None
    if ftype == "LaneCenter":
        widths = units.length(_lane_widths(prim, len(pts), where))

    if ftype == "ParkingSpot":
        if "center" not in kwargs:  # hand-authored: derive the rectangle's fields
            kwargs.update(_rectangle_fields(pts, path, where))
        return [m.ParkingSpot(fid or name, **kwargs)]

    out = []
    start = 0
    for k, c in enumerate(counts):
        seg = pts[start:start + c]
        fid_k = (fid or name) if len(counts) == 1 else f"{fid or name}_{k}"
        if polygon:
            if len(seg) > 3 and np.array_equal(seg[0], seg[-1]):
                seg = seg[:-1]  # explicitly closed ring
            if ftype == "Building":
                if m.polygon_area(seg) < 0:
                    seg = seg[::-1].copy()
                out.append(m.Building(fid_k, footprint=seg, **kwargs))
            else:
                out.append(m.FEATURE_CLASS_BY_TYPE[ftype](fid_k, polygon=seg, **kwargs))
        elif ftype == "LaneCenter":
            out.append(m.LaneCenter(fid_k, points=seg, widths=widths[start:start + c], **kwargs))
        else:
            out.append(m.FEATURE_CLASS_BY_TYPE[ftype](fid_k, points=seg, **kwargs))
        start += c
    return out


def _curve_counts(prim: Usd.Prim, n: int, where: str) -> list[int]:
    attr = prim.GetAttribute("curveVertexCounts")
    if not attr or not attr.HasAuthoredValue():
        return [n]
    counts = [int(c) for c in attr.Get()]
    if sum(counts) != n or any(c < 1 for c in counts):
        raise InputError(f"{where}: {prim.GetPath()}: attribute curveVertexCounts {counts} does not "
                         f"add up to the {n} points")
    return counts


def _lane_widths(prim: Usd.Prim, n: int, where: str) -> np.ndarray:
    attr = prim.GetAttribute("widths")
    if not attr or not attr.HasAuthoredValue():
        return np.full(n, m.DEFAULT_LANE_WIDTH)
    if attr.GetTypeName() not in (T.FloatArray, T.DoubleArray):
        raise InputError(f"{where}: {prim.GetPath()}: attribute widths has type {attr.GetTypeName()}, "
                         "expected float[]")
    w = np.asarray(attr.Get(), dtype=np.float64)
    if len(w) == 1:
        w = np.full(n, w[0])
    if len(w) != n:
        raise InputError(f"{where}: {prim.GetPath()}: attribute widths has {len(w)} values for "
                         f"{n} points (give 1 or one per point)")
    return _prefer64(prim, "widths64", w, where, T.DoubleArray)


def _per_point(prim: Usd.Prim, name: str, n: int, where: str, default: float) -> np.ndarray:
    v = _get(prim, name, T.DoubleArray, where)
    if v is None:
        return np.full(n, default)
    v = np.asarray(v, dtype=np.float64)
    if len(v) == 1:
        v = np.full(n, v[0])
    if len(v) != n:
        raise InputError(f"{where}: {prim.GetPath()}: attribute {NS}{name} has {len(v)} values for "
                         f"{n} points")
    return v


def _rectangle_fields(pts: np.ndarray, path, where: str) -> dict:
    if len(pts) == 5 and np.allclose(pts[0], pts[-1]):
        pts = pts[:-1]
    if len(pts) != 4:
        raise InputError(f"{where}: {path}: a ParkingSpot without {NS}center needs a 4-corner "
                         f"rectangle in points, got {len(pts)} points")
    e1, e2 = pts[1] - pts[0], pts[2] - pts[1]
    l1, l2 = np.linalg.norm(e1[:2]), np.linalg.norm(e2[:2])
    long_edge = e1 if l1 >= l2 else e2
    return {"center": pts.mean(axis=0), "heading": float(np.arctan2(long_edge[1], long_edge[0])),
            "length": float(max(l1, l2)), "width": float(min(l1, l2))}
