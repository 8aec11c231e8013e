"""`add_actors`: place parked and moving actors in a scene's actors layer (by reference)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Usd

from lsd3d_usd import scene as S
from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors import people as P
from lsd3d_usd.actors.placement import KIND_WEIGHTS, crosswalk_footprints, parked_placements, parking_slots
from lsd3d_usd.actors.street import MAX_CYCLISTS, MAX_PEDESTRIANS, STATES, simulate_street
from lsd3d_usd.actors.traffic import simulate
from lsd3d_usd.actors.usdio import (
    ActorSpec,
    actors_layer,
    extend_root_time_range,
    scene_time_codes_per_second,
)
from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import ACTOR_SAMPLES, CLIP_SECONDS, FRAMES
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
    pedestrian_kinds: list[str] = field(default_factory=list)
    cyclist_kinds: list[str] = field(default_factory=list)
    street: object | None = None     # street.StreetRun when pedestrians or cyclists were asked


def resolve_library(scene, assets_dir=None, people: bool = False) -> dict[str, Path]:
    """kind -> asset file: ``assets_dir`` if given, else the scene's own assets/ folder, the
    procedural library written into it where missing (so the scene folder is
    self-contained: it never references a source checkout); with ``people`` the
    procedural pedestrians and cyclist too."""
    if assets_dir is not None:
        return A.library_assets(assets_dir)
    folder = Path(scene.root) / "assets"
    A.ensure_library(folder)
    if people:
        kinds = P.PEDESTRIAN_KINDS + P.CYCLIST_KINDS
        missing = [k for k in kinds if not (folder / f"{k}.usda").is_file()]
        if missing:
            P.write_people_library(folder, missing)
    return A.library_assets(folder)


DEFAULT_PEDESTRIANS = 12    # a street has people (`add_actors` with None)
DEFAULT_CYCLISTS = 2


def check_counts(**counts) -> None:
    """One error naming every count that is not a whole number in its range."""
    limits = {"pedestrians": MAX_PEDESTRIANS, "cyclists": MAX_CYCLISTS}
    bad = []
    for name, n in counts.items():
        hi = limits.get(name, 100_000)
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 0 <= n <= hi:
            bad.append(f"--{name} {n!r} (must be a whole number from 0 to {hi})")
    if bad:
        raise InputError(f"actors: {'; '.join(bad)}")


def add_actors(scene, layout, parked: int = 12, moving: int = 8, seed: int = 0, *,
               seconds: float = 8.0, fps: float = 10.0, assets_dir=None,
               kinds: dict | None = None, pedestrians: int | None = 0,
               cyclists: int | None = 0) -> ActorsResult:
    """Write the scene's actors layer: ``parked`` static actors in free parking slots,
    ``moving`` vehicles driven by the seeded IDM traffic model, ``pedestrians`` on the
    sidewalks and crosswalks and ``cyclists`` on bike lanes or the right of driving lanes
    (`street.simulate_street`), for ``seconds`` (samples at ``fps``, written at the scene's
    timeCodesPerSecond). Deterministic per seed. Replaces any previous actors layer (a step
    owns its layer). ``pedestrians`` / ``cyclists`` None: DEFAULT_PEDESTRIANS /
    DEFAULT_CYCLISTS where the asset folder has such assets, else none (a default never
    refuses a folder of vehicles only; an asked number does)."""

    check_counts(parked=parked, moving=moving,
                 **{k: v for k, v in (("pedestrians", pedestrians), ("cyclists", cyclists))
                    if v is not None})
    if not (fps > 0) or not (seconds > 0):
        raise InputError(f"actors: need --fps > 0 and --seconds > 0 (got {fps}, {seconds})")
    CLIP_SECONDS.check(seconds, "actors: --seconds")
    FRAMES.check(fps * seconds, "actors: --fps x --seconds", what="time samples per actor")
    ACTOR_SAMPLES.check((moving + (DEFAULT_PEDESTRIANS if pedestrians is None else pedestrians)
                         + (DEFAULT_CYCLISTS if cyclists is None else cyclists)) * fps * seconds,
                        "actors: (--moving + --pedestrians + --cyclists) x --fps x --seconds")
    t0 = time.perf_counter()
    library = resolve_library(scene, assets_dir, people=pedestrians != 0 or cyclists != 0)
    all_infos = {k: A.read_asset(p) for k, p in library.items()}
    by_class = {c: sorted(k for k, i in all_infos.items() if i.label == c)
                for c in (P.PEDESTRIAN_CLASS, P.CYCLIST_CLASS)}
    if pedestrians is None:
        pedestrians = DEFAULT_PEDESTRIANS if by_class[P.PEDESTRIAN_CLASS] else 0
    if cyclists is None:
        cyclists = DEFAULT_CYCLISTS if by_class[P.CYCLIST_CLASS] else 0
    for cls, n, flag in ((P.PEDESTRIAN_CLASS, pedestrians, "pedestrians"), (P.CYCLIST_CLASS, cyclists, "cyclists")):
        if n and not by_class[cls]:
            raise InputError(f"actors: --{flag} {n}: the asset folder {assets_dir} has no asset of "
                             f"UsdSemantics class {cls!r}")
    infos = {k: i for k, i in all_infos.items()
             if i.label not in (P.PEDESTRIAN_CLASS, P.CYCLIST_CLASS)}
    if not infos and (parked or moving):
        raise InputError(f"actors: the asset folder {assets_dir} has no vehicle asset")
    dims = {k: tuple(i.dimensions) for k, i in infos.items()}
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xAC7]))
    weights = {k: w for k, w in (kinds or KIND_WEIGHTS).items() if k in dims} or {k: 1.0 for k in dims}
    wk = sorted(weights)
    wp = np.array([weights[k] for k in wk], np.float64)
    wp /= wp.sum()
    notes = []

    # never on a crosswalk: pedestrians cross there (and parking on one is not allowed)
    places = parked_placements(layout, parked, seed, dims, weights, avoid=crosswalk_footprints(layout))
    if len(places) < parked:
        n_slots = len(parking_slots(layout))
        notes.append(f"no parked actors: the layout has no parking (no free parking spot, no lane "
                     "of type parking)" if n_slots == 0 else
                     f"only {len(places)} of {parked} parked actors fit in the layout's {n_slots} "
                     "free parking slots")
    moving_kinds = [wk[int(rng.choice(len(wk), p=wp))] for _ in range(moving)]
    run, street = None, None
    # the people are drawn from their own generator: vehicles keep their seeded draws
    prng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xBED]))
    ped_kinds = [by_class[P.PEDESTRIAN_CLASS][int(prng.integers(len(by_class[P.PEDESTRIAN_CLASS])))]
                 for _ in range(pedestrians)]
    cyc_kinds = [by_class[P.CYCLIST_CLASS][int(prng.integers(len(by_class[P.CYCLIST_CLASS])))]
                 for _ in range(cyclists)]
    if pedestrians or cyclists:
        street = simulate_street(
            layout, [(dims[k][0], dims[k][1]) for k in moving_kinds],
            [(all_infos[k].dimensions[0], all_infos[k].dimensions[1]) for k in cyc_kinds],
            [(k, all_infos[k].dimensions[0], all_infos[k].dimensions[1], _is_child(all_infos[k]))
             for k in ped_kinds], seed=seed, seconds=seconds, fps=fps)
        run = street.traffic
        n_cars = int((~run.cyclist).sum())
        n_cyc = int(run.cyclist.sum())
        if n_cars < moving:
            notes.append(f"only {n_cars} of {moving} moving actors found room on the lanes")
        if n_cyc < cyclists:
            notes.append(f"only {n_cyc} of {cyclists} cyclists found room on the lanes")
        if street.people.n < pedestrians:
            notes.append("no pedestrians: the layout has no sidewalk area (no sidewalk polygons or lanes, "
                         "and none derived along its roads within its extent)" if not street.walkable.tracks else
                         f"only {street.people.n} of {pedestrians} pedestrians found room on the "
                         f"sidewalks ({street.walkable.area.area:.0f} m²)")
        moving_kinds = moving_kinds[:n_cars]
        cyc_kinds = cyc_kinds[:n_cyc]
        ped_kinds = street.people.kinds
    elif moving:
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
    if street is not None:
        specs += _people_specs(street, moving_kinds, cyc_kinds, ped_kinds, all_infos, rel, name, prng)
    tcps = scene_time_codes_per_second(scene)
    info = {"seed": seed, "fps": fps, "seconds": seconds,
            "model": "IDM" if street is None else "IDM + sidewalk walkers"}
    layer = actors_layer(specs, tcps, seconds, info)
    prov = S.provenance("actors", {"parked": parked, "moving": moving, "pedestrians": pedestrians,
                                   "cyclists": cyclists, "fps": fps, "seconds": seconds,
                                   "assets": {k: str(v) for k, v in library.items()}},
                        seed=seed, timings={"seconds": round(time.perf_counter() - t0, 3)})
    path = scene.write_layer("actors", layer, prov)
    extend_root_time_range(scene, seconds * tcps, tcps)
    return ActorsResult(path, places, moving_kinds, run, library, tcps, seconds, notes,
                        list(ped_kinds), list(cyc_kinds), street)


def _is_child(info) -> bool:
    return info.kind == "child" or float(info.dimensions[2]) < 1.4


def _people_specs(street, moving_kinds, cyc_kinds, ped_kinds, infos, rel, name, rng) -> list:
    """ActorSpecs of the cyclists and pedestrians of a street run, with per-instance
    clothing colours and their joints driven by the distance each covers."""
    run, people = street.traffic, street.people
    specs = []
    parts = {k: _part_paths(infos[k].path) for k in set(cyc_kinds) | set(ped_kinds)}

    def own(kind, d):   # overs only on prims the asset has (a user asset named "adult" too)
        return {k: v for k, v in d.items() if k in parts[kind]}

    dt = float(run.t[1] - run.t[0]) if len(run.t) > 1 else 0.0
    for j, kind in enumerate(cyc_kinds):
        i = len(moving_kinds) + j
        dist = np.concatenate([[0.0], np.cumsum(0.5 * (run.speed[i, 1:] + run.speed[i, :-1]) * dt)])
        joints = P.cyclist_angles(dist) if kind in P.CYCLIST_KINDS else {}
        specs.append(ActorSpec(name(kind), "moving", rel[kind], run.position[i], run.yaw[i],
                               times=run.t, speed=run.speed[i], group="Cyclists",
                               colors=own(kind, _clothes(kind, rng)), joints=own(kind, joints)))
    for i, kind in enumerate(ped_kinds):
        joints = (P.gait_angles(people.walked[i], people.speed[i], P.BODIES[kind])
                  if kind in P.BODIES else {})
        state = STATES[int(people.state[i, 0])]
        specs.append(ActorSpec(name(kind), "moving", rel[kind], people.position[i], people.yaw[i],
                               times=run.t, speed=people.speed[i], group="Pedestrians",
                               colors=own(kind, _clothes(kind, rng)), joints=own(kind, joints),
                               extra={"behaviour": "standing" if state == "stand" else "walking"}))
    return specs


def _part_paths(asset_path) -> set[str]:
    """Paths of the prims below an asset's defaultPrim, relative to it ("LeftLeg/Mesh")."""
    stage = Usd.Stage.Open(str(asset_path))
    root = stage.GetDefaultPrim()
    if not root:
        return set()
    base = root.GetPath()
    return {str(p.GetPath().MakeRelativePath(base)) for p in Usd.PrimRange(root) if p != root}


def _clothes(kind: str, rng) -> dict:
    """Per-instance colours of a procedural person's parts (none for a user asset)."""
    if kind not in P.BODIES and kind not in P.CYCLIST_KINDS:
        return {}
    shirt = tuple(float(c) for c in P.SHIRTS[int(rng.integers(len(P.SHIRTS)))])
    legs = tuple(float(c) for c in P.TROUSERS[int(rng.integers(len(P.TROUSERS)))])
    skin = tuple(float(c) for c in P.SKIN[int(rng.integers(len(P.SKIN)))])
    if kind in P.CYCLIST_KINDS:
        return {"Torso": shirt, "Arms": shirt, "Head": skin, "LeftLeg/Mesh": legs, "RightLeg/Mesh": legs}
    return {"Torso": shirt, "LeftArm/Mesh": shirt, "RightArm/Mesh": shirt, "Head": skin,
            "LeftLeg/Mesh": legs, "RightLeg/Mesh": legs}


def layout_of_scene(scene):
    """The scene's layout (from its composed stage)."""
    stage = scene.open_stage(load=False)
    if not stage.GetPrimAtPath(LAYOUT_PATH):
        raise InputError(f"{scene.root}: the scene has no layout ({LAYOUT_PATH}); actors are placed "
                         "on its lanes and parking slots")
    return layout_from_stage(stage, str(scene.root))
