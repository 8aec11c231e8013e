"""`add_actors`: place parked and moving actors in a scene's actors layer (by reference)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors.placement import KIND_WEIGHTS, parked_placements, parking_slots
from lsd3d_usd.actors.traffic import simulate
from lsd3d_usd.actors.usdio import (
    ActorSpec,
    actors_layer,
    extend_root_time_range,
    scene_time_codes_per_second,
)
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.usdio import layout_from_stage
from lsd3d_usd.scene import LAYOUT_PATH


@dataclass
class ActorsResult:
    layer: Path
    parked: list                     # placement.Placement
    moving_kinds: list[str]
    run: object | None               # traffic.TrafficRun
    assets: dict[str, Path]
    tcps: float
    seconds: float
    notes: list[str] = field(default_factory=list)


def resolve_library(scene, assets_dir=None) -> dict[str, Path]:
    """kind -> asset file: ``assets_dir`` if given, else the scene's own assets/ folder, the
    procedural library written into it where missing (so the scene folder is
    self-contained: it never references a source checkout)."""
    if assets_dir is not None:
        return A.library_assets(assets_dir)
    folder = Path(scene.root) / "assets"
    A.ensure_library(folder)
    return A.library_assets(folder)


def add_actors(scene, layout, parked: int = 12, moving: int = 8, seed: int = 0, *,
               seconds: float = 8.0, fps: float = 10.0, assets_dir=None,
               kinds: dict | None = None) -> ActorsResult:
    """Write the scene's actors layer: ``parked`` static actors in free parking slots and
    ``moving`` actors driven by the seeded IDM traffic model for ``seconds`` (samples at
    ``fps``, written at the scene's timeCodesPerSecond). Deterministic per seed.
    Replaces any previous actors layer (a step owns its layer)."""

    if parked < 0 or moving < 0:
        raise InputError(f"actors: counts must be >= 0 (parked={parked}, moving={moving})")
    if not (fps > 0) or not (seconds > 0):
        raise InputError(f"actors: need --fps > 0 and --seconds > 0 (got {fps}, {seconds})")
    t0 = time.perf_counter()
    library = resolve_library(scene, assets_dir)
    infos = {k: A.read_asset(p) for k, p in library.items()}
    dims = {k: tuple(i.dimensions) for k, i in infos.items()}
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xAC7]))
    weights = {k: w for k, w in (kinds or KIND_WEIGHTS).items() if k in dims} or {k: 1.0 for k in dims}
    wk = sorted(weights)
    wp = np.array([weights[k] for k in wk], np.float64)
    wp /= wp.sum()
    notes = []

    places = parked_placements(layout, parked, seed, dims, weights)
    if len(places) < parked:
        n_slots = len(parking_slots(layout))
        notes.append(f"no parked actors: the layout has no parking (no free parking spot, no lane "
                     "of type parking)" if n_slots == 0 else
                     f"only {len(places)} of {parked} parked actors fit in the layout's {n_slots} "
                     "free parking slots")
    moving_kinds = [wk[int(rng.choice(len(wk), p=wp))] for _ in range(moving)]
    run = None
    if moving:
        run = simulate(layout, [dims[k][0] for k in moving_kinds], seed=seed, seconds=seconds, fps=fps)
        if run.n < moving:
            notes.append(f"only {run.n} of {moving} moving actors found room on the lanes")
        moving_kinds = moving_kinds[:run.n]

    layer_dir = scene.layer_path("actors").parent
    rel = {k: A.relative_asset_path(p, layer_dir) for k, p in library.items()}
    specs, counter = [], {}

    def name(kind):
        counter[kind] = counter.get(kind, -1) + 1
        return f"{kind[:1].upper()}{kind[1:]}_{counter[kind]:03d}"

    def paint():
        return tuple(float(c) for c in A.PAINTS[int(rng.integers(len(A.PAINTS)))])

    for pl in places:
        specs.append(ActorSpec(name(pl.kind), "parked", rel[pl.kind], pl.position, pl.yaw,
                               paint=paint(), extra={"slot": pl.slot},
                               paint_slot=infos[pl.kind].paint_slot))
    for i, kind in enumerate(moving_kinds):
        specs.append(ActorSpec(name(kind), "moving", rel[kind], run.position[i], run.yaw[i],
                               times=run.t, speed=run.speed[i], paint=paint(),
                               paint_slot=infos[kind].paint_slot))
    tcps = scene_time_codes_per_second(scene)
    info = {"seed": seed, "fps": fps, "seconds": seconds, "model": "IDM"}
    layer = actors_layer(specs, tcps, seconds, info)
    prov = S.provenance("actors", {"parked": parked, "moving": moving, "fps": fps, "seconds": seconds,
                                   "assets": {k: str(v) for k, v in library.items()}},
                        seed=seed, timings={"seconds": round(time.perf_counter() - t0, 3)})
    path = scene.write_layer("actors", layer, prov)
    extend_root_time_range(scene, seconds * tcps, tcps)
    return ActorsResult(path, places, moving_kinds, run, library, tcps, seconds, notes)


def layout_of_scene(scene):
    """The scene's layout (from its composed stage)."""
    stage = scene.open_stage(load=False)
    if not stage.GetPrimAtPath(LAYOUT_PATH):
        raise InputError(f"{scene.root}: the scene has no layout ({LAYOUT_PATH}); actors are placed "
                         "on its lanes and parking slots")
    return layout_from_stage(stage, str(scene.root))
