"""Pinhole cameras: the numeric core's OpenCV convention and UsdGeom.Camera.

Core convention (as gsplat): ``viewmat`` is the 4x4 world->camera matrix with
OpenCV camera axes (x right, y down, z forward); ``K`` holds pixel intrinsics
with pixel centres at +0.5 (pixel (i, j) covers [i, i+1) x [j, j+1)).

A USD camera looks down its local -Z with +Y up, so the OpenCV camera frame is
the USD camera frame with y and z negated. Lens and filmback attributes
(focalLength, horizontal/verticalAperture and their offsets) are in tenths of a
scene unit (UsdGeomCamera spec); only their ratios enter the projection, so the
unit matters only when we author values (``to_usd``), where we write physically
sensible millimetre values converted to the stage's tenths of a unit.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom

from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import check_image_size

# OpenCV camera axes from USD camera axes: flip y and z.
_CV_FROM_USD = np.diag([1.0, -1.0, -1.0, 1.0])

CONFORM_POLICIES = ("horizontal", "vertical", "stretch")
DEFAULT_WIDTH = 960  # from_usd's image width when neither width nor height is given


@dataclass
class Camera:
    """A pinhole camera. ``pose`` is the 4x4 float64 world-from-camera transform
    (OpenCV axes: columns 0..2 are the camera's right, down and forward
    directions in world space; column 3 its centre)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    near: float = 0.1
    far: float = 10000.0

    def __post_init__(self):
        self.pose = np.asarray(self.pose, dtype=np.float64).reshape(4, 4)
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera: image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise InputError(f"camera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (0 < self.near < self.far):
            raise InputError(f"camera: need 0 < near < far, got near={self.near}, far={self.far}")
        if not np.all(np.isfinite(self.pose)):
            raise InputError("camera: pose contains NaN or Inf")

    @property
    def K(self) -> np.ndarray:
        """3x3 pixel intrinsics (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def viewmat(self) -> np.ndarray:
        """4x4 world->camera (OpenCV axes), float64: the rigid inverse of ``pose``."""
        R = self.pose[:3, :3]
        t = self.pose[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center(self) -> np.ndarray:
        return self.pose[:3, 3].copy()

    def with_resolution(self, width: int, height: int) -> "Camera":
        """The same view at another resolution (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                       cx=self.cx * sx, cy=self.cy * sy)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N,3) -> (pixel coords (N,2), camera depth z (N,))."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        V = self.viewmat
        pc = p @ V[:3, :3].T + V[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], axis=1)
        return uv, z

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x_deg: float, pose=None,
                 near: float = 0.1, far: float = 10000.0) -> "Camera":
        """Square pixels, centred principal point, horizontal field of view in degrees."""
        if not 0.0 < fov_x_deg < 180.0:
            raise InputError(f"camera: horizontal field of view must be in (0, 180) degrees, got {fov_x_deg}")
        fx = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2.0)
        return cls(width, height, fx, fx, width / 2.0, height / 2.0,
                   np.eye(4) if pose is None else pose, near, far)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-from-camera pose (OpenCV axes) of a camera at ``eye`` looking at
    ``target``, with image-up as close to ``up`` as possible."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    n = np.linalg.norm(fwd)
    if n == 0.0:
        raise InputError("look_at: eye and target coincide")
    fwd /= n
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-9 * max(np.linalg.norm(up), 1e-300):
        raise InputError("look_at: viewing direction is parallel to the up vector")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, fwd, eye
    return pose


def pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through every pixel centre: origins (H,W,3) and unit
    directions (H,W,3), float64."""
    return np.broadcast_to(camera.pose[:3, 3], (camera.height, camera.width, 3)).copy(), \
        pixel_directions(camera)


def pixel_directions(camera: Camera) -> np.ndarray:
    """(H,W,3) float64 unit world-space directions through every pixel centre. Broadcast
    rather than a (H·W,3)@(3,3) matmul: 2-3x faster, equal to the matmul within 3e-16
    (GGDS recomputes these every step instead of keeping them per view)."""
    x = (np.arange(camera.width, dtype=np.float64) + 0.5 - camera.cx) / camera.fx
    y = (np.arange(camera.height, dtype=np.float64) + 0.5 - camera.cy) / camera.fy
    R = camera.pose[:3, :3]
    d = x[None, :, None] * R[:, 0] + y[:, None, None] * R[:, 1] + R[:, 2]
    d /= np.sqrt(np.einsum("hwc,hwc->hw", d, d))[..., None]
    return d


# --- USD ------------------------------------------------------------------------------

def _tenth_unit_mm(stage) -> float:
    """Millimetres per 'tenth of a scene unit' on this stage."""
    return 100.0 * UsdGeom.GetStageMetersPerUnit(stage)


def from_usd(prim, time=None, width: int | None = None, height: int | None = None,
             conform: str = "horizontal") -> Camera:
    """Camera from a UsdGeom.Camera prim at ``time`` (default: the default time).

    ``width``/``height`` default to DEFAULT_WIDTH (960) and the aperture's aspect. When the image
    aspect differs from the filmback's, ``conform`` decides: "horizontal" keeps
    the horizontal field of view (square pixels), "vertical" keeps the vertical
    one, "stretch" keeps both (non-square pixels).
    """

    if conform not in CONFORM_POLICIES:
        raise InputError(f"camera: conform must be one of {CONFORM_POLICIES}, got {conform!r}")
    if prim is None or not prim.IsValid():
        raise InputError("camera: invalid camera prim")
    if not prim.IsA(UsdGeom.Camera):
        raise InputError(f"camera: prim {prim.GetPath()} is a {prim.GetTypeName() or 'typeless prim'}, "
                         "not a Camera")
    cam = UsdGeom.Camera(prim)
    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    where = f"camera {prim.GetPath()}"
    if cam.GetProjectionAttr().Get(t) not in (None, UsdGeom.Tokens.perspective):
        raise InputError(f"{where}: only perspective projection is supported")
    f = float(cam.GetFocalLengthAttr().Get(t))
    hA = float(cam.GetHorizontalApertureAttr().Get(t))
    vA = float(cam.GetVerticalApertureAttr().Get(t))
    hO = float(cam.GetHorizontalApertureOffsetAttr().Get(t) or 0.0)
    vO = float(cam.GetVerticalApertureOffsetAttr().Get(t) or 0.0)
    clip = cam.GetClippingRangeAttr().Get(t)
    if not (f > 0 and hA > 0 and vA > 0):
        raise InputError(f"{where}: focalLength and apertures must be positive "
                         f"(focalLength={f}, horizontalAperture={hA}, verticalAperture={vA})")
    if width is None and height is None:
        width = DEFAULT_WIDTH
    if width is None:
        width = max(1, round(height * hA / vA))
    if height is None:
        height = max(1, round(width * vA / hA))
    # a width alone takes its height from the aperture: the image size is known only here
    check_image_size(width, height, f"{where}: image")
    fx = f * width / hA
    fy = f * height / vA
    if conform == "horizontal":
        fy = fx
    elif conform == "vertical":
        fx = fy
    # Window centre is at offset/focal (USD camera axes, y up); see module doc.
    cx = width / 2.0 - hO * fx / f
    cy = height / 2.0 + vO * fy / f
    near, far = float(clip[0]), float(clip[1])

    m = Gf.Matrix4d(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t))
    M = np.array(m, dtype=np.float64).T  # USD stores row-vector matrices
    R = M[:3, :3]
    # Drop scale/shear: a camera's pose is rigid; scaled parents are common in DCC exports.
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        raise InputError(f"{where}: world transform is mirrored (negative determinant)")
    M_rigid = np.eye(4)
    M_rigid[:3, :3], M_rigid[:3, 3] = Rn, M[:3, 3]
    pose = M_rigid @ _CV_FROM_USD
    return Camera(width, height, fx, fy, cx, cy, pose, near, far)


def to_usd(stage, path: str, camera: Camera, time=None, horizontal_aperture_mm: float = 36.0):
    """Author ``camera`` as a UsdGeom.Camera at ``path`` (its parent's transform is
    taken into account so the world pose is exact). Returns the UsdGeom.Camera.

    The filmback is ``horizontal_aperture_mm`` wide; the vertical aperture and the
    focal length follow from the intrinsics, so ``from_usd(..., conform="stretch")``
    gives back the same K at the same resolution."""

    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    cam = UsdGeom.Camera.Define(stage, Sdf.Path(path))
    unit = _tenth_unit_mm(stage)
    hA = horizontal_aperture_mm / unit
    f = camera.fx * hA / camera.width
    vA = camera.height * f / camera.fy
    hO = (camera.width / 2.0 - camera.cx) * f / camera.fx
    vO = (camera.cy - camera.height / 2.0) * f / camera.fy
    cam.GetProjectionAttr().Set(UsdGeom.Tokens.perspective)
    cam.GetFocalLengthAttr().Set(float(f), t)
    cam.GetHorizontalApertureAttr().Set(float(hA), t)
    cam.GetVerticalApertureAttr().Set(float(vA), t)
    cam.GetHorizontalApertureOffsetAttr().Set(float(hO), t)
    cam.GetVerticalApertureOffsetAttr().Set(float(vO), t)
    cam.GetClippingRangeAttr().Set(Gf.Vec2f(camera.near, camera.far), t)

    world = camera.pose @ _CV_FROM_USD  # USD camera local-to-world (column vectors)
    parent = cam.GetPrim().GetParent()
    if parent and parent.IsA(UsdGeom.Xformable):
        P = np.array(UsdGeom.Xformable(parent).ComputeLocalToWorldTransform(t), dtype=np.float64).T
        local = np.linalg.solve(P, world)
    else:
        local = world
    xf = UsdGeom.Xformable(cam)
    op = None
    for existing in xf.GetOrderedXformOps():
        if existing.GetOpType() == UsdGeom.XformOp.TypeTransform:
            op = existing
    if op is None:
        xf.ClearXformOpOrder()
        op = xf.AddTransformOp(UsdGeom.XformOp.PrecisionDouble)
    op.Set(Gf.Matrix4d(local.T.tolist()), t)
    return cam
