"""Proxy from a point cloud (the paper's "predicted from point-cloud data" path).

Per chunk (same 100 m grid as the layout path):

1. voxelise the points on a world-aligned lattice (voxel ``v``, default 0.2 m),
   over the chunk box padded by enough voxels that every operation below sees
   the same neighbourhood in both chunks of a seam;
2. fill the ground: in columns near the data whose lowest occupied voxel is
   within ``ground_band`` of the fitted ground plane, everything below it is
   solid, so the ground becomes one upward surface instead of a thin slab;
3. close holes: binary closing (``closing`` iterations);
4. smooth the occupancy (Gaussian, sigma 0.7 voxel) and extract the 0.5 level
   set with marching cubes (scikit-image);
5. simplify by vertex clustering on a world-aligned lattice (cells of
   ``simplify`` voxels; written here), before cutting, so both chunks of a
   seam produce the same vertices there;
6. keep the faces whose centroid lies in the chunk (each face in one chunk);
7. label faces: from per-point labels (nearest point) when the cloud has
   them, else by height above the fitted ground plane (< ``ground_band``:
   road; non-ground connected components reaching ``building_height``:
   building; lower ones: vehicle) — a crude rule, documented as such.

Shells (walls sampled from both sides or once) give a closed thin surface
around them (outer and inner side ~1-2 voxels apart): no global hole filling,
because it is not local and would differ between chunks.
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes
from tqdm import tqdm

from lsd3d_usd import limits
from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import CHUNK_VOXELS, PLY_VERTICES
from lsd3d_usd.plyio import read_ply_vertices
from lsd3d_usd.scene import chunk_prim_name
from lsd3d_usd.semantics import CLASS_ID, CLASSES

from .mesh import BUILDING, ROAD, VEHICLE, MeshPart
from .usdio import write_proxy

LABEL_PROPS = ("label", "class", "semantic", "semantic_id", "scalar_label", "labels")


@dataclass(frozen=True)
class PointProxyParams:
    voxel: float = 0.2
    closing: int = 2
    simplify: float = 2.0          # vertex-clustering cell size in voxels (0 = off)
    chunk_size: float = 100.0
    sigma: float = 0.7             # Gaussian smoothing of the occupancy, voxels
    ground_band: float = 0.3       # m above the ground plane still counted as ground
    building_height: float = 3.0   # m: taller non-ground components are buildings
    min_points: int = 20

    def as_dict(self):
        return asdict(self)


# --------------------------------------------------------------------------- reading
def read_ply_points(path: str | Path, max_vertices: int | None = None
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) float64 and labels (N,) int32 or None from a PLY file's vertex element.

    ASCII and binary (little/big endian) PLY (lsd3d_usd.plyio: elements before the
    vertex element must have fixed-size properties; more than limits.PLY_VERTICES
    points, or ``max_vertices``, are refused before the body is read).
    """

    arr = read_ply_vertices(path, max_vertices)
    names = arr.dtype.names
    for c in ("x", "y", "z"):
        if c not in names:
            raise InputError(f"{path}: PLY vertex element has no '{c}' property")
    pts = np.column_stack([arr["x"], arr["y"], arr["z"]]).astype(np.float64)
    lab = next((arr[p] for p in LABEL_PROPS if p in names), None)
    return pts, (None if lab is None else np.asarray(lab).astype(np.int32))


def _npz_shape(z, key: str) -> tuple:
    """Shape of an array in an open .npz, from its header (nothing decompressed)."""
    fmt = np.lib.format
    with z.zip.open(key + ".npy") as fh:
        version = fmt.read_magic(fh)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _, _ = read(fh)
    return shape


def read_npz_points(path: str | Path, max_vertices: int | None = None
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    """NPZ with 'points' (N, 3) and optional 'labels' (N,) ids; optional 'classes'
    (names the ids index, mapped onto lsd3d_usd.semantics.CLASSES). More than
    limits.PLY_VERTICES points (or ``max_vertices``) are refused before decompressing."""
    path = Path(path)
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as e:
        raise InputError(f"{path}: cannot be read as .npz: {e}") from None
    key = next((k for k in ("points", "xyz", "positions") if k in z.files), None)
    if key is None:
        raise InputError(f"{path}: no 'points' array (has: {', '.join(z.files) or 'nothing'})")
    try:
        shape = _npz_shape(z, key)
    except Exception as e:
        raise InputError(f"{path}: array {key!r} cannot be read: {e}") from None
    n = int(np.prod(shape, dtype=object)) // 3 if shape else 0
    PLY_VERTICES.check(n, f"{path}: array {key!r}", max_vertices, what="point count")
    try:
        pts = np.asarray(z[key], dtype=np.float64)
    except (ValueError, TypeError) as e:
        raise InputError(f"{path}: array {key!r} is not numeric: {e}") from None
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise InputError(f"{path}: 'points' must be (N, 3), got {pts.shape}")
    labels = None
    if "labels" in z.files:
        labels = np.asarray(z["labels"]).astype(np.int32).reshape(-1)
        if len(labels) != len(pts):
            raise InputError(f"{path}: 'labels' has {len(labels)} entries for {len(pts)} points")
        if "classes" in z.files:
            names = [str(c) for c in z["classes"]]
            unknown = [c for c in names if c not in CLASS_ID]
            if unknown:
                raise InputError(f"{path}: class {unknown[0]!r} in 'classes' is not a known "
                                 "semantic class")
            lut = np.array([CLASS_ID[c] for c in names] + [-1], dtype=np.int32)
            labels = lut[np.where((labels >= 0) & (labels < len(names)), labels, len(names))]
    return pts[:, :3], labels


def read_cloud(path: str | Path, max_vertices: int | None = None
               ) -> tuple[np.ndarray, np.ndarray | None]:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    ext = p.suffix.lower()
    if ext == ".ply":
        pts, lab = read_ply_points(p, max_vertices)
    elif ext == ".npz":
        pts, lab = read_npz_points(p, max_vertices)
    else:
        raise InputError(f"{path}: point clouds must be .ply or .npz (got {ext or 'no extension'})")
    finite = np.isfinite(pts).all(1)
    if not finite.all():
        raise InputError(f"{path}: {int((~finite).sum())} points have non-finite coordinates")
    if lab is not None:
        bad = (lab < -1) | (lab >= len(CLASSES))
        if bad.any():
            raise InputError(f"{path}: label {int(lab[bad][0])} is not a class id "
                             f"(-1..{len(CLASSES) - 1}, see lsd3d_usd.semantics.CLASSES)")
        if (lab < 0).all():
            lab = None
    return pts, lab


# ----------------------------------------------------------------------- ground plane
def fit_ground_plane(points: np.ndarray, cell: float = 2.0, iters: int = 200,
                     thresh: float = 0.15, seed: int = 0) -> np.ndarray:
    """Plane (a, b, c) with z = a*x + b*y + c: RANSAC over the lowest point of each
    XY cell, then least squares over all points within ``thresh`` of it."""
    xy = np.floor(points[:, :2] / cell).astype(np.int64)
    order = np.lexsort((points[:, 2], xy[:, 1], xy[:, 0]))
    key = xy[order]
    first = np.ones(len(order), bool)
    first[1:] = (key[1:] != key[:-1]).any(1)
    low = points[order[first]]
    if len(low) < 3:
        return np.array([0.0, 0.0, float(np.median(points[:, 2]))])
    rng = np.random.default_rng(seed)
    A = np.column_stack([low[:, 0], low[:, 1], np.ones(len(low))])
    best, best_in = None, -1
    for _ in range(iters):
        s = rng.choice(len(low), 3, replace=False)
        try:
            coef = np.linalg.solve(A[s], low[s, 2])
        except np.linalg.LinAlgError:
            continue
        if abs(coef[0]) > 0.3 or abs(coef[1]) > 0.3:       # ground is not steeper than ~17 deg
            continue
        n_in = int((np.abs(A @ coef - low[:, 2]) < thresh).sum())
        if n_in > best_in:
            best, best_in = coef, n_in
    if best is None:
        return np.array([0.0, 0.0, float(np.percentile(points[:, 2], 5))])
    # refine on every point near the plane (the per-cell minima sit low in the noise)
    inl = np.abs(height_above(best, points)) < thresh
    P = points[inl]
    coef, *_ = np.linalg.lstsq(np.column_stack([P[:, 0], P[:, 1], np.ones(len(P))]), P[:, 2],
                               rcond=None)
    return coef


def height_above(plane: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p[:, 2] - (plane[0] * p[:, 0] + plane[1] * p[:, 1] + plane[2])


# ------------------------------------------------------------------ simplification
def cluster_vertices(vertices: np.ndarray, faces: np.ndarray, cell: float,
                     face_data: np.ndarray | None = None):
    """Vertex clustering: vertices in one world-aligned cell merge into their mean.

    Faces that collapse (repeated vertex) are dropped, as are duplicate faces;
    a pair of opposite faces on the same three vertices (a collapsed thin
    sliver) is dropped entirely. Returns (vertices, faces, face_data).
    """
    if len(faces) == 0 or cell <= 0:
        return vertices, faces, face_data
    q = np.floor(vertices / cell).astype(np.int64)
    _, cid, counts = np.unique(q, axis=0, return_inverse=True, return_counts=True)
    cid = cid.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, cid, vertices)
    newv = sums / counts[:, None]
    f = cid[faces]
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    fd = None if face_data is None else face_data[ok]
    # duplicates: one face per oriented triple; a triple present in both orientations
    # (a collapsed thin sliver) is dropped entirely
    r = np.argmin(f, axis=1)[:, None]
    canon = np.concatenate([np.take_along_axis(f, (r + k) % 3, 1) for k in range(3)], 1)
    _, first = np.unique(canon, axis=0, return_index=True)
    first = np.sort(first)
    f = f[first]
    fd = None if fd is None else fd[first]
    _, inv, cnt = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
    keep = cnt[inv.reshape(-1)] == 1
    f = f[keep]
    fd = None if fd is None else fd[keep]
    used = np.unique(f)
    remap = np.full(len(newv), -1, np.int64)
    remap[used] = np.arange(len(used))
    return newv[used], remap[f].astype(np.int32), fd


# ------------------------------------------------------------------- reconstruction
def _chunk_surface(pts: np.ndarray, key, prm: PointProxyParams, plane: np.ndarray):
    """Marching-cubes surface of one chunk (padded), simplified, cut to the chunk."""

    v = prm.voxel
    S = prm.chunk_size
    pad_vox = int(np.ceil(2 * prm.closing + 3 * prm.sigma + 3 + 2 * max(prm.simplify, 1)))
    pad = pad_vox * v
    x0, y0 = key[0] * S, key[1] * S
    lo_xy = np.floor(np.array([x0 - pad, y0 - pad]) / v) * v
    hi_xy = np.ceil(np.array([x0 + S + pad, y0 + S + pad]) / v) * v
    sel = ((pts[:, 0] >= lo_xy[0]) & (pts[:, 0] < hi_xy[0])
           & (pts[:, 1] >= lo_xy[1]) & (pts[:, 1] < hi_xy[1]))
    p = pts[sel]
    if len(p) < prm.min_points:
        return None
    # shrink the grid to the data (+ pad); the lattice stays world-aligned
    lo_xy = np.maximum(lo_xy, np.floor((p[:, :2].min(0) - pad) / v) * v)
    hi_xy = np.minimum(hi_xy, np.ceil((p[:, :2].max(0) + pad) / v) * v)
    z_lo = np.floor((min(p[:, 2].min(), _plane_min(plane, lo_xy, hi_xy)) - pad) / v) * v
    z_hi = np.ceil((p[:, 2].max() + pad) / v) * v
    origin = np.array([lo_xy[0], lo_xy[1], z_lo])
    shape = np.round((np.array([hi_xy[0], hi_xy[1], z_hi]) - origin) / v).astype(np.int64) + 1
    CHUNK_VOXELS.check(int(np.prod(shape, dtype=object)),
                       f"chunk {key[0]},{key[1]} ({shape[0]}x{shape[1]}x{shape[2]} voxels of "
                       f"{v:g} m; use a larger --voxel)")
    # voxel (i, j, k) is centred on origin + (i, j, k) * v (a global lattice: origins are
    # multiples of v), so neighbouring chunks see identical samples in their overlap
    idx = np.floor((p - origin) / v + 0.5).astype(np.int64)
    idx = np.clip(idx, 0, shape - 1)
    occ = np.zeros(shape, bool)
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True

    # ground fill: below the lowest occupied voxel of ground-level columns
    has = occ.any(axis=2)
    kmin = np.where(has, occ.argmax(axis=2), -1)
    gi, gj = np.nonzero(has)
    cx = origin[0] + gi * v
    cy = origin[1] + gj * v
    cz = origin[2] + kmin[gi, gj] * v
    ground = cz - (plane[0] * cx + plane[1] * cy + plane[2]) < prm.ground_band
    near = ndimage.binary_closing(has, iterations=3, border_value=0) | has
    fill_to = np.full(has.shape, -1)
    fill_to[gi[ground], gj[ground]] = kmin[gi[ground], gj[ground]]
    # unobserved columns inside the data footprint: fill up to the plane
    ii, jj = np.nonzero(near & ~has)
    kp = np.floor((plane[0] * (origin[0] + ii * v) + plane[1] * (origin[1] + jj * v)
                   + plane[2] - origin[2]) / v + 0.5).astype(int)
    fill_to[ii, jj] = np.clip(kp, -1, shape[2] - 1)
    ks = np.arange(shape[2])
    occ |= ks[None, None, :] <= fill_to[:, :, None]

    if prm.closing > 0:
        occ = ndimage.binary_closing(occ, iterations=prm.closing, border_value=0) | occ
    vol = ndimage.gaussian_filter(occ.astype(np.float32), prm.sigma, mode="nearest") \
        if prm.sigma > 0 else occ.astype(np.float32)
    if vol.max() < 0.5 or vol.min() > 0.5:
        return None
    verts, faces, _, _ = marching_cubes(vol, level=0.5, spacing=(v, v, v),
                                        gradient_direction="descent", allow_degenerate=False)
    verts = verts.astype(np.float64) + origin
    faces = faces[:, ::-1].astype(np.int64)     # skimage winds clockwise seen from outside
    if prm.simplify > 0:
        verts, faces, _ = cluster_vertices(verts, faces, prm.simplify * v)
    c = verts[faces].mean(1)
    # the filled ground ends in a skirt down to the grid bottom where the data ends: drop it
    below = height_above(plane, c) < -2 * v
    inside = ~below & (c[:, 0] >= x0) & (c[:, 0] < x0 + S) & (c[:, 1] >= y0) & (c[:, 1] < y0 + S)
    faces = faces[inside]
    if len(faces) == 0:
        return None
    used = np.unique(faces)
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    return verts[used], remap[faces].astype(np.int32)


def _plane_min(plane, lo_xy, hi_xy) -> float:
    xs = np.array([lo_xy[0], hi_xy[0]])
    ys = np.array([lo_xy[1], hi_xy[1]])
    X, Y = np.meshgrid(xs, ys)
    return float((plane[0] * X + plane[1] * Y + plane[2]).min())


def label_faces(verts: np.ndarray, faces: np.ndarray, plane: np.ndarray,
                prm: PointProxyParams, tree=None, labels: np.ndarray | None = None) -> np.ndarray:
    """Class id per face: nearest labelled point, else the height rule."""

    c = verts[faces].mean(1)
    if tree is not None and labels is not None:
        _, nn = tree.query(c, k=1)
        return labels[nn].astype(np.int32)
    h = height_above(plane, c)
    out = np.full(len(faces), CLASS_ID[ROAD], np.int32)
    above = np.nonzero(h >= prm.ground_band)[0]
    if len(above):
        f = faces[above]
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
        n = len(verts)
        g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        _, comp = connected_components(g, directed=False)
        fc = comp[f[:, 0]]
        top = np.full(comp.max() + 1, -np.inf)
        np.maximum.at(top, fc, height_above(plane, verts[f].reshape(-1, 3)).reshape(-1, 3).max(1))
        out[above] = np.where(top[fc] >= prm.building_height, CLASS_ID[BUILDING], CLASS_ID[VEHICLE])
    return out


def points_to_parts(points: np.ndarray, labels: np.ndarray | None = None,
                    params: PointProxyParams = PointProxyParams(), progress: bool = False,
                    max_chunks: int | None = None) -> dict[tuple[int, int], list[MeshPart]]:
    """Mesh parts per chunk (one open part per class) reconstructed from points. More than
    limits.CHUNKS chunks (or ``max_chunks``) are refused before the first is built."""

    if not params.voxel > 0:
        raise InputError(f"--voxel {params.voxel}: must be > 0")
    limits.CHUNK_SIZE_MIN.check(params.chunk_size, "--chunk-size")
    limits.CHUNK_SIZE_MAX.check(params.chunk_size, "--chunk-size")
    if len(points) < params.min_points:
        raise InputError(f"point cloud has {len(points)} points; need at least {params.min_points}")
    plane = fit_ground_plane(points)
    keys = sorted({(int(a), int(b)) for a, b in
                   np.unique(np.floor(points[:, :2] / params.chunk_size).astype(np.int64), axis=0)})
    limits.CHUNKS.check(len(keys), f"point cloud in {params.chunk_size:g} m chunks", max_chunks)
    tree = cKDTree(points) if labels is not None else None
    it = keys
    if progress:
        it = tqdm(keys, desc="point-cloud chunks", unit="chunk")
    out = {}
    for key in it:
        surf = _chunk_surface(points, key, params, plane)
        if surf is None:
            continue
        v, f = surf
        fl = label_faces(v, f, plane, params, tree, labels)
        parts = []
        for cid in np.unique(fl):
            cls = CLASSES[cid] if cid >= 0 else ROAD
            sub = f[fl == cid]
            used = np.unique(sub)
            remap = np.full(len(v), -1, np.int64)
            remap[used] = np.arange(len(used))
            parts.append(MeshPart(v[used], remap[sub], cls,
                                  f"points/{cls}/{chunk_prim_name(*key)}", faces_up=False))
        out[key] = parts
    return out


def proxy_from_points(cloud_path, output, params: PointProxyParams = PointProxyParams(),
                      progress: bool = False, max_chunks: int | None = None,
                      max_vertices: int | None = None) -> dict:
    """Read a cloud, reconstruct, write a proxy layer (same layout as the layout path)."""

    t0 = time.perf_counter()
    out = Path(output)
    if out.suffix.lower() not in (".usdc", ".usda", ".usd"):
        raise InputError(f"{output}: the proxy layer must be a .usdc, .usda or .usd file")
    pts, labels = read_cloud(cloud_path, max_vertices)
    parts = points_to_parts(pts, labels, params, progress, max_chunks)
    if not parts:
        raise InputError(f"{cloud_path}: no surface could be reconstructed (too few points?)")
    h = hashlib.sha256(pts.tobytes() + (b"" if labels is None else labels.tobytes())
                       + repr(params.as_dict()).encode()).hexdigest()
    write_proxy(parts, out, hashes={k: h for k in parts}, layout_hash=h,
                params={**params.as_dict(), "source": str(cloud_path)})
    return {"chunks": len(parts), "points": len(pts),
            "triangles": sum(p.n_faces for ps in parts.values() for p in ps),
            "labels": "per-point labels" if labels is not None else "height rule",
            "seconds": time.perf_counter() - t0}
