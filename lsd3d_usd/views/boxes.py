"""Boxes of the actors at a frame: each actor's oriented 3D box (the tight box of its geometry
in its own frame, placed by its transform) with its velocity, and per camera the tight 2D box
of its instance pixels, the 2D box of its projected 3D box, how much of it is visible, and
how much of its projected box lies outside the image (``truncated``, 0 to 1).

Velocity: the motion of the box centre over ±VELOCITY_DT seconds (central difference of the
actor's transforms, which USD interpolates linearly between time samples), in world axes and
the same vector in the ego's axes. Visible fraction: the actor's pixels in the composited
frame over its pixels when it is rendered alone from the same camera (1: unoccluded and
inside the image; a box partly outside the image counts the outside as hidden).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsd3d_usd import scene as S
from lsd3d_usd.render.gbuffer import render_gbuffer

VELOCITY_DT = 0.05
CORNERS = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8)
         if np.sum(CORNERS[a] != CORNERS[b]) == 1]


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


def box_corners(box: dict) -> np.ndarray:
    """(8, 3) world corners of a box dict."""
    R = Rotation.from_quat(box["rotation_xyzw"]).as_matrix()
    return (CORNERS * np.asarray(box["size"])) @ R.T + np.asarray(box["center"])


def actor_boxes(actor_set, instances, lboxes, code: float, tcps: float,
                world_from_ego: np.ndarray | None) -> list[dict]:
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
        out.append({"instance_id": int(instances.ids[q]), "prim": a.path, "class": a.label,
                    "class_id": int(instances.class_ids()[q]), "kind": a.kind, "role": a.role,
                    "center": centre.tolist(), "size": (hi - lo).tolist(),
                    "rotation_xyzw": Rotation.from_matrix(R).as_quat().tolist(),
                    "yaw": float(np.arctan2(R[1, 0], R[0, 0])),
                    "velocity_world": v.tolist(), "velocity_ego": (Rego.T @ v).tolist(),
                    "cameras": {}})
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


def camera_boxes(boxes: list[dict], camera, name: str, labels, actors_frame, instances) -> None:
    """Per box, in box["cameras"][name]: the tight 2D box of its instance pixels, its
    projected 3D box, pixel counts and the visible fraction (see the module doc)."""
    inst = labels.instance_id
    for b in boxes:
        proj = projected_box(camera, box_corners(b))
        if proj is None:
            continue
        mask = inst == b["instance_id"]
        seen = int(mask.sum())
        q = int(np.flatnonzero(instances.ids == b["instance_id"])[0])
        alone = _alone_pixels(actors_frame, q, camera)
        full = projected_box(camera, box_corners(b), clip=False)
        area = (full[2] - full[0]) * (full[3] - full[1])
        inside = (proj[2] - proj[0]) * (proj[3] - proj[1])
        entry = {"box_3d_projected": proj, "pixels": seen, "pixels_alone": alone,
                 "visible_fraction": round(seen / alone, 4) if alone else 0.0,
                 "truncated": round(float(np.clip(1.0 - inside / area, 0.0, 1.0)), 4)
                 if area > 0 else 1.0}
        if seen:
            ys, xs = np.nonzero(mask)
            entry["box_2d"] = [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1]
        b["cameras"][name] = entry


def _alone_pixels(actors_frame, q: int, camera) -> int:
    f = np.flatnonzero(actors_frame.face_actor == q)
    if not len(f):
        return 0
    g = render_gbuffer(actors_frame.vertices, actors_frame.faces[f], camera)
    return int((g.face_index >= 0).sum())


def write_boxes(path: Path, frame: int, time: float, boxes: list[dict]) -> Path:
    return S.atomic_write_text(path, json.dumps({"frame": frame, "time": time, "boxes": boxes},
                                                indent=1))
