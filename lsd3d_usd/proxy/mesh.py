"""Mesh containers for the proxy: one small part per object, merged per chunk and class.

A `MeshPart` is one object (a building, a curb piece, a road patch) with a
semantic class and a stable id. Parts are merged per class by concatenating
arrays (milliseconds) rather than by a boolean union (seconds for hundreds of
parts); the merged `ClassMesh` keeps a per-face index into its part ids so a
face can still be traced back to the object it came from.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Semantic class names (must match lsd3d_usd.semantics.CLASSES; a test checks).
ROAD = "road"
LANE_MARKING = "lane_marking"
CURB = "curb"
SIDEWALK = "sidewalk"
CROSSWALK = "crosswalk"
BUILDING = "building"
VEGETATION = "vegetation"
VEHICLE = "vehicle"
POLE = "pole"
SIGN = "sign"
TERRAIN = "terrain"
TRAFFIC_LIGHT = "traffic_light"

PROXY_CLASSES = (ROAD, LANE_MARKING, CURB, SIDEWALK, CROSSWALK, BUILDING, VEGETATION,
                 VEHICLE, POLE, SIGN, TERRAIN, TRAFFIC_LIGHT)

# Faces whose area is below this (m^2) count as degenerate.
MIN_FACE_AREA = 1e-9


@dataclass
class MeshPart:
    """One object: triangles, semantic class, stable id.

    ``solid`` parts must be closed (watertight, outward normals); open parts
    (ground patches, markings) must face up (+Z) unless ``faces_up`` is False
    (surfaces reconstructed from point clouds face any way).
    """
    vertices: np.ndarray            # (N, 3) float64
    faces: np.ndarray               # (M, 3) int32, counter-clockwise seen from outside
    cls: str
    part_id: str
    solid: bool = False
    color: tuple[float, float, float] | None = None   # linear RGB override of the class colour
    faces_up: bool = True

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32).reshape(-1, 3)

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))

    def bounds(self) -> np.ndarray:
        """(2, 3) min/max corner."""
        if len(self.vertices) == 0:
            return np.zeros((2, 3))
        return np.stack([self.vertices.min(0), self.vertices.max(0)])


@dataclass
class ClassMesh:
    """All parts of one class in one chunk, concatenated."""
    vertices: np.ndarray            # (N, 3) float64
    faces: np.ndarray               # (M, 3) int32
    cls: str
    part_ids: tuple[str, ...]
    face_part: np.ndarray           # (M,) int32 index into part_ids
    name: str = ""
    part_colors: tuple = ()         # per part: linear RGB or None (class colour)

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))


def face_areas_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Areas (M,) and unnormalised normals (M,3) (cross products) of the triangles."""
    v = vertices[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return 0.5 * np.linalg.norm(n, axis=1), n


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray,
                    min_area: float = MIN_FACE_AREA) -> np.ndarray:
    """Faces without zero-area or repeated-index triangles."""
    if len(faces) == 0:
        return faces
    area, _ = face_areas_normals(vertices, faces)
    keep = ((area > min_area) & (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
            & (faces[:, 0] != faces[:, 2]))
    return faces[keep]


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove vertices no face uses (and reindex)."""
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces].astype(np.int32)


def check_part(part: MeshPart) -> list[str]:
    """Problems with a part (empty list when valid).

    Checks: finite vertices, indices in range, no degenerate faces; solids
    watertight with consistent winding and positive volume (outward normals);
    open parts facing up.
    """
    errs = []
    v, f = part.vertices, part.faces
    where = f"part {part.part_id!r} ({part.cls})"
    if len(f) == 0:
        return [f"{where}: no faces"]
    if not np.isfinite(v).all():
        errs.append(f"{where}: non-finite vertices")
        return errs
    if f.min() < 0 or f.max() >= len(v):
        errs.append(f"{where}: face index out of range")
        return errs
    area, n = face_areas_normals(v, f)
    if (area <= MIN_FACE_AREA).any():
        errs.append(f"{where}: {int((area <= MIN_FACE_AREA).sum())} degenerate faces")
    if part.solid:
        # local import: not loaded for --help
        import trimesh
        tm = trimesh.Trimesh(v, f, process=False, validate=False)
        if not tm.is_watertight:
            errs.append(f"{where}: solid is not watertight")
        elif not tm.is_winding_consistent:
            errs.append(f"{where}: inconsistent winding")
        elif not tm.volume > 0:
            errs.append(f"{where}: normals point inwards (volume {tm.volume:.3g})")
    elif part.faces_up:
        good = area > MIN_FACE_AREA
        if good.any() and (n[good, 2] <= 0).any():
            errs.append(f"{where}: {int((n[good, 2] <= 0).sum())} faces of an open part face down")
    return errs


def merge_parts(parts: list[MeshPart], prefix: str = "") -> dict[str, ClassMesh]:
    """Concatenate parts per class. Returns {class: ClassMesh}, classes in first-seen order."""
    by_cls: dict[str, list[MeshPart]] = {}
    for p in parts:
        if p.n_faces:
            by_cls.setdefault(p.cls, []).append(p)
    out = {}
    for cls, ps in by_cls.items():
        nv = np.cumsum([0] + [len(p.vertices) for p in ps])
        verts = np.concatenate([p.vertices for p in ps])
        faces = np.concatenate([p.faces + nv[k] for k, p in enumerate(ps)]).astype(np.int32)
        face_part = np.repeat(np.arange(len(ps), dtype=np.int32), [p.n_faces for p in ps])
        out[cls] = ClassMesh(verts, faces, cls, tuple(p.part_id for p in ps), face_part,
                             name=f"{prefix}{cls}", part_colors=tuple(p.color for p in ps))
    return out


def transform_points(points: np.ndarray, yaw: float = 0.0,
                     translate=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Rotate about +Z by yaw (radians), then translate."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return points @ R.T + np.asarray(translate, dtype=np.float64)
