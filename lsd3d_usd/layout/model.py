"""The map layout as plain Python: dataclasses over numpy arrays.

This is the in-memory form of the layout layer (``/World/Layout``); ``usdio``
reads and writes it losslessly, the generator and the importers produce it,
the proxy builder consumes it.

Conventions (all features):

- Units are metres, Z up, world coordinates (the stage's, no per-feature
  transform). Every coordinate array is ``float64``; ``points`` are ``(N, 3)``.
- A *polyline* (lane centre, road line, road edge, stop line, hedge) runs in
  its direction of travel / authoring; ``N >= 2``.
- A *polygon* (crosswalk, building footprint, sidewalk, road area, zone) is
  ``(N, 3)`` with ``N >= 3``, implicitly closed: the first vertex is **not**
  repeated at the end. Building footprints are counter-clockwise seen from +Z.
- ``id`` is unique within a layout across all feature kinds (the USD writer
  turns it into a prim name).
- Feature type names follow the Waymo Open Motion map features
  (``LaneCenter``, ``RoadLine``, ``RoadEdge``, ``Crosswalk``, ``StopSign``)
  extended with the ones Waymo lacks (``Building``, ``Tree``, ...); each class
  carries its name in ``FEATURE_TYPE``.

Whole-road surfaces (``RoadArea``) and sidewalks are optional: the generator
and the OpenDRIVE importer produce them, a hand-authored layout may leave them
out, and a consumer then derives the road surface from lane widths and the
sidewalks from the road edges.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Iterator

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry.polyline import signed_area
from lsd3d_usd.limits import COORDINATE, FEATURE_POINTS, LAYOUT_EXTENT, LAYOUT_POINTS

DEFAULT_LANE_WIDTH = 3.5          # m, used when a lane has no widths
DEFAULT_SPEED_LIMIT = 13.89       # m/s (50 km/h)
DEFAULT_CHUNK_SIZE = 100.0        # m, the paper's chunk size

LANE_TYPES = ("driving", "bike", "bus", "parking", "shoulder", "sidewalk",
              "border", "median", "restricted", "entry", "exit", "other")
# The lane types a car drives along: general traffic, bus lanes, motorway entry and exit
# ramps. Not bike lanes, parking lanes (cars stand there), shoulders or anything else. The
# one definition of "drivable": traffic, ego routes, GGDS cameras and surfel density use it.
DRIVABLE_TYPES = ("driving", "bus", "entry", "exit")
LANE_DIRECTIONS = ("forward", "backward", "both")
ROAD_LINE_KINDS = ("solid", "broken")
ROAD_LINE_COLORS = ("white", "yellow")
ROAD_EDGE_KINDS = ("boundary", "median")
VEGETATION_KINDS = ("grass", "shrub", "forest", "park")
# Map signs other than stop signs (StopSign), by what a driver reads from them.
SIGN_KINDS = ("yield", "speed_limit", "no_entry", "priority", "warning", "mandatory",
              "prohibition", "information", "other")
POLE_KINDS = ("pole", "street_lamp", "bollard")
BARRIER_KINDS = ("fence", "wall", "guard_rail", "jersey", "railing")

Box = tuple[tuple[float, float], tuple[float, float]]  # ((xmin, ymin), (xmax, ymax))


def as_points(value, what: str, min_points: int = 1) -> np.ndarray:
    """``value`` as a C-contiguous float64 (N, 3) array (an (N, 2) input gets z = 0).

    Raises ValueError naming ``what`` when the shape is wrong, there are too
    few points, or a coordinate is not finite.
    """
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] in (2, 3) and min_points <= 1:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] not in (2, 3):
        raise ValueError(f"{what}: expected points of shape (N, 3), got {a.shape}")
    if a.shape[1] == 2:
        a = np.concatenate([a, np.zeros((a.shape[0], 1))], axis=1)
    if a.shape[0] < min_points:
        raise ValueError(f"{what}: needs at least {min_points} points, got {a.shape[0]}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: non-finite coordinate")
    return np.ascontiguousarray(a)


def as_position(value, what: str) -> np.ndarray:
    """A single point as float64 (3,) (an (2,) input gets z = 0)."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape not in ((2,), (3,)):
        raise ValueError(f"{what}: expected a 2D or 3D point, got shape {a.shape}")
    return as_points(a[None, :], what, 1)[0].copy()


def _check_choice(value: str, choices: tuple[str, ...], what: str) -> str:
    if value not in choices:
        raise ValueError(f"{what}: {value!r} is not one of {', '.join(choices)}")
    return value


polygon_area = signed_area     # the layout's name for it


def polyline_length(points: np.ndarray) -> float:
    """Length of a polyline (3D)."""
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


# ---------------------------------------------------------------- features

@dataclass(eq=False)
class _Feature:
    id: str

    FEATURE_TYPE = ""

    def coords(self) -> np.ndarray:
        """All coordinates of the feature as (N, 3), for bounds and chunking."""
        raise NotImplementedError  # abstract: each feature type defines it

    def bbox(self) -> Box:
        c = self.coords()
        lo, hi = c[:, :2].min(axis=0), c[:, :2].max(axis=0)
        return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))

    def __eq__(self, other) -> bool:
        """Field-wise equality; arrays compare exactly (bitwise values and shape)."""
        if type(self) is not type(other):
            return NotImplemented
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
                        and a.shape == b.shape and a.dtype == b.dtype
                        and np.array_equal(a, b)):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # mutable


@dataclass(eq=False)
class LaneCenter(_Feature):
    """A lane centre line, in the direction of travel (for ``direction='forward'``).

    ``widths`` is the full lane width at each vertex (default 3.5 m).
    ``predecessors`` / ``successors`` are lane ids: a successor's first point
    coincides with this lane's last point. ``left_neighbors`` /
    ``right_neighbors`` are adjacent lanes of the same road (seen along the
    lane's direction), for lane changes and actor placement.
    """
    points: np.ndarray = None
    widths: np.ndarray | None = None
    lane_type: str = "driving"
    direction: str = "forward"
    speed_limit_mps: float = DEFAULT_SPEED_LIMIT
    predecessors: list[str] = field(default_factory=list)
    successors: list[str] = field(default_factory=list)
    road_id: str = ""
    is_junction: bool = False
    left_neighbors: list[str] = field(default_factory=list)
    right_neighbors: list[str] = field(default_factory=list)

    FEATURE_TYPE = "LaneCenter"

    def __post_init__(self):
        self.points = as_points(self.points, f"lane {self.id} points", 2)
        if self.widths is None:
            self.widths = np.full(len(self.points), DEFAULT_LANE_WIDTH)
        else:
            w = np.asarray(self.widths, dtype=np.float64)
            if w.ndim == 0:
                w = np.full(len(self.points), float(w))
            if w.shape != (len(self.points),):
                raise ValueError(f"lane {self.id} widths: expected shape ({len(self.points)},), "
                                 f"got {w.shape}")
            if not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError(f"lane {self.id} widths: must be finite and >= 0")
            self.widths = np.ascontiguousarray(w)
        _check_choice(self.direction, LANE_DIRECTIONS, f"lane {self.id} direction")
        self.speed_limit_mps = float(self.speed_limit_mps)
        self.predecessors = list(self.predecessors)
        self.successors = list(self.successors)
        self.left_neighbors = list(self.left_neighbors)
        self.right_neighbors = list(self.right_neighbors)
        self.is_junction = bool(self.is_junction)

    def coords(self):
        return self.points

    def length(self) -> float:
        return polyline_length(self.points)


@dataclass(eq=False)
class RoadLine(_Feature):
    """A painted line: ``kind`` solid|broken, ``color`` white|yellow, ``double`` for double lines."""
    points: np.ndarray = None
    kind: str = "solid"
    color: str = "white"
    double: bool = False

    FEATURE_TYPE = "RoadLine"

    def __post_init__(self):
        self.points = as_points(self.points, f"road line {self.id} points", 2)
        _check_choice(self.kind, ROAD_LINE_KINDS, f"road line {self.id} kind")
        _check_choice(self.color, ROAD_LINE_COLORS, f"road line {self.id} color")
        self.double = bool(self.double)

    def coords(self):
        return self.points


@dataclass(eq=False)
class RoadEdge(_Feature):
    """A road boundary (curb line) or a median edge. Road surface lies to the
    left of the edge when walking along ``points`` (the generator and importer
    keep this orientation; hand-authored edges may not)."""
    points: np.ndarray = None
    kind: str = "boundary"

    FEATURE_TYPE = "RoadEdge"

    def __post_init__(self):
        self.points = as_points(self.points, f"road edge {self.id} points", 2)
        _check_choice(self.kind, ROAD_EDGE_KINDS, f"road edge {self.id} kind")

    def coords(self):
        return self.points


@dataclass(eq=False)
class _PolygonFeature(_Feature):
    polygon: np.ndarray = None

    def __post_init__(self):
        self.polygon = as_points(self.polygon, f"{self.FEATURE_TYPE} {self.id} polygon", 3)

    def coords(self):
        return self.polygon

    def area(self) -> float:
        return abs(polygon_area(self.polygon))


@dataclass(eq=False)
class Crosswalk(_PolygonFeature):
    """A pedestrian crossing, as the polygon painted on the road."""
    FEATURE_TYPE = "Crosswalk"


@dataclass(eq=False)
class Sidewalk(_PolygonFeature):
    """A raised sidewalk area (polygon, union semantics with other sidewalks)."""
    FEATURE_TYPE = "Sidewalk"


@dataclass(eq=False)
class RoadArea(_PolygonFeature):
    """Drivable road surface; the road surface is the union of all RoadArea polygons."""
    FEATURE_TYPE = "RoadArea"


@dataclass(eq=False)
class VegetationZone(_PolygonFeature):
    """An area of vegetation: ``kind`` grass|shrub|forest|park."""
    kind: str = "grass"

    FEATURE_TYPE = "VegetationZone"

    def __post_init__(self):
        super().__post_init__()
        _check_choice(self.kind, VEGETATION_KINDS, f"vegetation zone {self.id} kind")


@dataclass(eq=False)
class StopLine(_Feature):
    """A stop line across the lanes it serves (polyline)."""
    points: np.ndarray = None

    FEATURE_TYPE = "StopLine"

    def __post_init__(self):
        self.points = as_points(self.points, f"stop line {self.id} points", 2)

    def coords(self):
        return self.points


@dataclass(eq=False)
class StopSign(_Feature):
    """A stop sign at ``position`` (ground point of the pole) controlling ``lane_ids``."""
    position: np.ndarray = None
    lane_ids: list[str] = field(default_factory=list)

    FEATURE_TYPE = "StopSign"

    def __post_init__(self):
        self.position = as_position(self.position, f"stop sign {self.id} position")
        self.lane_ids = list(self.lane_ids)

    def coords(self):
        return self.position[None, :]


@dataclass(eq=False)
class Building(_Feature):
    """A building footprint (CCW polygon at ground level) with height hints.

    ``height_hint`` is the eave height in metres; ``floors_hint`` the number
    of storeys (0 = unknown). Consumers may vary both.
    """
    footprint: np.ndarray = None
    height_hint: float = 12.0
    floors_hint: int = 0

    FEATURE_TYPE = "Building"

    def __post_init__(self):
        self.footprint = as_points(self.footprint, f"building {self.id} footprint", 3)
        self.height_hint = float(self.height_hint)
        self.floors_hint = int(self.floors_hint)
        if not (self.height_hint > 0):
            raise ValueError(f"building {self.id} height_hint: must be > 0")

    def coords(self):
        return self.footprint


@dataclass(eq=False)
class Tree(_Feature):
    """A single tree at ``position`` (ground point of the trunk)."""
    position: np.ndarray = None
    height_hint: float = 8.0
    crown_radius_hint: float = 2.5

    FEATURE_TYPE = "Tree"

    def __post_init__(self):
        self.position = as_position(self.position, f"tree {self.id} position")
        self.height_hint = float(self.height_hint)
        self.crown_radius_hint = float(self.crown_radius_hint)

    def coords(self):
        return self.position[None, :]


@dataclass(eq=False)
class Hedge(_Feature):
    """A hedge along a polyline, ``height`` and ``width`` in metres."""
    points: np.ndarray = None
    height: float = 1.2
    width: float = 0.8

    FEATURE_TYPE = "Hedge"

    def __post_init__(self):
        self.points = as_points(self.points, f"hedge {self.id} points", 2)
        self.height = float(self.height)
        self.width = float(self.width)

    def coords(self):
        return self.points


@dataclass(eq=False)
class ParkingSpot(_Feature):
    """A parking spot: rectangle of ``length`` x ``width`` at ``center``,
    its long axis at ``heading`` (radians from +X, CCW). ``occupied`` hints
    that a parked vehicle stands there."""
    center: np.ndarray = None
    heading: float = 0.0
    length: float = 5.5
    width: float = 2.3
    occupied: bool = True

    FEATURE_TYPE = "ParkingSpot"

    def __post_init__(self):
        self.center = as_position(self.center, f"parking spot {self.id} center")
        self.heading = float(self.heading)
        self.length = float(self.length)
        self.width = float(self.width)
        self.occupied = bool(self.occupied)

    def polygon(self) -> np.ndarray:
        """The spot's rectangle, (4, 3) CCW."""
        c, s = np.cos(self.heading), np.sin(self.heading)
        u = np.array([c, s, 0.0]) * (self.length / 2)
        v = np.array([-s, c, 0.0]) * (self.width / 2)
        return np.stack([self.center - u - v, self.center + u - v,
                         self.center + u + v, self.center - u + v])

    def coords(self):
        return self.polygon()


@dataclass(eq=False)
class TrafficLight(_Feature):
    """A traffic signal head from a map. ``position`` is the ground point below the head,
    ``heading`` (rad from +X, CCW) the direction the lights face (towards the traffic they
    control), ``height`` the top of the head above the ground, ``lane_ids`` the lanes it
    controls. The proxy stands its mast at the roadside of those lanes and reaches over the
    road to the head when the head is above a lane."""
    position: np.ndarray = None
    heading: float = 0.0
    height: float = 5.5
    lane_ids: list[str] = field(default_factory=list)

    FEATURE_TYPE = "TrafficLight"

    def __post_init__(self):
        self.position = as_position(self.position, f"traffic light {self.id} position")
        self.heading = float(self.heading)
        self.height = float(self.height)
        self.lane_ids = list(self.lane_ids)
        if not (np.isfinite(self.heading) and 0 < self.height < 100):
            raise ValueError(f"traffic light {self.id}: heading must be finite and height in (0, 100) m")

    def coords(self):
        return self.position[None, :]


@dataclass(eq=False)
class TrafficSign(_Feature):
    """A road sign from a map other than a stop sign (those are StopSign): ``kind`` one of
    SIGN_KINDS, ``code`` the map's own sign code (e.g. ``DE:205``, ``US:R1-2``), ``value``
    its number where it has one (a speed limit in the map's unit, else 0), facing
    ``heading`` (rad; towards the traffic it addresses), the top of the plate ``height``
    above the ground at ``position``, for ``lane_ids``."""
    position: np.ndarray = None
    heading: float = 0.0
    kind: str = "other"
    code: str = ""
    value: float = 0.0
    height: float = 2.5
    lane_ids: list[str] = field(default_factory=list)

    FEATURE_TYPE = "TrafficSign"

    def __post_init__(self):
        self.position = as_position(self.position, f"traffic sign {self.id} position")
        _check_choice(self.kind, SIGN_KINDS, f"traffic sign {self.id} kind")
        self.heading, self.value, self.height = float(self.heading), float(self.value), float(self.height)
        self.code = str(self.code)
        self.lane_ids = list(self.lane_ids)
        if not (np.isfinite(self.heading) and np.isfinite(self.value) and 0 < self.height < 100):
            raise ValueError(f"traffic sign {self.id}: heading and value must be finite, height "
                             "in (0, 100) m")

    def coords(self):
        return self.position[None, :]


@dataclass(eq=False)
class Pole(_Feature):
    """A pole from a map at ``position`` (ground point): ``kind`` pole | street_lamp |
    bollard, ``height`` in metres."""
    position: np.ndarray = None
    kind: str = "pole"
    height: float = 6.0

    FEATURE_TYPE = "Pole"

    def __post_init__(self):
        self.position = as_position(self.position, f"pole {self.id} position")
        _check_choice(self.kind, POLE_KINDS, f"pole {self.id} kind")
        self.height = float(self.height)
        if not (0 < self.height < 100):
            raise ValueError(f"pole {self.id} height: must be in (0, 100) m")

    def coords(self):
        return self.position[None, :]


@dataclass(eq=False)
class Barrier(_Feature):
    """A fence, wall, guard rail, jersey barrier or railing along a polyline (``kind`` one
    of BARRIER_KINDS), ``height`` and ``width`` (thickness) in metres."""
    points: np.ndarray = None
    kind: str = "fence"
    height: float = 1.2
    width: float = 0.2

    FEATURE_TYPE = "Barrier"

    def __post_init__(self):
        self.points = as_points(self.points, f"barrier {self.id} points", 2)
        _check_choice(self.kind, BARRIER_KINDS, f"barrier {self.id} kind")
        self.height, self.width = float(self.height), float(self.width)
        if not (0 < self.height < 100 and 0 < self.width < 20):
            raise ValueError(f"barrier {self.id}: height must be in (0, 100) m, width in (0, 20) m")

    def coords(self):
        return self.points


FEATURE_CLASSES: tuple[type[_Feature], ...] = (
    LaneCenter, RoadLine, RoadEdge, Crosswalk, StopLine, StopSign, Building, Tree,
    Hedge, VegetationZone, ParkingSpot, Sidewalk, RoadArea, TrafficLight, TrafficSign, Pole,
    Barrier)
FEATURE_CLASS_BY_TYPE = {c.FEATURE_TYPE: c for c in FEATURE_CLASSES}

# Layout list attribute holding each feature class.
LIST_FOR_TYPE = {
    "LaneCenter": "lanes", "RoadLine": "road_lines", "RoadEdge": "road_edges",
    "Crosswalk": "crosswalks", "StopLine": "stop_lines", "StopSign": "stop_signs",
    "Building": "buildings", "Tree": "trees", "Hedge": "hedges",
    "VegetationZone": "vegetation_zones", "ParkingSpot": "parking_spots",
    "Sidewalk": "sidewalks", "RoadArea": "road_areas", "TrafficLight": "traffic_lights",
    "TrafficSign": "traffic_signs", "Pole": "poles", "Barrier": "barriers",
}


# ------------------------------------------------------------------ layout

@dataclass(eq=False)
class Layout:
    """A whole map layout.

    ``extent`` is the authored area ((xmin, ymin), (xmax, ymax)) — for a
    generated layout everything lies inside it; ``None`` means "the bounds of
    the features". ``chunk_size`` is the side of the square chunks (m) used
    by chunk-wise consumers, with chunk (i, j) covering
    [i*chunk_size, (i+1)*chunk_size) x [j*chunk_size, (j+1)*chunk_size).
    ``metadata`` is free-form JSON-like data (generator description,
    source file, ...), stored in the layer's customLayerData.
    """
    lanes: list[LaneCenter] = field(default_factory=list)
    road_lines: list[RoadLine] = field(default_factory=list)
    road_edges: list[RoadEdge] = field(default_factory=list)
    crosswalks: list[Crosswalk] = field(default_factory=list)
    stop_lines: list[StopLine] = field(default_factory=list)
    stop_signs: list[StopSign] = field(default_factory=list)
    buildings: list[Building] = field(default_factory=list)
    trees: list[Tree] = field(default_factory=list)
    hedges: list[Hedge] = field(default_factory=list)
    vegetation_zones: list[VegetationZone] = field(default_factory=list)
    parking_spots: list[ParkingSpot] = field(default_factory=list)
    sidewalks: list[Sidewalk] = field(default_factory=list)
    road_areas: list[RoadArea] = field(default_factory=list)
    traffic_lights: list[TrafficLight] = field(default_factory=list)
    traffic_signs: list[TrafficSign] = field(default_factory=list)
    poles: list[Pole] = field(default_factory=list)
    barriers: list[Barrier] = field(default_factory=list)
    extent: Box | None = None
    chunk_size: float = DEFAULT_CHUNK_SIZE
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        self._lane_index: dict[str, LaneCenter] | None = None

    # -- iteration
    def features(self) -> Iterator[_Feature]:
        """Every feature, grouped by kind in FEATURE_CLASSES order."""
        for cls in FEATURE_CLASSES:
            yield from getattr(self, LIST_FOR_TYPE[cls.FEATURE_TYPE])

    def add(self, feature: _Feature) -> _Feature:
        """Append ``feature`` to the list for its type; returns it."""
        getattr(self, LIST_FOR_TYPE[feature.FEATURE_TYPE]).append(feature)
        self._lane_index = None
        return feature

    def counts(self) -> dict[str, int]:
        """Number of features per feature type."""
        return {t: len(getattr(self, name)) for t, name in LIST_FOR_TYPE.items()}

    # -- lane graph
    def lane_by_id(self, lane_id: str) -> LaneCenter:
        """The lane with this id (KeyError if none). The index is rebuilt when
        the lane list changes length; call ``reindex()`` after replacing lanes."""
        if self._lane_index is None or len(self._lane_index) != len(self.lanes):
            self.reindex()
        return self._lane_index[lane_id]

    def reindex(self) -> None:
        self._lane_index = {lane.id: lane for lane in self.lanes}

    def successors_of(self, lane_id: str) -> list[LaneCenter]:
        return [self.lane_by_id(s) for s in self.lane_by_id(lane_id).successors]

    def predecessors_of(self, lane_id: str) -> list[LaneCenter]:
        return [self.lane_by_id(p) for p in self.lane_by_id(lane_id).predecessors]

    def drivable_lanes(self) -> list[LaneCenter]:
        """The lanes a car drives along: a DRIVABLE_TYPES type, a speed limit above 0 and a
        centre line of positive length, in layout order."""
        return [ln for ln in self.lanes if ln.lane_type in DRIVABLE_TYPES
                and ln.speed_limit_mps > 0 and ln.length() > 1e-6]

    # -- geometry
    def bounds(self) -> Box:
        """XY bounds of all features (including lane half-widths); the extent if empty."""
        lo = np.array([np.inf, np.inf])
        hi = -lo
        for f in self.features():
            c = f.coords()[:, :2]
            pad = 0.0
            if isinstance(f, LaneCenter):
                pad = float(f.widths.max()) / 2 if len(f.widths) else 0.0
            lo = np.minimum(lo, c.min(axis=0) - pad)
            hi = np.maximum(hi, c.max(axis=0) + pad)
        if not np.all(np.isfinite(lo)):
            if self.extent is not None:
                return self.extent
            return (0.0, 0.0), (0.0, 0.0)
        return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))

    def area_box(self) -> Box:
        """The extent if set, else the feature bounds."""
        return self.extent if self.extent is not None else self.bounds()

    def chunk_range(self) -> tuple[range, range]:
        """Ranges of chunk indices (i, j) covering ``area_box()``."""
        (x0, y0), (x1, y1) = self.area_box()
        s = self.chunk_size
        i0, j0 = int(np.floor(x0 / s)), int(np.floor(y0 / s))
        i1, j1 = int(np.ceil(x1 / s)), int(np.ceil(y1 / s))
        return range(i0, max(i1, i0 + 1)), range(j0, max(j1, j0 + 1))

    def chunk_box(self, i: int, j: int) -> Box:
        s = self.chunk_size
        return (i * s, j * s), ((i + 1) * s, (j + 1) * s)

    def features_in_box(self, box: Box, margin: float = 0.0) -> "Layout":
        """A Layout holding the features whose XY bounding box intersects
        ``box`` grown by ``margin``. Features are shared (not copied, not
        clipped): a consumer clips geometry itself. Lane ids stay valid; links
        to lanes outside the box are kept as ids."""
        (bx0, by0), (bx1, by1) = box
        bx0, by0, bx1, by1 = bx0 - margin, by0 - margin, bx1 + margin, by1 + margin
        out = Layout(extent=self.extent, chunk_size=self.chunk_size, metadata=self.metadata)
        for f in self.features():
            (fx0, fy0), (fx1, fy1) = f.bbox()
            if isinstance(f, LaneCenter):
                pad = float(f.widths.max()) / 2
                fx0, fy0, fx1, fy1 = fx0 - pad, fy0 - pad, fx1 + pad, fy1 + pad
            if fx1 >= bx0 and fx0 <= bx1 and fy1 >= by0 and fy0 <= by1:
                out.add(f)
        return out

    def __eq__(self, other) -> bool:
        if not isinstance(other, Layout):
            return NotImplemented
        for name in LIST_FOR_TYPE.values():
            a, b = getattr(self, name), getattr(other, name)
            if len(a) != len(b) or any(x != y for x, y in zip(a, b)):
                return False
        ext = lambda e: None if e is None else tuple(tuple(float(v) for v in p) for p in e)
        return (ext(self.extent) == ext(other.extent) and self.chunk_size == other.chunk_size
                and self.metadata == other.metadata)

    __hash__ = None


def check_size(layout: Layout, where: str) -> None:
    """Refuse (InputError, one line) a layout whose features span more than
    limits.LAYOUT_EXTENT on a side (chunk-wise consumers would start that many chunks, and
    USD's float32 points lose precision beyond) or lie farther than limits.COORDINATE from
    the origin. Readers and importers call it before they return a layout."""

    if layout.extent is not None:   # e.g. an import's --bbox: every reader checks it
        (ex0, ey0), (ex1, ey1) = layout.extent
        if not LAYOUT_EXTENT.ok(max(ex1 - ex0, ey1 - ey0)):
            raise InputError(f"{where}: the layout's extent is {ex1 - ex0:.6g} m x {ey1 - ey0:.6g} m, "
                             f"more than the limit of {LAYOUT_EXTENT.value:.0f} m on a side "
                             "(choose a smaller area)")
    (x0, y0), (x1, y1) = layout.bounds()
    size = max(x1 - x0, y1 - y0)
    if not LAYOUT_EXTENT.ok(size):
        raise InputError(f"{where}: the features span {x1 - x0:.6g} m x {y1 - y0:.6g} m, more than "
                         f"the limit of {LAYOUT_EXTENT.value:.0f} m on a side")
    feats = [(f, f.coords()) for f in layout.features()]
    far = max([abs(x0), abs(y0), abs(x1), abs(y1)]
              + [float(np.abs(c[:, 2]).max()) for _, c in feats])
    COORDINATE.check(far, where, what="a coordinate at")
    # what an importer writes, the layout reader must read back: its point limits hold here
    if feats:
        big, c = max(feats, key=lambda fc: len(fc[1]))
        FEATURE_POINTS.check(len(c), where, what=f"points of {big.FEATURE_TYPE} {big.id}")
        LAYOUT_POINTS.check(sum(len(c) for _, c in feats), where, what="points of all features")
