"""A LiDAR sweep of a scene from a moving ego: rays from render.lidar's model, each column at its
own time and ego pose (rolling shutter), cast against the scene's surfels and the mesh actors
placed at that time (render.lidar.cast), labelled with the classes and instances of the camera
ground truth (views.labels), and written as a point cloud.

Points (one per return): ``xyz`` in the sensor frame at the sweep's start (the frame of the
sweep's timestamp; motion-compensated, so a static world is one rigid cloud), ``xyz_world``,
``origin_world`` (the beam's origin at its column's time), ``range`` (metres along the beam),
``intensity``, ``ring``, ``column``, ``t`` (seconds after the sweep's start), ``class_id``,
``instance_id``. The ego's own body returns nothing (as datasets remove self-returns).

Intensity is a model, not a measurement: the class's reflectivity (REFLECTIVITY, in [0, 1])
× |cos| of the angle between the beam and the surface normal × 1 / (1 + (range / 30 m)²).
Noise, when the model has it: a Gaussian range error of ``range_sigma`` and returns dropped
with ``drop_prob``, both seeded by (seed, sweep index): the same sweep twice is the same.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, UsdGeom

from lsd3d_usd import scene as S
from lsd3d_usd.render.lidar import MeshActors, RayHits, cast, rotate_columns, surfel_frames
from lsd3d_usd.semantics import CLASS_ID
from lsd3d_usd.sensors.lidar import LidarModel
from lsd3d_usd.views import labels as L
from lsd3d_usd.views.frame import surfel_codes

FALLOFF_M = 30.0
REFLECTIVITY = {"road": 0.10, "lane_marking": 0.70, "curb": 0.25, "sidewalk": 0.20,
                "crosswalk": 0.65, "building": 0.30, "vegetation": 0.40, "vehicle": 0.45,
                "pole": 0.35, "sign": 0.90, "terrain": 0.25, "traffic_light": 0.40,
                "pedestrian": 0.30, "cyclist": 0.35}
BEV_SIZE = 800            # px of the bird's-eye view
BEV_EXTENT = 100.0        # m across


def reflectivity_table() -> np.ndarray:
    """(256,) reflectivity per class id (0.3 where the table has none)."""
    r = np.full(256, 0.3)
    for name, v in REFLECTIVITY.items():
        if name in CLASS_ID:
            r[CLASS_ID[name]] = v
    return r


@dataclass
class Sweep:
    """The returns of one sweep (arrays of equal length) and its poses."""
    xyz: np.ndarray
    xyz_world: np.ndarray
    origin_world: np.ndarray
    range: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    column: np.ndarray
    t: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray
    world_from_sensor: np.ndarray            # at the sweep's start
    stats: dict = field(default_factory=dict)

    def arrays(self) -> dict:
        return {k: getattr(self, k) for k in ("xyz", "xyz_world", "origin_world", "range",
                                              "intensity", "ring", "column", "t", "class_id",
                                              "instance_id")}


class SurfelCache:
    """The kernel's arrays of the reader's surfels, made again only when they change."""

    def __init__(self):
        self._key = None
        self._value = None

    def get(self, field_):
        if field_ is None:
            return None
        if self._key is not field_:
            codes = surfel_codes(field_)
            self._value = (surfel_frames(field_.positions, field_.orientations, field_.scales,
                                         field_.opacities), codes % L.CODE)
            self._key = field_
        return self._value


def mesh_actors(actor_set, tcps: float) -> tuple[MeshActors | None, np.ndarray]:
    """The ActorSet's mesh actors for the LiDAR (the ego left out) and the index of each in the
    set; placed at any times by their transforms (invisible ones out of reach)."""
    if actor_set is None or not len(actor_set):
        return None, np.zeros(0, np.int64)
    keep = [q for q, a in enumerate(actor_set.actors) if a.role != "ego" and a.meshes]
    if not keep:
        return None, np.zeros(0, np.int64)
    V, F, lo, hi, blo, bhi, n = [], [], [], [], [], [], 0
    for q in keep:
        a = actor_set.actors[q]
        lo.append(sum(len(f) for f in F))
        for m in a.meshes:
            V.append(m.vertices)
            F.append(m.faces + n)
            n += len(m.vertices)
        hi.append(sum(len(f) for f in F))
        allv = np.concatenate([m.vertices for m in a.meshes])
        blo.append(allv.min(0))
        bhi.append(allv.max(0))
    faraway = np.eye(4)
    faraway[:3, 3] = 1e9        # an invisible actor: no ray reaches it

    def local_from_world(times):
        out = np.empty((len(times), len(keep), 4, 4))
        for g, t in enumerate(times):
            code = float(t) * tcps
            Ms = actor_set.transforms(code)
            vis = actor_set.visible(code)
            for i, q in enumerate(keep):
                out[g, i] = np.linalg.inv(Ms[q]) if vis[q] else faraway
        return out
    return (MeshActors(np.concatenate(V), np.concatenate(F), np.array(lo), np.array(hi),
                       np.array(blo), np.array(bhi), local_from_world), np.array(keep))


def sensor_poses(model: LidarModel, world_from_ego, t0: float) -> np.ndarray:
    """(C, 4, 4) world-from-sensor of each column; ``world_from_ego(times)`` (n, 4, 4)."""
    return world_from_ego(t0 + model.column_times()) @ model.ego_from_sensor()


def cast_sweep(model: LidarModel, poses: np.ndarray, frames, actors: MeshActors | None,
               t0: float) -> RayHits:
    """Rays of the model from column poses ``poses`` (C, 4, 4) against ``frames``
    (surfel_frames) and the mesh actors: render.lidar.cast."""
    d = model.directions()                                     # (R, C, 3) sensor frame
    dirs = rotate_columns(np.ascontiguousarray(poses[:, :3, :3]), np.ascontiguousarray(d))
    origins = poses[:, :3, 3]
    return cast(frames, actors, origins, dirs, t0 + model.column_times(),
                min_range=model.min_range, max_range=model.max_range), origins, dirs


def sweep(reader, model: LidarModel, world_from_ego, t0: float, tcps: float, instances,
          actors=None, cache: SurfelCache | None = None, seed: int = 0, index: int = 0) -> Sweep:
    """One sweep starting at ``t0`` seconds (see the module doc). ``reader``: a
    stage_data.SceneReader (its surfels around the sensor at t0); ``actors``: mesh_actors of
    the reader's ActorSet (made once per render); ``instances``: views.labels.Instances."""
    poses = sensor_poses(model, world_from_ego, t0)
    field_ = reader.surfels(t0 * tcps, near=poses[:, :3, 3][::max(1, model.columns // 8)])
    got = (cache or SurfelCache()).get(field_)
    frames, surfel_class = got if got is not None else (None, None)
    mesh, keep = actors if actors is not None else (None, np.zeros(0, np.int64))
    if frames is None:
        frames = surfel_frames(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 2)), np.zeros(0))
    hits, origins, dirs = cast_sweep(model, poses, frames, mesh, t0)
    ok = np.isfinite(hits.t)
    rng = np.random.default_rng([int(seed), int(index), 0x11DA])
    if model.drop_prob > 0:
        ok &= rng.uniform(size=ok.shape) >= model.drop_prob
    ring, col = np.nonzero(ok)
    r = hits.t[ring, col]
    if model.range_sigma > 0:
        r = r + rng.normal(0.0, model.range_sigma, r.shape)
    d = dirs[ring, col]
    o = origins[col]
    world = o + r[:, None] * d
    k = hits.surfel[ring, col]
    a = hits.actor[ring, col]
    cls = np.full(len(r), L.UNLABELLED, np.int64)
    inst = np.zeros(len(r), np.int64)
    normal = np.zeros((len(r), 3))
    s_rows = k >= 0
    if s_rows.any():
        cls[s_rows] = surfel_class[k[s_rows]]
        normal[s_rows] = frames.n[k[s_rows]]
    a_rows = a >= 0
    if a_rows.any():
        q = keep[a[a_rows]]
        cls[a_rows] = instances.class_ids()[q]
        inst[a_rows] = instances.ids[q]
        normal[a_rows] = _actor_normals(mesh, hits, ring[a_rows], col[a_rows], d[a_rows])
    cos = np.abs(np.einsum("ij,ij->i", normal, d))
    intensity = reflectivity_table()[np.clip(cls, 0, 255)] * cos / (1.0 + (r / FALLOFF_M) ** 2)
    M0 = (world_from_ego(np.array([t0])) @ model.ego_from_sensor())[0]
    inv = np.linalg.inv(M0)
    xyz = world @ inv[:3, :3].T + inv[:3, 3]
    return Sweep(xyz.astype(np.float32), world, o, r.astype(np.float32),
                 intensity.astype(np.float32), ring.astype(np.uint16), col.astype(np.uint32),
                 (model.column_times()[col]).astype(np.float32), cls.astype(np.uint8),
                 inst.astype(np.uint16), M0,
                 {"rays": int(ok.size), "returns": len(r), **hits.stats})


def _actor_normals(mesh: MeshActors, hits: RayHits, ring, col, d) -> np.ndarray:
    """Normals at mesh-actor hits (the faces the kernel reports)."""
    f = hits.face[ring, col]
    tri = mesh.vertices[mesh.faces[f]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


# ----------------------------------------------------------------------------- files
def write_sweep(out_dir: Path, name: str, sw: Sweep, ply: bool = True) -> dict:
    """OUT/<name>.npz (the arrays), OUT/<name>.ply (x y z intensity ring class instance, sensor
    frame), each written atomically."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {}
    tmp = out_dir / f".{name}.tmp{os.getpid()}.npz"
    np.savez_compressed(tmp, **sw.arrays(), world_from_sensor=sw.world_from_sensor)
    os.replace(tmp, out_dir / f"{name}.npz")
    files["npz"] = out_dir / f"{name}.npz"
    if ply:
        files["ply"] = write_ply(out_dir / f"{name}.ply", sw)
    return files


def write_ply(path: Path, sw: Sweep) -> Path:
    n = len(sw.range)
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                             ("ring", "<u2"), ("class_id", "u1"), ("instance_id", "<u2")])
    rec["x"], rec["y"], rec["z"] = sw.xyz[:, 0], sw.xyz[:, 1], sw.xyz[:, 2]
    rec["intensity"], rec["ring"] = sw.intensity, sw.ring
    rec["class_id"], rec["instance_id"] = sw.class_id, sw.instance_id
    head = ("ply\nformat binary_little_endian 1.0\ncomment lsd3d-usd LiDAR sweep, sensor frame\n"
            f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
            "property float intensity\nproperty ushort ring\nproperty uchar class_id\n"
            "property ushort instance_id\nend_header\n").encode()
    return S.atomic_write_bytes(path, head + rec.tobytes())


def bev_image(sw: Sweep, size: int = BEV_SIZE, extent: float = BEV_EXTENT) -> np.ndarray:
    """(size, size, 3) uint8 bird's-eye view of a sweep in the sensor frame (x up the image,
    y to the left), points coloured by class, the sensor at the centre; actors' points drawn
    3 px wide and lighter over the rest (a car 20 m out is a few points: seen at a glance)."""
    img = np.full((size, size, 3), 18, np.uint8)
    pal = L.palette()
    px = size / extent
    u = np.round(size / 2 - sw.xyz[:, 1] * px).astype(np.int64)
    v = np.round(size / 2 - sw.xyz[:, 0] * px).astype(np.int64)
    ok = (u >= 0) & (u < size) & (v >= 0) & (v < size)
    order = np.argsort(sw.xyz[ok, 2])            # higher points drawn last
    uu, vv, cc = u[ok][order], v[ok][order], sw.class_id[ok][order]
    img[vv, uu] = pal[cc]
    act = ok & (sw.instance_id > 0)
    lit = (pal[sw.class_id[act]] // 2 + 110).astype(np.uint8)    # lighter: dark on dark else
    for du in (-1, 0, 1):
        for dv in (-1, 0, 1):
            img[np.clip(v[act] + dv, 0, size - 1), np.clip(u[act] + du, 0, size - 1)] = lit
    c = size // 2
    img[c - 2:c + 3, c - 2:c + 3] = (255, 255, 255)
    return img


def usd_lidar_prim(stage, path: str, model: LidarModel) -> None:
    """The LiDAR as a USD prim (under the ego): its mount as the transform, its parameters as
    attributes, so a USD tool shows where it is."""
    x = UsdGeom.Xform.Define(stage, path)
    x.AddTransformOp().Set(Gf.Matrix4d(*model.ego_from_sensor().T.ravel().tolist()))
    prim = x.GetPrim()
    T = Sdf.ValueTypeNames
    prim.CreateAttribute("lsd3d:lidar:name", T.String, custom=True).Set(model.name)
    prim.CreateAttribute("lsd3d:lidar:elevationsDeg", T.FloatArray, custom=True).Set(
        [float(e) for e in model.elevations_deg])
    for key, tn, v in (("columns", T.Int, int(model.columns)), ("hfovDeg", T.Float, model.hfov_deg),
                       ("minRange", T.Float, model.min_range), ("maxRange", T.Float, model.max_range),
                       ("rotationHz", T.Float, model.rotation_hz),
                       ("rangeSigma", T.Float, model.range_sigma),
                       ("dropProb", T.Float, model.drop_prob)):
        prim.CreateAttribute(f"lsd3d:lidar:{key}", tn, custom=True).Set(v)
