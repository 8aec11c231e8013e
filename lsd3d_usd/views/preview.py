"""`render SCENE --camera PRIM`: frames of a composed stage seen from one USD camera.

Surfels (every visible ParticleField of the scene: our Lsd3dSurfelField and the official
ParticleField3DGaussianSplat), the actors at each frame's time (relit) and the first visible
DomeLight's latlong env behind, composited by views.frame.render_scene (the rig's path);
written as PNG (tone-mapped, sRGB, 8 bit) or EXR (scene-linear RGBA + Z).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lsd3d_usd.assetroots import check_scene
from lsd3d_usd import scene
from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import from_usd
from lsd3d_usd.views.boxes import actor_boxes, camera_boxes, local_boxes, write_boxes
from lsd3d_usd.views.deferred import deferred_name, write_provenance
from lsd3d_usd.views.frame import render_scene
from lsd3d_usd.views.ground_truth import needs_labels, write_ground_truth
from lsd3d_usd.views.images import TONEMAPS, write_frame
from lsd3d_usd.views.labels import Instances, write_tables
from lsd3d_usd.views.stage_data import SceneReader, camera_prim, usd_time

MAX_FRAMES = 100_000   # frames of one `render --frames` range


def parse_times(frames: str | None, time: float | None, where: str = "--frames") -> list:
    """The time codes of a render: ``frames`` START:END[:STEP] (inclusive), else [``time``]
    (None: the stage's earliest time). One InputError line naming ``where`` otherwise."""
    if frames is None:
        return [time]
    m = re.fullmatch(r"\s*(-?[\d.]+)\s*:\s*(-?[\d.]+)\s*(?::\s*([\d.]+))?\s*", frames)
    if not m:
        raise InputError(f"{where} {frames!r}: use START:END or START:END:STEP (inclusive)")
    a, b = float(m.group(1)), float(m.group(2))
    step = float(m.group(3)) if m.group(3) else 1.0
    if step <= 0 or b < a:
        raise InputError(f"{where} {frames!r}: need END >= START and STEP > 0")
    n = int(np.floor((b - a) / step + 1e-9)) + 1
    if n > MAX_FRAMES:
        raise InputError(f"{where} {frames!r}: {n} frames exceed the limit of {MAX_FRAMES}")
    return [a + i * step for i in range(n)]


def frame_name(camera_path: str, time, fmt: str, multiple: bool) -> str:
    """OUT file name: <camera>.<fmt>, or <camera>.<frame>.<fmt> for a frame range."""
    base = camera_path.rstrip("/").rsplit("/", 1)[-1]
    if not multiple:
        return f"{base}.{fmt}"
    t = float(time)
    tag = f"{int(t):04d}" if t == int(t) else f"{t:09.3f}"
    return f"{base}.{tag}.{fmt}"


def render_preview(scene_path, camera_path: str, out_dir, *, times=(None,), resolution=None,
                   fmt: str = "png", exposure: float = 0.0, tonemap_method: str = "aces",
                   use_env: bool = True, sh_degree=None, progress: bool = True,
                   outputs=("rgb",), deferrer=None) -> list[Path]:
    """Render frames of ``scene_path`` (scene folder or USD file) from ``camera_path`` at
    ``times`` (time codes; None = the stage's earliest time). Returns the written files.
    ``outputs`` (views.ground_truth.OUTPUTS): ground truth beside each frame, the class and
    instance tables in OUT/, boxes in OUT/boxes/<frame>.json.
    With ``deferrer`` (views.deferred.Deferrer) each frame is also deferred through the
    scene's prior: <name>_deferred.<fmt> beside it, provenance in OUT/deferred.json."""

    if fmt not in ("png", "exr"):
        raise InputError(f"--format {fmt!r}: choose png or exr")
    if tonemap_method not in TONEMAPS:
        raise InputError(f"--tonemap {tonemap_method!r}: choose from {', '.join(TONEMAPS)}")
    stage = scene.open_stage(scene_path)
    check_scene(stage, scene_path)
    prim = camera_prim(stage, camera_path)
    reader = SceneReader(stage, use_env=use_env)
    width, height = resolution if resolution else (None, None)
    times = list(times)
    written = []
    labelled = needs_labels(outputs)
    instances = Instances.of(reader.actors) if labelled else None
    if labelled:
        written += list(write_tables(out_dir, instances))
    lboxes = local_boxes(reader.actors) if "boxes" in outputs and reader.actors else None
    tcps = stage.GetTimeCodesPerSecond()
    for k, t in enumerate(tqdm(times, desc="render", unit="frame",
                               disable=not progress or len(times) < 2)):
        if reader.surfels(t) is None:
            raise InputError(f"{scene_path}: no surfels to render (no visible ParticleField prim "
                             "with particles; run mesh -> surfel initialisation or import a PLY)")
        cam = from_usd(prim, usd_time(t), width, height)
        frame = render_scene(reader, cam, t, sh_degree, instances=instances)
        path = Path(out_dir) / frame_name(camera_path, t if t is not None else 0, fmt, len(times) > 1)
        written.append(write_frame(path, frame, fmt, exposure, tonemap_method))
        if frame.labels is not None:
            written += list(write_ground_truth(path, frame.labels, outputs).values())
        if lboxes is not None:
            code = stage.GetStartTimeCode() if t is None else float(t)
            boxes = actor_boxes(reader.actors, instances, lboxes, code, tcps, None)
            name = camera_path.rstrip("/").rsplit("/", 1)[-1]
            boxes = camera_boxes(boxes, cam, name, frame.labels, reader.actors_at(t),
                                 instances)
            written.append(write_boxes(Path(out_dir) / "boxes" / f"{k:04d}.json", k,
                                       code / tcps, boxes))
        if deferrer is not None:
            written.append(write_frame(deferred_name(path), deferrer.defer_frame(frame, cam), fmt,
                                       exposure, tonemap_method))
    if deferrer is not None:
        written.append(write_provenance(Path(out_dir) / "deferred.json", deferrer,
                                        camera=camera_path, format=fmt))
    return written
