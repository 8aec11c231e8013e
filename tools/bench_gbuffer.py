"""Benchmark the mesh G-buffer rasteriser: ~1 M triangles at 480x270 (and larger).

Usage: python tools/bench_gbuffer.py [--faces 1000000] [--repeat 3]
Prints seconds per frame (first call includes numba compilation / cache load).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import lsd3d_usd  # noqa: F401
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.render.gbuffer import render_gbuffer


def street_mesh(n_faces: int, seed: int = 0):
    """A ground grid plus box 'buildings' along a 400 m street: n_faces triangles, mostly
    small, as a proxy mesh at fine tessellation has."""
    rng = np.random.default_rng(seed)
    k = int(np.sqrt(n_faces / 4))
    xs = np.linspace(-200, 200, k + 1)
    ys = np.linspace(-30, 30, k + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = 0.02 * rng.standard_normal(X.shape)
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    idx = np.arange((k + 1) ** 2).reshape(k + 1, k + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    # facades: a second grid folded up on both sides
    V2 = V.copy()
    side = np.abs(V[:, 1]) >= 10.0
    V2[:, 2] = np.where(side, (np.abs(V[:, 1]) - 10.0), 0.0)
    V2[:, 1] = np.where(side, np.sign(V[:, 1]) * 10.0, V[:, 1])
    V = np.vstack([V, V2 + [0, 0, 0.01]])
    F = np.vstack([F, F + (k + 1) ** 2])
    return V, F


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--faces", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    V, F = street_mesh(args.faces)
    ids = np.zeros(len(F), np.int32)
    print(f"mesh: {len(F)} triangles, {len(V)} vertices")
    pose = look_at([-150, 0, 1.8], [0, 0, 1.5])
    for (w, h) in ((480, 270), (960, 540), (1920, 1080)):
        cam = Camera.from_fov(w, h, 90.0, pose, near=0.1, far=1000.0)
        times = []
        for _ in range(args.repeat + 1):
            t = time.perf_counter()
            g = render_gbuffer(V, F, cam, ids)
            times.append(time.perf_counter() - t)
        print(f"{w}x{h}: first {times[0]:.3f} s, best of {args.repeat} {min(times[1:]):.3f} s, "
              f"coverage {g.mask.mean():.2f}")


if __name__ == "__main__":
    main()
