"""`lsd3d-usd bench lidar`: time and accuracy of LiDAR sweeps of a scene (default: the README
sample generated with generate's defaults) along its default route.

Speed: seconds per waymo_top sweep (median over the sweeps; the surfels' kernel arrays made
once per loaded scene, timed apart), the rays and binned pairs, the memory a sweep adds, and
a 960×540 camera render of the same surfels from the LiDAR's pose in the same run.
Accuracy: ranges against ray casting on the proxy mesh (trimesh with Embree, an independent
implementation) per class, against the float64 per-ray reference (render.lidar.
cast_reference) on the surfels within 12 m of the sensor (≥ 20 k), and against the camera
depth of a pinhole camera at the LiDAR's pose where both see the same surface.
"""
from __future__ import annotations

import json
import resource
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from pxr import Usd

from lsd3d_usd import scene as S
from lsd3d_usd.config import generate_config
from lsd3d_usd.layout.usdio import read_layout
from lsd3d_usd.pipeline import RunOptions, generate
from lsd3d_usd.proxy.usdio import proxy_arrays
from lsd3d_usd.render.camera import Camera
from lsd3d_usd.render.lidar import cast_reference, cast_surfels
from lsd3d_usd.semantics import CLASS_ID
from lsd3d_usd.sensors.lidar import preset
from lsd3d_usd.views import labels as L
from lsd3d_usd.views.ego import frame_times, track_from_route
from lsd3d_usd.views.frame import composite, render_surfels
from lsd3d_usd.views.lidar_sweep import SurfelCache, sweep
from lsd3d_usd.layout.routes import default_route
from lsd3d_usd.views.stage_data import ActorFrame, SceneReader

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "layouts" / "hand_crossing.usda"
ACCURACY_CLASSES = ("road", "sidewalk", "building")


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(scene_dir, *, sweeps: int = 5, lidar: str = "waymo_top", log=print) -> dict:
    model = preset(lidar)
    sc = S.Scene.open(scene_dir)
    stage = Usd.Stage.Open(str(sc.root_layer_path))
    layout = read_layout(sc.layer_path("layout"))
    route, _ = default_route(layout, float(sweeps))
    track = track_from_route(layout, route, frame_times(10.0, max(float(sweeps), 0.2)))
    reader = SceneReader(stage, actors=False)
    instances = L.Instances.of(None)
    tcps = stage.GetTimeCodesPerSecond()
    cache = SurfelCache()
    t = time.perf_counter()
    field_ = reader.surfels()
    surfels = cache.get(field_)[0]
    setup_s = time.perf_counter() - t
    starts = np.linspace(0.0, max(track.times[-1] - model.sweep_seconds, 0.0), sweeps)
    t = time.perf_counter()     # the first sweep loads (or compiles) the kernels: not timed
    sweep(reader, model, track.at, float(starts[0]), tcps, instances, cache=cache)
    warm_s = time.perf_counter() - t
    rss0 = _rss_mb()
    times_, results = [], []
    for k, t0 in enumerate(starts):
        t = time.perf_counter()
        sw = sweep(reader, model, track.at, float(t0), tcps, instances, cache=cache, index=k)
        times_.append(time.perf_counter() - t)
        results.append(sw)
    extra_mb = _rss_mb() - rss0
    # camera render of the same surfels from the LiDAR's pose (looking forward)
    pose = track.at([starts[0]])[0] @ model.ego_from_sensor()
    cam_pose = pose @ np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    cam = Camera.from_fov(960, 540, 90.0, cam_pose, near=0.1, far=500.0)
    render_surfels(field_, cam)     # warm-up
    cam_times = []
    for _ in range(3):
        t = time.perf_counter()
        render_surfels(field_, cam)
        cam_times.append(time.perf_counter() - t)
    out = {"lidar": lidar, "rays": int(model.rings * model.columns),
           "surfels": int(field_.n), "s_per_sweep": statistics.median(times_),
           "s_per_sweep_all": [round(x, 3) for x in times_], "setup_s": round(setup_s, 3),
           "first_sweep_s": round(warm_s, 3),
           "stage_s": {k: round(statistics.median([r.stats.get(k, 0.0) for r in results]), 3)
                       for k in ("bin_s", "trace_s", "meshes_s")},
           "camera_s": statistics.median(cam_times), "memory_mb_beyond_scene": round(extra_mb, 1),
           "returns_per_sweep": int(np.median([len(s.range) for s in results]))}
    out["sweep_over_camera"] = out["s_per_sweep"] / out["camera_s"]
    # accuracy against the proxy mesh
    proxy = proxy_arrays(sc.layer_path("proxy"))
    errs = {c: [] for c in ACCURACY_CLASSES}
    same = {c: [] for c in ACCURACY_CLASSES}
    signed = {c: [] for c in ACCURACY_CLASSES}
    for k, t0 in enumerate(starts):
        sw = results[k]
        origins = sw.origin_world
        d = (sw.xyz_world - origins) / sw.range[:, None].astype(np.float64)
        pr, pcls = _proxy_along(proxy, origins, d, model.max_range)
        for c in ACCURACY_CLASSES:
            sel = (sw.class_id == CLASS_ID[c]) & np.isfinite(pr)
            dr = sw.range[sel] - pr[sel]
            errs[c].append(np.abs(dr))
            signed[c].append(dr)
            same[c].append(np.abs(dr[pcls[sel] == CLASS_ID[c]]))
    for c in ACCURACY_CLASSES:
        e = np.concatenate(errs[c])
        out[f"range_err_{c}_median_m"] = float(np.median(e)) if len(e) else None
        out[f"range_err_{c}_p95_m"] = float(np.percentile(e, 95)) if len(e) else None
        out[f"range_err_{c}_points"] = len(e)
        out[f"range_bias_{c}_median_m"] = float(np.median(np.concatenate(signed[c]))) if len(e) else None
        # where the proxy face the ray meets has the return's class: the same surface (the
        # rest are disk edges overhanging a class boundary, e.g. a kerb's lip)
        e = np.concatenate(same[c])
        out[f"range_err_{c}_same_class_median_m"] = float(np.median(e)) if len(e) else None
        out[f"range_err_{c}_same_class_p95_m"] = float(np.percentile(e, 95)) if len(e) else None
        out[f"range_err_{c}_same_class_points"] = len(e)
    out.update(_vs_reference(surfels, results[0], model))
    out.update(_vs_camera(reader, results[0], cam, field_))
    log(f"lidar {lidar}: {out['rays']} rays, {out['s_per_sweep']:.3f} s/sweep, camera 960x540 "
        f"{out['camera_s']:.3f} s ({out['sweep_over_camera']:.2f}x); road |dr| median "
        f"{out['range_err_road_median_m']}, p95 {out['range_err_road_p95_m']}; vs float64 "
        f"max {out['vs_reference_max_m']}")
    return out


def _proxy_along(proxy, origins, d, max_range):
    """(range to the proxy mesh along each ray (inf: none), its face class) with trimesh's
    Embree intersector."""
    import trimesh  # local import: the benchmark's independent reference only
    V, F, C = proxy
    mesh = trimesh.Trimesh(V, F, process=False)
    loc, ray, tri = mesh.ray.intersects_location(origins, d, multiple_hits=False)
    r = np.full(len(d), np.inf)
    r[ray] = np.einsum("ij,ij->i", loc - origins[ray], d[ray])
    cls = np.full(len(d), -1, np.int64)
    cls[ray] = C[tri]
    r[r > max_range] = np.inf
    return r, cls


def _vs_reference(surfels, sw, model, radius: float = 12.0, max_rays: int = 3000) -> dict:
    """Kernel against the float64 per-ray reference on the surfels near the sensor, for rays
    drawn at random from the sweep (so not in sweep order: the kernel's unordered path)."""
    o = sw.world_from_sensor[:3, 3]
    near = np.flatnonzero(np.linalg.norm(surfels.c - o, axis=1) < radius)
    sub = surfels.subset(near)
    rng = np.random.default_rng(0)
    d_all = model.directions()
    R, C = d_all.shape[:2]
    pick = rng.choice(R * C, size=min(max_rays, R * C), replace=False)
    dirs = (d_all.reshape(-1, 3)[pick] @ sw.world_from_sensor[:3, :3].T)[None]   # (1, n, 3)
    origins = np.tile(o, (dirs.shape[1], 1))
    t, _, _ = cast_surfels(sub, origins, dirs, min_range=model.min_range, max_range=radius)
    tr, _ = cast_reference(sub, origins, dirs, min_range=model.min_range, max_range=radius)
    both = np.isfinite(t) & np.isfinite(tr)
    return {"vs_reference_surfels": len(near), "vs_reference_rays": int(dirs.shape[1]),
            "vs_reference_max_m": float(np.max(np.abs(t[both] - tr[both]))) if both.any() else None,
            "vs_reference_same_returns": bool(np.array_equal(np.isfinite(t), np.isfinite(tr)))}


def _vs_camera(reader, sw, cam, field_) -> dict:
    """LiDAR ranges against the depth of a pinhole camera at the LiDAR's pose, where the
    camera pixel a return projects to shows the same class (the same surface)."""
    frame = composite(field_, ActorFrame.empty(), cam, None, None, L.Instances.of(None))
    p = sw.xyz_world
    pc = p @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
    ok = pc[:, 2] > cam.near
    uv = (pc[ok] @ cam.K.T)[:, :2] / pc[ok, 2:3]
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    inside = (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
    rows = np.flatnonzero(ok)[inside]
    u, v = u[inside], v[inside]
    z_cam = frame.labels.z[v, u]
    same = (frame.labels.class_id[v, u] == sw.class_id[rows]) & np.isfinite(z_cam)
    rel = np.abs(z_cam[same] - pc[rows[same], 2]) / pc[rows[same], 2]
    # pixels whose 3x3 neighbourhood spans < 1 % in depth: there a pixel's one depth stands
    # for the whole footprint the beam may land in (elsewhere, at grazing angles and edges,
    # a pixel's depth and a ray through another point of it differ by the gradient)
    z = frame.labels.z
    zp = np.pad(z, 1, mode="edge")
    win = np.stack([zp[1 + dy:1 + dy + z.shape[0], 1 + dx:1 + dx + z.shape[1]]
                    for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    with np.errstate(invalid="ignore"):
        spread = (win.max(0) - win.min(0)) / z
    smooth = spread[v, u][same] < 0.01
    return {"vs_camera_points": int(same.sum()),
            "vs_camera_rel_median": float(np.median(rel)) if len(rel) else None,
            "vs_camera_within_1pct": float(np.mean(rel <= 0.01)) if len(rel) else None,
            "vs_camera_smooth_points": int(smooth.sum()),
            "vs_camera_smooth_within_1pct": (float(np.mean(rel[smooth] <= 0.01))
                                             if smooth.any() else None)}


def main(json_path=None, *, scene=None, quick=False, sweeps=None, log=print) -> dict:
    sweeps = sweeps or (2 if quick else 5)
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(scene) if scene else Path(tmp) / "scene"
        if scene is None:
            kw = dict(steps=0, surfels=100_000) if quick else {}
            log(f"bench lidar: generating the README sample ({'quick' if quick else 'defaults'})")
            generate(generate_config(layout=SAMPLE, prompt="sunny afternoon in Madrid",
                                     actors=False, **kw),
                     RunOptions(out=target, progress=False, log=lambda *a: None))
        res = measure(target, sweeps=sweeps, log=log)
    if json_path:
        Path(json_path).write_text(json.dumps(res, indent=2))
        log(f"wrote {json_path}")
    return res
