"""Build a small sample scene (layout -> proxy -> surfels -> env -> actors) and render a
multi-camera rig clip from it: the frames docs/actors.md shows.

    python tools/make_rig_sample.py OUT_DIR [--seconds 3] [--fps 10] [--width 320] [--surfels 300000]

Until the lead's `generate` command lands this stands in for it: it calls the same library
steps (layout.generator, proxy.usdio.build_proxy_layer, splats.init.mesh_to_surfels,
env.write_env_layer, actors.compose.add_actors, views.rig.render_rig).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def build_scene(root: Path, seed: int = 3, extent=(200.0, 200.0), n_surfels: int = 300_000,
                parked: int = 14, moving: int = 10, seconds: float = 3.0, fps: float = 10.0,
                env: bool = True, log=print):
    from lsd3d_usd import semantics
    from lsd3d_usd.actors.compose import add_actors
    from lsd3d_usd.layout.generator import generate
    from lsd3d_usd.layout.usdio import layout_to_stage
    from lsd3d_usd.proxy.usdio import build_proxy_layer, read_proxy
    from lsd3d_usd.scene import Scene, new_stage, provenance
    from lsd3d_usd.splats.init import mesh_to_surfels
    from lsd3d_usd.splats.usdio import write_surfels

    t0 = time.perf_counter()
    scene = Scene.create(root, seed=seed, exist_ok=True)
    layout = generate(seed, extent)
    scene.write_layer("layout", layout_to_stage(layout), provenance("layout", seed=seed))
    log(f"layout: {layout.counts()['LaneCenter']} lanes ({time.perf_counter() - t0:.1f} s)")
    build_proxy_layer(layout, scene.layer_path("proxy"))
    scene.add_layer("proxy")
    meshes = [cm for chunk in read_proxy(scene.layer_path("proxy")).values() for cm in chunk.values()]
    V, F, ids, n = [], [], [], 0
    for cm in meshes:
        V.append(cm.vertices)
        F.append(cm.faces + n)
        ids.append(np.full(len(cm.faces), semantics.CLASS_ID.get(cm.cls, -1), np.int32))
        n += len(cm.vertices)
    field = mesh_to_surfels(np.concatenate(V), np.concatenate(F), np.concatenate(ids),
                            count=n_surfels, seed=seed, opacity=0.95, scale_factor=1.3)
    st = new_stage()
    write_surfels(st, "/World/Surfels", field)
    scene.write_layer("surfels", st, provenance("surfels", {"count": n_surfels}, seed=seed))
    log(f"proxy + {field.n} surfels ({time.perf_counter() - t0:.1f} s)")
    if env:
        from lsd3d_usd.env import write_env_layer
        from lsd3d_usd.env.prompt import build_params
        params, _ = build_params("sunny summer afternoon")
        write_env_layer(scene.layer_path("env"), params, width=512, height=256)
        scene.add_layer("env")
        log(f"env ({time.perf_counter() - t0:.1f} s)")
    res = add_actors(scene, layout, parked, moving, seed, seconds=seconds, fps=fps)
    log(f"actors: {len(res.parked)} parked, {res.run.n if res.run else 0} moving "
        f"({time.perf_counter() - t0:.1f} s)")
    return scene, layout


def pick_route(layout, min_length: float = 60.0) -> list[str]:
    """A drivable route through at least one junction: the longest non-junction lane, its
    first successor, and that lane's first successor."""
    from lsd3d_usd.layout.routes import LaneGraph
    g = LaneGraph(layout)
    order = np.argsort(-g.length)
    for i in order:
        if g.junction[i] or not g.succ[i]:
            continue
        route = [int(i)]
        while len(route) < 3 and g.succ[route[-1]]:
            route.append(g.succ[route[-1]][0])
        if sum(g.length[r] for r in route) >= min_length:
            return [g.ids[r] for r in route]
    return [g.ids[int(order[0])]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--surfels", type=int, default=300_000)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--no-env", action="store_true")
    a = ap.parse_args(argv)
    out = Path(a.out)
    scene, layout = build_scene(out / "scene", a.seed, n_surfels=a.surfels, seconds=max(a.seconds, 8.0),
                                fps=a.fps, env=not a.no_env)
    route = pick_route(layout)
    print("route:", ",".join(route))
    from lsd3d_usd.views.options import RigOptions
    from lsd3d_usd.views.rig import render_rig
    t0 = time.perf_counter()
    res = render_rig(scene.root, out / "clip",
                     RigOptions(name="waymo5", route=",".join(route), fps=a.fps, seconds=a.seconds),
                     width=a.width, progress=sys.stderr.isatty())
    n = sum(len(v) for v in res.frames.values())
    dt = time.perf_counter() - t0
    print(f"{n} frames in {dt:.1f} s ({dt / max(n, 1):.2f} s/frame); videos: {len(res.videos)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
