"""Cameras above the road, looking down at it: GGDS's elevated views (the colour start fits
to them; the steps train on them with ``ggds.elevated_train``) and the placement eval's
elevated family shares with them.

A drone, a chase camera or a scene's own Overview cameras see roofs, the tops of façades and
the terrain from above, which views at eye height along the lanes never do; a scene trained on
those alone has nothing to fit there. ``sample_elevated_views`` gives GGDS (seeded):

- "over a lane": a target drawn one per equal part of the lanes' length (clipped to a chunk
  region as sample_views clips), seen from a height log-uniform in ``heights`` above it,
  ``pitch_deg`` below the horizon, from a uniform azimuth; the camera stands h / tan(pitch)
  back, so its optical axis hits the target. A camera outside the layout, inside a building
  footprint or whose sight line passes through a building (below eave + ROOF_MARGIN_M) is
  redrawn (``place``), as eval's are.
- "framing the layout" (whole-scene runs only, ``overview_frac`` of them): a point near the
  layout's centre seen from 30-80° above the horizon at 0.6-1.1 × the distance that frames the
  layout's diagonal, the way the scene's Overview cameras (views.scene_cameras) stand, but at
  drawn azimuths, elevations and distances rather than those five poses.
"""
from __future__ import annotations

import numpy as np

from lsd3d_usd.conditioning.view_sampling import (View, _inside_arcs, _lanes, _point_on, _strata,
                                          building_paths, inside_paths)
from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, look_at

ELEVATED = "elevated"              # View.kind of these views
ROOF_MARGIN_M = 3.0     # parapets and pitched roofs rise above the eave height (proxy.buildings)
SIGHT_SAMPLES = 24
ATTEMPTS = 50
FRAME_ELEVATION_DEG = (30.0, 80.0)
FRAME_DISTANCE = (0.6, 1.1)        # × the distance at which the layout's diagonal fills the view
FRAME_JITTER = 0.25                # target within ± this × the layout's extent of its centre


class Obstacles:
    """What a camera above the layout must not stand in or look through: the layout's XY
    bounds and its buildings up to their eave height + ROOF_MARGIN_M."""

    def __init__(self, layout):
        (self.x0, self.y0), (self.x1, self.y1) = layout.bounds()
        self.centre = np.array([(self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2])
        buildings = getattr(layout, "buildings", None) or []
        self.paths = building_paths(layout)
        self.tops = [float(np.min(np.asarray(b.footprint)[:, 2])) + b.height_hint + ROOF_MARGIN_M
                     for b in buildings]

    def clear(self, eye, target) -> bool:
        if not (self.x0 <= eye[0] <= self.x1 and self.y0 <= eye[1] <= self.y1):
            return False
        if inside_paths(eye, self.paths):
            return False
        for s in np.linspace(0.0, 1.0, SIGHT_SAMPLES, endpoint=False)[1:]:
            p = eye + s * (target - eye)
            if any(p[2] < top and inside_paths(p, [path])
                   for path, top in zip(self.paths, self.tops)):
                return False
        return True


def eye_at(target, h: float, pitch_deg: float, az: float) -> np.ndarray:
    """The camera h metres above ``target`` looking at it ``pitch_deg`` below the horizon from
    azimuth ``az`` (radians: the direction the camera looks along)."""
    back = h / np.tan(np.radians(pitch_deg))
    return target + np.array([-back * np.cos(az), -back * np.sin(az), h])


def place(rng, target, h: float, pitch_range, obstacles: Obstacles, az: float,
          pitch: float) -> tuple[np.ndarray, float, float]:
    """(eye, azimuth, pitch) of a camera h above ``target``, first tried at (az, pitch), redrawn
    (uniform azimuth, pitch in ``pitch_range``) up to ATTEMPTS times while it is not
    ``obstacles.clear``; else the steepest pitch from the layout centre's side of the target."""
    lo, hi = pitch_range
    eye = eye_at(target, h, pitch, az)
    for _attempt in range(ATTEMPTS):
        if obstacles.clear(eye, target):
            return eye, az, pitch
        az, pitch = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(lo, hi)
        eye = eye_at(target, h, pitch, az)
    d = target[:2] - obstacles.centre
    az = float(np.arctan2(d[1], d[0])) if np.hypot(*d) > 1e-9 else 0.0
    return eye_at(target, h, hi, az), az, hi


def sample_elevated_views(layout, n: int, width: int, height: int, *, seed: int,
                          fov_deg: float = 70.0, heights=(4.0, 40.0), pitch_deg=(25.0, 70.0),
                          overview_frac: float = 0.0, region=None, clip: bool = False,
                          far: float = 1000.0) -> list[View]:
    """``n`` elevated views (module doc), kind ELEVATED; ``offset_m`` is the camera's height
    above the point it looks at. ``region``/``clip`` select lanes as sample_views does; views
    framing the layout (round(n · overview_frac)) only when ``clip`` is off."""
    if n <= 0:
        return []
    rng = np.random.default_rng(seed)
    lanes = _lanes(layout, region)
    n_frame = 0 if clip else int(round(n * overview_frac))
    if clip and region is not None:
        arcs = _inside_arcs(lanes, region)
        lengths = np.array([float(len(a)) for a in arcs])
        if lengths.sum() <= 0:
            raise InputError(f"elevated views: no drivable lane inside the region {region}")
    else:
        arcs = None
        lengths = np.array([max(ln.length(), 1e-6) for ln in lanes])
    obstacles = Obstacles(layout)
    (h_lo, h_hi), (p_lo, p_hi) = heights, pitch_deg
    views = []
    for li, f in _strata(rng, n - n_frame, lengths):
        lane = lanes[li]
        if arcs is None:
            s = f * lane.length()
        else:
            k = min(int(f * len(arcs[li])), len(arcs[li]) - 1)
            s = arcs[li][k] + rng.uniform(0.0, 0.5)
        target, _ = _point_on(lane.points, s)
        h = float(np.exp(rng.uniform(np.log(h_lo), np.log(h_hi))))
        eye, _, _ = place(rng, target, h, (p_lo, p_hi), obstacles, rng.uniform(0.0, 2.0 * np.pi),
                          rng.uniform(p_lo, p_hi))
        cam = Camera.from_fov(width, height, fov_deg, pose=look_at(eye, target), near=0.1,
                              far=max(far, 20.0 * h))
        views.append(View(cam, ELEVATED, lane.id, h))
    if n_frame:
        z = float(np.median(np.concatenate([ln.points[:, 2] for ln in lanes])))
        ext = np.array([obstacles.x1 - obstacles.x0, obstacles.y1 - obstacles.y0])
        fill = 0.55 * float(np.hypot(*np.maximum(ext, 1.0))) / np.tan(np.radians(fov_deg) / 2)
        for _ in range(n_frame):
            target = np.append(obstacles.centre + rng.uniform(-FRAME_JITTER, FRAME_JITTER, 2) * ext,
                               z)
            d = fill * rng.uniform(*FRAME_DISTANCE)
            el, az = np.radians(rng.uniform(*FRAME_ELEVATION_DEG)), rng.uniform(0.0, 2.0 * np.pi)
            eye = target + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                         np.sin(el)])
            cam = Camera.from_fov(width, height, fov_deg, pose=look_at(eye, target), near=0.5,
                                  far=max(far, 4.0 * d))
            views.append(View(cam, ELEVATED, "", float(eye[2] - z)))
    return views
