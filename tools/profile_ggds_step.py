#!/usr/bin/env python
"""Time one GGDS step (GGDSRun.step) and its parts on a synthetic street.

Builds a 100 m street chunk (road, sidewalks, building façades on both sides, parked cars) as
a proxy mesh, seeds N surfels on it with mesh_to_surfels (default 500 k), samples views along
its lanes at WxH (default 480x270) and runs GGDSRun.step with the ProceduralPrior (or the
constant class-colour test prior with --prior class-colour), printing per step:

    view     the view's G-buffer unpacked from its cache
    render   rasterize forward (incl. parameter activation) ; rast_fwd = the rasteriser alone
    prior    prior.target
    loss     the loss terms (the EfficientNet perceptual loss unless --no-perceptual)
    backward loss.backward(); rast_bwd = the rasteriser's numba backward inside it
    update   selective Adam, the MCMC strategy

The per-view G-buffers are built (and cached by GGDSRun) before timing, as a real run builds
each once. Medians over the timed steps are printed last, with the machine load.

    python tools/profile_ggds_step.py [--n 500000] [--size 480x270] [--steps 6] [--no-perceptual]
"""
from __future__ import annotations

import argparse
import os
import time

# torch's and numba's OpenMP pools otherwise spin-wait after each parallel region and steal
# the cores from each other; must be set before torch loads (see the report / --spin).
if "--spin" not in __import__("sys").argv:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402


def street_mesh(length=100.0):
    """Proxy of one 100 m chunk: road |y|<4 with sidewalks to 7 m, façades at |y| = 7 m
    (12-20 m high, split into 10 m bays), terrain strips, a few parked cars (boxes)."""
    from lsd3d_usd.semantics import CLASS_ID
    v, f, ids = [], [], []

    def quad(p0, p1, p2, p3, cls):
        b = len(v)
        v.extend([p0, p1, p2, p3])
        f.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]])
        ids.extend([CLASS_ID[cls]] * 2)

    def box(x0, y0, x1, y1, h, cls):
        quad((x0, y0, h), (x1, y0, h), (x1, y1, h), (x0, y1, h), cls)
        quad((x0, y0, 0), (x1, y0, 0), (x1, y0, h), (x0, y0, h), cls)
        quad((x1, y1, 0), (x0, y1, 0), (x0, y1, h), (x1, y1, h), cls)
        quad((x0, y1, 0), (x0, y0, 0), (x0, y0, h), (x0, y1, h), cls)
        quad((x1, y0, 0), (x1, y1, 0), (x1, y1, h), (x1, y0, h), cls)

    rng = np.random.default_rng(0)
    for x in np.arange(0.0, length, 5.0):
        quad((x, -4, 0), (x + 5, -4, 0), (x + 5, 4, 0), (x, 4, 0), "road")
        for s in (-1, 1):
            quad((x, 4 * s, 0.15), (x + 5, 4 * s, 0.15), (x + 5, 7 * s, 0.15), (x, 7 * s, 0.15), "sidewalk")
    for x in np.arange(0.0, length, 10.0):
        for s in (-1, 1):
            h = float(rng.uniform(12, 20))
            quad((x, 7 * s, 0), (x + 10, 7 * s, 0), (x + 10, 7 * s, h), (x, 7 * s, h), "building")
    for x in np.arange(5.0, length - 5.0, 17.0):
        s = 1 if rng.uniform() < 0.5 else -1
        box(x, 2.2 * s, x + 4.5, 3.9 * s, 1.5, "vehicle")
    return np.array(v, float), np.array(f, np.int64), np.array(ids, np.int32)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=500_000, help="surfel count (default 500000)")
    ap.add_argument("--size", default="480x270", help="render resolution WxH (default 480x270)")
    ap.add_argument("--steps", type=int, default=6, help="timed steps (default 6, after 1 warm-up)")
    ap.add_argument("--prior", choices=("procedural", "class-colour"), default="procedural")
    ap.add_argument("--no-perceptual", action="store_true", help="without the perceptual loss")
    ap.add_argument("--views", type=int, default=8, help="training views (default 8)")
    ap.add_argument("--spin", action="store_true",
                    help="leave OMP_WAIT_POLICY unset (OpenMP threads spin-wait; the default "
                         "without this tool's setting)")
    a = ap.parse_args(argv)
    w, h = (int(x) for x in a.size.lower().split("x"))

    import lsd3d_usd  # noqa: F401  (schema registration; torch first as in the CLI)
    from lsd3d_usd.conditioning.scene import Conditioning
    from lsd3d_usd.conditioning.view_sampling import sample_views
    from lsd3d_usd.ggds.priors.base import Prior
    from lsd3d_usd.ggds.run import step as step_mod
    from lsd3d_usd.ggds.run.inputs import GGDSInputs
    from lsd3d_usd.ggds.run.optimisation import GGDSRun
    from lsd3d_usd.ggds.settings import GGDSConfig
    from lsd3d_usd.layout.model import LaneCenter, Layout
    from lsd3d_usd.semantics import CLASS_COLORS
    from lsd3d_usd.splats.init import mesh_to_surfels

    torch.manual_seed(0)
    t0 = time.perf_counter()
    V, F, ids = street_mesh()
    field, face = mesh_to_surfels(V, F, ids, count=a.n, seed=0, sh_degree=1, return_face_index=True)
    layout = Layout(lanes=[LaneCenter(id="l0", points=[[2, -2, 0], [98, -2, 0]]),
                           LaneCenter(id="l1", points=[[98, 2, 0], [2, 2, 0]])])
    views = sample_views(layout, a.views, w, h, seed=0, novel_frac=0.25)
    sky = torch.tensor([0.55, 0.65, 0.85])
    if a.prior == "procedural":
        from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
        prior = ProceduralPrior()
    else:
        class ClassColour(Prior):
            name = "class-colour"

            def target(self, x, gbuffer, env, t, n_steps=5, seed=None):
                col = torch.from_numpy(CLASS_COLORS)[gbuffer.semantic.clamp(min=0)]
                return torch.where((gbuffer.semantic >= 0)[..., None], col, sky)
        prior = ClassColour()
    weights = dict(GGDSConfig().weights, perceptual=0.0 if a.no_perceptual else 0.05)
    cfg = GGDSConfig(steps=1000, resolution=(w, h), views=a.views, seed=0, weights=weights,
                     perceptual=not a.no_perceptual)
    cond = Conditioning.of_arrays((V, F, ids),
                                  backdrop=lambda cam: sky.expand(cam.height, cam.width, 3).contiguous())
    run = GGDSRun(GGDSInputs(field=field, conditioning=cond, views=views, face_index=face),
                  prior, cfg)
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(len(views)):
        run.view_data(i)
    t_views = time.perf_counter() - t0
    print(f"setup {t_setup:.2f} s ({len(field.positions)} surfels, {len(F)} faces); "
          f"G-buffers of {len(views)} views {t_views:.2f} s (once per view, cached)")

    stats: dict = {}
    orig_rasterize = step_mod.rasterize

    def rasterize_spy(*args, **kw):
        t = time.perf_counter()
        out = orig_rasterize(*args, **kw)
        stats["rast_fwd"] = time.perf_counter() - t
        stats["raster"] = out.stats  # the backward adds its timings to it
        return out

    step_mod.rasterize = rasterize_spy
    cols = ("total", "view", "render", "rast_fwd", "prior", "loss", "backward", "rast_bwd",
            "update")
    rows = []
    try:
        print(" ".join(f"{c:>9}" for c in ("step", "visible") + cols))
        for k in range(a.steps + 1):
            rec = run.step()
            t = {"total": rec["seconds"], "rast_fwd": stats["rast_fwd"],
                 "rast_bwd": stats["raster"].timings.get("backward_s", float("nan")),
                 **{c: rec[f"{c}_s"] for c in ("view", "render", "prior", "loss", "backward",
                                                "update")}}
            tag = "warm-up" if k == 0 else str(k)
            print(f"{tag:>9} {rec['visible']:>9} " + " ".join(f"{t[c]:9.3f}" for c in cols),
                  flush=True)
            if k > 0:
                rows.append([t[c] for c in cols])
    finally:
        step_mod.rasterize = orig_rasterize
    med = np.median(np.array(rows), axis=0)
    print(f"{'median':>9} {'':>9} " + " ".join(f"{v:9.3f}" for v in med))
    print(f"load average {os.getloadavg()} on {os.cpu_count()} cores, OMP_WAIT_POLICY="
          f"{os.environ.get('OMP_WAIT_POLICY', 'unset')} (timings are wall seconds; a loaded "
          f"machine inflates them)")


if __name__ == "__main__":
    main()
