"""`render --rig`: a multi-camera sensor rig driven along a route or a pose list.

Writes OUT/rig.usda (views.rig_stage: the scene + the animated rig), then renders every
camera at every frame from that stage with views.frame.render_scene — the same path as
`render --camera` — PNGs under OUT/<camera>/ and an MP4 per camera.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from pxr import Sdf
from tqdm import tqdm

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import from_usd
from lsd3d_usd.scene import save_layer
from lsd3d_usd.views.deferred import deferred_name, write_provenance
from lsd3d_usd.views.frame import render_scene
from lsd3d_usd.views.images import display_uint8, write_frame
from lsd3d_usd.views.options import RIG_WIDTH as DEFAULT_WIDTH
from lsd3d_usd.views.options import RigOptions
from lsd3d_usd.views.rig_stage import build_rig_stage
from lsd3d_usd.views.rigs import OVERVIEW, RIGS
from lsd3d_usd.views.stage_data import SceneReader
from lsd3d_usd.views.video import ffmpeg_exe, write_mp4


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


def render_rig(scene_path, out_dir, rig: RigOptions | None = None, *,
               width: int = DEFAULT_WIDTH, use_env: bool = True, exposure: float = 0.0,
               tonemap_method: str = "aces", progress: bool = True, log=print,
               deferrer=None) -> RigResult:
    """Render every camera of the rig ``rig.name`` (default waymo5; and the overview) at
    every frame of ``rig`` (views.options.RigOptions: route or trajectory, fps, seconds,
    speed, streaming, video, overview); PNGs under OUT/<camera>/, and an MP4 per camera
    unless ``rig.video`` is False. ``rig.stream_radius`` > 0: only the chunks within that
    distance of the cameras are loaded (memory independent of the route's length); 0 loads
    the whole scene. With ``deferrer`` (a views.deferred.Deferrer of this
    scene) every frame is also deferred through the scene's prior: *_deferred.png beside each
    PNG, *_deferred.mp4 beside each MP4, and the deferral's provenance in rig.usda and
    OUT/deferred.json."""

    rig = rig or RigOptions()
    rig_name = rig.name or "waymo5"
    fps, seconds, video, stream_radius = rig.fps, rig.seconds, rig.video, rig.stream_radius
    if int(width) < 8:
        raise InputError(f"--resolution: rig frames need a width >= 8, got {width}")
    if not stream_radius >= 0:
        raise InputError(f"--stream-radius {stream_radius}: must be >= 0 (0 loads everything)")
    if video:
        ffmpeg_exe()   # checked before minutes of rendering
    stage, paths, track, tcps, notes, route_ids = build_rig_stage(
        scene_path, out_dir, rig_name, route=rig.route, trajectory=rig.trajectory, fps=fps,
        seconds=seconds, speed=rig.speed, seed=rig.seed, load_all=not stream_radius)
    if not rig.overview:
        paths = [p for p in paths if not p.endswith("/" + OVERVIEW.name)]
    reader = SceneReader(stage, use_env=use_env, stream_radius=stream_radius or None)
    if not (reader.stream.chunks if reader.stream else reader.surfels() is not None):
        notes.append("the scene has no surfels: frames show actors over the env only")
    out = Path(out_dir).absolute()
    specs = {c.name: c for c in list(RIGS[rig_name]) + [OVERVIEW]}
    frames = {p.rsplit("/", 1)[-1]: [] for p in paths}
    images = {k: [] for k in frames}
    d_frames = {k: [] for k in frames} if deferrer is not None else None
    d_images = {k: [] for k in frames}
    bar = tqdm(total=len(track.times) * len(paths), desc="render rig", unit="frame", disable=not progress)
    for k, t in enumerate(track.times):
        code = round(float(t) * tcps, 6)
        for path in paths:
            name = path.rsplit("/", 1)[-1]
            cam = from_usd(stage.GetPrimAtPath(path), code, int(width), specs[name].height_for(width))
            frame = render_scene(reader, cam, code)
            frames[name].append(write_frame(out / name / f"{name}.{k:04d}.png", frame, "png",
                                            exposure, tonemap_method))
            if video:
                images[name].append(display_uint8(frame.rgb, exposure, tonemap_method))
            if deferrer is not None:
                dframe = deferrer.defer_frame(frame, cam)
                d_frames[name].append(write_frame(deferred_name(frames[name][-1]), dframe, "png",
                                                  exposure, tonemap_method))
                if video:
                    d_images[name].append(display_uint8(dframe.rgb, exposure, tonemap_method))
            bar.update(1)
    bar.close()
    videos, d_videos = {}, {}
    if video:
        for name, ims in images.items():
            videos[name] = write_mp4(out / f"{name}.mp4", ims, fps)
            if deferrer is not None:
                d_videos[name] = write_mp4(deferred_name(videos[name]), d_images[name], fps)
    described = None
    if deferrer is not None:
        described = deferrer.describe()
        record_deferral(out / "rig.usda", described)
        write_provenance(out / "deferred.json", deferrer, rig=rig_name, fps=fps, seconds=seconds,
                         width=int(width))
    for n in notes:
        log(f"note: {n}")
    return RigResult(out / "rig.usda", frames, videos, notes, d_frames,
                     d_videos if deferrer is not None else None, described, route=route_ids)


def record_deferral(rig_file: Path, described: dict) -> Path:
    """Add the deferral's provenance to rig.usda (customLayerData lsd3d.deferred)."""

    layer = Sdf.Layer.FindOrOpen(str(rig_file))
    return save_layer(layer, rig_file, {"deferred": json.dumps(described, default=str)})
