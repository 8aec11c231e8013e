"""Our labels in nuScenes' terms (docs/datasets.md holds the same tables).

CATEGORIES: nuScenes' 32 categories with the lidarseg ``index`` nuScenes gives them.
Actors map by kind (car and van -> vehicle.car, truck, bus -> vehicle.bus.rigid) or class
(pedestrian, cyclist); stuff (proxy and surfel classes) maps by class for lidarseg.
Attributes follow the actor's motion: speed above MOVING_MPS is moving; a vehicle below it is
parked when its role is parked, else stopped. Visibility: the actor's visible pixels over its
pixels when rendered alone, pooled over all cameras, in nuScenes' four bins.
"""
from __future__ import annotations

import numpy as np

from lsd3d_usd.semantics import CLASS_ID
from lsd3d_usd.views import labels as L

CATEGORIES = (
    ("noise", "Any lidar return that does not correspond to a physical object"),
    ("animal", "All animals"),
    ("human.pedestrian.adult", "Adult pedestrian moving around the city"),
    ("human.pedestrian.child", "Child pedestrian moving around the city"),
    ("human.pedestrian.construction_worker", "Construction worker"),
    ("human.pedestrian.personal_mobility", "A small electric or self-propelled vehicle"),
    ("human.pedestrian.police_officer", "Police officer"),
    ("human.pedestrian.stroller", "Strollers"),
    ("human.pedestrian.wheelchair", "Wheelchairs"),
    ("movable_object.barrier", "Temporary road barrier"),
    ("movable_object.debris", "Movable object that is left on the driveable surface"),
    ("movable_object.pushable_pullable", "Objects that a pedestrian may push or pull"),
    ("movable_object.trafficcone", "All types of traffic cones"),
    ("static_object.bicycle_rack", "Area or device intended to park or secure bicycles"),
    ("vehicle.bicycle", "Human or electric powered 2-wheeled vehicle"),
    ("vehicle.bus.bendy", "Bendy bus subcategory"),
    ("vehicle.bus.rigid", "Rigid bus subcategory"),
    ("vehicle.car", "Vehicle designed primarily for personal use"),
    ("vehicle.construction", "Vehicles primarily designed for construction"),
    ("vehicle.emergency.ambulance", "All types of ambulances"),
    ("vehicle.emergency.police", "All types of police vehicles"),
    ("vehicle.motorcycle", "Gasoline or electric powered 2-wheeled vehicle"),
    ("vehicle.trailer", "Any vehicle trailer"),
    ("vehicle.truck", "Vehicles primarily designed to haul cargo"),
    ("flat.driveable_surface", "Surfaces should be regarded with no dimension"),
    ("flat.other", "Horizontal surfaces between the drivable surface and the sidewalk"),
    ("flat.sidewalk", "Sidewalk, pedestrian walkways, bike paths"),
    ("flat.terrain", "Natural horizontal surfaces such as ground level horizontal vegetation"),
    ("static.manmade", "Man-made structures: buildings, walls, poles, signs, traffic lights"),
    ("static.other", "Points in the background that are not distinguishable"),
    ("static.vegetation", "Any vegetation in the frame that is higher than the ground"),
    ("vehicle.ego", "The vehicle on which the sensors are mounted"),
)
CATEGORY_INDEX = {name: i for i, (name, _) in enumerate(CATEGORIES)}

STUFF_CATEGORY = {   # our class -> nuScenes category (lidarseg of stuff)
    "road": "flat.driveable_surface", "lane_marking": "flat.driveable_surface",
    "crosswalk": "flat.driveable_surface", "curb": "flat.other", "sidewalk": "flat.sidewalk",
    "terrain": "flat.terrain", "building": "static.manmade", "pole": "static.manmade",
    "sign": "static.manmade", "traffic_light": "static.manmade",
    "vegetation": "static.vegetation", "vehicle": "vehicle.car",
    "pedestrian": "human.pedestrian.adult", "cyclist": "vehicle.bicycle",
}
KIND_CATEGORY = {"car": "vehicle.car", "van": "vehicle.car", "truck": "vehicle.truck",
                 "bus": "vehicle.bus.rigid", "bicycle": "vehicle.bicycle",
                 "motorcycle": "vehicle.motorcycle", "trailer": "vehicle.trailer"}
UNLABELLED_CATEGORY = "static.other"

ATTRIBUTES = (
    ("vehicle.moving", "Vehicle is moving."),
    ("vehicle.stopped", "Vehicle, with a driver/rider in/on it, is currently stationary."),
    ("vehicle.parked", "Vehicle is stationary (usually for longer duration) with no driver."),
    ("cycle.with_rider", "There is a rider on the bicycle or motorcycle."),
    ("cycle.without_rider", "There is NO rider on the bicycle or motorcycle."),
    ("pedestrian.sitting_lying_down", "The human is sitting or lying down."),
    ("pedestrian.standing", "The human is standing."),
    ("pedestrian.moving", "The human is moving."),
)
MOVING_MPS = 0.5
VISIBILITY = (("1", "v0-40", "visibility of whole object is between 0 and 40%"),
              ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
              ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
              ("4", "v80-100", "visibility of whole object is between 80 and 100%"))


def actor_category(cls: str, kind: str) -> str:
    """The nuScenes category of an actor of class ``cls`` and kind ``kind``."""
    if cls == "vehicle":
        return KIND_CATEGORY.get(kind, "vehicle.car")
    if cls == "pedestrian" and kind == "child":
        return "human.pedestrian.child"
    return STUFF_CATEGORY.get(cls, UNLABELLED_CATEGORY)


def attribute(category: str, role: str, speed: float) -> str | None:
    moving = speed > MOVING_MPS
    if category in ("vehicle.bicycle", "vehicle.motorcycle"):
        return "cycle.with_rider" if role != "parked" else "cycle.without_rider"
    if category.startswith("human.pedestrian"):
        return "pedestrian.moving" if moving else "pedestrian.standing"
    if category.startswith("vehicle."):
        return "vehicle.moving" if moving else "vehicle.parked" if role == "parked" else \
            "vehicle.stopped"
    return None


def visibility_token(fraction: float) -> str:
    f = float(fraction)
    return "1" if f <= 0.4 else "2" if f <= 0.6 else "3" if f <= 0.8 else "4"


def lidarseg_table(instance_rows) -> tuple[np.ndarray, dict]:
    """(256,) uint8 nuScenes index per class id of our points (stuff), and
    {instance id: index} of the actors (their own category)."""
    t = np.full(256, CATEGORY_INDEX[UNLABELLED_CATEGORY], np.uint8)
    for name, i in CLASS_ID.items():
        t[i] = CATEGORY_INDEX[STUFF_CATEGORY.get(name, UNLABELLED_CATEGORY)]
    t[L.SKY] = CATEGORY_INDEX["noise"]
    by_inst = {int(r["id"]): CATEGORY_INDEX[actor_category(r["class"], r["kind"])]
               for r in instance_rows if r["role"] != "ego"}
    return t, by_inst


def point_labels(class_id: np.ndarray, instance_id: np.ndarray, table, by_inst) -> np.ndarray:
    out = table[np.asarray(class_id, np.int64)]
    for inst, idx in by_inst.items():
        out[instance_id == inst] = idx
    return out.astype(np.uint8)
