"""Analytic street G-buffers (ray-cast ground plane + axis-aligned boxes) for tests, docs and
benchmarks of the priors, independent of the mesh G-buffer renderer.

The street runs along world +X: road |y| < 4 m (lane line dashes on y = 0), curbs 4-4.2 m,
sidewalks to 7 m, terrain beyond; boxes are buildings, cars, trees (semantic per box).
Sun visibility comes from shadow rays against the boxes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from lsd3d_usd.conditioning.gbuffer import GBuffer
from lsd3d_usd.semantics import CLASS_ID


@dataclass
class Box:
    lo: tuple
    hi: tuple
    semantic: str


def default_boxes() -> list[Box]:
    return [
        Box((-60, 7.0, 0), (-22, 20, 15.5), "building"),
        Box((-21.5, 7.0, 0), (4, 18, 22.0), "building"),
        Box((4.5, 7.0, 0), (60, 19, 12.0), "building"),
        Box((-60, -20, 0), (-5, -7.0, 18.5), "building"),
        Box((-4.5, -20, 0), (60, -7.0, 9.0), "building"),
        Box((6.0, 2.2, 0.2), (10.5, 3.9, 1.6), "vehicle"),
        Box((14.0, -3.9, 0.2), (18.4, -2.1, 1.5), "vehicle"),
        Box((20.0, 5.2, 2.5), (23.0, 6.8, 6.5), "vegetation"),
        Box((21.3, 5.8, 0.0), (21.7, 6.2, 2.5), "pole"),
    ]


def ground_semantic(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    ay = y.abs()
    sem = torch.full_like(x, CLASS_ID["terrain"], dtype=torch.long)
    sem[ay < 7.0] = CLASS_ID["sidewalk"]
    sem[ay < 4.2] = CLASS_ID["curb"]
    sem[ay < 4.0] = CLASS_ID["road"]
    dash = (ay < 0.075) & ((x % 9.0) < 3.0)
    edge = (ay > 3.75) & (ay < 3.87)
    sem[dash | edge] = CLASS_ID["lane_marking"]
    cross = (x > 26) & (x < 30) & (ay < 4.0) & ((y % 1.0) < 0.5)
    sem[cross] = CLASS_ID["crosswalk"]
    return sem


def look_at_rays(eye, target, width, height, fov_x_deg=70.0):
    """World rays (H, W, 3) of a pinhole camera (OpenCV axes) and its forward axis."""
    eye = torch.tensor(eye, dtype=torch.float64)
    f = torch.nn.functional.normalize(torch.tensor(target, dtype=torch.float64) - eye, dim=0)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    r = torch.nn.functional.normalize(torch.linalg.cross(f, up), dim=0)
    d = torch.linalg.cross(f, r)                      # image down
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    u = (torch.arange(width, dtype=torch.float64) + 0.5 - width / 2) / fx
    v = (torch.arange(height, dtype=torch.float64) + 0.5 - height / 2) / fx
    rays = f + u[None, :, None] * r + v[:, None, None] * d
    return torch.nn.functional.normalize(rays, dim=-1), f, eye


def _hit_boxes(o, dirs, boxes):
    """Nearest hit distance, normal and box index of rays (N,3) from origins o (N,3) or (3,)."""
    N = dirs.shape[0]
    best = torch.full((N,), math.inf, dtype=torch.float64)
    nrm = torch.zeros(N, 3, dtype=torch.float64)
    idx = torch.full((N,), -1, dtype=torch.long)
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    for k, b in enumerate(boxes):
        lo = torch.tensor(b.lo, dtype=torch.float64)
        hi = torch.tensor(b.hi, dtype=torch.float64)
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
        tmin = torch.minimum(t0, t1)
        tmax = torch.maximum(t0, t1)
        tn, axis = tmin.max(-1)
        tf = tmax.min(-1).values
        hit = (tn <= tf) & (tn > 1e-6) & (tn < best)
        best = torch.where(hit, tn, best)
        sgn = -torch.sign(dirs.gather(1, axis[:, None]))[:, 0]
        n_new = torch.nn.functional.one_hot(axis, 3).double() * sgn[:, None]
        nrm = torch.where(hit[:, None], n_new, nrm)
        idx = torch.where(hit, torch.full_like(idx, k), idx)
    return best, nrm, idx


def street_gbuffer(width=480, height=270, eye=(-12.0, -1.8, 1.6), target=(20.0, 0.5, 1.2),
                   boxes=None, sun_direction=(0.35, -0.45, 0.82), fov_x_deg=75.0) -> GBuffer:
    """G-buffer of the synthetic street seen from `eye` (float32 tensors; world_pos float64)."""
    boxes = default_boxes() if boxes is None else boxes
    dirs, fwd, eye_t = look_at_rays(eye, target, width, height, fov_x_deg)
    D = dirs.reshape(-1, 3)
    tb, nb, ib = _hit_boxes(eye_t, D, boxes)
    tg = torch.where(D[:, 2] < -1e-9, -eye_t[2] / D[:, 2], torch.full_like(tb, math.inf))
    use_ground = tg < tb
    t = torch.minimum(tb, tg)
    pos = eye_t + t[:, None] * D
    nrm = torch.where(use_ground[:, None], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), nb)
    box_sem = torch.tensor([CLASS_ID[b.semantic] for b in boxes] + [-1])
    sem = torch.where(use_ground, ground_semantic(pos[:, 0], pos[:, 1]), box_sem[ib])
    hit = torch.isfinite(t)
    sem = torch.where(hit, sem, torch.full_like(sem, -1))
    depth = torch.where(hit, t * (D @ fwd), torch.full_like(t, math.inf))
    # shadow rays towards the sun from the hit points
    s = torch.nn.functional.normalize(torch.tensor(sun_direction, dtype=torch.float64), dim=0)
    ts, _, _ = _hit_boxes(torch.where(hit[:, None], pos, torch.zeros_like(pos)) + 1e-4 * nrm, s.expand_as(D).contiguous(), boxes)
    vis = (~torch.isfinite(ts)).float()
    pos = torch.where(hit[:, None], pos, torch.full_like(pos, float("nan")))
    H, W = height, width
    return GBuffer(depth=depth.float().reshape(H, W), normal=nrm.float().reshape(H, W, 3),
                   semantic=sem.reshape(H, W).int(), world_pos=pos.reshape(H, W, 3),
                   view_dirs=D.float().reshape(H, W, 3), camera_position=eye_t.float(),
                   sun_visibility=vis.reshape(H, W))
