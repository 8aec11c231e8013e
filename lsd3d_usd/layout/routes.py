"""The one lane graph of a layout and its route API: traffic, ego tracks, rigs, datasets
and the closed-loop simulator all plan and follow routes here.

`LaneGraph` holds the drivable lanes (`Layout.drivable_lanes`, the one definition; with
``bike_lanes`` also the bike lanes, for cyclists), their successor / predecessor indices,
each lane's arc-length geometry (`LaneGeom`), the junction lanes that conflict with each
other and the crosswalks each lane crosses. A route is a list of lane ids, each a successor
of the one before; `Route` is a validated one with arc length along it (point, heading,
projection of a point onto it). `nearest_lane` finds the lane (and its frame) at a point.
"""
from __future__ import annotations

import bisect
import difflib
import math
from dataclasses import dataclass

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry.polyline import arc_table, nearest_point
from lsd3d_usd.layout.model import DRIVABLE_TYPES

ROUTE_SEARCH_BUDGET = 20_000   # lane expansions of the route search (large maps stay < 1 s)
CONFLICT_DISTANCE = 1.5        # m: junction lanes whose centre lines come this close conflict


class LaneGeom:
    """Arc-length parameterisation of one lane's centre line (direction of travel)."""

    def __init__(self, lane):
        pts = np.asarray(lane.points, np.float64)
        if lane.direction == "backward":
            pts = pts[::-1]
        self.points, self.cum = arc_table(pts)
        self.length = float(self.cum[-1])
        self.id = lane.id
        self.limit = float(lane.speed_limit_mps)
        self.is_junction = bool(lane.is_junction)
        self.bike = lane.lane_type == "bike"
        w = np.asarray(lane.widths, np.float64) if lane.widths is not None and len(lane.widths) else \
            np.full(len(lane.points), 3.5)
        self.width = float(np.min(w))

    def pose2d(self, s: float, offset: float = 0.0, half: float = 1.0) -> tuple[float, float, float]:
        """(x, y, yaw) at one arc length, ``offset`` m to the left: the scalar fast path of
        `point` / `heading` / `offset_point` (same values) for per-step queries."""
        if not hasattr(self, "_cum_list"):
            self._cum_list = self.cum.tolist()
            self._xy_list = self.points[:, :2].tolist()
        x, y = self._xy2(s)
        ax, ay = self._xy2(max(s - half, 0.0))
        bx, by = self._xy2(min(s + half, self.length))
        yaw = math.atan2(by - ay, bx - ax)
        if offset:
            x, y = x - math.sin(yaw) * offset, y + math.cos(yaw) * offset
        return x, y, yaw

    def _xy2(self, s: float) -> tuple[float, float]:
        cum, xy = self._cum_list, self._xy_list
        s = min(max(s, 0.0), self.length)
        j = min(max(bisect.bisect_right(cum, s) - 1, 0), len(cum) - 2)
        d = cum[j + 1] - cum[j]
        f = (s - cum[j]) / d if d > 0 else 0.0
        return xy[j][0] + f * (xy[j + 1][0] - xy[j][0]), xy[j][1] + f * (xy[j + 1][1] - xy[j][1])

    def offset_point(self, s, offset) -> np.ndarray:
        """The point ``offset`` m to the left of the centre line (negative: right) at s."""
        p = self.point(s)
        h = self.heading(s)
        off = np.asarray(offset, np.float64)
        return p + np.stack([-np.sin(h) * off, np.cos(h) * off, np.zeros_like(h * off)], axis=-1)

    def point(self, s) -> np.ndarray:
        s = np.clip(np.asarray(s, np.float64), 0.0, self.length)
        return np.stack([np.interp(s, self.cum, self.points[:, k]) for k in range(3)], axis=-1)

    def heading(self, s, half: float = 1.0) -> np.ndarray:
        """Yaw (radians) of the chord over s +- half (smooth through polyline vertices)."""
        s = np.asarray(s, np.float64)
        a = self.point(np.maximum(s - half, 0.0))
        b = self.point(np.minimum(s + half, self.length))
        d = b - a
        return np.arctan2(d[..., 1], d[..., 0])


@dataclass(frozen=True)
class LanePoint:
    """Where a point lies on the lane graph: lane index, arc length on it, signed lateral
    offset (m, + left of the direction of travel), distance to the centre line, the lane's
    heading there (radians) and the point's heading relative to it (wrapped to [-pi, pi],
    0 when no heading was given)."""
    lane: int
    s: float
    offset: float
    distance: float
    heading: float
    relative_heading: float


class LaneGraph:
    """Drivable lanes of a layout with successor indices, junction conflict sets and the
    crosswalks each lane crosses; with ``bike_lanes`` also the layout's bike lanes, for
    cyclists (a car never chooses one)."""

    def __init__(self, layout, conflict_distance: float = CONFLICT_DISTANCE, bike_lanes: bool = False):
        self.layout = layout
        drivable = {id(ln) for ln in layout.drivable_lanes()}
        lanes = [ln for ln in layout.lanes if id(ln) in drivable or (
            bike_lanes and ln.lane_type == "bike" and ln.speed_limit_mps > 0 and ln.length() > 1e-6)]
        self.lanes = lanes
        self.geoms = [LaneGeom(ln) for ln in lanes]
        self.ids = [g.id for g in self.geoms]
        self.index = {lid: i for i, lid in enumerate(self.ids)}
        self.succ = [[self.index[s] for s in ln.successors if s in self.index] for ln in lanes]
        self.pred = [[self.index[p] for p in ln.predecessors if p in self.index] for ln in lanes]
        self.length = np.array([g.length for g in self.geoms])
        self.limit = np.array([g.limit for g in self.geoms])
        self.junction = np.array([g.is_junction for g in self.geoms], bool)
        self.bike = np.array([g.bike for g in self.geoms], bool)
        self.width = np.array([g.width for g in self.geoms])
        self.conflicts = self._conflicts(conflict_distance)
        self.crossings: list[list] = [[] for _ in self.geoms]   # per lane: (crosswalk, s_in, s_out)
        self.crossings_of = None       # what the crossings were computed for (street's walkable)
        self.n_crosswalks = 0
        self._segments = None

    def __len__(self) -> int:
        return len(self.ids)

    # ---- crosswalks
    def set_crosswalks(self, polygons) -> None:
        """For every lane, the arc-length interval where the lane's width touches each
        crosswalk polygon (shapely): ``crossings[lane] = [(k, s_in, s_out), ...]``."""
        self.crossings = [[] for _ in self.geoms]
        self.n_crosswalks = 0
        if not hasattr(self, "_bounds"):
            self._bounds = [(g.points[:, :2].min(0), g.points[:, :2].max(0)) for g in self.geoms]
        for poly in polygons:
            self.add_crosswalk(poly)

    def add_crosswalk(self, poly, step: float = 0.25) -> int:
        """Add one crossing polygon (a crosswalk, or a mid-block crossing while it lasts);
        returns its index."""
        import shapely   # only traffic with pedestrians needs it
        k = self.n_crosswalks
        self.n_crosswalks += 1
        if not hasattr(self, "_bounds"):
            self._bounds = [(g.points[:, :2].min(0), g.points[:, :2].max(0)) for g in self.geoms]
        x0, y0, x1, y1 = poly.bounds
        for i, g in enumerate(self.geoms):
            pad = self.width[i] / 2
            lo, hi = self._bounds[i]
            if lo[0] > x1 + pad or hi[0] < x0 - pad or lo[1] > y1 + pad or hi[1] < y0 - pad:
                continue
            s = np.linspace(0.0, g.length, max(2, int(np.ceil(g.length / step)) + 1))
            p = g.point(s)
            inside = shapely.dwithin(poly, shapely.points(p[:, 0], p[:, 1]), pad)
            if inside.any():
                idx = np.flatnonzero(inside)
                self.crossings[i].append((k, float(s[max(idx[0] - 1, 0)]),
                                          float(s[min(idx[-1] + 1, len(s) - 1)])))
        return k

    def truncate_crosswalks(self, n: int) -> None:
        """Forget the crossing polygons from index ``n`` on (a run's mid-block crossings)."""
        if self.n_crosswalks > n:
            self.crossings = [[c for c in row if c[0] < n] for row in self.crossings]
            self.n_crosswalks = n

    def _conflicts(self, dist: float) -> list[set]:
        """For each junction lane: the other junction lanes whose centre lines come within
        ``dist`` (crossing, merging or diverging paths)."""
        out = [set() for _ in self.geoms]
        J = np.flatnonzero(self.junction)
        if len(J) < 2:
            return out
        samples = {}
        for j in J:
            g = self.geoms[j]
            n = max(2, int(np.ceil(g.length / 0.5)) + 1)
            samples[j] = g.point(np.linspace(0.0, g.length, n))[:, :2]
        lo = {j: samples[j].min(0) - dist for j in J}
        hi = {j: samples[j].max(0) + dist for j in J}
        for a_i, a in enumerate(J):
            for b in J[a_i + 1:]:
                if np.any(lo[a] > hi[b]) or np.any(lo[b] > hi[a]):
                    continue
                d = np.linalg.norm(samples[a][:, None, :] - samples[b][None, :, :], axis=2)
                if d.min() < dist:
                    out[a].add(int(b))
                    out[b].add(int(a))
        return out

    # ---- routes
    def route_indices(self, lane_ids) -> list[int]:
        """Validate a route: known drivable lanes, each the successor of the one before."""
        idx = []
        lane_ids = list(lane_ids)
        for k, lid in enumerate(lane_ids):
            if lid not in self.index or self.bike[self.index[lid]]:
                raise InputError(f"route: {route_hint(self.layout, lid)}")
            i = self.index[lid]
            if idx and i not in self.succ[idx[-1]]:
                raise InputError(f"route: lane {lid!r} does not follow lane {lane_ids[k - 1]!r} "
                                 f"(successors: {', '.join(self.ids[j] for j in self.succ[idx[-1]]) or 'none'})")
            idx.append(i)
        if not idx:
            raise InputError("route: no lanes given")
        return idx

    def route(self, lane_ids) -> "Route":
        """A validated `Route` along ``lane_ids`` (a list, or a comma-separated string)."""
        ids = parse_route(lane_ids) if isinstance(lane_ids, str) else list(lane_ids)
        return Route(self, self.route_indices(ids))

    def entries(self) -> list[int]:
        """Lane indices where traffic enters the graph (no drivable predecessor; every lane
        when the graph has none), sorted by id; bike lanes left out."""
        cars = [i for i in range(len(self.ids)) if not self.bike[i]]
        starts = [i for i in cars if not any(not self.bike[p] for p in self.pred[i])]
        return sorted(starts or cars, key=lambda i: self.ids[i])

    def car_successors(self, i: int) -> list[int]:
        return [j for j in self.succ[i] if not self.bike[j]]

    # ---- where a point is
    def _segment_table(self):
        if self._segments is None:
            a, b, lane, s0 = [], [], [], []
            for i, g in enumerate(self.geoms):
                if len(g.points) < 2:
                    continue
                a.append(g.points[:-1, :2])
                b.append(g.points[1:, :2])
                lane.append(np.full(len(g.points) - 1, i))
                s0.append(g.cum[:-1])
            self._segments = (np.concatenate(a), np.concatenate(b), np.concatenate(lane),
                              np.concatenate(s0)) if a else None
        return self._segments

    def nearest_lane(self, xy, heading: float | None = None, lanes=None,
                     cars_only: bool = True) -> LanePoint | None:
        """The lane whose centre line is nearest to ``xy`` (None without lanes). With
        ``heading`` (radians), lanes within 90 degrees of it win over nearer lanes against it
        when they lie within their half width plus 1 m (a car on the right lane of a road is
        not placed on the oncoming one). ``lanes``: restrict to these indices."""
        tab = self._segment_table()
        if tab is None:
            return None
        A, B, L, S0 = tab
        p = np.asarray(xy, np.float64)[:2]
        keep = np.ones(len(L), bool)
        if cars_only:
            keep &= ~self.bike[L]
        if lanes is not None:
            keep &= np.isin(L, np.asarray(list(lanes), np.int64))
        if not keep.any():
            return None
        # segments whose box lies within reach first (a large map has many); all when none
        reach = float(self.width.max()) + 5.0
        near = keep & (np.minimum(A[:, 0], B[:, 0]) - reach <= p[0]) \
            & (np.maximum(A[:, 0], B[:, 0]) + reach >= p[0]) \
            & (np.minimum(A[:, 1], B[:, 1]) - reach <= p[1]) \
            & (np.maximum(A[:, 1], B[:, 1]) + reach >= p[1])
        for sel in ((near, keep) if near.any() else (keep,)):
            A1, B1, L1, S1 = A[sel], B[sel], L[sel], S0[sel]
            d = B1 - A1
            dd = np.einsum("ij,ij->i", d, d)
            f = np.clip(np.einsum("ij,ij->i", p - A1, d) / np.maximum(dd, 1e-18), 0.0, 1.0)
            q = A1 + f[:, None] * d
            dist = np.hypot(p[0] - q[:, 0], p[1] - q[:, 1])
            if dist.min() <= reach:      # exact: every segment left out is farther than reach
                break
        A, B, L, S0 = A1, B1, L1, S1
        seg_yaw = np.arctan2(d[:, 1], d[:, 0])
        if heading is not None:
            rel = np.angle(np.exp(1j * (heading - seg_yaw)))
            near = dist <= self.width[L] / 2 + 1.0
            aligned = near & (np.abs(rel) <= np.pi / 2)
            cand = np.flatnonzero(aligned) if aligned.any() else np.arange(len(L))
        else:
            cand = np.arange(len(L))
        k = int(cand[np.argmin(dist[cand])])
        i = int(L[k])
        s = float(S0[k] + f[k] * math.sqrt(dd[k]))
        cross = d[k, 0] * (p[1] - A[k, 1]) - d[k, 1] * (p[0] - A[k, 0])
        off = math.copysign(float(dist[k]), cross) if dist[k] > 0 else 0.0
        yaw = float(self.geoms[i].heading(s))
        rel = float(np.angle(np.exp(1j * (heading - yaw)))) if heading is not None else 0.0
        return LanePoint(i, s, off, float(dist[k]), yaw, rel)


class Route:
    """A validated route on a `LaneGraph`: lane indices ``idx`` with arc length ``d`` along
    the whole route (0 at the start of the first lane)."""

    def __init__(self, graph: LaneGraph, idx: list[int]):
        self.graph = graph
        self.idx = list(idx)
        self.ids = [graph.ids[i] for i in self.idx]
        self.starts = np.concatenate([[0.0], np.cumsum(graph.length[self.idx])])
        self.length = float(self.starts[-1])
        self._poly = None

    def locate(self, d) -> tuple[int, float]:
        """(position in the route, arc length on that lane) at route distance ``d`` (clipped)."""
        d = min(max(float(d), 0.0), self.length)
        j = min(int(np.searchsorted(self.starts, d, side="right")) - 1, len(self.idx) - 1)
        return j, d - float(self.starts[j])

    def point(self, d) -> np.ndarray:
        j, s = self.locate(d)
        return self.graph.geoms[self.idx[j]].point(s)

    def heading(self, d) -> float:
        j, s = self.locate(d)
        return float(self.graph.geoms[self.idx[j]].heading(s))

    def pose2d(self, d, offset: float = 0.0) -> tuple[float, float, float]:
        j, s = self.locate(d)
        return self.graph.geoms[self.idx[j]].pose2d(s, offset)

    def polyline(self) -> tuple[np.ndarray, np.ndarray]:
        """(points (n, 3), route distance of each point): the lanes' centre lines joined
        (a lane's first point dropped where it repeats the one before)."""
        if self._poly is None:
            pts, cum = [], []
            for j, i in enumerate(self.idx):
                g = self.graph.geoms[i]
                p, c = g.points, g.cum + self.starts[j]
                if pts and np.linalg.norm(p[0, :2] - pts[-1][-1, :2]) < 1e-6:
                    p, c = p[1:], c[1:]
                pts.append(p)
                cum.append(c)
            self._poly = (np.concatenate(pts), np.concatenate(cum))
        return self._poly

    def project(self, xy, near: float | None = None, window: float = 30.0) -> tuple[float, float]:
        """(route distance, signed lateral offset, + left) of the point of the route nearest
        to ``xy``; with ``near`` only within ``window`` m of that distance (a route that
        passes the same place twice stays on the pass being driven)."""
        pts, cum = self.polyline()
        if len(pts) < 2:
            return 0.0, 0.0
        lo, hi = 0, len(pts)
        if near is not None:
            keep = np.flatnonzero((cum[1:] >= near - window) & (cum[:-1] <= near + window))
            if len(keep):          # cum increases: the kept segments are one run
                lo, hi = int(keep[0]), int(keep[-1]) + 2
        p = np.asarray(xy, np.float64)[:2]
        dist, s, c, u = nearest_point(pts[lo:hi], p)
        cross = u[0] * (p[1] - c[1]) - u[1] * (p[0] - c[0])
        return float(cum[lo] + s), math.copysign(dist, cross)

    def points(self, d) -> np.ndarray:
        """(n, 3) points at route distances ``d`` (clipped to the route): `point` for many."""
        pts, cum = self.polyline()
        d = np.clip(np.asarray(d, np.float64), 0.0, self.length)
        return np.stack([np.interp(d, cum, pts[:, k]) for k in range(3)], axis=-1)

    def ahead(self, d: float, n: int, spacing: float) -> np.ndarray:
        """(n, 3) points of the route from distance ``d`` on, ``spacing`` m apart (held at
        the route's end)."""
        return self.points(d + spacing * np.arange(n))


def parse_route(text) -> list[str]:
    """Lane ids of a route given as "a,b,c" (blanks ignored) or as a list."""
    if isinstance(text, str):
        return [r.strip() for r in text.split(",") if r.strip()]
    return [str(r).strip() for r in text if str(r).strip()]


def longest_route(layout_or_graph, max_length: float | None = None,
                  budget: int = ROUTE_SEARCH_BUDGET) -> tuple[list[str], float]:
    """(lane ids, length in m) of the longest drivable successor path that repeats no lane,
    searched depth-first from the lanes where traffic enters the graph (no drivable
    predecessor; every lane when the graph has none), ids in sorted order, for at most
    ``budget`` lane expansions. With ``max_length`` the first path reaching it is returned
    (a clip needs no more). Deterministic; ([], 0.0) without drivable lanes."""
    g = layout_or_graph if isinstance(layout_or_graph, LaneGraph) else LaneGraph(layout_or_graph)
    if not any(~g.bike):
        return [], 0.0
    best: tuple[list[str], float] = ([], -1.0)
    expansions = 0
    for start in g.entries():
        stack = [(start, [g.ids[start]], float(g.length[start]))]
        while stack:
            lid, path_ids, length = stack.pop()
            expansions += 1
            if length > best[1]:
                best = (path_ids, length)
                if max_length is not None and length >= max_length:
                    return best
            if expansions >= budget:
                return best
            on_path = set(path_ids)
            # reversed: the smallest successor id is expanded first
            for nxt in sorted(g.car_successors(lid), key=lambda j: g.ids[j], reverse=True):
                if g.ids[nxt] not in on_path:
                    stack.append((nxt, path_ids + [g.ids[nxt]], length + float(g.length[nxt])))
    return best


def default_route(layout, seconds: float, speed: float | None = None) -> tuple[list[str], float]:
    """(lane ids, length) driven when no route is given: the longest drivable successor
    path, cut once it covers ``seconds`` at ``speed`` (default: the fastest lane limit,
    which IDM does not exceed). Empty without drivable lanes."""
    lanes = layout.drivable_lanes()
    if not lanes:
        return [], 0.0
    v = speed if speed is not None else max(ln.speed_limit_mps for ln in lanes)
    return longest_route(layout, max_length=float(seconds) * float(v))


def random_routes(layout_or_graph, n: int, length: float, seed: int) -> list[list[str]]:
    """``n`` distinct routes: seeded random successor walks from the lanes where traffic
    enters the graph, each as long as ``length`` (or until no successor is left).
    InputError when the layout has no drivable lanes or fewer distinct routes."""
    g = layout_or_graph if isinstance(layout_or_graph, LaneGraph) else LaneGraph(layout_or_graph)
    cars = [i for i in range(len(g.ids)) if not g.bike[i]]
    if not cars:
        raise InputError("the layout has no drivable lanes")
    starts = g.entries()
    rng = np.random.default_rng([int(seed), 0x5EED])
    got, seen = [], set()
    for _ in range(50 * n):
        i = starts[rng.integers(len(starts))]
        path, dist = [i], float(g.length[i])
        while dist < length:
            nxt = sorted((j for j in g.car_successors(path[-1]) if j not in path),
                         key=lambda j: g.ids[j])
            if not nxt:
                break
            path.append(nxt[rng.integers(len(nxt))])
            dist += float(g.length[path[-1]])
        ids = tuple(g.ids[j] for j in path)
        if ids not in seen:
            seen.add(ids)
            got.append(list(ids))
            if len(got) == n:
                return got
    raise InputError(f"--routes {n}: the layout has only {len(got)} distinct routes of this kind")


def constant_speed_route(layout, lane_ids, speed: float, times) -> tuple[np.ndarray, np.ndarray]:
    """(positions (n,3), yaw (n,)) at ``times`` driving ``lane_ids`` at ``speed`` from the
    start of the first lane; the car stops at the end of the last lane."""
    route = LaneGraph(layout).route(list(lane_ids))
    if not speed > 0:
        raise InputError(f"route: speed must be > 0, got {speed}")
    d = np.clip(np.asarray(times, np.float64) * speed, 0.0, route.length)
    pos, yaw = np.zeros((len(d), 3)), np.zeros(len(d))
    for k, dk in enumerate(d):
        pos[k] = route.point(dk)
        yaw[k] = route.heading(dk)
    return pos, np.unwrap(yaw)


def similar_ids(layout, lane_id: str, k: int = 6) -> tuple[str, list[str]]:
    """What to tell a user who named ``lane_id`` in a route: (why it is not drivable, up to
    ``k`` valid drivable ids near it — spatially for a lane of another type, by spelling for
    an unknown id, else the first ids)."""
    rows = layout.drivable_lanes()
    ids = [ln.id for ln in rows]
    other = next((ln for ln in layout.lanes if ln.id == lane_id), None)
    if other is not None:
        why = (f"is a {other.lane_type} lane (a car drives lanes of type "
               f"{', '.join(DRIVABLE_TYPES)})" if other.lane_type not in DRIVABLE_TYPES
               else "has no length or a speed limit of 0")
        if rows:
            here = np.asarray(other.points)[:, :2]
            d = [float(np.min(np.linalg.norm(np.asarray(ln.points)[:, None, :2] - here[None], axis=2)))
                 for ln in rows]
            return why, [ids[i] for i in np.argsort(d, kind="stable")[:k]]
        return why, []
    close = difflib.get_close_matches(lane_id, ids, n=k, cutoff=0.5)
    return "is not a lane of the layout", close or sorted(ids)[:k]


def route_hint(layout, lane_id: str) -> str:
    """One clause for an error about ``lane_id``: why, and valid ids to try."""
    why, near = similar_ids(layout, lane_id)
    nearby = f"; drivable lanes nearby: {', '.join(near)}" if near else "; the layout has no drivable lanes"
    return f"lane {lane_id!r} {why}{nearby} (all: `lsd3d-usd layout lanes LAYOUT_OR_SCENE`)"
