"""The off-path family of novel views: the cameras a driving stack carries where it drives,
not where GGDS trained (eye height near lane centres).

A station is a point on a drivable lane (the lane graph's centre line, layout.routes.LaneGeom,
in its direction of travel) with the lane frame there: heading = the chord over ±1 m, left =
the heading turned +90°. Every bin places one camera per station, changing one thing from the
on-path camera (lane centre, 1.6 m above the centre line's point, looking along the heading,
level):

- ``lateral_<m>``: moved <m> metres to the left (negative: right) — 0, ±1.75 (half a lane),
  ±3.5 (a whole lane); height 1.6 m, yaw 0;
- ``height_<m>``: <m> metres above the centre line's point — 0.6 (a delivery robot), 1.6
  (a car), 3.0 (a truck); on the centre line, yaw 0;
- ``yaw_<deg>``: turned by <deg> degrees (+ = left) off the heading — ±15; on the centre
  line, 1.6 m high.

Keys are ``f"{prefix}_{value:g}"`` (``lateral_-1.75``, ``lateral_0``, ``height_3``,
``yaw_-15``). ``lateral_0`` and ``height_1.6`` are the same cameras (the on-path reference),
rendered once. The intrinsics are the simulator's: the ``nuscenes6`` rig's CAM_FRONT (its
horizontal field of view and aspect, sensors.camera.rig_camera) at eval's render width.

Stations (seeded) are spread over the GGDS run's regions (its plan's chunk sets; the whole
layout without a run): station k is drawn in region k mod n_regions, uniformly by arc length
over the lane centre line inside that region's chunks, at least END_MARGIN_M from the lane's
ends. A station where a camera of any bin would stand inside a building footprint is redrawn,
so every bin shows the same places.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lsd3d_usd.conditioning.view_sampling import building_paths, inside_paths
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.render.camera import Camera
from lsd3d_usd.sensors.camera import rig_camera
from lsd3d_usd.sensors.rigs import load_rig

LATERAL_M = (-3.5, -1.75, 0.0, 1.75, 3.5)
HEIGHTS_M = (0.6, 1.6, 3.0)
YAW_DEG = (15.0, -15.0)
ON_PATH_HEIGHT_M = 1.6
RIG, RIG_CAMERA = "nuscenes6", "CAM_FRONT"
END_MARGIN_M = 3.0
STEP_M = 1.0            # arc-length spacing of the candidate stations
TRIES = 50


def bin_key(prefix: str, value: float) -> str:
    return f"{prefix}_{float(value):g}"


def bin_poses() -> dict[str, tuple[float, float, float]]:
    """Bin key -> (lateral m, height m, yaw deg) of its cameras in the lane frame."""
    out = {bin_key("lateral", v): (v, ON_PATH_HEIGHT_M, 0.0) for v in LATERAL_M}
    out.update({bin_key("height", h): (0.0, h, 0.0) for h in HEIGHTS_M})
    out.update({bin_key("yaw", y): (0.0, ON_PATH_HEIGHT_M, y) for y in YAW_DEG})
    return out


@dataclass
class OffPathView:
    camera: Camera
    station: int
    lane: str
    s_m: float
    lateral_m: float
    height_m: float
    yaw_deg: float


@dataclass
class OffPathSet:
    views: list                 # OffPathView, one per distinct pose and station
    bins: dict                  # bin key -> indices into views (station order)
    regions: int                # regions the stations were spread over
    stations: int = 0


def lane_frame(geom, s: float) -> tuple[np.ndarray, float]:
    """(centre-line point (3,), heading in radians) of a lane at arc length s."""
    return np.asarray(geom.point(s), np.float64), float(geom.heading(s))


def camera_at(point, heading: float, lateral: float, height: float, yaw_deg: float,
              width: int) -> Camera:
    """The rig camera (nuscenes6 CAM_FRONT intrinsics) ``lateral`` m left of ``point`` across
    the lane, ``height`` m above it, turned ``yaw_deg`` off ``heading``, level."""
    model = replace(load_rig(RIG).camera(RIG_CAMERA), mount=(0.0, 0.0, float(height)),
                    yaw_deg=float(yaw_deg), pitch_deg=0.0)
    c, s = np.cos(heading), np.sin(heading)
    ego = np.eye(4)
    ego[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    ego[:3, 3] = np.asarray(point, np.float64) + lateral * np.array([-s, c, 0.0])
    return rig_camera(model, ego, width)


def _regions(regions) -> list:
    """Chunk-key sets of the regions (None: the whole layout)."""
    if not regions:
        return [None]
    return [{tuple(int(v) for v in k) for k in keys} for keys in regions]


def _candidates(graph: LaneGraph, size: float, region) -> list[tuple[int, float]]:
    out = []
    for i, g in enumerate(graph.geoms):
        if g.length <= 2 * END_MARGIN_M:
            continue
        s = np.arange(END_MARGIN_M, g.length - END_MARGIN_M + 1e-9, STEP_M)
        if region is not None:
            p = g.point(s)
            keys = zip(np.floor(p[:, 0] / size).astype(int), np.floor(p[:, 1] / size).astype(int))
            s = s[[k in region for k in keys]]
        out += [(i, float(v)) for v in s]
    return out


def off_path_views(layout, per_bin: int, width: int, seed: int, regions=None) -> OffPathSet:
    """``per_bin`` stations (module doc) and every bin's camera at each. ``regions``: the GGDS
    run's regions as lists of chunk keys (None: the whole layout is one)."""
    if per_bin <= 0:
        return OffPathSet([], {k: [] for k in bin_poses()}, 0, 0)
    graph = LaneGraph(layout)
    if not len(graph):
        raise InputError("layout has no drivable lanes: the off-path views stand on them")
    regs = _regions(regions)
    cands = [_candidates(graph, float(layout.chunk_size), r) for r in regs]
    cands = [c for c in cands if c] or [_candidates(graph, float(layout.chunk_size), None)]
    if not cands[0]:
        raise InputError(f"layout has no drivable lane longer than {2 * END_MARGIN_M:g} m: the "
                         "off-path views stand on one")
    rng = np.random.default_rng(seed)
    fps = building_paths(layout)
    poses = bin_poses()
    distinct = list(dict.fromkeys(poses.values()))
    views, bins = [], {k: [] for k in poses}
    for k in range(per_bin):
        pool = cands[k % len(cands)]
        for _ in range(TRIES):
            lane, s = pool[int(rng.integers(len(pool)))]
            p, h = lane_frame(graph.geoms[lane], s)
            cams = [camera_at(p, h, lat, z, yaw, width) for lat, z, yaw in distinct]
            if not any(inside_paths(c.center, fps) for c in cams):
                break
        index = {}
        for pose, cam in zip(distinct, cams):
            index[pose] = len(views)
            views.append(OffPathView(cam, k, graph.ids[lane], round(s, 3), *pose))
        for key, pose in poses.items():
            bins[key].append(index[pose])
    return OffPathSet(views, bins, len(cands), per_bin)


def run_regions(sc, run: str | None) -> list | None:
    """The chunk keys of each region of GGDS run ``run`` (its plan), or None (one region:
    the whole layout) without a run or a readable plan."""
    if run is None:
        return None
    # local import: not loaded for --help
    from lsd3d_usd.ggds.run.store import read_plan
    try:
        regions = read_plan(sc, run).get("regions") or {}
    except InputError:
        return None
    return [keys for keys in regions.values() if keys] or None
