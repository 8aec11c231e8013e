"""The rig's USD layer, OUT/rig.usda: the scene by sublayer (nothing copied) plus
/World/Cameras/Ego (translate + orient time samples) with one UsdGeom.Camera per rig camera
and the third-person Overview camera, and the ego car as an actor.

The ego car is the scene's own assets/car.usda (written by generate's actors step); a scene
without one gets the procedural car written into OUT/assets/, so rig.usda never points into
a source checkout. The layer is authored detached (Sdf level) and only opened once written
next to its relative asset paths: nothing tries to resolve them early (no USD warnings).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom
from scipy.spatial.transform import Rotation

from lsd3d_usd.assetroots import check_scene
from lsd3d_usd import scene as S
from lsd3d_usd.actors.assets import relative_asset_path, write_vehicle_asset
from lsd3d_usd.actors.usdio import ROLE_ATTR, ActorSpec, actor_label, author_actor
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import default_route
from lsd3d_usd.layout.usdio import layout_from_stage
from lsd3d_usd.render.camera import to_usd
from lsd3d_usd.scene import ACTORS_PATH, ASSETS_DIR, CAMERAS_PATH, new_stage
from lsd3d_usd.sensors.camera import rig_camera
from lsd3d_usd.sensors.rigs import OVERVIEW, load_rig
from lsd3d_usd.views.ego import (
    EgoTrack,
    frame_times,
    load_trajectory,
    resample,
    track_from_route,
)
from lsd3d_usd.views.lidar_sweep import usd_lidar_prim

EGO_PATH = "/World/Cameras/Ego"
EGO_ASSET = "car.usda"


def ego_car_asset(scene_root_file: Path, out_dir: Path) -> Path:
    """The car the ego drives: the scene's assets/car.usda, else the procedural car written
    to OUT/assets/car.usda."""
    own = Path(scene_root_file).parent / ASSETS_DIR / EGO_ASSET
    if own.is_file():
        return own
    return write_vehicle_asset("car", Path(out_dir) / ASSETS_DIR / EGO_ASSET)


def rig_layer(rig, track: EgoTrack, tcps: float, ego_asset: str | None = None, lidar=None):
    """(anonymous Sdf layer, camera prim paths): /World/Cameras/Ego with its cameras following
    ``track``, and /World/Actors/Ego/Ego_000 referencing ``ego_asset`` (a path relative to
    where the layer will be saved) if given."""

    # Cameras and xform ops on an in-memory stage (nothing there references a file) ...
    stage = new_stage()
    UsdGeom.Xform.Define(stage, CAMERAS_PATH)
    ego = UsdGeom.Xform.Define(stage, EGO_PATH)
    paths = []
    for cam in list(rig) + [OVERVIEW]:
        path = f"{EGO_PATH}/{cam.name}"
        to_usd(stage, path, rig_camera(cam, np.eye(4), cam.size[0]))  # local = ego-relative
        paths.append(path)
    if lidar is not None:
        usd_lidar_prim(stage, f"{EGO_PATH}/LIDAR_TOP", lidar)
    tr = ego.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
    ori = ego.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
    quats = Rotation.from_matrix(track.rotations).as_quat()  # xyzw
    for k, t in enumerate(track.times):
        code = round(float(t) * tcps, 6)
        tr.Set(Gf.Vec3d(*map(float, track.positions[k])), code)
        x, y, z, w = map(float, quats[k])
        ori.Set(Gf.Quatd(w, x, y, z), code)
    # ... then the ego actor's reference on a detached layer, where it is not resolved.
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(stage.GetRootLayer())
    if ego_asset:
        with Sdf.ChangeBlock():
            for p in (ACTORS_PATH, f"{ACTORS_PATH}/Ego"):
                spec = Sdf.CreatePrimInLayer(layer, p)
                spec.specifier = Sdf.SpecifierDef
                spec.typeName = "Xform"
            author_actor(layer, f"{ACTORS_PATH}/Ego",
                         ActorSpec("Ego_000", "ego", ego_asset, track.positions, track.yaws(),
                                   times=track.times), tcps)
    return layer, paths


def scene_pedestrians(stage, tcps: float):
    """``positions(t)`` -> (n, 2) xy at t seconds of the stage's pedestrian actors (UsdSemantics
    class pedestrian), or None when it has none."""
    start = stage.GetPrimAtPath(S.ACTORS_PATH)
    if not start:
        return None
    prims = [p for p in Usd.PrimRange(start) if p.GetAttribute(ROLE_ATTR)
             and p.GetAttribute(ROLE_ATTR).HasValue() and actor_label(p) == "pedestrian"]
    if not prims:
        return None
    xf = [UsdGeom.Xformable(p) for p in prims]

    def positions(t: float) -> np.ndarray:
        code = Usd.TimeCode(float(t) * tcps)
        return np.array([np.array(x.ComputeLocalToWorldTransform(code).ExtractTranslation())[:2]
                         for x in xf])
    return positions


def build_rig_stage(scene_path, out_dir, rig_name: str = "waymo5", *, route=None, trajectory=None,
                    fps: float = 10.0, seconds: float = 8.0, speed: float | None = None,
                    seed: int = 0, ego_body: bool = True, load_all: bool = True, lidar=None):
    """Write OUT/rig.usda (sublayering the scene) and return (composed stage, camera paths,
    track, timeCodesPerSecond, notes, route lane ids or None). Without ``route`` and
    ``trajectory`` the ego drives :func:`default_route` (said in a note, to be reused).
    ``rig_name``: a rig name or a rig FILE.toml (sensors.rigs.load_rig). ``lidar``
    (sensors.lidar.LidarModel): the LiDAR as a prim under the ego, LIDAR_TOP."""

    rig = load_rig(rig_name)
    if route is not None and trajectory is not None:
        raise InputError("--rig takes one of --route LANE_IDS or --trajectory poses.json, not both")
    sp = Path(scene_path)
    root_file = (sp / S.ROOT_FILE if sp.is_dir() else sp).absolute()
    scene_stage = S.open_stage(root_file, load=False)
    check_scene(scene_stage, root_file)
    root_layer = scene_stage.GetRootLayer()
    tcps = float(root_layer.timeCodesPerSecond) if root_layer.HasTimeCodesPerSecond() else 24.0
    times = frame_times(fps, seconds)
    notes = []
    ids = None
    if trajectory is None:
        if not scene_stage.GetPrimAtPath(S.LAYOUT_PATH):
            raise InputError(f"{scene_path}: {'--route' if route is not None else 'a rig without --trajectory'} "
                             f"needs the scene's layout ({S.LAYOUT_PATH}); give --trajectory poses.json")
        layout = layout_from_stage(scene_stage, str(scene_path))
        if route is None:
            ids, length = default_route(layout, seconds, speed)
            if not ids:
                raise InputError(f"{scene_path}: the layout has no drivable lanes to drive the rig "
                                 "along; give --trajectory poses.json")
            route = ",".join(ids)
            notes.append(f"no --route given: driving the longest drivable successor path, cut "
                         f"where it covers the clip ({length:.0f} m; `lsd3d-usd layout lanes` "
                         f"lists the lanes); reuse it with --route {route}")
        ids = [r.strip() for r in (route.split(",") if isinstance(route, str) else route) if r.strip()]
        track = track_from_route(layout, ids, times, speed, seed,
                                 pedestrians=scene_pedestrians(scene_stage, tcps))
    else:
        track, clamped = resample(load_trajectory(trajectory), times)
        if clamped:
            notes.append(f"{clamped} frame(s) lie outside the trajectory's time range: "
                         "the ego holds its first/last pose there")
    out = Path(out_dir).absolute()
    out.mkdir(parents=True, exist_ok=True)
    ego_asset = relative_asset_path(ego_car_asset(root_file, out), out) if ego_body else None
    layer, paths = rig_layer(rig.cameras, track, tcps, ego_asset, lidar)
    layer.subLayerPaths = [relative_asset_path(root_file, out)]
    layer.timeCodesPerSecond = tcps
    layer.framesPerSecond = tcps
    layer.startTimeCode = 0.0
    layer.endTimeCode = float(times[-1] * tcps)
    rig_file = out / "rig.usda"
    S.save_layer(layer, rig_file, S.provenance("rig", {"rig": rig_name, "fps": fps, "seconds": seconds,
                                                       "route": ",".join(route) if isinstance(route, list)
                                                       else route, "trajectory": trajectory}, seed=seed))
    load = Usd.Stage.LoadAll if load_all else Usd.Stage.LoadNone
    return Usd.Stage.Open(str(rig_file), load), paths, track, tcps, notes, ids
