"""ASAM OpenDRIVE (1.4–1.8) → layout model.

Reads the reference line (line, arc, spiral, poly3, paramPoly3), laneOffset,
lane sections with width polynomials, lane types and road marks, the
elevation profile, and road / junction links (→ lane predecessors and
successors). Curves are sampled adaptively so every lane centre and lane
boundary polyline stays within ``tolerance`` of the exact curve.

Superelevation rolls the cross section about the reference line. Not read
(yet): lateral <shape> and <crossfall> (a warning per road), lane <border>
records (a lane with only borders gets a warning and is skipped), objects and
signals, geoReference projection (kept as metadata).

Parsing is hardened: entities are not resolved, no network, no huge trees,
and work is bounded by lsd3d_usd.limits (road and lane sizes checked before
sampling, a point budget per road). A malformed file raises InputError; a bad
road warns (OpenDriveWarning, naming the road id) and the rest still imports
(or InputError with strict); a file of which no road imports is an error.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from lxml import etree
from scipy.special import fresnel

from lsd3d_usd.errors import InputError, excerpt
from lsd3d_usd.layout import model as m
from lsd3d_usd.limits import OPENDRIVE_FILE_BYTES

DEFAULT_TOLERANCE = 0.02
MAX_FILE_BYTES = 512 * 1024 * 1024   # = limits.OPENDRIVE_FILE_BYTES


class OpenDriveWarning(UserWarning):
    """A part of the map was skipped; the message names the road."""


class _RoadError(Exception):
    pass


LANE_TYPE_MAP = {"driving": "driving", "biking": "bike", "bike": "bike", "bus": "bus",
                 "taxi": "driving", "hov": "driving", "parking": "parking", "shoulder": "shoulder",
                 "restricted": "restricted", "entry": "entry", "exit": "exit", "onramp": "entry",
                 "offramp": "exit", "connectingramp": "driving", "slipLane": "driving",
                 "sliplane": "driving", "stop": "shoulder", "bidirectional": "driving"}
NON_LANE_TYPES = {"sidewalk", "walking", "border", "median", "none", "curb", "rail", "tram",
                  "special1", "special2", "special3", "roadworks"}


# ================================================================ XML

def _local(el) -> str:
    return etree.QName(el).localname if isinstance(el.tag, str) else ""


def _kids(el, name):
    return [c for c in el if isinstance(c.tag, str) and _local(c) == name]


def _kid(el, name):
    k = _kids(el, name)
    return k[0] if k else None


def _f(el, name, default=None, road=None) -> float:
    v = el.get(name)
    if v is None:
        if default is None:
            raise _RoadError(f"<{_local(el)}> lacks attribute {name}")
        return float(default)
    try:
        x = float(v)
    except ValueError:
        raise _RoadError(f"<{_local(el)}> attribute {name}={v!r} is not a number") from None
    if not np.isfinite(x):
        raise _RoadError(f"<{_local(el)}> attribute {name}={v!r} is not finite")
    return x


def parse_xml(path: str | Path):
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    OPENDRIVE_FILE_BYTES.check(p.stat().st_size, f"{path}", what="OpenDRIVE file size")
    parser = etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=False,
                             load_dtd=False, dtd_validation=False, remove_comments=True)
    try:
        tree = etree.parse(str(p), parser)
    except etree.XMLSyntaxError as e:
        raise InputError(f"{path}: malformed XML: {_one_line(e)}") from None
    except (OSError, UnicodeError, ValueError) as e:   # e.g. bytes invalid in the file's encoding
        raise InputError(f"{path}: cannot be read as XML: {_one_line(e)}") from None
    root = tree.getroot()
    if _local(root) != "OpenDRIVE":
        raise InputError(f"{path}: root element is <{_local(root)}>, expected <OpenDRIVE>")
    return root


from lsd3d_usd.limits import (  # noqa: E402
    COORDINATE,
    FEATURE_POINTS,
    LANE_WIDTH,
    LATERAL_OFFSET,
    LAYOUT_EXTENT,
    ROAD_LENGTH,
    ROAD_POINTS,
    TOTAL_ROAD_LENGTH,
)

# Floating-point faults inside a road make that road bad (skipped), never a stray warning;
# underflow to zero is harmless.
_FP = dict(over="raise", divide="raise", invalid="raise", under="ignore")


def _one_line(e: Exception) -> str:
    text = " ".join(str(e).split())
    return text if len(text) <= 200 else excerpt(text, 200)


def _within(limit, value, what: str | None = None) -> None:
    """_RoadError (the road is skipped) unless ``value`` is within a limits.Limit."""
    if not limit.ok(value):
        raise _RoadError(limit.describe(value, what=what))


# ====================================================== reference line

@dataclass
class _Geom:
    s: float
    x: float
    y: float
    hdg: float
    length: float
    kind: str
    p: dict = field(default_factory=dict)
    table: tuple | None = None      # poly3: (s samples, u samples)

    def eval(self, ds: np.ndarray):
        """x, y, heading at distances ds (array) from the geometry start."""
        k = self.kind
        if k == "line":
            h = np.full_like(ds, self.hdg)
            return self.x + ds * np.cos(self.hdg), self.y + ds * np.sin(self.hdg), h
        if k == "arc":
            c = self.p["curvature"]
            if abs(c) < 1e-15:
                return _Geom(self.s, self.x, self.y, self.hdg, self.length, "line").eval(ds)
            h = self.hdg + c * ds
            return (self.x + (np.sin(h) - np.sin(self.hdg)) / c,
                    self.y - (np.cos(h) - np.cos(self.hdg)) / c, h)
        if k == "spiral":
            return _spiral(self.x, self.y, self.hdg, self.p["curvStart"], self.p["curvEnd"],
                           self.length, ds)
        if k == "poly3":
            s_tab, u_tab = self.table
            u = np.interp(ds, s_tab, u_tab)
            a, b, c, d = (self.p[n] for n in "abcd")
            v = a + b * u + c * u**2 + d * u**3
            dv = b + 2 * c * u + 3 * d * u**2
            return self._local(u, v, np.arctan(dv))
        if k == "paramPoly3":
            pr = ds / self.length if self.p["normalized"] else ds
            P = self.p
            u = P["aU"] + P["bU"] * pr + P["cU"] * pr**2 + P["dU"] * pr**3
            v = P["aV"] + P["bV"] * pr + P["cV"] * pr**2 + P["dV"] * pr**3
            du = P["bU"] + 2 * P["cU"] * pr + 3 * P["dU"] * pr**2
            dv = P["bV"] + 2 * P["cV"] * pr + 3 * P["dV"] * pr**2
            return self._local(u, v, np.arctan2(dv, du))
        raise AssertionError(k)

    def _local(self, u, v, dh):
        c, s = np.cos(self.hdg), np.sin(self.hdg)
        return self.x + c * u - s * v, self.y + s * u + c * v, self.hdg + dh


def _spiral(x0, y0, h0, c0, c1, length, ds):
    """Clothoid with curvature linear from c0 to c1 over ``length`` (Fresnel integrals)."""
    cdot = (c1 - c0) / length
    if abs(cdot) < 1e-15:
        g = _Geom(0, x0, y0, h0, length, "arc", {"curvature": c0})
        return g.eval(ds)
    heading = h0 + c0 * ds + 0.5 * cdot * ds**2
    sign = 1.0 if cdot > 0 else -1.0
    # mirror a decreasing-curvature spiral into an increasing one: h' = -h, y' = -y
    hh, cc0, cd = sign * h0, sign * c0, abs(cdot)
    k = np.sqrt(cd / np.pi)
    u0 = cc0 / cd
    if abs(u0 * k) > 2e3:   # nearly an arc: Fresnel differences lose precision; integrate
        x, y = _spiral_quad(x0, y0, h0, c0, cdot, ds)
        return x, y, heading
    phi0 = hh - cc0**2 / (2 * cd)
    S0, C0 = fresnel(u0 * k)
    S, C = fresnel((ds + u0) * k)
    dC, dS = C - C0, S - S0
    xi = (np.cos(phi0) * dC - np.sin(phi0) * dS) / k
    eta = (np.sin(phi0) * dC + np.cos(phi0) * dS) / k
    return x0 + xi, y0 + sign * eta, heading


def _spiral_quad(x0, y0, h0, c0, cdot, ds):
    """Clothoid position by composite Gauss–Legendre quadrature (fallback), integrated once
    along the sorted distances (pieces of at most 5 m), so the work grows with the
    geometry's length plus the number of samples, not with their product."""
    ds = np.atleast_1d(np.asarray(ds, dtype=np.float64))
    knots = np.unique(np.concatenate([[0.0], ds]))
    xs, ws = np.polynomial.legendre.leggauss(12)
    a, b = knots[:-1], knots[1:]
    steps = np.maximum(1, np.ceil((b - a) / 5.0)).astype(np.int64)
    owner = np.repeat(np.arange(len(a)), steps)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(steps) - steps, steps)
    width = ((b - a) / steps)[owner]
    pa = a[owner] + width * k
    u = pa[:, None] + width[:, None] * (xs[None, :] + 1) / 2
    h = h0 + c0 * u + 0.5 * cdot * u**2
    w = width[:, None] / 2 * ws[None, :]
    cx = np.concatenate([[0.0], np.cumsum(np.bincount(owner, (w * np.cos(h)).sum(1), len(a)))])
    cy = np.concatenate([[0.0], np.cumsum(np.bincount(owner, (w * np.sin(h)).sum(1), len(a)))])
    zero = np.searchsorted(knots, 0.0)
    at = np.searchsorted(knots, ds)
    return x0 + cx[at] - cx[zero], y0 + cy[at] - cy[zero]


class _RefLine:
    def __init__(self, geoms: list[_Geom]):
        self.geoms = sorted(geoms, key=lambda g: g.s)
        self.starts = np.array([g.s for g in self.geoms])
        self.length = self.geoms[-1].s + self.geoms[-1].length - self.geoms[0].s

    def eval(self, s: np.ndarray):
        s = np.asarray(s, dtype=np.float64)
        idx = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.geoms) - 1)
        x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
        for k in np.unique(idx):
            sel = idx == k
            g = self.geoms[k]
            x[sel], y[sel], h[sel] = g.eval(s[sel] - g.s)
        return x, y, h


def _parse_geometry(el, rid) -> _Geom:
    s, x, y = _f(el, "s"), _f(el, "x"), _f(el, "y")
    hdg, length = _f(el, "hdg"), _f(el, "length")
    if length < 0:
        raise _RoadError(f"geometry at s={s} has negative length {length}")
    _within(ROAD_LENGTH, length, f"geometry at s={s}: length")
    kinds = [c for c in el if isinstance(c.tag, str)]
    if len(kinds) != 1:
        raise _RoadError(f"geometry at s={s} needs exactly one shape element")
    c = kinds[0]
    k = _local(c)
    if k == "line":
        return _Geom(s, x, y, hdg, length, "line")
    if k == "arc":
        return _Geom(s, x, y, hdg, length, "arc", {"curvature": _f(c, "curvature")})
    if k == "spiral":
        return _Geom(s, x, y, hdg, length, "spiral",
                     {"curvStart": _f(c, "curvStart"), "curvEnd": _f(c, "curvEnd")})
    if k == "poly3":
        p = {n: _f(c, n) for n in "abcd"}
        # arc length s(u) on a dense grid, inverted by interpolation
        u_max = length * 1.5 + 1.0           # u <= arc length for a poly3
        u = np.linspace(0, u_max, int(min(max(2000, u_max * 20), POLY3_TABLE_MAX)))
        dv = p["b"] + 2 * p["c"] * u + 3 * p["d"] * u**2
        sp = np.sqrt(1 + dv**2)
        s_tab = np.concatenate([[0], np.cumsum((sp[1:] + sp[:-1]) / 2 * np.diff(u))])
        return _Geom(s, x, y, hdg, length, "poly3", p, (s_tab, u))
    if k == "paramPoly3":
        p = {n: _f(c, n) for n in ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV")}
        pr = c.get("pRange", "normalized")
        if pr not in ("normalized", "arcLength"):
            raise _RoadError(f"paramPoly3 at s={s}: unknown pRange {pr!r}")
        p["normalized"] = pr == "normalized"
        if p["normalized"] and length <= 0:
            raise _RoadError(f"paramPoly3 at s={s}: zero length")
        return _Geom(s, x, y, hdg, length, "paramPoly3", p)
    raise _RoadError(f"unknown geometry element <{k}> at s={s}")


POLY3_TABLE_MAX = 2_000_000   # arc-length table of a poly3 (~13 per metre at the road length limit)


# ================================================================ polynomials

class _Piecewise:
    """Piecewise cubic a + b ds + c ds² + d ds³ with records starting at ``starts``.

    Before the first record the first record's value ``a`` holds: extrapolating its cubic
    backwards gave shoulders 40 m wide and elevations off by metres (other readers hold too).
    """

    def __init__(self, records: list[tuple[float, float, float, float, float]]):
        records = sorted(records, key=lambda r: r[0]) or [(0.0, 0.0, 0.0, 0.0, 0.0)]
        self.starts = np.array([r[0] for r in records])
        self.coef = np.array([r[1:] for r in records])

    @property
    def late_start(self) -> float | None:
        """The first record's start when it lies after 0 (so its value is held before it)."""
        return float(self.starts[0]) if self.starts[0] > LATE_START_EPS else None

    def __call__(self, s):
        s = np.asarray(s, dtype=np.float64)
        idx = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.starts) - 1)
        ds = np.maximum(s - self.starts[idx], 0.0)
        a, b, c, d = self.coef[idx].T
        return a + b * ds + c * ds**2 + d * ds**3


# a first record starting later than this is "late" (below it the held value is the same)
LATE_START_EPS = 1e-6


def _late_note(late: list[str]) -> str:
    return ("records start after s = 0, so their first value is held before them "
            "(not extrapolated): " + ", ".join(late))


def _records(parent, tag, s_attr="s"):
    out = []
    for r in _kids(parent, tag) if parent is not None else []:
        out.append((_f(r, s_attr), _f(r, "a"), _f(r, "b", 0), _f(r, "c", 0), _f(r, "d", 0)))
    return out


# ================================================================ roads

@dataclass
class _Lane:
    id: int
    type: str
    width: _Piecewise | None
    marks: list            # (sOffset, type, color)
    pred: int | None
    succ: int | None
    speed: float | None


@dataclass
class _Section:
    s0: float
    s1: float
    left: list[_Lane]      # ids 1, 2, ... (inner first)
    right: list[_Lane]     # ids -1, -2, ...
    center_marks: list


@dataclass
class _Road:
    id: str
    length: float
    junction: str
    ref: _RefLine
    offset: _Piecewise
    elevation: _Piecewise
    sections: list[_Section]
    links: dict            # "predecessor"/"successor" -> (elementType, elementId, contactPoint)
    speed: float
    lht: bool
    superelevation: _Piecewise | None = None   # roll angle (rad) about the reference line
    notes: list = field(default_factory=list)  # ignored parts, warned once per road


def _speed(el) -> float | None:
    if el is None or el.get("max") is None:
        return None
    v = el.get("max")
    if v in ("no limit", "undefined"):
        return None
    try:
        x = float(v)
    except ValueError:
        return None
    if not (np.isfinite(x) and x > 0):
        return None
    unit = el.get("unit", "m/s")
    return x / 3.6 if unit == "km/h" else x * 0.44704 if unit == "mph" else x


def _parse_road(el) -> _Road:
    rid = el.get("id")
    length = _f(el, "length")
    if length < 0:
        raise _RoadError(f"negative length {length}")
    _within(ROAD_LENGTH, length)
    pv = _kid(el, "planView")
    if pv is None:
        raise _RoadError("no <planView>")
    geoms = [_parse_geometry(g, rid) for g in _kids(pv, "geometry")]
    if not geoms:
        raise _RoadError("<planView> has no <geometry>")
    ref = _RefLine(geoms)
    lanes_el = _kid(el, "lanes")
    if lanes_el is None:
        raise _RoadError("no <lanes>")
    offset = _Piecewise(_records(lanes_el, "laneOffset"))
    elevation = _Piecewise(_records(_kid(el, "elevationProfile"), "elevation"))
    lateral = _kid(el, "lateralProfile")
    superelevation = None
    notes = []
    late = []              # records held before their start, named in one warning per road
    for name, pw in (("laneOffset", offset), ("elevation", elevation)):
        if pw.late_start is not None:
            late.append(f"<{name}> s={pw.late_start:g}")
    if lateral is not None:
        sup = _records(lateral, "superelevation")
        if sup:
            superelevation = _Piecewise(sup)
            if superelevation.late_start is not None:
                late.append(f"<superelevation> s={superelevation.late_start:g}")
        ignored = sorted({_local(c) for c in lateral if isinstance(c.tag, str)} - {"superelevation"})
        if ignored:
            notes.append("lateral " + ", ".join(f"<{n}>" for n in ignored)
                         + " ignored (the cross section is flat apart from superelevation)")
    speed = None
    for t in _kids(el, "type"):
        speed = _speed(_kid(t, "speed")) or speed
    secs_el = sorted(_kids(lanes_el, "laneSection"), key=lambda s: _f(s, "s"))
    if not secs_el:
        raise _RoadError("no <laneSection>")
    sections = []
    for k, se in enumerate(secs_el):
        s0 = _f(se, "s")
        if not -1e-6 <= s0 <= length + 1e-6:
            raise _RoadError(f"laneSection s={s0} lies outside the road [0, {length}]")
        s1 = _f(secs_el[k + 1], "s") if k + 1 < len(secs_el) else length
        if s1 - s0 <= 1e-9:
            continue
        side = {}
        for name in ("left", "right"):
            lanes = []
            sl = _kid(se, name)
            for ln in (_kids(sl, "lane") if sl is not None else []):
                lid = int(_f(ln, "id"))
                widths = _records(ln, "width", "sOffset")
                if not widths and _kids(ln, "border"):
                    raise _RoadError(f"lane {lid}: <border> lane geometry is not supported")
                if widths and min(w[0] for w in widths) > LATE_START_EPS:
                    late.append(f"<width> of lane {lid} in laneSection s={s0:g} "
                                f"sOffset={min(w[0] for w in widths):g}")
                link = _kid(ln, "link")
                pred = _kid(link, "predecessor") if link is not None else None
                succ = _kid(link, "successor") if link is not None else None
                marks = [(_f(rm, "sOffset", 0), rm.get("type", "none"), rm.get("color", "standard"))
                         for rm in _kids(ln, "roadMark")]
                lanes.append(_Lane(lid, ln.get("type", "driving"),
                                   _Piecewise(widths) if widths else _Piecewise([]), marks,
                                   int(_f(pred, "id")) if pred is not None else None,
                                   int(_f(succ, "id")) if succ is not None else None,
                                   _speed(_kid(ln, "speed"))))
            lanes.sort(key=lambda l: abs(l.id))
            side[name] = lanes
        cen = _kid(se, "center")
        cmarks = []
        if cen is not None:
            for ln in _kids(cen, "lane"):
                cmarks = [(_f(rm, "sOffset", 0), rm.get("type", "none"), rm.get("color", "standard"))
                          for rm in _kids(ln, "roadMark")]
        sections.append(_Section(s0, s1, side["left"], side["right"], cmarks))
    if not sections:
        raise _RoadError("no lane section of positive length")
    if late:
        notes.append(_late_note(late))
    links = {}
    link = _kid(el, "link")
    for kind in ("predecessor", "successor"):
        le = _kid(link, kind) if link is not None else None
        if le is not None:
            links[kind] = (le.get("elementType", "road"), le.get("elementId"),
                           le.get("contactPoint", "start"))
    return _Road(rid, length, el.get("junction", "-1"), ref, offset, elevation, sections, links,
                 speed or m.DEFAULT_SPEED_LIMIT, el.get("rule", "RHT").upper() == "LHT",
                 superelevation, notes)


# ============================================================ sampling

def _boundaries(road: _Road, sec: _Section, s: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """lane id -> (inner t, outer t) at s; id 0 -> (t0, t0) the centre lane."""
    t0 = road.offset(s)
    out = {0: (t0, t0)}
    for lanes, sign in ((sec.left, 1.0), (sec.right, -1.0)):
        inner = t0
        for ln in lanes:
            w = np.maximum(ln.width(s - sec.s0), 0.0)
            if len(w):
                _within(LANE_WIDTH, float(w.max()), f"lane {ln.id}: width")
            outer = inner + sign * w
            out[ln.id] = (inner, outer)
            inner = outer
        if len(s):
            _within(LATERAL_OFFSET, float(np.abs(inner).max()))
    return out


def _xy(road: _Road, s, t):
    """Points at (s, t): t is measured along the cross section, which superelevation rolls
    about the reference line (right-handed about the direction of travel: a positive
    angle lowers the right side), so it reaches t cos(roll) sideways and t sin(roll) up."""
    x, y, h = road.ref.eval(s)
    z = road.elevation(s)
    if road.superelevation is not None:
        roll = road.superelevation(s)
        if np.any(np.abs(roll) > np.pi / 2):
            raise _RoadError(f"superelevation {float(np.abs(roll).max()):.4g} rad is beyond "
                             "+-pi/2")
        t, z = t * np.cos(roll), z + t * np.sin(roll)
    return np.stack([x - t * np.sin(h), y + t * np.cos(h), z], axis=1)


def _sample_section(road: _Road, sec: _Section, tol: float, road_points: int = 0) -> np.ndarray:
    """s values on [s0, s1] such that every lane boundary/centre polyline is within tol.
    ``road_points``: points the road's earlier sections used; the road's total stays
    within limits.ROAD_POINTS (checked before each refinement, _RoadError past it)."""
    knots = {sec.s0, sec.s1}
    for g in road.ref.geoms:
        if sec.s0 < g.s < sec.s1:
            knots.add(g.s)
    base = np.array(sorted(knots))
    grid = [base[:1]]
    for a, b in zip(base[:-1], base[1:]):
        n = max(1, int(np.ceil((b - a) / 5.0)))
        grid.append(np.linspace(a, b, n + 1)[1:])
    s = np.concatenate(grid)
    n_lines = 3 * (1 + len(sec.left) + len(sec.right))

    def budget(n):
        _within(ROAD_POINTS, road_points + n * n_lines,
                f"polyline points at tolerance {tol:g} m ({len(sec.left) + len(sec.right)} lanes)")

    budget(len(s))

    def lines(sv):
        bnd = _boundaries(road, sec, sv)
        ts = []
        for inner, outer in bnd.values():
            ts += [inner, outer, (inner + outer) / 2]
        return [_xy(road, sv, t) for t in ts]

    for _ in range(30):
        a, b = s[:-1], s[1:]
        fr = np.array([0.25, 0.5, 0.75])
        mids = (a[:, None] + (b - a)[:, None] * fr[None, :]).ravel()
        L_a, L_b, L_m = lines(a), lines(b), lines(mids)
        err = np.zeros(len(a))
        for pa, pb, pm in zip(L_a, L_b, L_m):
            pm = pm.reshape(len(a), 3, 3)
            chord = pb - pa
            cl = np.linalg.norm(chord, axis=1)
            for q in range(3):
                v = pm[:, q] - pa
                tt = np.clip(np.einsum("ij,ij->i", v, chord) / np.maximum(cl**2, 1e-18), 0, 1)
                d = np.linalg.norm(v - tt[:, None] * chord, axis=1)
                err = np.maximum(err, d)
        bad = (err > tol) & ((b - a) > 1e-3)
        if not bad.any():
            break
        budget(len(s) + int(bad.sum()))
        s = np.sort(np.concatenate([s, (a[bad] + b[bad]) / 2]))
    return s


# ================================================================ import

def read_opendrive(path: str | Path, tolerance: float = DEFAULT_TOLERANCE,
                   strict: bool = False) -> m.Layout:
    """Import an OpenDRIVE file as a Layout. Bad roads warn (OpenDriveWarning) and are
    skipped (InputError with ``strict``); InputError when no road can be imported."""
    if not (tolerance > 0 and np.isfinite(tolerance)):
        raise InputError(f"tolerance must be a number > 0, got {tolerance}")
    root = parse_xml(path)
    roads: dict[str, _Road] = {}
    skipped: list[str] = []
    for el in _kids(root, "road"):
        rid = el.get("id")
        try:
            if rid is None:
                raise _RoadError("road without id")
            if rid in roads:
                raise _RoadError("duplicate road id")
            with np.errstate(**_FP):
                roads[rid] = _parse_road(el)
        except (_RoadError, ValueError, ZeroDivisionError, FloatingPointError, OverflowError) as e:
            _bad(path, rid, e, strict)
            skipped.append(f"road {rid}: {_one_line(e)}")
    total = sum(r.length for r in roads.values())
    TOTAL_ROAD_LENGTH.check(total, f"{path}", what=f"total length of its {len(roads)} roads")

    layout = m.Layout(metadata={"source": {"format": "OpenDRIVE", "file": Path(path).name,
                                           **_header(root)}})
    mid_links = _split_at_mid_road_links(path, root, roads, strict)
    lane_meta: dict[str, tuple[_Road, int, _Lane, bool]] = {}
    section_s: dict[tuple[str, int], np.ndarray] = {}
    imported = 0
    for rid, road in list(roads.items()):
        try:
            with np.errstate(**_FP):
                feats = _road_features(road, tolerance, lane_meta, section_s)
        except (_RoadError, ValueError, FloatingPointError, ZeroDivisionError, OverflowError) as e:
            _bad(path, rid, e, strict)
            skipped.append(f"road {rid}: {_one_line(e)}")
            del roads[rid]
            for key in [k for k, v in lane_meta.items() if v[0] is road]:
                del lane_meta[key]
            continue
        for note in road.notes:
            warnings.warn(f"{path}: road {rid}: {note}", OpenDriveWarning, stacklevel=2)
        for f in feats:
            layout.add(f)
        imported += 1
    if not imported or not any(True for _ in layout.features()):
        what = (f"all {len(skipped)} roads were skipped; first {skipped[0]}" if skipped
                else "it has no <road>")
        raise InputError(f"{path}: no road could be imported ({what})")
    m.check_size(layout, str(path))
    layout.metadata["opendrive_lanes"] = _lane_index(lane_meta, section_s)
    _link_lanes(root, roads, layout, lane_meta, _mid_road_pairs(roads, mid_links))
    layout.reindex()
    from lsd3d_usd.layout.opendrive_objects import read_objects_and_signals
    read_objects_and_signals(path, root, roads, layout, strict)
    _attach_georef(path, root, layout)
    m.check_size(layout, str(path))
    return layout


def _bad(path, rid, e, strict):
    msg = f"{path}: road {rid}: {_one_line(e)}; road skipped"
    if strict:
        raise InputError(msg) from None
    warnings.warn(msg, OpenDriveWarning, stacklevel=3)


def _header(root) -> dict:
    h = _kid(root, "header")
    if h is None:
        return {}
    out = {k: v for k, v in h.attrib.items() if k in ("revMajor", "revMinor", "name", "vendor", "date")}
    geo = _kid(h, "geoReference")
    if geo is not None and (geo.text or "").strip():
        out["geoReference"] = geo.text.strip()
    return out


def _lane_key(rid: str, k: int, lid: int) -> str:
    return f"{rid}_{k}_{lid}"


def _lane_index(lane_meta, section_s) -> dict:
    """What keeps OpenDRIVE lanes addressable in the layout (scenario LanePositions): per
    layout lane id its road id, OpenDRIVE lane id, direction and the road's s at each
    vertex in the s direction (points of backward lanes run the other way)."""
    out = {}
    for lk, (road, k, ln, forward) in lane_meta.items():
        s = section_s.get((road.id, k))
        if s is not None:
            out[lk] = {"road": road.id, "lane": int(ln.id), "forward": bool(forward),
                       "s": [round(float(v), 6) for v in s]}
    return out


def _road_features(road: _Road, tol: float, lane_meta, section_s=None) -> list:
    feats = []
    rid = road.id
    in_junction = road.junction not in ("-1", "", None)
    points = 0
    for k, sec in enumerate(road.sections):
        s = _sample_section(road, sec, tol, points)
        if section_s is not None:
            section_s[(road.id, k)] = s
        points += len(s) * 3 * (1 + len(sec.left) + len(sec.right))
        bnd = _boundaries(road, sec, s)
        drive_left = drive_right = None
        for ln, side in [(l, 1) for l in sec.left] + [(l, -1) for l in sec.right]:
            inner, outer = bnd[ln.id]
            typ = ln.type
            width = np.abs(outer - inner)
            if np.all(width < 1e-6):
                continue
            if typ.lower() in ("sidewalk", "walking"):
                poly = np.concatenate([_xy(road, s, inner), _xy(road, s[::-1], outer[::-1])])
                feats.append(m.Sidewalk(f"walk_{_lane_key(rid, k, ln.id)}", polygon=_ccw(poly)))
                continue
            if typ.lower() == "median":
                for t, n in ((inner, "i"), (outer, "o")):
                    feats.append(m.RoadEdge(f"median_{_lane_key(rid, k, ln.id)}{n}",
                                            points=_xy(road, s, t), kind="median"))
            if typ.lower() not in NON_LANE_TYPES:
                pts = _xy(road, s, (inner + outer) / 2)
                forward = (side < 0) != road.lht
                if not forward:
                    pts, width = pts[::-1].copy(), width[::-1].copy()
                lk = _lane_key(rid, k, ln.id)
                feats.append(m.LaneCenter(lk, points=pts, widths=width,
                                          lane_type=LANE_TYPE_MAP.get(typ, LANE_TYPE_MAP.get(typ.lower(), "other")),
                                          speed_limit_mps=ln.speed or road.speed, road_id=rid,
                                          is_junction=in_junction))
                lane_meta[lk] = (road, k, ln, forward)
            if typ.lower() not in ("sidewalk", "walking", "border", "none", "curb"):
                if side > 0:
                    drive_left = outer
                else:
                    drive_right = outer
            # road marks on the lane's outer boundary
            feats += _marks(road, sec, k, s, outer, ln.marks, f"mark_{_lane_key(rid, k, ln.id)}")
        feats += _marks(road, sec, k, s, bnd[0][0], sec.center_marks, f"mark_{rid}_{k}_0")
        t0 = bnd[0][0]
        left = drive_left if drive_left is not None else t0
        right = drive_right if drive_right is not None else t0
        if np.any(np.abs(left - right) > 1e-6):
            poly = np.concatenate([_xy(road, s, right), _xy(road, s[::-1], left[::-1])])
            feats.append(m.RoadArea(f"road_{rid}_{k}", polygon=_ccw(poly)))
            if not in_junction:
                feats.append(m.RoadEdge(f"edge_{rid}_{k}_r", points=_xy(road, s, right)))
                feats.append(m.RoadEdge(f"edge_{rid}_{k}_l", points=_xy(road, s[::-1], left[::-1])))
    if feats:   # one road alone must fit in a layout (the whole file is checked afterwards)
        c = np.concatenate([f.coords() for f in feats])
        span = float(max(np.ptp(c[:, 0]), np.ptp(c[:, 1]), 2 * np.abs(c[:, 2]).max()))
        _within(LAYOUT_EXTENT, span, "size of the road's geometry")
        _within(COORDINATE, float(np.abs(c).max()), "a coordinate at")
        # every feature must also be readable back (the layout reader's own limit)
        big = max(feats, key=lambda f: len(f.coords()))
        _within(FEATURE_POINTS, len(big.coords()), f"points of {big.id}")
    return feats


def _ccw(poly: np.ndarray) -> np.ndarray:
    keep = np.ones(len(poly), bool)
    keep[1:] = np.linalg.norm(np.diff(poly, axis=0), axis=1) > 1e-9
    poly = poly[keep]
    if len(poly) > 3 and np.allclose(poly[0], poly[-1]):
        poly = poly[:-1]
    return poly if m.polygon_area(poly) >= 0 else poly[::-1].copy()


def _marks(road, sec, k, s, t, marks, prefix) -> list:
    out = []
    marks = sorted(marks, key=lambda r: r[0])
    for n, (off, typ, color) in enumerate(marks):
        typ = typ.lower()
        if typ in ("none", "curb", "grass", "edge", "botts dots", "custom"):
            continue
        a = sec.s0 + off
        b = sec.s0 + marks[n + 1][0] if n + 1 < len(marks) else sec.s1
        sel = (s >= a - 1e-9) & (s <= b + 1e-9)
        if sel.sum() < 2:
            continue
        parts = typ.split()
        kind = "broken" if parts and parts[0] == "broken" and all(p == "broken" for p in parts) else "solid"
        out.append(m.RoadLine(f"{prefix}_{n}", points=_xy(road, s[sel], t[sel]), kind=kind,
                              color="yellow" if color.lower() in ("yellow", "orange") else "white",
                              double=len(parts) > 1))
    return out


# ================================================================ lane graph

def _link_lanes(root, roads, layout, lane_meta, extra_pairs=()) -> None:
    """Predecessors/successors from lane links, road links and junction connections
    (default junctions through their connecting roads, direct junctions from the incoming to
    the linked road); ``extra_pairs``: lane ends joined in the middle of a road (virtual
    junctions, ``_mid_road_pairs``).

    Every link pairs two lane *ends* ("start"/"end" in s); a pair becomes a
    successor link when it joins one lane's exit (end in its travel direction)
    to the other's entry.
    """
    pairs = set()

    def end_of(road: _Road, contact: str) -> tuple[int, str]:
        return (0, "start") if contact == "start" else (len(road.sections) - 1, "end")

    for rid, road in roads.items():
        n = len(road.sections)
        for k, sec in enumerate(road.sections):
            for ln in sec.left + sec.right:
                if ln.succ is not None and k + 1 < n:
                    pairs.add(((rid, k, ln.id, "end"), (rid, k + 1, ln.succ, "start")))
                if ln.pred is not None and k > 0:
                    pairs.add(((rid, k - 1, ln.pred, "end"), (rid, k, ln.id, "start")))
        for kind, (etype, eid, contact) in road.links.items():
            if etype != "road" or eid not in roads:
                continue
            other = roads[eid]
            ok, oend = end_of(other, contact)
            k, end = (n - 1, "end") if kind == "successor" else (0, "start")
            for ln in road.sections[k].left + road.sections[k].right:
                target = ln.succ if kind == "successor" else ln.pred
                if target is not None:
                    pairs.add(tuple(sorted([(rid, k, ln.id, end), (eid, ok, target, oend)])))
    for j in _kids(root, "junction"):
        jid = j.get("id")
        direct = j.get("type") == "direct"
        for c in _kids(j, "connection"):
            if c.get("type") == "virtual":
                continue          # a mid-road connection: _mid_road_pairs joins it
            inc = c.get("incomingRoad")
            # a direct junction joins the incoming road to a linked road, with no road between
            con = (c.get("linkedRoad") or c.get("connectingRoad")) if direct else c.get("connectingRoad")
            if inc not in roads or con not in roads:
                continue
            ri, rc = roads[inc], roads[con]
            iend = _junction_end(ri, jid)
            if iend is None:
                continue
            ik = len(ri.sections) - 1 if iend == "end" else 0
            contact = c.get("contactPoint") or (_junction_end(rc, jid) if direct else None) or "start"
            ck, cend = end_of(rc, contact)
            for ll in _kids(c, "laneLink"):
                try:
                    f, t = int(float(ll.get("from"))), int(float(ll.get("to")))
                except (TypeError, ValueError, OverflowError):
                    continue
                pairs.add(tuple(sorted([(inc, ik, f, iend), (con, ck, t, cend)])))

    pairs.update(extra_pairs)

    def exit_end(fwd):
        return "end" if fwd else "start"

    for p, q in pairs:
        for a, b in ((p, q), (q, p)):
            ka, kb = _lane_key(*a[:3]), _lane_key(*b[:3])
            if ka not in lane_meta or kb not in lane_meta:
                continue
            fa, fb = lane_meta[ka][3], lane_meta[kb][3]
            if a[3] == exit_end(fa) and b[3] != exit_end(fb):
                la, lb = layout.lane_by_id(ka), layout.lane_by_id(kb)
                if kb not in la.successors:
                    la.successors.append(kb)
                if ka not in lb.predecessors:
                    lb.predecessors.append(ka)


# ================================================================ junctions beyond "default"

def _junction_end(road: _Road, jid: str) -> str | None:
    """The end ("start" / "end") of ``road`` that its road link gives to junction ``jid``."""
    if road.links.get("successor", (None, None))[:2] == ("junction", jid):
        return "end"
    if road.links.get("predecessor", (None, None))[:2] == ("junction", jid):
        return "start"
    return None


@dataclass
class _MidLink:
    """One end of road ``road`` joined to road ``main`` at ``s`` (not at an end of ``main``):
    OpenDRIVE 1.7 virtual junctions (a road link with ``elementS``, or the deprecated
    ``connection type="virtual"``). ``lanes``: (lane of ``road`` at that end, lane of
    ``main``), from the lane links or the connection's laneLinks."""
    road: str
    end: str                 # "start" (the road's predecessor link) or "end"
    main: str
    s: float
    lanes: list


def _split_at_mid_road_links(path, root, roads: dict, strict: bool) -> list[_MidLink]:
    """Find the roads joined to another road part-way along it and split that road's lane
    sections at each such s, so the lanes there have an end to link (lane ids of the split
    road count the new sections). A link to a missing road or an s off the road warns
    (InputError with ``strict``) and is dropped."""
    links: list[_MidLink] = []
    for el in _kids(root, "road"):
        rid = el.get("id")
        link = _kid(el, "link")
        if rid not in roads or link is None:
            continue
        for kind, end in (("predecessor", "start"), ("successor", "end")):
            le = _kid(link, kind)
            if le is None or le.get("elementS") is None:
                continue
            # not a link to the other road's end: _link_lanes must not read it as one
            roads[rid].links.pop(kind, None)
            sec = roads[rid].sections[0 if end == "start" else -1]
            lanes = [(ln.id, ln.pred if end == "start" else ln.succ) for ln in sec.left + sec.right]
            links.append(_MidLink(rid, end, le.get("elementId"), le.get("elementS"),
                                  [(a, b) for a, b in lanes if b is not None]))
    for j in _kids(root, "junction"):
        for c in _kids(j, "connection"):
            if c.get("type") != "virtual":
                continue
            con = c.get("connectingRoad")
            for kind, end in (("predecessor", "start"), ("successor", "end")):
                le = _kid(c, kind)
                if le is None or con not in roads:
                    continue
                ll = []
                for x in _kids(c, "laneLink"):
                    try:
                        ll.append((int(float(x.get("to"))), int(float(x.get("from")))))
                    except (TypeError, ValueError, OverflowError):
                        continue
                links.append(_MidLink(con, end, le.get("elementId"), le.get("elementS"), ll))
    out = []
    for ml in links:
        try:
            s_ = float(ml.s)
        except (TypeError, ValueError):
            s_ = float("nan")
        main = roads.get(ml.main)
        why = (f"links to road {ml.main}, which is not imported" if main is None else
               f"links to road {ml.main} at s={ml.s}, outside it (length {main.length:g})"
               if not (np.isfinite(s_) and -1e-6 <= s_ <= main.length + 1e-6) else None)
        if why:
            msg = f"{path}: road {ml.road}: its {ml.end} {why}; link dropped"
            if strict:
                raise InputError(msg)
            warnings.warn(msg, OpenDriveWarning, stacklevel=3)
            continue
        ml.s = min(max(s_, 0.0), main.length)
        _split_road(main, ml.s)
        out.append(ml)
    return out


class _Shifted:
    """A lane-width polynomial of a section read from ``delta`` further along (the second
    part of a split section)."""

    def __init__(self, fn, delta: float):
        self.fn, self.delta = fn, delta

    def __call__(self, ds):
        return self.fn(np.asarray(ds, dtype=np.float64) + self.delta)


def _split_road(road: _Road, s: float, eps: float = 1e-6) -> None:
    """Split the lane section containing ``s`` in two at ``s`` (nothing when ``s`` already
    bounds a section). The halves keep the lanes, widths and marks; lanes continue from the
    first half into the second."""
    from dataclasses import replace
    for k, sec in enumerate(road.sections):
        if sec.s0 + eps < s < sec.s1 - eps:
            break
    else:
        return
    d = s - sec.s0

    def marks(ms, first: bool):
        ms = sorted(ms, key=lambda r: r[0])
        if first:
            return [m_ for m_ in ms if m_[0] < d]
        active = [m_ for m_ in ms if m_[0] <= d]
        later = [(o - d, t, c) for o, t, c in ms if o > d]
        return ([(0.0,) + active[-1][1:]] if active else []) + later

    def halves(lanes):
        a = [replace(ln, marks=marks(ln.marks, True), succ=ln.id) for ln in lanes]
        b = [replace(ln, width=_Shifted(ln.width, d), marks=marks(ln.marks, False), pred=ln.id)
             for ln in lanes]
        return a, b

    la, lb = halves(sec.left)
    ra, rb = halves(sec.right)
    road.sections[k:k + 1] = [_Section(sec.s0, s, la, ra, marks(sec.center_marks, True)),
                              _Section(s, sec.s1, lb, rb, marks(sec.center_marks, False))]


def _mid_road_pairs(roads: dict, links: list[_MidLink]) -> set:
    """Lane-end pairs of the mid-road links: the linked road's lane end meets both the main
    road lane ending at s and the one starting there; ``_link_lanes`` keeps the pair whose
    ends are an exit and an entry in the lanes' directions of travel (so a road branching off
    gets the main lane as predecessor, one merging in gets it as successor)."""
    pairs = set()
    for ml in links:
        if ml.road not in roads or ml.main not in roads:
            continue
        road, main = roads[ml.road], roads[ml.main]
        rk = 0 if ml.end == "start" else len(road.sections) - 1
        ends = []
        for k, sec in enumerate(main.sections):
            if abs(sec.s1 - ml.s) < 1e-6:
                ends.append((k, "end"))
            if abs(sec.s0 - ml.s) < 1e-6:
                ends.append((k, "start"))
        for r_lane, m_lane in ml.lanes:
            for k, e in ends:
                pairs.add(tuple(sorted([(ml.road, rk, r_lane, ml.end), (ml.main, k, m_lane, e)])))
    return pairs


def _attach_georef(path, root, layout) -> None:
    """The header's geoReference (and <offset>) as the layout's frame (``georef``); a text
    pyproj cannot read warns and stays text in ``metadata.source.geoReference``."""
    from lsd3d_usd.layout import georef
    h = _kid(root, "header")
    if h is None:
        return
    geo, off = _kid(h, "geoReference"), _kid(h, "offset")

    def warn(msg):
        warnings.warn(msg, OpenDriveWarning, stacklevel=4)
    ref = georef.from_opendrive_header(None if geo is None else geo.text,
                                       None if off is None else dict(off.attrib), str(path), warn)
    if ref is not None:
        georef.attach(layout, ref)
