"""`lsd3d-usd bench sim`: closed-loop steps per second on a scene (default: the README sample
generated with generate's defaults) and the memory of a long episode.

Three configurations, each the median over ``repeats`` runs of ``steps`` env steps (the
planner drives; only `env.step` is timed: the world, the scores and the sensors): (a) ``world`` no sensors (traffic, pedestrians, scores), (b) ``front`` one front
camera at 480×270, (c) ``full`` nuscenes6 at 480×270 + hdl32. Peak RSS of the process, and
with ``memory_seconds`` an episode of that length (rig none, the planner driving routes back
to back) with RSS sampled each simulated minute: growth after the first minute.
"""
from __future__ import annotations

import json
import resource
import statistics
import time
from pathlib import Path

from lsd3d_usd.benchmarks.sample import scene_or_sample

CONFIGS = {
    "world": dict(rig="none", lidar="none"),
    "front": dict(rig="nuscenes6", lidar="none", cameras=("CAM_FRONT",), width=480),
    "full": dict(rig="nuscenes6", lidar="hdl32", width=480),
}


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _current_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def steps_per_second(scene, config: dict, steps: int, repeats: int, seed: int = 0) -> dict:
    """Median env steps per second over ``repeats`` timed runs; only `env.step` is timed (the
    planner drives, its own time and the resets between routes left out)."""
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.policies import Planner
    env = DriveEnv(scene, seconds=3600.0, **config)
    rates = []
    for r in range(repeats + 1):              # run 0 warms up (kernels, chunk loading)
        obs, info = env.reset(seed=seed + r)
        pol = Planner(env)
        spent, n = 0.0, 0
        while n < steps:
            action = pol(obs, info)
            t = time.perf_counter()
            obs, _, term, trunc, info = env.step(action)
            spent += time.perf_counter() - t
            n += 1
            if term or trunc:
                obs, info = env.reset(seed=seed + r + 1000 + n)
                pol = Planner(env)
        if r:
            rates.append(n / spent)
    env.close()
    return {"steps_per_s": statistics.median(rates), "runs": [round(x, 2) for x in rates]}


def memory_over(scene, seconds: float, seed: int = 0, log=print) -> dict:
    """RSS (MB) each simulated minute of a long closed-loop run (the planner, rig none)."""
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.policies import Planner
    env = DriveEnv(scene, rig="none", lidar="none", seconds=seconds)
    obs, info = env.reset(seed=seed)
    pol = Planner(env)
    samples, t, k = [], 0.0, 0
    while t < seconds:
        obs, _, term, trunc, info = env.step(pol(obs, info))
        t += env.dt
        k += 1
        if k % int(round(60 * env.settings.hz)) == 0:
            samples.append(round(_current_rss_mb(), 1))
            log(f"bench sim: {t / 60:.0f} simulated min, RSS {samples[-1]} MB")
        if term or trunc:                     # a new route: the same process goes on
            obs, info = env.reset(seed=seed + k)
    env.close()
    growth = (samples[-1] / samples[0] - 1.0) if len(samples) > 1 else 0.0
    return {"rss_mb_per_minute": samples, "rss_growth_after_first_minute": growth}


def main(json_path=None, *, scene=None, quick=False, steps=None, repeats=None,
         memory_seconds=None, remote=False, log=print) -> dict:
    steps = steps or (20 if quick else 100)
    repeats = repeats or (1 if quick else 3)
    with scene_or_sample(scene, quick, "bench sim", log) as target:
        res = {"scene": str(scene or "README sample"), "steps": steps, "repeats": repeats}
        for name, cfg in CONFIGS.items():
            n = steps if name == "world" else max(5, steps // (10 if name == "full" else 4))
            got = steps_per_second(target, cfg, n, repeats)
            res[f"steps_per_s_{name}"] = round(got["steps_per_s"], 3)
            res[f"runs_{name}"] = got["runs"]
            log(f"bench sim: {name}: {got['steps_per_s']:.2f} steps/s (runs {got['runs']})")
        if memory_seconds:
            res.update(memory_over(target, memory_seconds, log=log))
        if remote:
            from lsd3d_usd.benchmarks.sim_remote import overhead
            r = overhead(target, "nuscenes6", "hdl32", 480, max(5, steps // 10))
            res.update({f"remote_{k}": (round(v, 4) if isinstance(v, float) else v)
                        for k, v in r.items()})
            log(f"bench sim: remote: {r['overhead_pct']:+.1f} % per step "
                f"(codec {r['codec_pct']:.1f} %)")
        res["peak_rss_mb"] = round(_rss_mb(), 1)
    log(json.dumps(res, indent=1))
    if json_path:
        Path(json_path).write_text(json.dumps(res, indent=2))
        log(f"wrote {json_path}")
    return res
