"""Geometry checks of rendered surfels: agreement with the proxy G-buffer per semantic class,
and multi-view depth consistency by reprojection. Arrays in, numbers out.

Surfel depth is the median depth (where the transmittance crosses 0.5: the surface a 2DGS
render shows), falling back to the expected depth where the median is undefined; surfel
normals are the rendered world normals, normalised (each surfel's normal faces the camera).
A pixel counts when the proxy covers it and the surfels are opaque there (alpha > 0.5).
"""
from __future__ import annotations

import numpy as np

from lsd3d_usd.render.camera import Camera, pixel_rays
from lsd3d_usd.semantics import CLASSES

ALPHA_MIN = 0.5
MAX_SAMPLES_PER_VIEW = 20000


def surfel_depth(frame: dict) -> np.ndarray:
    d = frame["depth_median"]
    return np.where(d > 0, d, frame["depth_expected"]).astype(np.float64)


def unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-12), 0.0)


class ClassAgreement:
    """Accumulates per-class relative depth errors and normal angles over views."""

    def __init__(self, seed: int = 0):
        self.depth: dict[int, list] = {}
        self.angle: dict[int, list] = {}
        self.proxy_px: dict[int, int] = {}
        self.covered_px: dict[int, int] = {}
        self.rng = np.random.default_rng(seed)

    def add(self, frame: dict, gbuf, camera: Camera) -> None:
        d_s = surfel_depth(frame)
        proxy = gbuf.mask & np.isfinite(gbuf.depth)
        covered = proxy & (frame["alpha"] > ALPHA_MIN) & (d_s > 0)
        sem = gbuf.semantic
        for c in np.unique(sem[proxy]):
            c = int(c)
            self.proxy_px[c] = self.proxy_px.get(c, 0) + int((proxy & (sem == c)).sum())
            self.covered_px[c] = self.covered_px.get(c, 0) + int((covered & (sem == c)).sum())
        idx = np.flatnonzero(covered)
        if idx.size > MAX_SAMPLES_PER_VIEW:
            idx = self.rng.choice(idx, MAX_SAMPLES_PER_VIEW, replace=False)
        if idx.size == 0:
            return
        dp = gbuf.depth.reshape(-1)[idx].astype(np.float64)
        rel = np.abs(d_s.reshape(-1)[idx] - dp) / dp
        _, rays = pixel_rays(camera)
        ray = rays.reshape(-1, 3)[idx]
        n_p = gbuf.normal.reshape(-1, 3)[idx].astype(np.float64)
        n_p = np.where((np.sum(n_p * ray, axis=1) > 0)[:, None], -n_p, n_p)   # face the camera
        n_s = unit(frame["normal_world"].reshape(-1, 3)[idx].astype(np.float64))
        ang = np.degrees(np.arccos(np.clip(np.sum(n_s * n_p, axis=1), -1.0, 1.0)))
        cls = sem.reshape(-1)[idx]
        for c in np.unique(cls):
            m = cls == c
            self.depth.setdefault(int(c), []).append(rel[m])
            self.angle.setdefault(int(c), []).append(ang[m])

    @staticmethod
    def _summary(rel: np.ndarray, ang: np.ndarray, proxy_px: int, covered_px: int) -> dict:
        return {"pixels": int(proxy_px), "coverage": round(covered_px / max(proxy_px, 1), 4),
                "depth_rel_err_median": round(float(np.median(rel)), 5) if rel.size else None,
                "depth_rel_err_p90": round(float(np.percentile(rel, 90)), 5) if rel.size else None,
                "normal_err_deg_median": round(float(np.median(ang)), 3) if ang.size else None,
                "normal_err_deg_p90": round(float(np.percentile(ang, 90)), 3) if ang.size else None}

    def result(self) -> dict:
        """{"per_class": {name: summary}, "all": summary}; medians over sampled pixels."""
        per = {}
        for c in sorted(self.proxy_px):
            name = CLASSES[c] if 0 <= c < len(CLASSES) else "unlabelled"
            rel = np.concatenate(self.depth.get(c, [np.zeros(0)]))
            ang = np.concatenate(self.angle.get(c, [np.zeros(0)]))
            per[name] = self._summary(rel, ang, self.proxy_px[c], self.covered_px.get(c, 0))
        rel = np.concatenate([np.concatenate(v) for v in self.depth.values()] or [np.zeros(0)])
        ang = np.concatenate([np.concatenate(v) for v in self.angle.values()] or [np.zeros(0)])
        return {"per_class": per, "all": self._summary(rel, ang, sum(self.proxy_px.values()),
                                                        sum(self.covered_px.values()))}


def unproject(camera: Camera, depth: np.ndarray, index: np.ndarray) -> np.ndarray:
    """World points of flat pixel indices `index` with camera z `depth` (flat values)."""
    j, i = np.divmod(index, camera.width)
    z = depth
    x_cam = np.stack([(i + 0.5 - camera.cx) / camera.fx * z, (j + 0.5 - camera.cy) / camera.fy * z, z], 1)
    return x_cam @ camera.pose[:3, :3].T + camera.pose[:3, 3]


def sample_depth(depth: np.ndarray, valid: np.ndarray, u: np.ndarray, v: np.ndarray,
                 edge: float = 0.05) -> np.ndarray:
    """Depth at continuous pixel coords (centres at +0.5): bilinear where the 4 neighbours are
    valid and within `edge` (relative) of each other — a smooth surface, where nearest-pixel
    sampling alone would leave an error of up to half a pixel's depth slope (large on ground
    seen at grazing angles) — else the nearest pixel (depth edges are not blended)."""
    h, w = depth.shape
    x = np.clip(u - 0.5, 0.0, w - 1.0)
    y = np.clip(v - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    d = np.stack([depth[y0, x0], depth[y0, x1], depth[y1, x0], depth[y1, x1]])
    ok = valid[y0, x0] & valid[y0, x1] & valid[y1, x0] & valid[y1, x1]
    lo, hi = d.min(0), d.max(0)
    ok &= (lo > 0) & (hi - lo <= edge * np.maximum(lo, 1e-12))
    fx, fy = x - x0, y - y0
    bil = (d[0] * (1 - fx) + d[1] * fx) * (1 - fy) + (d[2] * (1 - fx) + d[3] * fx) * fy
    ni = np.clip(np.floor(u).astype(np.int64), 0, w - 1)
    nj = np.clip(np.floor(v).astype(np.int64), 0, h - 1)
    return np.where(ok, bil, depth[nj, ni])


def _pixel_of(camera: Camera, points: np.ndarray):
    uv, z = camera.project(points)
    ok = np.isfinite(uv).all(1) & (z > camera.near)
    i = np.floor(np.where(ok, uv[:, 0], -1)).astype(np.int64)
    j = np.floor(np.where(ok, uv[:, 1], -1)).astype(np.int64)
    ok &= (i >= 0) & (i < camera.width) & (j >= 0) & (j < camera.height)
    return ok, np.where(ok, j * camera.width + i, 0), z


def reprojection_depth_error(cam_a: Camera, frame_a: dict, gbuf_a, cam_b: Camera, frame_b: dict,
                             gbuf_b, visibility_tol: float = 0.02) -> dict | None:
    """Reproject view a's surfel depth into view b and compare with b's surfel depth (sampled
    with `sample_depth`) where both see the same surface. Visibility comes from the proxy
    (independent of the surfels' own errors): a pixel of a counts when the proxy point it
    shows projects into b at a proxy depth within `visibility_tol` (relative) of its own —
    i.e. not occluded in b and not outside b's frame. Returns relative errors
    |z_ab − d_b| / z_ab summarised, or None when the views share no surface.
    """
    d_a = surfel_depth(frame_a).reshape(-1)
    ok_a = (frame_a["alpha"].reshape(-1) > ALPHA_MIN) & (d_a > 0) & gbuf_a.mask.reshape(-1)
    idx = np.flatnonzero(ok_a)
    if idx.size == 0:
        return None
    # proxy visibility test
    p_proxy = gbuf_a.position.reshape(-1, 3)[idx]
    vis, pix_p, z_p = _pixel_of(cam_b, p_proxy)
    pd_b = gbuf_b.depth.reshape(-1)[pix_p].astype(np.float64)
    vis &= np.isfinite(pd_b) & (np.abs(z_p - pd_b) <= visibility_tol * z_p)
    # surfel point of a, seen from b
    p_s = unproject(cam_a, d_a[idx], idx)
    ok, pix, z = _pixel_of(cam_b, p_s)
    depth_b = surfel_depth(frame_b)
    valid_b = (frame_b["alpha"] > ALPHA_MIN) & (depth_b > 0)
    uv, _ = cam_b.project(p_s)
    uv = np.where(ok[:, None], uv, 0.5)
    d_b = sample_depth(depth_b, valid_b, uv[:, 0], uv[:, 1])
    ok &= vis & valid_b.reshape(-1)[pix] & (d_b > 0)
    if not ok.any():
        return None
    rel = np.abs(z[ok] - d_b[ok]) / z[ok]
    return {"pixels": int(ok.sum()), "shared_frac": round(float(ok.sum() / idx.size), 4),
            "median": float(np.median(rel)), "mean": float(rel.mean()),
            "frac_over_5pct": float((rel > 0.05).mean()), "errors": rel}
