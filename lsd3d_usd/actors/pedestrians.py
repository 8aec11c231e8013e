"""Seeded pedestrians: walking the sidewalk tracks, waiting and crossing at crosswalks,
standing at corners. Arrays in, arrays out; one step at a time, driven by `street`.

A walker follows its track (`sidewalks.Track`) at its own desired speed. Where its track
passes the leave point of a crosswalk it crosses with probability ``cross_probability``:
it stops there, waits ``wait`` seconds, and then until the traffic model says the
crosswalk is clear (no vehicle over it, every vehicle heading across able to stop before
it: `traffic.Simulation.crosswalk_clear`). From then on the crosswalk counts as occupied
(vehicles stop before it) until the walker has stepped off its far end; it walks to the
crosswalk's near end, along its axis on the right-hand half, to the far end and on to the
other track. Standing pedestrians keep their spot (near corners first).

Every move is checked against the boxes of every other actor at that step (vehicles and
cyclists as they stand, pedestrians as already moved): a move that would overlap one is
shortened or not made, so no two boxes overlap at any step when none did at the start.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field

import numpy as np
import shapely

WALK, WAIT, CROSS, STAND = "walk", "wait", "cross", "stand"


@dataclass(frozen=True)
class WalkParams:
    speed_adult: tuple = (1.1, 1.6)      # m/s desired walking speed, drawn per adult
    speed_child: tuple = (0.8, 1.3)      # m/s, per child
    cross_probability: float = 0.6       # at each crosswalk a walker passes
    wait: tuple = (0.5, 3.0)             # s waited at the kerb before looking for a gap
    midblock_rate: float = 0.01          # per second walked: cross straight over the road here
    start_at_crosswalk: float = 0.35     # share of walkers that start waiting at a crosswalk
    stand_share: float = 0.2             # share of pedestrians standing (at corners)
    clearance: float = 0.05              # m kept between boxes by the move check
    track_offset: float = 0.6            # m from the sidewalk edge (walking tracks)
    stand_offset: float = 1.5            # m from the sidewalk edge (standing spots)


PASS_AFTER = 2.0     # s a walker stands blocked before it steps aside ...
ASIDE_MAX = 1.2      # ... by at most this many metres


def _as_lists(others):
    """Vehicle boxes (centres, yaws, halves) as Python lists, and the tuple they came from."""
    oc, oy, oh = others
    return (np.asarray(oc, np.float64).reshape(-1, 2).tolist(), np.asarray(oy, np.float64).tolist(),
            np.asarray(oh, np.float64).reshape(-1, 2).tolist(), others)


def _overlap(box, cx, cy, yaw, half) -> bool:
    """`obb_overlap` of one box (x, y, cos, sin, half along, half across) and another, in
    scalars (the same separating-axis test; touching counts as apart)."""
    x, y, c1, s1, a1, b1 = box
    c2, s2 = math.cos(yaw), math.sin(yaw)
    a2, b2 = half
    dx, dy = cx - x, cy - y
    for nx, ny in ((c1, s1), (-s1, c1), (c2, s2), (-s2, c2)):
        r1 = a1 * abs(c1 * nx + s1 * ny) + b1 * abs(-s1 * nx + c1 * ny)
        r2 = a2 * abs(c2 * nx + s2 * ny) + b2 * abs(-s2 * nx + c2 * ny)
        if abs(dx * nx + dy * ny) >= r1 + r2:
            return False
    return True


def obb_overlap(c1, yaw1, half1, c2, yaw2, half2) -> np.ndarray:
    """Do oriented rectangles overlap (separating axis test)? Centres (..., 2), yaws (...),
    half extents (..., 2) (along, across); arrays broadcast. Touching counts as apart."""
    c1, c2 = np.asarray(c1, np.float64), np.asarray(c2, np.float64)
    h1, h2 = np.asarray(half1, np.float64), np.asarray(half2, np.float64)
    y1, y2 = np.asarray(yaw1, np.float64), np.asarray(yaw2, np.float64)
    u1 = np.stack([np.cos(y1), np.sin(y1)], -1)
    v1 = np.stack([-np.sin(y1), np.cos(y1)], -1)
    u2 = np.stack([np.cos(y2), np.sin(y2)], -1)
    v2 = np.stack([-np.sin(y2), np.cos(y2)], -1)
    d = c2 - c1
    sep = np.zeros(np.broadcast_shapes(d.shape[:-1], u1.shape[:-1], u2.shape[:-1]), bool)
    for n in (u1, v1, u2, v2):
        r1 = h1[..., 0] * np.abs((u1 * n).sum(-1)) + h1[..., 1] * np.abs((v1 * n).sum(-1))
        r2 = h2[..., 0] * np.abs((u2 * n).sum(-1)) + h2[..., 1] * np.abs((v2 * n).sum(-1))
        sep |= np.abs((d * n).sum(-1)) >= r1 + r2
    return ~sep


@dataclass
class Walker:
    kind: str
    length: float
    width: float
    v_des: float
    state: str
    track: int = -1
    s: float = 0.0
    xy: np.ndarray = field(default_factory=lambda: np.zeros(2))
    yaw: float = 0.0
    v: float = 0.0
    walked: float = 0.0               # distance covered (drives the gait)
    wait_left: float = 0.0
    crosswalk: int = -1               # the crosswalk it waits at / is on
    forward: bool = True              # crossing from end a to end b
    path: np.ndarray | None = None    # (4, 2) leave point, near end, far end, join point
    cum: np.ndarray | None = None
    u: float = 0.0
    release_u: float = 0.0            # arc length on the path past which the crosswalk is free
    join: tuple = (-1, 0.0)
    last_crossed: int = -1
    occupying: bool = False
    midblock: tuple | None = None     # (far point, far track, its arc length) of a mid-block crossing
    blocked: float = 0.0              # seconds it has stood wanting to move
    aside: float = 0.0                # metres it has stepped aside to let someone pass
    aside_dir: float = 0.0            # the side it steps to (+1 left, -1 right), once chosen


class Pedestrians:
    """The walkers of a run on a `sidewalks.Walkable`; `step(dt, others)` moves them."""

    def __init__(self, walkable, rng: np.random.Generator, params: WalkParams = WalkParams(),
                 add_crossing=None):
        """``add_crossing(polygon) -> index``: registers a mid-block crossing corridor with
        the traffic (None: no mid-block crossings)."""
        self.w = walkable
        self.rng = rng
        self.p = params
        self.add_crossing = add_crossing
        self.polygons = [c.polygon for c in walkable.crosswalks]   # + mid-block corridors
        self.people: list[Walker] = []
        self._boxes = ([], [], [])        # everyone's box during a step (`step`)
        self._vehicles = None
        # leave points per track: (s, crosswalk index, forward)
        self.leave = [[] for _ in walkable.tracks]
        for k, c in enumerate(walkable.crosswalks):
            self.leave[c.track_a].append((c.s_a, k, True))
            self.leave[c.track_b].append((c.s_b, k, False))

    # ---- boxes
    def half(self, p: Walker) -> np.ndarray:
        return np.array([p.length / 2 + self.p.clearance / 2, p.width / 2 + self.p.clearance / 2])

    def _free(self, i: int, xy, yaw, others) -> bool:
        """Would walker i at (xy, yaw) stay clear of every other box? ``others``: (centres
        (n, 2), yaws (n,), halves (n, 2)) of the vehicles. Scalar code: a step asks this
        for a handful of nearby boxes, where numpy's per-call cost dominated."""
        me = self.people[i]
        h = self.half(me)
        x, y, yw = float(xy[0]), float(xy[1]), float(yaw)
        box = (x, y, math.cos(yw), math.sin(yw), float(h[0]), float(h[1]))
        lists = self._vehicles if self._vehicles is not None and self._vehicles[3] is others \
            else _as_lists(others)
        vc, vy, vh = lists[:3]
        for k in range(len(vc)):
            cx, cy = vc[k]
            if max(abs(cx - x), abs(cy - y)) < vh[k][0] + 1.5 and _overlap(box, cx, cy, vy[k], vh[k]):
                return False
        if len(self.people) > 1:
            P, Y, H = self._boxes
            for j in range(len(P)):
                if j != i and max(abs(P[j][0] - x), abs(P[j][1] - y)) < 2.5 and \
                        _overlap(box, P[j][0], P[j][1], Y[j], H[j]):
                    return False
        return True

    def free_spot(self, xy, yaw, length, width, others) -> bool:
        """Is a new pedestrian box at (xy, yaw) clear of everyone placed so far?"""
        h = np.array([length / 2 + self.p.clearance, width / 2 + self.p.clearance])
        oc, oy, oh = others
        if len(oc) and obb_overlap(xy, yaw, h, oc, oy, oh).any():
            return False
        if self.people:
            pc = np.array([q.xy for q in self.people])
            py = np.array([q.yaw for q in self.people])
            ph = np.array([self.half(q) for q in self.people])
            if obb_overlap(xy, yaw, h, pc, py, ph).any():
                return False
        return True

    # ---- crossing
    def _start_crossing(self, p: Walker, k: int, forward: bool) -> None:
        if p.midblock is not None:
            q, jt, js = p.midblock
            path = np.array([p.xy, q])
            p.path, p.cum, p.u = path, np.array([0.0, float(np.linalg.norm(q - p.xy))]), 0.0
            p.release_u, p.join, p.state, p.occupying, p.midblock = p.cum[-1], (jt, js), CROSS, True, None
            return
        c = self.w.crosswalks[k]
        a, b = (c.a, c.b) if forward else (c.b, c.a)
        d = (b - a) / max(np.linalg.norm(b - a), 1e-9)
        right = np.array([d[1], -d[0]])
        o = float(np.clip(c.width / 2 - p.width / 2 - 0.15, 0.0, 0.6))
        jt, js = (c.track_b, c.s_b) if forward else (c.track_a, c.s_a)
        join = self.w.tracks[jt].point(js)
        path = np.array([p.xy, a + o * right, b + o * right, join])
        seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
        p.path, p.cum, p.u = path, np.concatenate([[0.0], np.cumsum(seg)]), 0.0
        p.release_u = p.cum[2] + p.length / 2 + self.w.curb_width + 0.3
        p.join = (jt, js)
        p.state = CROSS
        p.occupying = True

    def _maybe_midblock(self, p: Walker, dt: float) -> None:
        if self.add_crossing is None or self.p.midblock_rate <= 0:
            return
        if self.rng.random() >= self.p.midblock_rate * dt:
            return
        from lsd3d_usd.actors.sidewalks import midblock_line
        line = midblock_line(self.w, p.track, p.s)
        if line is None:
            return
        start, jt, js, corridor = line
        k = self.add_crossing(corridor)
        self.polygons.append(corridor)
        p.state, p.crosswalk, p.midblock = WAIT, k, (self.w.tracks[jt].point(js), jt, js)
        p.wait_left = float(self.rng.uniform(*self.p.wait))

    def _path_point(self, p: Walker, u: float):
        u = min(u, p.cum[-1])
        xy = np.array([np.interp(u, p.cum, p.path[:, k]) for k in range(2)])
        j = min(int(np.searchsorted(p.cum, u, side="right")) - 1, len(p.path) - 2)
        d = p.path[j + 1] - p.path[j]
        yaw = float(np.arctan2(d[1], d[0])) if np.linalg.norm(d) > 1e-9 else p.yaw
        return xy, yaw

    # ---- one step
    def occupied(self) -> set[int]:
        return {p.crosswalk for p in self.people if p.occupying}

    def step(self, dt: float, others, crosswalk_clear) -> None:
        """Move every walker by one step of ``dt`` s. ``others``: the vehicles' boxes;
        ``crosswalk_clear(k)``: may a walker step onto crosswalk k now."""
        # everyone's box as arrays, a row updated as its walker moves (what `_free` reads)
        self._boxes = ([[float(p.xy[0]), float(p.xy[1])] for p in self.people],
                       [float(p.yaw) for p in self.people],
                       [[float(v) for v in self.half(p)] for p in self.people])
        self._vehicles = _as_lists(others)
        for i, p in enumerate(self.people):
            if p.state == STAND:
                p.v = 0.0
                continue
            if p.state == WAIT:
                p.v = 0.0
                p.wait_left -= dt
                if p.wait_left <= 0.0 and crosswalk_clear(p.crosswalk):
                    self._start_crossing(p, p.crosswalk, p.forward)
                continue
            if p.state == CROSS:
                self._step_cross(i, p, dt, others)
                continue
            self._step_walk(i, p, dt, others)

    def _move_ok(self, i, xy, yaw, others) -> bool:
        return self._free(i, xy, yaw, others)

    def _step_walk(self, i: int, p: Walker, dt: float, others) -> None:
        t = self.w.tracks[p.track]
        ds = p.v_des * dt
        # a crosswalk's leave point within this step: stop there, maybe to cross
        stop = None
        for s_leave, k, fwd in self.leave[p.track]:
            ahead = (s_leave - p.s) % t.length
            if ahead <= ds + 1e-9 and k != p.last_crossed:
                stop = (ahead, k, fwd)
                break
        for frac in (1.0, 0.5, 0.25):
            d = (stop[0] if stop is not None else ds) * frac
            d_fwd, aside = self._back(p, d)
            s_new = (p.s + d_fwd) % t.length
            xy, yaw = self._beside(*t.pose2d(s_new), aside)
            if self._move_ok(i, xy, yaw, others):
                p.s, p.xy, p.yaw, p.v = s_new, xy, yaw, d / dt
                self._boxes[0][i], self._boxes[1][i] = [float(xy[0]), float(xy[1])], float(yaw)
                p.walked += d
                p.blocked = 0.0
                p.aside = aside
                p.aside_dir = p.aside_dir if aside else 0.0
                if stop is not None and frac == 1.0:
                    if self.rng.random() < self.p.cross_probability:
                        p.state, p.crosswalk, p.forward = WAIT, stop[1], stop[2]
                        p.wait_left = float(self.rng.uniform(*self.p.wait))
                        p.v = d / dt
                    else:
                        p.last_crossed = stop[1]    # walk past it
                elif stop is None and frac == 1.0:
                    self._maybe_midblock(p, dt)
                return
        p.v = 0.0
        p.blocked += dt
        self._sidestep(i, p, dt, others)

    @staticmethod
    def _back(p: Walker, d: float) -> tuple[float, float]:
        """(distance along the path, offset from it after the move) of a move of ``d`` m by
        a walker that stepped aside: it returns to its path by at most half the move."""
        if not p.aside:
            return d, 0.0
        back = min(abs(p.aside), 0.5 * d)
        return math.sqrt(max(d * d - back * back, 0.0)), p.aside - math.copysign(back, p.aside)

    @staticmethod
    def _beside(xy, yaw, aside: float):
        if not aside:
            return xy, yaw
        return np.asarray(xy) + aside * np.array([-math.sin(yaw), math.cos(yaw)]), yaw

    def _make_room(self, i: int, p: Walker, ds: float, dt: float, others) -> None:
        """A walker crossing the road and blocked by people waiting at the crosswalk's end
        (who wait for the traffic, which waits for the crossing walker) asks them to step
        back along their track at their walking speed; otherwise the three wait forever."""
        if p.blocked < PASS_AFTER / 2:
            return
        u = min(p.u + ds, p.cum[-1])
        xy, yaw = self._path_point(p, u)
        box = (float(xy[0]), float(xy[1]), math.cos(yaw), math.sin(yaw), *map(float, self.half(p)))
        P, Y, H = self._boxes
        for j, q in enumerate(self.people):
            if j == i or q.state not in (WAIT, STAND) or q.track < 0:
                continue
            if max(abs(P[j][0] - box[0]), abs(P[j][1] - box[1])) >= 2.5 or \
                    not _overlap(box, P[j][0], P[j][1], Y[j], H[j]):
                continue
            t = self.w.tracks[q.track]
            for back in (-1.0, 1.0):           # behind it on its track, else ahead
                s_new = (q.s + back * q.v_des * dt) % t.length
                xy_q, yaw_q = t.pose2d(s_new)
                if self._free(j, xy_q, yaw_q, others):
                    q.s, q.xy, q.yaw = s_new, xy_q, yaw_q
                    self._boxes[0][j], self._boxes[1][j] = [float(xy_q[0]), float(xy_q[1])], float(yaw_q)
                    break
            else:
                # hemmed in on its track (a queue behind it): off the track, away from the
                # crossing walker, where the walkable area allows
                away = np.asarray(q.xy, float) - np.asarray(xy, float)
                n = float(np.hypot(*away))
                if n > 1e-9:
                    self._step_to(j, q, np.asarray(q.xy, float) + away / n * q.v_des * dt, others)

    def _step_to(self, j: int, q: Walker, xy, others) -> bool:
        """Move walker j to ``xy`` (same heading) if the walkable area and every box allow."""
        area = getattr(self.w, "area", None)
        inside = area is None or bool(shapely.contains_xy(area, xy[0], xy[1])) or \
            any(bool(shapely.contains_xy(c, xy[0], xy[1])) for c in self.polygons)
        if inside and self._free(j, xy, q.yaw, others):
            q.xy = xy
            self._boxes[0][j] = [float(xy[0]), float(xy[1])]
            return True
        return False

    def _sidestep(self, i: int, p: Walker, dt: float, others) -> None:
        """Two people facing each other (on a crosswalk, at its end) would otherwise wait for
        each other forever: one that has stood PASS_AFTER seconds steps aside at its walking
        speed, up to ASIDE_MAX m, where the walkable area and everyone's boxes allow, so the
        other can pass; it walks on along its path once that is free."""
        if p.blocked < PASS_AFTER or abs(p.aside) >= ASIDE_MAX:
            return
        left = np.array([-np.sin(p.yaw), np.cos(p.yaw)])
        area = getattr(self.w, "area", None)
        step = p.v_des * dt
        for sign in ((p.aside_dir,) if p.aside_dir else (1.0, -1.0)):
            xy = p.xy + sign * step * left
            inside = area is None or bool(shapely.contains_xy(area, xy[0], xy[1])) or \
                any(bool(shapely.contains_xy(c, xy[0], xy[1])) for c in self.polygons)
            if inside and self._free(i, xy, p.yaw, others):
                p.xy = xy
                self._boxes[0][i] = [float(xy[0]), float(xy[1])]
                p.aside += sign * step
                p.aside_dir = sign
                return

    def _step_cross(self, i: int, p: Walker, dt: float, others) -> None:
        ds = p.v_des * dt
        for frac in (1.0, 0.5, 0.25):
            d_fwd, aside = self._back(p, ds * frac)
            u = min(p.u + d_fwd, p.cum[-1])
            xy, yaw = self._beside(*self._path_point(p, u), aside)
            if self._move_ok(i, xy, yaw, others):
                p.v = (u - p.u) / dt
                p.walked += u - p.u
                p.u, p.xy, p.yaw = u, xy, yaw
                self._boxes[0][i], self._boxes[1][i] = [float(xy[0]), float(xy[1])], float(yaw)
                p.blocked = 0.0
                p.aside = aside
                p.aside_dir = p.aside_dir if aside else 0.0
                break
        else:
            p.v = 0.0
            p.blocked += dt
            self._make_room(i, p, ds, dt, others)
            self._sidestep(i, p, dt, others)
        if p.occupying and p.u >= p.release_u:
            p.occupying = False
        if p.u >= p.cum[-1] - 1e-9:
            p.occupying = False
            p.state, p.track, p.s = WALK, p.join[0], p.join[1]
            p.last_crossed = p.crosswalk
            p.path = None
