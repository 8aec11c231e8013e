"""The ego's sensors in the loop: each camera of the rig and its LiDAR rendered through
views/ (views.frame.composite, views.lidar_sweep.sweep) at the ego's simulated pose, with
the episode's agents where the world put them; the same composite and depth rule as the
datasets, so labels and pixels agree.

Observation layout (fixed shapes): ``cameras/<NAME>/rgb`` (H, W, 3) uint8, and on request
``depth`` (H, W) float32 metres along the optical axis (inf: sky), ``semantic`` (H, W) uint8
class ids, ``instance`` (H, W) uint16; ``lidar``: the sweep's returns in the sensor frame
padded to a fixed maximum, with ``count`` valid rows and the sweep npz's channels.
"""
from __future__ import annotations

import numpy as np
from gymnasium import spaces

from lsd3d_usd.errors import InputError
from lsd3d_usd.views.frame import composite
from lsd3d_usd.views.images import display_uint8
from lsd3d_usd.views.labels import Instances
from lsd3d_usd.views.lidar_sweep import SurfelCache, mesh_actors
from lsd3d_usd.views.lidar_sweep import sweep as lidar_sweep
from lsd3d_usd.sensors.camera import rig_camera
from lsd3d_usd.sensors.lidar import lidar_model
from lsd3d_usd.sensors.rigs import load_rig


def rig_sensors(rig: str, lidar: str, cameras=None) -> tuple[list, object]:
    """(rig cameras, LiDAR model or None) of a rig (a name or FILE.toml; "none": no cameras)
    and a LiDAR spec ("auto": the rig's own, "none", a preset or FILE.toml)."""
    r = None if rig in (None, "none") else load_rig(rig)
    cams = list(r.cameras) if r is not None else []
    if cameras:
        names = [c.name for c in cams]
        bad = [c for c in cameras if c not in names]
        if bad:
            raise InputError(f"--cameras: {bad[0]!r} is not a camera of rig {rig!r} "
                             f"({', '.join(names) or 'none'})")
        cams = [c for c in cams if c.name in cameras]
    if lidar in (None, "auto"):
        model = r.lidar if r is not None else None
    else:
        model = None if lidar == "none" else lidar_model(lidar)
    return cams, model


class SensorRig:
    """Cameras and LiDAR of an env (see the module doc)."""

    def __init__(self, scene, settings):
        self.scene = scene
        self.s = settings
        self.cameras, self.lidar = rig_sensors(settings.rig, settings.lidar, settings.cameras)
        self.width = int(settings.width)
        self.labels = bool({"depth", "semantic", "instance"} & set(settings.outputs))
        self.max_points = int(settings.lidar_max_points or
                              (self.lidar.rings * self.lidar.columns if self.lidar else 0))
        self._code = 0.0
        self._cache = SurfelCache()

    def spaces(self) -> dict:
        out = {}
        if self.cameras:
            cams = {}
            for c in self.cameras:
                h = c.height_for(self.width)
                d = {"rgb": spaces.Box(0, 255, (h, self.width, 3), np.uint8)}
                if "depth" in self.s.outputs:
                    d["depth"] = spaces.Box(0.0, np.inf, (h, self.width), np.float32)
                if "semantic" in self.s.outputs:
                    d["semantic"] = spaces.Box(0, 255, (h, self.width), np.uint8)
                if "instance" in self.s.outputs:
                    d["instance"] = spaces.Box(0, 65535, (h, self.width), np.uint16)
                cams[c.name] = spaces.Dict(d)
            out["cameras"] = spaces.Dict(cams)
        if self.lidar is not None:
            n = self.max_points
            out["lidar"] = spaces.Dict({
                "points": spaces.Box(-np.inf, np.inf, (n, 3), np.float32),
                "intensity": spaces.Box(0.0, np.inf, (n,), np.float32),
                "ring": spaces.Box(0, 65535, (n,), np.uint16),
                "class": spaces.Box(0, 255, (n,), np.uint8),
                "instance": spaces.Box(0, 65535, (n,), np.uint16),
                "time": spaces.Box(0.0, np.inf, (n,), np.float32),
                "count": spaces.Box(0, n, (), np.int64),
            })
        return out

    def start_episode(self, actors, seed: int) -> None:
        """Use the episode's actors (sim.scene.SimActors) from now on."""
        self.actors = actors
        self.scene.reader.actors = actors
        self.instances = Instances.of(actors)
        self.mesh = mesh_actors(actors, self.scene.tcps) if self.lidar is not None else None
        self.seed = int(seed)

    def observe(self, ego, t: float, k: int) -> dict:
        self._code += 1.0               # a new instant: the reader places the actors again
        out = {}
        reader = self.scene.reader
        M = ego.matrix()
        if self.cameras:
            env = reader.env(None)
            frames = {}
            for c in self.cameras:
                cam = rig_camera(c, M, self.width)
                surf = reader.surfels_seen(cam)
                f = composite(surf, reader.actors_at(self._code), cam, env,
                              instances=self.instances if self.labels else None)
                d = {"rgb": display_uint8(f.rgb, self.s.exposure)}
                if "depth" in self.s.outputs:
                    d["depth"] = f.labels.z.astype(np.float32)
                if "semantic" in self.s.outputs:
                    d["semantic"] = f.labels.class_id
                if "instance" in self.s.outputs:
                    d["instance"] = f.labels.instance_id
                frames[c.name] = d
            out["cameras"] = frames
        if self.lidar is not None:
            out["lidar"] = self._sweep(ego, t, k)
        return out

    def _sweep(self, ego, t: float, k: int) -> dict:
        v, r = ego.v, ego.yaw_rate

        def world_from_ego(times):
            # the ego over the sweep at its current speed and yaw rate (rolling shutter)
            dt = np.asarray(times, np.float64).reshape(-1) - t
            yaw = ego.yaw + r * dt
            mid = ego.yaw + r * dt / 2
            M = np.tile(np.eye(4), (len(dt), 1, 1))
            c, s = np.cos(yaw), np.sin(yaw)
            M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1] = c, -s, s, c
            M[:, 0, 3] = ego.x + v * dt * np.cos(mid)
            M[:, 1, 3] = ego.y + v * dt * np.sin(mid)
            M[:, 2, 3] = ego.z
            return M

        sw = lidar_sweep(self.scene.reader, self.lidar, world_from_ego, t, self.scene.tcps,
                         self.instances, actors=self.mesh, cache=self._cache, seed=self.seed, index=k)
        n = min(len(sw.xyz), self.max_points)
        N = self.max_points

        def pad(a, dtype, shape=()):
            out = np.zeros((N,) + shape, dtype)
            out[:n] = a[:n]
            return out
        return {"points": pad(sw.xyz, np.float32, (3,)), "intensity": pad(sw.intensity, np.float32),
                "ring": pad(sw.ring, np.uint16), "class": pad(sw.class_id, np.uint8),
                "instance": pad(sw.instance_id, np.uint16), "time": pad(sw.t, np.float32),
                "count": np.int64(n)}

