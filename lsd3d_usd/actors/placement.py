"""Parked actors: free parking spots first, then slots along parking lanes (the curb side),
never overlapping each other or the vehicles the proxy already stands on occupied spots.

Footprints are oriented rectangles (shapely); every choice comes from one seeded generator.
Roads without a parking lane get no curbside actors: a car parked on a driving lane would
block the moving traffic.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from shapely import STRtree
from shapely.geometry import Polygon

from lsd3d_usd.layout.routes import LaneGeom

KIND_WEIGHTS = {"car": 0.72, "van": 0.18, "truck": 0.05, "bus": 0.05}
CLEARANCE = 0.3          # m kept free around every parked footprint


@dataclass
class Placement:
    """A static actor: kind, ground position (x, y, z) and yaw (radians), the slot it fills."""
    kind: str
    position: np.ndarray
    yaw: float
    slot: str


def footprint(center, yaw: float, length: float, width: float, pad: float = 0.0) -> Polygon:
    c, s = np.cos(yaw), np.sin(yaw)
    u = np.array([c, s]) * (length / 2 + pad)
    v = np.array([-s, c]) * (width / 2 + pad)
    p = np.asarray(center, np.float64)[:2]
    return Polygon([p - u - v, p + u - v, p + u + v, p - u + v])


def crosswalk_footprints(layout) -> list[Polygon]:
    """The layout's crosswalks as polygons (valid ones), to keep parked actors off them."""
    out = []
    for cw in layout.crosswalks:
        p = Polygon(np.asarray(cw.polygon, np.float64)[:, :2])
        p = p if p.is_valid else p.buffer(0)
        if not p.is_empty:
            out.append(p)
    return out


def parking_slots(layout, pitch: float = 6.0):
    """(id, centre, heading, max length, max width) of every candidate slot."""
    out = []
    for sp in layout.parking_spots:
        if not sp.occupied:
            out.append((sp.id, sp.center, sp.heading, sp.length, sp.width))
    for ln in layout.lanes:
        if ln.lane_type != "parking":
            continue
        g = LaneGeom(ln)
        w = float(np.min(ln.widths)) if len(ln.widths) else 2.3
        for k, s in enumerate(np.arange(pitch / 2, g.length - pitch / 2 + 1e-9, pitch)):
            out.append((f"{ln.id}@{k}", g.point(s), float(g.heading(s)), pitch, max(w, 2.0)))
    return out


def parked_placements(layout, n: int, seed: int, dims: dict, weights: dict | None = None,
                      avoid: list[Polygon] | None = None) -> list[Placement]:
    """Up to ``n`` parked actors. ``dims``: kind -> (length, width, height) of the available
    assets; ``avoid``: extra footprints to keep clear of. Fewer than ``n`` when slots run out."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x9A4C]))
    weights = {k: w for k, w in (weights or KIND_WEIGHTS).items() if k in dims} or \
        {k: 1.0 for k in dims}
    kinds = sorted(weights)
    p = np.array([weights[k] for k in kinds], np.float64)
    p /= p.sum()
    taken: list[Polygon] = [footprint(sp.center, sp.heading, min(sp.length, 5.0), min(sp.width, 2.0))
                            for sp in layout.parking_spots if sp.occupied]
    taken += list(avoid or [])
    slots = parking_slots(layout)
    order = rng.permutation(len(slots))
    out: list[Placement] = []
    tree = STRtree(taken) if taken else None
    chosen: list[Polygon] = []
    for i in order:
        if len(out) >= n:
            break
        sid, c, h, slot_len, slot_w = slots[i]
        kind = kinds[int(rng.choice(len(kinds), p=p))]
        L, W = float(dims[kind][0]), float(dims[kind][1])
        if L > slot_len + 0.2 or W > slot_w + 0.3:   # fall back to the smallest kind
            kind = min(dims, key=lambda k: dims[k][0])
            L, W = float(dims[kind][0]), float(dims[kind][1])
            if L > slot_len + 0.2:
                continue
        yaw = float(h) + (np.pi if rng.random() < 0.5 and sid.find("@") < 0 else 0.0)
        fp = footprint(c, yaw, L, W, CLEARANCE / 2)
        if tree is not None and any(taken[j].intersects(fp) for j in tree.query(fp)):
            continue
        if any(o.intersects(fp) for o in chosen):
            continue
        chosen.append(fp)
        out.append(Placement(kind, np.asarray(c, np.float64).copy(), yaw, sid))
    return out
