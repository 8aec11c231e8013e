"""Lanelet2 map (.osm) → layout model, read with the ``lanelet2`` package's own IO,
projector, traffic rules and routing graph.

- The map is projected with ``LocalCartesianProjector`` (east-north-up around the origin, metres)
  on the ellipsoid; a node's ``ele`` is its z (the map's own height, ``_ele_as_z``).
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
  at the sign with the lanelets that refer to it; each light of a traffic-light rule →
  ``TrafficLight`` (facing the traffic of the lanelets that refer to it); other traffic signs
  → ``TrafficSign`` (kind from the sign type, ``signcodes``). A map with traffic-light rules
  lists its lights completely (``metadata.source.signalsComplete``).
- Points and line strings of type ``pole`` / ``street_lamp`` / ``bollard`` → ``Pole``; line
  strings ``fence``, ``wall``, ``guard_rail`` → ``Barrier`` (a guard rail is a ``RoadEdge`` too).
- Degenerate source geometry (``lanelet_geometry``, ``drop_far_markings``): a lanelet whose
  bounds differ in length by more than max(BOUND_SLACK_M, (BOUND_RATIO - 1) x the shorter)
  beyond what its turn explains (parallel bounds around a bend differ by their distance times
  the turn) has the longer bound cut to the stretch alongside the shorter (repaired; skipped
  if they still differ so); a lanelet whose bounds cross away from its ends is skipped; a lane marking that
  bounds no lanelet and lies more than FAR_MARKING_M from every lanelet is skipped. Each
  warns with the element id (an error with ``strict``).
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
from lsd3d_usd.geometry.polyline import (clean_ring, distance_to_polyline,
                                           distance_to_segments, resample)
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout.importers import ImportOptions, MapWarning, xml_root_name
from lsd3d_usd.layout.osmxml import bad_location, header_centre, osmium_errors

MAX_FILE_BYTES = 256 * 1024 * 1024
MAX_LANELETS = 200_000
FAR_WARN_M = 10_000.0        # float32 USD points keep ~1 mm only this close to the origin
FAR_ERROR_M = 100_000.0
# stop_sign: Autoware's subtype of the traffic_sign line string
STOP_SIGN_TYPES = re.compile(r"(^|[:_])(stop|stop_sign|de206|r1-1|206)$", re.IGNORECASE)
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
    centre = header_centre(path)
    if centre is not None:
        return centre, "file bounds"
    with osmium_errors(path):
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


def _ring(ll) -> np.ndarray:
    """Polygon of a lanelet: left bound, then the right bound backwards."""
    return np.concatenate([_arr(ll.leftBound), _arr(ll.rightBound)[::-1]])


def read_lanelet2(path: str | Path, options: ImportOptions | None = None) -> m.Layout:
    """Import a Lanelet2 map; see the module doc for the mapping."""

    options = options or ImportOptions()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    if p.stat().st_size > MAX_FILE_BYTES:
        raise InputError(f"{path}: {p.stat().st_size} bytes; Lanelet2 maps of at most "
                         f"{MAX_FILE_BYTES} bytes are read (lanelet2 holds the whole map in memory)")
    bad = bad_location(p)   # lanelet2 would project a NaN node silently
    if bad:
        raise InputError(f"{path}: {bad}; fix or remove the node")
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
    _ele_as_z(lmap, projector)
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
            geom = lanelet_geometry(path, ll, options)
            if geom is None:
                continue
            c, left_b, right_b = geom
            keep = np.ones(len(c), bool)
            keep[1:] = np.hypot(*np.diff(c[:, :2], axis=0).T) > 1e-9
            c = c[keep]
            if len(c) < 2:
                _warn(f"{path}: lanelet {ll.id}: zero-length centre line; skipped", options)
                continue
            w = distance_to_polyline(c, left_b) + distance_to_polyline(c, right_b)
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
            ring = clean_ring(np.concatenate([left_b, right_b[::-1]])) if ll.id in drive else None
            if ring is not None:
                layout.add(m.RoadArea(f"area_ll{ll.id}", polygon=ring))
        elif sub == "crosswalk":
            ring = clean_ring(_ring(ll))
            if ring is not None:
                layout.add(m.Crosswalk(f"crosswalk_ll{ll.id}", polygon=ring))
        elif sub in ("walkway", "shared_walkway"):
            ring = clean_ring(_ring(ll))
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
    map_signals(lmap, layout)
    map_furniture(lmap, layout)
    drop_far_markings(path, lmap, layout, options)
    _areas(path, lmap, layout, options, far)
    far.report(path, options)
    from lsd3d_usd.layout.georef import attach_origin
    attach_origin(layout, "lanelet2 origin (LocalCartesianProjector)")
    layout.reindex()
    return layout


def _ele_as_z(lmap, projector) -> None:
    """Lanelet2 / Autoware ``ele`` is the map's own z, not a height above the ellipsoid:
    LocalCartesianProjector's 3D east-north-up made a flat map sag by d²/2R (0.79 m at
    3.2 km) and scaled the plan by (1 + ele/R). Each point is put back on the tangent-plane
    frame of the ellipsoid's surface (the layout's geoReference) with z = ele. The round trip
    through ``reverse`` recovers the node's lat, lon and ele exactly."""
    from lanelet2.core import BasicPoint3d, GPSPoint
    for pt in lmap.pointLayer:
        g = projector.reverse(BasicPoint3d(pt.x, pt.y, pt.z))
        q = projector.forward(GPSPoint(g.lat, g.lon, 0.0))
        pt.x, pt.y, pt.z = q.x, q.y, g.alt


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
        ring = clean_ring(np.array([[p.x, p.y, p.z] for p in ar.outerBoundPolygon()]))
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


# ============================================================ signals, furniture, bad geometry

BOUND_RATIO = 2.0           # bounds differing by more than (ratio - 1) x the shorter: a spike
BOUND_SLACK_M = 5.0         # ... and by more than this (short lanelets), beyond their turn
END_ZONE_M = 1.0            # bounds may touch / cross this close to a lanelet's ends
FAR_MARKING_M = 15.0        # a lane marking this far from every lanelet is not of the road


def _length(xy: np.ndarray) -> float:
    return float(np.hypot(*np.diff(xy[:, :2], axis=0).T).sum()) if len(xy) > 1 else 0.0


def _cut(line: np.ndarray, a: float, b: float) -> np.ndarray:
    """The part of a polyline (N, 3) between arc lengths a < b."""
    seg = np.hypot(*np.diff(line[:, :2], axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    inner = line[(s > a) & (s < b)]
    at = lambda x: np.array([np.interp(x, s, line[:, k]) for k in range(3)])  # noqa: E731
    return np.vstack([at(a), inner, at(b)])


def _excess(short_b: np.ndarray, long_b: np.ndarray, diff: float) -> float:
    """How much two bounds differ in length beyond what parallel bounds around the shorter
    one's turn differ by (their distance times its net change of heading)."""
    if len(short_b) < 2 or len(long_b) < 2:
        return 0.0
    d = np.diff(short_b[:, :2], axis=0)
    d = d[np.hypot(*d.T) > 1e-9]
    turn = float(np.abs(np.sum(np.angle(np.exp(1j * np.diff(np.arctan2(d[:, 1], d[:, 0]))))))) \
        if len(d) > 1 else 0.0
    width = float(np.median(distance_to_segments(short_b[:, :2], long_b[:-1, :2], long_b[1:, :2])))
    return diff - width * turn


def _midline(left: np.ndarray, right: np.ndarray, n: int | None = None) -> np.ndarray:
    """Centre line of two bounds: the mean of points at equal fractions of their lengths."""
    n = n or max(len(left), len(right), 2)
    t = np.linspace(0.0, 1.0, n)
    return (resample(left, t) + resample(right, t)) / 2


def lanelet_geometry(path, ll, options: ImportOptions):
    """(centre line, left bound, right bound) of a lanelet as (N, 3) arrays, repaired or
    None (skipped, warned) by the rule in the module doc."""
    from shapely.geometry import LineString, Point
    left, right = _arr(ll.leftBound), _arr(ll.rightBound)
    la, lb = _length(left), _length(right)
    short, long_ = min(la, lb), max(la, lb)
    keep, cut = (left, right) if la < lb else (right, left)
    if _excess(keep, cut, long_ - short) > max(BOUND_SLACK_M, (BOUND_RATIO - 1) * short):
        line = LineString(cut[:, :2])
        a, b = sorted((line.project(Point(keep[0, :2])), line.project(Point(keep[-1, :2]))))
        what = f"lanelet {ll.id}: its {'right' if la < lb else 'left'} bound is {long_:.0f} m long, " \
               f"its {'left' if la < lb else 'right'} bound {short:.0f} m"
        trimmed = _cut(cut, a, b) if b - a > 1e-3 else None
        if trimmed is not None and _excess(keep, trimmed, abs(b - a - short)) <= \
                max(BOUND_SLACK_M, (BOUND_RATIO - 1) * min(short, b - a)):
            if la < lb:
                right = trimmed
            else:
                left = trimmed
            _warn(f"{path}: {what}; the longer bound is cut to the {b - a:.0f} m alongside the "
                  "other (repaired)", options)
            return _midline(left, right), left, right
        _warn(f"{path}: {what}, and no stretch of it runs alongside the other; skipped", options)
        return None
    if len(left) >= 2 and len(right) >= 2:
        cross = LineString(left[:, :2]).intersection(LineString(right[:, :2]))
        ends = [left[0, :2], left[-1, :2], right[0, :2], right[-1, :2]]
        pts = [g for g in getattr(cross, "geoms", [cross]) if not g.is_empty]
        for g in pts:
            q = np.asarray(g.coords)[:, :2] if g.geom_type != "Polygon" else np.zeros((0, 2))
            if any(min(np.hypot(*(e - x)) for e in ends) > END_ZONE_M for x in q):
                _warn(f"{path}: lanelet {ll.id}: its left and right bounds cross at "
                      f"({q[0, 0]:.1f}, {q[0, 1]:.1f}); skipped", options)
                return None
    return _arr(ll.centerline), left, right


def _facing(pos: np.ndarray, lane_ids, layout) -> float | None:
    """Heading that faces the traffic of ``lane_ids`` at their point nearest ``pos``."""
    best, yaw = np.inf, None
    for lid in lane_ids:
        try:
            ln = layout.lane_by_id(lid)
        except KeyError:
            continue
        a, b = ln.points[:-1, :2], ln.points[1:, :2]
        d = b - a
        t = np.clip(np.einsum("ij,ij->i", pos[:2] - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-18), 0, 1)
        dist = np.hypot(*(a + t[:, None] * d - pos[:2]).T)
        k = int(np.argmin(dist))
        if dist[k] < best:
            best, yaw = dist[k], float(np.arctan2(-d[k, 1], -d[k, 0]))
    return yaw


def _number_suffix(text: str) -> float:
    mt = re.search(r"[-_](\d+(?:\.\d+)?)$", str(text))
    return float(mt.group(1)) if mt else 0.0


def map_signals(lmap, layout) -> None:
    """TrafficLight per light of each traffic-light rule, TrafficSign per sign of each
    traffic-sign rule that is not a stop (those are StopSigns, ``_regulatory``)."""
    from lanelet2.core import TrafficLight, TrafficSign

    from lsd3d_usd.layout.signcodes import sign_kind, split_code
    users: dict[int, list[str]] = {}
    lanes = {ln.id for ln in layout.lanes}
    for ll in lmap.laneletLayer:
        for r in ll.regulatoryElements:
            if f"ll{ll.id}" in lanes:
                users.setdefault(r.id, []).append(f"ll{ll.id}")
    have = {f.id for f in layout.features()}
    for r in lmap.regulatoryElementLayer:
        if isinstance(r, TrafficLight):
            for k, light in enumerate(r.trafficLights):
                pts = np.array([[p.x, p.y, p.z] for p in light]).reshape(-1, 3)
                fid = f"light{r.id}_{k}"
                if not len(pts) or fid in have:
                    continue
                pos = np.append(pts[:, :2].mean(axis=0), 0.0)
                h = _number(light.attributes["height"]) if "height" in light.attributes else None
                top = float(pts[:, 2].max()) + (h or 0.8)
                d = pts[-1, :2] - pts[0, :2]
                yaw = _facing(pos, users.get(r.id, []), layout)
                if yaw is None:
                    yaw = float(np.arctan2(-d[0], d[1]))      # normal to the light's line
                layout.add(m.TrafficLight(fid, position=pos, heading=yaw,
                                          height=top if 2.0 <= top < 100 else 5.5,
                                          lane_ids=users.get(r.id, [])))
                have.add(fid)
        elif isinstance(r, TrafficSign) and not STOP_SIGN_TYPES.search(str(r.type() or "")):
            code = str(r.type() or "")
            country, sign = split_code(code)
            kind = sign_kind(country or "DE", sign)
            if kind in ("stop", "traffic_light"):
                continue
            for k, sg in enumerate(r.trafficSigns()):
                pts = np.array([[p.x, p.y, p.z] for p in sg]).reshape(-1, 3)
                fid = f"sign{r.id}_{k}"
                if not len(pts) or fid in have:
                    continue
                pos = np.append(pts[0, :2], 0.0)
                yaw = _facing(pos, users.get(r.id, []), layout)
                top = float(pts[:, 2].max())
                layout.add(m.TrafficSign(fid, position=pos, heading=yaw or 0.0, kind=kind,
                                         code=code, value=_number_suffix(code),
                                         height=top if 1.0 <= top < 100 else 2.5,
                                         lane_ids=users.get(r.id, [])))
                have.add(fid)
    if layout.traffic_lights:
        layout.metadata.setdefault("source", {})["signalsComplete"] = True


POLE_TYPES = {"pole": "pole", "post": "pole", "street_lamp": "street_lamp",
              "street_light": "street_lamp", "bollard": "bollard"}
BARRIER_TYPES = {"fence": ("fence", 1.5, 0.05), "wall": ("wall", 2.5, 0.3),
                 "guard_rail": ("guard_rail", 0.8, 0.3)}


def map_furniture(lmap, layout) -> None:
    """Poles (points, or the foot of line strings, of a pole type) and barriers (line strings
    fence, wall, guard_rail)."""
    have = {f.id for f in layout.features()}
    for pt in lmap.pointLayer:
        a = pt.attributes
        kind = POLE_TYPES.get(a["type"] if "type" in a else "")
        if kind and f"pole{pt.id}" not in have:
            h = _number(a["height"]) if "height" in a else None
            layout.add(m.Pole(f"pole{pt.id}", position=[pt.x, pt.y, pt.z], kind=kind,
                              height=h or {"street_lamp": 7.0, "bollard": 1.0}.get(kind, 4.0)))
    for ls in lmap.lineStringLayer:
        a = ls.attributes
        typ = a["type"] if "type" in a else ""
        pts = _arr(ls)
        if typ in POLE_TYPES and len(pts) and f"pole{ls.id}" not in have:
            kind = POLE_TYPES[typ]
            h = float(np.ptp(pts[:, 2])) or {"street_lamp": 7.0, "bollard": 1.0}.get(kind, 4.0)
            layout.add(m.Pole(f"pole{ls.id}", position=pts[0], kind=kind, height=h))
        elif typ in BARRIER_TYPES:
            keep = np.ones(len(pts), bool)
            keep[1:] = np.hypot(*np.diff(pts[:, :2], axis=0).T) > 1e-9
            pts = pts[keep]
            if len(pts) < 2:
                continue
            kind, h, w = BARRIER_TYPES[typ]
            hh = _number(a["height"]) if "height" in a else None
            layout.add(m.Barrier(f"barrier{ls.id}", points=pts, kind=kind, height=hh or h, width=w))


def drop_far_markings(path, lmap, layout, options: ImportOptions) -> None:
    """Remove the RoadLines of lane markings that bound no imported lanelet and lie more than
    FAR_MARKING_M from every imported lanelet (each warned with its id)."""
    import shapely
    from shapely.geometry import LineString, Polygon
    kept = {int(mt.group(1)) for f in layout.features()
            if (mt := re.match(r"^(?:area_|crosswalk_|walk_)?ll(\d+)$", f.id))}
    bounds = set()
    rings = []
    for ll in lmap.laneletLayer:
        if ll.id not in kept:       # a skipped lanelet's bounds do not keep a marking
            continue
        bounds.update((ll.leftBound.id, ll.rightBound.id))
        ring = _arr(ll.leftBound)[:, :2].tolist() + _arr(ll.rightBound)[::-1, :2].tolist()
        if len(ring) >= 3:
            rings.append(Polygon(ring).buffer(0) if not Polygon(ring).is_valid else Polygon(ring))
    if not rings:
        return
    area = shapely.union_all([r for r in rings if not r.is_empty])
    drop = set()
    for rl in layout.road_lines:
        if not rl.id.startswith("ls"):
            continue
        try:
            lsid = int(rl.id[2:])
        except ValueError:
            continue
        if lsid in bounds:
            continue
        d = area.distance(LineString(rl.points[:, :2]))
        if d > FAR_MARKING_M:
            _warn(f"{path}: line string {lsid}: a lane marking {d:.0f} m from the nearest "
                  f"lanelet (more than {FAR_MARKING_M:g} m); skipped", options)
            drop.add(rl.id)
    if drop:
        layout.road_lines = [rl for rl in layout.road_lines if rl.id not in drop]
