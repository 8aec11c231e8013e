"""What an OpenStreetMap file holds besides roads, buildings and vegetation, and how far an
import reaches: signals, signs, lamps, barriers, crossings; bad ways; the clip at the area.

Used by ``osm_import.read_osm`` (the mapping is documented in docs/layout.md):

- ``highway=traffic_signals`` on a junction node: a TrafficLight beside the rightmost lane of
  every road entering the junction there; on a way: one per direction of travel (only
  ``traffic_signals:direction=forward|backward`` when tagged, along / against the way),
  beside the rightmost lane, controlling that direction's lanes.
- ``highway=give_way`` → TrafficSign ``yield`` (``direction`` tag, else the approach to the
  nearer junction); ``traffic_sign=*`` nodes → TrafficSign at the node, kind from the code
  (``signcodes``), facing the nearest lane's traffic.
- ``highway=street_lamp`` → Pole ``street_lamp``; ``barrier=bollard|post|block`` nodes →
  Pole ``bollard``.
- ``barrier=fence|wall|guard_rail|retaining_wall|city_wall|jersey_barrier|handrail`` ways →
  Barrier (``height`` tag, else the kind's default); ``barrier=hedge`` → Hedge.
- ``footway=crossing`` ways → Crosswalk: the way's 3 m strip over the road surface.
- Bad highway ways (``sound_highways``): fewer than two distinct node positions → skipped;
  a node where the way turns back on itself (a spike, > 170 degrees) → dropped from the
  way (repaired). Both warn with the way id (errors with ``strict``).
- Clip (``clip_area``, ``record_clip``): the area is ``--bbox``, else the file's
  ``<bounds>``; features are cut at it (polygons intersected, lines clipped, points
  outside dropped, road edges along the cut removed) unless ``--no-clip``.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import shapely
from shapely.geometry import LineString, Point, Polygon

from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry.polyline import nearest_point
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout.importers import ImportOptions, MapWarning

SIGNAL_SIDE_M = 1.5          # a light / sign stands this far right of its lane's edge
JUNCTION_REACH_M = 20.0      # lanes ending this close to a signals node enter its junction
SPIKE_DEG = 170.0
POINT_TAGS = {"natural": {"tree"},
              "highway": {"crossing", "stop", "traffic_signals", "give_way", "street_lamp"},
              "barrier": {"bollard", "post", "block"}}
BARRIERS = {"fence": ("fence", 1.5, 0.05), "wall": ("wall", 2.0, 0.3),
            "guard_rail": ("guard_rail", 0.8, 0.3), "retaining_wall": ("wall", 1.5, 0.4),
            "city_wall": ("wall", 5.0, 1.0), "jersey_barrier": ("jersey", 0.8, 0.6),
            "handrail": ("railing", 1.0, 0.05)}
HEDGE = (1.2, 0.8)


def point_wanted(tags) -> bool:
    """A node the importer keeps (its tags: an osmium TagList or a dict)."""
    return (any(tags.get(k) in vs for k, vs in POINT_TAGS.items())
            or tags.get("traffic_sign") is not None)


def _warn(msg: str, options: ImportOptions) -> None:
    if options.strict:
        raise InputError(msg)
    warnings.warn(msg, MapWarning, stacklevel=3)


# ================================================================ clip

def clip_area(path, options: ImportOptions) -> tuple[tuple | None, str | None]:
    """The area (min lon, min lat, max lon, max lat) features are cut at and where it comes
    from: ``--bbox``, else the file's ``<bounds>``; (None, None) with ``options.clip`` False
    or when the file has no bounds."""
    if not options.clip:
        return None, None
    if options.bbox is not None:
        return tuple(options.bbox), "bbox"
    import osmium
    try:
        reader = osmium.io.Reader(str(path), osmium.osm.osm_entity_bits.NOTHING)
        try:
            box = reader.header().box()
        finally:
            reader.close()
    except (RuntimeError, osmium.InvalidLocationError):
        return None, None           # the reader itself reports what is wrong with the file
    if not box.valid():
        return None, None
    b = (box.bottom_left.lon, box.bottom_left.lat, box.top_right.lon, box.top_right.lat)
    if not (b[0] < b[2] and b[1] < b[3]):
        return None, None
    return b, "file bounds"


def _cut_lines(pts: np.ndarray, clip) -> list[np.ndarray]:
    g = shapely.intersection(LineString(pts[:, :2]), clip)
    lines = [x for x in getattr(g, "geoms", [g]) if x.geom_type == "LineString" and x.length > 0.1]
    return [np.column_stack([np.asarray(x.coords)[:, :2], np.zeros(len(x.coords))]) for x in lines]


def _cut_polygon(poly: np.ndarray, clip) -> list[np.ndarray]:
    from lsd3d_usd.layout import roadnet as R
    g = shapely.intersection(Polygon(poly[:, :2]).buffer(0), clip)
    return [R.xyz(p) for p in R.polygons(g) if Polygon(p).area >= 1.0]


def _off_boundary(points: np.ndarray, clip, tol: float = 1e-6) -> list[np.ndarray]:
    """A road edge without its stretches along the clip box (where the road is cut, not
    bounded)."""
    x0, y0, x1, y1 = clip.bounds
    p = points[:, :2]
    a, b = p[:-1], p[1:]
    on = np.zeros(len(a), bool)
    for k, v in ((0, x0), (0, x1), (1, y0), (1, y1)):
        on |= (np.abs(a[:, k] - v) < tol) & (np.abs(b[:, k] - v) < tol)
    out, cur = [], [0]
    for i, o in enumerate(on):
        if o:
            if len(cur) >= 2:
                out.append(points[cur])
            cur = [i + 1]
        else:
            cur.append(i + 1)
    if len(cur) >= 2:
        out.append(points[cur])
    return out


def record_clip(layout, clip, clip_box, clip_from: str | None, options: ImportOptions) -> None:
    """Cut the layout's features at the clip box (see the module doc) and record the clip in
    ``metadata.source.clip`` (``from``: bbox / file bounds, ``box``: degrees, ``extent``: m)."""
    src = layout.metadata.setdefault("source", {})
    if clip is None:
        if not options.clip:
            src["clip"] = {"from": None, "note": "--no-clip: the ways touching the area kept whole"}
        return
    src["clip"] = {"from": clip_from, "box": [float(v) for v in clip_box],
                   "extent": [float(v) for v in clip.bounds]}
    inside = lambda p: clip.covers(Point(p[0], p[1]))  # noqa: E731
    buildings = []
    for bd in layout.buildings:
        if Polygon(bd.footprint[:, :2]).within(clip):
            buildings.append(bd)
            continue
        for k, fp in enumerate(_cut_polygon(bd.footprint, clip)):
            fp = fp if m.polygon_area(fp) > 0 else fp[::-1].copy()
            buildings.append(m.Building(bd.id if k == 0 else f"{bd.id}_{k}", footprint=fp,
                                        height_hint=bd.height_hint, floors_hint=bd.floors_hint))
    layout.buildings = buildings
    layout.crosswalks = [m.Crosswalk(cw.id if k == 0 else f"{cw.id}_{k}", polygon=p)
                         for cw in layout.crosswalks
                         for k, p in enumerate(_cut_polygon(cw.polygon, clip))]
    edges = []
    for e in layout.road_edges:
        pieces = _off_boundary(e.points, clip)
        edges += [m.RoadEdge(e.id if k == 0 else f"{e.id}_{k}", points=p, kind=e.kind)
                  for k, p in enumerate(pieces)]
    layout.road_edges = edges
    for name, cls in (("barriers", m.Barrier), ("hedges", m.Hedge)):
        out = []
        for f in getattr(layout, name):
            for k, p in enumerate(_cut_lines(f.points, clip)):
                out.append(dataclasses.replace(f, id=f.id if k == 0 else f"{f.id}_{k}", points=p))
        setattr(layout, name, out)
    for name in ("trees", "stop_signs", "traffic_lights", "traffic_signs", "poles"):
        setattr(layout, name, [f for f in getattr(layout, name) if inside(f.position)])
    layout.reindex()


# ================================================================ bad ways

def sound_highways(path, roads, xy_of: dict, options: ImportOptions) -> list:
    """The highway ways with spikes removed and those of less than two distinct positions
    dropped (each warned, naming the way). Ways with nodes the file lacks pass unchanged
    (the importer reports those)."""
    out = []
    for wid, t, refs in roads:
        if any(r not in xy_of for r in refs):
            out.append((wid, t, refs))
            continue
        keep = [refs[0]]
        for r in refs[1:]:
            if np.hypot(*(xy_of[r] - xy_of[keep[-1]])) > 1e-6:
                keep.append(r)
        if len(keep) < 2:
            _warn(f"{path}: way {wid}: a highway of {len(refs)} node(s) at one position; skipped",
                  options)
            continue
        # One pass with a stack (linear time): at a node b where the way turns back (a, b, c)
        # the node whose removal shortens the way most is dropped: b (a spike), or the way's
        # first node a / last node c when that is the outlier (dropping b there kept the
        # outlier and dropped the good nodes one by one). Then the turn before is looked at
        # again.
        spikes, turns = [], []
        limit = np.cos(np.radians(SPIKE_DEG))
        stack = keep[:1]
        last = keep[-1]
        for r in keep[1:]:
            while len(stack) >= 2:
                a, b, c = xy_of[stack[-2]], xy_of[stack[-1]], xy_of[r]
                u, v = b - a, c - b
                if np.dot(u, v) / max(np.hypot(*u) * np.hypot(*v), 1e-12) >= limit:
                    break
                turns.append(stack[-1])
                lu, lv = np.hypot(*u), np.hypot(*v)
                gain_b = lu + lv - np.hypot(*(c - a))
                gain_a = lu if len(stack) == 2 else -1.0
                gain_c = lv if r == last else -1.0
                if gain_c > max(gain_a, gain_b):
                    spikes.append(r)
                    r = None
                    break
                spikes.append(stack.pop(-2 if gain_a > gain_b else -1))
            if r is not None:
                stack.append(r)
        keep = stack
        if spikes:
            def length(ids):
                q = np.array([xy_of[i] for i in ids])
                return float(np.hypot(*np.diff(q, axis=0).T).sum())

            ends = {refs[0]: " (its first node)", refs[-1]: " (its last node)"}
            named = ", ".join(f"{x}{ends.get(x, '')}" for x in spikes[:3])
            _warn(f"{path}: way {wid}: turns back on itself at node {turns[0]}"
                  f"{f' (and {len(turns) - 1} more)' if len(turns) > 1 else ''}; dropped node(s) "
                  f"{named}{' ...' if len(spikes) > 3 else ''}, length {length(refs):.0f} m -> "
                  f"{length(keep):.0f} m (repaired)", options)
            dropped = set(spikes)
            refs = [r for r in refs if r not in dropped]
        out.append((wid, t, refs))
    return out


# ================================================================ signals and furniture

def _roadside(lanes, q: np.ndarray) -> tuple[np.ndarray, float]:
    """Beside the rightmost of ``lanes`` (one direction) at their point nearest q: the ground
    point and the heading facing their traffic."""
    best = None
    for ln in lanes:
        _, _, c, u = nearest_point(ln.points, q)
        right = np.array([u[1], -u[0]])
        off = float(np.dot(c - q, right)) + float(ln.widths.max()) / 2
        if best is None or off > best[0]:
            best = (off, c, u, float(ln.widths.max()))
    off, c, u, w = best
    right = np.array([u[1], -u[0]])
    pos = c + right * (w / 2 + SIGNAL_SIDE_M)
    return np.array([pos[0], pos[1], 0.0]), float(np.arctan2(-u[1], -u[0]))


def _groups(lanes) -> dict:
    """Lanes by (road, direction letter of the OSM lane id ``w<way>_<k>_<f|b><q>``)."""
    out: dict = {}
    for ln in lanes:
        side = ln.id.rsplit("_", 1)[-1][:1]
        out.setdefault((ln.road_id, side), []).append(ln)
    return out


def _signal_sites(layout, q: np.ndarray, direction: str | None):
    """Where the signals of a node at q stand: per entering road at a junction, else per
    direction of the road through q. Yields (lanes, ground point, heading)."""
    drive = [ln for ln in layout.lanes if ln.lane_type == "driving" and not ln.is_junction]
    ending = []
    for ln in drive:
        if np.hypot(*(ln.points[-1, :2] - q)) < JUNCTION_REACH_M:
            _, s, _, _ = nearest_point(ln.points, q)
            if s >= ln.length() - 1e-6:       # q lies ahead of the lane's end
                ending.append(ln)
    if ending:
        for (road, side), lanes in sorted(_groups(ending).items()):
            ends = np.array([ln.points[-1, :2] for ln in lanes]).mean(axis=0)
            pos, yaw = _roadside(lanes, ends)
            yield lanes, pos, yaw
        return
    passing = [ln for ln in drive if nearest_point(ln.points, q)[0] < float(ln.widths.max()) * 3]
    for (road, side), lanes in sorted(_groups(passing).items()):
        if direction in ("forward", "backward") and side != direction[0]:
            continue
        pos, yaw = _roadside(lanes, q)
        yield lanes, pos, yaw


def map_features(path, points, ways, coords, clip, layout, xy, options: ImportOptions) -> None:
    """Signals, signs, lamps, bollards, barriers, hedges and crossing ways (module doc)."""
    from lsd3d_usd.layout.signcodes import sign_kind, split_code
    for nid, t, lat, lon in points:
        q = xy(lat, lon)
        hw = t.get("highway")
        if hw == "traffic_signals":
            direction = t.get("traffic_signals:direction") or t.get("direction")
            for k, (lanes, pos, yaw) in enumerate(_signal_sites(layout, q, direction)):
                layout.add(m.TrafficLight(f"signals{nid}_{k}", position=pos, heading=yaw,
                                          lane_ids=[ln.id for ln in lanes]))
        elif hw == "give_way":
            sites = list(_signal_sites(layout, q, t.get("direction")))
            if t.get("direction") not in ("forward", "backward") and len(sites) > 1:
                # the approach to the nearer junction: lanes that lead on, ending soonest
                sites.sort(key=lambda st: (not any(ln.successors for ln in st[0]),
                                           min(ln.length() - nearest_point(ln.points, q)[1]
                                               for ln in st[0])))
                sites = sites[:1]
            for k, (lanes, pos, yaw) in enumerate(sites):
                layout.add(m.TrafficSign(f"giveway{nid}_{k}", position=pos, heading=yaw,
                                         kind="yield", code="give_way",
                                         lane_ids=[ln.id for ln in lanes]))
        elif t.get("traffic_sign") and hw not in ("stop",):
            code = t["traffic_sign"].split(";")[0].strip()
            country, sign = split_code(code)
            kind = sign_kind(country, sign)
            if kind in ("stop", "traffic_light"):
                continue
            near = [ln for ln in layout.lanes if ln.lane_type == "driving"]
            yaw = 0.0
            if near:
                ln = min(near, key=lambda x: nearest_point(x.points, q)[0])
                u = nearest_point(ln.points, q)[3]
                yaw = float(np.arctan2(-u[1], -u[0]))
            value = 0.0
            if kind == "speed_limit":
                digits = "".join(ch for ch in sign.split("-")[-1] if ch.isdigit())
                value = float(digits) if digits and sign.count("-") else 0.0
            layout.add(m.TrafficSign(f"sign{nid}", position=[q[0], q[1], 0.0], heading=yaw,
                                     kind=kind, code=code, value=value))
        elif hw == "street_lamp":
            layout.add(m.Pole(f"lamp{nid}", position=[q[0], q[1], 0.0], kind="street_lamp",
                              height=7.0))
        elif t.get("barrier") in ("bollard", "post", "block"):
            layout.add(m.Pole(f"bollard{nid}", position=[q[0], q[1], 0.0], kind="bollard",
                              height=1.0))
    from lsd3d_usd.layout.osm_import import _num
    surface = None
    way_walks = []     # (node ids, polygon) of crossing ways' crosswalks
    for wid, t, refs in ways:
        kind = t.get("barrier")
        crossing = t.get("footway") == "crossing" or (t.get("highway") == "footway"
                                                      and t.get("crossing") is not None)
        if kind not in BARRIERS and kind != "hedge" and not crossing:
            continue
        pts = coords(wid, refs)
        if pts is None or len(pts) < 2 or LineString(pts).length < 0.1:
            continue
        p3 = np.column_stack([pts, np.zeros(len(pts))])
        if crossing:
            if surface is None:
                surface = shapely.union_all([Polygon(r.polygon[:, :2]) for r in layout.road_areas]) \
                    if layout.road_areas else Polygon()
            g = shapely.intersection(LineString(pts).buffer(1.5, cap_style="flat"), surface)
            for k, poly in enumerate(p for p in getattr(g, "geoms", [g])
                                     if p.geom_type == "Polygon" and p.area > 1.0):
                ring = np.asarray(shapely.geometry.polygon.orient(poly, 1.0).exterior.coords)[:-1]
                layout.add(m.Crosswalk(f"crossingway{wid}" + (f"_{k}" if k else ""),
                                       polygon=np.column_stack([ring, np.zeros(len(ring))])))
                way_walks.append((set(refs), poly))
        elif kind == "hedge":
            h = _num(t.get("height"))
            layout.add(m.Hedge(f"hedge{wid}", points=p3, height=h if h and h < 20 else HEDGE[0],
                               width=HEDGE[1]))
        else:
            bkind, dh, dw = BARRIERS[kind]
            h = _num(t.get("height"))
            layout.add(m.Barrier(f"barrier{wid}", points=p3, kind=bkind,
                                 height=h if h and 0 < h < 50 else dh, width=dw))
    if way_walks:
        _drop_doubled_crossings(layout, way_walks)


def _drop_doubled_crossings(layout, way_walks) -> None:
    """A crossing is often mapped twice: a ``highway=crossing`` node on the road and a
    ``footway=crossing`` way through it. The way's crosswalk (the mapped line) is kept; the
    node's is dropped when the node is on that way or the two overlap by half or more."""
    def doubled(cw) -> bool:
        if not cw.id.startswith("crossing") or cw.id.startswith("crossingway"):
            return False
        nid = cw.id[len("crossing"):]
        node = Polygon(cw.polygon[:, :2])
        for refs, poly in way_walks:
            if (nid.isdigit() and int(nid) in refs) or (
                    node.is_valid and node.area > 0
                    and node.intersection(poly).area >= 0.5 * min(node.area, poly.area)):
                return True
        return False

    layout.crosswalks = [cw for cw in layout.crosswalks if not doubled(cw)]
    layout.reindex()
