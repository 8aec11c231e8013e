"""Level of detail for surfels: a hierarchy of merged surfels and a per-camera cut.

`build_lod(field)` groups the surfels in an octree of cells (cell size doubling per level,
from about one surfel's footprint up to the field's extent): each cell of each level is one
node, a surfel fitted to every surfel below it by moments (weight = opacity x area): its
centre the weighted mean, its disk the two largest axes of the weighted covariance (each
child's own disk covariance plus its offset), its normal the smallest axis, its colour (all
SH bands) the weighted mean, its class the class of the largest weight, its opacity that of
its children stacked, 1 - prod(1 - o_i). A node is drawn in place of its children only when
its bounding sphere (grown for nodes that are not flat or not of one colour, shrunk for a flat
node seen at a grazing angle) covers at most a pixel budget on screen: there the rasteriser draws every
child as its low-pass blob of about a pixel (render/kernels.py, sigma sqrt(2)/2 px), so the
children composite like a stack of that many blobs, which the stacked opacity reproduces.

`LodTree.cut(...)` walks the hierarchy from the top for one pinhole camera: a node whose
bounding sphere is outside the view frustum is dropped with everything below it; a node
whose sphere projects to at most ``budget_px`` pixels is drawn as itself; otherwise its
children are visited. A flat node's disk seen at angle theta to its normal covers |cos theta|
of its face-on area, so its footprint counts sqrt(|cos theta|) of the sphere's diameter (no
less than sqrt(its floor): TILT_FLOOR, or its thickness for a node that is not flat): ground
seen from eye height at 50-100 m (most of an eye-height frame's surfels) merges along the
view where its surfels stacked within a pixel row anyway, while the same ground seen from
above keeps its detail. Leaves (the surfels themselves) are drawn where reached. The drawn
set is bounded by the screen, not by the size of the scene.

Leaves keep their order by cell (Morton order), so a tree's leaves are the field's surfels
permuted (`LodTree.leaves`); rendering does not depend on the order (the rasteriser sorts by
depth).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from lsd3d_usd.shmath import C0 as SH_C0
from lsd3d_usd.splats.field import KERNEL_SIGMAS, SurfelField, matrix_to_quat, quat_to_matrix

# a node that is not flat (an edge, a corner, foliage) looks larger to the cut by this much per
# unit thickness (_thickness): one surfel cannot stand for a 3D shape as it can for a patch
THICK_WEIGHT = 4.0
# likewise per unit of its children's colour spread (_colour_spread): a lane marking merged
# into asphalt is what a view from above loses first (the README sample's Top camera at 4 px:
# 35.0 -> 36.9 dB with 3; 1 and 6 gave 36.8 and 36.9; eye-height views unchanged)
COLOUR_WEIGHT = 3.0
# the least a flat node's footprint counts for, as a fraction of its face-on area (the projected
# disk's |cos theta|): 0.05 lets ground seen at 3 deg merge 4.5x larger. README sample at 4 px
# against full detail (bench frame): drawn surfels at its poses 174 k -> 127 k, lane views 43.1
# dB, Overview cameras 54.1 -> 44.1 dB; 0.12 drew 171 k (48.1 dB): little gained for the blur
TILT_FLOOR = 0.05
MAX_LEVELS = 20                # 2^20 cells of the finest size span any field we build
NODE_SPREAD = 1.4             # node disks widened past their moments: adjacent nodes overlap as
                              # their leaves did (1.4 measured best of 1, 1.4, 1.7)
_OPACITY_CAP = 0.999           # children at opacity 1 would give log(0)


@dataclass
class LodTree:
    """Leaves and merged nodes of one surfel field, in one index space.

    nodes: SurfelField of N leaves (rows [0, N)) then every level's merged nodes, finest
    level first. centre (M, 3) float64 and radius (M,) float64: each row's bounding sphere
    (a leaf's: its KERNEL_SIGMAS disk; a node's: the spheres of its leaves). first / last
    (M,) int64: a node's children rows [first, last) (leaves: first == last). roots: the
    coarsest level's rows."""
    nodes: SurfelField
    n_leaves: int
    centre: np.ndarray
    radius: np.ndarray
    first: np.ndarray
    last: np.ndarray
    roots: np.ndarray
    levels: int
    size: np.ndarray = None     # (M,) the radius the cut's footprint test uses: the sphere's,
                                # grown for nodes that are not flat (_thickness)
    floor: np.ndarray = None    # (M,) the least |cos theta| a node's footprint counts (TILT_FLOOR,
                                # or its thickness: a blob looks its size from every side)

    @property
    def leaves(self) -> SurfelField:
        return self.nodes.rows(0, self.n_leaves)

    @property
    def nbytes(self) -> int:
        f = self.nodes
        arrays = [f.positions, f.orientations, f.scales, f.opacities, f.sh, self.centre,
                  self.radius, self.first, self.last, self.roots, self.size, self.floor]
        if f.semantic_ids is not None:
            arrays.append(f.semantic_ids)
        return int(sum(a.nbytes for a in arrays))

    def cut(self, viewmat, K, width: int, height: int, near: float, far: float,
            budget_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Rows to draw for a pinhole camera, as runs (start (R,), count (R,)): viewmat (4, 4)
        world -> camera (OpenCV axes), K (3, 3) pixel intrinsics. ``budget_px``: a node is
        drawn in place of its children when its bounding sphere's diameter covers at most
        this many pixels; 0 draws leaves only (frustum culling alone)."""
        V = np.asarray(viewmat, np.float64)
        Kf = np.asarray(K, np.float64)
        planes = _frustum_planes(Kf, int(width), int(height))
        focal = float(max(Kf[0, 0], Kf[1, 1]))
        return _cut(self.centre, self.radius, self.size, self.floor, self.nodes.orientations,
                    self.first, self.last, self.roots, self.n_leaves,
                    np.ascontiguousarray(V[:3, :3]), np.ascontiguousarray(V[:3, 3]), planes,
                    float(near), float(far), focal, float(budget_px))

    def cut_field(self, viewmat, K, width, height, near, far, budget_px) -> SurfelField:
        """The surfels to draw (SurfelField) for a camera: see `cut`."""
        start, count = self.cut(viewmat, K, width, height, near, far, budget_px)
        return self.gather(start, count)

    def gather(self, start: np.ndarray, count: np.ndarray) -> SurfelField:
        """Rows given as runs, copied into one SurfelField."""
        return gather_cuts([self], [(start, count)])


def gather_cuts(trees: list[LodTree], cuts: list) -> SurfelField:
    """The rows of several trees' cuts ((start, count) runs each) copied once into one
    SurfelField (SH padded to the highest degree; semantics kept where the trees share one
    class table, dropped otherwise, as SurfelField.concat does)."""
    fields = [t.nodes for t in trees]
    k = max((f.sh.shape[1] for f in fields), default=1)
    classes = next((f.semantic_classes for f in fields if f.semantic_classes), ())
    same = all(not f.semantic_classes or f.semantic_classes == classes for f in fields)
    has_sem = same and any(f.semantic_ids is not None for f in fields)
    total = int(sum(int(np.sum(c)) for _, c in cuts))
    pos, quat = np.empty((total, 3), np.float32), np.empty((total, 4), np.float32)
    scl, opa = np.empty((total, 2), np.float32), np.empty(total, np.float32)
    same_k = all(f.sh.shape[1] == k for f in fields)
    sh = (np.empty if same_k else np.zeros)((total, k, 3), np.float32)
    every_id = all(f.semantic_ids is not None for f in fields)
    sem = None if not has_sem else np.empty(total, np.int32) if every_id else np.full(total, -1, np.int32)
    base = 0
    for f, (start, count) in zip(fields, cuts):
        at = np.zeros(len(count) + 1, np.int64)
        np.cumsum(count, out=at[1:])
        at += base
        kf = f.sh.shape[1]
        ids = f.semantic_ids if has_sem and f.semantic_ids is not None else None
        # one pass over the runs for every array (they are read and written together);
        # a lower SH degree fills the first of each surfel's SH rows
        _gather_rows(start, at, f.positions, f.orientations, f.scales, f.opacities,
                     f.sh.reshape(f.n, 3 * kf), pos, quat, scl, opa, sh.reshape(total, 3 * k),
                     ids is not None, ids if ids is not None else np.zeros(1, np.int32), sem
                     if sem is not None else np.zeros(1, np.int32))
        base = int(at[-1])
    out = SurfelField(pos, quat, scl, opa, sh, sem, classes if has_sem else ())
    return out.mark_checked() if all(f.checked for f in fields) else out   # rows copied as they are


@nb.njit(cache=True, nogil=True)
def _gather_rows(start, at, P, Q, S, O, H, pos, quat, scl, opa, sh, with_ids, ids, sem):
    # serial: bound by memory (a README sim frame: 0.52 M rows, 47 MB, ~9 ms); a parallel loop
    # over the runs gained 4 % and a slice copy per run (runs of ~12 rows) lost 20-60 %
    kh = H.shape[1]
    for r in range(start.shape[0]):
        s = start[r]
        for j in range(at[r + 1] - at[r]):
            i, o = s + j, at[r] + j
            for c in range(3):
                pos[o, c] = P[i, c]
            for c in range(4):
                quat[o, c] = Q[i, c]
            scl[o, 0] = S[i, 0]
            scl[o, 1] = S[i, 1]
            opa[o] = O[i]
            for c in range(kh):
                sh[o, c] = H[i, c]
            if with_ids:
                sem[o] = ids[i]


def _frustum_planes(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(4, 3) unit inward normals of the four side planes through the camera centre (camera
    axes: x right, y down, z forward): a point p is inside when n . p >= 0 for all four."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n = np.array([[fx, 0.0, cx],               # u >= 0
                  [-fx, 0.0, width - cx],      # u <= width
                  [0.0, fy, cy],               # v >= 0
                  [0.0, -fy, height - cy]])    # v <= height
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@nb.njit(cache=True, nogil=True)
def _cut(centre, radius, size, floor, quats, first, last, roots, n_leaves, R, t, planes, near,
         far, focal, budget):
    # depth-first from the roots; a node expanded whose children are leaves and whose
    # sphere lies inside the frustum emits its leaves as one run (the common case near the
    # camera), without a test per leaf
    start = np.empty(64, np.int64)
    count = np.empty(64, np.int64)
    n_out = 0
    stack = np.empty(max(256, 2 * roots.shape[0]), np.int64)
    top = 0
    for r in roots:
        stack[top] = r
        top += 1
    while top > 0:
        top -= 1
        i = stack[top]
        c0, c1, c2 = centre[i, 0], centre[i, 1], centre[i, 2]
        x = R[0, 0] * c0 + R[0, 1] * c1 + R[0, 2] * c2 + t[0]
        y = R[1, 0] * c0 + R[1, 1] * c1 + R[1, 2] * c2 + t[1]
        z = R[2, 0] * c0 + R[2, 1] * c1 + R[2, 2] * c2 + t[2]
        rad = radius[i]
        if z + rad < near or z - rad > far:
            continue
        inside = z - rad >= near and z + rad <= far
        outside = False
        for p in range(4):
            s = planes[p, 0] * x + planes[p, 1] * y + planes[p, 2] * z
            if s < -rad:
                outside = True
                break
            if s < rad:
                inside = False
        if outside:
            continue
        a, b = first[i], last[i]
        run = 1
        if a < b:
            dist = math.sqrt(x * x + y * y + z * z)
            d = dist - rad
            if d <= near or (2.0 * size[i] * _tilt(quats, i, R, x, y, z, dist, floor[i]) * focal
                             > budget * d):
                if inside and b <= n_leaves:
                    i = a
                    run = b - a
                else:
                    need = top + (b - a)
                    if need > stack.shape[0]:
                        grown = np.empty(max(need, 2 * stack.shape[0]), np.int64)
                        grown[:top] = stack[:top]
                        stack = grown
                    for c in range(b - 1, a - 1, -1):   # popped ascending: runs join
                        stack[top] = c
                        top += 1
                    continue
        if n_out == start.shape[0]:
            grown = np.empty(2 * n_out, np.int64)
            grown[:n_out] = start
            start = grown
            grown = np.empty(2 * n_out, np.int64)
            grown[:n_out] = count[:n_out]
            count = grown
        if n_out > 0 and run == 1 and start[n_out - 1] + count[n_out - 1] == i:
            count[n_out - 1] += 1           # consecutive rows join the previous run
        else:
            start[n_out] = i
            count[n_out] = run
            n_out += 1
    return start[:n_out].copy(), count[:n_out].copy()


@nb.njit(cache=True, inline="always")
def _tilt(quats, i, R, x, y, z, dist, floor):
    """sqrt(max(|cos theta|, floor)): theta between node i's normal (its disk's z axis, from
    the quaternion xyzw) and the ray to its centre (x, y, z) in camera axes (R: world ->
    camera rotation)."""
    qx, qy, qz, qw = (np.float64(quats[i, 0]), np.float64(quats[i, 1]),
                      np.float64(quats[i, 2]), np.float64(quats[i, 3]))
    q2 = qx * qx + qy * qy + qz * qz + qw * qw
    if not q2 > 0.0:
        return 1.0              # no orientation: the sphere's full footprint
    nx = 2.0 * (qx * qz + qw * qy) / q2
    ny = 2.0 * (qy * qz - qw * qx) / q2
    nz = 1.0 - 2.0 * (qx * qx + qy * qy) / q2
    cx = R[0, 0] * nx + R[0, 1] * ny + R[0, 2] * nz
    cy = R[1, 0] * nx + R[1, 1] * ny + R[1, 2] * nz
    cz = R[2, 0] * nx + R[2, 1] * ny + R[2, 2] * nz
    cos = abs(cx * x + cy * y + cz * z) / max(dist, 1e-300)
    return math.sqrt(max(cos, floor))


def _spread(v: np.ndarray) -> np.ndarray:
    """The 21 low bits of ``v`` (uint64) moved to every third bit (Morton interleaving)."""
    v = v & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


def leaf_radius(field: SurfelField) -> np.ndarray:
    """Bounding-sphere radius of each surfel's KERNEL_SIGMAS disk."""
    return KERNEL_SIGMAS * np.max(np.abs(field.scales.astype(np.float64)), axis=1)


def build_lod(field: SurfelField, cell: float | None = None) -> LodTree:
    """The hierarchy of ``field`` (see the module doc). ``cell``: the finest cell size in
    metres (default: the median surfel's bounding diameter). Exact moments from the leaves
    at every level, float64."""
    n = field.n
    pos = field.positions.astype(np.float64)
    rad = leaf_radius(field)
    if n == 0:
        return LodTree(field, 0, pos, rad, np.zeros(0, np.int64), np.zeros(0, np.int64),
                       np.zeros(0, np.int64), 0, rad, np.ones(0, np.float32))
    lo = pos.min(axis=0)
    span = float(np.max(pos.max(axis=0) - lo))
    if cell is None:
        cell = 2.0 * float(np.median(rad))
    cell = max(float(cell), span / float(1 << MAX_LEVELS), 1e-6)
    levels = 1
    while cell * (1 << (levels - 1)) < span and levels < MAX_LEVELS:
        levels += 1
    q = np.minimum(np.floor((pos - lo) / cell), (1 << 21) - 1).astype(np.uint64)
    code = _spread(q[:, 0]) | (_spread(q[:, 1]) << np.uint64(1)) | (_spread(q[:, 2]) << np.uint64(2))
    order = np.argsort(code, kind="stable")
    code = code[order]
    leaves = field.subset(order)
    pos, rad = pos[order], rad[order]

    # moments per row, level by level: a node's from its children's (parallel-axis theorem,
    # exact); W weight, mu mean, C covariance, r bounding radius, votes per class
    W, C, normal_w = _leaf_moments(leaves.orientations, leaves.scales, leaves.opacities)
    mu, r = pos, rad
    nsh = leaves.sh.shape[1] * 3
    dc = 0.5 + SH_C0 * leaves.sh[:, 0, :].astype(np.float64)
    # the SH moments and, after them, the second moments of the base colour: a node's
    # colour spread is its children's, from the same sums
    sh_w = np.concatenate([leaves.sh.astype(np.float64).reshape(n, -1), dc * dc], axis=1) * W[:, None]
    log_t = np.log1p(-np.clip(leaves.opacities.astype(np.float64), 0.0, _OPACITY_CAP))
    c = (np.zeros(n, np.int64) if leaves.semantic_ids is None
         else leaves.semantic_ids.astype(np.int64) + 1)      # -1 (unlabelled) -> column 0
    votes = np.zeros((n, int(c.max(initial=0)) + 1))
    votes[np.arange(n), c] = W

    parts, centres, radii, sizes, floors = [], [pos], [rad], [rad], [np.ones(n, np.float32)]
    first_parts, last_parts = [np.zeros(n, np.int64)], [np.zeros(n, np.int64)]
    child_code, prev_offset, offset = code, 0, n
    roots = np.arange(n, dtype=np.int64)
    for k in range(levels):
        cell_code = child_code >> np.uint64(3 if k else 0)
        starts = np.flatnonzero(np.r_[True, cell_code[1:] != cell_code[:-1]]).astype(np.int64)
        m = len(starts)
        ends = np.r_[starts[1:], len(cell_code)].astype(np.int64)
        W, mu, C, r, normal_w, sh_w, log_t, votes = _merge(
            starts, ends, W, mu, C, r, normal_w, sh_w, log_t, votes)
        sem = None
        if leaves.semantic_ids is not None:
            sem = (np.argmax(votes, axis=1) - 1).astype(np.int32)
        fit = _fit_nodes(C, mu, normal_w, sh_w[:, :nsh] / W[:, None], log_t, leaves.sh.shape[1])
        # the sphere also holds the node's own widened disk (culling keeps its tails), and
        # the level above bounds these spheres
        r = np.maximum(r, KERNEL_SIGMAS * fit[2].max(axis=1).astype(np.float64))
        thick = _thickness(C)
        floors.append(np.clip(thick, TILT_FLOOR, 1.0).astype(np.float32))
        sizes.append(r * (1.0 + THICK_WEIGHT * thick)
                     * (1.0 + COLOUR_WEIGHT * _colour_spread(sh_w, W, nsh)))
        parts.append(SurfelField(*fit, sem, leaves.semantic_classes))
        centres.append(mu)
        radii.append(r)
        first_parts.append(starts + prev_offset)
        last_parts.append(ends + prev_offset)
        roots = np.arange(offset, offset + m, dtype=np.int64)
        child_code = cell_code[starts]
        prev_offset, offset = offset, offset + m
        if m == 1:
            levels = k + 1
            break
    all_nodes = SurfelField.concat([leaves] + parts)
    return LodTree(all_nodes, n, np.concatenate(centres), np.concatenate(radii),
                   np.concatenate(first_parts), np.concatenate(last_parts), roots, levels,
                   np.concatenate(sizes), np.concatenate(floors))


def _colour_spread(sh_w, W, nsh) -> np.ndarray:
    """Standard deviation of the children's base colour (0.5 + C0 dc), the largest of the
    three channels: 0 for a uniform patch, ~0.3 for a lane marking on asphalt."""
    mean = 0.5 + SH_C0 * sh_w[:, :3] / W[:, None]
    var = sh_w[:, nsh:nsh + 3] / W[:, None] - mean * mean
    return np.sqrt(np.maximum(var, 0.0)).max(axis=1)


def _thickness(C) -> np.ndarray:
    """How far a node's surfels are from one plane: sqrt(smallest / middle eigenvalue) of
    their covariance, 0 for a flat patch, 1 for a blob (a roof meeting a wall, a tree)."""
    lam = np.maximum(np.linalg.eigvalsh(C), 0.0)
    return np.sqrt(lam[:, 0] / np.maximum(lam[:, 1], 1e-30))


@nb.njit(cache=True, nogil=True)
def _leaf_moments(quats, scales, opac):
    """Per surfel: weight (opacity x area), disk covariance (3, 3), weighted normal."""
    n = quats.shape[0]
    W = np.empty(n)
    C = np.empty((n, 3, 3))
    N = np.empty((n, 3))
    for i in range(n):
        x, y, z, w = (np.float64(quats[i, 0]), np.float64(quats[i, 1]),
                      np.float64(quats[i, 2]), np.float64(quats[i, 3]))
        q = math.sqrt(x * x + y * y + z * z + w * w)
        x, y, z, w = x / q, y / q, z / q, w / q
        ax = (1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w))
        ay = (2 * (x * y - z * w), 1 - 2 * (x * x + z * z), 2 * (y * z + x * w))
        az = (2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y))
        su, sv = np.float64(scales[i, 0]), np.float64(scales[i, 1])
        # opacities a hair below 0 pass the reader's tolerance: no negative weights
        W[i] = max(np.float64(opac[i]), 0.0) * abs(su * sv) + 1e-30
        for a in range(3):
            N[i, a] = az[a] * W[i]
            for b in range(3):
                C[i, a, b] = su * su * ax[a] * ax[b] + sv * sv * ay[a] * ay[b]
    return W, C, N


@nb.njit(cache=True, nogil=True)
def _merge(starts, ends, W, mu, C, r, nw, shw, lt, votes):
    """One level up: each node [starts[j], ends[j]) of the rows below, summed."""
    m = starts.shape[0]
    Wn = np.zeros(m)
    mun = np.zeros((m, 3))
    Cn = np.zeros((m, 3, 3))
    rn = np.zeros(m)
    nwn = np.zeros((m, 3))
    shn = np.zeros((m, shw.shape[1]))
    ltn = np.zeros(m)
    vn = np.zeros((m, votes.shape[1]))
    for j in range(m):
        for i in range(starts[j], ends[j]):
            Wn[j] += W[i]
            for a in range(3):
                mun[j, a] += W[i] * mu[i, a]
                nwn[j, a] += nw[i, a]
            for a in range(shw.shape[1]):
                shn[j, a] += shw[i, a]
            for a in range(votes.shape[1]):
                vn[j, a] += votes[i, a]
            ltn[j] += lt[i]
        for a in range(3):
            mun[j, a] /= Wn[j]
        for i in range(starts[j], ends[j]):
            d0, d1, d2 = mu[i, 0] - mun[j, 0], mu[i, 1] - mun[j, 1], mu[i, 2] - mun[j, 2]
            d = (d0, d1, d2)
            for a in range(3):
                for b in range(3):
                    Cn[j, a, b] += W[i] * (C[i, a, b] + d[a] * d[b])
            rn[j] = max(rn[j], math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) + r[i])
        for a in range(3):
            for b in range(3):
                Cn[j, a, b] /= Wn[j]
    return Wn, mun, Cn, rn, nwn, shn, ltn, vn


def _fit_nodes(C, mu, normal_sum, sh, log_t, k):
    """Surfels from moments: (positions, quats, scales, opacities, sh) of m nodes."""
    m = len(mu)
    lam, vec = np.linalg.eigh(C)                        # ascending eigenvalues
    lam = np.maximum(lam, 0.0)
    n_axis = vec[:, :, 0]
    flip = np.einsum("ni,ni->n", n_axis, normal_sum) < 0
    n_axis = np.where(flip[:, None], -n_axis, n_axis)
    a_axis = vec[:, :, 2]
    b_axis = np.cross(n_axis, a_axis)                   # right-handed (a, b, n)
    rot = np.stack([a_axis, b_axis, n_axis], axis=2)
    scales = np.sqrt(lam[:, [2, 1]]) * NODE_SPREAD
    opac = np.minimum(-np.expm1(log_t), _OPACITY_CAP)
    return (mu.astype(np.float32), matrix_to_quat(rot).astype(np.float32),
            np.maximum(scales, 1e-7).astype(np.float32), opac.astype(np.float32),
            sh.reshape(m, k, 3).astype(np.float32))
