"""Geometry of the generator's blocks: road pieces, junctions, curves, roundabouts.

Pure functions over numpy arrays (2D, z = 0 added by the caller). Lateral
offsets are measured to the *left* of a direction of travel; right-hand
traffic: the lanes travelling A→B lie right of the A→B centre line.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Flatness of sampled arcs and connector curves: max chord error (m).
ARC_TOLERANCE = 0.01


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def left_normal(d: np.ndarray) -> np.ndarray:
    return np.array([-d[1], d[0]])


def angle_of(d) -> float:
    return float(np.arctan2(d[1], d[0]))


def wrap_angle(a: float) -> float:
    """Angle in (-pi, pi]."""
    a = (a + np.pi) % (2 * np.pi) - np.pi
    return np.pi if a == -np.pi else a


@dataclass(frozen=True)
class Section:
    """Cross-section of a road: lanes per direction, lane width, median, parking lane."""
    lanes: int
    lane_width: float
    median: float = 0.0
    parking: float = 0.0   # width of a parking lane on each side (0: none)

    @property
    def half_width(self) -> float:
        return self.median / 2 + self.lanes * self.lane_width + self.parking

    def lane_offset(self, k: int) -> float:
        """Distance from the centre line to driving lane k (0 = innermost)."""
        return self.median / 2 + (k + 0.5) * self.lane_width

    def parking_offset(self) -> float:
        return self.median / 2 + self.lanes * self.lane_width + self.parking / 2

    def to_dict(self) -> dict:
        return {"lanes": self.lanes, "lane_width": self.lane_width, "median": self.median,
                "parking": self.parking}


def arc_points(center, radius: float, a0: float, sweep: float, tol: float = ARC_TOLERANCE) -> np.ndarray:
    """Points on a circle from angle a0 over ``sweep`` (signed), chord error <= tol."""
    radius = abs(radius)
    if radius < 1e-9 or abs(sweep) < 1e-12:
        p = np.asarray(center) + radius * np.array([np.cos(a0), np.sin(a0)])
        return np.stack([p, p])
    # sagitta r(1 - cos(step/2)) <= tol
    step = 2 * np.arccos(max(-1.0, 1 - tol / radius)) if tol < radius else np.pi / 4
    n = max(2, int(np.ceil(abs(sweep) / max(step, 1e-6))) + 1)
    a = a0 + np.linspace(0.0, sweep, n)
    return np.asarray(center) + radius * np.stack([np.cos(a), np.sin(a)], axis=1)


def hermite(p0, t0, p1, t1, tol: float = ARC_TOLERANCE) -> np.ndarray:
    """Cubic Hermite curve from p0 (unit tangent t0) to p1 (unit tangent t1).

    Tangent magnitudes: the chord length (straight-ish) or 0.55 × chord for turns,
    which keeps quarter turns close to circular. Endpoints are exact.
    """
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    chord = float(np.linalg.norm(p1 - p0))
    if chord < 1e-9:
        return np.stack([p0, p1])
    turn = abs(wrap_angle(angle_of(t1) - angle_of(t0)))
    k = chord * (0.55 if turn > 0.3 else 1.0)
    m0, m1 = np.asarray(t0) * k, np.asarray(t1) * k
    n = max(2, int(np.ceil(chord / 0.75)) + 1 + int(turn * 8))
    s = np.linspace(0.0, 1.0, n)[:, None]
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    pts = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
    pts[0], pts[-1] = p0, p1
    return pts


def fillet(node: np.ndarray, d_in: np.ndarray, d_out: np.ndarray, radius: float):
    """Fillet between the lines node+s*d_in and node+s*d_out (unit arm directions
    pointing away from the node). Travel enters along -d_in and leaves along d_out.

    Returns (tangent distance t, centre, signed turn angle), or None if the arms
    are collinear (no turn).
    """
    u = -d_in
    turn = wrap_angle(angle_of(d_out) - angle_of(u))
    if abs(turn) < 1e-9:
        return None
    t = radius * np.tan(abs(turn) / 2)
    bis = unit(d_in + d_out)
    centre = node + bis * radius / np.cos(abs(turn) / 2)
    return t, centre, turn


def curve_path(node, d_in, d_out, radius: float, lateral: float) -> np.ndarray:
    """Path through a fillet curve for a lane at lateral offset ``lateral``
    (left of the travel direction), from the tangent point on arm d_in to the
    tangent point on arm d_out: an arc concentric with the centre-line fillet."""
    f = fillet(node, d_in, d_out, radius)
    u = -d_in
    if f is None:
        p = node + lateral * left_normal(u)
        return np.stack([p, p])
    t, centre, turn = f
    s = np.sign(turn)
    start = node + t * d_in + lateral * left_normal(u)
    r = radius - s * lateral
    a0 = angle_of(start - centre)
    pts = arc_points(centre, r, a0, turn)
    pts[0] = start
    pts[-1] = node + t * d_out + lateral * left_normal(d_out)
    return pts


def corner_cutbacks(node, dirs: list[np.ndarray], halves: list[float], corner_radius: float) -> list[float]:
    """Distance from the node at which each arm's straight road may start so that
    a curb fillet of ``corner_radius`` fits between every pair of adjacent arms.

    ``dirs`` must be sorted by angle (CCW). Arms whose curb lines do not meet
    (gap >= 180°) impose only a minimum of their half width.
    """
    n = len(dirs)
    cut = [max(h, 4.0) for h in halves]
    if n < 2:
        return cut
    for k in range(n):
        k2 = (k + 1) % n
        d1, d2 = dirs[k], dirs[k2]
        beta = (angle_of(d2) - angle_of(d1)) % (2 * np.pi)
        if beta >= np.pi - 1e-6 or beta < 1e-6:
            continue
        # left curb of arm k: s1*d1 + h1*n1 ; right curb of arm k2: s2*d2 - h2*n2
        n1, n2 = left_normal(d1), left_normal(d2)
        a = np.stack([d1, -d2], axis=1)
        rhs = -halves[k2] * n2 - halves[k] * n1
        s1, s2 = np.linalg.solve(a, rhs)
        tan_len = corner_radius / np.tan(beta / 2)
        cut[k] = max(cut[k], s1 + tan_len)
        cut[k2] = max(cut[k2], s2 + tan_len)
    return cut
