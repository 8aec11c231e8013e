"""Layout → ASAM OpenDRIVE 1.7, so a layout (procedural, imported or hand-written) drives in
OpenDRIVE simulators.

Every lane (``LaneCenter``) becomes a road of its own whose reference line is the lane centre,
fitted with lines, arcs and paramPoly3 (``fitting.fit_polyline``). The road has one right
lane (id -1, travelling along the reference line) with the lane's widths, and a
``laneOffset`` of half the width, so that the lane's centre is the reference line itself.
Widths, lane offset and elevation are piecewise linear in s, exactly as the layout's
per-vertex values are.

Links: where a lane's end meets exactly one lane's start (and that lane has no other
predecessor), the two roads link directly. Every other meeting point of lane ends becomes a
``<junction>``: each link through it is a ``<connection>`` whose connecting road is the
successor lane (when it has only that predecessor) or else the predecessor lane (when it has
only that successor; contactPoint "end"); a lane that is a connecting road at both of its ends
is cut in two roads. A link between a lane with several successors and a lane with several
predecessors has no connecting road of its own in OpenDRIVE's model; it is written as a
connection whose connecting road lies outside the junction (readers that follow connections,
like ours, keep it; strict tools may drop it) and counted in the report.

Not exported: road lines, edges, crosswalks, buildings and other non-lane features; the
``both`` direction of a lane (written as a lane along its points); lane types without an
OpenDRIVE lane counterpart in our importer (``sidewalk``, ``border``, ``median``, ``other``)
do not come back as lanes.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
from lxml import etree

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import fitting
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout.importers import MapWarning
from lsd3d_usd.scene import atomic_write_bytes

DEFAULT_TOLERANCE = 0.02
REV_MAJOR, REV_MINOR = 1, 7
MAX_LANES = 200_000
MAX_VERTICES = 20_000_000

LANE_TYPE_TO_ODR = {"driving": "driving", "bike": "biking", "bus": "bus", "parking": "parking",
                    "shoulder": "shoulder", "restricted": "restricted", "entry": "entry", "exit": "exit",
                    "sidewalk": "sidewalk", "border": "border", "median": "median", "other": "none"}


@dataclass
class ExportReport:
    """What the export wrote: road ids per lane id, counts, and the largest fit deviations."""
    roads: dict = field(default_factory=dict)          # lane id -> [road id, ...] in travel order
    junctions: int = 0
    geometries: dict = field(default_factory=dict)     # kind -> count
    max_curve_deviation: float = 0.0                   # fitted curve to lane polyline, m
    max_vertex_deviation: float = 0.0                  # lane vertices to fitted curve, m
    skipped: list = field(default_factory=list)        # lane ids not exported (zero length)
    outside_connections: int = 0                       # see module doc


@dataclass
class _Piece:
    road_id: str
    lane: m.LaneCenter
    points: np.ndarray      # (N, 3), deduplicated, in travel order
    widths: np.ndarray
    junction: str = "-1"
    pred: tuple | None = None   # ("road"|"junction", id, contactPoint or None)
    succ: tuple | None = None


def _lf(x: float) -> str:
    """A float as OpenDRIVE text, exact (shortest repr that round-trips)."""
    x = float(x)
    return "0" if x == 0 else repr(x)


def _linear_records(s: np.ndarray, values: np.ndarray) -> list[tuple[float, float, float]]:
    """(s, a, b) records of the piecewise linear function through (s, values); consecutive
    pieces on one line are merged."""
    out = []
    for k in range(len(s) - 1):
        ds = s[k + 1] - s[k]
        b = (values[k + 1] - values[k]) / ds if ds > 0 else 0.0
        if out:
            s0, a0, b0 = out[-1]
            if abs(b - b0) <= 1e-12 * max(1.0, abs(b0)) and abs(a0 + b0 * (s[k] - s0) - values[k]) <= 1e-9:
                continue
        out.append((float(s[k]), float(values[k]), float(b)))
    return out or [(0.0, float(values[0]), 0.0)]


def _fit_piece(piece: _Piece, tol: float, rep: ExportReport):
    """Primitives of the piece's reference line and s of each vertex along it."""
    pts = piece.points
    prims, starts = fitting.fit_polyline(pts[:, :2], tol)
    s_vertex = np.empty(len(pts))
    s_geom = 0.0
    for prim, i, j in zip(prims, starts[:-1], starts[1:]):
        # vertices of a span get s by their share of the span's polyline length
        seg = np.hypot(*np.diff(pts[i:j + 1, :2], axis=0).T)
        frac = np.concatenate([[0.0], np.cumsum(seg)]) / seg.sum()
        s_vertex[i:j + 1] = s_geom + frac * prim.length
        d_curve, d_vertex = fitting.deviation(prim, pts[i:j + 1, :2])
        rep.max_curve_deviation = max(rep.max_curve_deviation, d_curve)
        rep.max_vertex_deviation = max(rep.max_vertex_deviation, d_vertex)
        rep.geometries[prim.kind] = rep.geometries.get(prim.kind, 0) + 1
        s_geom += prim.length
    return prims, s_vertex, s_geom


def _pieces(layout: m.Layout, rep: ExportReport) -> tuple[dict, list]:
    """Cut lanes into road pieces (one, or two for a lane that is a connecting road at both
    ends) and decide the links; returns (pieces by lane id, junctions)."""
    lanes = {}
    for ln in layout.lanes:
        pts = ln.points if ln.direction != "backward" else ln.points[::-1]
        w = ln.widths if ln.direction != "backward" else ln.widths[::-1]
        pts_d, keep = fitting.dedupe(pts)
        if len(pts_d) < 2:
            rep.skipped.append(ln.id)
            warnings.warn(f"lane {ln.id}: zero length; not exported", MapWarning, stacklevel=3)
            continue
        lanes[ln.id] = (ln, pts_d, np.asarray(w, dtype=np.float64)[keep])
    succ = {lid: [s for s in lanes[lid][0].successors if s in lanes] for lid in lanes}
    pred = {lid: [p for p in lanes[lid][0].predecessors if p in lanes] for lid in lanes}
    for lid in lanes:                       # links given on one side only count on both
        for s in succ[lid]:
            if lid not in pred[s]:
                pred[s].append(lid)
        for p in pred[lid]:
            if lid not in succ[p]:
                succ[p].append(lid)
    for lid, (ln, _, _) in lanes.items():
        for other in ln.successors + ln.predecessors:
            if other not in lanes:
                warnings.warn(f"lane {lid}: link to {other!r}, which is not an exported lane; "
                              "link dropped", MapWarning, stacklevel=3)

    # meeting points: connected groups of (exit of L) -- (entry of S) over links L -> S
    parent: dict = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    links = [(lid, s) for lid in lanes for s in succ[lid]]
    for lid, s in links:
        parent[find(("exit", lid))] = find(("entry", s))
    groups: dict = {}
    for lid, s in links:
        groups.setdefault(find(("exit", lid)), []).append((lid, s))

    start_junction: dict = {}     # lane id -> junction where the lane is a connecting road (start)
    end_junction: dict = {}       # lane id -> junction where it is one (end)
    direct: dict = {}             # lane id -> successor lane id (1:1)
    junctions = []                # (junction index, [(incoming lane, connecting lane, contact)])
    exit_in: dict = {}            # lane id -> junction index its end leads into
    entry_in: dict = {}           # lane id -> junction index its start comes from
    for key, glinks in groups.items():
        if len(glinks) == 1 and len(succ[glinks[0][0]]) == 1 and len(pred[glinks[0][1]]) == 1:
            direct[glinks[0][0]] = glinks[0][1]
            continue
        jx = len(junctions)
        conns = []
        for lid, s in glinks:
            if len(pred[s]) == 1:
                start_junction[s] = jx
                exit_in[lid] = jx
                conns.append((lid, s, "start"))
            elif len(succ[lid]) == 1:
                end_junction[lid] = jx
                entry_in[s] = jx
                conns.append((s, lid, "end"))
            else:
                exit_in[lid] = jx
                entry_in[s] = jx
                conns.append((lid, s, "start"))
                rep.outside_connections += 1
        junctions.append(conns)

    # road pieces
    pieces: dict[str, list[_Piece]] = {}
    next_id = 1
    for lid, (ln, pts, w) in lanes.items():
        if lid in start_junction and lid in end_junction:
            seg = np.hypot(*np.diff(pts[:, :2], axis=0).T)
            cum = np.concatenate([[0.0], np.cumsum(seg)])
            # cut at the interior vertex nearest to half the length (a 2-point lane gets one)
            if len(pts) == 2:
                pts = np.stack([pts[0], (pts[0] + pts[1]) / 2, pts[1]])
                w = np.array([w[0], (w[0] + w[1]) / 2, w[1]])
                k = 1
            else:
                k = int(np.clip(np.argmin(np.abs(cum - cum[-1] / 2)), 1, len(pts) - 2))
            parts = [(pts[:k + 1], w[:k + 1]), (pts[k:], w[k:])]
        else:
            parts = [(pts, w)]
        pieces[lid] = []
        for p, ww in parts:
            pieces[lid].append(_Piece(str(next_id), ln, p, ww))
            next_id += 1
        rep.roads[lid] = [pc.road_id for pc in pieces[lid]]
    junction_ids = [str(next_id + k) for k in range(len(junctions))]

    for lid, ps in pieces.items():
        head, tail = ps[0], ps[-1]
        if len(ps) == 2:
            head.succ = ("road", tail.road_id, "start")
            tail.pred = ("road", head.road_id, "end")
        if lid in start_junction:
            head.junction = junction_ids[start_junction[lid]]
            (p,) = pred[lid]
            head.pred = ("road", pieces[p][-1].road_id, "end")
        elif lid in entry_in:
            head.pred = ("junction", junction_ids[entry_in[lid]], None)
        if lid in end_junction:
            tail.junction = junction_ids[end_junction[lid]]
            (s,) = succ[lid]
            tail.succ = ("road", pieces[s][0].road_id, "start")
        elif lid in exit_in:
            tail.succ = ("junction", junction_ids[exit_in[lid]], None)
        if lid in direct:
            s = direct[lid]
            tail.succ = ("road", pieces[s][0].road_id, "start")
            pieces[s][0].pred = ("road", tail.road_id, "end")
    conn_out = []
    for jid, conns in zip(junction_ids, junctions):
        rows = []
        for inc, con, contact in conns:
            inc_piece = pieces[inc][-1] if contact == "start" else pieces[inc][0]
            con_piece = pieces[con][0] if contact == "start" else pieces[con][-1]
            rows.append((inc_piece.road_id, con_piece.road_id, contact))
        conn_out.append((jid, rows))
    rep.junctions = len(conn_out)
    return pieces, conn_out


def layout_to_opendrive(layout: m.Layout, tolerance: float = DEFAULT_TOLERANCE,
                        name: str = "lsd3d-usd layout"):
    """(lxml root element of the OpenDRIVE document, ExportReport)."""
    if not (tolerance > 0):
        raise InputError(f"export tolerance must be > 0, got {tolerance}")
    if len(layout.lanes) > MAX_LANES:
        raise InputError(f"layout has {len(layout.lanes)} lanes; the exporter takes at most {MAX_LANES}")
    n_vert = sum(len(ln.points) for ln in layout.lanes)
    if n_vert > MAX_VERTICES:
        raise InputError(f"layout lanes have {n_vert} vertices; the exporter takes at most {MAX_VERTICES}")
    rep = ExportReport()
    pieces, junctions = _pieces(layout, rep)
    if not pieces:
        raise InputError("the layout has no lane of positive length to export")

    root = etree.Element("OpenDRIVE")
    hdr = etree.SubElement(root, "header", revMajor=str(REV_MAJOR), revMinor=str(REV_MINOR), name=name,
                           version="1", vendor="lsd3d-usd")
    _write_georef(hdr, layout)
    for lid, ps in pieces.items():
        for pc in ps:
            _road(root, pc, tolerance, rep)
    for jid, rows in junctions:
        j = etree.SubElement(root, "junction", id=jid, name=f"junction {jid}")
        for n, (inc, con, contact) in enumerate(rows):
            c = etree.SubElement(j, "connection", id=str(n), incomingRoad=inc, connectingRoad=con,
                                 contactPoint=contact)
            etree.SubElement(c, "laneLink", **{"from": "-1", "to": "-1"})
    return root, rep


def _road(root, pc: _Piece, tol: float, rep: ExportReport) -> None:
    ln = pc.lane
    prims, s_v, length = _fit_piece(pc, tol, rep)
    r = etree.SubElement(root, "road", name=ln.id, length=_lf(length), id=pc.road_id,
                         junction=pc.junction, rule="RHT")
    if pc.pred or pc.succ:
        link = etree.SubElement(r, "link")
        for tag, lk in (("predecessor", pc.pred), ("successor", pc.succ)):
            if lk is None:
                continue
            attrs = {"elementType": lk[0], "elementId": lk[1]}
            if lk[2]:
                attrs["contactPoint"] = lk[2]
            etree.SubElement(link, tag, **attrs)
    pv = etree.SubElement(r, "planView")
    s = 0.0
    for p in prims:
        g = etree.SubElement(pv, "geometry", s=_lf(s), x=_lf(p.x), y=_lf(p.y), hdg=_lf(p.hdg),
                             length=_lf(p.length))
        if p.kind == "line":
            etree.SubElement(g, "line")
        elif p.kind == "arc":
            etree.SubElement(g, "arc", curvature=_lf(p.curvature))
        else:
            names = ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV")
            etree.SubElement(g, "paramPoly3", pRange="normalized",
                             **{k: _lf(v) for k, v in zip(names, p.coeffs)})
        s += p.length
    ep = etree.SubElement(r, "elevationProfile")
    for s0, a, b in _linear_records(s_v, pc.points[:, 2]):
        etree.SubElement(ep, "elevation", s=_lf(s0), a=_lf(a), b=_lf(b), c="0", d="0")
    lanes = etree.SubElement(r, "lanes")
    for s0, a, b in _linear_records(s_v, pc.widths / 2):
        etree.SubElement(lanes, "laneOffset", s=_lf(s0), a=_lf(a), b=_lf(b), c="0", d="0")
    sec = etree.SubElement(lanes, "laneSection", s="0")
    center = etree.SubElement(etree.SubElement(sec, "center"), "lane", id="0", type="none", level="false")
    etree.SubElement(center, "roadMark", sOffset="0", type="none", color="standard")
    right = etree.SubElement(sec, "right")
    lane = etree.SubElement(right, "lane", id="-1", type=LANE_TYPE_TO_ODR.get(ln.lane_type, "driving"),
                            level="false")
    if pc.pred and pc.pred[0] == "road" or pc.succ and pc.succ[0] == "road":
        ll = etree.SubElement(lane, "link")
        if pc.pred and pc.pred[0] == "road":
            etree.SubElement(ll, "predecessor", id="-1")
        if pc.succ and pc.succ[0] == "road":
            etree.SubElement(ll, "successor", id="-1")
    for s0, a, b in _linear_records(s_v, pc.widths):
        etree.SubElement(lane, "width", sOffset=_lf(s0), a=_lf(a), b=_lf(b), c="0", d="0")
    etree.SubElement(lane, "roadMark", sOffset="0", type="none", color="standard")
    if ln.speed_limit_mps > 0:
        etree.SubElement(lane, "speed", sOffset="0", max=_lf(ln.speed_limit_mps), unit="m/s")


def write_opendrive(layout: m.Layout, path: str | Path, tolerance: float = DEFAULT_TOLERANCE,
                    name: str | None = None) -> ExportReport:
    """Write ``layout`` as an OpenDRIVE 1.7 file (atomic: temp file + rename)."""
    root, rep = layout_to_opendrive(layout, tolerance, name or Path(path).stem)
    data = etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)
    atomic_write_bytes(Path(path), data)
    return rep


def opendrive_xsd() -> Path | None:
    """The ASAM OpenDRIVE 1.7 core schema shipped in the ``scenariogeneration`` package, if
    installed (it is a test dependency); None otherwise."""
    try:
        files = metadata.files("scenariogeneration") or []
    except metadata.PackageNotFoundError:
        return None
    for f in files:
        if str(f).replace("\\", "/").endswith("schemas/opendrive_17_core.xsd"):
            p = Path(f.locate())
            return p if p.is_file() else None
    return None


def validate(path: str | Path) -> list[str]:
    """Errors of the file against the ASAM OpenDRIVE 1.7 XSD (empty: valid). Raises
    InputError when no copy of the schema is installed."""
    xsd = opendrive_xsd()
    if xsd is None:
        raise InputError("no ASAM OpenDRIVE XSD installed (it ships with the scenariogeneration "
                         "package: pip install scenariogeneration)")
    schema = etree.XMLSchema(etree.parse(str(xsd)))
    doc = etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True))
    if schema.validate(doc):
        return []
    return [f"line {e.line}: {e.message}" for e in schema.error_log]




def _write_georef(hdr, layout: m.Layout) -> None:
    """The layout's geoReference (``georef``) as the header's <geoReference> and <offset>;
    for an older layout with only a geographic origin, the frame of that origin."""
    from lxml import etree

    from lsd3d_usd.layout import georef
    ref = georef.of_layout(layout)
    if ref is None:
        origin = (layout.metadata.get("source") or {}).get("origin")
        if not origin:
            return
        ref = georef.local_tangent(origin[0], origin[1])
    text, off = georef.opendrive_header_text(ref)
    geo = etree.SubElement(hdr, "geoReference")
    geo.text = etree.CDATA(text)
    if off:
        etree.SubElement(hdr, "offset", **off)
