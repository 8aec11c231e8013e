"""OpenDRIVE ``<objects>`` and ``<signals>`` of each road → layout features.

Objects (position s, t on the road, ``hdg`` relative to the road, ``length`` / ``width`` /
``radius`` / ``height``, an ``<outline>`` of ``cornerRoad`` / ``cornerLocal`` points, and
``<repeat>`` records):

| object type | layout |
|---|---|
| building | Building (outline, else the length x width box; ``height``) |
| tree; vegetation without an outline | Tree (``height``, ``radius`` as crown) |
| vegetation with an outline; trafficIsland | VegetationZone (shrub / grass) |
| pole (subtype bollard, permanentDelineator: bollard), streetLamp | Pole |
| barrier, railing, soundBarrier (kind from the subtype / name) | Barrier along the repeat, the outline or the box's long axis |
| parkingSpace | ParkingSpot, not occupied |
| car, van, bus, trailer | ParkingSpot, occupied (a parked vehicle) |
| crosswalk | Crosswalk (outline, else the box) |

A ``<repeat>`` with ``distance`` 0 is one continuous object along [s, s + length] (t, width
and height interpolated): a Barrier polyline, or for area types a strip; with a distance,
copies every ``distance`` metres. Other types (patch, roadMark, gantry, obstacle, none, ...)
are counted in ``metadata.source.objectsNotRead``.

Signals (``s``, ``t``, ``orientation`` + / - / none, ``hOffset``, ``zOffset`` + ``height``,
``country`` / ``type`` / ``subtype`` / ``value``, ``<validity fromLane toLane>``,
``<positionInertial>`` / ``<positionRoad>``): dynamic signals and StVO 1000xxx types →
TrafficLight; stop signs (StVO 206, MUTCD R1-1) → StopSign; everything else → TrafficSign
(kind by ``signcodes.sign_kind``). A signal faces the traffic it is valid for: ``+`` the
traffic travelling along s, so it faces -s. Its lanes: the validity range, else the lanes
travelling in its direction, at its s; ``<signalReference>`` on other roads adds their lanes.
A file with any traffic light says its signals are complete (``metadata.source.
signalsComplete``: the proxy then derives no traffic lights).

A bad object or signal (a number that is not one, a position off its road) is skipped with
a warning naming the road and the element's id (an error with ``strict``).
"""
from __future__ import annotations

import warnings

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry.polyline import clean_ring
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout.signcodes import sign_kind

VEHICLE_TYPES = {"car", "van", "bus", "trailer"}
NOT_READ_NOTE = "objectsNotRead"
MAX_REPEAT_COPIES = 10_000     # per <repeat>: more is a broken file, not a map


class _Skip(Exception):
    pass


def _num(el, name, default=None) -> float | None:
    v = el.get(name)
    if v is None or v == "":
        return default
    try:
        x = float(v)
    except ValueError:
        raise _Skip(f"<{_tag(el)}> attribute {name}={v!r} is not a number") from None
    if not np.isfinite(x):
        raise _Skip(f"<{_tag(el)}> attribute {name}={v!r} is not finite")
    return x


def _tag(el) -> str:
    from lxml import etree
    return etree.QName(el).localname if isinstance(el.tag, str) else ""


def _kids(el, name):
    return [c for c in el if isinstance(c.tag, str) and _tag(c) == name]


def _kid(el, name):
    k = _kids(el, name)
    return k[0] if k else None


class _Place:
    """Road coordinates of one road → world XY, heading and ground height."""

    def __init__(self, road):
        from lsd3d_usd.layout.opendrive import _xy
        self.road, self._xy = road, _xy

    def xy(self, s, t) -> np.ndarray:
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        t = np.broadcast_to(np.asarray(t, dtype=np.float64), s.shape)
        if np.any(s < -1e-6) or np.any(s > self.road.length + 1e-6):
            raise _Skip(f"s={float(s.min()):g}..{float(s.max()):g} lies outside the road "
                        f"(length {self.road.length:g})")
        s = np.clip(s, 0.0, self.road.length)
        return self._xy(self.road, s, t)

    def heading(self, s) -> float:
        _, _, h = self.road.ref.eval(np.array([min(max(float(s), 0.0), self.road.length)]))
        return float(h[0])


def _box(c: np.ndarray, yaw: float, length: float, width: float) -> np.ndarray:
    u = np.array([np.cos(yaw), np.sin(yaw)]) * length / 2
    v = np.array([-np.sin(yaw), np.cos(yaw)]) * width / 2
    xy = np.stack([c[:2] - u - v, c[:2] + u - v, c[:2] + u + v, c[:2] - u + v])
    return np.column_stack([xy, np.full(4, c[2])])


def _outline(obj, place: _Place, origin: np.ndarray, yaw: float) -> tuple[np.ndarray, float] | None:
    """The object's outline (N, 3) and its largest corner height, from <outline> (1.4) or the
    first <outlines><outline> (1.5+)."""
    ol = _kid(obj, "outline")
    if ol is None and _kid(obj, "outlines") is not None:
        ol = _kid(_kid(obj, "outlines"), "outline")
    if ol is None:
        return None
    road_c = _kids(ol, "cornerRoad")
    local_c = _kids(ol, "cornerLocal")
    if road_c:
        s = np.array([_num(c, "s") for c in road_c])
        t = np.array([_num(c, "t") for c in road_c])
        pts = place.xy(s, t)
        h = max(_num(c, "height", 0.0) for c in road_c)
    elif local_c:
        u = np.array([_num(c, "u") for c in local_c])
        v = np.array([_num(c, "v") for c in local_c])
        cs, sn = np.cos(yaw), np.sin(yaw)
        pts = np.column_stack([origin[0] + cs * u - sn * v, origin[1] + sn * u + cs * v,
                               np.full(len(u), origin[2])])
        h = max(_num(c, "height", 0.0) for c in local_c)
    else:
        return None
    return pts, float(h)


def _barrier_kind(typ: str, sub: str, name: str) -> str:
    w = f"{typ} {sub} {name}".lower()
    for key, kind in (("guard", "guard_rail"), ("jersey", "jersey"), ("wall", "wall"),
                      ("noise", "wall"), ("sound", "wall"), ("railing", "railing"),
                      ("fence", "fence")):
        if key in w:
            return kind
    return "fence"


BARRIER_DEFAULTS = {"fence": (1.5, 0.05), "wall": (3.0, 0.3), "guard_rail": (0.8, 0.3),
                    "jersey": (0.8, 0.6), "railing": (1.0, 0.05)}     # height, width (m)


def road_objects(path, el, road, counts: dict, strict: bool) -> list:
    """Layout features of the ``<objects>`` of one road (``el``: its XML element)."""
    objs = _kid(el, "objects")
    if objs is None:
        return []
    place = _Place(road)
    out: list = []
    for obj in _kids(objs, "object"):
        oid = obj.get("id") or f"{len(out)}"
        try:
            out += _object(obj, oid, road, place, counts)
        except (_Skip, FloatingPointError, ValueError) as e:
            _bad(path, road.id, f"object {oid}", e, strict)
    return out


def _object(obj, oid, road, place: _Place, counts: dict) -> list:
    typ = (obj.get("type") or "none").strip()
    t_low = typ.lower()
    sub = (obj.get("subtype") or "").strip()
    name = obj.get("name") or ""
    fid = f"obj_{road.id}_{oid}"
    kinds = {"building", "tree", "vegetation", "pole", "streetlamp", "barrier", "railing",
             "soundbarrier", "parkingspace", "crosswalk", "trafficisland"} | VEHICLE_TYPES
    if t_low not in kinds:
        counts[typ] = counts.get(typ, 0) + 1
        return []
    s0, t0 = _num(obj, "s", 0.0), _num(obj, "t", 0.0)
    length, width = _num(obj, "length", 0.0), _num(obj, "width", 0.0)
    radius, height = _num(obj, "radius", 0.0), _num(obj, "height", 0.0)
    hdg = _num(obj, "hdg", 0.0)
    repeats = _kids(obj, "repeat")
    if repeats:
        out = []
        for k, rp in enumerate(repeats):
            out += _repeat(rp, f"{fid}_r{k}" if len(repeats) > 1 else fid, t_low, sub, name,
                           road, place, (s0, t0, length, width, radius, height, hdg))
        return out
    c = place.xy(s0, t0)[0]
    yaw = place.heading(s0) + hdg
    return _single(fid, t_low, sub, name, c, yaw, length, width, radius, height,
                   _outline(obj, place, c, yaw))


def _single(fid, t_low, sub, name, c, yaw, length, width, radius, height, outline) -> list:
    poly = None
    if outline is not None:
        poly = clean_ring(outline[0])
        height = height or outline[1]
    elif length > 0 and width > 0:
        poly = _box(c, yaw, length, width)
    elif radius > 0 and t_low in ("building", "crosswalk", "vegetation", "trafficisland",
                                  "parkingspace"):
        a = np.arange(12) * (2 * np.pi / 12)
        poly = np.column_stack([c[0] + radius * np.cos(a), c[1] + radius * np.sin(a),
                                np.full(12, c[2])])
    if t_low == "building":
        if poly is None:
            raise _Skip("a building without an outline or a length and width")
        return [m.Building(fid, footprint=poly, height_hint=height if 0 < height < 1000 else 12.0)]
    if t_low == "tree" or (t_low == "vegetation" and poly is None):
        h = height if 0 < height < 150 else (8.0 if t_low == "tree" else 1.5)
        r = radius if 0 < radius < 60 else (max(length, width) / 2 if max(length, width) > 0
                                            else min(2.5, 0.3 * h))
        return [m.Tree(fid, position=c, height_hint=h, crown_radius_hint=r)]
    if t_low in ("vegetation", "trafficisland"):
        kind = "shrub" if t_low == "vegetation" and height > 0.5 else "grass"
        return [m.VegetationZone(fid, polygon=poly, kind=kind)]
    if t_low in ("pole", "streetlamp"):
        kind = ("street_lamp" if t_low == "streetlamp" else
                "bollard" if sub.lower() in ("bollard", "permanentdelineator") else "pole")
        h = height if 0 < height < 100 else {"street_lamp": 7.0, "bollard": 1.0}.get(kind, 4.0)
        return [m.Pole(fid, position=c, kind=kind, height=h)]
    if t_low in ("barrier", "railing", "soundbarrier"):
        kind = _barrier_kind(t_low, sub, name)
        dh, dw = BARRIER_DEFAULTS[kind]
        if outline is not None and poly is not None:
            pts = np.vstack([poly, poly[:1]])
        elif length > 0:
            u = np.array([np.cos(yaw), np.sin(yaw), 0.0]) * length / 2
            pts = np.stack([c - u, c + u])
        else:
            raise _Skip("a barrier without an outline, a repeat or a length")
        return [m.Barrier(fid, points=pts, kind=kind, height=height if 0 < height < 100 else dh,
                          width=width if 0 < width < 20 and outline is None else dw)]
    if t_low == "crosswalk":
        if poly is None:
            raise _Skip("a crosswalk without an outline or a length and width")
        return [m.Crosswalk(fid, polygon=poly)]
    # parking spaces and vehicles: a rectangle
    if poly is not None and outline is not None:
        from shapely.geometry import Polygon
        r = np.asarray(Polygon(poly[:, :2]).minimum_rotated_rectangle.exterior.coords)[:4]
        e1, e2 = r[1] - r[0], r[2] - r[1]
        lo, sh = (e1, e2) if np.hypot(*e1) >= np.hypot(*e2) else (e2, e1)
        centre, yaw = np.append(r.mean(axis=0), c[2]), float(np.arctan2(lo[1], lo[0]))
        length, width = float(np.hypot(*lo)), float(np.hypot(*sh))
    else:
        centre = c
        if width > length:
            length, width, yaw = width, length, yaw + np.pi / 2
    if not (length > 0 and width > 0):
        raise _Skip(f"a {t_low} without an outline or a length and width")
    return [m.ParkingSpot(fid, center=centre, heading=float(yaw), length=length, width=width,
                          occupied=t_low in VEHICLE_TYPES)]


def _repeat(rp, fid, t_low, sub, name, road, place: _Place, base) -> list:
    s0, t0, length0, width0, radius0, height0, hdg = base
    s = _num(rp, "s", s0)
    run = _num(rp, "length", 0.0)
    dist = _num(rp, "distance", 0.0)
    t_a, t_b = _num(rp, "tStart", t0), _num(rp, "tEnd", None)
    t_b = t_a if t_b is None else t_b

    def lerp(a, b, f):
        return a + (b - a) * f

    def val(key, default):
        a = _num(rp, f"{key}Start", default)
        b = _num(rp, f"{key}End", a)
        return a, b

    (w_a, w_b), (h_a, h_b) = val("width", width0), val("height", height0)
    (l_a, l_b), (r_a, r_b) = val("length", length0), val("radius", radius0)
    if run <= 0:
        raise _Skip("<repeat> of length 0")
    s_end = min(s + run, road.length)
    if dist <= 0:       # one continuous object along the road
        n = max(2, int(np.ceil((s_end - s) / 2.0)) + 1)
        ss = np.linspace(s, s_end, n)
        f = (ss - s) / max(s_end - s, 1e-9)
        tt = lerp(t_a, t_b, f)
        line = place.xy(ss, tt)
        if t_low in ("barrier", "railing", "soundbarrier"):
            kind = _barrier_kind(t_low, sub, name)
            dh, dw = BARRIER_DEFAULTS[kind]
            h, w = max(h_a, h_b), max(w_a, w_b)
            return [m.Barrier(fid, points=line, kind=kind, height=h if 0 < h < 100 else dh,
                              width=w if 0 < w < 20 else dw)]
        w = lerp(w_a, w_b, f)
        if np.all(w > 0):
            left, right = place.xy(ss, tt + w / 2), place.xy(ss[::-1], (tt - w / 2)[::-1])
            poly = clean_ring(np.vstack([left, right]))
            if poly is not None and t_low in ("vegetation", "trafficisland", "crosswalk",
                                              "building"):
                return _single(fid, t_low, sub, name, line[0], 0.0, 0, 0, 0, max(h_a, h_b),
                               (poly, max(h_a, h_b)))
        dist = 10.0     # a point object "along" the road: one every 10 m
    n = int(np.floor((s_end - s) / dist + 1e-9)) + 1
    if n > MAX_REPEAT_COPIES:
        raise _Skip(f"<repeat> of {n} copies (more than {MAX_REPEAT_COPIES})")
    out = []
    for k in range(n):
        sk = s + k * dist
        f = (sk - s) / max(s_end - s, 1e-9)
        c = place.xy(sk, lerp(t_a, t_b, f))[0]
        yaw = place.heading(sk) + hdg
        out += _single(f"{fid}_{k}", t_low, sub, name, c, yaw, lerp(l_a, l_b, f),
                       lerp(w_a, w_b, f), lerp(r_a, r_b, f), lerp(h_a, h_b, f), None)
    return out


# ================================================================ signals

def road_signals(path, el, road, lane_keys: set, strict: bool) -> tuple[list, dict]:
    """Features of the ``<signals>`` of one road, and {signal id: feature} for references.
    ``lane_keys``: the imported lane ids (``<road>_<section>_<lane>``)."""
    sigs = _kid(el, "signals")
    if sigs is None:
        return [], {}
    place = _Place(road)
    out, by_id = [], {}
    for sg in _kids(sigs, "signal"):
        sid = sg.get("id") or f"{len(out)}"
        try:
            f = _signal(sg, sid, road, place, lane_keys)
        except (_Skip, FloatingPointError, ValueError) as e:
            _bad(path, road.id, f"signal {sid}", e, strict)
            continue
        out.append(f)
        by_id[sid] = f
    return out, by_id


def signal_references(el, road, lane_keys: set, signals: dict) -> None:
    """Add the lanes of ``<signalReference>``\\ s on this road to the signals they name."""
    sigs = _kid(el, "signals")
    if sigs is None:
        return
    for ref in _kids(sigs, "signalReference"):
        f = signals.get(ref.get("id"))
        if f is None or not hasattr(f, "lane_ids"):
            continue
        try:
            s = _num(ref, "s", 0.0)
        except _Skip:
            continue
        for lid in _lanes_at(ref, road, s, ref.get("orientation", "none"), lane_keys):
            if lid not in f.lane_ids:
                f.lane_ids.append(lid)


def _lanes_at(el, road, s: float, orientation: str, lane_keys: set) -> list[str]:
    """The imported lanes of ``road`` at ``s`` the signal is valid for: its <validity>
    ranges, else the lanes travelling in its direction (+: along s)."""
    k = max(0, min(int(np.searchsorted([sec.s0 for sec in road.sections], s, side="right")) - 1,
                   len(road.sections) - 1))
    sec = road.sections[k]
    ids = [ln.id for ln in sec.left + sec.right]
    ranges = []
    for v in _kids(el, "validity"):
        try:
            a, b = int(float(v.get("fromLane"))), int(float(v.get("toLane")))
        except (TypeError, ValueError, OverflowError):
            continue
        ranges.append((min(a, b), max(a, b)))
    if ranges:
        chosen = [i for i in ids if any(a <= i <= b for a, b in ranges)]
    else:
        along = [i for i in ids if (i < 0) != road.lht]        # lanes travelling along s
        chosen = along if orientation == "+" else [i for i in ids if i not in along] \
            if orientation == "-" else ids
    return [key for key in (f"{road.id}_{k}_{i}" for i in chosen) if key in lane_keys]


def _signal(sg, sid, road, place: _Place, lane_keys: set):
    s, t = _num(sg, "s", 0.0), _num(sg, "t", 0.0)
    orient = (sg.get("orientation") or "none").strip()
    h_off = _num(sg, "hOffset", 0.0)
    z_off, height = _num(sg, "zOffset", 0.0), _num(sg, "height", 0.0)
    pos = place.xy(s, t)[0]
    base = place.heading(s) + (np.pi if orient != "-" else 0.0)
    yaw = base + h_off
    inertial = _kid(sg, "positionInertial")
    if inertial is not None:
        pos = np.array([_num(inertial, "x"), _num(inertial, "y"), _num(inertial, "z", 0.0)])
        yaw = _num(inertial, "hdg", yaw)
    on_road = _kid(sg, "positionRoad")
    if on_road is not None and on_road.get("roadId") in (None, road.id):
        ps, pt = _num(on_road, "s", s), _num(on_road, "t", t)
        pos = place.xy(ps, pt)[0]
        yaw = place.heading(ps) + (np.pi if orient != "-" else 0.0) + _num(on_road, "hOffset", 0.0)
    yaw = float(np.arctan2(np.sin(yaw), np.cos(yaw)))
    country = (sg.get("country") or "").strip()
    typ, sub = (sg.get("type") or "").strip(), (sg.get("subtype") or "").strip()
    kind = sign_kind(country, typ, sg.get("name") or "")
    if sg.get("dynamic", "no").lower() == "yes":
        kind = "traffic_light"
    lanes = _lanes_at(sg, road, s, orient, lane_keys)
    fid = f"sig_{road.id}_{sid}"
    top = z_off + height
    ground = pos.copy()
    if kind == "traffic_light":
        return m.TrafficLight(fid, position=ground, heading=yaw,
                              height=top if 2.0 <= top < 100 else 5.5, lane_ids=lanes)
    if kind == "stop":
        return m.StopSign(fid, position=ground, lane_ids=lanes)
    code = f"{country}:{typ}" if country else typ
    if sub and sub not in ("-1", "none"):
        code += f"-{sub}"
    value = _num(sg, "value", 0.0)
    return m.TrafficSign(fid, position=ground, heading=yaw, kind=kind, code=code,
                         value=value, height=top if 1.0 <= top < 100 else 2.5, lane_ids=lanes)


def _bad(path, rid, what, e, strict) -> None:
    msg = f"{path}: road {rid}: {what}: {e}; skipped"
    if strict:
        raise InputError(msg) from None
    from lsd3d_usd.layout.opendrive import OpenDriveWarning
    warnings.warn(msg, OpenDriveWarning, stacklevel=4)


def read_objects_and_signals(path, root, roads: dict, layout, strict: bool) -> None:
    """Add every imported road's objects and signals to ``layout`` (called by
    ``read_opendrive`` once the lanes are in it)."""
    from lsd3d_usd.layout.opendrive import _kids as road_kids
    lane_keys = {ln.id for ln in layout.lanes}
    counts: dict[str, int] = {}
    signals: dict[str, object] = {}
    elements = [(el, roads[el.get("id")]) for el in road_kids(root, "road") if el.get("id") in roads]
    have = {f.id for f in layout.features()}
    for el, road in elements:
        with np.errstate(over="raise", divide="raise", invalid="raise", under="ignore"):
            feats = road_objects(path, el, road, counts, strict)
            sig, by_id = road_signals(path, el, road, lane_keys, strict)
        for f in feats + sig:
            if f.id in have:
                _bad(path, road.id, f"{type(f).__name__} {f.id}", "duplicate id", strict)
                continue
            have.add(f.id)
            layout.add(f)
        signals.update({k: v for k, v in by_id.items() if k not in signals})
    for el, road in elements:
        signal_references(el, road, lane_keys, signals)
    src = layout.metadata.setdefault("source", {})
    if counts:
        src[NOT_READ_NOTE] = dict(sorted(counts.items()))
    if layout.traffic_lights:
        src["signalsComplete"] = True
