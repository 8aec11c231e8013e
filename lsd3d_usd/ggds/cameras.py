"""Training and held-out cameras for GGDS: along the layout's lanes at driving height with
lateral and heading jitter, plus novel positions off the lanes (sidewalks, lane changes,
higher mounts) so the optimised scene is supervised beyond the driven lines."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, look_at


@dataclass
class View:
    camera: Camera
    kind: str          # "lane" | "novel" | "held_out"
    lane_id: str
    offset_m: float    # lateral distance from the lane centreline

    def to_json(self) -> dict:
        c = self.camera
        return {"kind": self.kind, "lane": self.lane_id, "offset_m": round(self.offset_m, 3),
                "pose": [round(float(v), 6) for v in c.pose.reshape(-1)],
                "intrinsics": [c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.near, c.far]}

    @classmethod
    def from_json(cls, d: dict) -> "View":
        w, h, fx, fy, cx, cy, near, far = d["intrinsics"]
        cam = Camera(int(w), int(h), fx, fy, cx, cy, np.array(d["pose"]).reshape(4, 4), near, far)
        return cls(cam, d["kind"], d["lane"], d["offset_m"])


def _lanes(layout, region=None):
    lanes = layout.drivable_lanes()
    if region is not None:
        x0, y0, x1, y1 = region
        lanes = [ln for ln in lanes if np.any((ln.points[:, 0] >= x0) & (ln.points[:, 0] <= x1)
                                              & (ln.points[:, 1] >= y0) & (ln.points[:, 1] <= y1))]
    if not lanes:
        where = f" inside {region}" if region is not None else ""
        raise InputError(f"layout has no drivable lanes{where}: GGDS samples its cameras along lanes")
    return lanes


def _point_on(points: np.ndarray, s: float):
    seg = np.diff(points, axis=0)
    length = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    s = float(np.clip(s, 0.0, cum[-1]))
    k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    f = (s - cum[k]) / max(length[k], 1e-12)
    p = points[k] + f * seg[k]
    t = seg[k] / max(length[k], 1e-12)
    return p, t


def _inside_arcs(lanes, region, step: float = 0.5):
    """Per lane, the arc lengths (sampled every ``step`` m) whose point lies in ``region``."""
    x0, y0, x1, y1 = region
    out = []
    for ln in lanes:
        pts = ln.points[:, :2]
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        s = np.arange(0.0, cum[-1] + 1e-9, step)
        x, y = np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])
        out.append(s[(x >= x0) & (x < x1) & (y >= y0) & (y < y1)])
    return out


def sample_views(layout, n: int, width: int, height: int, *, seed: int = 0, fov_deg: float = 70.0,
                 eye_height: float = 1.6, lateral_jitter: float = 0.5, heading_jitter_deg: float = 8.0,
                 pitch_deg: float = -4.0, novel_frac: float = 0.25, region=None, clip: bool = False,
                 kind_lane: str = "lane", kind_novel: str = "novel", far: float = 400.0) -> list[View]:
    """`n` views: (1-novel_frac) along lanes (driving direction, small jitter) and novel_frac
    off the lanes (larger offsets, free headings, eye heights 1.2-3 m). Deterministic per seed.
    region (x0, y0, x1, y1): only lanes that pass through it; with ``clip`` the views' lane
    points themselves lie inside it (chunk-wise GGDS: views of the chunk being optimised)."""
    if n <= 0:
        return []
    rng = np.random.default_rng(seed)
    lanes = _lanes(layout, region)
    if clip and region is not None:
        arcs = _inside_arcs(lanes, region)
        lengths = np.array([float(len(a)) for a in arcs])
        if not lengths.sum():
            raise InputError(f"layout has no drivable lane points inside {region}: GGDS samples "
                             "its cameras along lanes")
    else:
        arcs = None
        lengths = np.array([max(ln.length(), 1e-6) for ln in lanes])
    prob = lengths / lengths.sum()
    views = []
    n_novel = int(round(n * novel_frac))
    for i in range(n):
        novel = i >= n - n_novel
        li = int(rng.choice(len(lanes), p=prob))
        lane = lanes[li]
        if arcs is None:
            p, t = _point_on(lane.points, rng.uniform(0, lane.length()))
        else:   # a sampled inside point, jittered within its half-metre step
            s0 = arcs[li][int(rng.integers(len(arcs[li])))]
            p, t = _point_on(lane.points, s0 + rng.uniform(0.0, 0.5))
        if lane.direction == "backward":
            t = -t
        t2 = np.array([t[0], t[1]]) / max(np.hypot(t[0], t[1]), 1e-12)
        left = np.array([-t2[1], t2[0]])
        width_here = float(np.median(lane.widths)) if len(lane.widths) else 3.5
        if novel:
            offset = rng.choice([-1.0, 1.0]) * rng.uniform(0.5 * width_here, 0.5 * width_here + 5.0)
            yaw = np.radians(rng.uniform(-60.0, 60.0)) + (np.pi if rng.uniform() < 0.15 else 0.0)
            h = rng.uniform(1.2, 3.0)
        else:
            offset = rng.normal(0.0, lateral_jitter)
            yaw = np.radians(rng.normal(0.0, heading_jitter_deg))
            h = eye_height
        c, s = np.cos(yaw), np.sin(yaw)
        fwd2 = np.array([c * t2[0] - s * t2[1], s * t2[0] + c * t2[1]])
        eye = np.array([p[0] + offset * left[0], p[1] + offset * left[1], p[2] + h])
        pitch = np.radians(pitch_deg)
        target = eye + np.array([fwd2[0] * np.cos(pitch), fwd2[1] * np.cos(pitch), np.sin(pitch)])
        cam = Camera.from_fov(width, height, fov_deg, pose=look_at(eye, target), near=0.1, far=far)
        views.append(View(cam, kind_novel if novel else kind_lane, lane.id, float(offset)))
    return views

