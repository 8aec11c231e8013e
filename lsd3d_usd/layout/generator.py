"""Procedural road networks, grown chunk by chunk from a seed (MetaDrive-like blocks).

Two steps, so a layout is replayable from its description:

1. ``plan(seed, extent, style)`` → a JSON-able *description*: one node per
   100 m chunk (position jittered around the chunk centre), which grid edges
   carry a road, each row's / column's cross-section, and per node the block
   that joins its roads with its parameters. Block types are classes in
   ``blocktypes.BLOCKS`` (``junction`` = 4-way/T intersection with corner
   radii, ``roundabout``, ``curve`` = fillet arc, ``deadend``, ``none``); the
   generator asks that table which type claims a node, and asks the node's
   block for its sockets' cut-backs, its geometry and its approach markings. Every decision comes from a seed hashed from the master
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

import numpy as np
import shapely
import shapely.prepared
from shapely.geometry import LineString, Point, Polygon, box as shp_box
from shapely.geometry.polygon import orient

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import blocks as B
from lsd3d_usd.layout import blocktypes as BT
from lsd3d_usd.layout import roadnet as R
from lsd3d_usd.layout import model as m

GENERATOR_NAME = "lsd3d-usd/blocks"
GENERATOR_VERSION = 1
STYLES = ("urban", "suburban", "highway")
JITTER = 10.0
MAX_BLOCK_REACH = R.MAX_BLOCK_REACH
STOP_GAP = R.STOP_GAP
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
        sections = [B.Section(**a["section"]) for a in degree[k]]
        cls = BT.choose(r, sections, sp)
        nd["block"], nd["params"] = cls.ID, cls.sample_params(r, sections, sp, glob)

    chunks = {node_key(i, j): int(_rng(seed, "chunk", i, j).integers(0, 2**31 - 1))
              for i in range(ni) for j in range(nj)}
    return {"generator": GENERATOR_NAME, "version": GENERATOR_VERSION, "seed": int(seed),
            "style": style, "extent": [0.0, 0.0, width, height], "chunk_size": cs,
            "globals": glob, "style_params": {k: (list(v) if isinstance(v, tuple) else v)
                                               for k, v in sp.items()},
            "nodes": nodes, "edges": edges, "chunks": chunks}


# ================================================================ build context

class Context:
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
            self.edges = {e["key"]: R.Edge(e["key"], e["a"], e["b"], B.Section(**e["section"]),
                                          np.array(self.nodes[e["a"]]["pos"], float),
                                          np.array(self.nodes[e["b"]]["pos"], float),
                                          np.zeros(2)) for e in desc["edges"]}
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"layout description is incomplete or malformed: {e!r}") from None
        self.arms: dict[str, list[R.Arm]] = {k: [] for k in self.nodes}
        for e in self.edges.values():
            e.d = B.unit(e.p_b - e.p_a)
            self.arms[e.a].append(R.Arm(e, e.d, e.section, True))
            self.arms[e.b].append(R.Arm(e, -e.d, e.section, False))
        self.blocks: dict[str, BT.Block] = {}
        for k, arms in self.arms.items():
            arms.sort(key=lambda a: B.angle_of(a.direction))
            nd = self.nodes[k]
            if nd["real"]:
                try:
                    cls = BT.block_class(nd["block"])
                except ValueError as e:
                    raise InputError(f"layout description, node {k}: {e}") from None
                blk = self.blocks[k] = cls(k, nd["pos"], arms, nd["params"])
                for arm, c in zip(arms, blk.cutbacks()):
                    arm.cut = c
        for e in self.edges.values():
            length = float(np.linalg.norm(e.p_b - e.p_a))
            e.s0 = self._end_cut(e, True)
            e.s1 = length - self._end_cut(e, False)
            if not self.nodes[e.a]["real"]:
                e.s0, e.border0 = self._extent_param(e, True)
            if not self.nodes[e.b]["real"]:
                e.s1, e.border1 = self._extent_param(e, False)
            e.pieces = self._split(e)

    def _end_cut(self, e: R.Edge, at_a: bool) -> float:
        node = e.a if at_a else e.b
        for arm in self.arms[node]:
            if arm.edge is e and arm.at_a == at_a:
                return arm.cut
        return 0.0

    def _extent_param(self, e: R.Edge, at_a: bool) -> float:
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

    def block_at(self, k: str) -> BT.Block | None:
        """The block at node k (None for a node outside the extent or without one)."""
        return self.blocks.get(k)

    def _inside(self, p, tol=0.0) -> bool:
        x0, y0, x1, y1 = self.extent
        return x0 - tol <= p[0] <= x1 + tol and y0 - tol <= p[1] <= y1 + tol

    def _split(self, e: R.Edge) -> list:
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


# ================================================================ build

def build(desc: dict, chunks: list[tuple[int, int]] | None = None, progress=None) -> m.Layout:
    """The layout of a description, grown chunk by chunk in raster order."""
    ctx = Context(desc)
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


def build_chunk(ctx: Context, i: int, j: int) -> list:
    """Features of chunk (i, j): its node's block, the road pieces crossing it, sidewalks,
    road areas, curbs, buildings, trees, parking spots."""
    ck = node_key(i, j)
    feats: list = []
    road_polys = []        # road surface pieces (extended past the chunk; clipped at the end)
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
    blk = ctx.block_at(ck)
    geo = blk.build() if blk is not None else None
    if geo is not None:
        lanes = {f.id: f for f in feats if isinstance(f, m.LaneCenter)}
        for lid, (preds, succs) in geo.links.items():
            lanes[lid].predecessors += preds   # road lanes ending at this node lie in this chunk
            lanes[lid].successors += succs
        feats += geo.features
        road_polys.append(geo.area)
        junction_zones += geo.zones
        for arm in blk.arms:
            road_polys.append(_strip(arm.edge, arm.edge.s0 - 0.05, arm.edge.s1 + 0.05))

    clip = shp_box(*ctx.clip_box(i, j))
    rng = _rng(ctx.chunk_seeds.get(ck, 0), "content")
    sw = float(ctx.glob["sidewalk"])
    roads = _no_slivers(shapely.union_all(road_polys)) if road_polys else Polygon()
    road_clip = roads.intersection(clip)
    for n, poly in enumerate(R.polygons(road_clip)):
        feats.append(m.RoadArea(f"c{ck}_road{n}", polygon=R.xyz(poly)))
    walks = Polygon()
    if sw > 0 and not roads.is_empty:
        walks = roads.buffer(sw, quad_segs=8).difference(roads).intersection(clip)
        for n, poly in enumerate(R.polygons(walks)):
            feats.append(m.Sidewalk(f"c{ck}_walk{n}", polygon=R.xyz(poly)))
    curbs = _curbs(road_clip, ctx.clip_box(i, j))
    for n, c in enumerate(curbs):
        feats.append(m.RoadEdge(f"c{ck}_curb{n}", points=R.xyz(c), kind="boundary"))

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


def _strip(e: R.Edge, sa: float, sb: float):
    """Road surface of a road between parameters sa and sb (rectangle)."""
    h = e.section.half_width
    n = B.left_normal(e.d)
    p, q = e.point(sa), e.point(sb)
    return Polygon([p - h * n, q - h * n, q + h * n, p + h * n])


def _road_piece(ctx: Context, e: R.Edge, pidx: int, sa: float, sb: float, ba, bb) -> list:
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
            lid = R.lane_id(e, pidx, fwd, k)
            prev_piece, next_piece = (pidx - 1, pidx + 1) if fwd else (pidx + 1, pidx - 1)
            preds = [R.lane_id(e, prev_piece, fwd, k)] if 0 <= prev_piece <= last else []
            succs = [R.lane_id(e, next_piece, fwd, k)] if 0 <= next_piece <= last else []
            left = [R.lane_id(e, pidx, fwd, k - 1)] if k > 0 else []
            right = [R.lane_id(e, pidx, fwd, k + 1)] if k + 1 < sec.lanes else []
            feats.append(m.LaneCenter(lid, points=R.xyz(pts), widths=np.full(2, sec.lane_width),
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
                f"{e.key}_p{pidx}_{tag}", points=R.xyz(pts), widths=np.full(2, sec.parking),
                lane_type="parking", speed_limit_mps=0.0, road_id=e.key,
                predecessors=[f"{e.key}_p{prv}_{tag}"] if 0 <= prv <= last else [],
                successors=[f"{e.key}_p{nxt}_{tag}"] if 0 <= nxt <= last else []))

    # lines start after the block's approach (crosswalk + stop line)
    a_block, b_block = ctx.block_at(e.a), ctx.block_at(e.b)
    trim_a = a_block.APPROACH_GAP if a_block is not None else 0.0
    trim_b = b_block.APPROACH_GAP if b_block is not None else 0.0
    def span(lat):
        la = e.s_at(sa, ba, lat) if ba is not None else max(sa, e.s0 + trim_a)
        lb = e.s_at(sb, bb, lat) if bb is not None else min(sb, e.s1 - trim_b)
        return la, lb

    if min(sb, e.s1 - trim_b) - max(sa, e.s0 + trim_a) > 0.5:
        for n, (lat, kind, color, double) in enumerate(R.line_specs(sec)):
            la, lb = span(lat)
            pts = np.stack([e.point(la, lat), e.point(lb, lat)])
            feats.append(m.RoadLine(f"{e.key}_p{pidx}_line{n}", points=R.xyz(pts), kind=kind,
                                    color=color, double=double))
        if sec.median > 0:
            for n, lat in enumerate((sec.median / 2, -sec.median / 2)):
                la, lb = span(lat)
                pts = np.stack([e.point(la, lat), e.point(lb, lat)])
                feats.append(m.RoadEdge(f"{e.key}_p{pidx}_median{n}", points=R.xyz(pts), kind="median"))

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
                                           center=R.xyz(e.point(s, lat)[None])[0], heading=heading,
                                           length=r_len, width=r_w, occupied=bool(flags[q, side])))

    # the block's markings (crosswalk, stop line) at an end held by this piece
    for at_a, blk in ((True, a_block), (False, b_block)):
        if blk is None or (at_a and pidx != 0) or (not at_a and pidx != last):
            continue
        feats += blk.approach_features(e, at_a)
    return feats


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
        park = R.polygons(clip.buffer(-2.0, join_style="mitre"))
        if park:
            feats.append(m.VegetationZone(f"c{ck}_park", polygon=R.xyz(park[0]), kind="park"))
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
                                feats.append(m.Hedge(f"c{ck}_hedge{nb}", points=R.xyz(np.asarray(hl.coords)),
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
        return [m.Building(f"c{ck}_bldg{nb}", footprint=R.xyz(fp), height_hint=h,
                           floors_hint=max(1, int(h // 3.2)))]
    return []
