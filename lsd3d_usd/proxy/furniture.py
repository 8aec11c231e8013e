"""Street furniture: poles, stop signs, traffic lights, street lights."""
from __future__ import annotations

import numpy as np

from .mesh import POLE, SIGN, TRAFFIC_LIGHT, MeshPart, transform_points
from .shapes import box, cylinder, ngon_prism


def _placed(v, f, cls, pid, yaw, pos):
    return MeshPart(transform_points(v, yaw, (pos[0], pos[1], 0.0)), f, cls, pid, solid=True)


def stop_sign_parts(sign_id: str, position, facing_yaw: float) -> list[MeshPart]:
    """A 2.2 m pole and an octagonal plate facing ``facing_yaw`` (towards approaching traffic)."""
    pv, pf = cylinder(0.04, 0.0, 2.2, segments=6)
    a = (np.arange(8) + 0.5) * (np.pi / 4)
    oct_xz = 0.38 * np.column_stack([np.cos(a), np.sin(a)])
    # plate: octagon in the local (y, z) plane, 3 cm thick along x (the facing direction)
    sv, sf = ngon_prism(oct_xz, -0.015, 0.015)        # (y, z, x) before the swap
    sv = sv[:, [2, 0, 1]] + np.array([0.06, 0.0, 2.3])  # a rotation (even permutation)
    return [_placed(pv, pf, POLE, f"{sign_id}/pole", facing_yaw, position),
            _placed(sv, sf, SIGN, f"{sign_id}/plate", facing_yaw, position)]


def traffic_light_parts(light_id: str, position, facing_yaw: float, arm: float = 3.0
                        ) -> list[MeshPart]:
    """A mast with an arm over the road and a signal head facing oncoming traffic.

    Local frame: +x = ``facing_yaw`` (towards the approaching cars); the arm
    reaches along -y, which is the drivers' left: over the road for a pole
    standing on the right-hand side of the approach.
    """
    mv, mf = cylinder(0.09, 0.0, 5.6, segments=8)
    av, af = box(0.12, arm, 5.35, 5.5)
    av = av - np.array([0.0, arm / 2, 0.0])
    hv, hf = box(0.3, 0.35, 4.35, 5.3)
    hv = hv + np.array([0.05, -(arm - 0.3), 0.0])
    return [_placed(mv, mf, POLE, f"{light_id}/mast", facing_yaw, position),
            _placed(av, af, POLE, f"{light_id}/arm", facing_yaw, position),
            _placed(hv, hf, TRAFFIC_LIGHT, f"{light_id}/head", facing_yaw, position)]


def street_light_parts(light_id: str, position, yaw: float) -> list[MeshPart]:
    """A 7 m lamp post with a short arm and lamp box towards +x of ``yaw``."""
    mv, mf = cylinder(0.07, 0.0, 7.0, segments=8)
    av, af = box(1.5, 0.1, 6.85, 6.95)
    av = av + np.array([0.75, 0.0, 0.0])
    lv, lf = box(0.6, 0.25, 6.7, 6.85)
    lv = lv + np.array([1.35, 0.0, 0.0])
    return [_placed(mv, mf, POLE, f"{light_id}/mast", yaw, position),
            _placed(av, af, POLE, f"{light_id}/arm", yaw, position),
            _placed(lv, lf, POLE, f"{light_id}/lamp", yaw, position)]
