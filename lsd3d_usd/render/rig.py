"""Multi-camera sensor rigs driven along a route or a pose list, rendered with actors.

The Waymo-like rig ``waymo5`` (see docs/actors.md for the facts it follows): five cameras,
front, front-left, front-right, side-left and side-right, ~50 deg horizontal field of view
each, yawed 0, +-45 and +-90 deg, mounted ~2 m above the ground on the roof. The ego frame
is x forward, y left, z up, origin on the ground at the centre of the rear axle.

`render_rig` writes OUT/rig.usda — a stage that sublayers the scene (by reference, nothing
copied) and adds /World/Cameras/Ego (translate + orient time samples) with one
UsdGeom.Camera per rig camera and a third-person ``Overview`` camera, plus the ego car as an
actor — then renders every camera at every frame from that stage: surfels (scene + surfel
actors) rasterised, mesh actors z-buffered and relit (actors.relight), composited per pixel
in depth order over the env background. Every frame is a pure function of (stage, time,
camera): nothing carries over between frames.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, look_at


@dataclass(frozen=True)
class RigCamera:
    name: str
    yaw_deg: float                  # about ego +Z, 0 = forward, + = left
    hfov_deg: float
    mount: tuple                    # (x, y, z) in the ego frame, metres
    size: tuple                     # native (width, height)
    pitch_deg: float = 0.0          # + = looking down


WAYMO5 = (
    RigCamera("Front", 0.0, 50.4, (1.55, 0.00, 2.10), (1920, 1280)),
    RigCamera("FrontLeft", 45.0, 50.4, (1.50, 0.45, 2.08), (1920, 1280)),
    RigCamera("FrontRight", -45.0, 50.4, (1.50, -0.45, 2.08), (1920, 1280)),
    RigCamera("SideLeft", 90.0, 50.4, (1.25, 0.85, 2.02), (1920, 886)),
    RigCamera("SideRight", -90.0, 50.4, (1.25, -0.85, 2.02), (1920, 886)),
)
RIGS = {"waymo5": WAYMO5}
OVERVIEW = RigCamera("Overview", 0.0, 60.0, (-14.0, 0.0, 8.0), (1920, 1080), pitch_deg=18.0)
EGO_PATH = "/World/Cameras/Ego"


def camera_in_ego(cam: RigCamera) -> np.ndarray:
    """Ego-from-camera pose (OpenCV camera axes) of a rig camera."""
    y, p = np.radians(cam.yaw_deg), np.radians(cam.pitch_deg)
    eye = np.asarray(cam.mount, np.float64)
    fwd = np.array([np.cos(y) * np.cos(p), np.sin(y) * np.cos(p), -np.sin(p)])
    return look_at(eye, eye + fwd, (0.0, 0.0, 1.0))


def rig_camera(cam: RigCamera, ego: np.ndarray, width: int) -> Camera:
    """The camera at render width ``width`` (height from its native aspect) for ego pose ``ego``."""
    w = int(width)
    h = max(1, int(round(w * cam.size[1] / cam.size[0])))
    return Camera.from_fov(w, h, cam.hfov_deg, ego @ camera_in_ego(cam), near=0.1, far=2000.0)


# ------------------------------------------------------------------ ego trajectories
@dataclass
class EgoTrack:
    """Ego poses at times (seconds): positions (n,3) and rotations (n,3,3) (world-from-ego)."""
    times: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray

    def matrices(self) -> np.ndarray:
        M = np.tile(np.eye(4), (len(self.times), 1, 1))
        M[:, :3, :3], M[:, :3, 3] = self.rotations, self.positions
        return M

    def yaws(self) -> np.ndarray:
        return np.unwrap(np.arctan2(self.rotations[:, 1, 0], self.rotations[:, 0, 0]))


def yaw_rotations(yaw) -> np.ndarray:
    y = np.asarray(yaw, np.float64).reshape(-1)
    c, s = np.cos(y), np.sin(y)
    R = np.zeros((len(y), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def frame_times(fps: float, seconds: float) -> np.ndarray:
    if not (fps > 0) or not (seconds > 0):
        raise InputError(f"rig: need --fps > 0 and --seconds > 0, got fps={fps}, seconds={seconds}")
    n = max(1, int(round(seconds * fps)))
    return np.arange(n) / float(fps)


def track_from_route(layout, lane_ids, times, speed: float | None = None, seed: int = 0) -> EgoTrack:
    """Drive ``lane_ids`` from the start of the first lane: at constant ``speed`` (m/s), or
    (default) with IDM on an empty road (accelerates towards the lanes' speed limits, yields at
    junctions, stops at the end of the route)."""
    from lsd3d_usd.actors import traffic as T
    times = np.asarray(times, np.float64)
    if speed is not None:
        pos, yaw = T.constant_speed_route(layout, lane_ids, speed, times)
        return EgoTrack(times, pos, yaw_rotations(yaw))
    fps = 1.0 / (times[1] - times[0]) if len(times) > 1 else 10.0
    sim = T.Simulation(layout, seed)
    sim.add_ego(sim.g.route_indices(list(lane_ids)), 4.8)
    run = sim.run(float(times[-1]), fps)
    return EgoTrack(times, run.position[0][:len(times)], yaw_rotations(run.yaw[0][:len(times)]))


def load_trajectory(path) -> EgoTrack:
    """poses.json: a list (or {"poses": [...]}) of {"t", "x", "y", "z", "yaw"} with yaw in
    degrees (counter-clockwise from +X, z defaults to 0) or {"t", "matrix"} with a 4x4
    world-from-ego matrix (row-major nested lists, translation in the last column)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputError(f"--trajectory {path}: no such file") from None
    except (OSError, ValueError) as e:
        raise InputError(f"--trajectory {path}: not valid JSON ({e})") from None
    poses = data.get("poses") if isinstance(data, dict) else data
    if not isinstance(poses, list) or not poses:
        raise InputError(f"--trajectory {path}: expected a non-empty list of poses (or {{\"poses\": [...]}})")
    T, P, R = [], [], []
    for k, q in enumerate(poses):
        where = f"--trajectory {path}: pose {k}"
        if not isinstance(q, dict) or "t" not in q:
            raise InputError(f"{where}: needs \"t\" and either x/y/yaw or matrix")
        try:
            t = float(q["t"])
            if "matrix" in q:
                M = np.asarray(q["matrix"], np.float64)
                if M.shape != (4, 4) or not np.all(np.isfinite(M)):
                    raise ValueError("matrix must be 4x4 and finite")
                U, _, Vt = np.linalg.svd(M[:3, :3])
                Rk = U @ Vt
                if np.linalg.det(Rk) < 0:
                    raise ValueError("matrix is mirrored")
                P.append(M[:3, 3])
                R.append(Rk)
            else:
                x, y, z = float(q["x"]), float(q["y"]), float(q.get("z", 0.0))
                P.append(np.array([x, y, z]))
                R.append(yaw_rotations(np.radians(float(q["yaw"])))[0])
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{where}: {e}") from None
        T.append(t)
    T = np.asarray(T)
    if not np.all(np.isfinite(T)) or np.any(np.diff(T) <= 0):
        raise InputError(f"--trajectory {path}: times \"t\" must be finite and strictly increasing")
    return EgoTrack(T, np.asarray(P), np.asarray(R))


def resample(track: EgoTrack, times) -> tuple[EgoTrack, int]:
    """The track at ``times`` (linear positions, slerped rotations); times outside the track
    hold its first/last pose. Returns (track, number of clamped times)."""
    from scipy.spatial.transform import Rotation, Slerp
    times = np.asarray(times, np.float64)
    tc = np.clip(times, track.times[0], track.times[-1])
    clamped = int(np.sum(tc != times))
    pos = np.stack([np.interp(tc, track.times, track.positions[:, k]) for k in range(3)], 1)
    if len(track.times) == 1:
        rot = np.repeat(track.rotations[:1], len(times), 0)
    else:
        rot = Slerp(track.times, Rotation.from_matrix(track.rotations))(tc).as_matrix()
    return EgoTrack(times, pos, rot), clamped


# ------------------------------------------------------------------ the rig stage
def author_rig(stage, rig, track: EgoTrack, tcps: float, ego_asset: str | None = None) -> list[str]:
    """/World/Cameras/Ego with its cameras (and /World/Actors/Ego/Ego_000 referencing
    ``ego_asset`` if given). Returns the camera prim paths."""
    from pxr import Gf, UsdGeom

    from lsd3d_usd.actors.usdio import ActorSpec, author_actor
    from lsd3d_usd.render.camera import to_usd
    from lsd3d_usd.scene import ACTORS_PATH, CAMERAS_PATH

    UsdGeom.Xform.Define(stage, CAMERAS_PATH)
    ego = UsdGeom.Xform.Define(stage, EGO_PATH)
    paths = []
    for cam in list(rig) + [OVERVIEW]:
        c = rig_camera(cam, np.eye(4), cam.size[0])   # ego at identity: local = ego-relative
        path = f"{EGO_PATH}/{cam.name}"
        to_usd(stage, path, c)
        paths.append(path)
    tr = ego.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
    ori = ego.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
    from scipy.spatial.transform import Rotation
    quats = Rotation.from_matrix(track.rotations).as_quat()  # xyzw
    for k, t in enumerate(track.times):
        code = round(float(t) * tcps, 6)
        tr.Set(Gf.Vec3d(*map(float, track.positions[k])), code)
        x, y, z, w = map(float, quats[k])
        ori.Set(Gf.Quatd(w, x, y, z), code)
    if ego_asset:
        UsdGeom.Xform.Define(stage, ACTORS_PATH)
        UsdGeom.Xform.Define(stage, f"{ACTORS_PATH}/Ego")
        author_actor(stage.GetRootLayer(), f"{ACTORS_PATH}/Ego",
                     ActorSpec("Ego_000", "ego", ego_asset, track.positions, track.yaws(),
                               times=track.times), tcps)
    return paths


# ------------------------------------------------------------------ frame composition
@dataclass
class StaticContent:
    """What does not change with time: scene surfels, env, lighting, shadow occluder."""
    surfels: object | None          # SurfelField (world) or None
    env: object | None              # preview.EnvMap or None
    lighting: object                # actors.relight.Lighting
    occluder: object                # actors.relight.Occluder
    actors: object                  # actors.usdio.ActorSet


def scene_surfels(stage):
    """Visible ParticleField prims outside /World/Actors and /World/Cameras, in world space."""
    from pxr import Usd, UsdGeom

    from lsd3d_usd.scene import ACTORS_PATH, CAMERAS_PATH
    from lsd3d_usd.splats.field import SurfelField
    from lsd3d_usd.splats.init import transform_surfels
    from lsd3d_usd.splats.usdio import read_surfels, surfel_prims

    t = Usd.TimeCode.Default()
    fields = []
    for prim in surfel_prims(stage):
        p = str(prim.GetPath())
        if p.startswith(ACTORS_PATH + "/") or p.startswith(CAMERAS_PATH + "/"):
            continue
        if UsdGeom.Imageable(prim).ComputeVisibility(t) == UsdGeom.Tokens.invisible:
            continue
        f = read_surfels(prim, t)
        if f.n:
            M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), np.float64).T
            fields.append(transform_surfels(f, M))
    if not fields:
        return None
    try:
        return SurfelField.concat(fields)
    except ValueError:
        from dataclasses import replace
        return SurfelField.concat([replace(f, semantic_ids=None, semantic_classes=()) for f in fields])


def load_static(stage, use_env: bool = True) -> StaticContent:
    from lsd3d_usd.actors.relight import lighting_from_stage, proxy_occluder
    from lsd3d_usd.render.preview import read_env
    from lsd3d_usd.actors.usdio import ActorSet
    return StaticContent(scene_surfels(stage), read_env(stage) if use_env else None,
                         lighting_from_stage(stage), proxy_occluder(stage), ActorSet(stage))


@dataclass
class ActorFrame:
    """Actors placed and lit at one time: one merged mesh and the surfel actors."""
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray              # (F,3) lit linear colour per face
    surfels: object | None


def actors_at(static: StaticContent, time_code: float) -> ActorFrame:
    """Actor geometry in world space at ``time_code``, relit (pure function of the time)."""
    from lsd3d_usd.actors.relight import actor_sample_points
    from lsd3d_usd.splats.field import SH_C0, SurfelField
    from lsd3d_usd.splats.init import transform_surfels

    vs, fs, cs, surf = [], [], [], []
    n = 0
    light = static.lighting
    Ms = static.actors.transforms(time_code)
    vis = static.actors.visible(time_code)
    for a, M, shown in zip(static.actors.actors, Ms, vis):
        if not shown:
            continue
        V = static.occluder.visibility(actor_sample_points(M, a.dims), light.sun_dir)
        for m in a.meshes:
            v = m.vertices @ M[:3, :3].T + M[:3, 3]
            tri = v[m.faces]
            nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            vs.append(v)
            fs.append(m.faces + n)
            cs.append(m.colors * light.factor(nrm, V))
            n += len(v)
        if a.surfels is not None:
            f = transform_surfels(a.surfels, M)
            k = light.factor(f.normals().astype(np.float64), V)
            rgb = np.maximum(0.5 + SH_C0 * f.sh[:, 0, :], 0.0) * k
            sh = f.sh * k[:, None, :]
            sh[:, 0, :] = (rgb - 0.5) / SH_C0
            surf.append(SurfelField(f.positions, f.orientations, f.scales, f.opacities, sh,
                                    f.semantic_ids, f.semantic_classes))
    if vs:
        V3, F3, C3 = np.concatenate(vs), np.concatenate(fs), np.concatenate(cs)
    else:
        V3, F3, C3 = np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32)
    S = None
    if surf:
        try:
            S = SurfelField.concat(surf)
        except ValueError:
            from dataclasses import replace
            S = SurfelField.concat([replace(f, semantic_ids=None, semantic_classes=()) for f in surf])
    return ActorFrame(V3, F3, C3.astype(np.float32), S)


def composite(surfels, actor: ActorFrame, camera: Camera, env=None) -> dict:
    """Render surfels (scene + surfel actors) and mesh actors for ``camera`` and composite
    them per pixel in depth order over the env background.

    Mesh actors are opaque: where an actor is nearer than the surfels' depth (the median
    depth, or the expected depth where the surfels' alpha stays below 0.5) the actor wins;
    elsewhere the surfels' premultiplied colour goes over the actor (or over the env).
    Returns numpy rgb (H,W,3), alpha (H,W), depth (H,W; inf where empty), actor_mask (H,W)."""
    import torch

    from lsd3d_usd.render.gbuffer import render_gbuffer
    from lsd3d_usd.render.preview import env_background
    from lsd3d_usd.splats.field import SurfelField

    H, W = camera.height, camera.width
    fields = [f for f in (surfels, actor.surfels) if f is not None and f.n]
    if fields:
        try:
            field = SurfelField.concat(fields)
        except ValueError:
            from dataclasses import replace
            field = SurfelField.concat([replace(f, semantic_ids=None, semantic_classes=()) for f in fields])
        from lsd3d_usd.render.raster_types import RasterSettings
        from lsd3d_usd.render.rasterize import rasterize
        with torch.no_grad():
            out = rasterize(torch.from_numpy(np.ascontiguousarray(field.positions)),
                            torch.from_numpy(np.ascontiguousarray(field.orientations)),
                            torch.from_numpy(np.ascontiguousarray(field.scales)),
                            torch.from_numpy(np.ascontiguousarray(field.opacities)),
                            torch.from_numpy(np.ascontiguousarray(field.sh)),
                            torch.from_numpy(camera.viewmat.astype(np.float32)),
                            torch.from_numpy(camera.K.astype(np.float32)), W, H,
                            settings=RasterSettings.for_camera(camera))
        s_rgb = out.rgb.numpy().astype(np.float32)
        s_a = out.alpha.numpy().astype(np.float32)
        dmed = out.depth_median.numpy()
        dexp = out.depth_expected.numpy()
        s_depth = np.where(dmed > 0, dmed, np.where(s_a > 1e-4, dexp, np.inf)).astype(np.float32)
    else:
        s_rgb = np.zeros((H, W, 3), np.float32)
        s_a = np.zeros((H, W), np.float32)
        s_depth = np.full((H, W), np.inf, np.float32)
    bg = env_background(env, camera)
    under = np.zeros((H, W, 3), np.float32) if bg is None else bg.astype(np.float32)
    a_mask = np.zeros((H, W), bool)
    a_depth = np.full((H, W), np.inf, np.float32)
    if len(actor.faces):
        g = render_gbuffer(actor.vertices, actor.faces, camera)
        a_mask = g.face_index >= 0
        a_depth = np.where(a_mask, g.depth, np.inf).astype(np.float32)
        a_rgb = np.zeros((H, W, 3), np.float32)
        a_rgb[a_mask] = actor.colors[g.face_index[a_mask]]
        under = np.where(a_mask[..., None], a_rgb, under)
    front = a_mask & (a_depth < s_depth)
    rgb = np.where(front[..., None], under, s_rgb + (1.0 - s_a)[..., None] * under)
    alpha = np.where(front | a_mask, 1.0, s_a).astype(np.float32)
    depth = np.minimum(a_depth, s_depth)
    return {"rgb": rgb.astype(np.float32), "alpha": alpha, "depth": depth, "actor_mask": front}


# ------------------------------------------------------------------ the command's core
@dataclass
class RigResult:
    rig_layer: Path
    frames: dict            # camera name -> list of PNG paths
    videos: dict            # camera name -> mp4 path
    notes: list


def _rel(target: Path, folder: Path) -> str:
    from lsd3d_usd.actors.assets import relative_asset_path
    return relative_asset_path(target, folder)


def build_rig_stage(scene_path, out_dir, rig_name: str = "waymo5", route=None, trajectory=None,
                    fps: float = 10.0, seconds: float = 8.0, speed: float | None = None,
                    seed: int = 0, ego_body: bool = True):
    """Write OUT/rig.usda (sublayering the scene) and return (stage, camera paths, track,
    tcps, notes)."""
    from pxr import Usd

    from lsd3d_usd import scene as S
    if rig_name not in RIGS:
        raise InputError(f"--rig {rig_name!r}: known rigs: {', '.join(RIGS)}")
    if (route is None) == (trajectory is None):
        raise InputError("--rig needs exactly one of --route LANE_IDS or --trajectory poses.json")
    sp = Path(scene_path)
    root_file = sp / S.ROOT_FILE if sp.is_dir() else sp
    scene_stage = S.open_stage(root_file, load=False)
    root_layer = scene_stage.GetRootLayer()
    tcps = float(root_layer.timeCodesPerSecond) if root_layer.HasTimeCodesPerSecond() else 24.0
    times = frame_times(fps, seconds)
    notes = []
    if route is not None:
        from lsd3d_usd.layout.usdio import layout_from_stage
        if not scene_stage.GetPrimAtPath(S.LAYOUT_PATH):
            raise InputError(f"{scene_path}: --route needs the scene's layout ({S.LAYOUT_PATH})")
        layout = layout_from_stage(scene_stage, str(scene_path))
        ids = [r.strip() for r in (route.split(",") if isinstance(route, str) else route) if r.strip()]
        track = track_from_route(layout, ids, times, speed, seed)
    else:
        track, clamped = resample(load_trajectory(trajectory), times)
        if clamped:
            notes.append(f"{clamped} frame(s) lie outside the trajectory's time range: "
                         "the ego holds its first/last pose there")
    out = Path(out_dir).absolute()
    out.mkdir(parents=True, exist_ok=True)
    stage = S.new_stage()
    ego_asset = None
    if ego_body:
        from lsd3d_usd.actors.assets import default_library_dir
        lib = default_library_dir()
        car = (lib / "car.usda") if lib else (root_file.parent / "assets" / "car.usda")
        if car.is_file():
            ego_asset = _rel(car, out)
        else:
            notes.append("no car asset found: the ego has no body in the overview")
    paths = author_rig(stage, RIGS[rig_name], track, tcps, ego_asset)
    # A detached copy gets the sublayer: on the in-memory stage the relative path could not
    # resolve (and would only produce warnings).
    from pxr import Sdf
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(stage.GetRootLayer())
    layer.subLayerPaths = [_rel(root_file.absolute(), out)]
    layer.timeCodesPerSecond = tcps
    layer.framesPerSecond = tcps
    layer.startTimeCode = 0.0
    layer.endTimeCode = float(times[-1] * tcps)
    rig_file = out / "rig.usda"
    S.save_layer(layer, rig_file, S.provenance("rig", {"rig": rig_name, "fps": fps, "seconds": seconds,
                                                       "route": ",".join(route) if isinstance(route, list)
                                                       else route, "trajectory": trajectory}, seed=seed))
    composed = Usd.Stage.Open(str(rig_file))
    return composed, paths, track, tcps, notes


def render_rig(scene_path, out_dir, rig_name: str = "waymo5", route=None, trajectory=None,
               fps: float = 10.0, seconds: float = 8.0, width: int = 480, speed=None, seed: int = 0,
               overview: bool = True, video: bool = True, use_env: bool = True, exposure: float = 0.0,
               tonemap_method: str = "aces", progress: bool = True, log=print) -> RigResult:
    """Render every rig camera (and the overview) at every frame; PNGs under OUT/<camera>/,
    an MP4 per camera when the encoder is available."""
    from tqdm import tqdm

    from lsd3d_usd.render.camera import from_usd
    from lsd3d_usd.render.preview import srgb_encode, tonemap, write_frame
    from lsd3d_usd.render.video import encoder_available, write_mp4

    if int(width) < 8:
        raise InputError(f"--resolution: rig frames need a width >= 8, got {width}")
    stage, paths, track, tcps, notes = build_rig_stage(scene_path, out_dir, rig_name, route, trajectory,
                                                       fps, seconds, speed, seed)
    if not overview:
        paths = [p for p in paths if not p.endswith("/" + OVERVIEW.name)]
    static = load_static(stage, use_env)
    if static.surfels is None:
        notes.append("the scene has no surfels: frames show actors over the env only")
    out = Path(out_dir).absolute()
    specs = {c.name: c for c in list(RIGS[rig_name]) + [OVERVIEW]}
    frames = {p.rsplit("/", 1)[-1]: [] for p in paths}
    images = {k: [] for k in frames}
    total = len(track.times) * len(paths)
    bar = tqdm(total=total, desc="render rig", unit="frame", disable=not progress)
    for k, t in enumerate(track.times):
        code = round(float(t) * tcps, 6)
        actor = actors_at(static, code)
        for path in paths:
            name = path.rsplit("/", 1)[-1]
            spec = specs[name]
            h = max(1, int(round(width * spec.size[1] / spec.size[0])))
            cam = from_usd(stage.GetPrimAtPath(path), code, int(width), h)
            frame = composite(static.surfels, actor, cam, static.env)
            f = write_frame(out / name / f"{name}.{k:04d}.png", frame, "png", exposure, tonemap_method)
            frames[name].append(f)
            if video:
                images[name].append(np.round(srgb_encode(tonemap(frame["rgb"], exposure, tonemap_method))
                                             * 255).astype(np.uint8))
            bar.update(1)
    bar.close()
    videos = {}
    if video:
        ok, why = encoder_available()
        if ok:
            for name, ims in images.items():
                videos[name] = write_mp4(out / f"{name}.mp4", ims, fps)
        else:
            notes.append(f"no MP4 written: {why}; PNG frames only")
    for n in notes:
        log(f"note: {n}")
    return RigResult(out / "rig.usda", frames, videos, notes)


# ------------------------------------------------------------------ CLI hooks (render command)
def add_rig_arguments(parser) -> None:
    """The flags `lsd3d-usd render` gains for rigs."""
    g = parser.add_argument_group("sensor rig (instead of --camera)")
    g.add_argument("--rig", choices=sorted(RIGS), help="render a multi-camera rig driven along --route or "
                   "--trajectory: every camera's frames under OUT/<camera>/, an MP4 per camera, a "
                   "third-person Overview, and OUT/rig.usda (the scene + the animated rig)")
    g.add_argument("--route", help="comma-separated lane ids the ego drives, each a successor of the one "
                   "before (IDM speed on an empty road unless --speed)")
    g.add_argument("--trajectory", help="poses.json: a list of {t, x, y, z, yaw (degrees)} or "
                   "{t, matrix (4x4 world-from-ego)}; see docs/actors.md")
    g.add_argument("--fps", type=float, default=10.0, help="rig frames per second (default 10)")
    g.add_argument("--seconds", type=float, default=8.0, help="rig clip length in seconds (default 8)")
    g.add_argument("--speed", type=float, help="constant ego speed along --route in m/s (default: IDM)")
    g.add_argument("--no-video", action="store_true", help="PNG frames only, no MP4")
    g.add_argument("--no-overview", action="store_true", help="skip the third-person overview camera")


def run_rig_from_args(args) -> int:
    import sys
    width = 480
    if getattr(args, "resolution", None):
        import re
        m = re.fullmatch(r"\s*(\d+)\s*(?:[xX]\s*\d+)?\s*", args.resolution)
        if not m:
            raise InputError(f"--resolution {args.resolution!r}: use WIDTH (rig heights follow each camera)")
        width = int(m.group(1))
    res = render_rig(args.scene, args.output, args.rig, args.route, args.trajectory, args.fps, args.seconds,
                     width, args.speed, overview=not args.no_overview, video=not args.no_video,
                     use_env=not args.no_env, exposure=args.exposure, tonemap_method=args.tonemap,
                     progress=sys.stderr.isatty())
    print(res.rig_layer)
    for name, fr in res.frames.items():
        print(f"{name}: {len(fr)} frames" + (f", {res.videos[name]}" if name in res.videos else ""))
    return 0
