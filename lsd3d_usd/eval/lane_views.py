"""Evaluation cameras: the seen views (the cameras a GGDS run trained on, from its layer's
provenance), novel views displaced from them at increasing distances, and a smooth
trajectory along a lane for temporal consistency.

Novel views (seeded): for distance bin d (metres), novel view k is seen view k mod n_seen whose
centre moves by d in a random direction of its own frame — uniform
heading on the ground plane (longitudinal/lateral mix), a vertical part uniform in
[-min(0.25 d, 0.5 m), +0.25 d] (cameras never sink more than 0.5 m) — and its heading turns by
a uniform angle in ±min(7.5°·d/m, 45°). Candidates whose centre falls inside a building
footprint of the layout are redrawn. Each novel view records its bin, source view, the
displacement, the yaw change and its distance to the nearest training camera (which can be
smaller than d: another training camera may lie nearby).
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from pxr import Sdf

from lsd3d_usd import scene as S
from lsd3d_usd.conditioning.view_sampling import View, building_paths, inside_paths, sample_views
from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry.polyline import point_at
from lsd3d_usd.ggds.settings import GGDSConfig
from lsd3d_usd.render.camera import Camera, look_at

DEFAULT_BINS = (0.5, 1.0, 2.0, 4.0, 8.0)
HEADING_DEG_PER_M = 7.5
MAX_HEADING_DEG = 45.0
MAX_DROP_M = 0.5
# GGDS's camera sampler defaults, used for scenes without a run.
GGDS_FOV_DEG = GGDSConfig().fov_deg
GGDS_NOVEL_FRAC = GGDSConfig().novel_frac
GGDS_N_VIEWS = GGDSConfig().views


@dataclass
class SeenSet:
    views: list            # all training views (View), at the eval resolution
    run: str | None        # GGDS run layer name, None when sampled
    source: str            # human-readable: where the views came from


@dataclass
class NovelView:
    view: View
    bin_m: float
    source: int            # index into the source (seen) views
    displacement: np.ndarray   # world (3,)
    yaw_deg: float
    nearest_train_m: float


def seen_views(sc: S.Scene, layout, run: str | None, width: int, height: int) -> SeenSet:
    """The training cameras of `run` (default: the newest unmuted GGDS run) rescaled to
    width×height (same field of view). A scene without any GGDS run gets the views GGDS would
    have sampled with the scene's seed and the default GGDS camera settings (and says so)."""
    runs = sc.runs()
    if run is not None:
        match = [li for li in runs if run in (li.name, li.path.name)]
        if not match:
            names = ", ".join(li.name for li in runs) or "none"
            raise InputError(f"{sc.root}: no GGDS run {run!r} (runs: {names})")
        info = match[0]
    else:
        active = [li for li in runs if not li.muted and li.exists]
        info = active[0] if active else None
    if info is None:
        seed = scene_seed(sc)
        n = GGDS_N_VIEWS
        views = sample_views(layout, n, width, height, seed=seed, novel_frac=GGDS_NOVEL_FRAC,
                             fov_deg=GGDS_FOV_DEG)
        return SeenSet(views, None, f"no GGDS run in the scene: {n} views sampled as GGDS would "
                                    f"(sample_views, scene seed {seed}, fov {GGDS_FOV_DEG:g} deg)")
    if not info.exists:
        raise InputError(f"{info.path}: GGDS run layer file is missing")
    # local import: not loaded for --help
    from lsd3d_usd.ggds.run.store import run_views
    raw = run_views(sc, info.name)      # ggds/<run>/**/views.json
    if raw is None:                     # older runs: in the layer's provenance
        raw = info.provenance.get("trainViews")
        raw = json.loads(raw) if isinstance(raw, str) else raw
    if not raw:
        raise InputError(f"{info.path}: the run records no training views (ggds/{info.name}/"
                         "views.json or customLayerData lsd3d.trainViews): cannot tell which "
                         "cameras it trained on")
    try:
        views = [View.from_json(d) for d in raw]
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(f"{info.path}: the run's training views are not a list of views "
                         f"({e})") from None
    views = [View(v.camera.with_resolution(width, height), v.kind, v.lane_id, v.offset_m)
             for v in views]
    muted = " (muted: its edits are not in the rendered stage)" if info.muted else ""
    return SeenSet(views, info.name, f"training cameras of GGDS run {info.name}{muted}")


def scene_seed(sc: S.Scene) -> int:
    layer = Sdf.Layer.FindOrOpen(str(sc.root_layer_path))
    prim = layer.GetPrimAtPath(S.WORLD) if layer else None
    attr = prim.attributes.get("lsd3d:scene:seed") if prim else None
    return int(attr.default) if attr is not None and attr.default is not None else 0


def pick(n_total: int, n: int, seed: int) -> np.ndarray:
    """A seeded subset of n indices (all, in order, when n >= n_total)."""
    if n >= n_total:
        return np.arange(n_total)
    return np.sort(np.random.default_rng(seed).choice(n_total, n, replace=False))


def _yawed_pose(pose: np.ndarray, centre: np.ndarray, yaw: float) -> np.ndarray:
    """`pose` turned by `yaw` (radians, about world Z) and moved to `centre`."""
    c, s = np.cos(yaw), np.sin(yaw)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = np.eye(4)
    out[:3, :3] = rz @ pose[:3, :3]
    out[:3, 3] = centre
    return out


def novel_views(sources: list, bins, per_bin: int, seed: int, layout=None,
                train_centres=None) -> list[NovelView]:
    """`per_bin` novel views per distance bin. View k of every bin is displaced from
    sources[k % len(sources)], so each bin has the same mix of source views as the seen set
    (the bins then differ by displacement only, not by which part of the scene they show).
    `train_centres` (default: the sources') is what nearest_train_m measures against."""
    if not sources:
        raise InputError("novel views need at least one source view")
    rng = np.random.default_rng(seed)
    centres = np.asarray(train_centres if train_centres is not None
                         else [v.camera.center for v in sources], np.float64)
    fps = building_paths(layout) if layout is not None else []
    out = []
    for d in bins:
        d = float(d)
        if not d > 0:
            raise InputError(f"--bins: distances must be positive, got {d:g}")
        max_yaw = np.radians(min(HEADING_DEG_PER_M * d, MAX_HEADING_DEG))
        for k in range(per_bin):
            src = k % len(sources)
            cam = sources[src].camera
            fwd = cam.pose[:3, 2].copy()
            fwd[2] = 0.0
            fwd /= max(np.linalg.norm(fwd), 1e-12)
            left = np.array([-fwd[1], fwd[0], 0.0])
            for _attempt in range(50):   # redraw the direction while inside a building
                dz = rng.uniform(-min(0.25 * d, MAX_DROP_M), 0.25 * d)
                horiz = np.sqrt(max(d * d - dz * dz, 0.0))
                phi = rng.uniform(0.0, 2.0 * np.pi)
                disp = horiz * (np.cos(phi) * fwd + np.sin(phi) * left) + np.array([0.0, 0.0, dz])
                centre = cam.center + disp
                if not inside_paths(centre, fps):
                    break
            yaw = rng.uniform(-max_yaw, max_yaw)
            new = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                         _yawed_pose(cam.pose, centre, yaw), cam.near, cam.far)
            near = float(np.min(np.linalg.norm(centres - centre, axis=1)))
            out.append(NovelView(View(new, "eval_novel", sources[src].lane_id,
                                      float(np.dot(disp, left))), d, src, disp,
                                 float(np.degrees(yaw)), near))
    return out


def fov_of(like: list) -> float:
    """Horizontal field of view in degrees of ``like[0]`` (GGDS's default without views)."""
    if not like:
        return GGDS_FOV_DEG
    c = like[0].camera
    return float(np.degrees(2.0 * np.arctan(0.5 * c.width / c.fx)))


def heldout_lane_views(layout, n: int, width: int, height: int, seed: int, like: list) -> list:
    """`n` fresh on-lane cameras (GGDS's lane sampler, another seed, no off-lane views) with
    the intrinsics of `like[0]`: views of other places in the scene, from the same kind of
    position as training. Their Fréchet distance to the seen views is the reference for how
    much FD a mere change of content gives at the same sample counts."""
    if n <= 0:
        return []
    views = sample_views(layout, n, width, height, seed=seed + 104729, novel_frac=0.0,
                         fov_deg=fov_of(like))
    return [v.camera for v in views]


# ------------------------------------------------------------------ trajectory
def lane_trajectory(layout, n_frames: int, step_m: float, width: int, height: int, *,
                    fov_deg: float = GGDS_FOV_DEG, eye_height: float = 1.6, pitch_deg: float = -4.0,
                    look_ahead_m: float = 4.0) -> tuple[list[Camera], dict]:
    """Cameras driving along the longest drivable lane (its direction of travel), `step_m`
    apart, at eye height, heading along the lane tangent smoothed over ±look_ahead_m: a
    smooth path with known poses. Centred on the lane's middle when the lane is longer."""
    lanes = layout.drivable_lanes()
    if not lanes:
        raise InputError("layout has no drivable lanes: the temporal check drives along one")
    lane = max(lanes, key=lambda ln: ln.length())
    pts = np.asarray(lane.points, np.float64)
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.zeros((len(pts), 1))], axis=1)
    if lane.direction == "backward":
        pts = pts[::-1]
    L = lane.length()
    span = step_m * (n_frames - 1)
    s0 = max(0.5 * (L - span), 0.0)
    s = s0 + step_m * np.arange(n_frames)
    p = point_at(pts, s)
    ahead = point_at(pts, s + look_ahead_m) - point_at(pts, s - look_ahead_m)
    cams = []
    pitch = np.radians(pitch_deg)
    for i in range(n_frames):
        t = ahead[i, :2] / max(np.linalg.norm(ahead[i, :2]), 1e-12)
        eye = p[i] + np.array([0.0, 0.0, eye_height])
        target = eye + np.array([t[0] * np.cos(pitch), t[1] * np.cos(pitch), np.sin(pitch)])
        cams.append(Camera.from_fov(width, height, fov_deg, pose=look_at(eye, target), near=0.1,
                                    far=400.0))
    info = {"lane": lane.id, "lane_length_m": round(float(L), 2), "frames": n_frames,
            "step_m": step_m, "path_m": round(float(min(span, L)), 2)}
    return cams, info
