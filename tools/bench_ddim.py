"""DDIM inversion round-trip error against the number of steps N.

Invert z_0 to level t with N steps, denoise back with the same N, report max / mean |z_0' - z_0|
(float64). Noise predictors:
  linear:   a small fixed random linear network on a 4x8x8 latent, eps(z, k) = W_k z / scale + b,
            smooth in z and k (not an oracle), so the round trip is inexact and the error
            shrinks with N;
  gaussian: the exact eps of N(mu, s^2) data (closed form);
  point:    the exact eps of data concentrated at z* (round trip exact for every N).

usage: python tools/bench_ddim.py [--t 0.5 0.98] [--steps 1 2 5 10 20 50 100] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import math
import time

import torch

from lsd3d_usd.ggds.priors.ddim import DDIMSchedule


def linear_net(sched, dim, seed=0):
    g = torch.Generator().manual_seed(seed)
    W0 = torch.randn(dim, dim, generator=g, dtype=torch.float64) / math.sqrt(dim)
    W1 = torch.randn(dim, dim, generator=g, dtype=torch.float64) / math.sqrt(dim)
    b = 0.1 * torch.randn(dim, generator=g, dtype=torch.float64)

    def eps(z, k):
        s = k / (sched.num_train_timesteps - 1)  # smooth dependence on the level
        flat = z.reshape(-1)
        a = sched.alpha_bar(k)
        # mostly the "noise part" of z plus a small random linear map: a plausible smooth eps
        out = math.sqrt(1 - a) * flat + 0.3 * ((1 - s) * W0 + s * W1) @ flat * 0.5 + b
        return out.reshape(z.shape)
    return eps


def gaussian(sched, mu=0.3, sd=0.6):
    def eps(z, k):
        a = sched.alpha_bar(k)
        return math.sqrt(1 - a) * (z - math.sqrt(a) * mu) / (a * sd * sd + 1 - a)
    return eps


def point(sched, z_star):
    def eps(z, k):
        a = sched.alpha_bar(k)
        return (z - math.sqrt(a) * z_star) / math.sqrt(1 - a)
    return eps


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--t", type=float, nargs="+", default=[0.5, 0.98], help="noise levels in (0, 1]")
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 2, 5, 10, 20, 50, 100, 200])
    ap.add_argument("--json", help="also write the table as JSON here")
    args = ap.parse_args(argv)

    sched = DDIMSchedule()
    shape = (4, 8, 8)
    g = torch.Generator().manual_seed(0)
    z0 = torch.randn(shape, generator=g, dtype=torch.float64)
    fns = {"linear": linear_net(sched, z0.numel()), "gaussian": gaussian(sched), "point": point(sched, z0)}
    rows = []
    print(f"{'eps':>9} {'t':>5} {'N':>5} {'max_err':>11} {'mean_err':>11} {'ms':>8}")
    for name, fn in fns.items():
        for t in args.t:
            k = sched.level(t)
            for n in args.steps:
                t0 = time.perf_counter()
                back = sched.denoise(sched.invert(z0, fn, k, n), fn, k, n)
                ms = 1e3 * (time.perf_counter() - t0)
                err = (back - z0).abs()
                rows.append({"eps": name, "t": t, "N": n, "max_err": float(err.max()),
                             "mean_err": float(err.mean()), "ms": ms})
                print(f"{name:>9} {t:5.2f} {n:5d} {float(err.max()):11.3e} {float(err.mean()):11.3e} {ms:8.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
