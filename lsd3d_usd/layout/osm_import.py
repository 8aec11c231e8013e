"""OpenStreetMap (.osm XML, .osm.pbf) → layout model, read with ``osmium`` (pyosmium).

Three streaming passes, so memory follows the area read, not the file: (1) nodes: the ids of
the nodes inside ``--bbox`` and the tagged point features there (``osm_features.point_wanted``); (2) ways with a relevant key
that touch one of those nodes; (3) nodes again: the locations of the nodes those ways use.
Counts are checked against limits while reading, before anything grows past them.

Projection: lanelet2's ``LocalCartesianProjector`` (east-north-up metres) around the origin:
``--origin LAT,LON``; else the centre of ``--bbox``; else of the header's bounds; else of
the nodes' extent.

Mapping (defaults per highway class in ``HIGHWAY``: lanes when untagged, lane width):

- ``highway`` ways (motorway … service, living_street, their ``_link``\\ s; ``cycleway`` as a
  bike lane) are split at nodes shared with other highways (junctions). Lane count from
  ``lanes`` (``lanes:forward`` / ``lanes:backward``), ``oneway`` (yes/1/true/-1; roundabouts and
  motorways are one-way), width from ``width`` / lanes or the class default; a two-way road with
  one lane is one lane of direction ``both``. Lanes are offset from the way's centre line
  (right-hand traffic). At a junction the roads are cut back and every incoming lane is joined
  to the outgoing lanes of the other roads (straight on lane by lane, right turns from the
  rightmost lane, left turns from the leftmost) by Hermite connectors (``is_junction``).
- Road surface: the union of the roads' and junctions' areas → ``RoadArea`` polygons, whose
  boundaries are the ``RoadEdge``\\ s; ``sidewalk=both|left|right`` → 2 m ``Sidewalk`` strips.
- Nodes: ``highway=crossing`` on a road → ``Crosswalk`` (3 m deep, across the road);
  ``highway=stop`` → ``StopSign`` beside the road for its lanes; ``natural=tree`` → ``Tree``
  (``height``, ``diameter_crown``); ``natural=tree_row`` ways → a tree every 8 m.
- Closed ways: ``building`` → ``Building`` (``height``, else ``building:levels`` × 3 m;
  ``floors_hint`` = levels); ``leisure=park|garden`` → park, ``landuse=grass|meadow|
  village_green|recreation_ground`` → grass, ``natural=wood`` / ``landuse=forest`` → forest,
  ``natural=scrub|heath`` → shrub (``VegetationZone``).
- Signals, signs, street lamps, bollards, barriers, hedges, crossing ways, bad highway ways
  and the clip at ``--bbox`` or the file's ``<bounds>``: ``osm_features``.
- Heights: node ``ele`` (metres) → z, the map's own height as in Lanelet2: ``osm_heights``.
- Not read: multipolygon relations (buildings and parks mapped as relations), turn
  restrictions, ``turn:lanes``, parking.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import osmium
import shapely
from lanelet2.core import GPSPoint
from lanelet2.io import Origin
from lanelet2.projection import LocalCartesianProjector
from shapely.geometry import LineString, Point, Polygon
from shapely.geometry import box as shp_box
from shapely.geometry.polygon import orient
from shapely.ops import substring

from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry.polyline import offset_polyline
from lsd3d_usd.limits import OSM_WAY_NODES
from lsd3d_usd.layout import blocks as B
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout import roadnet as R
from lsd3d_usd.layout.importers import ImportOptions, MapWarning, xml_root_name
from lsd3d_usd.layout.lanelet2_import import FAR_ERROR_M, FAR_WARN_M, check_origin
from lsd3d_usd.layout.osmxml import header_centre, osmium_errors
from lsd3d_usd.layout.osm_heights import apply_heights, node_heights
from lsd3d_usd.layout.osm_features import (clip_area, map_features, point_wanted, record_clip,
                                           sound_highways)

MAX_FILE_BYTES = 4 * 1024**3
MAX_NODES = 2_000_000       # nodes inside the area (ids held in memory)
MAX_WAYS = 200_000          # relevant ways touching the area
SIDEWALK_WIDTH = 2.0
CROSSWALK_DEPTH = 3.0
TREE_ROW_SPACING = 8.0
LEVEL_HEIGHT = 3.0

# class -> (lanes when untagged, lane width m)
HIGHWAY = {
    "motorway": (2, 3.75), "trunk": (2, 3.5), "primary": (2, 3.5), "secondary": (2, 3.5),
    "tertiary": (2, 3.25), "unclassified": (2, 3.0), "residential": (2, 3.0), "road": (2, 3.0),
    "motorway_link": (1, 3.5), "trunk_link": (1, 3.5), "primary_link": (1, 3.5),
    "secondary_link": (1, 3.5), "tertiary_link": (1, 3.25), "service": (1, 3.0),
    "living_street": (1, 3.0), "busway": (1, 3.5), "cycleway": (1, 1.5),
}
VEGETATION = {("leisure", "park"): "park", ("leisure", "garden"): "park",
              ("landuse", "grass"): "grass", ("landuse", "meadow"): "grass",
              ("landuse", "village_green"): "grass", ("landuse", "recreation_ground"): "grass",
              ("natural", "wood"): "forest", ("landuse", "forest"): "forest",
              ("natural", "scrub"): "shrub", ("natural", "heath"): "shrub"}
KEYS = ("highway", "building", "natural", "landuse", "leisure", "barrier", "footway")


def sniff(path: Path, head: bytes) -> bool:
    # PBF: a 4-byte BlobHeader length, then a BlobHeader of type "OSMHeader"
    return xml_root_name(head) == "osm" or b"OSMHeader" in head[:64]


def _num(text) -> float | None:
    mt = re.match(r"\s*([0-9]+(?:[.,][0-9]+)?)\s*(m|ft|')?\s*$", str(text or ""))
    if not mt:
        return None
    v = float(mt.group(1).replace(",", "."))
    return v * 0.3048 if mt.group(2) in ("ft", "'") else v


def _warn(msg: str, options: ImportOptions) -> None:
    if options.strict:
        raise InputError(msg)
    warnings.warn(msg, MapWarning, stacklevel=3)


# ================================================================ reading

def _read(path: Path, options: ImportOptions):
    """(point features [(id, tags, lat, lon)], ways [(id, tags, [node ids])], locations
    {node id: (lat, lon)}, the ways' nodes' ``ele`` texts {node id: text}, nodes' extent) of
    the area."""
    bbox = options.bbox
    if bbox is not None:
        x0, y0, x1, y1 = bbox
        if not (-180 <= x0 < x1 <= 180 and -90 <= y0 < y1 <= 90):
            raise InputError(f"--bbox {bbox}: expected MINLON,MINLAT,MAXLON,MAXLAT with min < max")
    inside: set[int] = set()
    points = []
    ext = [np.inf, np.inf, -np.inf, -np.inf]
    with osmium_errors(path):
        for n in osmium.FileProcessor(str(path), osmium.osm.NODE):
            loc = n.location
            if not loc.valid():
                continue
            lat, lon = loc.lat, loc.lon
            if bbox is not None and not (bbox[0] <= lon <= bbox[2] and bbox[1] <= lat <= bbox[3]):
                continue
            ext = [min(ext[0], lat), min(ext[1], lon), max(ext[2], lat), max(ext[3], lon)]
            if bbox is not None:
                inside.add(n.id)
                if len(inside) > MAX_NODES:
                    raise InputError(f"{path}: more than {MAX_NODES} nodes in the area; choose a "
                                     "smaller --bbox")
            t = n.tags
            if point_wanted(t):
                points.append((n.id, dict(t), lat, lon))
        ways = []
        needed: set[int] = set()
        for w in osmium.FileProcessor(str(path), osmium.osm.WAY).with_filter(osmium.filter.KeyFilter(*KEYS)):
            if not OSM_WAY_NODES.ok(len(w.nodes)):
                _warn(OSM_WAY_NODES.message(len(w.nodes), f"{path}: way {w.id}") + "; way skipped",
                      options)
                continue
            refs = [nd.ref for nd in w.nodes]
            if bbox is not None and not any(r in inside for r in refs):
                continue
            ways.append((w.id, dict(w.tags), refs))
            needed.update(refs)
            if len(ways) > MAX_WAYS or len(needed) > MAX_NODES:
                raise InputError(f"{path}: more than {MAX_WAYS} ways or {MAX_NODES} of their nodes in "
                                 "the area; choose a smaller --bbox")
        locs, eles = {}, {}
        for n in osmium.FileProcessor(str(path), osmium.osm.NODE):
            if n.id in needed and n.location.valid():
                locs[n.id] = (n.location.lat, n.location.lon)
                if "ele" in n.tags:
                    eles[n.id] = n.tags["ele"]
    return points, ways, locs, eles, ext


# ================================================================ import

def read_osm(path: str | Path, options: ImportOptions | None = None) -> m.Layout:
    """Import an OpenStreetMap file; see the module doc for the mapping."""

    options = options or ImportOptions()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    if p.stat().st_size > MAX_FILE_BYTES:
        raise InputError(f"{path}: {p.stat().st_size} bytes; at most {MAX_FILE_BYTES} are read")
    clip_box, clip_from = clip_area(p, options)
    points, ways, locs, eles, ext = _read(p, options)
    if not ways and not np.isfinite(ext[0]) and options.bbox is None:
        raise InputError(f"{path}: no nodes or ways could be read (an empty or truncated file)")
    if options.origin is not None:
        origin, origin_from = check_origin(options.origin, f"{path}: --origin"), "flag"
    elif options.bbox is not None:
        b = options.bbox
        origin, origin_from = ((b[1] + b[3]) / 2, (b[0] + b[2]) / 2), "bbox"
    else:
        centre = header_centre(p)
        if centre is not None:
            origin, origin_from = centre, "file bounds"
        elif np.isfinite(ext[0]):
            origin, origin_from = ((ext[0] + ext[2]) / 2, (ext[1] + ext[3]) / 2), "node extent"
        else:
            raise InputError(f"{path}: no node with a valid location in the area")
    origin = check_origin(origin, str(path))
    proj = LocalCartesianProjector(Origin(origin[0], origin[1]))

    def xy(lat, lon) -> np.ndarray:
        q = proj.forward(GPSPoint(lat, lon, 0.0))
        return np.array([q.x, q.y])

    xy_of = {nid: xy(*ll) for nid, ll in locs.items()}
    layout = m.Layout(metadata={"source": {
        "format": "osm", "file": p.name, "origin": [origin[0], origin[1]], "originFrom": origin_from,
        "projector": "lanelet2 LocalCartesianProjector"}})
    clip = None
    if options.bbox is not None:
        layout.metadata["source"]["bbox"] = list(options.bbox)
    if clip_box is not None:
        b = clip_box
        corners = np.array([xy(b[1], b[0]), xy(b[1], b[2]), xy(b[3], b[2]), xy(b[3], b[0])])
        (cx0, cy0), (cx1, cy1) = corners.min(axis=0), corners.max(axis=0)
        clip = shp_box(cx0, cy0, cx1, cy1)
        layout.extent = ((float(cx0), float(cy0)), (float(cx1), float(cy1)))

    cut_ways: dict = {}   # with --bbox: ways cut at the file's own edge, warned once

    def coords(wid, refs) -> np.ndarray | None:
        missing = [r for r in refs if r not in xy_of]
        if missing:
            if options.bbox is None:
                _warn(f"{path}: way {wid}: references node {missing[0]}, which the file lacks; "
                      "way skipped", options)
            else:   # an extract's ways often run past its edge: one warning for all of them
                cut_ways.setdefault(wid, missing[0])
            return None
        return np.array([xy_of[r] for r in refs])

    far = _far_check(path, xy_of)
    roads = [(wid, t, refs) for wid, t, refs in ways if t.get("highway") in HIGHWAY
             and t.get("area") != "yes"]
    roads = sound_highways(path, roads, xy_of, options)
    _highways(path, roads, coords, clip, layout, points, xy, options)
    _areas(path, ways, coords, clip, layout, options)
    _trees(points, ways, coords, clip, layout, xy)
    map_features(path, points, ways, coords, clip, layout, xy, options)
    record_clip(layout, clip, clip_box, clip_from, options)
    zmap = node_heights(path, eles, ways, xy_of, lambda msg: _warn(msg, options))
    apply_heights(layout, zmap, roads, ways, xy_of)
    if cut_ways:
        wid, nid = next(iter(cut_ways.items()))
        _warn(f"{path}: {len(cut_ways)} way(s) reference nodes the file lacks (first: way {wid}, "
              f"node {nid}), e.g. cut at the file's edge; those ways skipped", options)
    if not layout.lanes:
        raise InputError(f"{path}: no drivable highway in the {'area' if clip is not None else 'file'} "
                         f"({len(roads)} highway ways read)")
    if far:
        _warn(far, options)
    from lsd3d_usd.layout.georef import attach_origin
    attach_origin(layout, "osm origin (LocalCartesianProjector)")
    layout.reindex()
    return layout


def _far_check(path, xy_of) -> str | None:
    if not xy_of:
        return None
    ids = np.fromiter(xy_of.keys(), dtype=np.int64, count=len(xy_of))
    d = np.hypot(*np.array(list(xy_of.values())).T)
    k = int(np.argmax(d))
    if d[k] > FAR_ERROR_M:
        raise InputError(f"{path}: node {ids[k]} lies {d[k] / 1000:.0f} km from the origin; pass "
                         "--origin LAT,LON or --bbox near the area")
    if d[k] > FAR_WARN_M:
        return (f"{path}: node {ids[k]} lies {d[k] / 1000:.1f} km from the origin (USD stores points "
                "as float32: ~1 mm or worse this far out); pass --origin or --bbox")
    return None


def _lanes_of(t: dict) -> tuple[int, int, float, bool]:
    """(forward lanes, backward lanes, lane width, one lane for both directions)."""
    cls = t["highway"]
    default_n, default_w = HIGHWAY[cls]
    oneway = t.get("oneway", "")
    one = oneway in ("yes", "true", "1", "-1") or t.get("junction") in ("roundabout", "circular") \
        or (cls in ("motorway", "motorway_link") and oneway != "no")
    n = _num(t.get("lanes"))
    n = int(n) if n and 1 <= n <= 12 else (default_n if not one or cls != "motorway" else 2)
    fwd, bwd = _num(t.get("lanes:forward")), _num(t.get("lanes:backward"))
    if one:
        f, b = n, 0
    elif fwd and bwd:
        f, b = int(fwd), int(bwd)
    elif n == 1:
        f, b = 1, 0
    else:
        f, b = n - n // 2, n // 2
    width = _num(t.get("width"))
    w = width / max(f + b, 1) if width and 2.0 <= width / max(f + b, 1) <= 6.0 else default_w
    return f, b, w, (not one and n == 1 and not (fwd and bwd))


def _highways(path, roads, coords, clip, layout, points, xy, options) -> None:
    # junction nodes: shared by highway ways, or used twice by one
    use: dict[int, int] = {}
    for _, _, refs in roads:
        for r in set(refs):
            use[r] = use.get(r, 0) + 1
        for r in refs[1:-1]:
            if refs.count(r) > 1:
                use[r] = use.get(r, 0) + 1
    segs = []   # (way id, k, tags, polyline, start node or None, end node or None)
    for wid, t, refs in roads:
        pts = coords(wid, refs)
        if pts is None:
            continue
        if t.get("oneway") == "-1":
            refs, pts = refs[::-1], pts[::-1]
        cuts = [0] + [i for i in range(1, len(refs) - 1) if use.get(refs[i], 0) > 1] + [len(refs) - 1]
        for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
            piece = pts[a:b + 1]
            keep = np.ones(len(piece), bool)
            keep[1:] = np.hypot(*np.diff(piece, axis=0).T) > 1e-6
            piece = piece[keep]
            if len(piece) < 2:
                continue
            if clip is None:
                segs.append((wid, k, t, piece, refs[a], refs[b]))
                continue
            g = LineString(piece).intersection(clip)
            parts = [g] if g.geom_type == "LineString" else list(getattr(g, "geoms", []))
            for q, part in enumerate(x for x in parts if x.geom_type == "LineString" and x.length > 0.5):
                c = np.asarray(part.coords)
                s_node = refs[a] if np.allclose(c[0], piece[0]) else None
                e_node = refs[b] if np.allclose(c[-1], piece[-1]) else None
                segs.append((wid, f"{k}_{q}" if len(parts) > 1 else k, t, c, s_node, e_node))

    at_node: dict[int, list] = {}
    for s in segs:
        for node, is_start in ((s[4], True), (s[5], False)):
            if node is not None and use.get(node, 0) > 1:
                at_node.setdefault(node, []).append((s, is_start))
    cut: dict[tuple, float] = {}
    for node, ends in at_node.items():
        hw = max(_half_width(s[2]) for s, _ in ends)
        for s, is_start in ends:
            length = LineString(s[3]).length
            cut[(id(s), is_start)] = min(hw + 2.0, 0.45 * length) if len(ends) > 2 else min(1.0, 0.2 * length)

    road_polys, lane_ends, walk_strips = [], {}, []
    crossings = {nid: (tg, lat, lon) for nid, tg, lat, lon in points if tg.get("highway") in ("crossing", "stop")}
    for s in segs:
        wid, k, t, pts, n0, n1 = s
        f, b, w, both = _lanes_of(t)
        line = LineString(pts)
        c0, c1 = cut.get((id(s), True), 0.0), cut.get((id(s), False), 0.0)
        if line.length - c0 - c1 < 0.5:
            continue
        centre = np.asarray(substring(line, c0, line.length - c1).coords)
        hw = (f + b) * w / 2 if not both else w / 2
        # the surface runs up to the junction node: the roads' strips overlap there
        road_polys.extend(_road_strip(pts, hw))
        lane_type = "bike" if t["highway"] == "cycleway" else "driving"
        speed = _num((t.get("maxspeed") or "").replace("km/h", "")) if "mph" not in (t.get("maxspeed") or "") else None
        base = f"w{wid}_{k}"
        ids_f, ids_b = [], []
        for side, count in (("f", f), ("b", b)):
            for q in range(count):
                if both:
                    off = 0.0
                elif b == 0:
                    off = ((f - 1) / 2 - q) * w         # one-way: lanes centred, q=0 leftmost
                else:
                    off = -(q + 0.5) * w                 # two-way: forward lanes right of centre
                pl = offset_polyline(centre, off)
                if side == "b":
                    pl = offset_polyline(centre, (q + 0.5) * w)[::-1]
                lid = f"{base}_{side}{q}"
                (ids_f if side == "f" else ids_b).append(lid)
                layout.add(m.LaneCenter(lid, points=R.xyz(pl), widths=np.full(len(pl), w),
                                        lane_type=lane_type, direction="both" if both else "forward",
                                        speed_limit_mps=speed / 3.6 if speed else m.DEFAULT_SPEED_LIMIT,
                                        road_id=f"w{wid}"))
        _neighbours(layout, ids_f)
        _neighbours(layout, ids_b)
        # lane ends at junction nodes: (lane id, point, tangent, width, index from the left)
        for node, is_start in ((n0, True), (n1, False)):
            if node is None or node not in at_node:
                continue
            for ids, incoming in ((ids_f, not is_start), (ids_b, is_start)):
                for q, lid in enumerate(ids):
                    lane_ends.setdefault(node, []).append((lid, incoming, id(s), q))
        # sidewalks
        sw = t.get("sidewalk", "")
        sides = {"both": (1, -1), "left": (1,), "right": (-1,)}.get(sw, ())
        for sign in sides:
            strip = LineString(centre).buffer(sign * (hw + SIDEWALK_WIDTH), single_sided=True, cap_style="flat")
            walk_strips.append((f"walk_{base}_{'l' if sign > 0 else 'r'}", strip))
        # crossings and stop signs on this segment
        for nid, (tg, lat, lon) in crossings.items():
            pxy = xy(lat, lon)
            if line.distance(Point(pxy)) > 0.5 or not (c0 <= line.project(Point(pxy)) <= line.length - c1):
                continue
            sd = line.project(Point(pxy))
            a_, b_ = np.asarray(line.interpolate(max(sd - 0.5, 0)).coords[0]), np.asarray(line.interpolate(min(sd + 0.5, line.length)).coords[0])
            d = B.unit(b_ - a_)
            n_ = B.left_normal(d)
            if tg.get("highway") == "crossing":
                u = d * CROSSWALK_DEPTH / 2
                poly = np.stack([pxy - u - hw * n_, pxy + u - hw * n_, pxy + u + hw * n_, pxy - u + hw * n_])
                if clip is None or clip.intersects(Polygon(poly)):    # cut by record_clip
                    layout.add(m.Crosswalk(f"crossing{nid}", polygon=R.xyz(poly)))
            else:
                pos = pxy - (hw + 1.0) * n_
                if clip is None or clip.contains(Point(pos)):
                    layout.add(m.StopSign(f"stop{nid}", position=R.xyz(pos[None])[0], lane_ids=list(ids_f)))
    by_id = {ln.id: ln for ln in layout.lanes}
    for node, ends in at_node.items():
        if len(ends) > 2:
            hw = max(_half_width(s[2]) for s, _ in ends)
            # round the corners between the arms
            road_polys.append(Point(ends[0][0][3][0] if ends[0][1] else ends[0][0][3][-1])
                              .buffer(hw, quad_segs=8))
        _connect(node, lane_ends.get(node, []), by_id, layout)
    if road_polys:
        surface = shapely.union_all(road_polys)
        if clip is not None:
            surface = surface.intersection(clip)
        for n_, poly in enumerate(R.polygons(surface)):
            layout.add(m.RoadArea(f"road{n_}", polygon=R.xyz(poly)))
        for name, strip in walk_strips:   # sidewalks end where a road's surface begins
            g = strip.difference(surface.buffer(0.01))
            if clip is not None:
                g = g.intersection(clip)
            for n_, poly in enumerate(R.polygons(g)):
                layout.add(m.Sidewalk(f"{name}{n_}", polygon=R.xyz(poly)))
        n_e = 0
        for g in getattr(surface, "geoms", [surface]):
            if g.geom_type != "Polygon" or g.is_empty:
                continue
            g = orient(g, 1.0)
            for ring in [g.exterior, *g.interiors]:
                c = np.asarray(ring.coords)[:, :2]
                layout.add(m.RoadEdge(f"edge{n_e}", points=R.xyz(c)))
                n_e += 1


STRIP_PIECE = 32   # points per buffered piece of a long way


def _road_strip(pts: np.ndarray, hw: float) -> list:
    """The road surface along ``pts`` (flat ends, round joins) as polygons. GEOS buffers
    a long line that crosses itself in quadratic time (2000 random points: 42 s, 1.4 GB),
    so a long way is buffered in pieces with a disc at each seam (the same set: a round
    join is the disc) and united by the caller (union_all is near linear)."""
    if len(pts) <= 2 * STRIP_PIECE:
        return [LineString(pts).buffer(hw, cap_style="flat", join_style="round", quad_segs=4)]
    out = []
    for s in range(0, len(pts) - 1, STRIP_PIECE):
        piece = pts[s:s + STRIP_PIECE + 1]
        out.append(LineString(piece).buffer(hw, cap_style="flat", join_style="round", quad_segs=4))
        if s > 0:
            out.append(Point(piece[0]).buffer(hw, quad_segs=4))
    return out


def _half_width(t: dict) -> float:
    f, b, w, both = _lanes_of(t)
    return w / 2 if both else (f + b) * w / 2


def _neighbours(layout, ids: list[str]) -> None:
    lanes = {ln.id: ln for ln in layout.lanes[-(len(ids) + 64):]} if ids else {}
    for q, lid in enumerate(ids):
        ln = lanes.get(lid)
        if ln is None:
            continue
        ln.left_neighbors = [ids[q - 1]] if q > 0 else []
        ln.right_neighbors = [ids[q + 1]] if q + 1 < len(ids) else []


def _connect(node, ends, by_id, layout) -> None:
    """Join incoming lane ends at a junction node to the outgoing lanes of the other roads."""
    ins = [(lid, seg, q) for lid, inc, seg, q in ends if inc]
    outs = [(lid, seg, q) for lid, inc, seg, q in ends if not inc]
    n = 0
    for lid_in, seg_in, q_in in ins:
        a = by_id[lid_in]
        p0, t0 = a.points[-1, :2], B.unit(a.points[-1, :2] - a.points[-2, :2])
        groups: dict = {}
        for lid_out, seg_out, q_out in outs:
            if seg_out != seg_in:
                groups.setdefault(seg_out, []).append((q_out, lid_out))
        n_in = sum(1 for _, s_, _ in ins if s_ == seg_in)
        for seg_out, cands in groups.items():
            cands.sort()
            b0 = by_id[cands[0][1]]
            t1 = B.unit(b0.points[1, :2] - b0.points[0, :2])
            turn = B.wrap_angle(B.angle_of(t1) - B.angle_of(t0))
            if abs(turn) < np.pi / 4 or len(groups) == 1:
                pick = [c for c in cands if c[0] == min(q_in, len(cands) - 1)]
            elif turn < 0:
                pick = [cands[-1]] if q_in == n_in - 1 else []
            else:
                pick = [cands[0]] if q_in == 0 else []
            for _, lid_out in pick:
                b = by_id[lid_out]
                p1 = b.points[0, :2]
                if np.hypot(*(p1 - p0)) < 1e-6:
                    a.successors.append(lid_out)
                    b.predecessors.append(lid_in)
                    continue
                cid = f"j{node}_{n}"
                n += 1
                lane = R.connector(cid, p0, t0, float(a.widths[-1]), p1, t1, float(b.widths[0]),
                                   [lid_in], [lid_out], f"j{node}")
                layout.add(lane)
                by_id[cid] = lane
                a.successors.append(cid)
                b.predecessors.append(cid)


def _areas(path, ways, coords, clip, layout, options) -> None:
    for wid, t, refs in ways:
        if len(refs) < 4 or refs[0] != refs[-1]:
            continue
        kind = next((v for (k, val), v in VEGETATION.items() if t.get(k) == val), None)
        if "building" not in t and kind is None:
            continue
        pts = coords(wid, refs)
        if pts is None:
            continue
        poly = Polygon(pts)
        if not poly.is_valid or poly.area < 1.0:
            _warn(f"{path}: way {wid}: not a valid polygon; skipped", options)
            continue
        if "building" in t:
            if clip is not None and not clip.intersects(poly):
                continue
            levels = _num(t.get("building:levels"))
            h = _num(t.get("height")) or (levels * LEVEL_HEIGHT if levels else None)
            fp = np.asarray(orient(poly, 1.0).exterior.coords)[:-1]
            layout.add(m.Building(f"b{wid}", footprint=R.xyz(fp), height_hint=h if h and h < 1000 else 12.0,
                                  floors_hint=int(levels) if levels and levels < 200 else 0))
        else:
            g = poly.intersection(clip) if clip is not None else poly
            for n_, ring in enumerate(R.polygons(g)):
                layout.add(m.VegetationZone(f"veg{wid}_{n_}" if n_ else f"veg{wid}", polygon=R.xyz(ring),
                                            kind=kind))


def _trees(points, ways, coords, clip, layout, xy) -> None:
    for nid, t, lat, lon in points:
        if t.get("natural") != "tree":
            continue
        p = xy(lat, lon)
        if clip is not None and not clip.contains(Point(p)):
            continue
        h = _num(t.get("height"))
        crown = _num(t.get("diameter_crown"))
        layout.add(m.Tree(f"tree{nid}", position=R.xyz(p[None])[0],
                          height_hint=h if h and h < 150 else 8.0,
                          crown_radius_hint=crown / 2 if crown and crown < 60 else 2.5))
    for wid, t, refs in ways:
        if t.get("natural") != "tree_row":
            continue
        pts = coords(wid, refs)
        if pts is None:
            continue
        line = LineString(pts)
        for k, s in enumerate(np.arange(0.0, line.length + 1e-9, TREE_ROW_SPACING)):
            p = np.asarray(line.interpolate(s).coords[0])
            if clip is None or clip.contains(Point(p)):
                layout.add(m.Tree(f"treerow{wid}_{k}", position=R.xyz(p[None])[0]))
