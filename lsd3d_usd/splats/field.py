"""SurfelField: a set of 2D Gaussian surfels as plain numpy arrays.

Conventions follow the official UsdVol ParticleField schema so that reading
and writing USD is a copy, not a conversion:
- orientations are unit quaternions in xyzw order (Gf memory order); the disk's
  axes are the rotated local x and y, its normal the rotated local z;
- scales are linear standard deviations along local x and y (not log);
- opacities are linear in [0, 1] (not logit);
- sh is (N, K, 3) with K = (degree+1)^2 in the usual real-SH order (l, then
  m = -l..l), and colour(d) = max(0, 0.5 + sum_lm c_lm Y_lm(d)) as in 3DGS.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from lsd3d_usd.shmath import C0 as SH_C0

KERNEL_SIGMAS = 3.0  # support of the surflet kernel per the schema: 99.7 % within 3 sigma


def sh_coeff_count(degree: int) -> int:
    return (int(degree) + 1) ** 2


def sh_degree_for(count: int) -> int:
    d = int(round(np.sqrt(count))) - 1
    if d < 0 or (d + 1) ** 2 != count:
        raise ValueError(f"{count} SH coefficients per particle is not (degree+1)^2")
    return d


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colour → degree-0 coefficient under colour = 0.5 + C0 * c."""
    return (np.asarray(rgb, np.float32) - 0.5) / SH_C0


def quat_normals(q: np.ndarray) -> np.ndarray:
    """(N,4) xyzw → (N,3) float32 disk normals (the local z axes in world)."""
    return np.ascontiguousarray(quat_to_matrix(q)[..., 2], np.float32)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N,4) xyzw → (N,3,3) rotation matrices (columns: local x, y, z axes in world)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - z * w)
    m[..., 0, 2] = 2 * (x * z + y * w)
    m[..., 1, 0] = 2 * (x * y + z * w)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - x * w)
    m[..., 2, 0] = 2 * (x * z - y * w)
    m[..., 2, 1] = 2 * (y * z + x * w)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(N,3,3) rotation matrices → (N,4) xyzw unit quaternions (w >= 0)."""
    m = np.asarray(m, dtype=np.float64)
    t = np.trace(m, axis1=-2, axis2=-1)
    q = np.empty(m.shape[:-2] + (4,))
    # Pick the numerically largest component per matrix (Shepperd's method).
    cands = np.stack([t, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1)
    k = np.argmax(cands, axis=-1)
    for case in range(4):
        sel = k == case
        if not np.any(sel):
            continue
        a = m[sel]
        if case == 0:
            s = np.sqrt(np.maximum(t[sel] + 1.0, 1e-30)) * 2
            q[sel] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s,
                               (a[:, 1, 0] - a[:, 0, 1]) / s, 0.25 * s], -1)
        elif case == 1:
            s = np.sqrt(np.maximum(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2], 1e-30)) * 2
            q[sel] = np.stack([0.25 * s, (a[:, 0, 1] + a[:, 1, 0]) / s,
                               (a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 2, 1] - a[:, 1, 2]) / s], -1)
        elif case == 2:
            s = np.sqrt(np.maximum(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2], 1e-30)) * 2
            q[sel] = np.stack([(a[:, 0, 1] + a[:, 1, 0]) / s, 0.25 * s,
                               (a[:, 1, 2] + a[:, 2, 1]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s], -1)
        else:
            s = np.sqrt(np.maximum(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1], 1e-30)) * 2
            q[sel] = np.stack([(a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 1, 2] + a[:, 2, 1]) / s,
                               0.25 * s, (a[:, 1, 0] - a[:, 0, 1]) / s], -1)
    q *= np.where(q[..., 3:4] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def kernel_bounds(positions: np.ndarray, orientations: np.ndarray, scales: np.ndarray,
                  surflet: bool = True, block: int = 1 << 16) -> np.ndarray:
    """(2,3) float64 bounds of every particle's kernel support (KERNEL_SIGMAS sigma): the
    one bounds function of validate, inspect and the writers' extents.

    ``orientations`` (N,4) xyzw, ``scales`` (N,2) or (N,3) linear. A surflet (2D disk in the
    local XY plane) ignores a third scale; a 3D Gaussian (``surflet=False``) uses all three
    axes. Exact for ellipses and ellipsoids. Zero particles: zeros.
    """
    positions = np.asarray(positions).reshape(-1, 3)
    n = len(positions)
    if n == 0:
        return np.zeros((2, 3))
    scales = np.asarray(scales).reshape(n, -1)
    orientations = np.asarray(orientations).reshape(n, 4)
    k = 2 if surflet else min(3, scales.shape[1])
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for a in range(0, n, block):   # float64 temporaries of a block, not of the whole field
        p = positions[a:a + block].astype(np.float64)
        s3 = np.zeros((len(p), 3))
        s3[:, :k] = scales[a:a + block, :k]
        rot = quat_to_matrix(orientations[a:a + block])
        axes = rot * (KERNEL_SIGMAS * s3[:, None, :])     # columns: the kernel's scaled axes
        half = np.sqrt((axes ** 2).sum(axis=2))          # per world axis half-extent
        lo, hi = np.minimum(lo, (p - half).min(0)), np.maximum(hi, (p + half).max(0))
    return np.stack([lo, hi])


def flatten_3d_gaussians(quats: np.ndarray, scales3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3D Gaussians (xyzw quats, 3 linear scales) → surfels: keep the two largest axes as
    the disk, the smallest becomes the normal (local z). Returns (quats, scales (N,2))."""
    scales3 = np.asarray(scales3, dtype=np.float64)
    rot = quat_to_matrix(quats)
    order = np.argsort(-scales3, axis=-1)  # largest, middle, smallest
    idx = np.arange(len(scales3))[:, None]
    axes = np.take_along_axis(rot, order[:, None, :], axis=2)  # columns reordered
    s = scales3[idx, order]
    # Keep a right-handed frame: flip the normal if the reorder made it left-handed.
    det = np.linalg.det(axes)
    axes[..., 2] *= np.where(det < 0, -1.0, 1.0)[:, None]
    return matrix_to_quat(axes).astype(np.float32), s[:, :2].astype(np.float32)


# the arrays whose values a SurfelField's `checked` mark vouches for
_VALUE_ARRAYS = ("positions", "orientations", "scales", "opacities", "sh", "semantic_ids")


@dataclass
class SurfelField:
    positions: np.ndarray                    # (N,3) float32
    orientations: np.ndarray                 # (N,4) float32 xyzw
    scales: np.ndarray                       # (N,2) float32, linear
    opacities: np.ndarray                    # (N,) float32 in [0,1]
    sh: np.ndarray                           # (N,K,3) float32
    semantic_ids: np.ndarray | None = None   # (N,) int32, -1 = unlabelled
    semantic_classes: tuple[str, ...] = field(default_factory=tuple)
    # set by mark_checked() only (the `checked` property): a new field, a replace() or a
    # reassigned value array starts unchecked
    _checked: bool = field(default=False, init=False, repr=False, compare=False)

    def __setattr__(self, name, value):
        if name in _VALUE_ARRAYS:
            object.__setattr__(self, "_checked", False)
        object.__setattr__(self, name, value)

    @property
    def checked(self) -> bool:
        """True only where the scene reader validated every value the rasteriser scans
        (views.stage_data.check_renderable), so a frame need not scan them again. The value
        arrays of a checked field are read-only: an in-place edit raises, and reassigning one
        makes the field unchecked. rows, subset, concat and lod.gather_cuts keep the mark
        where all their inputs had it."""
        return self._checked

    def mark_checked(self) -> "SurfelField":
        """Mark the field validated and make its value arrays read-only (see `checked`)."""
        for name in _VALUE_ARRAYS:
            a = getattr(self, name)
            if a is not None:
                a.setflags(write=False)
        object.__setattr__(self, "_checked", True)
        return self

    def __post_init__(self):
        self.positions = np.asarray(self.positions, dtype=np.float32).reshape(-1, 3)
        n = len(self.positions)
        self.orientations = np.asarray(self.orientations, dtype=np.float32).reshape(n, 4)
        self.scales = np.asarray(self.scales, dtype=np.float32).reshape(n, 2)
        self.opacities = np.asarray(self.opacities, dtype=np.float32).reshape(n)
        sh = np.asarray(self.sh, dtype=np.float32)
        # reshape(n, -1, 3) cannot infer the middle axis when n == 0.
        self.sh = sh if sh.ndim == 3 and sh.shape[0] == n else sh.reshape(n, -1, 3)
        sh_degree_for(self.sh.shape[1])
        if self.semantic_ids is not None:
            self.semantic_ids = np.asarray(self.semantic_ids, dtype=np.int32).reshape(n)
        self.semantic_classes = tuple(self.semantic_classes)

    # ---------------------------------------------------------------- basics
    @property
    def n(self) -> int:
        return len(self.positions)

    def __len__(self) -> int:
        return self.n

    @property
    def sh_degree(self) -> int:
        return sh_degree_for(self.sh.shape[1])

    @classmethod
    def empty(cls, sh_degree: int = 0) -> "SurfelField":
        k = sh_coeff_count(sh_degree)
        return cls(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 2)), np.zeros(0), np.zeros((0, k, 3)))

    def normals(self) -> np.ndarray:
        return quat_normals(self.orientations)

    def colors(self) -> np.ndarray:
        """View-independent (DC) colour per surfel."""
        return np.maximum(0.5 + SH_C0 * self.sh[:, 0, :], 0.0)

    def extent(self) -> np.ndarray:
        """(2,3) float64 bounds of the kernels' 3-sigma disks (kernel_bounds of surflets)."""
        return kernel_bounds(self.positions, self.orientations, self.scales, surflet=True)

    def with_sh_degree(self, degree: int) -> "SurfelField":
        """Same field with SH truncated or zero-padded to `degree`."""
        k = sh_coeff_count(degree)
        sh = np.zeros((self.n, k, 3), np.float32)
        m = min(k, self.sh.shape[1])
        sh[:, :m] = self.sh[:, :m]
        return replace(self, sh=sh)

    def rows(self, a: int, b: int) -> "SurfelField":
        """Rows a..b as views of this field's arrays (no copy)."""
        sem = None if self.semantic_ids is None else self.semantic_ids[a:b]
        out = SurfelField(self.positions[a:b], self.orientations[a:b], self.scales[a:b],
                          self.opacities[a:b], self.sh[a:b], sem, self.semantic_classes)
        return out.mark_checked() if self.checked else out

    def subset(self, index) -> "SurfelField":
        sem = None if self.semantic_ids is None else self.semantic_ids[index]
        out = SurfelField(self.positions[index], self.orientations[index], self.scales[index],
                          self.opacities[index], self.sh[index], sem, self.semantic_classes)
        return out.mark_checked() if self.checked else out

    @staticmethod
    def concat(fields: list["SurfelField"], drop_mismatched_semantics: bool = False) -> "SurfelField":
        """One field holding all of ``fields`` (SH padded to the highest degree). Semantic ids
        need one class table: fields whose tables differ raise ValueError, or with
        ``drop_mismatched_semantics`` are joined without semantics (ids and classes dropped:
        what rendering wants, where semantics are optional)."""
        if not fields:
            return SurfelField.empty()
        if len(fields) == 1:        # nothing to join: the field itself (a frame's common case)
            return fields[0]
        checked = all(f.checked for f in fields)    # before with_sh_degree's zero padding
        deg = max(f.sh_degree for f in fields)
        fields = [f.with_sh_degree(deg) if f.sh_degree != deg else f for f in fields]
        classes = next((f.semantic_classes for f in fields if f.semantic_classes), ())
        if any(f.semantic_classes and f.semantic_classes != classes for f in fields):
            if not drop_mismatched_semantics:
                raise ValueError("cannot concatenate surfel fields with different semantic class tables")
            fields = [replace(f, semantic_ids=None, semantic_classes=()) for f in fields]
            classes = ()
        has_sem = any(f.semantic_ids is not None for f in fields)
        sem = (np.concatenate([f.semantic_ids if f.semantic_ids is not None
                               else np.full(f.n, -1, np.int32) for f in fields]) if has_sem else None)
        out = SurfelField(np.concatenate([f.positions for f in fields]),
                          np.concatenate([f.orientations for f in fields]),
                          np.concatenate([f.scales for f in fields]),
                          np.concatenate([f.opacities for f in fields]),
                          np.concatenate([f.sh for f in fields]), sem, classes)
        return out.mark_checked() if checked else out

    # ------------------------------------------------------------ validation
    def problems(self, quat_tol: float = 1e-3) -> list[str]:
        """Every violated invariant, as 'attribute: what is wrong (first index i)'."""
        out: list[str] = []

        def first(mask) -> str:
            idx = np.flatnonzero(mask)
            return f"{len(idx)} particle(s), first index {idx[0]}"

        for name, arr in (("positions", self.positions), ("orientations", self.orientations),
                          ("scales", self.scales), ("opacities", self.opacities), ("sh", self.sh)):
            bad = ~np.isfinite(arr.reshape(self.n, -1)).all(axis=1) if self.n else np.zeros(0, bool)
            if bad.any():
                out.append(f"{name}: non-finite values in {first(bad)}")
        if self.n:
            bad = ~(self.scales > 0).all(axis=1)
            if bad.any():
                out.append(f"scales: not > 0 in {first(bad)}")
            bad = (self.opacities < 0) | (self.opacities > 1)
            if bad.any():
                out.append(f"opacities: outside [0, 1] in {first(bad)}")
            norm = np.linalg.norm(self.orientations.astype(np.float64), axis=1)
            bad = np.abs(norm - 1.0) > quat_tol
            if bad.any():
                out.append(f"orientations: not unit quaternions (|q| off by > {quat_tol}) in {first(bad)}")
        if self.semantic_ids is not None and self.n:
            bad = (self.semantic_ids < -1) | (self.semantic_ids >= max(len(self.semantic_classes), 0))
            if self.semantic_classes and bad.any():
                out.append(f"semantic_ids: outside [-1, {len(self.semantic_classes)}) in {first(bad)}")
        return out
