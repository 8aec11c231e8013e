"""Block types of the procedural generator: one class per type, registered in one table.

After MetaDrive's ``pgblock`` idea: a block type has an ``ID``, a *parameter space* sampled
from a seeded generator, and *sockets*, the places where the roads of its node attach
(position, direction and cross-section of each arm's straight road). The generator knows no
block by name: ``plan()`` asks :func:`choose` which type claims a node and samples its
parameters; ``build()`` makes an instance per node, asks it for its cut-backs (how far each
road stays away from the node), for its geometry, and for the markings on each approach.

Adding a block type = one subclass + ``register(cls, before=...)``. Types are asked in table
order whether they claim a node (``claims``, which may draw from the node's generator);
``junction`` comes last and claims everything. The order of draws is part of a layout's
seed: changing it changes every layout generated from a seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import LineString, Point, Polygon

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import blocks as B
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout import roadnet as R
from lsd3d_usd.registry import Registry


# ============================================================ parameter spaces

@dataclass(frozen=True)
class Uniform:
    """A float drawn uniformly from [low, high], rounded to centimetres (descriptions stay short)."""
    low: float
    high: float

    def sample(self, rng: np.random.Generator) -> float:
        return round(float(rng.uniform(self.low, self.high)), 2)

    def contains(self, value) -> bool:
        return isinstance(value, float) and self.low <= value <= self.high


@dataclass(frozen=True)
class Chance:
    """True with probability ``p``; never true (and no draw) when not ``active``."""
    p: float
    active: bool = True

    def sample(self, rng: np.random.Generator) -> bool:
        return bool(self.active and rng.random() < self.p)

    def contains(self, value) -> bool:
        return isinstance(value, bool) and (self.active or not value)


@dataclass(frozen=True)
class Fixed:
    """A value derived from the layout's globals, not drawn."""
    value: float

    def sample(self, rng: np.random.Generator) -> float:
        return self.value

    def contains(self, value) -> bool:
        return value == self.value


@dataclass(frozen=True)
class Socket:
    """Where a road attaches to a block: the start of its straight road on the centre line."""
    position: np.ndarray
    direction: np.ndarray       # unit, away from the node
    section: B.Section


@dataclass
class BlockGeometry:
    """What a block adds to its chunk: features, road surface, zones kept free of trees, and
    links to add to the lanes of the attached roads (lane id -> (predecessors, successors))."""
    features: list
    area: object                # shapely geometry
    zones: list = field(default_factory=list)
    links: dict = field(default_factory=dict)

    def link(self, lane_id: str, pred: str | None = None, succ: str | None = None) -> None:
        preds, succs = self.links.setdefault(lane_id, ([], []))
        if pred:
            preds.append(pred)
        if succ:
            succs.append(succ)


# ===================================================================== base

class Block:
    """A block at one node. ``arms`` are sorted by angle (CCW) and carry the sockets' cuts."""

    ID = ""
    APPROACH_GAP = 0.0   # road lines stop this far before the block (room for stop lines)

    @classmethod
    def claims(cls, rng: np.random.Generator, sections: list[B.Section], sp: dict) -> bool:
        """Whether this type takes a node whose roads have ``sections`` (may draw from rng)."""
        raise NotImplementedError  # abstract: each block type defines it

    @classmethod
    def parameter_space(cls, sections: list[B.Section], sp: dict, glob: dict) -> dict:
        """Name -> Uniform | Chance | Fixed, in drawing order."""
        return {}

    @classmethod
    def sample_params(cls, rng, sections, sp, glob) -> dict:
        return {k: p.sample(rng) for k, p in cls.parameter_space(sections, sp, glob).items()}

    def __init__(self, key: str, pos, arms: list[R.Arm], params: dict):
        self.key = key
        self.node = np.array(pos, dtype=np.float64)
        self.arms = arms
        self.params = params
        self.road_id = f"n{key}"

    def cutbacks(self) -> list[float]:
        """Distance from the node at which each arm's straight road starts."""
        return [0.0] * len(self.arms)

    def sockets(self) -> list[Socket]:
        return [Socket(self.node + a.direction * a.cut, a.direction, a.section) for a in self.arms]

    def build(self) -> BlockGeometry | None:
        """The block's own geometry (None: nothing at the node)."""
        raise NotImplementedError  # abstract: each block type defines it

    def approach_features(self, e: R.Edge, at_a: bool) -> list:
        """Markings on the road ``e`` where it enters this block (crosswalks, stop lines)."""
        return []

    # helpers
    def _stubs(self) -> list[Polygon]:
        """Road surface from the node to each socket (5 cm past it, so unions close)."""
        out = []
        for a in self.arms:
            h = a.section.half_width
            n = B.left_normal(a.direction)
            p, q = self.node, self.node + a.direction * (a.cut + 0.05)
            out.append(Polygon([p - h * n, q - h * n, q + h * n, p + h * n]))
        return out

    @staticmethod
    def _lanes(arm: R.Arm, incoming: bool):
        return R.end_lanes(arm.edge, arm.at_a, incoming)


# ================================================================ the types

class NoBlock(Block):
    """A node without roads: its chunk becomes a park."""
    ID = "none"

    @classmethod
    def claims(cls, rng, sections, sp):
        return len(sections) == 0

    def build(self):
        return None


class DeadEnd(Block):
    """One road ending at the node in a round turning area."""
    ID = "deadend"

    @classmethod
    def claims(cls, rng, sections, sp):
        return len(sections) == 1

    def build(self):
        hmax = max(a.section.half_width for a in self.arms)
        area = shapely.union_all(self._stubs() + [Point(self.node).buffer(hmax + 1.0, quad_segs=16)])
        return BlockGeometry([], area)


class Curve(Block):
    """Two roads of equal cross-section joined by a fillet arc (a gentle bend when nearly straight)."""
    ID = "curve"

    @classmethod
    def claims(cls, rng, sections, sp):
        return len(sections) == 2 and sections[0] == sections[1]

    @classmethod
    def parameter_space(cls, sections, sp, glob):
        return {"radius": Uniform(25.0, 60.0)}

    def radius_t(self) -> tuple[float, float, float]:
        """(radius, tangent length, signed turn); the tangent length keeps the arc in its chunk."""
        a0, a1 = self.arms
        turn = B.wrap_angle(B.angle_of(a1.direction) - B.angle_of(-a0.direction))
        half = abs(turn) / 2
        want = self.params["radius"]
        if abs(turn) < 1e-3:
            return float("inf"), 5.0, turn
        t = float(np.clip(want * np.tan(half), 5.0, R.MAX_BLOCK_REACH - 3))
        return t / np.tan(half), t, turn

    def cutbacks(self):
        t = self.radius_t()[1]
        return [t for _ in self.arms]

    def build(self):
        node = self.node
        a0, a1 = self.arms
        radius, _, _ = self.radius_t()
        sec = a0.section
        geo = BlockGeometry([], None)
        # travel a0 → a1 for lanes incoming on a0; and a1 → a0 for the others
        for src, dst in ((a0, a1), (a1, a0)):
            ins, outs = self._lanes(src, True), self._lanes(dst, False)
            for k, ((lin, p0, w0), (lout, p1, w1)) in enumerate(zip(ins, outs)):
                lid = f"{self.road_id}_{'ab' if src is a0 else 'ba'}{k}"
                lateral = -sec.lane_offset(k)  # incoming lanes are right of travel
                pts = R.curve_or_line(node, src.direction, dst.direction, radius, lateral, p0, p1)
                lane = R.connector(lid, p0, None, w0, p1, None, w1, [lin], [lout], self.road_id, pts)
                lane.is_junction = False
                geo.features.append(lane)
                geo.link(lin, succ=lid)
                geo.link(lout, pred=lid)
        # lines continue through the curve
        for n_, (lat, kind, color, double) in enumerate(R.line_specs(sec)):
            # a0's edge frame (a→b) vs the travel frame (along -a0.direction)
            lat_t = -lat if a0.at_a else lat
            pts = R.curve_or_line(node, a0.direction, a1.direction, radius, lat_t)
            geo.features.append(m.RoadLine(f"{self.road_id}_line{n_}", points=R.xyz(pts), kind=kind,
                                           color=color, double=double))
        for n_, lat in enumerate((sec.median / 2, -sec.median / 2) if sec.median > 0 else ()):
            pts = R.curve_or_line(node, a0.direction, a1.direction, radius, lat)
            geo.features.append(m.RoadEdge(f"{self.road_id}_median{n_}", points=R.xyz(pts),
                                           kind="median"))
        center = R.curve_or_line(node, a0.direction, a1.direction, radius, 0.0)
        geo.area = LineString(center).buffer(sec.half_width, cap_style="flat", quad_segs=16)
        return geo


class Roundabout(Block):
    """A one-lane ring around a grass island; entry and exit connectors per arm."""
    ID = "roundabout"
    APPROACH_GAP = R.STOP_GAP

    @classmethod
    def claims(cls, rng, sections, sp):
        return (len(sections) >= 3 and rng.random() < sp["p_roundabout"]
                and max(s.half_width for s in sections) < 9.0)

    @classmethod
    def parameter_space(cls, sections, sp, glob):
        return {"island": Uniform(7.0, 11.0),
                "ring_width": Fixed(round(glob["lane_width"] + 1.5, 2)),
                "corner_radius": Uniform(*sp["corner"])}

    def cutbacks(self):
        c = self.params["island"] + self.params["ring_width"] + 8.0
        return [c for _ in self.arms]

    def build(self):
        node, arms, params = self.node, self.arms, self.params
        road_id = self.road_id
        geo = BlockGeometry([], None)
        feats = geo.features
        ri, rw = params["island"], params["ring_width"]
        r_lane = ri + rw / 2
        gaps = [(B.angle_of(arms[(k + 1) % len(arms)].direction) - B.angle_of(arms[k].direction))
                % (2 * np.pi) for k in range(len(arms))]
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
                for q, (lin, p0, w0) in enumerate(self._lanes(a, True)):
                    lid = f"{road_id}_in{arms.index(a)}_{q}"
                    feats.append(R.connector(lid, p0, -a.direction, w0, ring_pts[k], ring_tangent(ang),
                                             lane_w, [lin], [ring_ids[k]], road_id))
                    geo.link(lin, succ=lid)
                    preds[ring_ids[k]].append(lid)
            else:
                prev = ring_ids[(k - 1) % n]
                for q, (lout, p1, w1) in enumerate(self._lanes(a, False)):
                    lid = f"{road_id}_out{arms.index(a)}_{q}"
                    feats.append(R.connector(lid, ring_pts[k], ring_tangent(ang), lane_w, p1, a.direction,
                                             w1, [prev], [lout], road_id))
                    geo.link(lout, pred=lid)
                    succs[prev].append(lid)
        for k in range(n):
            a0, a1 = marks[k][0], marks[(k + 1) % n][0]
            sweep = (a1 - a0) % (2 * np.pi)
            pts = B.arc_points(node, r_lane, a0, sweep)
            pts[0], pts[-1] = ring_pts[k], ring_pts[(k + 1) % n]
            feats.append(m.LaneCenter(ring_ids[k], points=R.xyz(pts), widths=np.full(len(pts), lane_w),
                                      road_id=road_id, is_junction=True, predecessors=preds[ring_ids[k]],
                                      successors=succs[ring_ids[k]]))
        island = Point(node).buffer(ri, quad_segs=32)
        ring = Point(node).buffer(ri + rw, quad_segs=32)
        core = shapely.union_all(self._stubs() + [ring])
        rc = params["corner_radius"]
        geo.area = core.buffer(rc, quad_segs=12).buffer(-rc, quad_segs=12).union(core).difference(island)
        isl = R.polygons(island.buffer(-0.3))
        if isl:
            feats.append(m.VegetationZone(f"{road_id}_island", polygon=R.xyz(isl[0]), kind="grass"))
        feats.append(m.Tree(f"{road_id}_islandtree", position=np.array([node[0], node[1], 0.0]),
                            height_hint=7.0, crown_radius_hint=min(3.0, ri * 0.4)))
        geo.zones = [Point(node).buffer(arms[0].cut)]
        return geo


class Junction(Block):
    """A 4-way / T (or 2-way, for unequal roads) intersection with rounded curb corners;
    crosswalks, stop lines and stop signs on its approaches."""
    ID = "junction"
    APPROACH_GAP = R.STOP_GAP

    @classmethod
    def claims(cls, rng, sections, sp):
        return True

    @classmethod
    def parameter_space(cls, sections, sp, glob):
        many = len(sections) >= 3
        return {"corner_radius": Uniform(*sp["corner"]),
                "crosswalks": Chance(sp["p_crosswalk"], many),
                "stop_signs": Chance(sp["p_stop"], many)}

    def cutbacks(self):
        cuts = B.corner_cutbacks(self.node, [a.direction for a in self.arms],
                                 [a.section.half_width for a in self.arms], self.params["corner_radius"])
        return [min(c + 1.0, R.MAX_BLOCK_REACH - 6) for c in cuts]

    def build(self):
        arms = self.arms
        geo = BlockGeometry([], None)
        for ia, a_in in enumerate(arms):
            ins = self._lanes(a_in, True)
            for io, a_out in enumerate(arms):
                if io == ia:
                    continue
                outs = self._lanes(a_out, False)
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
                    lid = f"{self.road_id}_{ia}{io}_{k_in}{k_out}"
                    geo.features.append(R.connector(lid, p0, -a_in.direction, w0, p1, a_out.direction,
                                                    w1, [lin], [lout], self.road_id))
                    geo.link(lin, succ=lid)
                    geo.link(lout, pred=lid)
        hmax = max(a.section.half_width for a in arms)
        core = shapely.union_all(self._stubs() + [Point(self.node).buffer(hmax, quad_segs=16)])
        rc = self.params["corner_radius"]
        geo.area = core.buffer(rc, quad_segs=12).buffer(-rc, quad_segs=12).union(core)
        geo.zones = [Point(self.node).buffer(max(a.cut for a in arms) + R.STOP_GAP)]
        return geo

    def approach_features(self, e, at_a):
        feats = []
        sec = e.section
        s_edge = e.s0 if at_a else e.s1
        inward = 1.0 if at_a else -1.0   # along +d away from the node at the a end
        h = sec.half_width
        tag = "a" if at_a else "b"
        if self.params.get("crosswalks"):
            s1_, s2_ = s_edge + inward * 0.5, s_edge + inward * (0.5 + R.CROSSWALK_DEPTH)
            poly = np.stack([e.point(s1_, -h), e.point(s2_, -h), e.point(s2_, h), e.point(s1_, h)])
            if m.polygon_area(poly) < 0:
                poly = poly[::-1].copy()
            feats.append(m.Crosswalk(f"{e.key}_cross{tag}", polygon=R.xyz(poly)))
        s_stop = s_edge + inward * (R.STOP_GAP - 0.3)
        in_side = 1.0 if at_a else -1.0   # incoming lanes toward a travel b→a: left of a→b
        lo, hi = sec.median / 2, sec.median / 2 + sec.lanes * sec.lane_width
        pts = np.stack([e.point(s_stop, in_side * lo), e.point(s_stop, in_side * hi)])
        feats.append(m.StopLine(f"{e.key}_stop{tag}", points=R.xyz(pts)))
        if self.params.get("stop_signs"):
            incoming = [lid for lid, _, _ in R.end_lanes(e, at_a, True)]
            pos = e.point(s_stop, in_side * (h + 0.8))
            feats.append(m.StopSign(f"{e.key}_sign{tag}", position=R.xyz(pos[None])[0],
                                    lane_ids=incoming))
        return feats


# ================================================================= registry

# Asked in this order whether they claim a node (Junction claims everything: keep it last);
# a plugin's block type registers before "junction" (entry point group lsd3d_usd.layout_blocks,
# or register()).
BLOCKS = Registry("lsd3d_usd.layout_blocks", "layout block type", {
    cls.ID: f"lsd3d_usd.layout.blocktypes:{cls.__name__}"
    for cls in (NoBlock, DeadEnd, Curve, Roundabout, Junction)})


def register(cls: type[Block], before: str | None = "junction") -> type[Block]:
    """Add a block type (asked before ``before``; default: before the catch-all junction)."""
    if not cls.ID:
        raise InputError("a block type needs an ID")
    BLOCKS.register(cls.ID, cls, before=before)
    return cls


def choose(rng: np.random.Generator, sections: list[B.Section], sp: dict) -> type[Block]:
    """The first registered type that claims a node with these road sections."""
    for _, cls in BLOCKS.items():
        if cls.claims(rng, sections, sp):
            return cls
    raise AssertionError("no block type claims the node")   # Junction claims everything


def block_class(block_id: str) -> type[Block]:
    if block_id not in BLOCKS.names():
        raise ValueError(f"unknown block type {block_id!r} (known: {', '.join(BLOCKS.ordered())})")
    return BLOCKS.get(block_id)
