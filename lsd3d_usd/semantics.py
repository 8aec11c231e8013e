"""Semantic classes shared by proxy meshes, surfels, G-buffers and priors.

Ids index CLASSES; -1 means unlabelled. The order is part of the file format
(surfel prims store ids and the class names they index), so only append.
"""
from __future__ import annotations

import numpy as np

CLASSES: tuple[str, ...] = (
    "road", "lane_marking", "curb", "sidewalk", "crosswalk", "building",
    "vegetation", "vehicle", "pole", "sign", "terrain", "traffic_light",
    "pedestrian", "cyclist",
)
CLASS_ID: dict[str, int] = {name: i for i, name in enumerate(CLASSES)}
UNLABELLED = -1

# Scene-linear Rec.709 albedo-like colours used to seed surfel colours and for
# previews; chosen to be plausible materials, not a palette.
CLASS_COLORS = np.array([
    (0.09, 0.09, 0.10),   # road: asphalt
    (0.80, 0.80, 0.78),   # lane_marking: white paint
    (0.45, 0.44, 0.42),   # curb: concrete
    (0.35, 0.34, 0.32),   # sidewalk: paving
    (0.75, 0.75, 0.73),   # crosswalk: paint
    (0.40, 0.33, 0.28),   # building: brick / render
    (0.10, 0.22, 0.06),   # vegetation: foliage
    (0.25, 0.27, 0.32),   # vehicle: car paint
    (0.30, 0.30, 0.30),   # pole: galvanised steel
    (0.60, 0.10, 0.08),   # sign
    (0.18, 0.20, 0.10),   # terrain: grass / soil
    (0.08, 0.08, 0.08),   # traffic_light: housing
    (0.20, 0.16, 0.14),   # pedestrian: clothing / skin
    (0.25, 0.10, 0.08),   # cyclist: rider and painted frame
], dtype=np.float32)


def class_id(name: str) -> int:
    """Id of a class name; raises KeyError listing the known classes."""
    try:
        return CLASS_ID[name]
    except KeyError:
        raise KeyError(f"unknown semantic class {name!r}; known: {', '.join(CLASSES)}") from None
