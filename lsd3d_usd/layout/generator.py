"""Procedural road networks, grown chunk by chunk from a seed (MetaDrive-like blocks).

Two steps, so a layout is replayable from its description:

1. ``plan(seed, extent, style)`` → a JSON-able *description*: one node per
   100 m chunk (position jittered around the chunk centre), which grid edges
   carry a road, each row's / column's cross-section, and per node the block
   that joins its roads (``junction`` = 4-way/T intersection with corner
   radii, ``roundabout``, ``curve`` = fillet arc, ``deadend``, ``none``) with
   its parameters. Every decision comes from a seed hashed from the master
   seed and the chunk / edge / row index, so neighbouring chunks agree on the
   roads crossing their shared border whatever order they are generated in.
2. ``build(description)`` → a :class:`Layout`, chunk by chunk (``build_chunk``):
   chunk (i, j) holds its node's block and the pieces of the roads crossing
   it, cut exactly at the chunk borders; lanes of consecutive pieces are
   linked (the end point of one is bit-identical to the start of the next).

Node jitter (±JITTER) keeps every node ≥ 40 m from its chunk's borders and
every block within MAX_BLOCK_REACH of its node, so a straight road crosses a
chunk border with the same direction on both sides (no kink) and a block never
leaves its chunk.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np
import shapely
import shapely.prepared
from shapely.geometry import LineString, Point, Polygon, box as shp_box
from shapely.geometry.polygon import orient

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import blocks as B
from lsd3d_usd.layout import model as m

GENERATOR_NAME = "lsd3d-usd/blocks"
GENERATOR_VERSION = 1
STYLES = ("urban", "suburban", "highway")
JITTER = 10.0
MAX_BLOCK_REACH = 36.0
CROSSWALK_DEPTH = 3.0
STOP_GAP = 4.5          # from junction boundary to where lane lines start
PARKING_SPOT = (5.5, 2.2)
PARKING_PITCH = 6.0

STYLE_PARAMS = {
    "urban": dict(p_node=1.0, p_edge_h=0.9, p_edge_v=0.9, lanes_h=(1, 2, 2, 3), lanes_v=(1, 2, 2, 3),
                  lane_width=(3.0, 3.5), median=(0.0, 0.0), p_parking=0.5, sidewalk=(3.0, 4.5),
                  setback=(0.5, 2.0), corner=(5.0, 9.0), p_roundabout=0.12, height=(9.0, 45.0),
                  b_width=(12.0, 32.0), b_depth=(12.0, 24.0), tree_spacing=12.0, p_crosswalk=1.0,
                  p_stop=0.0, p_building=0.9, hedges=False),
    "suburban": dict(p_node=0.95, p_edge_h=0.75, p_edge_v=0.75, lanes_h=(1, 1, 2), lanes_v=(1, 1, 2),
                     lane_width=(3.0, 3.5), median=(0.0, 0.0), p_parking=0.3, sidewalk=(2.0, 3.0),
                     setback=(3.0, 6.0), corner=(6.0, 10.0), p_roundabout=0.2, height=(5.0, 10.0),
                     b_width=(9.0, 16.0), b_depth=(9.0, 14.0), tree_spacing=9.0, p_crosswalk=0.5,
                     p_stop=1.0, p_building=0.75, hedges=True),
    "highway": dict(p_node=1.0, p_edge_h=1.0, p_edge_v=0.25, lanes_h=(3, 4), lanes_v=(1, 2),
                    lane_width=(3.5, 3.75), median=(2.0, 4.0), p_parking=0.0, sidewalk=(0.0, 0.0),
                    setback=(8.0, 14.0), corner=(10.0, 14.0), p_roundabout=0.0, height=(6.0, 15.0),
                    b_width=(15.0, 40.0), b_depth=(15.0, 30.0), tree_spacing=15.0, p_crosswalk=0.0,
                    p_stop=0.0, p_building=0.4, hedges=False),
}


# ============================================================== hashing seeds

def _key_ints(keys) -> list[int]:
    out = []
    for k in keys:
        if isinstance(k, str):
            out.append(zlib.crc32(k.encode()))
        else:
            k = int(k)
            out.append(2 * k if k >= 0 else -2 * k - 1)  # zigzag: non-negative
    return out


def _rng(seed: int, *keys) -> np.random.Generator:
    """A generator seeded by the master seed and ``keys`` (order-independent of anything else)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFFFFFF, *_key_ints(keys)]))


def _enc(k: int) -> str:
    return f"m{-k}" if k < 0 else str(k)


def node_key(i: int, j: int) -> str:
    return f"{_enc(i)}_{_enc(j)}"


def edge_key(kind: str, i: int, j: int) -> str:
    """Edge from node (i, j) to (i+1, j) (kind 'h') or (i, j+1) (kind 'v')."""
    return f"{kind}{_enc(i)}_{_enc(j)}"


def parse_extent(text: str) -> tuple[float, float]:
    """'400x400' → (400.0, 400.0)."""
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--extent {text!r}: expected WIDTHxHEIGHT in metres, e.g. 400x400") from None
    if not (w >= 50 and h >= 50) or not (w <= 20000 and h <= 20000):
        raise InputError(f"--extent {text!r}: each side must be between 50 and 20000 m")
    return w, h


# ======================================================================= plan

def plan(seed: int, extent: tuple[float, float], style: str = "urban",
         chunk_size: float = m.DEFAULT_CHUNK_SIZE) -> dict:
    """The description of a layout (JSON-able): nodes, edges, sections, blocks."""
    if style not in STYLES:
        raise InputError(f"unknown style {style!r}; choose one of {', '.join(STYLES)}")
    if chunk_size != m.DEFAULT_CHUNK_SIZE:
        raise InputError("the block generator is tuned for 100 m chunks")
    width, height = float(extent[0]), float(extent[1])
    sp = STYLE_PARAMS[style]
    cs = chunk_size
    ni, nj = int(np.ceil(width / cs - 1e-9)), int(np.ceil(height / cs - 1e-9))

    g = _rng(seed, "globals")
    lane_width = round(float(g.uniform(*sp["lane_width"])), 2)
    glob = {"lane_width": lane_width, "sidewalk": round(float(g.uniform(*sp["sidewalk"])), 2),
            "setback": round(float(g.uniform(*sp["setback"])), 2)}

    def full(i, j):  # chunk entirely inside the extent
        return 0 <= i and 0 <= j and (i + 1) * cs <= width + 1e-9 and (j + 1) * cs <= height + 1e-9

    def node_pos(i, j):
        r = _rng(seed, "node", i, j)
        return [float((i + 0.5) * cs + r.uniform(-JITTER, JITTER)),
                float((j + 0.5) * cs + r.uniform(-JITTER, JITTER))], bool(r.random() < sp["p_node"])

    def section(kind, k):
        r = _rng(seed, "section", kind, k)
        lanes = int(r.choice(sp[f"lanes_{kind}"]))
        med = round(float(r.uniform(*sp["median"])), 2) if kind == "h" or style != "highway" else 0.0
        park = 2.4 if (r.random() < sp["p_parking"] and lanes <= 2) else 0.0
        return B.Section(lanes, lane_width, med, park).to_dict()

    nodes: dict[str, dict] = {}
    for i in range(-1, ni + 1):
        for j in range(-1, nj + 1):
            pos, present = node_pos(i, j)
            real = full(i, j) and present
            nodes[node_key(i, j)] = {"ij": [i, j], "pos": pos, "real": real}

    edges = []
    for i in range(-1, ni + 1):
        for j in range(-1, nj + 1):
            for kind, (i2, j2) in (("h", (i + 1, j)), ("v", (i, j + 1))):
                a, b = nodes[node_key(i, j)], nodes.get(node_key(i2, j2))
                if b is None or not (a["real"] or b["real"]):
                    continue
                r = _rng(seed, "edge", kind, i, j)
                if r.random() >= sp[f"p_edge_{kind}"]:
                    continue
                sec = section(kind, j if kind == "h" else i)
                edges.append({"key": edge_key(kind, i, j), "a": node_key(i, j),
                              "b": node_key(i2, j2), "section": sec})

    degree = {k: [] for k in nodes}
    for e in edges:
        degree[e["a"]].append(e)
        degree[e["b"]].append(e)
    for k, nd in nodes.items():
        if not nd["real"]:
            continue
        i, j = nd["ij"]
        r = _rng(seed, "block", i, j)
        arms = degree[k]
        deg = len(arms)
        if deg == 0:
            nd["block"], nd["params"] = "none", {}
        elif deg == 1:
            nd["block"], nd["params"] = "deadend", {}
        elif deg == 2 and arms[0]["section"] == arms[1]["section"]:
            nd["block"], nd["params"] = "curve", {"radius": round(float(r.uniform(25.0, 60.0)), 2)}
        elif deg >= 3 and r.random() < sp["p_roundabout"] and \
                max(B.Section(**a["section"]).half_width for a in arms) < 9.0:
            nd["block"] = "roundabout"
            nd["params"] = {"island": round(float(r.uniform(7.0, 11.0)), 2),
                            "ring_width": round(lane_width + 1.5, 2),
                            "corner_radius": round(float(r.uniform(*sp["corner"])), 2)}
        else:
            nd["block"] = "junction"
            nd["params"] = {"corner_radius": round(float(r.uniform(*sp["corner"])), 2),
                            "crosswalks": bool(deg >= 3 and r.random() < sp["p_crosswalk"]),
                            "stop_signs": bool(deg >= 3 and r.random() < sp["p_stop"])}

    chunks = {node_key(i, j): int(_rng(seed, "chunk", i, j).integers(0, 2**31 - 1))
              for i in range(ni) for j in range(nj)}
    return {"generator": GENERATOR_NAME, "version": GENERATOR_VERSION, "seed": int(seed),
            "style": style, "extent": [0.0, 0.0, width, height], "chunk_size": cs,
            "globals": glob, "style_params": {k: (list(v) if isinstance(v, tuple) else v)
                                               for k, v in sp.items()},
            "nodes": nodes, "edges": edges, "chunks": chunks}


# ================================================================ build context

@dataclass
class _Arm:
    edge: dict
    direction: np.ndarray      # unit, away from the node
    section: B.Section
    at_a: bool                 # the node is the edge's a end
    cut: float = 0.0


@dataclass
class _Edge:
    key: str
    a: str
    b: str
    section: B.Section
    p_a: np.ndarray            # node positions
    p_b: np.ndarray
    d: np.ndarray              # unit a→b
    s0: float = 0.0            # road starts at p_a + s0*d
    s1: float = 0.0
    pieces: list = field(default_factory=list)   # [(chunk (i, j), s_start, s_end, border_start, border_end)]
    border0: tuple | None = None   # (axis, value) of the extent border at s0, None at a node
    border1: tuple | None = None

    def s_at(self, s: float, border, lateral: float) -> float:
        """Parameter where the line at ``lateral`` meets ``border`` (axis, value); ``s`` at a node.
        Offset lines of a road crossing a border at an angle are cut on the border itself."""
        if border is None:
            return s
        axis, value = border
        return float((value - (self.p_a[axis] + lateral * B.left_normal(self.d)[axis])) / self.d[axis])

    def point(self, s: float, lateral: float = 0.0) -> np.ndarray:
        return self.p_a + s * self.d + lateral * B.left_normal(self.d)


class _Context:
    """Everything ``build_chunk`` needs, derived from the description only."""

    def __init__(self, desc: dict):
        try:
            self.desc = desc
            self.seed = int(desc["seed"])
            self.style = desc["style"]
            x0, y0, x1, y1 = (float(v) for v in desc["extent"])
            self.extent = (x0, y0, x1, y1)
            self.cs = float(desc["chunk_size"])
            self.glob = desc["globals"]
            self.sp = desc["style_params"]
            self.nodes = desc["nodes"]
            self.chunk_seeds = desc["chunks"]
            self.edges = {e["key"]: _Edge(e["key"], e["a"], e["b"], B.Section(**e["section"]),
                                          np.array(self.nodes[e["a"]]["pos"], float),
                                          np.array(self.nodes[e["b"]]["pos"], float),
                                          np.zeros(2)) for e in desc["edges"]}
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"layout description is incomplete or malformed: {e!r}") from None
        self.arms: dict[str, list[_Arm]] = {k: [] for k in self.nodes}
        for e in self.edges.values():
            e.d = B.unit(e.p_b - e.p_a)
            self.arms[e.a].append(_Arm(e, e.d, e.section, True))
            self.arms[e.b].append(_Arm(e, -e.d, e.section, False))
        for k, arms in self.arms.items():
            arms.sort(key=lambda a: B.angle_of(a.direction))
            if self.nodes[k]["real"]:
                self._cutbacks(k, arms)
        for e in self.edges.values():
            length = float(np.linalg.norm(e.p_b - e.p_a))
            e.s0 = self._end_cut(e, True)
            e.s1 = length - self._end_cut(e, False)
            if not self.nodes[e.a]["real"]:
                e.s0, e.border0 = self._extent_param(e, True)
            if not self.nodes[e.b]["real"]:
                e.s1, e.border1 = self._extent_param(e, False)
            e.pieces = self._split(e)

    def _end_cut(self, e: _Edge, at_a: bool) -> float:
        node = e.a if at_a else e.b
        for arm in self.arms[node]:
            if arm.edge is e and arm.at_a == at_a:
                return arm.cut
        return 0.0

    def _cutbacks(self, k: str, arms: list[_Arm]) -> None:
        nd = self.nodes[k]
        block, params = nd["block"], nd["params"]
        node = np.array(nd["pos"])
        if block == "junction":
            cuts = B.corner_cutbacks(node, [a.direction for a in arms],
                                     [a.section.half_width for a in arms], params["corner_radius"])
            for a, c in zip(arms, cuts):
                a.cut = min(c + 1.0, MAX_BLOCK_REACH - 6)
        elif block == "roundabout":
            for a in arms:
                a.cut = params["island"] + params["ring_width"] + 8.0
        elif block == "curve":
            t = self._curve_t(k)
            for a in arms:
                a.cut = t
        # deadend / none: roads end at the node

    def curve_radius_t(self, k: str) -> tuple[float, float, float]:
        """(radius, tangent length, signed turn) of a curve block."""
        a0, a1 = self.arms[k]
        turn = B.wrap_angle(B.angle_of(a1.direction) - B.angle_of(-a0.direction))
        half = abs(turn) / 2
        want = self.nodes[k]["params"]["radius"]
        if abs(turn) < 1e-3:
            return float("inf"), 5.0, turn
        t = float(np.clip(want * np.tan(half), 5.0, MAX_BLOCK_REACH - 3))
        return t / np.tan(half), t, turn

    def _curve_t(self, k: str) -> float:
        return self.curve_radius_t(k)[1]

    def _extent_param(self, e: _Edge, at_a: bool) -> float:
        """Parameter along e where its line crosses the extent boundary (leaving the real end)."""
        x0, y0, x1, y1 = self.extent
        ts = []
        for axis, lo, hi in ((0, x0, x1), (1, y0, y1)):
            if abs(e.d[axis]) > 1e-12:
                for bound in (lo, hi):
                    ts.append(((bound - e.p_a[axis]) / e.d[axis], (axis, bound)))
        length = float(np.linalg.norm(e.p_b - e.p_a))
        # past a virtual node that lies inside the extent the road runs on, straight
        inside = [(t, bd) for t, bd in ts if (t <= length + 1e-9 if at_a else t >= -1e-9)
                  and self._inside(e.point(t), 1e-7)]
        if not inside:
            raise InputError(f"road {e.key} does not cross the extent")
        t, bd = (min if at_a else max)(inside, key=lambda x: x[0])
        return float(t), bd

    def _inside(self, p, tol=0.0) -> bool:
        x0, y0, x1, y1 = self.extent
        return x0 - tol <= p[0] <= x1 + tol and y0 - tol <= p[1] <= y1 + tol

    def _split(self, e: _Edge) -> list:
        """Pieces of the road between s0 and s1, cut at chunk borders."""
        cuts = {e.s0: e.border0, e.s1: e.border1}
        for axis in (0, 1):
            if abs(e.d[axis]) < 1e-12:
                continue
            a, b = sorted((e.point(e.s0)[axis], e.point(e.s1)[axis]))
            for k in range(int(np.floor(a / self.cs)) + 1, int(np.ceil(b / self.cs))):
                s = (k * self.cs - e.p_a[axis]) / e.d[axis]
                if e.s0 < s < e.s1:
                    cuts[float(s)] = (axis, k * self.cs)
        keys = sorted(cuts)
        pieces = []
        for s_a, s_b in zip(keys[:-1], keys[1:]):
            if s_b - s_a < 1e-6:
                continue
            mid = e.point((s_a + s_b) / 2)
            pieces.append(((int(np.floor(mid[0] / self.cs)), int(np.floor(mid[1] / self.cs))),
                           s_a, s_b, cuts[s_a], cuts[s_b]))
        return pieces

    def clip_box(self, i: int, j: int):
        x0, y0, x1, y1 = self.extent
        return (max(i * self.cs, x0), max(j * self.cs, y0),
                min((i + 1) * self.cs, x1), min((j + 1) * self.cs, y1))


# ============================================================ lane naming

def _lane_id(e: _Edge, piece: int, fwd: bool, k: int) -> str:
    return f"{e.key}_p{piece}_{'f' if fwd else 'b'}{k}"


def _end_lanes(e: _Edge, at_a: bool, incoming: bool) -> list[tuple[str, np.ndarray, float]]:
    """(lane id, end point, width) of the driving lanes at one end of a road,
    incoming = travelling toward that end. Index 0 = innermost lane."""
    piece = 0 if at_a else len(e.pieces) - 1
    s = e.s0 if at_a else e.s1
    fwd = (not at_a) if incoming else at_a
    out = []
    for k in range(e.section.lanes):
        off = e.section.lane_offset(k)
        out.append((_lane_id(e, piece, fwd, k), e.point(s, -off if fwd else off), e.section.lane_width))
    return out


# ================================================================ build

def build(desc: dict, chunks: list[tuple[int, int]] | None = None, progress=None) -> m.Layout:
    """The layout of a description, grown chunk by chunk in raster order."""
    ctx = _Context(desc)
    x0, y0, x1, y1 = ctx.extent
    layout = m.Layout(extent=((x0, y0), (x1, y1)), chunk_size=ctx.cs, metadata={"generator": desc})
    if chunks is None:
        ni, nj = int(np.ceil((x1 - x0) / ctx.cs - 1e-9)), int(np.ceil((y1 - y0) / ctx.cs - 1e-9))
        chunks = [(i, j) for j in range(nj) for i in range(ni)]
    for ij in chunks:
        for f in build_chunk(ctx, *ij):
            layout.add(f)
        if progress is not None:
            progress.update(1)
    layout.reindex()
    return layout


def generate(seed: int, extent: tuple[float, float] = (400.0, 400.0), style: str = "urban",
             progress=None) -> m.Layout:
    """plan + build."""
    return build(plan(seed, extent, style), progress=progress)


def build_chunk(ctx: _Context, i: int, j: int) -> list:
    """Features of chunk (i, j): its node's block, the road pieces crossing it, sidewalks,
    road areas, curbs, buildings, trees, parking spots."""
    ck = node_key(i, j)
    feats: list = []
    road_polys = []        # road surface pieces (extended past the chunk; clipped at the end)
    node = ctx.nodes.get(ck)
    junction_zones = []

    # -- road pieces
    touching = []
    for e in ctx.edges.values():
        for pidx, (chunk, sa, sb, ba, bb) in enumerate(e.pieces):
            if chunk == (i, j):
                feats += _road_piece(ctx, e, pidx, sa, sb, ba, bb)
                touching.append(e)
    # strips overlap the blocks by 5 cm so unions leave no sliver gaps
    for e in {id(e): e for e in touching}.values():
        road_polys.append(_strip(e, e.s0 - 0.05, e.s1 + 0.05))

    # -- the node's block
    if node is not None and node["real"] and node.get("block", "none") != "none":
        block_feats, area, zones, pending = _node_block(ctx, ck)
        lanes = {f.id: f for f in feats if isinstance(f, m.LaneCenter)}
        for lid, (preds, succs) in pending.items():
            lanes[lid].predecessors += preds   # road lanes ending at this node lie in this chunk
            lanes[lid].successors += succs
        feats += block_feats
        road_polys.append(area)
        junction_zones += zones
        for arm in ctx.arms[ck]:
            road_polys.append(_strip(arm.edge, arm.edge.s0 - 0.05, arm.edge.s1 + 0.05))

    clip = shp_box(*ctx.clip_box(i, j))
    rng = _rng(ctx.chunk_seeds.get(ck, 0), "content")
    sw = float(ctx.glob["sidewalk"])
    roads = _no_slivers(shapely.union_all(road_polys)) if road_polys else Polygon()
    road_clip = roads.intersection(clip)
    for n, poly in enumerate(_polygons(road_clip)):
        feats.append(m.RoadArea(f"c{ck}_road{n}", polygon=_xyz(poly)))
    walks = Polygon()
    if sw > 0 and not roads.is_empty:
        walks = roads.buffer(sw, quad_segs=8).difference(roads).intersection(clip)
        for n, poly in enumerate(_polygons(walks)):
            feats.append(m.Sidewalk(f"c{ck}_walk{n}", polygon=_xyz(poly)))
    curbs = _curbs(road_clip, ctx.clip_box(i, j))
    for n, c in enumerate(curbs):
        feats.append(m.RoadEdge(f"c{ck}_curb{n}", points=_xyz(c), kind="boundary"))

    # -- buildings, trees, hedges
    taken = roads.union(walks) if not walks.is_empty else roads
    feats += _buildings_and_plants(ctx, ck, rng, clip, taken, curbs, walks, sw, junction_zones)
    return feats


def _no_slivers(geom, min_hole: float = 1.0):
    """Drop holes smaller than ``min_hole`` m² (numerical slivers between unioned pieces)."""
    polys = []
    for g in getattr(geom, "geoms", [geom]):
        if g.geom_type == "Polygon" and not g.is_empty:
            polys.append(Polygon(g.exterior, [r for r in g.interiors if Polygon(r).area >= min_hole]))
    return shapely.union_all(polys) if polys else Polygon()


def _xyz(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return np.concatenate([a, np.zeros((len(a), 1))], axis=1)


def _polygons(geom) -> list[np.ndarray]:
    """Hole-free CCW polygons (implicitly closed) covering ``geom``: a polygon
    with holes is cut through each hole's centre (the layout format has no holes)."""
    out = []
    stack = list(getattr(geom, "geoms", [geom]))
    while stack:
        g = stack.pop(0)
        if g.is_empty or g.geom_type not in ("Polygon", "MultiPolygon", "GeometryCollection"):
            continue
        if g.geom_type != "Polygon":
            stack[:0] = list(g.geoms)
            continue
        if g.area < 0.05:
            continue
        if g.interiors:
            cx = g.interiors[0].centroid.x
            minx, miny, maxx, maxy = g.bounds
            left = g.intersection(shp_box(minx - 1, miny - 1, cx, maxy + 1))
            right = g.intersection(shp_box(cx, miny - 1, maxx + 1, maxy + 1))
            stack[:0] = [left, right]
            continue
        g = orient(g.simplify(0.002), 1.0)
        if g.is_empty or g.geom_type != "Polygon":
            continue
        out.append(np.asarray(g.exterior.coords)[:-1, :2])
    return out


def _curbs(road_clip, clip_box) -> list[np.ndarray]:
    """Curb polylines: the road boundary without the parts on the chunk / extent borders.
    Oriented with the road on the left."""
    x0, y0, x1, y1 = clip_box
    eps = 1e-6

    def on_border(p, q):
        for axis, v in ((0, x0), (0, x1), (1, y0), (1, y1)):
            if abs(p[axis] - v) < eps and abs(q[axis] - v) < eps:
                return True
        return False

    out = []
    for g in getattr(road_clip, "geoms", [road_clip]):
        if g.is_empty or g.geom_type != "Polygon":
            continue
        g = orient(g.simplify(0.002), 1.0)
        for ring in [g.exterior, *g.interiors]:
            pts = np.asarray(ring.coords)[:, :2]
            n = len(pts) - 1
            border = [on_border(pts[k], pts[k + 1]) for k in range(n)]
            if not any(border):
                out.append(pts.copy())
                continue
            start = border.index(True)
            run: list = []
            for step in range(1, n + 1):
                k = (start + step) % n
                if border[k]:
                    if run:
                        out.append(np.array(run))
                    run = []
                else:
                    if not run:
                        run = [pts[k]]
                    run.append(pts[k + 1])
            if run:
                out.append(np.array(run))
    return [c for c in (_dedupe(c) for c in out) if len(c) >= 2]


def _dedupe(c: np.ndarray) -> np.ndarray:
    keep = np.ones(len(c), bool)
    keep[1:] = np.linalg.norm(np.diff(c, axis=0), axis=1) > 1e-9
    return c[keep]


def _strip(e: _Edge, sa: float, sb: float):
    """Road surface of a road between parameters sa and sb (rectangle)."""
    h = e.section.half_width
    n = B.left_normal(e.d)
    p, q = e.point(sa), e.point(sb)
    return Polygon([p - h * n, q - h * n, q + h * n, p + h * n])


def _line_specs(sec: B.Section) -> list[tuple[float, str, str, bool]]:
    """(lateral offset, kind, colour, double) of painted lines, in the a→b frame."""
    specs = []
    if sec.median > 0:
        specs += [(sec.median / 2, "solid", "yellow", False), (-sec.median / 2, "solid", "yellow", False)]
    elif sec.lanes >= 2:
        specs.append((0.0, "solid", "yellow", True))
    else:
        specs.append((0.0, "broken", "yellow", False))
    for k in range(1, sec.lanes):
        off = sec.median / 2 + k * sec.lane_width
        specs += [(off, "broken", "white", False), (-off, "broken", "white", False)]
    if sec.parking > 0:
        off = sec.median / 2 + sec.lanes * sec.lane_width
        specs += [(off, "solid", "white", False), (-off, "solid", "white", False)]
    return specs


def _road_piece(ctx: _Context, e: _Edge, pidx: int, sa: float, sb: float, ba, bb) -> list:
    """Lanes, lines, parking spots, crosswalks and stop lines of one piece of a road."""
    feats = []
    sec = e.section
    last = len(e.pieces) - 1
    speed = 13.89 if sec.lanes < 3 else 27.78
    for fwd in (True, False):
        for k in range(sec.lanes):
            off = sec.lane_offset(k)
            lat = -off if fwd else off
            pts = np.stack([e.point(e.s_at(sa, ba, lat), lat), e.point(e.s_at(sb, bb, lat), lat)])
            if not fwd:
                pts = pts[::-1].copy()
            lid = _lane_id(e, pidx, fwd, k)
            prev_piece, next_piece = (pidx - 1, pidx + 1) if fwd else (pidx + 1, pidx - 1)
            preds = [_lane_id(e, prev_piece, fwd, k)] if 0 <= prev_piece <= last else []
            succs = [_lane_id(e, next_piece, fwd, k)] if 0 <= next_piece <= last else []
            left = [_lane_id(e, pidx, fwd, k - 1)] if k > 0 else []
            right = [_lane_id(e, pidx, fwd, k + 1)] if k + 1 < sec.lanes else []
            feats.append(m.LaneCenter(lid, points=_xyz(pts), widths=np.full(2, sec.lane_width),
                                      lane_type="driving", direction="forward", speed_limit_mps=speed,
                                      predecessors=preds, successors=succs, road_id=e.key,
                                      left_neighbors=left, right_neighbors=right))
        if sec.parking > 0:
            lat = -sec.parking_offset() if fwd else sec.parking_offset()
            pts = np.stack([e.point(e.s_at(sa, ba, lat), lat), e.point(e.s_at(sb, bb, lat), lat)])
            if not fwd:
                pts = pts[::-1].copy()
            tag = "pf" if fwd else "pb"
            nxt = pidx + 1 if fwd else pidx - 1
            prv = pidx - 1 if fwd else pidx + 1
            feats.append(m.LaneCenter(
                f"{e.key}_p{pidx}_{tag}", points=_xyz(pts), widths=np.full(2, sec.parking),
                lane_type="parking", speed_limit_mps=0.0, road_id=e.key,
                predecessors=[f"{e.key}_p{prv}_{tag}"] if 0 <= prv <= last else [],
                successors=[f"{e.key}_p{nxt}_{tag}"] if 0 <= nxt <= last else []))

    # lines start after the junction approach (crosswalk + stop line)
    a_block = ctx.nodes[e.a].get("block") if ctx.nodes[e.a]["real"] else None
    b_block = ctx.nodes[e.b].get("block") if ctx.nodes[e.b]["real"] else None
    trim_a = STOP_GAP if a_block in ("junction", "roundabout") else 0.0
    trim_b = STOP_GAP if b_block in ("junction", "roundabout") else 0.0
    def span(lat):
        la = e.s_at(sa, ba, lat) if ba is not None else max(sa, e.s0 + trim_a)
        lb = e.s_at(sb, bb, lat) if bb is not None else min(sb, e.s1 - trim_b)
        return la, lb

    if min(sb, e.s1 - trim_b) - max(sa, e.s0 + trim_a) > 0.5:
        for n, (lat, kind, color, double) in enumerate(_line_specs(sec)):
            la, lb = span(lat)
            pts = np.stack([e.point(la, lat), e.point(lb, lat)])
            feats.append(m.RoadLine(f"{e.key}_p{pidx}_line{n}", points=_xyz(pts), kind=kind,
                                    color=color, double=double))
        if sec.median > 0:
            for n, lat in enumerate((sec.median / 2, -sec.median / 2)):
                la, lb = span(lat)
                pts = np.stack([e.point(la, lat), e.point(lb, lat)])
                feats.append(m.RoadEdge(f"{e.key}_p{pidx}_median{n}", points=_xyz(pts), kind="median"))

    # parking spots on a global grid along the road, kept in the piece that holds them whole
    if sec.parking > 0:
        r_len, r_w = PARKING_SPOT
        occ = _rng(ctx.seed, "parking", e.key)
        s_first, s_last = e.s0 + STOP_GAP + 4.0, e.s1 - STOP_GAP - 4.0
        count = int(max(0, np.floor((s_last - s_first) / PARKING_PITCH))) + 1 if s_last > s_first else 0
        flags = occ.random((max(count, 0), 2)) < 0.6
        for q in range(count):
            s = s_first + q * PARKING_PITCH
            if not (sa + r_len / 2 <= s <= sb - r_len / 2):
                continue
            for side, fwd in enumerate((True, False)):
                lat = -sec.parking_offset() if fwd else sec.parking_offset()
                heading = B.angle_of(e.d if fwd else -e.d)
                feats.append(m.ParkingSpot(f"{e.key}_spot{q}_{'r' if fwd else 'l'}",
                                           center=_xyz(e.point(s, lat)[None])[0], heading=heading,
                                           length=r_len, width=r_w, occupied=bool(flags[q, side])))

    # crosswalk and stop line at a junction end held by this piece
    for at_a, block in ((True, a_block), (False, b_block)):
        if block != "junction" or (at_a and pidx != 0) or (not at_a and pidx != last):
            continue
        node = ctx.nodes[e.a if at_a else e.b]
        s_edge = e.s0 if at_a else e.s1
        inward = 1.0 if at_a else -1.0   # along +d away from the node at the a end
        h = sec.half_width
        if node["params"].get("crosswalks"):
            s1_, s2_ = s_edge + inward * 0.5, s_edge + inward * (0.5 + CROSSWALK_DEPTH)
            poly = np.stack([e.point(s1_, -h), e.point(s2_, -h), e.point(s2_, h), e.point(s1_, h)])
            if m.polygon_area(poly) < 0:
                poly = poly[::-1].copy()
            feats.append(m.Crosswalk(f"{e.key}_cross{'a' if at_a else 'b'}", polygon=_xyz(poly)))
        s_stop = s_edge + inward * (STOP_GAP - 0.3)
        in_side = 1.0 if at_a else -1.0   # incoming lanes toward a travel b→a: left of a→b
        lo, hi = sec.median / 2, sec.median / 2 + sec.lanes * sec.lane_width
        pts = np.stack([e.point(s_stop, in_side * lo), e.point(s_stop, in_side * hi)])
        feats.append(m.StopLine(f"{e.key}_stop{'a' if at_a else 'b'}", points=_xyz(pts)))
        if node["params"].get("stop_signs"):
            incoming = [lid for lid, _, _ in _end_lanes(e, at_a, True)]
            pos = e.point(s_stop, in_side * (h + 0.8))
            feats.append(m.StopSign(f"{e.key}_sign{'a' if at_a else 'b'}", position=_xyz(pos[None])[0],
                                    lane_ids=incoming))
    return feats


# ----------------------------------------------------------------- node blocks

def _connector(lid, p0, t0, w0, p1, t1, w1, preds, succs, road_id, curve_pts=None):
    pts = curve_pts if curve_pts is not None else B.hermite(p0, t0, p1, t1)
    pts = pts.copy()
    pts[0], pts[-1] = p0, p1
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    frac = s / s[-1] if s[-1] > 0 else np.zeros_like(s)
    widths = w0 + (w1 - w0) * frac
    return m.LaneCenter(lid, points=_xyz(pts), widths=widths, lane_type="driving", road_id=road_id,
                        predecessors=preds, successors=succs, is_junction=True)


def _node_block(ctx: _Context, ck: str):
    """(features, road surface polygon, junction zones) of a node's block."""
    nd = ctx.nodes[ck]
    block, params = nd["block"], nd["params"]
    node = np.array(nd["pos"], float)
    arms = ctx.arms[ck]
    feats: list = []
    road_id = f"n{ck}"

    def arm_lanes(arm, incoming):
        return _end_lanes(arm.edge, arm.at_a, incoming)

    def link(lane_id, pred=None, succ=None):
        pending.setdefault(lane_id, ([], []))
        if pred:
            pending[lane_id][0].append(pred)
        if succ:
            pending[lane_id][1].append(succ)

    pending: dict[str, tuple[list, list]] = {}
    stubs = []
    for a in arms:
        h = a.section.half_width
        n = B.left_normal(a.direction)
        p, q = node, node + a.direction * (a.cut + 0.05)
        stubs.append(Polygon([p - h * n, q - h * n, q + h * n, p + h * n]))
    hmax = max(a.section.half_width for a in arms)

    if block == "deadend":
        area = shapely.union_all(stubs + [Point(node).buffer(hmax + 1.0, quad_segs=16)])
        return feats, area, [], pending

    if block == "curve":
        a0, a1 = arms
        radius, t, turn = ctx.curve_radius_t(ck)
        sec = a0.section
        # travel a0 → a1 for lanes incoming on a0; and a1 → a0 for the others
        for src, dst in ((a0, a1), (a1, a0)):
            ins, outs = arm_lanes(src, True), arm_lanes(dst, False)
            for k, ((lin, p0, w0), (lout, p1, w1)) in enumerate(zip(ins, outs)):
                lid = f"{road_id}_{'ab' if src is a0 else 'ba'}{k}"
                lateral = -sec.lane_offset(k)  # incoming lanes are right of travel
                pts = _curve_or_line(node, src.direction, dst.direction, radius, lateral, p0, p1)
                feats.append(_connector(lid, p0, None, w0, p1, None, w1, [lin], [lout], road_id, pts))
                feats[-1].is_junction = False
                link(lin, succ=lid)
                link(lout, pred=lid)
        # lines continue through the curve
        for n_, (lat, kind, color, double) in enumerate(_line_specs(sec)):
            # a0's edge frame (a→b) vs the travel frame (along -a0.direction)
            lat_t = -lat if a0.at_a else lat
            pts = _curve_or_line(node, a0.direction, a1.direction, radius, lat_t)
            feats.append(m.RoadLine(f"{road_id}_line{n_}", points=_xyz(pts), kind=kind, color=color,
                                    double=double))
        for n_, lat in enumerate((sec.median / 2, -sec.median / 2) if sec.median > 0 else ()):
            pts = _curve_or_line(node, a0.direction, a1.direction, radius, lat)
            feats.append(m.RoadEdge(f"{road_id}_median{n_}", points=_xyz(pts), kind="median"))
        center = _curve_or_line(node, a0.direction, a1.direction, radius, 0.0)
        area = LineString(center).buffer(sec.half_width, cap_style="flat", quad_segs=16)
        return feats, area, [], pending

    if block == "roundabout":
        feats_r, area = _roundabout(ctx, ck, node, arms, params, arm_lanes, link, stubs)
        return feats + feats_r, area, [Point(node).buffer(arms[0].cut)], pending

    # junction
    for ia, a_in in enumerate(arms):
        ins = arm_lanes(a_in, True)
        for io, a_out in enumerate(arms):
            if io == ia:
                continue
            outs = arm_lanes(a_out, False)
            turn = B.wrap_angle(B.angle_of(a_out.direction) - B.angle_of(-a_in.direction))
            if len(arms) == 2 or abs(turn) < np.pi / 4:
                pairs = [(k, min(k, len(outs) - 1)) for k in range(len(ins))]
            elif turn < 0:
                pairs = [(len(ins) - 1, len(outs) - 1)]
            else:
                pairs = [(0, 0)]
            for k_in, k_out in pairs:
                lin, p0, w0 = ins[k_in]
                lout, p1, w1 = outs[k_out]
                lid = f"{road_id}_{ia}{io}_{k_in}{k_out}"
                feats.append(_connector(lid, p0, -a_in.direction, w0, p1, a_out.direction, w1,
                                        [lin], [lout], road_id))
                link(lin, succ=lid)
                link(lout, pred=lid)
    core = shapely.union_all(stubs + [Point(node).buffer(hmax, quad_segs=16)])
    rc = params["corner_radius"]
    area = core.buffer(rc, quad_segs=12).buffer(-rc, quad_segs=12).union(core)
    zone = Point(node).buffer(max(a.cut for a in arms) + STOP_GAP)
    return feats, area, [zone], pending


def _curve_or_line(node, d_in, d_out, radius, lateral, p0=None, p1=None):
    if np.isinf(radius):
        u = -d_in
        s = B.left_normal(u) * lateral
        a = node + 5.0 * d_in + s if p0 is None else p0
        b = node + 5.0 * d_out + B.left_normal(d_out) * lateral if p1 is None else p1
        return np.stack([a, b])
    pts = B.curve_path(node, d_in, d_out, radius, lateral)
    if p0 is not None:
        pts[0], pts[-1] = p0, p1
    return pts


def _roundabout(ctx, ck, node, arms, params, arm_lanes, link, stubs):
    feats = []
    road_id = f"n{ck}"
    ri, rw = params["island"], params["ring_width"]
    r_lane = ri + rw / 2
    gaps = [(B.angle_of(arms[(k + 1) % len(arms)].direction) - B.angle_of(arms[k].direction)) % (2 * np.pi)
            for k in range(len(arms))]
    alpha = min(np.radians(25.0), 0.4 * min(gaps))
    marks = []   # (angle, kind, arm)
    for a in arms:
        phi = B.angle_of(a.direction)
        marks.append(((phi - alpha) % (2 * np.pi), "exit", a))
        marks.append(((phi + alpha) % (2 * np.pi), "entry", a))
    marks.sort(key=lambda t: t[0])
    n = len(marks)
    ring_ids = [f"{road_id}_ring{k}" for k in range(n)]

    def ring_point(ang):
        return node + r_lane * np.array([np.cos(ang), np.sin(ang)])

    def ring_tangent(ang):
        return np.array([-np.sin(ang), np.cos(ang)])

    ring_pts = [ring_point(mk[0]) for mk in marks]
    preds = {rid: [] for rid in ring_ids}
    succs = {rid: [] for rid in ring_ids}
    for k in range(n):
        succs[ring_ids[k]].append(ring_ids[(k + 1) % n])
        preds[ring_ids[(k + 1) % n]].append(ring_ids[k])
    lane_w = rw - 1.5
    for k, (ang, kind, a) in enumerate(marks):
        if kind == "entry":
            for q, (lin, p0, w0) in enumerate(arm_lanes(a, True)):
                lid = f"{road_id}_in{arms.index(a)}_{q}"
                feats.append(_connector(lid, p0, -a.direction, w0, ring_pts[k], ring_tangent(ang), lane_w,
                                        [lin], [ring_ids[k]], road_id))
                link(lin, succ=lid)
                preds[ring_ids[k]].append(lid)
        else:
            prev = ring_ids[(k - 1) % n]
            for q, (lout, p1, w1) in enumerate(arm_lanes(a, False)):
                lid = f"{road_id}_out{arms.index(a)}_{q}"
                feats.append(_connector(lid, ring_pts[k], ring_tangent(ang), lane_w, p1, a.direction, w1,
                                        [prev], [lout], road_id))
                link(lout, pred=lid)
                succs[prev].append(lid)
    for k in range(n):
        a0, a1 = marks[k][0], marks[(k + 1) % n][0]
        sweep = (a1 - a0) % (2 * np.pi)
        pts = B.arc_points(node, r_lane, a0, sweep)
        pts[0], pts[-1] = ring_pts[k], ring_pts[(k + 1) % n]
        feats.append(m.LaneCenter(ring_ids[k], points=_xyz(pts), widths=np.full(len(pts), lane_w),
                                  road_id=road_id, is_junction=True, predecessors=preds[ring_ids[k]],
                                  successors=succs[ring_ids[k]]))
    island = Point(node).buffer(ri, quad_segs=32)
    ring = Point(node).buffer(ri + rw, quad_segs=32)
    core = shapely.union_all(stubs + [ring])
    rc = params["corner_radius"]
    area = core.buffer(rc, quad_segs=12).buffer(-rc, quad_segs=12).union(core).difference(island)
    isl = _polygons(island.buffer(-0.3))
    if isl:
        feats.append(m.VegetationZone(f"{road_id}_island", polygon=_xyz(isl[0]), kind="grass"))
    feats.append(m.Tree(f"{road_id}_islandtree", position=np.array([node[0], node[1], 0.0]),
                        height_hint=7.0, crown_radius_hint=min(3.0, ri * 0.4)))
    return feats, area


# ------------------------------------------------------------- buildings etc.

def _rect(c, t, w, d):
    v = B.left_normal(t)
    return np.stack([c - t * w / 2 - v * d / 2, c + t * w / 2 - v * d / 2,
                     c + t * w / 2 + v * d / 2, c - t * w / 2 + v * d / 2])


def _buildings_and_plants(ctx, ck, rng, clip, taken, curbs, walks, sw, zones) -> list:
    sp = ctx.sp
    setback = float(ctx.glob["setback"])
    feats = []
    free = clip.buffer(-0.5, join_style="mitre")
    if not taken.is_empty:
        free = free.difference(taken.buffer(setback + 0.05, quad_segs=4))
    free_p = shapely.prepared.prep(free) if not free.is_empty else None
    placed = []
    nb = 0
    no_roads = taken.is_empty or not curbs
    if no_roads and not free.is_empty:
        park = _polygons(clip.buffer(-2.0, join_style="mitre"))
        if park:
            feats.append(m.VegetationZone(f"c{ck}_park", polygon=_xyz(park[0]), kind="park"))
    # buildings along the curbs (frontage), then a few tries deeper in the block
    if free_p is not None and not no_roads:
        for c in curbs:
            line = LineString(c)
            L = line.length
            s = float(rng.uniform(0, 6))
            while s < L:
                w = float(rng.uniform(*sp["b_width"]))
                d = float(rng.uniform(*sp["b_depth"]))
                q = np.asarray(line.interpolate(s).coords[0])
                q2 = np.asarray(line.interpolate(min(s + 1.0, L)).coords[0])
                q1 = np.asarray(line.interpolate(max(s - 1.0, 0)).coords[0])
                if np.linalg.norm(q2 - q1) < 1e-6:
                    break
                t = B.unit(q2 - q1)
                out = -B.left_normal(t)           # road on the left → outward is right
                ctr = q + t * w / 2 + out * (sw + setback + 0.3 + d / 2)
                if rng.random() < sp["p_building"]:
                    feats_b = _try_building(ctx, ck, rng, free_p, placed, ctr, t, w, d, nb)
                    if feats_b:
                        feats += feats_b
                        nb += 1
                        if sp["hedges"] and setback >= 2.0:
                            hq = q + out * (sw + 0.8)
                            hl = LineString([hq, hq + t * w]).intersection(
                                clip.buffer(-0.5, join_style="mitre")).difference(taken)
                            if hl.geom_type == "LineString" and hl.length > 2.0:
                                feats.append(m.Hedge(f"c{ck}_hedge{nb}", points=_xyz(np.asarray(hl.coords)),
                                                     height=1.1, width=0.7))
                s += w + float(rng.uniform(1.5, 6.0))
    # trees along the sidewalks
    spacing = float(sp["tree_spacing"])
    walks_p = shapely.prepared.prep(walks.buffer(-0.4)) if not walks.is_empty else None
    zone = shapely.union_all(zones) if zones else None
    nt = 0
    for c in curbs:
        line = LineString(c)
        s = float(rng.uniform(2, spacing))
        while s < line.length:
            q = np.asarray(line.interpolate(s).coords[0])
            q2 = np.asarray(line.interpolate(min(s + 0.5, line.length)).coords[0])
            q1 = np.asarray(line.interpolate(max(s - 0.5, 0)).coords[0])
            s += spacing * float(rng.uniform(0.8, 1.2))
            if np.linalg.norm(q2 - q1) < 1e-6:
                continue
            out = -B.left_normal(B.unit(q2 - q1))
            p = q + out * (sw * 0.6 if sw > 0 else 5.0)
            pt = Point(p)
            if zone is not None and zone.contains(pt):
                continue
            ok = walks_p.contains(pt) if walks_p is not None else (free_p is not None and free_p.contains(pt))
            if not ok or not clip.contains(pt):
                continue
            feats.append(m.Tree(f"c{ck}_tree{nt}", position=np.array([p[0], p[1], 0.0]),
                                height_hint=float(rng.uniform(6, 12)),
                                crown_radius_hint=float(rng.uniform(1.8, 3.2))))
            nt += 1
    if no_roads and not free.is_empty:   # a park: trees scattered inside
        x0, y0, x1, y1 = free.bounds
        for _ in range(12):
            p = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            if free_p.contains(Point(p)):
                feats.append(m.Tree(f"c{ck}_tree{nt}", position=np.array([p[0], p[1], 0.0]),
                                    height_hint=float(rng.uniform(6, 14)),
                                    crown_radius_hint=float(rng.uniform(2, 4))))
                nt += 1
    return feats


def _try_building(ctx, ck, rng, free_p, placed, ctr, t, w, d, nb):
    sp = ctx.sp
    for shrink in (1.0, 0.8, 0.6):
        ww, dd = w * shrink, d * shrink
        if ww < 6 or dd < 6:
            break
        fp = _rect(ctr - t * (w - ww) / 2, t, ww, dd)
        poly = Polygon(fp)
        if not free_p.contains(poly):
            continue
        grown = poly.buffer(1.0, join_style="mitre")
        if any(grown.intersects(p) for p in placed):
            continue
        placed.append(poly)
        h = float(rng.uniform(*sp["height"]))
        return [m.Building(f"c{ck}_bldg{nb}", footprint=_xyz(fp), height_hint=h,
                           floors_hint=max(1, int(h // 3.2)))]
    return []
