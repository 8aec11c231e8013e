"""`render --rig`: a multi-camera sensor rig driven along a route or a pose list.

Writes OUT/rig.usda (views.rig_stage: the scene + the animated rig), then renders every
camera at every frame from that stage with views.frame.render_scene — the same path as
`render --camera` — PNGs under OUT/<camera>/ and an MP4 per camera.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from pxr import Sdf
from tqdm import tqdm

from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import FRAMES
from lsd3d_usd.render.camera import from_usd
from lsd3d_usd.scene import save_layer
from lsd3d_usd.sensors import rigs as sensor_rigs
from lsd3d_usd.sensors.rigs import OVERVIEW, check_rig_width, load_rig
from lsd3d_usd.views.boxes import actor_boxes, camera_boxes, local_boxes, write_boxes
from lsd3d_usd.views.deferred import deferred_name, write_provenance
from lsd3d_usd.views.frame import render_scene
from lsd3d_usd.views.ground_truth import needs_labels, write_ground_truth
from lsd3d_usd.views.images import display_uint8, write_frame, write_image
from lsd3d_usd.views.labels import Instances, write_tables
from lsd3d_usd.views.lidar_sweep import SurfelCache, bev_image, mesh_actors, write_sweep
from lsd3d_usd.views.lidar_sweep import sweep as lidar_sweep
from lsd3d_usd.views.options import RIG_WIDTH as DEFAULT_WIDTH
from lsd3d_usd.views.options import RigOptions
from lsd3d_usd.views.rig_stage import build_rig_stage
from lsd3d_usd.views.stage_data import SceneReader
from lsd3d_usd.views.video import ffmpeg_exe, write_mp4

LIDAR_NAME = "LIDAR_TOP"   # the sweeps' folder, and the LiDAR's prim under the ego


@dataclass
class RigResult:
    rig_layer: Path
    frames: dict            # camera name -> list of PNG paths
    videos: dict            # camera name -> mp4 path
    notes: list
    deferred_frames: dict | None = None    # camera name -> list of *_deferred.png paths (deferral only)
    deferred_videos: dict | None = None    # camera name -> *_deferred.mp4 path
    deferred: dict | None = None           # the deferral's provenance (views.deferred.Deferrer.describe)
    route: list | None = None   # lane ids driven (given or default), None for a trajectory
    sweeps: list = field(default_factory=list)   # OUT/<lidar>/<frame>.npz
    timing: dict = field(default_factory=dict)   # cameras_s, lidar_s


def rig_lidar(rig: RigOptions):
    """The LiDAR model of the run (--lidar, else the rig's own; sensors.lidar), or None."""
    return sensor_rigs.rig_lidar(rig.name or "waymo5", rig.lidar)


def render_rig(scene_path, out_dir, rig: RigOptions | None = None, *,
               width: int = DEFAULT_WIDTH, use_env: bool = True, exposure: float = 0.0,
               tonemap_method: str = "aces", outputs=("rgb",), progress: bool = True,
               log=print, deferrer=None) -> RigResult:
    """Render every camera of the rig ``rig.name`` (default waymo5; and the overview) at
    every frame of ``rig`` (views.options.RigOptions: route or trajectory, fps, seconds,
    speed, streaming, video, overview, LiDAR); PNGs under OUT/<camera>/, and an MP4 per camera
    unless ``rig.video`` is False. ``outputs`` (views.ground_truth.OUTPUTS): the ground truth
    written beside each camera's PNG, and OUT/boxes/<frame>.json. With a LiDAR
    (``rig.lidar``, or the rig's own), one sweep per frame starting at the frame's time:
    OUT/<lidar>/<frame>.npz / .ply / _bev.png and an MP4 of the bird's-eye views.
    ``rig.stream_radius`` > 0: only the chunks within that distance of the cameras are loaded
    (memory independent of the route's length); 0 loads the whole scene. With ``deferrer`` (a
    views.deferred.Deferrer of this scene) every frame is also deferred through the scene's
    prior: *_deferred.png beside each PNG, *_deferred.mp4 beside each MP4, and the deferral's
    provenance in rig.usda and OUT/deferred.json."""

    rig = rig or RigOptions()
    rig_name = rig.name or "waymo5"
    outputs = tuple(outputs)
    fps, seconds, video, stream_radius = rig.fps, rig.seconds, rig.video, rig.stream_radius
    if int(width) < 8:
        raise InputError(f"--resolution: rig frames need a width >= 8, got {width}")
    check_rig_width(rig_name, width, f"--resolution {width}", overview=rig.overview)
    FRAMES.check(fps * seconds, "render --rig: --fps x --seconds", what="frames per camera")
    if not stream_radius >= 0:
        raise InputError(f"--stream-radius {stream_radius}: must be >= 0 (0 loads everything)")
    lidar = rig_lidar(rig)
    if video:
        ffmpeg_exe()   # checked before minutes of rendering
    stage, paths, track, tcps, notes, route_ids = build_rig_stage(
        scene_path, out_dir, rig_name, route=rig.route, trajectory=rig.trajectory, fps=fps,
        seconds=seconds, speed=rig.speed, seed=rig.seed, load_all=not stream_radius,
        lidar=lidar)
    if not rig.overview:
        paths = [p for p in paths if not p.endswith("/" + OVERVIEW.name)]
    reader = SceneReader(stage, use_env=use_env, stream_radius=stream_radius or None,
                         lod_px=rig.lod_px if rig.lod else 0.0)
    if not (reader.stream.chunks if reader.stream else reader.surfels() is not None):
        notes.append("the scene has no surfels: frames show actors over the env only")
    out = Path(out_dir).absolute()
    labelled = needs_labels(outputs) or lidar is not None
    instances = Instances.of(reader.actors) if labelled else None
    if labelled:
        write_tables(out, instances)
    lboxes = local_boxes(reader.actors) if "boxes" in outputs and reader.actors else None
    specs = {c.name: c for c in load_rig(rig_name).cameras + (OVERVIEW,)}
    frames = {p.rsplit("/", 1)[-1]: [] for p in paths}
    images = {k: [] for k in frames}
    d_frames = {k: [] for k in frames} if deferrer is not None else None
    d_images = {k: [] for k in frames}
    sweeps, bevs = [], []
    lidar_actors = mesh_actors(reader.actors, tcps) if lidar is not None else None
    surfel_cache = SurfelCache()
    timing = {"cameras_s": 0.0, "lidar_s": 0.0}
    bar = tqdm(total=len(track.times) * len(paths), desc="render rig", unit="frame", disable=not progress)
    for k, t in enumerate(track.times):
        code = round(float(t) * tcps, 6)
        ego = track.at([t])[0]
        boxes = (actor_boxes(reader.actors, instances, lboxes, code, tcps, ego)
                 if lboxes is not None else None)
        for path in paths:
            t0 = time.perf_counter()
            name = path.rsplit("/", 1)[-1]
            cam = from_usd(stage.GetPrimAtPath(path), code, int(width), specs[name].height_for(width))
            frame = render_scene(reader, cam, code, instances=instances if labelled else None)
            frames[name].append(write_frame(out / name / f"{name}.{k:04d}.png", frame, "png",
                                            exposure, tonemap_method))
            if frame.labels is not None:
                write_ground_truth(frames[name][-1], frame.labels, outputs)
                if boxes is not None:
                    boxes = camera_boxes(boxes, cam, name, frame.labels, reader.actors_at(code),
                                         instances)
            if video:
                images[name].append(display_uint8(frame.rgb, exposure, tonemap_method))
            if deferrer is not None:
                dframe = deferrer.defer_frame(frame, cam)
                d_frames[name].append(write_frame(deferred_name(frames[name][-1]), dframe, "png",
                                                  exposure, tonemap_method))
                if video:
                    d_images[name].append(display_uint8(dframe.rgb, exposure, tonemap_method))
            timing["cameras_s"] += time.perf_counter() - t0
            bar.update(1)
        if boxes is not None:
            write_boxes(out / "boxes" / f"{k:04d}.json", k, float(t), boxes)
        if lidar is not None:
            t0 = time.perf_counter()
            sw = lidar_sweep(reader, lidar, track.at, float(t), tcps, instances,
                             actors=lidar_actors, cache=surfel_cache, seed=rig.seed, index=k)
            write_sweep(out / LIDAR_NAME, f"{k:04d}", sw)
            bev = bev_image(sw)
            write_image(out / LIDAR_NAME / f"{k:04d}_bev.png", bev)
            sweeps.append(out / LIDAR_NAME / f"{k:04d}.npz")
            if video:
                bevs.append(bev)
            timing["lidar_s"] += time.perf_counter() - t0
    bar.close()
    videos, d_videos = {}, {}
    if video:
        for name, ims in images.items():
            videos[name] = write_mp4(out / f"{name}.mp4", ims, fps)
            if deferrer is not None:
                d_videos[name] = write_mp4(deferred_name(videos[name]), d_images[name], fps)
        if bevs:
            videos[LIDAR_NAME] = write_mp4(out / f"{LIDAR_NAME}_bev.mp4", bevs, fps)
    described = None
    if deferrer is not None:
        described = deferrer.describe()
        record_deferral(out / "rig.usda", described)
        write_provenance(out / "deferred.json", deferrer, rig=rig_name, fps=fps, seconds=seconds,
                         width=int(width))
    for n in notes:
        log(f"note: {n}")
    return RigResult(out / "rig.usda", frames, videos, notes, d_frames,
                     d_videos if deferrer is not None else None, described, route=route_ids,
                     sweeps=sweeps, timing=timing)


def record_deferral(rig_file: Path, described: dict) -> Path:
    """Add the deferral's provenance to rig.usda (customLayerData lsd3d.deferred)."""

    layer = Sdf.Layer.FindOrOpen(str(rig_file))
    return save_layer(layer, rig_file, {"deferred": json.dumps(described, default=str)})
