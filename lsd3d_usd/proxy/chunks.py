"""Layout -> proxy meshes, one 100 m chunk at a time.

Chunk (i, j) covers [i*s, (i+1)*s) x [j*s, (j+1)*s) (s = layout.chunk_size) and
is built from the features within ``margin`` of it. Two rules keep neighbours
seamless (no cracks, no double cover):

* Flat ground and strip solids (road, curb, sidewalk, vegetation patches,
  terrain, markings, crosswalks, hedges) are computed from the features
  around the chunk and then **cut exactly at the chunk border** as polygons;
  strip solids become closed again with a cap on the cut (prism walls).
* Compact solids (buildings, trees, vehicles, poles, signs, traffic lights)
  are **owned by the chunk containing their anchor** (footprint centroid,
  trunk or pole foot, spot centre, the ground point of a map signal) and kept
  whole, so they never appear twice; a building may overhang its chunk's box.

The map's own signals and furniture (TrafficLight, TrafficSign, StopSign, Pole, Barrier)
are built as given; the derived furniture fills in only where the map is silent
(``derive_fixtures``).

A chunk's inputs (the features within the margin, the few layout-wide
derived features that land in it, the parameters and ``PROXY_VERSION``) hash to
``chunk_inputs_hash``; the USD writer uses it to skip chunks that did not change.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field, fields

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from lsd3d_usd.configtree import option
from lsd3d_usd.geometry.polyline import nearest_point
from lsd3d_usd.layout.signals import derived_lights
from lsd3d_usd.limits import CHUNKS
from lsd3d_usd.scene import chunk_prim_name

from .buildings import BuildingStyle, building_mesh
from .furniture import stop_sign_parts, street_light_parts, traffic_light_parts
from .ground import GroundStyle, ground_areas, ground_parts
from .markings import MarkingStyle, crosswalk_part, road_line_part, stop_line_part
from .mesh import MeshPart
from .planar import area_from_points
from .signals import barrier_part, pole_parts, sign_parts, signal_parts
from .vegetation import hedge_part, tree_parts, zone_shrubs
from .vehicles import vehicle_part

# Bump when the geometry rules change, so stored chunks are rebuilt.
PROXY_VERSION = "2"


@dataclass(frozen=True)
class ProxyParams:
    """How the proxy is built from a layout (`proxy build`'s flags, generate's proxy.*)."""
    margin: float = option(12.0, help="metres around a chunk whose features it reads", lo=0.0,
                           hi=1000.0)
    street_light_spacing: float = option(35.0, help="street lights along road edges every this "
                                                    "many metres (0 = none)", lo=0.0)
    traffic_lights: bool = option(True, help="traffic lights at junction approaches")
    ground: GroundStyle = field(default_factory=GroundStyle)
    markings: MarkingStyle = field(default_factory=MarkingStyle)
    building: BuildingStyle = field(default_factory=BuildingStyle)

    def as_dict(self) -> dict:
        return asdict(self)


ChunkKey = tuple[int, int]


def chunk_of(x: float, y: float, size: float) -> ChunkKey:
    return int(np.floor(x / size)), int(np.floor(y / size))


def chunk_bounds(i: int, j: int, size: float) -> tuple[float, float, float, float]:
    return i * size, j * size, (i + 1) * size, (j + 1) * size


def chunk_label(i: int, j: int) -> str:
    """Chunk name used in part ids (same as the USD prim name)."""
    return chunk_prim_name(i, j)


def chunk_count(layout) -> int:
    """Number of chunks covering the layout's area (computed without listing them)."""
    ri, rj = layout.chunk_range()
    return len(ri) * len(rj)


def check_chunk_count(layout, n: int | None = None, max_chunks: int | None = None) -> None:
    """Refuse (InputError, one line) to build more than limits.CHUNKS chunks (or
    ``max_chunks``); ``n`` defaults to every chunk of the layout's area."""
    n = chunk_count(layout) if n is None else n
    if not CHUNKS.ok(n, max_chunks):
        (x0, y0), (x1, y1) = layout.area_box()
        where = (f"layout area {x1 - x0:.0f} m x {y1 - y0:.0f} m in {layout.chunk_size:g} m "
                 f"chunks")
        CHUNKS.check(n, where, max_chunks)


def all_chunks(layout, max_chunks: int | None = None) -> list[ChunkKey]:
    """Every chunk key of the layout's area; refuses more than limits.CHUNKS (or
    ``max_chunks``) before listing them."""
    check_chunk_count(layout, max_chunks=max_chunks)
    ri, rj = layout.chunk_range()
    return [(i, j) for i in ri for j in rj]


# ------------------------------------------------------- layout-wide derived features
@dataclass(frozen=True)
class Fixture:
    """A derived point feature (traffic light, street light) with its inputs' ids."""
    kind: str
    id: str
    position: tuple[float, float]
    yaw: float


def _heading(points: np.ndarray, at_end: bool) -> np.ndarray:
    d = points[-1, :2] - points[-2, :2] if at_end else points[1, :2] - points[0, :2]
    n = np.linalg.norm(d)
    return d / n if n > 0 else np.array([1.0, 0.0])


def derive_fixtures(layout, params: ProxyParams) -> list[Fixture]:
    """Traffic lights at junction approaches and street lights along road edges, where the
    map is silent about them.

    The traffic lights are layout.signals' derived lights (its module doc says which
    approaches get one; the simulator runs the phases of the same lights). Street lights
    stand every ``street_light_spacing`` metres along each boundary road edge, on its outer
    (right-hand) side, starting half a spacing from the edge's first point, except within
    half a spacing of a map street lamp.
    """
    out: list[Fixture] = []
    g = params.ground
    if params.traffic_lights:
        for sg in derived_lights(layout, g.curb_width):
            x, y, yaw = sg.light
            out.append(Fixture("traffic_light", sg.id, (x, y), yaw))
    sp = params.street_light_spacing
    lamps = np.array([p.position[:2] for p in layout.poles if p.kind == "street_lamp"]).reshape(-1, 2)
    if sp > 0:
        for e in layout.road_edges:
            if e.kind != "boundary":
                continue
            xy = e.points[:, :2]
            seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
            s = np.concatenate([[0.0], np.cumsum(seg)])
            for k, a in enumerate(np.arange(sp / 2, s[-1], sp)):
                q = int(np.clip(np.searchsorted(s, a) - 1, 0, len(seg) - 1))
                d = (xy[q + 1] - xy[q]) / max(seg[q], 1e-9)
                right = np.array([d[1], -d[0]])          # road on the left: outside is right
                p = np.array([np.interp(a, s, xy[:, 0]), np.interp(a, s, xy[:, 1])])
                p = p + right * (g.curb_width + 0.6)
                if len(lamps) and np.hypot(*(lamps - p).T).min() < sp / 2:
                    continue
                yaw = float(np.arctan2(-right[1], -right[0]))   # arm over the road
                out.append(Fixture("street_light", f"sl_{e.id}_{k}", (float(p[0]), float(p[1])), yaw))
    return out


# ----------------------------------------------------------------------- hashing
def _feature_bytes(f) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    h.update(type(f).__name__.encode())
    for fl in fields(f):
        v = getattr(f, fl.name)
        h.update(fl.name.encode())
        if isinstance(v, np.ndarray):
            h.update(str((v.shape, v.dtype.str)).encode())
            h.update(np.ascontiguousarray(v).tobytes())
        else:
            h.update(repr(v).encode())
    return h.digest()


def chunk_inputs_hash(local_layout, fixtures: list[Fixture], params: ProxyParams,
                      key: ChunkKey, feature_bytes=_feature_bytes) -> str:
    """Content hash of everything a chunk is built from. ``feature_bytes``: a feature's
    digest (ProxyBuilder passes a cached _feature_bytes)."""
    h = hashlib.sha256()
    h.update(f"proxy v{PROXY_VERSION} chunk {key} size {local_layout.chunk_size}".encode())
    h.update(repr(params.as_dict()).encode())
    for f in sorted(local_layout.features(), key=lambda f: (type(f).__name__, f.id)):
        h.update(feature_bytes(f))
    for fx in fixtures:
        h.update(repr(fx).encode())
    return h.hexdigest()


# ------------------------------------------------------------------------ build
@dataclass
class ChunkInputs:
    key: ChunkKey
    bounds: tuple[float, float, float, float]
    layout: object                    # features within the margin (a Layout)
    fixtures: list[Fixture]
    hash: str


class FeatureIndex:
    """The features of a layout with their XY bounds in one array, so the features near a
    chunk are found by one vectorised comparison instead of a walk over every feature
    (which made a chunk's cost grow with the whole layout). ``near`` returns what
    ``Layout.features_in_box`` returns, in the same order."""

    def __init__(self, layout):
        from lsd3d_usd.layout import model as lm
        self.layout = layout
        self.features = list(layout.features())
        b = np.empty((len(self.features), 4))
        for k, f in enumerate(self.features):
            (x0, y0), (x1, y1) = f.bbox()
            pad = float(f.widths.max()) / 2 if isinstance(f, lm.LaneCenter) else 0.0
            b[k] = (x0 - pad, y0 - pad, x1 + pad, y1 + pad)
        self.bounds = b

    def near(self, box, margin: float = 0.0):
        from lsd3d_usd.layout.model import Layout
        (bx0, by0), (bx1, by1) = box
        b = self.bounds
        hit = ((b[:, 2] >= bx0 - margin) & (b[:, 0] <= bx1 + margin)
               & (b[:, 3] >= by0 - margin) & (b[:, 1] <= by1 + margin))
        L = self.layout
        out = Layout(extent=L.extent, chunk_size=L.chunk_size, metadata=L.metadata)
        for k in np.nonzero(hit)[0]:
            out.add(self.features[k])
        return out


class ProxyBuilder:
    """Builds chunks of one layout; derived features and the feature index are computed
    once per layout."""

    def __init__(self, layout, params: ProxyParams | None = None):
        self.layout = layout
        self.params = params or ProxyParams()
        self.size = float(layout.chunk_size)
        self.fixtures = derive_fixtures(layout, self.params)
        self.index = FeatureIndex(layout)
        # a feature's digest is hashed into every chunk near it (a long lane: dozens); the
        # builder works on one unchanging layout, whose features it holds (ids stay unique)
        self._digests: dict[int, bytes] = {}
        self._areas: dict[int, object] = {}
        self._fixtures_at: dict[ChunkKey, list[Fixture]] = {}
        for f in self.fixtures:
            self._fixtures_at.setdefault(chunk_of(*f.position, self.size), []).append(f)

    def chunks(self, max_chunks: int | None = None) -> list[ChunkKey]:
        return all_chunks(self.layout, max_chunks)

    def feature_bytes(self, f) -> bytes:
        """_feature_bytes of a feature of this layout, computed once."""
        d = self._digests.get(id(f))
        if d is None:
            d = self._digests[id(f)] = _feature_bytes(f)
        return d

    def area_of(self, f, points) -> object:
        """area_from_points(points) of a polygon feature of this layout, computed once (a
        long sidewalk or road area is near dozens of chunks)."""
        a = self._areas.get(id(f))
        if a is None:
            a = self._areas[id(f)] = area_from_points(points)
        return a

    def inputs(self, key: ChunkKey) -> ChunkInputs:
        i, j = key
        b = chunk_bounds(i, j, self.size)
        local = self.index.near(((b[0], b[1]), (b[2], b[3])), self.params.margin)
        fx = list(self._fixtures_at.get(key, []))
        return ChunkInputs(key, b, local, fx, chunk_inputs_hash(local, fx, self.params, key,
                                                                self.feature_bytes))

    def build(self, key: ChunkKey, inputs: ChunkInputs | None = None) -> list[MeshPart]:
        inp = inputs or self.inputs(key)
        return build_chunk_parts(inp, self.params, self.area_of)


def _owned(x: float, y: float, b) -> bool:
    return b[0] <= x < b[2] and b[1] <= y < b[3]


def _area_of(f, points):
    return area_from_points(points)


def build_chunk_parts(inp: ChunkInputs, params: ProxyParams, area_of=_area_of) -> list[MeshPart]:
    """All mesh parts of one chunk. ``area_of(feature, points)``: area_from_points of a
    feature's polygon (ProxyBuilder passes a cached one)."""
    L, b = inp.layout, inp.bounds
    clip = box(*b)
    name = chunk_label(*inp.key)
    g = params.ground
    parts: list[MeshPart] = []

    areas = ground_areas(
        b, params.margin,
        lanes=[(ln.points, ln.widths, ln.lane_type) for ln in L.lanes],
        road_areas=[area_of(r, r.polygon) for r in L.road_areas],
        sidewalks=[area_of(s, s.polygon) for s in L.sidewalks],
        vegetation=[area_of(z, z.polygon) for z in L.vegetation_zones],
        buildings=[area_of(bd, bd.footprint) for bd in L.buildings],
        style=g, extent=_extent(L))
    parts += ground_parts(areas, name, g)

    def add(p):
        if p is not None:
            parts.append(p)

    for rl in L.road_lines:
        add(road_line_part(rl.id, rl.points, rl.kind, rl.color, rl.double, clip, g.road_z,
                           params.markings))
    for sl in L.stop_lines:
        add(stop_line_part(sl.id, sl.points, clip, g.road_z, params.markings))
    for cw in L.crosswalks:
        add(crosswalk_part(cw.id, cw.polygon, clip, g.road_z, params.markings))
    for h in L.hedges:
        add(hedge_part(h.id, h.points, h.height, h.width, clip))

    for bd in L.buildings:
        fp = Polygon(bd.footprint[:, :2])
        if fp.is_valid:
            c = fp.centroid
        else:   # a messy footprint: its cleaned area (or its vertices) decide the owner
            fp = area_of(bd, bd.footprint)
            c = fp.representative_point() if not fp.is_empty else shapely.Point(bd.footprint[:, :2].mean(0))
        if _owned(c.x, c.y, b):
            add(building_mesh(bd.id, bd.footprint, bd.height_hint, bd.floors_hint,
                              style=params.building))
    for t in L.trees:
        if _owned(t.position[0], t.position[1], b):
            parts += tree_parts(t.id, t.position, t.height_hint, t.crown_radius_hint)
    for z in L.vegetation_zones:
        parts += zone_shrubs(z.id, area_of(z, z.polygon), z.kind, clip)
    for ps in L.parking_spots:
        if ps.occupied and _owned(ps.center[0], ps.center[1], b):
            add(vehicle_part(ps.id, ps.center, ps.heading, ps.length, ps.width))
    lanes_by_id = {ln.id: ln for ln in L.lanes}
    for s in L.stop_signs:
        if _owned(s.position[0], s.position[1], b):
            parts += stop_sign_parts(s.id, s.position, _sign_yaw(s, lanes_by_id))
    for tl in L.traffic_lights:
        if _owned(tl.position[0], tl.position[1], b):
            parts += signal_parts(tl.id, _mast(tl, L.lanes, g.curb_width), tl.position,
                                  tl.heading, tl.height)
    for ts in L.traffic_signs:
        if _owned(ts.position[0], ts.position[1], b):
            parts += sign_parts(ts.id, ts.position, ts.heading, ts.kind, ts.height)
    for po in L.poles:
        if _owned(po.position[0], po.position[1], b):
            parts += pole_parts(po.id, po.position, po.kind, po.height,
                                _towards_road(po.position, L.lanes))
    for ba in L.barriers:
        add(barrier_part(ba.id, ba.points, ba.kind, ba.height, ba.width, clip))
    for fx in inp.fixtures:
        if fx.kind == "traffic_light":
            parts += traffic_light_parts(fx.id, fx.position, fx.yaw)
        else:
            parts += street_light_parts(fx.id, fx.position, fx.yaw)
    return parts


def _mast(light, lanes, curb_width: float) -> np.ndarray:
    """Where a map traffic light's mast stands: below the head, unless the head hangs over a
    lane it controls (or, naming none, any driving lane within 10 m): then on the right-hand
    roadside of those lanes (seen by the traffic the light faces), at most MAX_ARM away."""
    from .signals import MAX_ARM
    head = np.asarray(light.position[:2], dtype=np.float64)
    ids = set(light.lane_ids)
    cands = [ln for ln in lanes if ln.id in ids] or \
        [ln for ln in lanes if ln.lane_type == "driving" and not ln.is_junction]
    travel = -np.array([np.cos(light.heading), np.sin(light.heading)])
    right = np.array([travel[1], -travel[0]])
    over, reach = False, 0.0
    for ln in cands:
        dist, _, c, _ = nearest_point(ln.points, head)
        if dist > 10.0:
            continue
        w = float(ln.widths.max()) / 2
        if dist <= w + 0.25:
            over = True
        reach = max(reach, float(np.dot(c - head, right)) + w)
    if not over or reach <= 0:
        return head
    reach = min(reach + curb_width + 0.8, MAX_ARM)
    return head + right * reach


def _towards_road(position, lanes) -> float:
    """Yaw from ``position`` towards the nearest lane centre (a lamp's arm over the road)."""
    best, yaw = np.inf, 0.0
    q = np.asarray(position[:2], dtype=np.float64)
    for ln in lanes:
        dist, _, c, _ = nearest_point(ln.points, q)
        if 1e-6 < dist < best:
            best, yaw = dist, float(np.arctan2(c[1] - q[1], c[0] - q[0]))
    return yaw


def _extent(layout):
    if layout.extent is None:
        return None
    (x0, y0), (x1, y1) = layout.extent
    return float(x0), float(y0), float(x1), float(y1)


def _sign_yaw(sign, lanes_by_id) -> float:
    """Face the traffic of the nearest controlled lane (towards its approaching cars)."""
    best, yaw = np.inf, 0.0
    for lid in sign.lane_ids:
        ln = lanes_by_id.get(lid)
        if ln is None:
            continue
        d = float(np.linalg.norm(ln.points[-1, :2] - sign.position[:2]))
        if d < best:
            h = _heading(ln.points, True)
            best, yaw = d, float(np.arctan2(-h[1], -h[0]))
    return yaw


def build_proxy(layout, chunks=None, params: ProxyParams | None = None,
                progress: bool = False, max_chunks: int | None = None
                ) -> dict[ChunkKey, list[MeshPart]]:
    """Mesh parts per chunk for ``chunks`` (default: every chunk of the layout's area;
    at most limits.CHUNKS or ``max_chunks``)."""
    if chunks is not None:
        chunks = list(chunks)
        check_chunk_count(layout, len(chunks), max_chunks)
    builder = ProxyBuilder(layout, params)
    keys = chunks if chunks is not None else builder.chunks(max_chunks)
    it = keys
    if progress:
        # local import: not loaded for --help
        from tqdm import tqdm
        it = tqdm(keys, desc="proxy chunks", unit="chunk")
    return {k: builder.build(k) for k in it}
