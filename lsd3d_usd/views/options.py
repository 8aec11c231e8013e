"""The configuration trees of `render` and of deferred rendering (lsd3d_usd.configtree): every
flag of `render` is a leaf, so `render --config FILE.toml --set KEY=VALUE` work as for
`generate`, and `eval` reuses the deferred subtree."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lsd3d_usd.cliutil import parse_size
from lsd3d_usd.configtree import option
from lsd3d_usd.ggds.priors.registry import check_device, check_prior_name
from lsd3d_usd.render.camera import DEFAULT_WIDTH as SINGLE_WIDTH
from lsd3d_usd.sensors.lidar import lidar_model
from lsd3d_usd.sensors.rigs import load_rig, rig_names
from lsd3d_usd.views.deferred import (
    DEFAULT_STEPS,
    DEFAULT_STRENGTH,
    check_steps,
    check_strength,
)

RIG_WIDTH = 480  # rig frames: five cameras x frames add up; `render --camera` uses 960
# Chunks within this distance of a camera are loaded (views.stage_data.ChunkStreamer): well
# beyond where 100 m chunks of surfels still cover more than a few pixels at rig resolutions.
DEFAULT_STREAM_RADIUS = 300.0
# splats.lod's budget for rig renders, datasets and the simulator (>= 40 dB against full detail
# on the README sample's rig frames; docs/render.md)
DEFAULT_LOD_PX = 4.0
TONEMAPS = ("aces", "reinhard", "clamp")


@dataclass
class DeferredConfig:
    """Deferred rendering (views/deferred.py): frames through the scene's prior."""
    enabled: bool = option(False, help="also pass the frames through the scene's image prior "
                                       "from a low noise level (the paper's deferred "
                                       "rendering), conditioned on the proxy G-buffer",
                           flag="--deferred")
    strength: float = option(DEFAULT_STRENGTH, help="noise level T in (0, 1] (chosen by "
                                                    "measurement, docs/render.md)",
                             flag="--deferred-strength", metavar="T",
                             check=lambda v, where: check_strength(v, where))
    steps: int = option(DEFAULT_STEPS, help="denoising steps N of a diffusion prior",
                        flag="--deferred-steps", metavar="N",
                        check=lambda v, where: check_steps(v, where))
    prior: str | None = option(None, help="prior to use instead of the one the scene's GGDS "
                                          "run recorded: 'procedural', 'diffusers:DIR' or "
                                          "another registered prior",
                               flag="--deferred-prior", metavar="PRIOR",
                               check=lambda v, where: check_prior_name(v, where))
    controlnet: Path | None = option(None, help="local depth ControlNet directory for a "
                                                "diffusers prior (overrides the recorded one)",
                                     flag="--deferred-controlnet", metavar="DIR")
    device: str | None = option(None, help="torch device of the prior (cpu, cuda[:N])",
                                flag="--deferred-device", metavar="DEV",
                                check=lambda v, where: check_device(v, where))
    seed: int | None = option(None, help="seed handed to the prior for every frame (default: "
                                         "the scene's seed; the built-in priors are "
                                         "deterministic and do not use it)",
                              flag="--deferred-seed", metavar="S")


def _check_resolution(v: str, where: str) -> str:
    parse_size(v, where, width_only=True)
    return v


def _check_lidar(v: str, where: str) -> str:
    if v not in ("auto", "none"):
        lidar_model(v, where)
    return v


def _check_rig(v: str | None, where: str) -> str | None:
    if v is not None:
        load_rig(v, where)
    return v


def _check_outputs(v: str, where: str) -> str:
    # local import: not loaded for --help
    from lsd3d_usd.views.ground_truth import check_outputs
    return check_outputs(v, where)


def _check_frames(v: str, where: str) -> str:
    # local import: not loaded for --help
    from lsd3d_usd.views.preview import parse_times
    parse_times(v, None, where)
    return v


@dataclass
class RigOptions:
    """A sensor rig driven through the scene (`render --rig`)."""
    name: str | None = option(None, help="render a multi-camera rig driven along --route or "
                                         "--trajectory: every camera's frames under "
                                         "OUT/<camera>/, an MP4 per camera, a third-person "
                                         "Overview, and OUT/rig.usda (the scene + the "
                                         "animated rig); a rig name ("
                                         f"{', '.join(rig_names())}) or a rig FILE.toml "
                                         "(docs/sensors.md)", flag="--rig", metavar="RIG",
                              check=lambda v, where: _check_rig(v, where))
    route: str | None = option(None, help="comma-separated lane ids the ego drives, each a "
                                          "successor of the one before (IDM speed on an empty "
                                          "road unless --speed); `lsd3d-usd layout lanes "
                                          "SCENE` lists them. Default (without --trajectory): "
                                          "the longest drivable successor path, printed so it "
                                          "can be reused", flag="--route")
    trajectory: Path | None = option(None, help="poses.json: a list of {t, x, y, z, yaw "
                                                "(degrees)} or {t, matrix (4x4 "
                                                "world-from-ego)}; see docs/actors.md",
                                     flag="--trajectory")
    fps: float = option(10.0, help="rig frames per second", flag="--fps", lo=0.01, hi=1000.0)
    seconds: float = option(8.0, help="rig clip length in seconds", flag="--seconds", lo=0.0,
                            hi=86400.0)
    speed: float | None = option(None, help="constant ego speed along --route in m/s "
                                            "(default: IDM)", flag="--speed", lo=0.0, hi=200.0)
    stream_radius: float = option(DEFAULT_STREAM_RADIUS, help="load only the scene chunks "
                                                             "within M metres of the cameras "
                                                             "and unload those left behind "
                                                             "(0 = load the whole scene)",
                                  flag="--stream-radius", metavar="M")   # checked by render_rig
    lod: bool = option(True, help="level of detail: surfels far enough to cover few pixels are "
                                  "drawn as merged nodes, and nothing outside a camera's view "
                                  "(docs/render.md)", flag="--lod", negate="--no-lod")
    lod_px: float = option(DEFAULT_LOD_PX, help="level-of-detail budget: a merged node stands "
                                                "for its surfels when its bounding sphere "
                                                "covers at most this many pixels",
                           flag="--lod-px", metavar="PX", lo=0.5, hi=256.0)
    video: bool = option(True, help="an MP4 per camera", negate="--no-video")
    overview: bool = option(True, help="the third-person overview camera",
                            negate="--no-overview")
    seed: int = option(0, help="seed of the rig's traffic interaction (IDM) and of the LiDAR's "
                               "noise")
    lidar: str = option("auto", help="a LiDAR on the rig: a preset (waymo_top, hdl32), a "
                                     "LiDAR FILE.toml (docs/sensors.md), none, or auto: the "
                                     "rig's own (nuscenes6 carries hdl32, waymo5 none); one "
                                     "sweep per frame under OUT/LIDAR_TOP/",
                               flag="--lidar", metavar="NAME|FILE.toml", check=_check_lidar)


@dataclass
class RenderConfig:
    """`render`: a scene from a USD camera, or a sensor rig's clips."""
    camera: str | None = option(None, help="camera prim path, e.g. /World/Cameras/Front "
                                           "(required unless --rig)", flag="--camera")
    resolution: str | None = option(None, help="WIDTHxHEIGHT, or WIDTH with the height from "
                                               "the camera's aperture aspect (default "
                                               f"{SINGLE_WIDTH} wide); with --rig only the "
                                               f"width counts (default {RIG_WIDTH}), heights "
                                               "follow each rig camera", flag="--resolution",
                                    check=_check_resolution)
    format: str = option("png", help="png: 8-bit sRGB after exposure and tone map; exr: float "
                                     "linear RGBA + Z", flag="--format", choices=("png", "exr"))
    time: float | None = option(None, help="time code of a single frame (default: the "
                                           "stage's earliest time)", flag="--time")
    frames: str | None = option(None, help="render a range of time codes START:END[:STEP] "
                                           "(inclusive)", flag="--frames", check=_check_frames)
    exposure: float = option(0.0, help="exposure in stops applied before the tone map (and to "
                                       "EXR pixels)", flag="--exposure", lo=-64.0, hi=64.0)
    tonemap: str = option("aces", help="PNG tone map (aces: a filmic curve)", flag="--tonemap",
                          choices=TONEMAPS)
    sh_degree: int | None = option(None, help="use only SH up to this degree (default: all the "
                                              "surfels have)", flag="--sh-degree",
                                   choices=(0, 1, 2, 3))
    env: bool = option(True, help="the env map behind the surfels (off: black)",
                       negate="--no-env")
    outputs: str = option("rgb", help="what to write per camera and frame, comma-separated: "
                                      "rgb, depth, semantic, instance, normal, boxes (ground "
                                      "truth from the same composite; docs/sensors.md)",
                          flag="--outputs", check=_check_outputs)
    rig: RigOptions = field(default_factory=RigOptions)
    deferred: DeferredConfig = field(default_factory=DeferredConfig)

    def width_height(self) -> tuple[int, int | None] | None:
        return parse_size(self.resolution, "--resolution", width_only=True)
