"""Coarse parked vehicles: one closed side-profile prism per car, van or truck."""
from __future__ import annotations

import numpy as np

from .buildings import stable_unit
from .mesh import VEHICLE, MeshPart, transform_points
from .shapes import profile_prism

# Side profiles (x forward, z up), metres, with the overall width. Convex on purpose:
# the prism fan-triangulates its caps.
PROFILES = {
    "car": (np.array([[-2.25, 0.25], [2.25, 0.25], [2.3, 0.75], [1.2, 0.95], [0.45, 1.45],
                      [-1.2, 1.45], [-2.2, 1.0]]), 1.8),
    "van": (np.array([[-2.6, 0.25], [2.6, 0.25], [2.65, 1.0], [1.9, 1.9], [-2.55, 1.95]]), 2.0),
    "truck": (np.array([[-4.0, 0.35], [4.0, 0.35], [4.05, 2.9], [-4.0, 2.95]]), 2.4),
}


def vehicle_kind(spot_id: str, spot_length: float) -> str:
    """Stable choice: trucks only fit long spots; otherwise mostly cars, some vans."""
    u = stable_unit(spot_id, "vehicle")
    if spot_length >= 8.5 and u < 0.5:
        return "truck"
    return "van" if u > 0.8 and spot_length >= 5.6 else "car"


def vehicle_part(spot_id: str, center, heading: float, spot_length: float,
                 spot_width: float) -> MeshPart:
    """A parked vehicle centred in its spot, scaled down if the spot is small."""
    kind = vehicle_kind(spot_id, spot_length)
    prof, width = PROFILES[kind]
    length = prof[:, 0].max() - prof[:, 0].min()
    s = min(1.0, 0.92 * spot_length / length) if spot_length > 0 else 1.0
    width = min(width, 0.9 * spot_width) if spot_width > 0 else width
    v, f = profile_prism(prof * np.array([s, 1.0]), width)
    yaw = float(heading) + (np.pi if stable_unit(spot_id, "flip") < 0.5 else 0.0)
    v = transform_points(v, yaw, (float(center[0]), float(center[1]), 0.0))
    return MeshPart(v, f, VEHICLE, f"{spot_id}/{kind}", solid=True)
