"""How a run splits a scene into regions, and the phases they run in (see the package doc)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.settings import RegionConfig


@dataclass(frozen=True)
class Region:
    keys: tuple       # sorted chunk keys
    name: str         # "" for a whole-scene region (files in the run folder), chunk_<i>_<j>

    def bounds(self, chunk_size: float) -> tuple[float, float, float, float]:
        k = np.asarray(self.keys, np.float64)
        return (float(k[:, 0].min() * chunk_size), float(k[:, 1].min() * chunk_size),
                float((k[:, 0].max() + 1) * chunk_size), float((k[:, 1].max() + 1) * chunk_size))

    def neighbourhood(self) -> set:
        return {(i + di, j + dj) for i, j in self.keys for di in (-1, 0, 1) for dj in (-1, 0, 1)}


def phases_from_plan(plan: dict) -> list[list[Region]]:
    """The phases a run recorded in its plan (run.json)."""
    return [[Region(tuple(tuple(k) for k in plan["regions"][name]), name) for name in phase]
            for phase in plan["phases"]]


def plan_regions(chunks, cfg: RegionConfig) -> list[list[Region]]:
    """Phases of regions over the scene's chunks ({key: info with "count"}, or keys; see the
    module doc)."""
    counts = chunks if isinstance(chunks, dict) else {k: {} for k in chunks}
    keys = sorted(tuple(int(v) for v in k) for k in counts)
    if not keys:
        raise InputError("GGDS: the scene has no surfel chunks")
    mode = cfg.mode
    if mode == "auto":
        total = sum(int((v or {}).get("count", 0)) for v in counts.values())
        small = len(keys) <= cfg.max_scene_chunks and total <= cfg.max_scene_surfels
        mode = "scene" if small else "chunk"
    if mode == "scene":
        return [[Region(tuple(keys), "")]]
    phases = {}
    for k in keys:
        phases.setdefault((k[0] % 2, k[1] % 2), []).append(
            Region((k,), S.chunk_prim_name(*k).lower()))
    return [phases[p] for p in sorted(phases, key=lambda p: (p[1], p[0]))]


def region_seed(seed: int, region: Region) -> int:
    if not region.name:
        return int(seed)
    ss = np.random.SeedSequence([int(seed)] + [int(v) & 0xFFFFFFFF for k in region.keys for v in k])
    return int(ss.generate_state(1)[0] % (2**31))
