"""Sensors: the typed parts a rig carries (cameras, LiDARs, and any registered type) and rigs
as data.

  camera.py  CameraModel (a pinhole camera on the ego), camera_in_ego, rig_camera
  lidar.py   LidarModel (a spinning LiDAR), the LiDAR presets and files (lidar_model)
  rigs.py    Rig, load_rig (a rig name or a rig FILE.toml), OVERVIEW
  tables.py  the checks every TOML reader here shares (one error line naming file and key)
  data/      the built-in rigs and LiDAR presets, as TOML files

A sensor type is a class registered in SENSORS (entry-point group ``lsd3d_usd.sensors``):
it has ``kind`` (the rig file's ``type``), ``name`` and a classmethod
``from_table(table, where) -> part`` that checks every key. Rigs and LiDAR presets are
registered as files (``"package:path/file.toml"``, lsd3d_usd.registry) in RIGS
(``lsd3d_usd.rigs``) and LIDARS (``lsd3d_usd.lidars``).

The renderer's kernels (render/lidar.py, render/camera.py) sit below this package and take
arrays: this package depends on them, never the reverse.
"""
from __future__ import annotations

from lsd3d_usd.registry import Registry

SENSORS = Registry("lsd3d_usd.sensors", "sensor type", {
    "camera": "lsd3d_usd.sensors.camera:CameraModel",
    "lidar": "lsd3d_usd.sensors.lidar:LidarModel",
})
RIGS = Registry("lsd3d_usd.rigs", "rig", {
    "waymo5": "lsd3d_usd.sensors:data/rigs/waymo5.toml",
    "nuscenes6": "lsd3d_usd.sensors:data/rigs/nuscenes6.toml",
})
LIDARS = Registry("lsd3d_usd.lidars", "LiDAR", {
    "waymo_top": "lsd3d_usd.sensors:data/lidars/waymo_top.toml",
    "hdl32": "lsd3d_usd.sensors:data/lidars/hdl32.toml",
})
