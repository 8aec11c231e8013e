"""The cameras of a generated scene (`layers/cameras.usda`): GGDS's training and held-out
views and a few overviews as UsdGeom.Camera prims under /World/Cameras, so usdview, `render
--camera` and any USD tool can look through them::

    /World/Cameras/Train/Train_<k>        the views GGDS samples for training
                                          (ggds.regions.region_views.region_views), region by region in
                                          region-name order; a chunk region trains on those
                                          that see its surfels, as the run records them
                                          (ggds/<run>/[<region>/]views.json)
    /World/Cameras/HeldOut/HeldOut_<k>    the held-out views its metrics are measured from
    /World/Cameras/Overview/Top           straight down over the layout, north up
    /World/Cameras/Overview/<SouthWest|SouthEast|NorthEast|NorthWest>
                                          35 degrees down from each corner, framing the layout

Each camera carries ``lsd3d:camera:kind`` (lane | novel | elevated | overview) and, for the
GGDS views, ``lsd3d:camera:lane`` (the lane it was sampled along; "" for an elevated view
framing the whole layout) and ``lsd3d:camera:region`` (the GGDS
region: "" for the whole scene, else chunk_<i>_<j>).
"""
from __future__ import annotations

import numpy as np
from pxr import Sdf, UsdGeom

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.regions.plan import plan_regions
from lsd3d_usd.ggds.regions.region_views import region_views
from lsd3d_usd.hashing import content_hash
from lsd3d_usd.render.camera import Camera, look_at, to_usd
from lsd3d_usd.splats.chunkio import read_chunk_map

OVERVIEW_SIZE = (960, 540)
OVERVIEW_FOV_DEG = 60.0
OVERVIEW_ELEVATION_DEG = 35.0


def overview_cameras(layout) -> dict:
    """name -> Camera: a top view and four corner obliques framing the layout's bounds."""
    (x0, y0), (x1, y1) = layout.bounds()
    lanes = layout.drivable_lanes() or layout.lanes
    z = float(np.median(np.concatenate([ln.points[:, 2] for ln in lanes]))) if lanes else 0.0
    c = np.array([(x0 + x1) / 2, (y0 + y1) / 2, z])
    w, h = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
    W, H = OVERVIEW_SIZE
    t = np.tan(np.radians(OVERVIEW_FOV_DEG) / 2)
    top = 0.55 * max(w / t, h / (t * H / W))     # 10 % margin around the bounds
    dist = 0.55 * float(np.hypot(w, h)) / t
    far = 4.0 * max(top, dist)
    cams = {"Top": Camera.from_fov(W, H, OVERVIEW_FOV_DEG, look_at(c + [0, 0, top], c, up=(0, 1, 0)),
                                   near=0.5, far=far)}
    el = np.radians(OVERVIEW_ELEVATION_DEG)
    for name, az in (("SouthWest", 225.0), ("SouthEast", 315.0), ("NorthEast", 45.0),
                     ("NorthWest", 135.0)):
        a = np.radians(az)
        eye = c + dist * np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
        cams[name] = Camera.from_fov(W, H, OVERVIEW_FOV_DEG, look_at(eye, c), near=0.5, far=far)
    return cams


def ggds_views(sc: S.Scene, layout, cfg) -> tuple[list, list]:
    """([(region, View)] training, [(region, View)] held-out) of a GGDS run of ``cfg`` on the
    scene's surfel chunks: its regions (ggds.regions.plan_regions) in name order, each
    sampled by ggds.regions.region_views.region_views; a region without lanes inside has none (GGDS
    keeps its surfels as they are)."""
    regions = sorted((r for phase in plan_regions(read_chunk_map(sc.layer_path("surfels")),
                                                  cfg.ggds.regions) for r in phase),
                     key=lambda r: r.name)
    train, held = [], []
    for r in regions:
        try:
            views, held_out = region_views(layout, cfg.ggds, cfg.seed, r)
        except InputError:
            if not r.name:
                raise
            continue
        train += [(r.name, v) for v in views]
        held += [(r.name, v) for v in held_out]
    return train, held


def write_scene_cameras(sc: S.Scene, layout, cfg, log=print) -> dict:
    """Write (or keep, when unchanged) the scene's cameras layer for a `generate`
    configuration ``cfg`` (GenerateConfig) on the scene's surfels: the views GGDS trains and
    evaluates on, and the overviews. Returns a summary for generate's."""

    train, held_out = ggds_views(sc, layout, cfg)
    overview = overview_cameras(layout)
    groups = [("Train", [(f"Train_{k:03d}", v.camera, v.kind, v.lane_id, r)
                         for k, (r, v) in enumerate(train)]),
              ("HeldOut", [(f"HeldOut_{k:03d}", v.camera, v.kind, v.lane_id, r)
                           for k, (r, v) in enumerate(held_out)]),
              ("Overview", [(name, cam, "overview", None, None) for name, cam in overview.items()])]
    inputs = content_hash("cameras-v2", [[(n, r, c.pose.round(9).tolist(),
                                           [c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.near, c.far])
                                          for n, c, _, _, r in cams] for _, cams in groups])
    summary = {"train": len(train), "held_out": len(held_out), "overview": len(overview)}
    if sc.layer_inputs_hash("cameras") == inputs:
        sc.add_layer("cameras")
        log(f"cameras: {S.CAMERAS_PATH} unchanged")
        return {**summary, "reused": True}
    stage = S.new_stage()
    UsdGeom.Xform.Define(stage, S.CAMERAS_PATH)
    for group, cams in groups:
        UsdGeom.Xform.Define(stage, f"{S.CAMERAS_PATH}/{group}")
        for name, cam, kind, lane, region in cams:
            prim = to_usd(stage, f"{S.CAMERAS_PATH}/{group}/{name}", cam).GetPrim()
            prim.CreateAttribute("lsd3d:camera:kind", Sdf.ValueTypeNames.Token, custom=True,
                                 variability=Sdf.VariabilityUniform).Set(kind)
            for attr, value in (("lane", lane), ("region", region)):
                if value is not None:
                    prim.CreateAttribute(f"lsd3d:camera:{attr}", Sdf.ValueTypeNames.String,
                                         custom=True, variability=Sdf.VariabilityUniform).Set(value)
    sc.write_layer("cameras", stage, S.provenance(
        "cameras", {"views": cfg.ggds.views, "heldOut": cfg.ggds.held_out,
                    "resolution": list(cfg.ggds.resolution), "fovDeg": cfg.ggds.fov_deg},
        seed=cfg.seed, inputsHash=inputs))
    log(f"cameras: {sum(summary.values())} under {S.CAMERAS_PATH} (Train, HeldOut, Overview)")
    return {**summary, "reused": False}
