"""OSM node heights (``ele``) → z of an OSM layout.

The layout is built in the plane (offsets, buffers and unions are 2D); its z is set at the
end. Like Lanelet2 (``lanelet2_import._ele_as_z``), ``ele`` is the map's own height in metres:
the origin lies at height 0 on the ellipsoid's surface and z = ``ele``.

- A node's height: its ``ele`` (a number, optionally followed by "m"); a node without one
  gets the arc-length interpolation between the nearest nodes with ``ele`` on its ways (held
  past a way's last one; averaged over the ways it is on); a way with no such node then
  takes its heights from the ways it meets; what is left (no way leads to a height) takes
  the height of the nearest node with ``ele``. Other values ("12 ft", "abc", NaN, 1e30) are ignored, with one warning.
- A way is a 3D polyline through its nodes. A lane takes z along its own way (its point
  projected onto the way's centre line), a junction connector runs linearly between the
  lanes it joins, the road surface and what stands on it take the nearest highway's z,
  other features (buildings, vegetation, barriers, trees, poles) the nearest way's. A
  building's footprint is flat at its lowest ground point so it does not float.

A map with no usable ``ele`` is not touched: its z stays exactly 0.
"""
from __future__ import annotations

import math
import re

import numpy as np
import shapely
from scipy.spatial import cKDTree

from lsd3d_usd.errors import excerpt

ELE_LIMIT_M = 10_000.0    # beyond any place on Earth (Everest 8849 m, the deepest mine -4 km)
_ELE = re.compile(r"\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(?:m)?\s*$")


def parse_ele(text) -> float | None:
    """Metres from an OSM ``ele`` value, None when it is not a height."""
    mt = _ELE.match(str(text))
    if not mt:
        return None
    v = float(mt.group(1))
    return v if math.isfinite(v) and abs(v) <= ELE_LIMIT_M else None


def node_heights(path, raw: dict, ways, xy_of: dict, warn) -> dict:
    """{node id: z} for every node in ``xy_of``, or {} when no node has a usable ``ele``.
    ``raw``: {node id: ele text}; ``warn(msg)`` reports the ignored values once."""
    z, bad = {}, []
    for nid, text in raw.items():
        v = parse_ele(text)
        if v is None:
            bad.append((nid, text))
        else:
            z[nid] = v
    if bad:
        nid, text = bad[0]
        more = f" ({len(bad)} nodes, e.g. this one)" if len(bad) > 1 else ""
        warn(f"{path}: node {nid}: ele {excerpt(str(text))!s} is not a height in metres{more}; "
             "ignored, the height is interpolated from the nodes around it")
    if not z:
        return {}
    out = dict(z)
    todo = [[r for r in refs if r in xy_of] for _, _, refs in ways]
    while todo:   # a way without ele takes its heights from the ways it meets, and so on
        acc, wait = {}, []
        for refs in todo:
            known = [i for i, r in enumerate(refs) if r in out]
            if not known:
                wait.append(refs)
                continue
            if len(known) == len(refs):
                continue
            p = np.array([xy_of[r] for r in refs])
            s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
            zi = np.interp(s, s[known], [out[refs[i]] for i in known])   # held beyond the ends
            for i, r in enumerate(refs):
                if r not in out:
                    a = acc.setdefault(r, [0.0, 0])
                    a[0] += zi[i]
                    a[1] += 1
        if not acc:
            break
        out.update({r: a[0] / a[1] for r, a in acc.items()})
        todo = wait
    rest = [n for n in xy_of if n not in out]
    if rest:   # on no way with a height: the nearest node that has one
        ids = list(z)
        _, k = cKDTree(np.array([xy_of[n] for n in ids])).query(np.array([xy_of[n] for n in rest]))
        out.update({n: z[ids[j]] for n, j in zip(rest, np.atleast_1d(k))})
    return out


class _Lines:
    """Ways as 2D lines with z along their arc length; nearest-way queries."""

    def __init__(self, ways, xy_of, zmap):
        self.by_id, geoms, self.ids = {}, [], []
        for wid, _, refs in ways:
            if wid in self.by_id or any(r not in xy_of for r in refs):
                continue
            p = np.array([xy_of[r] for r in refs])
            keep = np.ones(len(p), bool)
            keep[1:] = np.hypot(*np.diff(p, axis=0).T) > 1e-9
            p, zs = p[keep], np.array([zmap[r] for r in refs])[keep]
            if len(p) < 2:
                continue
            line = shapely.LineString(p)
            s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
            self.by_id[wid] = (line, s, zs)
            geoms.append(line)
            self.ids.append(wid)
        self.tree = shapely.STRtree(geoms) if geoms else None

    def along(self, wid, xy: np.ndarray) -> np.ndarray:
        line, s, zs = self.by_id[wid]
        return np.interp(shapely.line_locate_point(line, shapely.points(xy)), s, zs)

    def nearest(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, float).reshape(-1, 2)
        z = np.zeros(len(xy))
        if self.tree is None or not len(xy):
            return z
        src, hit = self.tree.query_nearest(shapely.points(xy), all_matches=False)
        for j in np.unique(hit):
            sel = src[hit == j]
            z[sel] = self.along(self.ids[j], xy[sel])
        return z


def apply_heights(layout, zmap: dict, roads, ways, xy_of) -> None:
    """Set the z of every feature of ``layout`` (built flat) from the node heights ``zmap``.
    ``roads``: the highway ways the lanes were built from (after outlier repair)."""
    if not zmap:
        return
    road = _Lines(roads, xy_of, zmap)
    road_ids = {wid for wid, _, _ in roads}
    every = _Lines(list(roads) + [w for w in ways if w[0] not in road_ids], xy_of, zmap)
    if road.tree is None:
        road = every

    def drape(a, lines):
        if a is not None and len(a):
            a[..., 2] = lines.nearest(a[..., :2]).reshape(a.shape[:-1])

    joins = []
    for ln in layout.lanes:
        wid = _way_of(ln.road_id)
        if ln.is_junction:
            joins.append(ln)
        elif wid in road.by_id:
            ln.points[:, 2] = road.along(wid, ln.points[:, :2])
        else:
            drape(ln.points, road)
    by_id = {ln.id: ln for ln in layout.lanes}
    for ln in joins:   # from the end of the lane it leaves to the start of the one it enters
        a, b = ln.predecessors[:1], ln.successors[:1]
        if not (a and b and a[0] in by_id and b[0] in by_id):
            drape(ln.points, road)
            continue
        z0, z1 = by_id[a[0]].points[-1, 2], by_id[b[0]].points[0, 2]
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ln.points[:, :2], axis=0).T))])
        ln.points[:, 2] = z0 + (z1 - z0) * (s / s[-1] if s[-1] > 0 else 0.0)
    for f in (*layout.road_lines, *layout.road_edges, *layout.stop_lines):
        drape(f.points, road)
    for f in (*layout.crosswalks, *layout.sidewalks, *layout.road_areas):
        drape(f.polygon, road)
    for f in layout.stop_signs + layout.traffic_lights + layout.traffic_signs:
        f.position[2] = road.nearest(f.position[None, :2])[0]
    for f in (*layout.trees, *layout.poles):
        f.position[2] = every.nearest(f.position[None, :2])[0]
    for f in layout.parking_spots:
        f.center[2] = every.nearest(f.center[None, :2])[0]
    for f in (*layout.hedges, *layout.barriers):
        drape(f.points, every)
    for f in layout.vegetation_zones:
        drape(f.polygon, every)
    for f in layout.buildings:
        f.footprint[:, 2] = every.nearest(f.footprint[:, :2]).min()


def _way_of(road_id: str):
    mt = re.fullmatch(r"w(-?\d+)", road_id or "")
    return int(mt.group(1)) if mt else None
