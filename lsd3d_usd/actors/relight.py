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

from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom, UsdLux

from lsd3d_usd.actors.assets import mesh_data_from_prim
from lsd3d_usd.env.sh import C0, eval_sh_irradiance
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
    resid = np.zeros(3)
    sun = env.GetChild("Sun")
    if sun:
        if UsdGeom.Imageable(sun).ComputeVisibility() != UsdGeom.Tokens.invisible:
            lx = UsdLux.LightAPI(sun)
            resid = float(lx.GetIntensityAttr().Get() or 0.0) * \
                np.asarray(lx.GetColorAttr().Get() or (1, 1, 1), np.float64)
    return Lighting(sh, s, np.maximum(total - resid, 0.0), resid)


class Occluder:
    """Triangles (world) for shadow rays, bucketed in a uniform XY grid."""

    def __init__(self, vertices, faces, cell: float = 8.0):
        V = np.asarray(vertices, np.float64).reshape(-1, 3)
        F = np.asarray(faces, np.int64).reshape(-1, 3)
        self.tri = V[F] if len(F) else np.zeros((0, 3, 3))
        self.cell = float(cell)
        self.zmax = float(self.tri[..., 2].max()) if len(self.tri) else 0.0
        self.grid: dict[tuple[int, int], np.ndarray] = {}
        if len(self.tri):
            lo = np.floor(self.tri[..., :2].min(1) / cell).astype(np.int64)
            hi = np.floor(self.tri[..., :2].max(1) / cell).astype(np.int64)
            buckets: dict = {}
            for f in range(len(self.tri)):
                for i in range(lo[f, 0], hi[f, 0] + 1):
                    for j in range(lo[f, 1], hi[f, 1] + 1):
                        buckets.setdefault((i, j), []).append(f)
            self.grid = {k: np.asarray(v, np.int64) for k, v in buckets.items()}

    def _candidates(self, o, d, tmax) -> np.ndarray:
        n = max(2, int(np.ceil(tmax * np.linalg.norm(d[:2]) / (0.5 * self.cell))) + 1)
        ts = np.linspace(0.0, tmax, n)
        cells = set()
        for p in o[None, :2] + ts[:, None] * d[None, :2]:
            ci, cj = int(np.floor(p[0] / self.cell)), int(np.floor(p[1] / self.cell))
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    cells.add((ci + di, cj + dj))
        found = [self.grid[c] for c in cells if c in self.grid]
        return np.unique(np.concatenate(found)) if found else np.zeros(0, np.int64)

    def hit(self, origin, direction, tmax: float = 500.0) -> bool:
        """Whether the ray origin + t d (0 < t < tmax) hits a triangle (Moller-Trumbore)."""
        o = np.asarray(origin, np.float64)
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        if not len(self.tri):
            return False
        if d[2] > 1e-9:  # rising ray: nothing above the tallest triangle
            tmax = min(tmax, max(0.0, (self.zmax - o[2]) / d[2]))
        idx = self._candidates(o, d, tmax)
        if not len(idx):
            return False
        T = self.tri[idx]
        e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - T[:, 0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        return bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-4) & (t < tmax)))

    def visibility(self, points, sun_dir) -> float:
        """Fraction of ``points`` (k,3) that see the sun."""
        s = np.asarray(sun_dir, np.float64)
        if s[2] <= 0:
            return 0.0
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        return float(np.mean([not self.hit(p, s) for p in pts]))


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
