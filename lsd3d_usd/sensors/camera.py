"""A camera on the ego: where it is mounted and what it sees, and its pose and camera for a
frame (render.camera.Camera). Ego frame: x forward, y left, z up, origin on the ground below
the centre of the rear axle.

In a rig file::

    [[sensor]]
    type = "camera"
    name = "Front"                 # the prim's and the output folder's name
    hfov = 50.4                    # horizontal field of view, degrees
    size = [1920, 1280]            # native width, height (the aspect of every render)
    mount = {x = 1.55, y = 0.0, z = 2.10, yaw = 0.0, pitch = 0.0}   # m; deg, yaw + = left,
                                                                     # pitch + = looking down
    # rate_hz = 12.0               # frames per second (default: the command's rate)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.sensors.tables import known_keys, mount, number

KEYS = {"type", "name", "hfov", "size", "mount", "rate_hz"}
MOUNT_KEYS = ("x", "y", "z", "yaw", "pitch")
MAX_SIZE = 16384


@dataclass(frozen=True)
class CameraModel:
    name: str
    yaw_deg: float                  # about ego +Z, 0 = forward, + = left
    hfov_deg: float
    mount: tuple                    # (x, y, z) in the ego frame, metres
    size: tuple                     # native (width, height)
    pitch_deg: float = 0.0          # + = looking down
    rate_hz: float | None = None    # None: the rate of the command that renders it

    kind = "camera"

    def height_for(self, width: int) -> int:
        """Render height at ``width`` with the camera's native aspect."""
        return max(1, int(round(int(width) * self.size[1] / self.size[0])))

    @classmethod
    def from_table(cls, table: dict, where: str) -> CameraModel:
        known_keys(table, KEYS, where)
        name = table.get("name")
        if not isinstance(name, str) or not name.isidentifier():
            raise InputError(f"{where}: name: a name like CAM_FRONT (letters, digits, _), "
                             f"got {name!r}")
        hfov = number(table, "hfov", where)
        if not 0.0 < hfov < 180.0:
            raise InputError(f"{where}: hfov: {hfov} is outside (0, 180) degrees")
        size = table.get("size")
        if (not isinstance(size, list) or len(size) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_SIZE
                           for v in size)):
            raise InputError(f"{where}: size: [width, height] in pixels (1 .. {MAX_SIZE}), "
                             f"got {size!r}")
        x, y, z, yaw, pitch = mount(table, MOUNT_KEYS, where)
        if not -90.0 < pitch < 90.0:
            raise InputError(f"{where}: mount: pitch: {pitch} is outside (-90, 90) degrees")
        rate = None
        if "rate_hz" in table:
            rate = number(table, "rate_hz", where)
            if not 0.0 < rate <= 1000.0:
                raise InputError(f"{where}: rate_hz: {rate} is outside (0, 1000]")
        return cls(name, yaw, hfov, (x, y, z), tuple(size), pitch, rate)


RigCamera = CameraModel   # the name the rig code used before sensors/ existed


def camera_in_ego(cam: CameraModel) -> np.ndarray:
    """Ego-from-camera pose (OpenCV camera axes) of a rig camera."""
    y, p = np.radians(cam.yaw_deg), np.radians(cam.pitch_deg)
    eye = np.asarray(cam.mount, np.float64)
    fwd = np.array([np.cos(y) * np.cos(p), np.sin(y) * np.cos(p), -np.sin(p)])
    return look_at(eye, eye + fwd, (0.0, 0.0, 1.0))


def rig_camera(cam: CameraModel, ego: np.ndarray, width: int) -> Camera:
    """The camera at render width ``width`` (height from its native aspect) for ego pose ``ego``."""
    return Camera.from_fov(int(width), cam.height_for(width), cam.hfov_deg, ego @ camera_in_ego(cam),
                           near=0.1, far=2000.0)
