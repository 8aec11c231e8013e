"""What a `dataset` run is asked for (light: the command-line parser imports it, and
`--resume` compares its signature). Its option leaves are `dataset`'s flags."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from lsd3d_usd.configtree import option
from lsd3d_usd.views.options import DEFAULT_LOD_PX

DEFAULT_VERSION = "v1.0-lsd3d"


@dataclass
class DatasetOptions:
    """`dataset`'s configuration tree (lsd3d_usd.configtree): its flags are these leaves."""
    format: str = option("nuscenes", help="dataset format (a registered writer, "
                                          "lsd3d_usd.dataset_writers)", flag="--format",
                         metavar="nuscenes|kitti|mcap")
    rig: str = option("nuscenes6", help="sensor rig: a rig name or a rig FILE.toml "
                                        "(docs/sensors.md)", flag="--rig",
                      metavar="nuscenes6|waymo5|FILE.toml")
    lidar: str = option("auto", help="the LiDAR (auto: the rig's own; nuscenes6 carries hdl32)",
                        flag="--lidar", metavar="hdl32|waymo_top|none|FILE.toml")
    route: str | None = option(None, help="lane ids to drive, comma-separated (default: the "
                                          "longest drivable route)", flag="--route",
                               metavar="IDS")
    routes: int | None = option(None, help="N distinct seeded routes per scene",
                                flag="--routes", metavar="N")
    seconds: float = option(20.0, help="length of each log", flag="--seconds",
                            metavar="SECONDS")
    camera_hz: float = option(12.0, help="camera frame rate", flag="--camera-hz",
                              metavar="CAMERA_HZ")
    lidar_hz: float = option(20.0, help="LiDAR sweep rate", flag="--lidar-hz",
                             metavar="LIDAR_HZ")
    keyframe_hz: float = option(2.0, help="keyframe (annotated sample) rate, dividing both "
                                          "sensor rates", flag="--keyframe-hz",
                                metavar="KEYFRAME_HZ")
    deferred: bool = option(False, help="camera images through the scene's image prior "
                                        "(docs/render.md)", flag="--deferred")
    resume: bool = option(False, help="continue the dataset in DIR: finished logs are kept, an "
                                      "unfinished one continues after its last keyframe "
                                      "(nuscenes, kitti)", flag="--resume")
    overwrite: bool = option(False, help="replace the dataset in DIR", flag="--overwrite")
    seed: int = option(0, help="seed of routes, traffic and LiDAR noise", flag="--seed",
                       metavar="SEED")
    version: str = option(DEFAULT_VERSION, help="nuScenes version folder", flag="--version",
                          metavar="VERSION")
    width: int | None = option(None, help="camera image width in pixels (default: the rig's "
                                          "native, 1600 for nuscenes6); heights follow each "
                                          "camera's aspect", flag="--width", metavar="WIDTH")
    lod: bool = option(True, help="level of detail for camera frames: surfels far enough to "
                                  "cover few pixels drawn as merged nodes (docs/render.md)",
                       flag="--lod", negate="--no-lod")
    lod_px: float = option(DEFAULT_LOD_PX, help="level-of-detail budget in pixels (a merged "
                                                "node's bounding sphere on screen)",
                           flag="--lod-px", metavar="PX", lo=0.5, hi=256.0)
    # set by batch specs and benchmarks, not by flags (field order: dataset.json's key order)
    exposure: float = 0.0
    tonemap: str = "aces"
    scenes: list = field(default_factory=list)

    def signature(self) -> dict:
        """What must match for --resume (everything that changes the output)."""
        d = asdict(self)
        for k in ("resume", "overwrite"):
            d.pop(k)
        return d
