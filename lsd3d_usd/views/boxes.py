"""Boxes of the actors at a frame: each actor's oriented 3D box (the tight box of its geometry
in its own frame, placed by its transform) with its velocity, and per camera the tight 2D box
of its instance pixels, the 2D box of its projected 3D box, how much of it is visible, and
how much of its projected box lies outside the image (``truncated``, 0 to 1).

Velocity: the motion of the box centre over ±VELOCITY_DT seconds (central difference of the
actor's transforms, which USD interpolates linearly between time samples), in world axes and
the same vector in the ego's axes. Visible fraction: the actor's pixels in the composited
frame over its pixels when it is rendered alone from the same camera (1: unoccluded and
inside the image; a box partly outside the image counts the outside as hidden).

A box is a frozen `Box` (its 2D boxes per camera `CameraBox`); `Box.to_json` is the dict of
OUT/boxes/<frame>.json (docs/sensors.md) and `Box.from_json` reads one back. Adding a
camera's entry or the keyframe counts makes a new box (`with_camera`, `with_counts`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsd3d_usd import scene as S
from lsd3d_usd.render.gbuffer import render_gbuffer

VELOCITY_DT = 0.05
CORNERS = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8)
         if np.sum(CORNERS[a] != CORNERS[b]) == 1]


@dataclass(frozen=True)
class CameraBox:
    """An actor's box in one camera's frame (pixels)."""
    box_3d_projected: tuple[float, float, float, float]   # its 3D box's corners, clipped
    pixels: int                     # its visible pixels
    pixels_alone: int               # its pixels when rendered alone from the same camera
    visible_fraction: float         # pixels / pixels_alone (0 when alone is 0)
    truncated: float                # share of the projected box outside the image, 0 to 1
    box_2d: tuple[int, int, int, int] | None = None   # tight box of its pixels; None: none

    def to_json(self) -> dict:
        d = {"box_3d_projected": list(self.box_3d_projected), "pixels": self.pixels,
             "pixels_alone": self.pixels_alone, "visible_fraction": self.visible_fraction,
             "truncated": self.truncated}
        if self.box_2d is not None:
            d["box_2d"] = list(self.box_2d)
        return d

    @classmethod
    def from_json(cls, d: dict) -> "CameraBox":
        b2 = d.get("box_2d")
        return cls(tuple(d["box_3d_projected"]), d["pixels"], d["pixels_alone"],
                   d["visible_fraction"], d["truncated"], None if b2 is None else tuple(b2))


@dataclass(frozen=True)
class Box:
    """An actor's oriented 3D box in world coordinates at one time. The fields after
    ``velocity_world`` are None where the maker does not know them (the simulator's boxes,
    sim.record, have no instance id, role or cameras); ``num_lidar_pts``, ``pixels`` and
    ``visible_fraction`` (pooled over the cameras) are set at a dataset's keyframes."""
    prim: str
    label: str                      # the semantic class (JSON key "class")
    class_id: int
    kind: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]            # length, width, height along its own x, y, z
    rotation_xyzw: tuple[float, float, float, float]
    velocity_world: tuple[float, float, float]  # m/s of the centre, world axes
    instance_id: int | None = None
    role: str | None = None
    yaw: float | None = None
    velocity_ego: tuple[float, float, float] | None = None   # the same vector in ego axes
    cameras: dict[str, CameraBox] = field(default_factory=dict)
    num_lidar_pts: int | None = None
    pixels: int | None = None
    visible_fraction: float | None = None

    def corners(self) -> np.ndarray:
        """(8, 3) world corners."""
        R = Rotation.from_quat(self.rotation_xyzw).as_matrix()
        return (CORNERS * np.asarray(self.size)) @ R.T + np.asarray(self.center)

    def speed(self) -> float:
        return float(np.linalg.norm(self.velocity_world))

    def with_camera(self, name: str, entry: CameraBox) -> "Box":
        return replace(self, cameras={**self.cameras, name: entry})

    def with_counts(self, num_lidar_pts: int, pixels: int, visible_fraction: float) -> "Box":
        return replace(self, num_lidar_pts=num_lidar_pts, pixels=pixels,
                       visible_fraction=visible_fraction)

    def to_json(self) -> dict:
        """The box as OUT/boxes/<frame>.json holds it (unknown fields left out)."""
        d = {"instance_id": self.instance_id, "prim": self.prim, "class": self.label,
             "class_id": self.class_id, "kind": self.kind, "role": self.role,
             "center": list(self.center), "size": list(self.size),
             "rotation_xyzw": list(self.rotation_xyzw), "yaw": self.yaw,
             "velocity_world": list(self.velocity_world),
             "velocity_ego": None if self.velocity_ego is None else list(self.velocity_ego),
             "cameras": {n: c.to_json() for n, c in self.cameras.items()},
             "num_lidar_pts": self.num_lidar_pts, "pixels": self.pixels,
             "visible_fraction": self.visible_fraction}
        return {k: v for k, v in d.items() if v is not None}

    @classmethod
    def from_json(cls, d: dict) -> "Box":
        def vec(k):
            return None if d.get(k) is None else tuple(d[k])
        return cls(d["prim"], d["class"], d["class_id"], d["kind"], vec("center"), vec("size"),
                   vec("rotation_xyzw"), vec("velocity_world"), d.get("instance_id"),
                   d.get("role"), d.get("yaw"), vec("velocity_ego"),
                   {n: CameraBox.from_json(c) for n, c in (d.get("cameras") or {}).items()},
                   d.get("num_lidar_pts"), d.get("pixels"), d.get("visible_fraction"))


def read_boxes(path: Path) -> tuple[int, float, list[Box]]:
    """(frame, time, boxes) of an OUT/boxes/<frame>.json."""
    doc = json.loads(Path(path).read_text())
    return doc["frame"], doc["time"], [Box.from_json(b) for b in doc["boxes"]]


def local_boxes(actor_set) -> list:
    """(lo, hi) of each actor's geometry in its own frame (meshes and surfels); for an
    articulated actor (limbs, wheels moving within it) its dimensions, the box of its whole
    motion cycle, so the box does not change with the pose."""
    out = []
    for a in actor_set.actors:
        pts = [] if a.animated else [m.vertices for m in a.meshes]
        if a.surfels is not None and a.surfels.n and not a.animated:
            pts.append(a.surfels.positions)
        if pts:
            p = np.concatenate(pts).astype(np.float64)
            out.append((p.min(0), p.max(0)))
        else:
            d = np.asarray(a.dims, np.float64)
            out.append((np.array([-d[0] / 2, -d[1] / 2, 0.0]), np.array([d[0] / 2, d[1] / 2, d[2]])))
    return out


def actor_boxes(actor_set, instances, lboxes, code: float, tcps: float,
                world_from_ego: np.ndarray | None) -> list[Box]:
    """The 3D box of every visible actor (ego left out) at time code ``code``."""
    dt = VELOCITY_DT * tcps
    now, before, after = (actor_set.transforms(c) for c in (code, code - dt, code + dt))
    vis = actor_set.visible(code)
    Rego = np.eye(3) if world_from_ego is None else world_from_ego[:3, :3]
    out = []
    for q, a in enumerate(actor_set.actors):
        if not vis[q] or a.role == "ego":
            continue
        lo, hi = lboxes[q]
        c_local = np.append((lo + hi) / 2, 1.0)
        centre = (now[q] @ c_local)[:3]
        v = ((after[q] @ c_local)[:3] - (before[q] @ c_local)[:3]) / (2 * VELOCITY_DT)
        R = now[q][:3, :3]
        out.append(Box(a.path, a.label, int(instances.class_ids()[q]), a.kind,
                       tuple(centre.tolist()), tuple((hi - lo).tolist()),
                       tuple(Rotation.from_matrix(R).as_quat().tolist()), tuple(v.tolist()),
                       instance_id=int(instances.ids[q]), role=a.role,
                       yaw=float(np.arctan2(R[1, 0], R[0, 0])),
                       velocity_ego=tuple((Rego.T @ v).tolist())))
    return out


def projected_box(camera, corners: np.ndarray, clip: bool = True):
    """[x0, y0, x1, y1] pixel box of a 3D box's part in front of the near plane, clipped to
    the image (unless ``clip`` is False); None when none of it is in view."""
    Rc = camera.viewmat[:3, :3]
    tc = camera.viewmat[:3, 3]
    pc = corners @ Rc.T + tc                      # camera frame, z forward
    near = camera.near
    pts = [p for p in pc if p[2] >= near]
    for a, b in EDGES:                            # edges crossing the near plane
        za, zb = pc[a][2], pc[b][2]
        if (za - near) * (zb - near) < 0:
            f = (near - za) / (zb - za)
            pts.append(pc[a] + f * (pc[b] - pc[a]))
    if not pts:
        return None
    P = np.array(pts)
    uv = (P @ camera.K.T)[:, :2] / P[:, 2:3]
    if not clip:
        return [float(v) for v in (*uv.min(0), *uv.max(0))]
    x0, y0 = np.clip(uv.min(0), 0, [camera.width, camera.height])
    x1, y1 = np.clip(uv.max(0), 0, [camera.width, camera.height])
    if x1 <= x0 or y1 <= y0:
        return None
    return [float(x0), float(y0), float(x1), float(y1)]


def camera_boxes(boxes: list[Box], camera, name: str, labels, actors_frame,
                 instances) -> list[Box]:
    """The boxes, each in view with its entry for camera ``name``: the tight 2D box of its
    instance pixels, its projected 3D box, pixel counts and the visible fraction (see the
    module doc)."""
    inst = labels.instance_id
    out = []
    for b in boxes:
        proj = projected_box(camera, b.corners())
        if proj is None:
            out.append(b)
            continue
        mask = inst == b.instance_id
        seen = int(mask.sum())
        q = int(np.flatnonzero(instances.ids == b.instance_id)[0])
        alone = _alone_pixels(actors_frame, q, camera)
        full = projected_box(camera, b.corners(), clip=False)
        area = (full[2] - full[0]) * (full[3] - full[1])
        inside = (proj[2] - proj[0]) * (proj[3] - proj[1])
        box_2d = None
        if seen:
            ys, xs = np.nonzero(mask)
            box_2d = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
        out.append(b.with_camera(name, CameraBox(
            tuple(proj), seen, alone, round(seen / alone, 4) if alone else 0.0,
            round(float(np.clip(1.0 - inside / area, 0.0, 1.0)), 4) if area > 0 else 1.0,
            box_2d)))
    return out


def _alone_pixels(actors_frame, q: int, camera) -> int:
    f = np.flatnonzero(actors_frame.face_actor == q)
    if not len(f):
        return 0
    g = render_gbuffer(actors_frame.vertices, actors_frame.faces[f], camera)
    return int((g.face_index >= 0).sum())


def write_boxes(path: Path, frame: int, time: float, boxes: list[Box]) -> Path:
    return S.atomic_write_text(path, json.dumps(
        {"frame": frame, "time": time, "boxes": [b.to_json() for b in boxes]}, indent=1))
