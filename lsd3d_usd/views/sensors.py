"""LiDAR presets and LiDAR files: the sensor models a rig carries (render.lidar.LidarModel).

Presets (figures from the manufacturers' and the datasets' published specifications):

  waymo_top  64 beams, elevations -17.6 to +2.4 deg (uniform), 2650 columns, 75 m, 10 Hz:
             the Waymo Open Dataset's top LiDAR (its range image is 64 x 2650).
  hdl32      the nuScenes LIDAR_TOP (Velodyne HDL-32E): 32 beams, -30.67 to +10.67 deg
             (uniform, 1.33 deg apart), 20 Hz, 70 m; 1086 columns = its ~695,000 single-return
             points per second / 20 sweeps / 32 beams (0.33 deg apart); mounted where nuScenes'
             calibration puts it (0.94 m ahead of the rear axle, 1.84 m up).

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

Every key is checked (one error line naming it), nothing is rendered before.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lsd3d_usd.configtree import read_toml
from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import LIDAR_FILE_BYTES, LIDAR_NAME_CHARS
from lsd3d_usd.render.lidar import MAX_COLUMNS, MAX_RINGS, LidarModel

PRESETS = {
    "waymo_top": LidarModel("waymo_top", tuple(np.linspace(-17.6, 2.4, 64).round(6)), 2650,
                            min_range=0.5, max_range=75.0, rotation_hz=10.0,
                            mount=(1.43, 0.0, 2.18, 0.0, 0.0, 0.0)),
    "hdl32": LidarModel("hdl32", tuple(np.linspace(-30.67, 10.67, 32).round(6)), 1086,
                        min_range=0.5, max_range=70.0, rotation_hz=20.0,
                        mount=(0.94, 0.0, 1.84, 0.0, 0.0, 0.0)),
}
KEYS = {"name", "beams", "elevation_min", "elevation_max", "elevations", "columns", "hfov",
        "min_range", "max_range", "rotation_hz", "range_sigma", "drop_prob", "mount"}
MOUNT_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")


def lidar_model(spec: str, where: str = "--lidar") -> LidarModel:
    """A preset by name, or a LiDAR TOML file; one InputError line otherwise."""
    if spec in PRESETS:
        return PRESETS[spec]
    p = Path(spec)
    if p.suffix.lower() != ".toml":
        raise InputError(f"{where} {spec!r}: unknown LiDAR; presets: {', '.join(PRESETS)}, "
                         "or a FILE.toml")
    if p.is_file():             # parsing a large TOML costs ~20x its size in memory
        LIDAR_FILE_BYTES.check(p.stat().st_size, f"{where} {spec}")
    data = read_toml(p, f"{where} {spec}: no such file")
    table = data.get("lidar", data)
    if not isinstance(table, dict):
        raise InputError(f"{p}: [lidar] must be a table")
    return model_from_table(table, str(p))


def _num(table, key, where, default=None, integer=False):
    v = table.get(key, default)
    if v is None:
        raise InputError(f"{where}: {key}: required")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{where}: {key}: expected a number, got {v!r}")
    if integer and (not float(v).is_integer()):
        raise InputError(f"{where}: {key}: expected an integer, got {v!r}")
    if not math.isfinite(float(v)):
        raise InputError(f"{where}: {key}: must be finite, got {v!r}")
    return int(v) if integer else float(v)


def model_from_table(table: dict, where: str) -> LidarModel:
    unknown = sorted(set(table) - KEYS)
    if unknown:
        raise InputError(f"{where}: unknown key {unknown[0]!r}; known: {', '.join(sorted(KEYS))}")
    if "elevations" in table:
        el = table["elevations"]
        if not isinstance(el, list) or not el:
            raise InputError(f"{where}: elevations: expected a list of degrees")
        if len(el) > MAX_RINGS:
            raise InputError(f"{where}: elevations: {len(el)} beams exceed the limit of {MAX_RINGS}")
        elev = tuple(_num({"e": e}, "e", f"{where}: elevations") for e in el)
    else:
        n = _num(table, "beams", where, integer=True)
        if not 1 <= n <= MAX_RINGS:
            raise InputError(f"{where}: beams: {n} is outside 1 .. {MAX_RINGS}")
        lo, hi = _num(table, "elevation_min", where), _num(table, "elevation_max", where)
        if hi < lo:
            raise InputError(f"{where}: elevation_max {hi} is below elevation_min {lo}")
        elev = tuple(np.linspace(lo, hi, n).round(9)) if n > 1 else (lo,)
    cols = _num(table, "columns", where, integer=True)
    if not 1 <= cols <= MAX_COLUMNS:
        raise InputError(f"{where}: columns: {cols} is outside 1 .. {MAX_COLUMNS}")
    mount = table.get("mount", {})
    if not isinstance(mount, dict) or set(mount) - set(MOUNT_KEYS):
        raise InputError(f"{where}: mount: a table of {', '.join(MOUNT_KEYS)}")
    m = tuple(_num(mount, k, f"{where}: mount", 0.0) for k in MOUNT_KEYS)
    name = table.get("name", Path(where).stem)
    if not isinstance(name, str):
        raise InputError(f"{where}: name: expected a string, got {type(name).__name__}")
    LIDAR_NAME_CHARS.check(len(name), f"{where}: name")
    model = LidarModel(name, elev, cols,
                       hfov_deg=_num(table, "hfov", where, 360.0),
                       min_range=_num(table, "min_range", where, 0.5),
                       max_range=_num(table, "max_range", where, 75.0),
                       rotation_hz=_num(table, "rotation_hz", where, 10.0),
                       range_sigma=_num(table, "range_sigma", where, 0.0),
                       drop_prob=_num(table, "drop_prob", where, 0.0), mount=m)
    return model.check(where)
