"""Training and held-out cameras for GGDS: along the layout's lanes at driving height with
lateral and heading jitter, plus novel positions off the lanes so the optimised scene is
supervised beyond the driven lines.

Off-lane views ("novel"), two styles:
  "displaced": a lane view moved by d metres (d log-uniform in [0.5, novel_max_m]) in a
      uniformly random horizontal direction of its own frame, with a vertical part uniform in
      [-min(0.25 d, 0.5), 0.25 d] and its heading turned by up to ±min(7.5°·d, 45°); positions
      inside a building footprint are redrawn. These are the positions `eval` calls novel
      (eval/lane_views.novel_views draws its distance bins 0.5-8 m the same way), so the surfaces
      such views see get supervised.
  "lane_offset": beside a lane, 0.5-5 m beyond its edge, free heading (±60°, turned round
      15 % of the time), eye height 1.2-3 m (the earlier sampler).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, look_at

NOVEL_STYLES = ("displaced", "lane_offset")
MAX_DROP_M = 0.5           # displaced views never sink more than this below the lane view
HEADING_DEG_PER_M = 7.5    # displaced views turn by up to this per metre moved ...
MAX_HEADING_DEG = 45.0     # ... and at most this


@dataclass
class View:
    camera: Camera
    kind: str          # "lane" | "novel" | "held_out" | "elevated" (conditioning.elevated_sampling)
    lane_id: str
    offset_m: float    # lateral distance from the lane centreline; elevated: height above
                       # the point looked at

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


def lane_length_inside(layout, box, step: float = 0.5) -> float:
    """Metres of drivable lane inside ``box`` (x0, y0, x1, y1), to ``step``, over the lanes
    sample_views(region=box, clip=True) draws from (_lanes: those with a vertex inside):
    what such views spread over; 0 when there are none."""
    try:
        lanes = _lanes(layout, box)
    except InputError:
        return 0.0
    return step * float(sum(len(a) for a in _inside_arcs(lanes, box, step)))


def _strata(rng: np.random.Generator, n: int, lengths: np.ndarray) -> list[tuple[int, float]]:
    """n (lane index, fraction along it) points, one in each of n equal parts of the lanes'
    concatenated length, in random order."""
    if n <= 0:
        return []
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    u = (rng.permutation(n) + rng.uniform(size=n)) / n * cum[-1]
    li = np.clip(np.searchsorted(cum, u, side="right") - 1, 0, len(lengths) - 1)
    f = np.clip((u - cum[li]) / np.maximum(lengths[li], 1e-12), 0.0, 1.0 - 1e-9)
    return [(int(a), float(b)) for a, b in zip(li, f)]


def building_paths(layout) -> list:
    """(footprint path, XY min, XY max) per building of ``layout`` (inside_paths tests them)."""
    # local import: not loaded for --help
    from matplotlib.path import Path as MPath
    out = []
    for b in getattr(layout, "buildings", None) or []:
        fp = np.asarray(b.footprint, np.float64)[:, :2]
        out.append((MPath(fp), fp.min(axis=0), fp.max(axis=0)))
    return out


def inside_paths(p, paths) -> bool:
    """Whether point ``p``'s XY lies inside one of ``paths`` (building_paths)."""
    return any(np.all(p[:2] >= lo) and np.all(p[:2] <= hi) and path.contains_point(p[:2])
               for path, lo, hi in paths)


def displace(rng: np.random.Generator, eye: np.ndarray, fwd2: np.ndarray, d: float, paths=(),
             tries: int = 50) -> tuple[np.ndarray, float]:
    """(new eye, yaw change in radians) of a view at ``eye`` looking along the horizontal unit
    vector ``fwd2`` moved by exactly ``d`` metres as module doc "displaced" says."""
    left = np.array([-fwd2[1], fwd2[0]])
    for _ in range(tries):
        dz = rng.uniform(-min(0.25 * d, MAX_DROP_M), 0.25 * d)
        horiz = np.sqrt(max(d * d - dz * dz, 0.0))
        phi = rng.uniform(0.0, 2.0 * np.pi)
        xy = horiz * (np.cos(phi) * fwd2 + np.sin(phi) * left)
        new = eye + np.array([xy[0], xy[1], dz])
        if not inside_paths(new, paths):
            break
    max_yaw = np.radians(min(HEADING_DEG_PER_M * d, MAX_HEADING_DEG))
    return new, float(rng.uniform(-max_yaw, max_yaw))


def sample_views(layout, n: int, width: int, height: int, *, seed: int = 0, fov_deg: float = 70.0,
                 eye_height: float = 1.6, lateral_jitter: float = 0.5, heading_jitter_deg: float = 8.0,
                 pitch_deg: float = -4.0, novel_frac: float = 0.25, region=None, clip: bool = False,
                 kind_lane: str = "lane", kind_novel: str = "novel", far: float = 400.0,
                 novel_style: str = "lane_offset", novel_max_m: float = 8.0,
                 stratified: bool = False) -> list[View]:
    """`n` views: round(n·novel_frac) off the lanes (module doc, ``novel_style``), the rest
    along lanes (driving direction, small lateral and heading jitter). Deterministic per
    seed. A "displaced" view's offset_m is its distance from the lane view it was moved
    from. region (x0, y0, x1, y1): only lanes that pass through it; with ``clip`` the views'
    lane points themselves lie inside it (chunk-wise GGDS: views of the chunk being
    optimised). Lane points are drawn independently, or with ``stratified`` one in each of
    n equal parts of the lanes' total length (lane and off-lane views each): no stretch of
    lane is left without views by chance."""
    if n <= 0:
        return []
    if novel_style not in NOVEL_STYLES:
        raise InputError(f"novel_style {novel_style!r}: choose one of {', '.join(NOVEL_STYLES)}")
    if not novel_max_m >= 0.5:
        raise InputError(f"novel_max_m must be >= 0.5 m, got {novel_max_m}")
    rng = np.random.default_rng(seed)
    paths = building_paths(layout) if novel_style == "displaced" else ()
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
    strata = (_strata(rng, n - n_novel, lengths) + _strata(rng, n_novel, lengths)
              if stratified else None)
    for i in range(n):
        novel = i >= n - n_novel
        li = int(rng.choice(len(lanes), p=prob)) if strata is None else strata[i][0]
        lane = lanes[li]
        if arcs is None:
            s0 = rng.uniform(0, lane.length()) if strata is None else strata[i][1] * lane.length()
            p, t = _point_on(lane.points, s0)
        else:   # a sampled inside point, jittered within its half-metre step
            k = (int(rng.integers(len(arcs[li]))) if strata is None
                 else min(int(strata[i][1] * len(arcs[li])), len(arcs[li]) - 1))
            p, t = _point_on(lane.points, arcs[li][k] + rng.uniform(0.0, 0.5))
        if lane.direction == "backward":
            t = -t
        t2 = np.array([t[0], t[1]]) / max(np.hypot(t[0], t[1]), 1e-12)
        left = np.array([-t2[1], t2[0]])
        width_here = float(np.median(lane.widths)) if len(lane.widths) else 3.5
        if novel and novel_style == "lane_offset":
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
        if novel and novel_style == "displaced":
            d = float(np.exp(rng.uniform(np.log(0.5), np.log(novel_max_m))))
            eye, dyaw = displace(rng, eye, fwd2, d, paths)
            c, s = np.cos(dyaw), np.sin(dyaw)
            fwd2 = np.array([c * fwd2[0] - s * fwd2[1], s * fwd2[0] + c * fwd2[1]])
            offset = d
        pitch = np.radians(pitch_deg)
        target = eye + np.array([fwd2[0] * np.cos(pitch), fwd2[1] * np.cos(pitch), np.sin(pitch)])
        cam = Camera.from_fov(width, height, fov_deg, pose=look_at(eye, target), near=0.1, far=far)
        views.append(View(cam, kind_novel if novel else kind_lane, lane.id, float(offset)))
    return views


