"""The label spaces of the sensor ground truth: class ids and instance ids, one table each
for a whole output (classes.json, instances.json), the same for every camera, frame and LiDAR.

Class ids are the indices of ``semantics.CLASSES`` (the proxy's and the surfels' classes, the
actors' UsdSemantics labels among them), plus SKY (255: nothing drawn) and UNLABELLED (254: a
surfel without a class). Instance ids: 0 for "stuff" (everything that is not an actor), then
1, 2, ... for the actors of the stage in the order of their prim paths, so an actor keeps its
id in every frame and camera of a render.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.semantics import CLASS_COLORS, CLASS_ID, CLASSES

SKY = 255
UNLABELLED = 254
STUFF = 0
CODE = 1024      # label code of a surfel: class + CODE * instance (one rasteriser channel)
# preview colours (sRGB): the Cityscapes convention where it has the class
PREVIEW = {"road": (128, 64, 128), "lane_marking": (255, 255, 255), "curb": (196, 196, 196),
           "sidewalk": (244, 35, 232), "crosswalk": (255, 255, 150), "building": (70, 70, 70),
           "vegetation": (107, 142, 35), "vehicle": (0, 0, 142), "pole": (153, 153, 153),
           "sign": (220, 220, 0), "terrain": (152, 251, 152), "traffic_light": (250, 170, 30),
           "pedestrian": (220, 20, 60), "cyclist": (255, 0, 0), "sky": (70, 130, 180),
           "unlabelled": (0, 0, 0)}


def class_table() -> list[dict]:
    """[{id, name, color (sRGB 0-255)}] of every class id an output may hold."""
    rows = [{"id": i, "name": name, "color": list(PREVIEW.get(name) or _srgb8(
        CLASS_COLORS[i] if i < len(CLASS_COLORS) else (0.5, 0.5, 0.5)))}
            for i, name in enumerate(CLASSES)]
    rows.append({"id": UNLABELLED, "name": "unlabelled", "color": list(PREVIEW["unlabelled"])})
    rows.append({"id": SKY, "name": "sky", "color": list(PREVIEW["sky"])})
    return rows


def _srgb8(rgb) -> list[int]:
    x = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return [int(round(v)) for v in np.clip(255 * x, 0, 255)]


def palette() -> np.ndarray:
    """(256, 3) uint8 colours of the class ids (a preview of a class image)."""
    pal = np.zeros((256, 3), np.uint8)
    for row in class_table():
        pal[row["id"]] = row["color"]
    return pal


def class_of_names(names) -> np.ndarray:
    """Class ids of class names (UNLABELLED for a name the project does not know)."""
    return np.array([CLASS_ID.get(str(n), UNLABELLED) for n in names], np.int64)


@dataclass
class Instances:
    """The actors of a stage as instances: ``ids[q]`` of actor q of the ActorSet, and its
    rows (id, prim path, class name, class id, kind, role)."""
    ids: np.ndarray
    rows: list

    @classmethod
    def of(cls, actor_set) -> "Instances":
        actors = [] if actor_set is None else actor_set.actors
        order = sorted(range(len(actors)), key=lambda q: actors[q].path)
        ids = np.zeros(len(actors), np.int64)
        rows = []
        for rank, q in enumerate(order):
            a = actors[q]
            ids[q] = rank + 1
            rows.append({"id": rank + 1, "prim": a.path, "class": a.label,
                         "class_id": int(CLASS_ID.get(a.label, UNLABELLED)), "kind": a.kind,
                         "role": a.role})
        return cls(ids, rows)

    def class_ids(self) -> np.ndarray:
        """Class id of each actor q (in ActorSet order)."""
        out = np.zeros(len(self.ids), np.int64)
        for row in self.rows:
            out[np.flatnonzero(self.ids == row["id"])] = row["class_id"]
        return out


def write_tables(out_dir, instances: Instances) -> tuple[Path, Path]:
    """OUT/classes.json and OUT/instances.json (atomic)."""
    out = Path(out_dir)
    a = S.atomic_write_text(out / "classes.json", json.dumps(
        {"sky": SKY, "unlabelled": UNLABELLED, "classes": class_table()}, indent=1))
    b = S.atomic_write_text(out / "instances.json", json.dumps(
        {"stuff": STUFF, "instances": instances.rows}, indent=1))
    return a, b
