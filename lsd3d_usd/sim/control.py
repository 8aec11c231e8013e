"""Tracking a short trajectory: pure pursuit for the steering, a PI controller on speed.

A trajectory action is K waypoints (x, y) in the ego frame at times spacing, 2 spacing, ...
K spacing ahead (as NAVSIM's and HUGSIM's planners output them). The tracker reads from it
a path (the waypoints after the ego's origin) and a target speed (the distance to the first
waypoint over its time, blended with the next), then

    delta = atan(2 L sin(alpha) / l_d)      pure pursuit on the point of the path l_d ahead,
    a     = k_p (v_target - v) + k_i integral    clipped to the vehicle's limits by the env.

with l_d = max(l_min, k_l v). Both are the textbook forms (Coulter 1992 for pure pursuit).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackerGains:
    lookahead_min: float = 3.0     # m
    lookahead_gain: float = 0.8    # s: lookahead per m/s
    kp: float = 1.2                # 1/s
    ki: float = 0.1                # 1/s^2
    integral_max: float = 5.0      # m/s (anti wind-up)


def path_point(path: np.ndarray, dist: float) -> np.ndarray:
    """The point ``dist`` metres along the polyline ``path`` (n, 2) from its first point
    (extended along the last segment beyond its end)."""
    if len(path) == 1:
        return path[0]
    seg = np.diff(path, axis=0)
    ln = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(ln)])
    if dist >= cum[-1]:
        last = seg[-1] / max(ln[-1], 1e-9)
        return path[-1] + last * (dist - cum[-1]) if ln[-1] > 1e-9 else path[-1]
    j = int(np.searchsorted(cum, dist, side="right") - 1)
    f = (dist - cum[j]) / max(ln[j], 1e-9)
    return path[j] + f * seg[j]


def pure_pursuit(path: np.ndarray, v: float, wheelbase: float, gains: TrackerGains) -> float:
    """Steering angle to reach the point of ``path`` (ego frame, (n, 2), starting at the ego)
    one lookahead ahead."""
    ld = max(gains.lookahead_min, gains.lookahead_gain * v)
    target = path_point(path, ld)
    dist = math.hypot(target[0], target[1])
    if dist < 1e-6:
        return 0.0
    alpha = math.atan2(target[1], target[0])
    return math.atan2(2.0 * wheelbase * math.sin(alpha), dist)


class TrajectoryTracker:
    """Turns waypoints (ego frame) into (acceleration, steering angle); keeps the PI state."""

    def __init__(self, wheelbase: float, spacing: float, gains: TrackerGains = TrackerGains()):
        self.wheelbase = float(wheelbase)
        self.spacing = float(spacing)
        self.g = gains
        self.integral = 0.0

    def reset(self) -> None:
        self.integral = 0.0

    def target_speed(self, waypoints: np.ndarray) -> float:
        """Speed the trajectory asks for now: distance to the first waypoint over its time,
        averaged with the second interval (a stop is a repeated point)."""
        pts = np.vstack([[0.0, 0.0], waypoints[:, :2]])
        d = np.hypot(*np.diff(pts, axis=0).T)
        n = min(2, len(d))
        return float(d[:n].mean() / self.spacing)

    def __call__(self, waypoints, v: float, dt: float) -> tuple[float, float]:
        w = np.asarray(waypoints, np.float64).reshape(-1, 2)
        v_t = self.target_speed(w)
        err = v_t - v
        self.integral = min(max(self.integral + err * dt, -self.g.integral_max), self.g.integral_max)
        a = self.g.kp * err + self.g.ki * self.integral
        ahead = w[w[:, 0] > -0.5] if (w[:, 0] > -0.5).any() else w
        steer = pure_pursuit(np.vstack([[0.0, 0.0], ahead]), max(v, v_t), self.wheelbase, self.g)
        if v_t < 0.05 and v < 0.5:
            steer = 0.0   # standing: hold the wheels straight instead of chasing a point
        return a, steer
