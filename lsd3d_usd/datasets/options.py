"""What a `dataset` run is asked for (light: the command-line parser imports it, and
`--resume` compares its signature)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

DEFAULT_VERSION = "v1.0-lsd3d"


@dataclass
class DatasetOptions:
    format: str = "nuscenes"
    rig: str = "nuscenes6"
    lidar: str = "auto"                 # auto (the rig's own) | none | preset | FILE.toml
    route: str | None = None            # lane ids, comma-separated (every scene)
    routes: int | None = None           # N distinct seeded routes per scene
    seconds: float = 20.0
    camera_hz: float = 12.0
    lidar_hz: float = 20.0
    keyframe_hz: float = 2.0
    deferred: bool = False
    resume: bool = False
    overwrite: bool = False
    seed: int = 0
    version: str = DEFAULT_VERSION
    width: int | None = None            # camera image width (default: the rig's native)
    exposure: float = 0.0
    tonemap: str = "aces"
    scenes: list = field(default_factory=list)

    def signature(self) -> dict:
        """What must match for --resume (everything that changes the output)."""
        d = asdict(self)
        for k in ("resume", "overwrite"):
            d.pop(k)
        return d
