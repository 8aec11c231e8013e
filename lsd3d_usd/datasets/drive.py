"""One log of a dataset: a scene driven along a route by a rig, rendered one tick at a time.

`drive(plan, ...)` writes the rig's stage (rig.usda, views.rig_stage) into a work folder and
yields a Sample per tick of the log's timeline (datasets.timeline): the cameras' images and
ground truth when they fire, the LiDAR sweep when it fires, and the actors' 3D boxes (with
per-camera 2D boxes, visibility and LiDAR point counts at keyframes). Nothing is kept between
ticks but the reader's caches: memory is bounded for any route length.

Frames: world = the scene's (Z up, metres); ego = x forward, y left, z up, origin on the
ground below the rear axle; cameras = OpenCV (x right, y down, z forward); LiDAR = its mount
on the ego (x forward, y left, z up for the presets). Poses are 4x4 parent-from-child.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsd3d_usd.render.camera import from_usd
from lsd3d_usd.sensors.camera import camera_in_ego
from lsd3d_usd.sensors.rigs import load_rig
from lsd3d_usd.views.boxes import actor_boxes, camera_boxes, local_boxes
from lsd3d_usd.views.frame import render_scene
from lsd3d_usd.views.images import display_uint8
from lsd3d_usd.views.labels import Instances
from lsd3d_usd.views.lidar_sweep import SurfelCache, mesh_actors
from lsd3d_usd.views.lidar_sweep import sweep as lidar_sweep
from lsd3d_usd.views.options import DEFAULT_STREAM_RADIUS
from lsd3d_usd.views.rig_stage import build_rig_stage
from lsd3d_usd.views.stage_data import SceneReader

LIDAR_CHANNEL = "LIDAR_TOP"


@dataclass
class LogPlan:
    """What one log is: a scene, a route (lane ids) and the log's place in the dataset."""
    index: int
    scene: Path
    scene_name: str
    route: list
    key: str                    # scene name + route: what the log's tokens hash


@dataclass
class CameraShot:
    channel: str
    image: np.ndarray           # (H, W, 3) uint8 sRGB
    K: np.ndarray               # 3x3 intrinsics at the image's size
    ego_from_sensor: np.ndarray
    labels: object              # views.frame.FrameLabels


@dataclass
class LidarShot:
    channel: str
    sweep: object               # views.lidar_sweep.Sweep (points in the sensor frame at start)
    ego_from_sensor: np.ndarray


@dataclass
class Sample:
    """One tick: ``time`` seconds into the log, the ego there, what fired."""
    tick: object                # datasets.timeline.Tick
    time: float
    world_from_ego: np.ndarray
    cameras: list = field(default_factory=list)
    lidar: LidarShot | None = None
    boxes: list = field(default_factory=list)   # views.boxes.Box (+ keyframe counts)
    timing: dict = field(default_factory=dict)  # seconds: cameras, lidar, boxes

    @property
    def keyframe(self) -> bool:
        return self.tick.keyframe


@dataclass
class LogInfo:
    """What a writer needs before the first sample of a log."""
    plan: LogPlan
    rig: str
    cameras: list               # sensors.camera.CameraModel of the rig, in order
    lidar: object               # sensors.lidar.LidarModel or None
    width: int
    timeline: object
    instances: Instances
    layout: object              # layout.model.Layout
    ego_from_camera: dict       # channel -> 4x4
    ego_from_lidar: np.ndarray | None
    route: list


def drive(plan: LogPlan, work: Path, *, rig: str, lidar, timeline, width: int,
          seed: int = 0, exposure: float = 0.0, tonemap: str = "aces", deferrer=None,
          stream_radius: float = DEFAULT_STREAM_RADIUS, start_tick: int = 0,
          lod_px: float = 0.0, log=print):
    """(LogInfo, iterator of Sample) of one log (module doc); ``work``: the log's work folder
    (rig.usda and the ego's asset). ``start_tick``: skip the ticks before it (a resumed log;
    every tick is a pure function of the scene, the plan and the seed, so the rest is the
    same as in an uninterrupted run)."""
    from lsd3d_usd.layout.usdio import layout_from_stage
    fps = float(timeline.tick_rate)
    stage, paths, track, tcps, notes, _ = build_rig_stage(
        plan.scene, work, rig, route=",".join(plan.route), fps=fps,
        seconds=timeline.n_ticks / fps, seed=seed, load_all=not stream_radius, lidar=lidar)
    for n in notes:
        log(f"note: {n}")
    specs = list(load_rig(rig).cameras)
    by_name = {p.rsplit("/", 1)[-1]: p for p in paths}
    reader = SceneReader(stage, stream_radius=stream_radius or None, lod_px=lod_px)
    instances = Instances.of(reader.actors)
    layout = layout_from_stage(stage, str(plan.scene))     # routes need one (build checks)
    info = LogInfo(plan, rig, specs, lidar, int(width), timeline, instances, layout,
                   {c.name: camera_in_ego(c) for c in specs},
                   None if lidar is None else lidar.ego_from_sensor(), list(plan.route))
    return info, _samples(info, stage, by_name, reader, track, tcps, seed, exposure, tonemap,
                          deferrer, start_tick)


def _samples(info: LogInfo, stage, by_name, reader, track, tcps, seed, exposure, tonemap,
             deferrer, start_tick=0):
    lboxes = local_boxes(reader.actors) if reader.actors is not None and len(reader.actors) \
        else None
    lidar_actors = mesh_actors(reader.actors, tcps) if info.lidar is not None else None
    cache = SurfelCache()
    for tick in info.timeline.ticks():
        if tick.index < start_tick:
            continue
        t = tick.time
        code = round(t * tcps, 6)
        ego = track.at([t])[0]
        s = Sample(tick, t, ego)
        c0 = time.perf_counter()
        if lboxes is not None:
            s.boxes = actor_boxes(reader.actors, info.instances, lboxes, code, tcps, ego)
        c1 = time.perf_counter()
        if tick.lidar and info.lidar is not None:
            sw = lidar_sweep(reader, info.lidar, track.at, t, tcps, info.instances,
                             actors=lidar_actors, cache=cache, seed=seed, index=tick.lidar_frame)
            s.lidar = LidarShot(LIDAR_CHANNEL, sw, info.ego_from_lidar)
        c2 = time.perf_counter()
        alone = 0.0
        if tick.cameras:
            actors_frame = reader.actors_at(code) if tick.keyframe and s.boxes else None
            for spec in info.cameras:
                cam = from_usd(stage.GetPrimAtPath(by_name[spec.name]), code, info.width,
                               spec.height_for(info.width))
                frame = render_scene(reader, cam, code, instances=info.instances)
                rgb = frame.rgb if deferrer is None else deferrer.defer_frame(frame, cam).rgb
                s.cameras.append(CameraShot(spec.name, display_uint8(rgb, exposure, tonemap),
                                            np.asarray(cam.K, np.float64),
                                            info.ego_from_camera[spec.name], frame.labels))
                if actors_frame is not None:
                    a0 = time.perf_counter()
                    s.boxes = camera_boxes(s.boxes, cam, spec.name, frame.labels,
                                           actors_frame, info.instances)
                    alone += time.perf_counter() - a0
        if tick.keyframe:
            _keyframe_stats(s)
        c3 = time.perf_counter()
        s.timing = {"boxes_s": c1 - c0 + alone, "lidar_s": c2 - c1,
                    "cameras_s": c3 - c2 - alone}
        yield s


def _keyframe_stats(s: Sample) -> None:
    """Per box: LiDAR points on it (its instance in the sweep) and its visible fraction pooled
    over the cameras (visible pixels / pixels when rendered alone)."""
    if s.lidar is not None:
        ids, counts = np.unique(s.lidar.sweep.instance_id, return_counts=True)
        n = dict(zip(ids.tolist(), counts.tolist()))
    else:
        n = {}
    out = []
    for b in s.boxes:
        seen = sum(e.pixels for e in b.cameras.values())
        alone = sum(e.pixels_alone for e in b.cameras.values())
        out.append(b.with_counts(int(n.get(b.instance_id, 0)), int(seen),
                                 float(seen / alone) if alone else 0.0))
    s.boxes = out
