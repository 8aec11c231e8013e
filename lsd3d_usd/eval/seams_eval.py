"""The seam measure of a scene (eval.seams) with the prior and light its GGDS run used."""
from __future__ import annotations

import numpy as np


def measure_seams(sc, run: str | None, layout, proxy, cameras, frames) -> tuple[dict | None, str | None]:
    """(seam statistics, None) over the given rendered views, or (None, why not)."""
    import torch

    from lsd3d_usd import configtree as ct
    from lsd3d_usd.env.exr import write_env
    from lsd3d_usd.eval.geometry import surfel_depth
    from lsd3d_usd.eval.seams import SeamStats
    from lsd3d_usd.ggds.conditioning import shadow_map, view_gbuffer
    from lsd3d_usd.ggds.envbridge import env_params, scene_light
    from lsd3d_usd.ggds.priors import PriorConfig, make_prior
    from lsd3d_usd.ggds.store import read_plan
    from lsd3d_usd.render.gbuffer import render_gbuffer
    from lsd3d_usd.splats.chunkio import read_chunk_map
    chunks = read_chunk_map(sc.layer_path("surfels"))
    keys = set(chunks)
    if len(keys) < 2:
        return None, "the scene's surfels are not stored in two or more chunks"
    if run is None:
        return None, "no GGDS run: the prior and light of its targets are unknown"
    try:
        plan = read_plan(sc, run)
    except Exception as e:  # an older run without a plan
        return None, f"run {run} has no readable plan ({e})"
    gen = plan["generate"]
    prior_cfg = ct.from_dict(PriorConfig, gen["prior"])
    if prior_cfg.kind != "procedural":
        return None, f"the run's prior ({prior_cfg.name}) is a GPU path; seams are measured " \
                     "with the procedural prior's targets only"
    seed = int(plan.get("seed", 0))
    params = env_params(gen["env"], seed)
    w, h = gen["env"]["resolution"]
    light = scene_light(params, write_env(params, sc.textures_dir, int(w), int(h)))
    prior = make_prior(prior_cfg, seed=seed)
    V, F, C = proxy
    shadow = shadow_map(V, F, light.sun_direction)
    bounds = {k: (b[0], b[1], b[3], b[4]) for k, v in chunks.items()
              if len(b := v.get("bounds") or []) == 6}
    stats = SeamStats(float(layout.chunk_size), keys, bounds=bounds)
    for j, (cam, fr) in enumerate(zip(cameras, frames)):
        gb = view_gbuffer(cam, V, F, C, shadow)
        x = torch.from_numpy(np.ascontiguousarray(fr["rgb"], np.float32))
        with torch.no_grad():
            tgt = prior.target(x.clamp(0, None), gb, light.prior_env, 1.0, seed=10_000 + j).numpy()
        stats.add(fr["rgb"], tgt, fr["alpha"], surfel_depth(fr), fr["normal_world"],
                  render_gbuffer(V, F, cam, C))
    return stats.result(), None
