"""A generated scene opened for closed-loop driving: its layout and lane graph, the drivable
area and static obstacles the scores need, and its sensors rendered through views/ with the
agents at their simulated poses.

The scene is read, never written. Chunks stream around the sensors (views.stage_data's
ChunkStreamer). The scene's parked actors stay where the scene put them (static obstacles
and rendered); its moving vehicles and people are replaced by the simulation's own agents,
drawn with the scene's asset files (procedural ones, written to a temporary folder, where
the scene has none of a kind).
"""
from __future__ import annotations

import math
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import shapely
from pxr import Sdf, Usd, UsdGeom

from lsd3d_usd import scene as S
from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors import people as P
from lsd3d_usd.actors.usdio import ROLE_ATTR, ActorSet, PlacedActor
from lsd3d_usd.assetroots import check_scene
from lsd3d_usd.datasets.maps import drivable_area as road_area
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.layout.usdio import layout_from_stage
from lsd3d_usd.views.stage_data import SceneReader
from lsd3d_usd.views.options import DEFAULT_LOD_PX

TRUNK_RADIUS = 0.3          # m: a tree is an obstacle at its trunk, not its crown
POLE_RADIUS = 0.15          # m
PAINTS = 4                  # paint variants per vehicle kind


def drivable_area(layout, margin: float = 0.25):
    """The layout's drivable area (shapely): the proxy's road surface (`datasets.maps`, the
    one the images show and the nuScenes map masks hold), grown by ``margin`` m (a wheel on
    the road's edge line is still on the road)."""
    road = road_area(layout)
    return road.buffer(margin) if margin and not road.is_empty else road


def static_obstacles(layout) -> tuple[list, list]:
    """(polygons, ids) of what the ego must not hit: buildings, poles, tree trunks, signs,
    traffic-light poles, barriers and hedges."""
    polys, ids = [], []
    for b in layout.buildings:
        p = shapely.Polygon(np.asarray(b.footprint, np.float64)[:, :2])
        polys.append(p if p.is_valid else p.buffer(0))
        ids.append(f"building:{b.id}")
    for group, name, r in ((layout.poles, "pole", POLE_RADIUS), (layout.trees, "tree", TRUNK_RADIUS),
                           (layout.traffic_signs, "sign", POLE_RADIUS),
                           (layout.traffic_lights, "traffic_light", POLE_RADIUS)):
        for f in group:
            x, y = np.asarray(f.position, np.float64)[:2]
            polys.append(shapely.Point(x, y).buffer(r, 8))
            ids.append(f"{name}:{f.id}")
    for group, name in ((layout.barriers, "barrier"), (layout.hedges, "hedge")):
        for f in group:
            pts = np.asarray(f.points, np.float64)[:, :2]
            if len(pts) >= 2:
                polys.append(shapely.LineString(pts).buffer(max(float(f.width), 0.1) / 2))
                ids.append(f"{name}:{f.id}")
    return polys, ids


def scaled_actor(a: PlacedActor, dims) -> PlacedActor:
    """``a`` stretched per axis to ``dims`` (length, width, height) about its frame's origin
    (the box's bottom centre, so it stays on the ground and centred); surfel disks scale by
    the mean stretch. Degenerate sizes (zero, not finite) keep the asset's own."""
    want = np.asarray(dims, np.float64)[:3]
    have = np.asarray(a.dims, np.float64)[:3]
    if not (np.all(np.isfinite(want)) and np.all(want > 0) and np.all(have > 0)):
        return a
    s = want / have
    meshes = [replace(m, vertices=np.asarray(m.vertices, np.float64) * s) for m in a.meshes]
    surfels = a.surfels
    if surfels is not None:
        g = float(np.cbrt(np.prod(s)))
        surfels = replace(surfels, positions=surfels.positions * s.astype(np.float32),
                          scales=surfels.scales * np.float32(g))
    return replace(a, meshes=meshes, surfels=surfels, dims=want.copy())


class SimActors:
    """The agents of an episode as `views` reads actors (the interface of
    actors.usdio.ActorSet): geometry in each agent's own frame, placed by `set_poses`."""

    def __init__(self, actors: list[PlacedActor], matrices: list[np.ndarray]):
        self.actors = actors
        self._M = [np.asarray(m, np.float64) for m in matrices]
        self._vis = [True] * len(actors)

    def __len__(self) -> int:
        return len(self.actors)

    def set_pose(self, q: int, x: float, y: float, z: float, yaw: float) -> None:
        c, s = math.cos(yaw), math.sin(yaw)
        M = np.eye(4)
        M[:2, :2] = [[c, -s], [s, c]]
        M[:3, 3] = x, y, z
        self._M[q] = M

    def set_visible(self, q: int, shown: bool) -> None:
        self._vis[q] = bool(shown)

    def transforms(self, time_code=None) -> list[np.ndarray]:
        return list(self._M)

    def visible(self, time_code=None) -> list[bool]:
        return list(self._vis)

    def part_transforms(self, q: int, time_code=None) -> list[np.ndarray]:
        return []


class SimScene:
    """A scene folder opened for driving (see the module doc)."""

    def __init__(self, scene, stream_radius: float = 300.0, use_env: bool = True,
                 lod_px: float = DEFAULT_LOD_PX):
        sp = Path(scene)
        root = (sp / S.ROOT_FILE if sp.is_dir() else sp).absolute()
        if not root.is_file():
            raise InputError(f"{scene}: not a scene (no {S.ROOT_FILE})")
        self.root = root
        self.stage = S.open_stage(root, load=False)
        check_scene(self.stage, root)
        if not self.stage.GetPrimAtPath(S.LAYOUT_PATH):
            raise InputError(f"{scene}: the scene has no layout ({S.LAYOUT_PATH}) to drive on")
        self.layout = layout_from_stage(self.stage, str(scene))
        self.graph = LaneGraph(self.layout, bike_lanes=True)
        if not any(~self.graph.bike):
            raise InputError(f"{scene}: the layout has no drivable lanes")
        rl = self.stage.GetRootLayer()
        self.tcps = float(rl.timeCodesPerSecond) if rl.HasTimeCodesPerSecond() else 24.0
        self.drivable = drivable_area(self.layout)
        shapely.prepare(self.drivable)
        self.obstacles, self.obstacle_ids = static_obstacles(self.layout)
        self.reader = SceneReader(self.stage, use_env=use_env, actors=False,
                                  stream_radius=stream_radius, lod_px=lod_px)
        self._tmp = None
        scene_actors = ActorSet(self.stage) if self.stage.GetPrimAtPath(S.ACTORS_PATH) else None
        self.parked: list[tuple[PlacedActor, np.ndarray]] = []
        if scene_actors is not None:
            t0 = Usd.TimeCode.EarliestTime()
            for a, M in zip(scene_actors.actors, scene_actors.transforms(t0)):
                if a.role == "parked":
                    self.parked.append((a, M))
        self.templates = self._templates()
        self._signal_groups = None

    @property
    def signal_groups(self) -> list:
        """layout.signals' groups of the scene: the map's lights, and the derived ones when
        the scene's proxy placed them (its ``traffic_lights`` parameter, default on)."""
        if self._signal_groups is None:
            from lsd3d_usd.layout.signals import CURB_WIDTH, signal_groups
            prm = {}
            for layer in self.stage.GetLayerStack():
                prov = S.read_provenance(layer)
                if prov.get("step") == "proxy":
                    prm = dict(prov.get("params") or {})
                    break
            curb = dict(prm.get("ground") or {}).get("curb_width", CURB_WIDTH)
            self._signal_groups = signal_groups(self.layout, bool(prm.get("traffic_lights", True)),
                                                float(curb))
        return self._signal_groups

    def close(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    # ---- agent geometry
    def _library(self) -> dict[str, Path]:
        """kind -> asset file: the scene's own assets/ where present, procedural ones in a
        temporary folder for the kinds it lacks (the scene is never written)."""
        own = {}
        folder = self.root.parent / S.ASSETS_DIR
        if folder.is_dir():
            try:
                own = A.library_assets(folder)
            except InputError:
                own = {}
        need_v = [k for k in ("car", "van") if k not in own]
        need_p = [k for k in P.PEDESTRIAN_KINDS + P.CYCLIST_KINDS if k not in own]
        if need_v or need_p:
            self._tmp = Path(tempfile.mkdtemp(prefix="lsd3d_sim_assets_"))
            for k in need_v:
                own[k] = A.write_vehicle_asset(k, self._tmp / f"{k}.usda")
            if need_p:
                own.update(P.write_people_library(self._tmp, need_p))
        return own

    def _templates(self) -> dict[str, list[PlacedActor]]:
        """label -> templates (one per kind and paint) read through a library stage in memory."""
        lib = self._library()
        stage = Usd.Stage.CreateInMemory()
        UsdGeom.Xform.Define(stage, "/Lib")
        rng = np.random.default_rng(0xB0D)
        for kind, path in sorted(lib.items()):
            info = A.read_asset(path)
            n = PAINTS if info.label == A.VEHICLE_CLASS else 1
            for k in range(n):
                prim = stage.DefinePrim(f"/Lib/{kind}_{k}", "Xform")
                prim.GetReferences().AddReference(str(path))
                prim.CreateAttribute(ROLE_ATTR, Sdf.ValueTypeNames.String).Set("moving")
                if info.label == A.VEHICLE_CLASS and info.paint_slot:
                    A.set_paint(prim, A.PAINTS[int(rng.integers(len(A.PAINTS)))])
        out: dict[str, list[PlacedActor]] = {}
        for a in ActorSet(stage, "/Lib").actors:
            # limbs and wheels stay in their first pose: the agents move, their joints do not
            out.setdefault(a.label, []).append(replace(a, animated=[]))
        return out

    def template(self, label: str, k: int, kind: str | None = None) -> PlacedActor:
        opts = self.templates.get(label) or self.templates[A.VEHICLE_CLASS]
        if kind is not None:
            opts = [t for t in opts if t.kind == kind] or opts
        return opts[k % len(opts)]

    def closest_kind(self, label: str, dims) -> str | None:
        """The kind of ``label``'s templates whose bounding box (length, width, height) is
        nearest to ``dims`` (a scenario entity drawn with the scene's own assets)."""
        opts = self.templates.get(label) or self.templates[A.VEHICLE_CLASS]
        want = np.asarray(dims, np.float64)[:3]
        best = min(opts, key=lambda t: (float(np.abs(np.asarray(t.dims, np.float64)[:3] - want).sum()),
                                        str(t.kind)))
        return best.kind

    def dims(self, label: str, kind: str | None = None) -> np.ndarray:
        return np.asarray(self.template(label, 0, kind).dims, np.float64)

    def actors_for(self, labels: list[str], kinds: list, dims: list | None = None) -> SimActors:
        """The episode's actors: the ego (role "ego", a car), then one per agent (vehicles,
        cyclists, pedestrians in `World.agents` order), then the scene's parked actors.
        ``dims``: per agent (length, width, height) its asset is scaled to (a scenario
        entity's bounding box), or None: the asset's own size."""
        acts, mats = [], []
        ego = self.template(A.VEHICLE_CLASS, 0, "car")
        acts.append(replace(ego, path="/World/Actors/Ego/Ego_000", role="ego"))
        mats.append(np.eye(4))
        for q, (label, kind) in enumerate(zip(labels, kinds)):
            t = self.template(label, q, kind)
            if dims is not None and dims[q] is not None:
                t = scaled_actor(t, dims[q])
            acts.append(replace(t, path=f"/World/Actors/Sim/{label.capitalize()}_{q:03d}",
                                role="moving"))
            mats.append(np.eye(4))
        for a, M in self.parked:
            acts.append(a)
            mats.append(M)
        return SimActors(acts, mats)
