"""A spinning LiDAR as a sensor: its beams, columns, timing and mount (LidarModel), the presets
(sensors/data/lidars/, registered in LIDARS) and LiDAR files. The kernels that cast its rays
are render/lidar.py's; they take this model's arrays (``directions``, ``column_times``).

The beams. Rings (one beam each, at fixed elevations, ring 0 lowest, as Velodyne numbers
them) and columns (azimuths swept as the head turns at ``rotation_hz``). Column j looks at
azimuth ``hfov/2 - (j + 0.5) · hfov / columns`` in the sensor frame (x forward, y left, z up:
the head turns clockwise seen from above, starting behind the sensor for a 360° model) and
fires ``(j + 0.5) / columns · (hfov / 360) / rotation_hz`` seconds after the sweep starts.

Presets (figures from the manufacturers' and the datasets' published specifications; each
file says where its numbers come from): ``waymo_top`` (64 beams, 2650 columns, 75 m, 10 Hz)
and ``hdl32`` (nuScenes' Velodyne HDL-32E: 32 beams, 1086 columns, 70 m, 20 Hz).

A LiDAR file (TOML)::

    [lidar]
    name = "my_lidar"
    beams = 32                   # uniform between elevation_min and elevation_max ...
    elevation_min = -30.67
    elevation_max = 10.67
    # elevations = [-15.0, -13.0, ...]   # ... or a table, one per beam (ascending)
    columns = 1086
    hfov = 360
    min_range = 0.5
    max_range = 70.0
    rotation_hz = 20
    range_sigma = 0.02           # metres, Gaussian
    drop_prob = 0.0
    mount = {x = 0.94, y = 0.0, z = 1.84, roll = 0.0, pitch = 0.0, yaw = 0.0}

The same keys (and ``type = "lidar"``) make a ``[[sensor]]`` of a rig file. Every key is
checked (one error line naming it), nothing is rendered before.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsd3d_usd.configtree import read_toml
from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import (LIDAR_BEAMS, LIDAR_COLUMNS, LIDAR_FILE_BYTES, LIDAR_MOUNT,
                              LIDAR_NAME_CHARS, LIDAR_RANGE, LIDAR_RAYS)
from lsd3d_usd.sensors import LIDARS
from lsd3d_usd.sensors.tables import known_keys, number

MAX_COLUMNS = int(LIDAR_COLUMNS.value)
MAX_RINGS = int(LIDAR_BEAMS.value)
MAX_RAYS = int(LIDAR_RAYS.value)
KEYS = {"name", "beams", "elevation_min", "elevation_max", "elevations", "columns", "hfov",
        "min_range", "max_range", "rotation_hz", "range_sigma", "drop_prob", "mount"}
MOUNT_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")


@dataclass(frozen=True)
class LidarModel:
    """A spinning LiDAR (see the module doc). Ranges in metres, angles in degrees."""
    name: str
    elevations_deg: tuple          # per ring, ascending
    columns: int
    hfov_deg: float = 360.0
    min_range: float = 0.5
    max_range: float = 75.0
    rotation_hz: float = 10.0
    range_sigma: float = 0.0       # Gaussian range noise (m), seeded per sweep
    drop_prob: float = 0.0         # probability a return is dropped, seeded per sweep
    mount: tuple = (0.0, 0.0, 2.0, 0.0, 0.0, 0.0)   # x, y, z (m), roll, pitch, yaw (deg) on the ego
    extras: dict = field(default_factory=dict, compare=False)

    kind = "lidar"

    @classmethod
    def from_table(cls, table: dict, where: str) -> LidarModel:
        """A ``[[sensor]]`` of type lidar in a rig file (the keys of a LiDAR file)."""
        return model_from_table({k: v for k, v in table.items() if k != "type"}, where)

    def check(self, where: str = "lidar") -> LidarModel:
        """One InputError line naming the first bad key."""
        el = np.asarray(self.elevations_deg, np.float64)
        if el.ndim != 1 or not 1 <= len(el) <= MAX_RINGS:
            raise InputError(f"{where}: beams: need 1 to {MAX_RINGS} beams, got {el.size}")
        if not np.all(np.isfinite(el)) or np.any(np.abs(el) >= 90.0):
            bad = el[~np.isfinite(el) | (np.abs(el) >= 90.0)][0]
            raise InputError(f"{where}: elevations: {bad:g} deg is outside (-90, 90)")
        if np.any(np.diff(el) < 0):
            raise InputError(f"{where}: elevations: must be ascending (ring 0 lowest)")
        if not isinstance(self.columns, (int, np.integer)) or not 1 <= self.columns <= MAX_COLUMNS:
            raise InputError(f"{where}: columns: {self.columns} is outside 1 .. {MAX_COLUMNS}")
        if len(el) * self.columns > MAX_RAYS:
            raise InputError(f"{where}: {len(el)} beams x {self.columns} columns = "
                             f"{len(el) * self.columns} rays exceed the limit of {MAX_RAYS}")
        if not (math.isfinite(self.hfov_deg) and 0.0 < self.hfov_deg <= 360.0):
            raise InputError(f"{where}: hfov: {self.hfov_deg} must be in (0, 360]")
        if not (math.isfinite(self.min_range) and self.min_range >= 0.0):
            raise InputError(f"{where}: min_range: {self.min_range} must be >= 0")
        if not (math.isfinite(self.max_range) and self.max_range > self.min_range):
            raise InputError(f"{where}: max_range: {self.max_range} must exceed min_range "
                             f"{self.min_range}")
        if not LIDAR_RANGE.ok(self.max_range):
            raise InputError(f"{where}: max_range: "
                             f"{LIDAR_RANGE.describe(self.max_range, what='').strip()}")
        if not (math.isfinite(self.rotation_hz) and 0.01 <= self.rotation_hz <= 1000.0):
            raise InputError(f"{where}: rotation_hz: {self.rotation_hz} is outside 0.01 .. 1000")
        if not (math.isfinite(self.range_sigma) and 0.0 <= self.range_sigma <= 10.0):
            raise InputError(f"{where}: range_sigma: {self.range_sigma} is outside 0 .. 10 m")
        if not (math.isfinite(self.drop_prob) and 0.0 <= self.drop_prob < 1.0):
            raise InputError(f"{where}: drop_prob: {self.drop_prob} is outside [0, 1)")
        m = np.asarray(self.mount, np.float64)
        if m.shape != (6,) or not np.all(np.isfinite(m)):
            raise InputError(f"{where}: mount: need x, y, z, roll, pitch, yaw (finite)")
        for k, v in zip(MOUNT_KEYS[:3], m[:3]):
            if not LIDAR_MOUNT.ok(abs(v)):
                raise InputError(f"{where}: mount: {k}: "
                                 f"{LIDAR_MOUNT.describe(abs(v), what='|' + k + '|').strip()}")
        return self

    @property
    def rings(self) -> int:
        return len(self.elevations_deg)

    @property
    def sweep_seconds(self) -> float:
        """Time from the first column to the end of the last."""
        return (self.hfov_deg / 360.0) / self.rotation_hz

    def azimuths_deg(self) -> np.ndarray:
        """(C,) azimuth of each column in the sensor frame."""
        j = np.arange(self.columns, dtype=np.float64)
        return self.hfov_deg / 2.0 - (j + 0.5) * self.hfov_deg / self.columns

    def column_times(self) -> np.ndarray:
        """(C,) seconds after the sweep starts at which each column fires."""
        j = np.arange(self.columns, dtype=np.float64)
        return (j + 0.5) / self.columns * self.sweep_seconds

    def directions(self) -> np.ndarray:
        """(R, C, 3) unit beam directions in the sensor frame."""
        el = np.radians(np.asarray(self.elevations_deg, np.float64))[:, None]
        az = np.radians(self.azimuths_deg())[None, :]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                            np.sin(el)), axis=-1)

    def ego_from_sensor(self) -> np.ndarray:
        """4x4 mount of the sensor on the ego (roll about x, pitch about y, yaw about z)."""
        x, y, z, roll, pitch, yaw = (float(v) for v in self.mount)
        return pose_matrix((x, y, z), roll, pitch, yaw)

    def describe(self) -> dict:
        return {"name": self.name, "beams": self.rings, "columns": int(self.columns),
                "elevations_deg": [float(e) for e in self.elevations_deg],
                "hfov_deg": self.hfov_deg, "min_range": self.min_range,
                "max_range": self.max_range, "rotation_hz": self.rotation_hz,
                "range_sigma": self.range_sigma, "drop_prob": self.drop_prob,
                "mount": [float(v) for v in self.mount]}


def pose_matrix(xyz, roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """4x4 rigid transform R = Rz(yaw) Ry(pitch) Rx(roll), then the translation."""
    r, p, y = (math.radians(v) for v in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    M = np.eye(4)
    M[:3, :3] = Rz @ Ry @ Rx
    M[:3, 3] = xyz
    return M


_PRESETS: dict[str, LidarModel] = {}   # registered names already read


def presets() -> dict[str, LidarModel]:
    """Every registered LiDAR preset by name."""
    return {n: preset(n) for n in LIDARS.ordered()}


def preset(name: str) -> LidarModel:
    if name not in _PRESETS:
        entry = LIDARS.get(name)
        _PRESETS[name] = entry if isinstance(entry, LidarModel) else read_lidar_file(entry)
    return _PRESETS[name]


def lidar_model(spec: str, where: str = "--lidar", base: Path | None = None) -> LidarModel:
    """A preset by name, or a LiDAR TOML file (relative to ``base``, if given); one
    InputError line otherwise."""
    if spec in LIDARS:
        return preset(spec)
    p = Path(spec)
    if p.suffix.lower() != ".toml":
        raise InputError(f"{where} {spec!r}: unknown LiDAR; presets: {', '.join(LIDARS.ordered())}, "
                         "or a FILE.toml")
    if base is not None and not p.is_absolute():
        p = base / p
    return read_lidar_file(p, where)


def read_lidar_file(path, where: str | None = None) -> LidarModel:
    p = Path(path)
    if p.is_file():             # parsing a large TOML costs ~20x its size in memory
        LIDAR_FILE_BYTES.check(p.stat().st_size, f"{where} {path}" if where else str(p))
    data = read_toml(p, f"{where} {path}: no such file" if where else f"{p}: no such file")
    table = data.get("lidar", data)
    if not isinstance(table, dict):
        raise InputError(f"{p}: [lidar] must be a table")
    if "lidar" in data:                 # a table beside [lidar] would be ignored silently
        known_keys(data, {"lidar"}, f"{p}: top level")
    return model_from_table(table, str(p))


def model_from_table(table: dict, where: str) -> LidarModel:
    known_keys(table, KEYS, where)
    both = [k for k in ("beams", "elevation_min", "elevation_max") if k in table]
    if "elevations" in table and both:
        # which one would win is a guess: the user meant one of them
        raise InputError(f"{where}: elevations and {both[0]} exclude each other (give the "
                         "elevations table, or beams with elevation_min and elevation_max)")
    if "elevations" in table:
        el = table["elevations"]
        if not isinstance(el, list) or not el:
            raise InputError(f"{where}: elevations: expected a list of degrees")
        if len(el) > MAX_RINGS:
            raise InputError(f"{where}: elevations: {len(el)} beams exceed the limit of {MAX_RINGS}")
        elev = tuple(number({"e": e}, "e", f"{where}: elevations") for e in el)
    else:
        n = number(table, "beams", where, integer=True)
        if not 1 <= n <= MAX_RINGS:
            raise InputError(f"{where}: beams: {n} is outside 1 .. {MAX_RINGS}")
        lo, hi = number(table, "elevation_min", where), number(table, "elevation_max", where)
        for k, v in (("elevation_min", lo), ("elevation_max", hi)):
            if not abs(v) < 90.0:          # reported as given, not as a derived beam angle
                raise InputError(f"{where}: {k}: {v:g} deg is outside (-90, 90)")
        if hi < lo:
            raise InputError(f"{where}: elevation_max {hi} is below elevation_min {lo}")
        elev = tuple(np.linspace(lo, hi, n).round(9)) if n > 1 else (lo,)
    cols = number(table, "columns", where, integer=True)
    if not 1 <= cols <= MAX_COLUMNS:
        raise InputError(f"{where}: columns: {cols} is outside 1 .. {MAX_COLUMNS}")
    mount = table.get("mount", {})
    if not isinstance(mount, dict) or set(mount) - set(MOUNT_KEYS):
        raise InputError(f"{where}: mount: a table of {', '.join(MOUNT_KEYS)}")
    m = tuple(number(mount, k, f"{where}: mount", 0.0) for k in MOUNT_KEYS)
    name = table.get("name", Path(where).stem)
    if not isinstance(name, str):
        raise InputError(f"{where}: name: expected a string, got {type(name).__name__}")
    LIDAR_NAME_CHARS.check(len(name), f"{where}: name")
    model = LidarModel(name, elev, cols,
                       hfov_deg=number(table, "hfov", where, 360.0),
                       min_range=number(table, "min_range", where, 0.5),
                       max_range=number(table, "max_range", where, 75.0),
                       rotation_hz=number(table, "rotation_hz", where, 10.0),
                       range_sigma=number(table, "range_sigma", where, 0.0),
                       drop_prob=number(table, "drop_prob", where, 0.0), mount=m)
    return model.check(where)
