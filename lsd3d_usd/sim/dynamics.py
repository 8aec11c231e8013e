"""The ego's motion: a kinematic bicycle model about the rear axle, and the limits that clip
what a policy asks for.

State: rear-axle centre (x, y), yaw, speed v >= 0 (no reverse), front-wheel steering angle
delta. Controls: longitudinal acceleration a and either the steering angle (``steer="angle"``)
or its rate (``steer="rate"``). Over one step of dt the model integrates, in ``substeps``
equal sub-steps (semi-implicit Euler: speed first, then the pose with the new speed),

    v'     = a                                  clipped so that 0 <= v <= v_max
    delta' = (delta_cmd - delta) / tau or rate   |delta| <= delta_max, |delta'| <= rate_max
    x'     = v cos(yaw),  y' = v sin(yaw),  yaw' = v tan(delta) / wheelbase

The ego frame is x forward, y left, z up, with its origin on the ground at the centre of the
rear axle (as the rigs mount their sensors); the box centre lies ``box_offset`` ahead of it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class VehicleLimits:
    """Documented bounds of the ego's controls (docs/sim.md)."""
    wheelbase: float = 2.75        # m, the procedural car's axles (actors.assets.SPECS["car"])
    length: float = 4.55           # m, box
    width: float = 1.80            # m, box
    box_offset: float = 1.35       # m, box centre ahead of the rear axle
    a_min: float = -8.0            # m/s^2, full braking
    a_max: float = 4.0             # m/s^2
    v_max: float = 30.0            # m/s
    delta_max: float = 0.61        # rad (35 deg) front-wheel angle
    delta_rate_max: float = 1.0    # rad/s, how fast the wheels turn
    substeps: int = 5


@dataclass
class EgoState:
    """The ego at one instant (see the module doc); ``a`` the acceleration last applied."""
    x: float
    y: float
    yaw: float
    v: float = 0.0
    delta: float = 0.0
    a: float = 0.0
    z: float = 0.0
    yaw_rate: float = 0.0

    def copy(self) -> "EgoState":
        return replace(self)

    def matrix(self) -> np.ndarray:
        """World-from-ego 4x4."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        M = np.eye(4)
        M[:2, :2] = [[c, -s], [s, c]]
        M[:3, 3] = self.x, self.y, self.z
        return M

    def box_centre(self, limits: VehicleLimits) -> np.ndarray:
        return np.array([self.x + limits.box_offset * math.cos(self.yaw),
                         self.y + limits.box_offset * math.sin(self.yaw)])


def clip_control(a: float, steer: float, limits: VehicleLimits, rate: bool) -> tuple[float, float, bool]:
    """(a, steer) within the limits, and whether anything was clipped."""
    hi = limits.delta_rate_max if rate else limits.delta_max
    a_c = min(max(a, limits.a_min), limits.a_max)
    s_c = min(max(steer, -hi), hi)
    return a_c, s_c, (a_c != a) or (s_c != steer)


def step_bicycle(state: EgoState, a: float, steer: float, dt: float, limits: VehicleLimits,
                 rate: bool = False) -> EgoState:
    """The state after ``dt`` seconds of (a, steer) (already clipped to the limits); the
    steering angle follows a commanded angle at most at the rate limit."""
    s = state.copy()
    h = dt / max(1, limits.substeps)
    yaw0 = s.yaw
    for _ in range(max(1, limits.substeps)):
        if rate:
            s.delta = s.delta + steer * h
        else:
            step = min(max(steer - s.delta, -limits.delta_rate_max * h), limits.delta_rate_max * h)
            s.delta = s.delta + step
        s.delta = min(max(s.delta, -limits.delta_max), limits.delta_max)
        v_new = min(max(s.v + a * h, 0.0), limits.v_max)
        s.yaw = s.yaw + v_new * math.tan(s.delta) / limits.wheelbase * h
        s.x += v_new * math.cos(s.yaw) * h
        s.y += v_new * math.sin(s.yaw) * h
        s.v = v_new
    s.a = (s.v - state.v) / dt if dt > 0 else 0.0
    s.yaw_rate = (s.yaw - yaw0) / dt if dt > 0 else 0.0
    return s
