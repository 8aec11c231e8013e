"""Temporal consistency along a camera path: frame-to-frame warp error with depth and known
poses, masked for disocclusions.

For consecutive frames (prev, cur): every surfel pixel of cur (alpha > 0.5) is unprojected
with its surfel depth, projected into prev and bilinearly sampled there. It counts when it
lands inside prev, prev has surfels at the nearest pixel, and prev's depth there agrees with
the point's depth in prev within `tol` (relative) — otherwise the point is occluded or newly
revealed (disoccluded) in prev. The error is the mean absolute difference of display (sRGB,
[0, 1]) colours over the counted pixels. Sky pixels are left out (alpha <= 0.5): the env map is
at infinity and does not test the surfels. For scale, the naive error (cur − prev, no warp,
all pixels) is reported beside it.
"""
from __future__ import annotations

import numpy as np

from lsd3d_usd.eval.geometry import ALPHA_MIN, surfel_depth, unproject
from lsd3d_usd.render.camera import Camera


def bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample img (H,W,C) at continuous pixel coords (pixel centres at +0.5), edge-clamped."""
    h, w = img.shape[:2]
    x = np.clip(u - 0.5, 0.0, w - 1.0)
    y = np.clip(v - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def warp_error(cam_prev: Camera, img_prev: np.ndarray, frame_prev: dict,
               cam_cur: Camera, img_cur: np.ndarray, frame_cur: dict, tol: float = 0.03) -> dict:
    """Warp error of one frame pair; img_* are display images (H,W,3) in [0, 1]."""
    h, w = img_cur.shape[:2]
    d_cur = surfel_depth(frame_cur).reshape(-1)
    idx = np.flatnonzero((frame_cur["alpha"].reshape(-1) > ALPHA_MIN) & (d_cur > 0))
    naive = float(np.abs(img_cur.astype(np.float64) - img_prev).mean())
    if idx.size == 0:
        return {"valid_frac": 0.0, "err": None, "naive_err": naive, "pixels": 0}
    pts = unproject(cam_cur, d_cur[idx], idx)
    uv, z = cam_prev.project(pts)
    ok = np.isfinite(uv).all(1) & (z > cam_prev.near)
    u, v = np.where(ok, uv[:, 0], -1.0), np.where(ok, uv[:, 1], -1.0)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ii = np.clip(np.floor(u).astype(np.int64), 0, w - 1)
    jj = np.clip(np.floor(v).astype(np.int64), 0, h - 1)
    d_prev = surfel_depth(frame_prev)[jj, ii]
    ok &= (frame_prev["alpha"][jj, ii] > ALPHA_MIN) & (d_prev > 0) & (np.abs(d_prev - z) <= tol * z)
    if not ok.any():
        return {"valid_frac": 0.0, "err": None, "naive_err": naive, "pixels": 0}
    warped = bilinear(img_prev.astype(np.float64), u[ok], v[ok])
    cur = img_cur.reshape(-1, 3)[idx[ok]].astype(np.float64)
    diff = np.abs(cur - warped).mean(axis=1)
    return {"valid_frac": round(float(ok.sum() / (h * w)), 4), "err": float(diff.mean()),
            "naive_err": naive, "pixels": int(ok.sum())}


def trajectory_warp_errors(cams: list, images: list, frames: list, tol: float = 0.03) -> dict:
    """Warp errors of all consecutive pairs along a path, pixel-weighted mean overall."""
    pairs = [warp_error(cams[t - 1], images[t - 1], frames[t - 1], cams[t], images[t], frames[t], tol)
             for t in range(1, len(cams))]
    n = sum(p["pixels"] for p in pairs)
    mean = sum(p["err"] * p["pixels"] for p in pairs if p["err"] is not None) / n if n else None
    return {"warp_err": None if mean is None else round(mean, 5),
            "naive_err": round(float(np.mean([p["naive_err"] for p in pairs])), 5) if pairs else None,
            "valid_frac": round(float(np.mean([p["valid_frac"] for p in pairs])), 4) if pairs else None,
            "pairs": len(pairs),
            "per_pair": [None if p["err"] is None else round(p["err"], 5) for p in pairs],
            "tol": tol}
