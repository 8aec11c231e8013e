"""Benchmark: a 2048x1024 sky per weather, seconds per stage (target: under 2 s per sky).

    python tools/bench_env.py [--resolution 2048x1024] [--repeat 3]

The one-time colour-science import (~1 s) is reported separately: a process pays it once.
"""
from __future__ import annotations

import argparse
import datetime as dt
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", default="2048x1024")
    ap.add_argument("--repeat", type=int, default=3, help="best of N per weather")
    args = ap.parse_args()
    w, h = (int(v) for v in args.resolution.lower().split("x"))

    t0 = time.perf_counter()
    from lsd3d_usd.env import EnvParams, render_sky, sh_irradiance
    from lsd3d_usd.env import colorspace as cs
    from lsd3d_usd.env.sky import SkyModel
    cs.xyz_to_rec709()
    cs.cmfs_1931()
    cs.daylight_rgb(6800.0)
    print(f"imports + colour-science tables (once per process): {time.perf_counter() - t0:.2f} s")

    tz = dt.timezone(dt.timedelta(hours=2))
    cases = [("clear noon", dict(weather="clear", when=dt.datetime(2026, 6, 21, 14, tzinfo=tz))),
             ("partly-cloudy morning", dict(weather="partly-cloudy",
                                            when=dt.datetime(2026, 6, 21, 9, tzinfo=tz))),
             ("rain dusk", dict(weather="rain", when=dt.datetime(2026, 6, 21, 22, 15, tzinfo=tz))),
             ("clear night (moon)", dict(weather="clear", when=dt.datetime(2026, 6, 22, 1, tzinfo=tz)))]
    for name, kw in cases:
        p = EnvParams(**kw)
        best, stages = float("inf"), {}
        for _ in range(args.repeat):
            t = time.perf_counter()
            m = SkyModel(p)
            img = render_sky(p, w, h, model=m)
            total = time.perf_counter() - t
            if total < best:
                best, stages = total, dict(m.timings)
        t = time.perf_counter()
        sh_irradiance(img)
        t_sh = time.perf_counter() - t
        detail = ", ".join(f"{k} {v:.3f}" for k, v in stages.items())
        print(f"{name:24s} {w}x{h}: {best:.3f} s  [{detail}]  (+ SH irradiance {t_sh:.3f} s)")


if __name__ == "__main__":
    main()
