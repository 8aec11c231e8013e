"""Multi-camera sensor rigs: the cameras' placement on the ego car.

The Waymo-like rig ``waymo5`` (see docs/actors.md for the facts it follows): five cameras,
front, front-left, front-right, side-left and side-right, ~50 deg horizontal field of view
each, yawed 0, +-45 and +-90 deg, mounted ~2 m above the ground on the roof. The ego frame
is x forward, y left, z up, origin on the ground at the centre of the rear axle. OVERVIEW is
a third-person camera behind and above the ego.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsd3d_usd.render.camera import Camera, look_at


@dataclass(frozen=True)
class RigCamera:
    name: str
    yaw_deg: float                  # about ego +Z, 0 = forward, + = left
    hfov_deg: float
    mount: tuple                    # (x, y, z) in the ego frame, metres
    size: tuple                     # native (width, height)
    pitch_deg: float = 0.0          # + = looking down

    def height_for(self, width: int) -> int:
        """Render height at ``width`` with the camera's native aspect."""
        return max(1, int(round(int(width) * self.size[1] / self.size[0])))


WAYMO5 = (
    RigCamera("Front", 0.0, 50.4, (1.55, 0.00, 2.10), (1920, 1280)),
    RigCamera("FrontLeft", 45.0, 50.4, (1.50, 0.45, 2.08), (1920, 1280)),
    RigCamera("FrontRight", -45.0, 50.4, (1.50, -0.45, 2.08), (1920, 1280)),
    RigCamera("SideLeft", 90.0, 50.4, (1.25, 0.85, 2.02), (1920, 886)),
    RigCamera("SideRight", -90.0, 50.4, (1.25, -0.85, 2.02), (1920, 886)),
)
# nuScenes' six cameras (1600 x 900) as its calibration places them on the ego (x forward,
# y left, z up; fields of view from the focal lengths: 2 atan(800 / f))
NUSCENES6 = (
    RigCamera("CAM_FRONT", 0.0, 64.6, (1.70, 0.02, 1.51), (1600, 900)),
    RigCamera("CAM_FRONT_LEFT", 55.0, 64.3, (1.52, 0.49, 1.51), (1600, 900)),
    RigCamera("CAM_FRONT_RIGHT", -55.0, 64.4, (1.50, -0.49, 1.52), (1600, 900)),
    RigCamera("CAM_BACK", 180.0, 89.4, (0.03, 0.00, 1.57), (1600, 900)),
    RigCamera("CAM_BACK_LEFT", 110.0, 64.2, (1.03, 0.48, 1.56), (1600, 900)),
    RigCamera("CAM_BACK_RIGHT", -110.0, 64.5, (1.04, -0.48, 1.57), (1600, 900)),
)
RIGS = {"waymo5": WAYMO5, "nuscenes6": NUSCENES6}
# the LiDAR a rig carries unless --lidar says otherwise (views.sensors presets)
RIG_LIDAR = {"waymo5": None, "nuscenes6": "hdl32"}
OVERVIEW = RigCamera("Overview", 0.0, 60.0, (-14.0, 0.0, 8.0), (1920, 1080), pitch_deg=18.0)


def camera_in_ego(cam: RigCamera) -> np.ndarray:
    """Ego-from-camera pose (OpenCV camera axes) of a rig camera."""
    y, p = np.radians(cam.yaw_deg), np.radians(cam.pitch_deg)
    eye = np.asarray(cam.mount, np.float64)
    fwd = np.array([np.cos(y) * np.cos(p), np.sin(y) * np.cos(p), -np.sin(p)])
    return look_at(eye, eye + fwd, (0.0, 0.0, 1.0))


def rig_camera(cam: RigCamera, ego: np.ndarray, width: int) -> Camera:
    """The camera at render width ``width`` (height from its native aspect) for ego pose ``ego``."""
    return Camera.from_fov(int(width), cam.height_for(width), cam.hfov_deg, ego @ camera_in_ego(cam),
                           near=0.1, far=2000.0)


def check_rig_width(rig_name: str, width: int, where: str, overview: bool = False) -> None:
    """Every camera of the rig at ``width`` (heights follow each camera's aspect) within the
    image-pixel limit, before anything is rendered."""
    from lsd3d_usd.limits import check_image_size
    for c in list(RIGS.get(rig_name, ())) + ([OVERVIEW] if overview else []):
        check_image_size(width, c.height_for(width), f"{where} ({c.name})")
