"""Relighting actors by the scene's environment, applied at render time.

Irradiance at a surface with world normal n and sun visibility V in [0, 1]:

    E(n, V) = max(0, E_sh(n) - (1 - V) E_map_sun max(0, n.s)) + V E_res max(0, n.s)

E_sh is the env layer's order-2 SH irradiance (lsd3d:env:shIrradiance; it already holds the
part of the sun the half-float map keeps, E_map_sun = sunIlluminance - residual), E_res the
residual sun carried by the /World/Env/Sun DistantLight, s the sun direction. V comes from
rays cast from points on the actor towards the sun against the proxy mesh (`Occluder`).

The actor's albedo (displayColor) is multiplied by E(n, V) / luma(E(+Z, 1)): relative to an
unshadowed upward-facing surface, so actors stay in the same range as the surfels (whose
colours are albedo-like), while the env's colour, the side/top contrast and shadows carry
over. Nothing is authored in the actors layer: the lighting follows whichever env variant
is selected at render time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from pxr import Usd, UsdGeom

from lsd3d_usd.actors.assets import mesh_data_from_prim
from lsd3d_usd.env.sh import C0, eval_sh_irradiance
from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import ENV_PATH, PROXY_PATH

LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclass
class Lighting:
    sh: np.ndarray                 # (9,3) irradiance SH (E(n) = sum c_k Y_k(n))
    sun_dir: np.ndarray            # (3,) unit, towards the sun
    sun_map: np.ndarray            # (3,) sun illuminance already inside the SH
    sun_residual: np.ndarray       # (3,) sun illuminance carried by the DistantLight

    def irradiance(self, normals, visibility) -> np.ndarray:
        """(..., 3) irradiance for unit normals (..., 3) and visibility (...) or scalar."""
        n = np.asarray(normals, np.float64)
        V = np.asarray(visibility, np.float64)[..., None] if np.ndim(visibility) else float(visibility)
        cos = np.maximum(n @ self.sun_dir, 0.0)[..., None] if self.sun_dir[2] > 0 else np.zeros(n.shape[:-1] + (1,))
        sky = np.maximum(eval_sh_irradiance(self.sh, n) - (1.0 - V) * self.sun_map * cos, 0.0)
        return sky + V * self.sun_residual * cos

    @property
    def reference(self) -> float:
        e = self.irradiance(np.array([0.0, 0.0, 1.0]), 1.0)
        return max(float(e @ LUMA), 1e-12)

    def factor(self, normals, visibility) -> np.ndarray:
        """Albedo multiplier (..., 3)."""
        return (self.irradiance(normals, visibility) / self.reference).astype(np.float32)


def default_lighting() -> Lighting:
    """Without an env layer: a uniform sky (E = 1) plus a sun 50 degrees up (E = 2.5 at normal incidence)."""
    s = np.array([np.cos(np.radians(50)) * 0.6, np.cos(np.radians(50)) * 0.8, np.sin(np.radians(50))])
    sh = np.zeros((9, 3))
    sh[0] = 1.0 / C0          # uniform sky: E(n) = 1 for every normal
    return Lighting(sh, s / np.linalg.norm(s), np.zeros(3), np.full(3, 2.5))


def lighting_from_stage(stage) -> Lighting:
    """The selected environment's lighting (env layer), or `default_lighting()` without one."""
    env = stage.GetPrimAtPath(ENV_PATH)
    if not env:
        return default_lighting()
    try:
        # local import: heavy, or only on this path
        from lsd3d_usd.env.usdlayer import read_env_prim
        info = read_env_prim(stage)
    except Exception:
        return default_lighting()
    if "shIrradiance" not in info or "sunDirection" not in info:
        return default_lighting()
    sh = np.asarray(info["shIrradiance"], np.float64).reshape(9, 3)
    s = np.asarray(info["sunDirection"], np.float64)
    s = s / max(np.linalg.norm(s), 1e-12)
    total = np.asarray(info.get("sunIlluminance", (0, 0, 0)), np.float64)
    from lsd3d_usd.env.usdlayer import residual_sun     # local import, as read_env_prim above
    try:
        resid = residual_sun(env)
    except InputError:
        return default_lighting()
    return Lighting(sh, s, np.maximum(total - resid, 0.0), resid)


class Occluder:
    """Triangles (world) for shadow rays, bucketed in a uniform XY grid (dense, CSR: the
    triangles of cell (i, j) are items[start[c]:start[c + 1]], c = (i - i0) nj + (j - j0))."""

    def __init__(self, vertices, faces, cell: float = 8.0):
        V = np.asarray(vertices, np.float64).reshape(-1, 3)
        F = np.asarray(faces, np.int64).reshape(-1, 3)
        self.tri = np.ascontiguousarray(V[F]) if len(F) else np.zeros((0, 3, 3))
        self.cell = float(cell)
        self.zmax = float(self.tri[..., 2].max()) if len(self.tri) else 0.0
        self.i0 = self.j0 = 0
        self.ni = self.nj = 0
        self.start = np.zeros(1, np.int64)
        self.items = np.zeros(0, np.int64)
        if len(self.tri):
            lo = np.floor(self.tri[..., :2].min(1) / cell).astype(np.int64)
            hi = np.floor(self.tri[..., :2].max(1) / cell).astype(np.int64)
            self.i0, self.j0 = (int(x) for x in lo.min(0))
            self.ni, self.nj = (int(x) for x in hi.max(0) - lo.min(0) + 1)
            span = hi - lo + 1                       # cells covered by each triangle's box
            count = span[:, 0] * span[:, 1]
            face = np.repeat(np.arange(len(F)), count)
            k = np.arange(len(face)) - np.repeat(np.cumsum(count) - count, count)
            i = lo[face, 0] + k // span[face, 1] - self.i0
            j = lo[face, 1] + k % span[face, 1] - self.j0
            c = i * self.nj + j
            order = np.argsort(c, kind="stable")
            self.items = face[order]
            self.start = np.concatenate([[0], np.cumsum(np.bincount(c, minlength=self.ni * self.nj))])

    def hits(self, origins, directions, tmax: float = 500.0) -> np.ndarray:
        """(n,) bool: whether each ray origin + t d (0 < t < tmax) hits a triangle
        (Moller-Trumbore, float64). Each ray tests the triangles of the cells within one
        cell of points every half cell along it (up to the tallest triangle for a rising ray)."""
        o = np.ascontiguousarray(np.asarray(origins, np.float64).reshape(-1, 3))
        d = np.ascontiguousarray(np.asarray(directions, np.float64).reshape(-1, 3))
        out = np.zeros(len(o), bool)
        if len(self.tri) and len(o):
            _rays_hit(self.tri, self.zmax, self.cell, self.i0, self.j0, self.ni, self.nj,
                      self.start, self.items, o, np.broadcast_to(d, o.shape).copy(), float(tmax), out)
        return out

    def hit(self, origin, direction, tmax: float = 500.0) -> bool:
        """Whether the ray origin + t d (0 < t < tmax) hits a triangle."""
        return bool(self.hits(origin, direction, tmax)[0])

    def visibility(self, points, sun_dir) -> float:
        """Fraction of ``points`` (k,3) that see the sun."""
        return float(self.visibility_many(np.asarray(points, np.float64).reshape(1, -1, 3), sun_dir)[0])

    def visibility_many(self, points, sun_dir) -> np.ndarray:
        """(m,) fraction of each row of ``points`` (m, k, 3) that sees the sun: every actor's
        sample points in one pass."""
        pts = np.asarray(points, np.float64)
        s = np.asarray(sun_dir, np.float64)
        if s[2] <= 0:
            return np.zeros(pts.shape[0])
        lit = ~self.hits(pts.reshape(-1, 3), np.broadcast_to(s, (pts.shape[0] * pts.shape[1], 3)))
        return lit.reshape(pts.shape[:2]).mean(1) if pts.shape[1] else np.full(pts.shape[0], np.nan)


@njit(cache=True)
def _rays_hit(tri, zmax, cell, i0, j0, ni, nj, start, items, O, D, tmax0, out):
    """Occluder.hits, ray by ray: candidate cells marked once per ray, each triangle tested
    once per ray, stopping at the first hit (the answer is only whether one exists)."""
    cell_seen = np.zeros(ni * nj, np.int64)
    tri_seen = np.zeros(tri.shape[0], np.int64)
    for r in range(O.shape[0]):
        stamp = r + 1
        ox, oy, oz = O[r, 0], O[r, 1], O[r, 2]
        dx, dy, dz = D[r, 0], D[r, 1], D[r, 2]
        nd = math.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx / nd, dy / nd, dz / nd
        tmax = tmax0
        if dz > 1e-9:  # rising ray: nothing above the tallest triangle
            tmax = min(tmax, max(0.0, (zmax - oz) / dz))
        n = max(2, int(math.ceil(tmax * math.sqrt(dx * dx + dy * dy) / (0.5 * cell))) + 1)
        step = tmax / (n - 1)
        found = False
        for k in range(n):
            t = tmax if k == n - 1 else k * step
            ci = int(math.floor((ox + t * dx) / cell)) - i0
            cj = int(math.floor((oy + t * dy) / cell)) - j0
            for i in range(ci - 1, ci + 2):
                if i < 0 or i >= ni:
                    continue
                for j in range(cj - 1, cj + 2):
                    if j < 0 or j >= nj:
                        continue
                    c = i * nj + j
                    if cell_seen[c] == stamp:
                        continue
                    cell_seen[c] = stamp
                    for m in range(start[c], start[c + 1]):
                        f = items[m]
                        if tri_seen[f] == stamp:
                            continue
                        tri_seen[f] = stamp
                        if _ray_triangle(tri, f, ox, oy, oz, dx, dy, dz, tmax):
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
            if found:
                break
        out[r] = found


@njit(cache=True, inline="always")
def _ray_triangle(tri, f, ox, oy, oz, dx, dy, dz, tmax):
    ax, ay, az = tri[f, 0, 0], tri[f, 0, 1], tri[f, 0, 2]
    e1x, e1y, e1z = tri[f, 1, 0] - ax, tri[f, 1, 1] - ay, tri[f, 1, 2] - az
    e2x, e2y, e2z = tri[f, 2, 0] - ax, tri[f, 2, 1] - ay, tri[f, 2, 2] - az
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if not abs(det) > 1e-12:
        return False
    inv = 1.0 / det
    sx, sy, sz = ox - ax, oy - ay, oz - az
    u = (sx * px + sy * py + sz * pz) * inv
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    v = (qx * dx + qy * dy + qz * dz) * inv
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    return u >= 0 and v >= 0 and u + v <= 1 and t > 1e-4 and t < tmax


def actor_sample_points(M: np.ndarray, dims) -> np.ndarray:
    """Points on an actor (world) whose sun visibility averages to its shadow term: the roof
    centre and four points at 70 % height near the corners."""
    L, W, H = (float(x) for x in dims)
    local = np.array([[0.0, 0.0, H + 0.05], [0.35 * L, 0.35 * W, 0.7 * H], [0.35 * L, -0.35 * W, 0.7 * H],
                      [-0.35 * L, 0.35 * W, 0.7 * H], [-0.35 * L, -0.35 * W, 0.7 * H]])
    return local @ M[:3, :3].T + M[:3, 3]


def proxy_occluder(stage) -> Occluder:
    """All proxy meshes (/World/Proxy, payloads loaded) as one occluder."""

    root = stage.GetPrimAtPath(PROXY_PATH)
    if not root:
        return Occluder(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    cache = UsdGeom.XformCache()
    vs, fs, n = [], [], 0
    for prim in Usd.PrimRange(root):
        if prim.IsA(UsdGeom.Mesh):
            M = np.array(cache.GetLocalToWorldTransform(prim), np.float64).T
            m = mesh_data_from_prim(prim, M)
            vs.append(m.vertices)
            fs.append(m.faces + n)
            n += len(m.vertices)
    if not vs:
        return Occluder(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    return Occluder(np.concatenate(vs), np.concatenate(fs))
