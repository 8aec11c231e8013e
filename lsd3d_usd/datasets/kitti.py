"""The KITTI 3D object writer: ROOT/training/{image_2, velodyne, label_2, calib}/NNNNNN.* for
the rig's first camera (the front) at every keyframe, and ROOT/ImageSets/train.txt. Frame ids
run over the logs in order (log k's keyframe j is k * keyframes per log + j).

As the KITTI object devkit documents them:
  image_2   PNG (8-bit sRGB) of the front camera
  velodyne  float32 x, y, z, reflectance per point, in the LiDAR frame (x forward, y left,
            z up) at the sweep's start; reflectance is the model's intensity in [0, 1]
  label_2   per object: type truncated occluded alpha left top right bottom height width
            length x y z rotation_y; the 2D box is the tight box of the object's pixels (pixel
            edges: right / bottom are one past the last pixel), the location the bottom centre
            of its 3D box in the camera frame (x right, y down, z forward), rotation_y about
            the camera's y axis (0: the object faces the camera's x axis), alpha the
            observation angle (rotation_y - atan2(x, z)); truncated the fraction of the
            projected 3D box outside the image; occluded from the visible fraction
            (>= 0.8: 0, >= 0.4: 1, > 0: 2, else 3)
  calib     P0..P3 = K [I | 0] (one camera, already rectified), R0_rect = I,
            Tr_velo_to_cam (camera from LiDAR), Tr_imu_to_velo (LiDAR from the ego frame,
            which stands for KITTI's IMU)
Objects: every actor with pixels in the front camera. Types: car -> Car, van -> Van,
truck -> Truck, bus -> Misc, pedestrian -> Pedestrian, cyclist -> Cyclist.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsd3d_usd import scene as S
from lsd3d_usd.datasets.writers import encode_image, write_bytes
from lsd3d_usd.views.boxes import Box, CameraBox

KITTI_TYPE = {"car": "Car", "van": "Van", "truck": "Truck", "bus": "Misc"}
CLASS_TYPE = {"pedestrian": "Pedestrian", "cyclist": "Cyclist"}


def kitti_type(cls: str, kind: str) -> str:
    if cls == "vehicle":
        return KITTI_TYPE.get(kind, "Car")
    return CLASS_TYPE.get(cls, "Misc")


def occluded(visible: float) -> int:
    return 0 if visible >= 0.8 else 1 if visible >= 0.4 else 2 if visible > 0 else 3


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def label_line(b: Box, entry: CameraBox, cam_from_world: np.ndarray) -> str:
    R = Rotation.from_quat(b.rotation_xyzw).as_matrix()
    L_, W_, H_ = b.size
    bottom = np.asarray(b.center) - R[:, 2] * H_ / 2
    loc = cam_from_world[:3, :3] @ bottom + cam_from_world[:3, 3]
    d = cam_from_world[:3, :3] @ R[:, 0]
    ry = _wrap(np.arctan2(-d[2], d[0]))
    alpha = _wrap(ry - np.arctan2(loc[0], loc[2]))
    x0, y0, x1, y1 = entry.box_2d
    vals = [kitti_type(b.label, b.kind), f"{entry.truncated:.2f}",
            str(occluded(entry.visible_fraction)), f"{alpha:.4f}",
            f"{x0:.2f}", f"{y0:.2f}", f"{x1:.2f}", f"{y1:.2f}",
            f"{H_:.4f}", f"{W_:.4f}", f"{L_:.4f}",
            f"{loc[0]:.4f}", f"{loc[1]:.4f}", f"{loc[2]:.4f}", f"{ry:.4f}"]
    return " ".join(vals)


def _row(M) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(M, np.float64).ravel())


class KittiWriter:
    name = "kitti"
    files = ("training/image_2/*.png", "training/velodyne/*.bin", "training/label_2/*.txt",
             "training/calib/*.txt", "ImageSets/*.txt")
    needs_lidar = True
    record_shape = {"ids": [str]}       # datasets.build.record_problem

    def __init__(self, root: Path, options):
        self.root = Path(root)

    def begin_log(self, info) -> None:
        self.info = info
        self.cam = info.cameras[0].name
        self.per_log = info.timeline.counts()["keyframes"]
        self.ids = []
        self.sent = 0                # ids already in a checkpoint
        self.ego_from_cam = info.ego_from_camera[self.cam]
        self.velo_to_cam = np.linalg.inv(self.ego_from_cam) @ info.ego_from_lidar

    def write(self, s) -> None:
        if not s.keyframe:
            return
        shot = next(c for c in s.cameras if c.channel == self.cam)
        fid = f"{self.info.plan.index * self.per_log + s.tick.keyframe_index:06d}"
        t = self.root / "training"
        write_bytes(t / "image_2" / f"{fid}.png", encode_image(shot.image, "png"))
        sw = s.lidar.sweep
        pts = np.empty((len(sw.range), 4), np.float32)
        pts[:, :3], pts[:, 3] = sw.xyz, sw.intensity
        write_bytes(t / "velodyne" / f"{fid}.bin", pts.tobytes())
        cam_from_world = np.linalg.inv(s.world_from_ego @ self.ego_from_cam)
        seen = [(b, b.cameras.get(self.cam)) for b in s.boxes]
        lines = [label_line(b, e, cam_from_world) for b, e in seen
                 if e is not None and e.box_2d is not None]
        write_bytes(t / "label_2" / f"{fid}.txt", "".join(ln + "\n" for ln in lines).encode())
        P = np.hstack([shot.K, np.zeros((3, 1))])
        calib = [f"P{i}: {_row(P)}" for i in range(4)]
        calib += [f"R0_rect: {_row(np.eye(3))}", f"Tr_velo_to_cam: {_row(self.velo_to_cam[:3])}",
                  f"Tr_imu_to_velo: {_row(np.linalg.inv(self.info.ego_from_lidar)[:3])}"]
        write_bytes(t / "calib" / f"{fid}.txt", ("\n".join(calib) + "\n").encode())
        self.ids.append(fid)

    def checkpoint(self) -> dict:
        """The frame ids written since the previous checkpoint."""
        delta, self.sent = self.ids[self.sent:], len(self.ids)
        return {"ids": delta}

    def restore(self, info, deltas: list) -> None:
        self.begin_log(info)
        self.ids = [i for d in deltas for i in d["ids"]]
        self.sent = len(self.ids)

    def end_log(self) -> dict:
        return {"ids": self.ids}

    def finish(self, records: list) -> dict:
        ids = [i for r in records for i in r["ids"]]
        (self.root / "ImageSets").mkdir(parents=True, exist_ok=True)
        S.atomic_write_text(self.root / "ImageSets" / "train.txt", "".join(i + "\n" for i in ids))
        return {"frames": len(ids)}
