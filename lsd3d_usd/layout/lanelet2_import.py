"""Lanelet2 map (.osm) → layout model, read with the ``lanelet2`` package's own IO,
projector, traffic rules and routing graph.

- The map is projected with ``LocalCartesianProjector`` (east-north-up around the origin, metres).
  Origin: ``--origin LAT,LON``; else the ``<bounds>`` of the file's header (its centre); else the
  centre of the nodes' extent. The origin goes into the layout's metadata and provenance.
- Lanelets that vehicles may use (German traffic rules of lanelet2, participant vehicle) become
  ``LaneCenter``\\ s from lanelet2's centre line; bicycle lanes become ``bike`` lanes. Widths at
  each centre-line vertex are its distances to the left and right bounds; successors,
  predecessors and left/right neighbours come from the routing graph (one per participant);
  a lanelet that is not one-way gets ``direction = both``. Speed limits from the traffic rules.
- Crosswalk lanelets → ``Crosswalk``; walkway lanelets and areas → ``Sidewalk``; each drivable
  lanelet's area → ``RoadArea``.
- Line strings: ``curbstone``, ``road_border``, ``guard_rail`` → ``RoadEdge`` (turned so the road
  lies on its left); ``line_thin`` / ``line_thick`` → ``RoadLine`` (dashed → broken, two-part
  subtypes → double, ``color`` yellow); ``stop_line`` → ``StopLine``.
- Regulatory elements: traffic lights, right of way and all-way stops → the ``StopLine``\\ s of
  their reference lines; stop signs (traffic signs of a stop type, all-way stops) → ``StopSign``
  at the sign with the lanelets that refer to it. The lights themselves have no layout feature.
- Areas: ``building`` → ``Building`` (``height`` attribute), ``vegetation`` and
  ``traffic_island`` → ``VegetationZone`` (grass), ``parking`` → ``ParkingSpot`` (its minimum
  rotated rectangle, not occupied), ``walkway`` → ``Sidewalk``.

Errors lanelet2 reports while loading (missing members, broken bounds) become warnings naming
the primitive; lanelets it names are skipped (``strict``: an error).
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import lanelet2
import numpy as np
import osmium
from lanelet2 import routing, traffic_rules
from lanelet2.core import (
    AllWayStop,
    RightOfWay,
    TrafficLight,
    TrafficSign,
    createMapFromLanelets,
)
from lanelet2.io import Origin
from lanelet2.projection import LocalCartesianProjector
from shapely.geometry import Polygon

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout.fitting import _dist_to_segments
from lsd3d_usd.layout.importers import ImportOptions, MapWarning, xml_root_name

MAX_FILE_BYTES = 256 * 1024 * 1024
MAX_LANELETS = 200_000
FAR_WARN_M = 10_000.0        # float32 USD points keep ~1 mm only this close to the origin
FAR_ERROR_M = 100_000.0
STOP_SIGN_TYPES = re.compile(r"(^|[:_])(stop|de206|r1-1|206)$", re.IGNORECASE)
_LANELET_TAG = re.compile(rb"""<tag\s+k\s*=\s*["']type["']\s+v\s*=\s*["']lanelet["']""")


def sniff(path: Path, head: bytes) -> bool:
    """OSM XML holding at least one relation tagged type=lanelet (scanned in bounded chunks)."""
    if xml_root_name(head) != "osm":
        return False
    if _LANELET_TAG.search(head):
        return True
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        return False
    tail = b""
    with open(path, "rb") as f:
        f.seek(len(head))
        while chunk := f.read(1 << 20):
            if _LANELET_TAG.search(tail + chunk):
                return True
            tail = chunk[-128:]
    return False


def file_origin(path: Path) -> tuple[tuple[float, float], str]:
    """(lat, lon) of the file's own origin and where it came from: the header's bounds, else the
    centre of the nodes' extent (read with osmium)."""
    reader = osmium.io.Reader(str(path), osmium.osm.osm_entity_bits.NOTHING)
    try:
        box = reader.header().box()
    finally:
        reader.close()
    if box.valid():
        bl, tr = box.bottom_left, box.top_right
        return ((bl.lat + tr.lat) / 2, (bl.lon + tr.lon) / 2), "file bounds"
    lat0 = lon0 = np.inf
    lat1 = lon1 = -np.inf
    for n in osmium.FileProcessor(str(path), osmium.osm.NODE):
        if n.location.valid():
            lat0, lat1 = min(lat0, n.location.lat), max(lat1, n.location.lat)
            lon0, lon1 = min(lon0, n.location.lon), max(lon1, n.location.lon)
    if not np.isfinite(lat0):
        raise InputError(f"{path}: no node with a valid location")
    return ((lat0 + lat1) / 2, (lon0 + lon1) / 2), "node extent"


def check_origin(origin, what: str) -> tuple[float, float]:
    lat, lon = (float(v) for v in origin)
    if not (-90 < lat < 90 and -180 <= lon <= 180):
        raise InputError(f"{what}: origin {lat}, {lon} is not a latitude, longitude in degrees")
    return lat, lon


def _arr(ls) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in ls], dtype=np.float64).reshape(-1, 3)


def _dist_to_polyline(q: np.ndarray, line: np.ndarray) -> np.ndarray:
    if len(line) == 1:
        return np.hypot(*(q[:, :2] - line[0, :2]).T)
    return _dist_to_segments(q[:, :2], line[:-1, :2], line[1:, :2])


def _ring(ll) -> np.ndarray:
    """Polygon of a lanelet: left bound, then the right bound backwards."""
    return np.concatenate([_arr(ll.leftBound), _arr(ll.rightBound)[::-1]])


def _clean_ring(poly: np.ndarray) -> np.ndarray | None:
    keep = np.ones(len(poly), bool)
    keep[1:] = np.hypot(*np.diff(poly[:, :2], axis=0).T) > 1e-9
    poly = poly[keep]
    if len(poly) > 3 and np.allclose(poly[0, :2], poly[-1, :2]):
        poly = poly[:-1]
    if len(poly) < 3 or abs(m.polygon_area(poly)) < 1e-6:
        return None
    return poly if m.polygon_area(poly) > 0 else poly[::-1].copy()


def read_lanelet2(path: str | Path, options: ImportOptions | None = None) -> m.Layout:
    """Import a Lanelet2 map; see the module doc for the mapping."""

    options = options or ImportOptions()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    if p.stat().st_size > MAX_FILE_BYTES:
        raise InputError(f"{path}: {p.stat().st_size} bytes; Lanelet2 maps of at most "
                         f"{MAX_FILE_BYTES} bytes are read (lanelet2 holds the whole map in memory)")
    if options.origin is not None:
        origin, origin_from = check_origin(options.origin, f"{path}: --origin"), "flag"
    else:
        origin, origin_from = file_origin(p)
        origin = check_origin(origin, str(path))
    projector = LocalCartesianProjector(Origin(origin[0], origin[1]))
    try:
        lmap, errors = lanelet2.io.loadRobust(str(p), projector)
    except RuntimeError as e:
        raise InputError(f"{path}: lanelet2 cannot read it: {e}") from None
    bad_ids = set()
    for err in errors:
        err = err.strip().lstrip("- \t")
        if not err or err.startswith("Errors ocurred"):
            continue
        bad_ids.update(int(x) for x in re.findall(r"(?:id|primitive) (\d+)", err))
        _warn(f"{path}: lanelet2: {err}", options)
    n_ll = len(lmap.laneletLayer)
    if n_ll > MAX_LANELETS:
        raise InputError(f"{path}: {n_ll} lanelets; at most {MAX_LANELETS} are imported")

    vehicle = traffic_rules.create(traffic_rules.Locations.Germany, traffic_rules.Participants.Vehicle)
    bicycle = traffic_rules.create(traffic_rules.Locations.Germany, traffic_rules.Participants.Bicycle)
    layout = m.Layout(metadata={"source": {
        "format": "lanelet2", "file": p.name, "origin": [origin[0], origin[1]],
        "originFrom": origin_from, "projector": "lanelet2 LocalCartesianProjector"}})

    def usable(ll) -> bool:
        if ll.id in bad_ids or len(ll.leftBound) < 2 or len(ll.rightBound) < 2:
            if ll.id not in bad_ids:
                _warn(f"{path}: lanelet {ll.id}: a bound has fewer than 2 points; skipped", options)
            return False
        return True

    lanelets = [ll for ll in lmap.laneletLayer if usable(ll)]
    drive = {ll.id for ll in lanelets if vehicle.canPass(ll)}
    bike = {ll.id for ll in lanelets if ll.id not in drive and bicycle.canPass(ll)
            and _attr(ll, "subtype") == "bicycle_lane"}
    # lanelet2's RoutingGraph crashes the process on lanelets with broken bounds: it gets a
    # map of the usable lanelets only
    graph_map = createMapFromLanelets([ll for ll in lanelets if ll.id in drive or ll.id in bike]) \
        if (drive or bike) else None
    graphs = {}
    if drive:
        graphs["vehicle"] = routing.RoutingGraph(graph_map, vehicle)
    if bike:
        graphs["bicycle"] = routing.RoutingGraph(graph_map, bicycle)

    def lid(x) -> str:
        return f"ll{x.id}"

    far = _Far(path)

    for ll in lanelets:
        sub = _attr(ll, "subtype", "road")
        if ll.id in drive or ll.id in bike:
            far.note(f"lanelet {ll.id}", _ring(ll))
            kind = "vehicle" if ll.id in drive else "bicycle"
            rules, g = (vehicle if kind == "vehicle" else bicycle), graphs[kind]
            c = _arr(ll.centerline)
            keep = np.ones(len(c), bool)
            keep[1:] = np.hypot(*np.diff(c[:, :2], axis=0).T) > 1e-9
            c = c[keep]
            if len(c) < 2:
                _warn(f"{path}: lanelet {ll.id}: zero-length centre line; skipped", options)
                continue
            w = _dist_to_polyline(c, _arr(ll.leftBound)) + _dist_to_polyline(c, _arr(ll.rightBound))
            lane_type = {"bus_lane": "bus", "bicycle_lane": "bike"}.get(sub, "driving" if kind == "vehicle" else "bike")
            layout.add(m.LaneCenter(
                lid(ll), points=c, widths=w, lane_type=lane_type,
                direction="forward" if rules.isOneWay(ll) else "both",
                speed_limit_mps=float(rules.speedLimit(ll).speedLimit) / 3.6,
                successors=[lid(x) for x in g.following(ll)],
                predecessors=[lid(x) for x in g.previous(ll)],
                left_neighbors=[lid(x) for x in (g.left(ll), g.adjacentLeft(ll)) if x is not None],
                right_neighbors=[lid(x) for x in (g.right(ll), g.adjacentRight(ll)) if x is not None],
                road_id=_attr(ll, "road_id")))
            ring = _clean_ring(_ring(ll)) if ll.id in drive else None
            if ring is not None:
                layout.add(m.RoadArea(f"area_ll{ll.id}", polygon=ring))
        elif sub == "crosswalk":
            ring = _clean_ring(_ring(ll))
            if ring is not None:
                layout.add(m.Crosswalk(f"crosswalk_ll{ll.id}", polygon=ring))
        elif sub in ("walkway", "shared_walkway"):
            ring = _clean_ring(_ring(ll))
            if ring is not None:
                layout.add(m.Sidewalk(f"walk_ll{ll.id}", polygon=ring))
    if not layout.lanes:
        raise InputError(f"{path}: no drivable lanelet ({n_ll} lanelets, none usable by vehicles "
                         "or bicycles)")
    known = {ln.id for ln in layout.lanes}
    for ln in layout.lanes:   # links to lanelets that were skipped
        for attr in ("successors", "predecessors", "left_neighbors", "right_neighbors"):
            setattr(ln, attr, [x for x in getattr(ln, attr) if x in known])

    _line_strings(path, lmap, lanelets, drive, layout, options)
    _regulatory(lmap, layout)
    _areas(path, lmap, layout, options, far)
    far.report(path, options)
    layout.reindex()
    return layout


def _line_strings(path, lmap, lanelets, drive, layout, options) -> None:
    side = {}   # line string id -> a drivable lanelet it bounds, and whether as left bound
    for ll in lanelets:
        if ll.id in drive:
            side.setdefault(ll.leftBound.id, (ll, True))
            side.setdefault(ll.rightBound.id, (ll, False))
    for ls in lmap.lineStringLayer:
        a = ls.attributes
        typ = a["type"] if "type" in a else ""
        sub = a["subtype"] if "subtype" in a else ""
        if typ not in ("curbstone", "road_border", "guard_rail", "line_thin", "line_thick", "stop_line"):
            continue
        pts = _arr(ls)
        keep = np.ones(len(pts), bool)
        keep[1:] = np.hypot(*np.diff(pts[:, :2], axis=0).T) > 1e-9
        pts = pts[keep]
        if len(pts) < 2:
            _warn(f"{path}: line string {ls.id}: fewer than 2 distinct points; skipped", options)
            continue
        if typ in ("curbstone", "road_border", "guard_rail"):
            if ls.id in side:   # road on the left: a lanelet's left bound runs the other way
                ll, is_left = side[ls.id]
                c = _arr(ll.centerline)[len(ll.centerline) // 2]
                mid = len(pts) // 2
                d = pts[min(mid + 1, len(pts) - 1)] - pts[max(mid - 1, 0)]
                q = c - pts[mid]
                if d[0] * q[1] - d[1] * q[0] < 0:
                    pts = pts[::-1].copy()
            layout.add(m.RoadEdge(f"ls{ls.id}", points=pts, kind="boundary"))
        elif typ == "stop_line":
            layout.add(m.StopLine(f"ls{ls.id}", points=pts))
        else:
            parts = [x for x in sub.split("_") if x] or ["solid"]
            color = a["color"] if "color" in a else "white"
            layout.add(m.RoadLine(f"ls{ls.id}", points=pts,
                                  kind="broken" if all(x == "dashed" for x in parts) else "solid",
                                  color="yellow" if color == "yellow" else "white",
                                  double=len(parts) > 1))


def _regulatory(lmap, layout) -> None:
    have = {f.id for f in layout.features()}
    users: dict[int, list[str]] = {}
    lanes = {ln.id for ln in layout.lanes}
    for ll in lmap.laneletLayer:
        for re_ in ll.regulatoryElements:
            if f"ll{ll.id}" in lanes:
                users.setdefault(re_.id, []).append(f"ll{ll.id}")
    for r in lmap.regulatoryElementLayer:
        stop_lines, signs = [], []
        if isinstance(r, TrafficLight):
            stop_lines = [] if r.stopLine is None else [r.stopLine]
        elif isinstance(r, RightOfWay):
            stop_lines = [] if r.stopLine is None else [r.stopLine]
        elif isinstance(r, AllWayStop):
            stop_lines = [s for s in r.stopLines() if s is not None]
            signs = list(r.trafficSigns())
        elif isinstance(r, TrafficSign):
            if STOP_SIGN_TYPES.search(str(r.type() or "")):
                signs = list(r.trafficSigns())
                stop_lines = list(r.refLines())
        for ls in stop_lines:
            fid = f"ls{ls.id}"
            pts = _arr(ls)
            if fid not in have and len(pts) >= 2 and np.hypot(*(pts[-1, :2] - pts[0, :2])) > 1e-9:
                layout.add(m.StopLine(fid, points=pts))
                have.add(fid)
        for k, sg in enumerate(signs):
            pts = _arr(sg)
            if len(pts):
                fid = f"sign{r.id}_{k}"
                layout.add(m.StopSign(fid, position=pts[0], lane_ids=users.get(r.id, [])))
                have.add(fid)


def _areas(path, lmap, layout, options, far) -> None:
    for ar in lmap.areaLayer:
        a = ar.attributes
        sub = a["subtype"] if "subtype" in a else ""
        if sub not in ("building", "vegetation", "traffic_island", "parking", "walkway"):
            continue
        ring = _clean_ring(np.array([[p.x, p.y, p.z] for p in ar.outerBoundPolygon()]))
        if ring is None:
            _warn(f"{path}: area {ar.id}: degenerate outer bound; skipped", options)
            continue
        far.note(f"area {ar.id}", ring)
        if sub == "building":
            h = _number(a["height"]) if "height" in a else None
            layout.add(m.Building(f"area{ar.id}", footprint=ring, height_hint=h or 12.0))
        elif sub in ("vegetation", "traffic_island"):
            layout.add(m.VegetationZone(f"area{ar.id}", polygon=ring, kind="grass"))
        elif sub == "walkway":
            layout.add(m.Sidewalk(f"area{ar.id}", polygon=ring))
        else:
            rect = np.asarray(Polygon(ring[:, :2]).minimum_rotated_rectangle.exterior.coords)[:4]
            e1, e2 = rect[1] - rect[0], rect[2] - rect[1]
            long_, short = (e1, e2) if np.hypot(*e1) >= np.hypot(*e2) else (e2, e1)
            layout.add(m.ParkingSpot(f"area{ar.id}", center=np.append(rect.mean(axis=0), ring[:, 2].mean()),
                                     heading=float(np.arctan2(long_[1], long_[0])),
                                     length=float(np.hypot(*long_)), width=float(np.hypot(*short)),
                                     occupied=False))


def _number(text) -> float | None:
    mt = re.match(r"\s*([0-9]+(?:\.[0-9]+)?)", str(text))
    v = float(mt.group(1)) if mt else None
    return v if v and 0 < v < 1000 else None


def _attr(prim, key: str, default: str = "") -> str:
    return str(prim.attributes[key]) if key in prim.attributes else default


class _Far:
    """The element farthest from the origin: one error or warning per import, naming it."""

    def __init__(self, path):
        self.path, self.dist, self.what = path, 0.0, None

    def note(self, what: str, pts: np.ndarray) -> None:
        d = float(np.hypot(pts[:, 0], pts[:, 1]).max()) if len(pts) else 0.0
        if d > self.dist:
            self.dist, self.what = d, what
        if d > FAR_ERROR_M:
            raise InputError(f"{self.path}: {what} lies {d / 1000:.0f} km from the origin; pass --origin "
                             "LAT,LON near the map")

    def report(self, path, options: ImportOptions) -> None:
        if self.dist > FAR_WARN_M:
            _warn(f"{path}: {self.what} lies {self.dist / 1000:.1f} km from the origin (USD stores "
                  "points as float32: ~1 mm or worse this far out); pass --origin near the map",
                  options)


def _warn(msg: str, options: ImportOptions) -> None:
    if options.strict:
        raise InputError(msg)
    warnings.warn(msg, MapWarning, stacklevel=3)
