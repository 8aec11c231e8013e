"""Rigs as data: the sensors a car carries, where they are mounted and how often they fire,
read from a TOML file. The built-in rigs (``waymo5``, ``nuscenes6``) are such files
(sensors/data/rigs/), registered by name in RIGS; wherever a rig name is accepted
(`render --rig`, `dataset --rig`, batch specs) a rig FILE.toml is too.

A rig file::

    [rig]
    name = "city4"               # default: the file's stem
    lidar = "hdl32"              # optional: a LiDAR preset or a LiDAR FILE.toml (relative to
                                 # this file) carried unless --lidar says otherwise
    [[sensor]]                   # one table per sensor, in order; type: a registered sensor
    type = "camera"              # type (SENSORS: camera, lidar, ...), the other keys its own
    name = "Front"               # (sensors/camera.py, sensors/lidar.py)
    hfov = 50.4
    size = [1920, 1280]
    mount = {x = 1.55, y = 0.0, z = 2.10, yaw = 0.0}

At least one camera; at most one LiDAR (``lidar =`` or a ``[[sensor]]`` of type lidar).
Every key is checked: a bad one is one InputError line naming the file, the sensor and key.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from lsd3d_usd.configtree import read_toml
from lsd3d_usd.errors import InputError
from lsd3d_usd.sensors import RIGS, SENSORS
from lsd3d_usd.sensors.camera import CameraModel
from lsd3d_usd.sensors.lidar import LidarModel, lidar_model
from lsd3d_usd.sensors.tables import known_keys

DATA = Path(__file__).parent / "data"
RIG_KEYS = {"name", "lidar"}
MAX_SENSORS = 64


@dataclass(frozen=True)
class Rig:
    name: str
    cameras: tuple                   # CameraModel (or another camera part), in file order
    lidar: LidarModel | None = None  # the LiDAR it carries unless --lidar says otherwise
    others: tuple = ()               # parts of other registered sensor types, in file order
    source: str = ""                 # the file it was read from

    def camera(self, name: str) -> CameraModel:
        return next(c for c in self.cameras if c.name == name)


def _overview() -> CameraModel:
    f = DATA / "overview.toml"
    return CameraModel.from_table(read_toml(f, f"{f}: no such file")["camera"], str(f))


# the third-person camera behind and above the ego that rig renders add to every rig
OVERVIEW = _overview()
_BUILT: dict[str, Rig] = {}     # registered rigs already read


def rig_names() -> list[str]:
    return RIGS.ordered()


def load_rig(spec, where: str = "--rig") -> Rig:
    """The rig ``spec``: a registered name, a rig FILE.toml, or a Rig (returned as is)."""
    if isinstance(spec, Rig):
        return spec
    spec = str(spec)
    if spec in RIGS:
        if spec not in _BUILT:
            entry = RIGS.get(spec)
            _BUILT[spec] = entry if isinstance(entry, Rig) else read_rig(entry, where)
        return _BUILT[spec]
    if Path(spec).suffix.lower() != ".toml":
        raise InputError(f"{where} {spec!r}: unknown rig; known: {', '.join(rig_names())}, "
                         "or a rig FILE.toml")
    return read_rig(spec, where)


def read_rig(path, where: str = "--rig") -> Rig:
    p = Path(path)
    data = read_toml(p, f"{where} {path}: no such file")
    known_keys(data, {"rig", "sensor"}, str(p))
    head = data.get("rig", {})
    if not isinstance(head, dict):
        raise InputError(f"{p}: [rig] must be a table")
    known_keys(head, RIG_KEYS, f"{p}: rig")
    name = head.get("name", p.stem)
    if not isinstance(name, str) or not name:
        raise InputError(f"{p}: rig: name: expected a string, got {name!r}")
    tables = data.get("sensor", [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise InputError(f"{p}: sensor: expected [[sensor]] tables")
    if len(tables) > MAX_SENSORS:
        raise InputError(f"{p}: {len(tables)} sensors exceed the limit of {MAX_SENSORS}")
    parts = []
    for i, t in enumerate(tables):
        kind = t.get("type")
        at = f"{p}: sensor[{i}]" + (f" ({t['name']})" if isinstance(t.get("name"), str) else "")
        if not isinstance(kind, str):
            raise InputError(f"{at}: type: required, one of {', '.join(SENSORS.names())}")
        if kind not in SENSORS:
            raise InputError(f"{at}: type: unknown sensor type {kind!r}; known: "
                             f"{', '.join(SENSORS.names())}")
        parts.append(SENSORS.get(kind).from_table(t, at))
    names = [getattr(q, "name", "") for q in parts]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise InputError(f"{p}: sensor name {dup!r} is used twice (each names an output folder)")
    cameras = tuple(q for q in parts if q.kind == "camera")
    lidars = [q for q in parts if q.kind == "lidar"]
    if "lidar" in head:
        if not isinstance(head["lidar"], str):
            raise InputError(f"{p}: rig: lidar: a preset name or a FILE.toml")
        if head["lidar"] != "none":
            lidars.append(lidar_model(head["lidar"], f"{p}: rig: lidar", base=p.parent))
    if not cameras:
        raise InputError(f"{p}: a rig needs at least one [[sensor]] of type camera")
    if len(lidars) > 1:
        raise InputError(f"{p}: {len(lidars)} LiDARs; a rig carries at most one")
    others = tuple(q for q in parts if q.kind not in ("camera", "lidar"))
    return Rig(name, cameras, lidars[0] if lidars else None, others, str(p))


def rig_lidar(rig, lidar: str | None) -> LidarModel | None:
    """The LiDAR of a run: ``lidar`` (a preset, a FILE.toml or none), or with None / auto the
    rig's own."""
    if lidar in (None, "auto"):
        return load_rig(rig).lidar
    return None if lidar == "none" else lidar_model(lidar)


def check_rig_width(rig, width: int, where: str, overview: bool = False) -> None:
    """Every camera of the rig at ``width`` (heights follow each camera's aspect) within the
    image-pixel limit, before anything is rendered."""
    from lsd3d_usd.limits import check_image_size
    for c in list(load_rig(rig).cameras) + ([OVERVIEW] if overview else []):
        check_image_size(width, c.height_for(width), f"{where} ({c.name})")
