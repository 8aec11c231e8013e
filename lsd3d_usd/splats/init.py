"""Mesh -> 2D Gaussian surfels (the paper's initialisation from the coarse layout).

Each surfel lies on a mesh face with the face normal n_F = t_u x t_v
(t_u = v1 - v0, t_v = v2 - v0, so the normal follows the winding). A target
count is distributed over faces in proportion to area by systematic sampling
(one uniform offset, then evenly spaced positions along the cumulative area),
so every face gets floor or ceil of its expected share and the total is exact.
Inside a face the m surfels are placed with the R2 low-discrepancy sequence
mapped to the triangle by Heitz's low-distortion square->triangle map, so a
large face is covered evenly rather than by clumped random points.

Scale: every surfel stands for the same share D = A / N of the mesh area (the
interval of cumulative area it was drawn from); its 1-sigma ellipse has area D
(pi * sx * sy = D), so the 1-sigma disks add up to the mesh area exactly. On a
face split into m surfels D equals A_F / m up to one surfel's rounding (m is
floor or ceil of A_F / D). Using D rather than A_F / m matters for faces
smaller than D: they get a surfel only with probability A_F / D, and sizing
that surfel to its tiny face would leave its unsampled neighbours (curbs,
poles, small facade pieces) as holes. The ellipse is aligned with the face's
principal axes; a sliver face split into m surfels is cut along its long axis
first, so the aspect ratio of its surfels is max(1, aspect(face) / m).
Neighbouring surfels sit about 1.8 sigma apart, where a sum of Gaussians is
close to flat (visually opaque coverage, no holes).

Everything is vectorised numpy; deterministic for a given seed.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from lsd3d_usd import semantics
from lsd3d_usd.errors import InputError
from lsd3d_usd.splats.field import (
    SurfelField,
    matrix_to_quat,
    quat_to_matrix,
    rgb_to_sh_dc,
)

MAX_SURFELS = 4_000_000  # the paper's upper bound per scene
_PLASTIC = 1.32471795724474602596  # R2 sequence generator (root of x^3 = x + 1)


# --- mesh -> surfels ----------------------------------------------------------------------

def _check_mesh(vertices, faces, face_semantic_ids):
    V = np.asarray(vertices)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3:
        raise InputError(f"mesh -> surfels: vertices must have shape (V, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3:
        raise InputError(f"mesh -> surfels: faces must be triangles of shape (F, 3), got {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        raise InputError(f"mesh -> surfels: faces must hold integer vertex indices, got {F.dtype}")
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise InputError(f"mesh -> surfels: face indices out of range [0, {len(V)})")
    if not np.all(np.isfinite(V)):
        raise InputError("mesh -> surfels: vertices contain NaN or Inf")
    ids = None
    if face_semantic_ids is not None:
        ids = np.asarray(face_semantic_ids)
        if ids.shape != (len(F),):
            raise InputError(f"mesh -> surfels: face_semantic_ids must have shape ({len(F)},), got {ids.shape}")
        ids = ids.astype(np.int32)
    return V.astype(np.float64), F.astype(np.int64), ids


def face_frames(vertices: np.ndarray, faces: np.ndarray):
    """Per face: area (F,), unit normal t_u x t_v (F,3), unit long principal axis
    (F,3), and the principal standard deviations (F,2) of the uniform
    distribution over the face (long, short). Degenerate faces get area 0."""
    p0, p1, p2 = (vertices[faces[:, i]] for i in range(3))
    tu, tv = p1 - p0, p2 - p0
    cr = np.cross(tu, tv)
    dbl = np.linalg.norm(cr, axis=1)
    area = 0.5 * dbl
    # Relative degeneracy test: area tiny against the longest edge squared.
    emax2 = np.maximum.reduce([np.einsum("ij,ij->i", e, e) for e in (tu, tv, p2 - p1)])
    ok = dbl > 1e-10 * emax2
    area = np.where(ok, area, 0.0)
    safe = np.where(ok, dbl, 1.0)[:, None]
    n = cr / safe
    # In-plane basis (e1 along t_u) and the 2x2 covariance of the uniform triangle:
    # Cov = 1/12 * sum_i (p_i - mu)(p_i - mu)^T.
    e1 = tu / np.maximum(np.linalg.norm(tu, axis=1, keepdims=True), 1e-300)
    e2 = np.cross(n, e1)
    mu = (p0 + p1 + p2) / 3.0
    a = b = c = 0.0
    for p in (p0, p1, p2):
        d = p - mu
        x, y = np.einsum("ij,ij->i", d, e1), np.einsum("ij,ij->i", d, e2)
        a, b, c = a + x * x, b + x * y, c + y * y
    a, b, c = a / 12.0, b / 12.0, c / 12.0
    # Closed-form eigen-decomposition of [[a, b], [b, c]].
    half_tr, disc = 0.5 * (a + c), np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    l1, l2 = half_tr + disc, np.maximum(half_tr - disc, 0.0)
    theta = 0.5 * np.arctan2(2.0 * b, a - c)  # angle of the major axis from e1
    major = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    return area, n, major, np.sqrt(np.stack([l1, l2], axis=1)), ok


def _heitz_triangle(u1, u2):
    """Low-distortion map of [0,1)^2 to barycentrics (b1, b2) of a triangle (Heitz 2019)."""
    swap = u2 > u1
    b1 = np.where(swap, 0.5 * u1, u1 - 0.5 * u2)
    b2 = np.where(swap, u2 - 0.5 * u1, 0.5 * u2)
    return b1, b2


def mesh_to_surfels(vertices, faces, face_semantic_ids=None, *, count: int = 2_000_000,
                    seed: int = 0, color="semantic", opacity: float = 0.8, sh_degree: int = 0,
                    scale_factor: float = 1.0, semantic_classes=None, max_count: int = MAX_SURFELS,
                    return_face_index: bool = False, face_weights=None):
    """Surfels on a triangle mesh.

    vertices (V,3), faces (F,3) int, face_semantic_ids (F,) int or None.
    ``count`` surfels exactly (capped by ``max_count``, the paper's 4 M),
    distributed over faces by area. ``color``: "semantic" (class colour from
    lsd3d_usd.semantics.CLASS_COLORS; unlabelled faces grey), or an RGB triple
    (monochrome, linear). ``scale_factor`` multiplies both scales (1 = the
    1-sigma disks tile the mesh area). ``face_weights`` (F,) >= 0 scales each
    face's surfel density (e.g. more near the lanes a camera drives); surfel
    sizes follow, so the disks still tile every face. Returns a SurfelField (and
    the source face index per surfel if ``return_face_index``).
    """

    V, F, ids = _check_mesh(vertices, faces, face_semantic_ids)
    count = int(count)
    if count < 0:
        raise InputError(f"mesh -> surfels: count must be >= 0, got {count}")
    if count > max_count:
        raise InputError(f"mesh -> surfels: count {count} exceeds the maximum {max_count} "
                         "(raise max_count deliberately if you need more)")
    if not 0.0 <= opacity <= 1.0:
        raise InputError(f"mesh -> surfels: opacity must be in [0, 1], got {opacity}")
    if sh_degree not in (0, 1, 2, 3):
        raise InputError(f"mesh -> surfels: sh_degree must be 0..3, got {sh_degree}")

    area, normal, major, sd, ok = face_frames(V, F)
    density = np.ones(len(F))
    if face_weights is not None:
        density = np.asarray(face_weights, dtype=np.float64).reshape(-1)
        if density.shape != (len(F),) or not np.all(np.isfinite(density)) or np.any(density < 0):
            raise InputError(f"mesh -> surfels: face_weights must be {len(F)} finite values >= 0")
    area = area * density  # sampling measure: weighted area
    total = float(area.sum())
    if count > 0 and not total > 0.0:
        raise InputError("mesh -> surfels: the mesh has no face with non-zero area")
    rng = np.random.default_rng(seed)

    # Systematic sampling along the cumulative area: exact count, each face
    # floor/ceil of its expected share, zero-area faces never hit.
    cum = np.cumsum(area)
    targets = (np.arange(count) + rng.random()) * (total / max(count, 1))
    fidx = np.searchsorted(cum, targets, side="right")
    fidx = np.minimum(fidx, len(F) - 1)
    # Floating-point guard: never land on a zero-area face.
    bad = area[fidx] <= 0.0
    if np.any(bad):
        nz = np.flatnonzero(area > 0)
        fidx[bad] = nz[np.minimum(np.searchsorted(nz, fidx[bad]), len(nz) - 1)]
        order = np.argsort(fidx, kind="stable")
        fidx = fidx[order]
    m = np.bincount(fidx, minlength=len(F))
    start = np.concatenate([[0], np.cumsum(m)[:-1]])
    k = np.arange(count) - start[fidx]  # rank of a surfel within its face

    # R2 sequence with a per-face random shift (Cranley-Patterson rotation).
    shift = rng.random((len(F), 2))
    a1, a2 = 1.0 / _PLASTIC, 1.0 / _PLASTIC ** 2
    u1 = np.mod(shift[fidx, 0] + k * a1, 1.0)
    u2 = np.mod(shift[fidx, 1] + k * a2, 1.0)
    b1, b2 = _heitz_triangle(u1, u2)
    p0, p1, p2 = (V[F[fidx, i]] for i in range(3))
    pos = p0 + b1[:, None] * (p1 - p0) + b2[:, None] * (p2 - p0)

    # Scales: 1-sigma ellipse area = total / count, aspect max(1, face aspect / m).
    mf = np.maximum(m[fidx], 1).astype(np.float64)
    aspect = sd[fidx, 0] / np.maximum(sd[fidx, 1], 1e-300)
    ratio = np.clip(aspect / mf, 1.0, 1e4)
    # A surfel's share of its face's true area: (weighted total / count) / face weight.
    share = total / max(count, 1) / np.maximum(density[fidx], 1e-300)
    s_short = np.sqrt(share / (np.pi * ratio))
    scales = np.stack([ratio * s_short, s_short], axis=1) * scale_factor

    nrm = normal[fidx]
    t1 = major[fidx]
    t2 = np.cross(nrm, t1)
    R = np.stack([t1, t2, nrm], axis=2)  # columns: disk x, disk y, normal
    quats = matrix_to_quat(R)

    nsh = (sh_degree + 1) ** 2
    sh = np.zeros((count, nsh, 3), dtype=np.float32)
    sem = ids[fidx] if ids is not None else None
    if isinstance(color, str):
        if color != "semantic":
            raise InputError(f"mesh -> surfels: color must be 'semantic' or an RGB triple, got {color!r}")
        rgb = np.full((count, 3), 0.5)
        if sem is not None:
            known = (sem >= 0) & (sem < len(semantics.CLASS_COLORS))
            rgb[known] = semantics.CLASS_COLORS[sem[known]]
    else:
        c = np.asarray(color, dtype=np.float64).reshape(-1)
        if c.shape != (3,):
            raise InputError(f"mesh -> surfels: color must be 'semantic' or an RGB triple, got {color!r}")
        rgb = np.broadcast_to(c, (count, 3))
    sh[:, 0, :] = rgb_to_sh_dc(rgb)

    field = SurfelField(
        positions=pos.astype(np.float32),
        orientations=quats.astype(np.float32),
        scales=scales.astype(np.float32),
        opacities=np.full(count, opacity, dtype=np.float32),
        sh=sh,
        semantic_ids=sem,
        semantic_classes=tuple(semantic_classes) if semantic_classes is not None else tuple(semantics.CLASSES),
    )
    return (field, fidx) if return_face_index else field


def split_faces(vertices, faces, max_area: float, max_faces: int = 20_000_000):
    """Bisect every triangle larger than ``max_area`` at the midpoint of its longest edge until
    none is (winding kept; T-junctions are harmless for sampling), so per-face quantities —
    surfel density weights — can vary across what were large faces (a 2000 m² terrain
    triangle reaching from the kerb to 60 m away). Returns (vertices (V',3) float64, faces
    (F',3) int64, parent (F',) index of the input face each output face lies in).
    Degenerate faces are kept as they are."""
    if not max_area > 0:
        raise InputError(f"split_faces: max_area must be > 0, got {max_area}")
    V, F, _ = _check_mesh(vertices, faces, None)
    parent = np.arange(len(F))
    verts = [V]
    nv = len(V)
    allv = V
    while True:
        p0, p1, p2 = (allv[F[:, i]] for i in range(3))
        area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
        big = area > max_area
        if not big.any():
            break
        if len(F) + int(big.sum()) > max_faces:
            raise InputError(f"split_faces: more than {max_faces} faces at max_area {max_area}")
        f = F[big]
        e = np.stack([np.linalg.norm(allv[f[:, (k + 1) % 3]] - allv[f[:, k]], axis=1)
                      for k in range(3)], axis=1)
        k = np.argmax(e, axis=1)
        r = np.arange(len(f))
        a, b, c = f[r, k], f[r, (k + 1) % 3], f[r, (k + 2) % 3]
        mid = 0.5 * (allv[a] + allv[b])
        m = nv + np.arange(len(f))
        nv += len(f)
        verts.append(mid)
        allv = np.concatenate(verts)
        verts = [allv]
        F = np.concatenate([F[~big], np.stack([a, m, c], 1), np.stack([m, b, c], 1)])
        parent = np.concatenate([parent[~big], parent[big], parent[big]])
    return allv, F, parent


def transform_surfels(field, M: np.ndarray):
    """Apply a 4x4 (column-vector) world transform to a SurfelField: positions, disk axes
    and scales (the scaled axes are re-orthonormalised around the transformed normal)."""

    if np.allclose(M, np.eye(4), atol=0, rtol=0):
        return field
    A = M[:3, :3]
    pos = field.positions.astype(np.float64) @ A.T + M[:3, 3]
    R = quat_to_matrix(field.orientations)
    ax = A @ R[..., 0][..., None]
    ay = A @ R[..., 1][..., None]
    ax, ay = ax[..., 0] * field.scales[:, :1], ay[..., 0] * field.scales[:, 1:2]
    sx, sy = np.linalg.norm(ax, axis=1), np.linalg.norm(ay, axis=1)
    x = ax / np.maximum(sx, 1e-30)[:, None]
    n = np.cross(x, ay)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    y = np.cross(n, x)
    q = matrix_to_quat(np.stack([x, y, n], axis=2))
    with np.errstate(over="ignore"):    # beyond float32 becomes inf, refused where it is read
        return replace(field, positions=pos.astype(np.float32), orientations=q.astype(np.float32),
                       scales=np.stack([sx, sy], 1).astype(np.float32))
