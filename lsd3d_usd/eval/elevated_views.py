"""The elevated family of novel views: cameras above the road, looking down at the scene.

Every other evaluation camera stands near a lane at eye height, so roofs, the tops of façades
and the terrain seen from above are never measured. These views are (seeded):

- per height h in ``heights`` (metres above the ground point looked at), ``per_height`` views.
  View k of every height looks at the same target — a point drawn uniformly by arc length on
  the layout's drivable lanes (all lanes when none is drivable) — from the same first
  azimuth, so the heights differ by height (and pitch) rather than by which part of the scene
  they show. Pitch is uniform in ``pitch_deg`` (degrees below the horizon); the camera stands
  h / tan(pitch) back from the target, so its optical axis hits the target exactly.
  A camera outside the layout's XY bounds, inside a building footprint, or whose sight line
  to the target passes through a building (below its eave height +
  conditioning.elevated_sampling.ROOF_MARGIN_M) is redrawn (another azimuth and pitch, up to 50
  times): the view shows the target, not a wall next to the camera. If none fits, it takes
  the steepest pitch from the side of the layout's centre
  (inside the bounds for any layout wider than 2 h / tan(max pitch)).
- the scene's own Overview cameras (/World/Cameras/Overview/*, written by `generate`:
  views.scene_cameras), in their own group ``"overview"``, not in the nearest height bin:
  they frame the whole layout from 60-200 m (the Top one straight down), well above the
  highest bin, and mixing them in would make that bin's figures depend on the layout's size.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import UsdGeom

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry.polyline import point_at
from lsd3d_usd.conditioning.elevated_sampling import Obstacles, place
from lsd3d_usd.render.camera import Camera, from_usd, look_at

DEFAULT_HEIGHTS = (5.0, 15.0, 30.0)
DEFAULT_PITCH = (20.0, 60.0)
OVERVIEW = "overview"
OVERVIEW_PATH = f"{S.CAMERAS_PATH}/Overview"


@dataclass
class ElevatedView:
    camera: Camera
    group: str              # height bin key ("5", "15", ...) or "overview"
    name: str               # h<height>_<k>, or the Overview camera's prim name
    height_m: float         # above the ground point looked at (overview: above the lanes' median z)
    pitch_deg: float        # below the horizon
    nearest_train_m: float = float("nan")


def height_key(h: float) -> str:
    return f"{float(h):g}"


def parse_heights(text, where: str = "--heights") -> tuple[float, ...]:
    """'5,15,30' → (5.0, 15.0, 30.0): distinct positive heights in metres."""
    try:
        vals = tuple(float(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise InputError(f"{where} {text!r}: expected comma-separated metres, e.g. 5,15,30") from None
    if not vals:
        raise InputError(f"{where}: give at least one height")
    if any(not (np.isfinite(h) and 0 < h <= 10_000) for h in vals):
        raise InputError(f"{where} {text}: heights must be in (0, 10000] m")
    if len({height_key(h) for h in vals}) != len(vals):
        raise InputError(f"{where} {text}: heights must be distinct")
    return vals


def parse_pitch(text, where: str = "--pitch") -> tuple[float, float]:
    """'20,60' → (20.0, 60.0): a range of degrees below the horizon inside (0, 90)
    (straight down has no heading to look along)."""
    try:
        vals = tuple(float(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        vals = ()
    if len(vals) == 1:
        vals = vals * 2
    if len(vals) != 2 or not all(np.isfinite(vals)):
        raise InputError(f"{where} {text!r}: expected MIN,MAX degrees below the horizon, e.g. 20,60")
    lo, hi = vals
    if not (0 < lo <= hi < 90):
        raise InputError(f"{where} {text}: need 0 < MIN <= MAX < 90 degrees")
    return lo, hi


def _lane_targets(layout, n: int, rng) -> np.ndarray:
    """n points (n, 3) uniform by arc length over the drivable lanes (all lanes if none)."""
    lanes = [ln for ln in (layout.drivable_lanes() or layout.lanes) if ln.length() > 0]
    if not lanes:
        raise InputError("layout has no lanes: elevated views look at points on them")
    pts = [np.asarray(ln.points, np.float64) for ln in lanes]
    lengths = np.array([ln.length() for ln in lanes])
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    s = rng.uniform(0.0, cum[-1], n)
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(lanes) - 1)
    return np.array([point_at(pts[i], np.array([si - cum[i]]))[0] for i, si in zip(k, s)])


def elevated_views(layout, heights, per_height: int, pitch_deg, seed: int, width: int,
                   height: int, fov_deg: float, train_centres=None) -> list[ElevatedView]:
    """``per_height`` elevated views per height (module doc); ``train_centres`` (N, 3), if
    given, fills in each view's distance to the nearest training camera."""
    if per_height <= 0:
        return []
    rng = np.random.default_rng(seed)
    lo, hi = pitch_deg
    targets = _lane_targets(layout, per_height, rng)
    azimuths = rng.uniform(0.0, 2.0 * np.pi, per_height)
    obstacles = Obstacles(layout)
    out = []
    for h in heights:
        h = float(h)
        for k in range(per_height):
            tgt = targets[k]
            eye, _, pitch = place(rng, tgt, h, (lo, hi), obstacles, azimuths[k],
                                  rng.uniform(lo, hi))
            cam = Camera.from_fov(width, height, fov_deg, pose=look_at(eye, tgt), near=0.1,
                                  far=max(1000.0, 20.0 * h))
            out.append(ElevatedView(cam, height_key(h), f"h{height_key(h)}_{k}", h,
                                    float(pitch)))
    _nearest(out, train_centres)
    return out


def overview_views(stage, layout, width: int, height: int, train_centres=None) -> list[ElevatedView]:
    """The stage's cameras under /World/Cameras/Overview (none if it has no such prims), at
    width×height with their horizontal field of view."""
    root = stage.GetPrimAtPath(OVERVIEW_PATH)
    if not root or not root.IsValid():
        return []
    lanes = layout.drivable_lanes() or layout.lanes
    # the ground the overviews frame (views.scene_cameras.overview_cameras)
    ground = float(np.median(np.concatenate([ln.points[:, 2] for ln in lanes]))) if lanes else 0.0
    out = []
    for prim in root.GetChildren():
        if not prim.IsA(UsdGeom.Camera):
            continue
        cam = from_usd(prim, None, width, height)
        fwd = cam.pose[:3, 2]
        pitch = float(np.degrees(np.arcsin(np.clip(-fwd[2], -1.0, 1.0))))
        out.append(ElevatedView(cam, OVERVIEW, prim.GetName(), float(cam.center[2] - ground),
                                pitch))
    _nearest(out, train_centres)
    return out


def _nearest(views, train_centres) -> None:
    if train_centres is None or not len(train_centres):
        return
    c = np.asarray(train_centres, np.float64)
    for v in views:
        v.nearest_train_m = float(np.min(np.linalg.norm(c - v.camera.center, axis=1)))


def group_stats(views: list) -> dict:
    """Count and medians of one group's poses (as eval's novel_views.<d>)."""
    if not views:
        return {}
    med = lambda xs, d: round(float(np.median(xs)), d)   # noqa: E731
    return {"count": len(views), "height_m_median": med([v.height_m for v in views], 2),
            "pitch_deg_median": med([v.pitch_deg for v in views], 2),
            "nearest_train_m_median": med([v.nearest_train_m for v in views], 3)}
