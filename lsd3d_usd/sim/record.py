"""`sim run --mcap`: an episode recorded with the datasets' MCAP writer (datasets.mcap), so it
opens in Foxglove like a dataset log. Each step becomes a datasets.drive.Sample:

  /tf_static               ego -> each camera and the LiDAR, once
  /tf                      world -> ego (the simulated ego pose) per step
  /<camera>/image          JPEG of the camera's RGB observation, with /<camera>/camera_info
  /LIDAR_TOP               the observed sweep (its ``count`` valid points, sensor frame)
  /markers/annotations     a cube per agent of info["boxes"] (parked ones included), every step
  /sim/scores              the step's scores (info["scores"] with t and step) as schema-less
                           JSON; non-finite numbers are written as null

Boxes: info["boxes"] has the agents' ground footprints only. Height and ground z come from the
actor that renders the agent (its asset's dims and its placed pose in env.actors), so a box
is where its pixels and LiDAR points are; an agent without one falls back to a fixed height
per kind (FALLBACK_HEIGHT) standing at the ego's ground height.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsd3d_usd.datasets.drive import LIDAR_CHANNEL, CameraShot, LidarShot, LogInfo, LogPlan, Sample
from lsd3d_usd.datasets.mcap import McapWriter
from lsd3d_usd.semantics import CLASS_ID
from lsd3d_usd.sim.metrics import AgentBox
from lsd3d_usd.sensors.camera import camera_in_ego, rig_camera
from lsd3d_usd.views import labels as L
from lsd3d_usd.views.boxes import Box

SCORES_TOPIC = "/sim/scores"
FALLBACK_HEIGHT = {"vehicle": 1.6, "cyclist": 1.7, "pedestrian": 1.75}   # m


@dataclass
class _Sweep:
    """The fields of views.lidar_sweep.Sweep that McapWriter reads, from a padded observation."""
    xyz: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    class_id: np.ndarray
    range: np.ndarray

    @classmethod
    def of(cls, obs: dict) -> "_Sweep":
        n = int(obs["count"])
        xyz = np.asarray(obs["points"][:n], np.float32)
        return cls(xyz, obs["intensity"][:n], obs["ring"][:n], obs["class"][:n],
                   np.linalg.norm(xyz, axis=1))


class EpisodeMcap:
    """One episode's MCAP log in ``folder`` (episode_<index>.mcap, written as a hidden partial
    file and renamed by `close`). `write(obs, info)` after reset and after every step."""

    def __init__(self, folder: Path | None, env, index: int, writer=None):
        self.env = env
        self.stem = f"episode_{index:03d}"
        rig = env.sensors
        cams = list(rig.cameras)
        # K does not depend on the ego pose: one per camera for the whole episode
        self.K = {c.name: np.asarray(rig_camera(c, np.eye(4), rig.width).K, np.float64)
                  for c in cams}
        self.ego_from_camera = {c.name: camera_in_ego(c) for c in cams}
        scene_path = Path(env.scene.root)
        plan = LogPlan(int(index), scene_path, scene_path.parent.name, list(env.route.ids),
                       f"{scene_path.parent.name}:{','.join(env.route.ids)}")
        ego_from_lidar = None if rig.lidar is None else rig.lidar.ego_from_sensor()
        self.info = LogInfo(plan, env.settings.rig, cams, rig.lidar, rig.width, None,
                            rig.instances, env.scene.layout, self.ego_from_camera,
                            ego_from_lidar, list(env.route.ids))
        # ``writer``: another sink of the same messages (sim.live: a Foxglove WebSocket server)
        self.writer = writer or McapWriter(Path(folder), None, stem=self.stem,
                                           boxes_with_cameras=False)
        self.writer.begin_log(self.info)
        self._actor_of = self._actor_index()

    def _actor_index(self) -> dict[str, int]:
        """Box id -> index into env.actors. SimScene.actors_for builds them as the ego, then
        one per agent named /World/Actors/Sim/<Label>_<q> (q: the vehicle slots, ids
        vehicle:k / cyclist:k, then the pedestrians, pedestrian:k), then the scene's parked
        actors (parked:<prim path>)."""
        n_slots = len(self.env.world.slots)
        out = {}
        for q, a in enumerate(self.env.actors.actors):
            if a.role == "parked":
                out[f"parked:{a.path}"] = q
            elif a.path.startswith("/World/Actors/Sim/"):
                label, k = a.path.rsplit("/", 1)[1].rsplit("_", 1)
                k = int(k)
                out[f"{label.lower()}:{k if k < n_slots else k - n_slots}"] = q
        return out

    def _boxes(self, boxes: list[dict]) -> list[Box]:
        """info["boxes"] (sim.metrics.AgentBox dicts) as 3D boxes for the writer."""
        env = self.env
        placed = env.actors.transforms()
        dims = [a.dims for a in env.actors.actors]
        cls = env.sensors.instances.class_ids()
        out = []
        for b in map(AgentBox.from_json, boxes):
            q = self._actor_of.get(b.id)
            if q is not None:
                h, z0, cid = float(dims[q][2]), float(placed[q][2, 3]), int(cls[q])
            else:
                h = FALLBACK_HEIGHT.get(b.kind, 1.6)
                z0, cid = float(env.ego.z), CLASS_ID.get(b.kind, L.UNLABELLED)
            yaw = float(b.yaw)
            (x, y), (vx, vy) = b.center, b.velocity
            out.append(Box(b.id, b.kind, cid, b.kind, (x, y, z0 + h / 2), (b.length, b.width, h),
                           (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)), (vx, vy, 0.0),
                           yaw=yaw))
        return out

    def write(self, obs: dict, info: dict) -> None:
        from lsd3d_usd.sim.episodes import _jsonable
        env = self.env
        s = Sample(None, float(env.t), env.ego.matrix())
        for name, d in (obs.get("cameras") or {}).items():
            s.cameras.append(CameraShot(name, d["rgb"], self.K[name], self.ego_from_camera[name],
                                        None))
        if "lidar" in obs:
            s.lidar = LidarShot(LIDAR_CHANNEL, _Sweep.of(obs["lidar"]), self.info.ego_from_lidar)
        s.boxes = self._boxes(info["boxes"])
        self.writer.write(s)
        self.writer.log_json(SCORES_TOPIC, _jsonable({"t": info["t"], "step": info["step"],
                                                      **info["scores"]}), s.time)

    def close(self) -> str:
        """Finish the file; its name in the episode folder."""
        return self.writer.end_log()["file"]
