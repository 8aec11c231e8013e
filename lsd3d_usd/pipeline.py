"""`generate`: layout → proxy → env → surfels → GGDS, each step writing its own layer.

Steps whose inputs did not change are reused (proxy chunks by content hash, the env EXR by
parameter hash, the surfel layer by the hash of its inputs), so re-running `generate` on a
scene only does the work that is new. GGDS always writes a new run layer (or, with
--resume, continues the newest unfinished one); layers/surfels.usdc is never rewritten by it.
"""
from __future__ import annotations

import hashlib
import json
import math
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError

DEFAULT_DENSITY = 80.0         # initial surfels per m² of view-weighted proxy surface (docs/ggds.md)
MAX_SURFELS = 4_000_000


@dataclass
class GenerateOptions:
    out: Path
    layout: Path | None = None
    seed: int = 0
    extent: tuple[float, float] = (200.0, 200.0)   # used when no layout is given
    style: str = "urban"
    prompt: str | None = None
    when: str | None = None
    lat: float | None = None
    lon: float | None = None
    weather: str | None = None
    season: str | None = None
    env_resolution: tuple[int, int] = (2048, 1024)
    surfels: int | None = None                     # None: DEFAULT_DENSITY × proxy area
    steps: int = 250
    prior: str = "procedural"
    resolution: tuple[int, int] = (480, 270)
    views: int = 128
    checkpoint_every: int = 50
    perceptual: bool = True
    perceptual_weight: float | None = None         # None: the prior's default (see below)
    lpips: Path | None = None                      # torchvision AlexNet/VGG16 weights: LPIPS term
    lpips_lin: Path | None = None                  # LPIPS linear weights (None: installed lpips pkg)
    parked: int = 12                               # actors parked along the curbs
    moving: int = 8                                # actors driven by the IDM traffic model
    actor_seconds: float = 8.0
    actor_fps: float = 10.0
    resume: bool = False
    force: bool = False
    progress: bool = True
    log: object = print
    extra: dict = field(default_factory=dict)


def _hash(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def _file_hash(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


# ------------------------------------------------------------------ checks before writing
def check_options(o: GenerateOptions):
    w, h = o.resolution
    if w <= 0 or h <= 0:
        raise InputError(f"--resolution {w}x{h}: width and height must be positive")
    if o.steps < 0:
        raise InputError(f"--steps {o.steps}: must be >= 0")
    if o.surfels is not None and not 0 < o.surfels <= MAX_SURFELS:
        raise InputError(f"--surfels {o.surfels}: must be in 1..{MAX_SURFELS:,}")
    if o.views <= 0:
        raise InputError(f"--views {o.views}: must be positive")
    if o.checkpoint_every <= 0:
        raise InputError(f"--checkpoint-every {o.checkpoint_every}: must be positive")
    if o.resume and o.force:
        raise InputError("--resume and --force exclude each other")
    if o.parked < 0 or o.moving < 0:
        raise InputError(f"--parked {o.parked} / --moving {o.moving}: counts must be >= 0")
    if o.lpips is not None:
        for flag, f in (("--lpips", o.lpips), ("--lpips-lin", o.lpips_lin)):
            if f is not None and not Path(f).is_file():
                raise InputError(f"{flag} {f}: no such file (LPIPS loads local weights only; "
                                 "nothing is downloaded)")
        if not o.perceptual or perceptual_weight(o) <= 0:
            raise InputError(f"--lpips {o.lpips}: the perceptual weight is 0 (--no-perceptual, or "
                             "the procedural prior's default), so LPIPS would not be used; "
                             "pass --perceptual-weight W")
        from lsd3d_usd.ggds.lpips import LPIPSLoss
        # keys, shapes, lin weights checked before anything is written; the loaded loss is
        # kept for the GGDS step so the weights are read once
        o.extra["lpips_loss"] = LPIPSLoss.from_files(o.lpips, o.lpips_lin, linear=True)  # renders are linear
    elif o.lpips_lin is not None:
        raise InputError("--lpips-lin needs --lpips BACKBONE.pth")


def make_prior(spec: str):
    """'procedural' or 'diffusers:DIR' → a Prior (the diffusers prior loads local files only)."""
    if spec == "procedural":
        from lsd3d_usd.ggds.procedural_prior import ProceduralPrior
        return ProceduralPrior()
    if spec.startswith("diffusers:"):
        d = spec.split(":", 1)[1]
        if not d:
            raise InputError("--prior diffusers:DIR needs a local model directory")
        if not Path(d).is_dir():
            raise InputError(f"--prior diffusers:{d}: no such directory (the diffusion prior "
                             "loads local weights only; nothing is downloaded)")
        from lsd3d_usd.ggds.diffusers_prior import DiffusersPrior
        return DiffusersPrior.from_pretrained(d)
    raise InputError(f"--prior {spec!r}: use 'procedural' or 'diffusers:DIR'")


def perceptual_weight(o: GenerateOptions) -> float:
    """The EfficientNet-Lite0 perceptual term's weight. The procedural prior's targets are exact
    per pixel, and with them the perceptual term only added chroma speckle (crossing sample,
    150 steps: 23.88 dB with it, 24.43 dB without; chroma noise 0.057 vs 0.034); a diffusion
    prior's looser targets are where it earns its place."""
    if o.perceptual_weight is not None:
        return float(o.perceptual_weight)
    return 0.0 if o.prior == "procedural" else 0.05


def read_layout_for(o: GenerateOptions):
    from lsd3d_usd.layout import generator
    from lsd3d_usd.layout.usdio import read_layout
    if o.layout is not None:
        if not Path(o.layout).is_file():
            raise InputError(f"--layout {o.layout}: no such file")
        layout = read_layout(o.layout)
        source = Path(o.layout)
    else:
        layout = generator.generate(o.seed, o.extent, o.style)
        source = None
    if not any(ln.lane_type in ("driving", "bus") for ln in layout.lanes):
        where = o.layout or "generated layout"
        raise InputError(f"{where}: the layout has no driving lanes (GGDS places its cameras "
                         "along lanes, and the proxy needs roads)")
    return layout, source


def prepare_scene(o: GenerateOptions, layout_hash: str) -> S.Scene:
    out = Path(o.out)
    if (out / S.ROOT_FILE).is_file():
        sc = S.Scene.open(out)
        stored = S.read_provenance(S.Sdf.Layer.FindOrOpen(str(sc.root_layer_path))).get("layoutHash")
        if stored and stored != layout_hash and not o.force:
            raise InputError(f"{out}: holds a different scene (another layout); use --force to "
                             "rebuild it here or choose another output folder")
        return sc
    if o.resume:
        raise InputError(f"{out}: no scene to resume (no {S.ROOT_FILE})")
    if out.exists() and any(out.iterdir()) and not o.force:
        raise InputError(f"{out}: exists and is not empty (and not a scene); use --force or "
                         "choose another output folder")
    return S.Scene.create(out, seed=o.seed, exist_ok=True)


# ------------------------------------------------------------------------- the steps
def _layout_step(sc: S.Scene, layout, source: Path | None, o: GenerateOptions) -> None:
    """The layout layer is the input exactly as given (bytes copied when it is usda)."""
    from lsd3d_usd.layout.usdio import write_layout
    dst = sc.layer_path("layout")
    if source is not None and source.suffix.lower() == ".usda":
        data = source.read_bytes()
        if not dst.is_file() or dst.read_bytes() != data:
            S.atomic_write_bytes(dst, data)
    else:
        write_layout(layout, dst, provenance=S.provenance(
            "layout", {"source": str(source) if source else "generator",
                       "extent": list(o.extent), "style": o.style}, seed=o.seed))
    sc.add_layer("layout")


def _proxy_step(sc: S.Scene, layout, o: GenerateOptions) -> dict:
    from lsd3d_usd.proxy.usdio import build_proxy_layer
    rep = build_proxy_layer(layout, sc.layer_path("proxy"), progress=o.progress)
    sc.add_layer("proxy")
    return {"built": len(rep.built), "skipped": len(rep.skipped), "seconds": round(rep.seconds, 2),
            "triangles": rep.triangles}


def env_params(o: GenerateOptions):
    from lsd3d_usd.env import build_params
    params, unknown = build_params(o.prompt, when=o.when, lat=o.lat, lon=o.lon, weather=o.weather,
                                   season=o.season, seed=o.seed)
    if o.prompt:
        params.extras["prompt"] = o.prompt
    if unknown:
        o.log(f"warning: prompt words not understood (ignored): {', '.join(unknown)}")
    return params


def _env_step(sc: S.Scene, o: GenerateOptions):
    from pxr import UsdLux
    from lsd3d_usd.env import write_env, write_env_layer
    from lsd3d_usd.ggds.envbridge import scene_light
    params = env_params(o)
    w, h = o.env_resolution
    exr = write_env(params, sc.root / S.TEXTURES_DIR, w, h)
    light = scene_light(params, exr)
    stage = S.new_stage()
    write_env_layer(stage, [params], texture_dir=sc.root / S.TEXTURES_DIR, width=w, height=h,
                    layer_dir=sc.root / S.LAYERS_DIR)
    # The surfels are authored in display-scaled radiance: record the scale on the dome as a
    # standard exposure, so USD renderers and our preview show the sky at the same level.
    env = stage.GetPrimAtPath(S.ENV_PATH)
    vset = env.GetVariantSets().GetVariantSet("environment")
    with vset.GetVariantEditContext():
        UsdLux.DomeLight_1(env.GetChild("Dome")).GetExposureAttr().Set(float(math.log2(light.exposure)))
        env.CreateAttribute("lsd3d:env:displayExposure", S.Sdf.ValueTypeNames.Float,
                            custom=True).Set(float(light.exposure))
    sc.write_layer("env", stage, S.provenance("env", params.to_dict(), seed=o.seed,
                                               exposure=light.exposure))
    return params, light


def _proxy_arrays(sc: S.Scene):
    """All proxy meshes concatenated (chunks and classes in sorted order): V, F, face class ids."""
    from lsd3d_usd.proxy.usdio import read_proxy
    from lsd3d_usd.semantics import CLASS_ID
    vs, fs, ids, base = [], [], [], 0
    for key, meshes in sorted(read_proxy(sc.layer_path("proxy")).items()):
        for name in sorted(meshes):
            cm = meshes[name]
            if cm.n_faces == 0:
                continue
            vs.append(cm.vertices)
            fs.append(cm.faces.astype(np.int64) + base)
            ids.append(np.full(cm.n_faces, CLASS_ID.get(cm.cls, -1), np.int32))
            base += len(cm.vertices)
    if not fs:
        raise InputError(f"{sc.layer_path('proxy')}: the proxy has no geometry")
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(ids)


def _surfel_step(sc: S.Scene, proxy, light, layout, o: GenerateOptions) -> tuple:
    from lsd3d_usd.ggds.conditioning import shadow_map
    from lsd3d_usd.semantics import CLASS_COLORS, CLASSES
    from lsd3d_usd.splats.field import rgb_to_sh_dc
    from lsd3d_usd.splats.importance import face_weights
    from lsd3d_usd.splats.init import mesh_to_surfels
    from lsd3d_usd.splats.usdio import read_surfel_file, write_surfel_file
    V, F, ids = proxy
    face_area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    area = float(face_area.sum())
    weights = face_weights(V, F, layout)
    weighted_area = float((face_area * weights).sum())
    count = o.surfels or int(min(MAX_SURFELS, max(1000, DEFAULT_DENSITY * weighted_area)))
    inputs = _hash(_file_hash(sc.layer_path("proxy")), count, o.seed, light.exposure,
                   light.sun_direction.tolist(), "surfels-v2")
    path = sc.layer_path("surfels")
    faces_path = sc.root / "ggds" / "surfel_faces.npy"
    if path.is_file() and faces_path.is_file():
        prov = S.read_provenance(S.Sdf.Layer.FindOrOpen(str(path)))
        if prov.get("inputsHash") == inputs:
            sc.add_layer("surfels")
            return read_surfel_file(str(path)), np.load(faces_path), {"reused": True, "count": count}
    t0 = time.perf_counter()
    field, face = mesh_to_surfels(V, F, ids, count=count, seed=o.seed, sh_degree=1,
                                  semantic_classes=CLASSES, return_face_index=True,
                                  face_weights=weights)
    # Initial colours: class albedo lit by the sky SH and the (shadowed) sun.
    shadow = shadow_map(V, F, light.sun_direction)
    vis = shadow.visibility(field.positions.astype(np.float64) + 0.05 * field.normals()) \
        if shadow is not None else None
    albedo = CLASS_COLORS[np.clip(field.semantic_ids, 0, None)]
    rgb = np.clip(albedo * light.irradiance(field.normals(), vis), 0.0, 4.0)
    field.sh[:, 0, :] = rgb_to_sh_dc(rgb)
    dt = time.perf_counter() - t0
    write_surfel_file(str(path), field, provenance=S.provenance(
        "surfels", {"count": count, "proxyArea_m2": round(area, 1), "density": DEFAULT_DENSITY,
                    "viewWeightedArea_m2": round(weighted_area, 1)},
        seed=o.seed, timings={"init_s": round(dt, 2)}, inputsHash=inputs))
    faces_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = faces_path.with_suffix(".tmp.npy")
    np.save(tmp, face.astype(np.int32))
    tmp.replace(faces_path)
    sc.add_layer("surfels")
    return read_surfel_file(str(path)), face, {"reused": False, "count": count, "init_s": round(dt, 2)}


def _actors_step(sc: S.Scene, layout, o: GenerateOptions) -> dict:
    """Parked and moving actors as references to the scene's own procedural vehicle assets
    (written once into assets/, so the scene folder is self-contained)."""
    from lsd3d_usd.actors import assets as A
    from lsd3d_usd.actors.compose import add_actors
    folder = sc.root / S.ASSETS_DIR
    missing = [k for k in A.LIBRARY_KINDS if not (folder / f"{k}.usda").is_file()]
    if missing:
        A.write_library(folder, missing)
    res = add_actors(sc, layout, parked=o.parked, moving=o.moving, seed=o.seed,
                     seconds=o.actor_seconds, fps=o.actor_fps, assets_dir=folder)
    for note in res.notes:
        o.log(f"actors: {note}")
    return {"parked": len(res.parked), "moving": len(res.moving_kinds), "seconds": res.seconds}


# ------------------------------------------------------------------------- GGDS
def _latest_unfinished(sc: S.Scene) -> str | None:
    runs = sorted((sc.root / "ggds").glob("ggds_*/state.pt"), reverse=True)
    return runs[0].parent.name if runs else None


def _write_run(sc: S.Scene, run_name: str, run, views_json, prior, params, metrics=None,
               final=False) -> None:
    import torch
    from lsd3d_usd.splats.usdio import write_surfels
    stage = S.new_stage()
    write_surfels(stage, S.SURFELS_PATH, run.field(), over=True,
                  attributes=("positions", "orientations", "scales", "opacities", "sh"))
    prov = S.provenance("ggds", {**run.cfg.to_dict(), **prior.describe()}, seed=run.cfg.seed,
                        timings={"optimise_s": round(run.seconds, 2),
                                 "s_per_step": round(run.seconds / max(run.step_index, 1), 4)},
                        stepsDone=run.step_index, complete=bool(final),
                        prompt=params.extras.get("prompt", ""),
                        trainViews=json.dumps(views_json), metrics=metrics)
    sc.write_layer(f"{run_name}.usdc", stage, prov)
    state_dir = sc.root / "ggds" / run_name
    state_dir.mkdir(parents=True, exist_ok=True)
    tmp = state_dir / "state.tmp.pt"
    torch.save(run.state_dict(), tmp)
    tmp.replace(state_dir / "state.pt")


def _plots(run, out_dir: Path, before_after: list) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    h = run.history
    if h:
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.2))
        steps = [r["step"] for r in h]
        for key in ("loss", "l1", "disparity", "normal"):
            ys = np.array([r.get(key, np.nan) for r in h])
            k = max(1, len(ys) // 20)
            ax[0].plot(steps, np.convolve(ys, np.ones(k) / k, mode="same"), label=key)
        ax[0].set_yscale("log"); ax[0].set_xlabel("step"); ax[0].legend(); ax[0].set_title("GGDS losses")
        ax[1].plot(steps, [r["psnr_target"] for r in h], ".", ms=3)
        ax[1].set_xlabel("step"); ax[1].set_ylabel("PSNR render vs prior target (dB)")
        fig.tight_layout(); fig.savefig(out_dir / "loss.png", dpi=100); plt.close(fig)
    if before_after:
        rows = len(before_after)
        fig, ax = plt.subplots(rows, 3, figsize=(12, 2.4 * rows), squeeze=False)
        for i, (b, a, t) in enumerate(before_after):
            for j, (img, title) in enumerate(((b, "initial surfels"), (a, "after GGDS"), (t, "prior target"))):
                ax[i, j].imshow(_srgb(img)); ax[i, j].set_axis_off()
                if i == 0:
                    ax[i, j].set_title(title)
        fig.tight_layout(); fig.savefig(out_dir / "before_after.png", dpi=100); plt.close(fig)


def _srgb(x) -> np.ndarray:
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _ggds_step(sc, layout, proxy, field, face, light, params, o: GenerateOptions) -> dict:
    import torch
    from lsd3d_usd.ggds.cameras import sample_views
    from lsd3d_usd.ggds.conditioning import shadow_map
    from lsd3d_usd.ggds.run import GGDSConfig, GGDSRun
    prior = make_prior(o.prior)
    state = None
    run_name = None
    if o.resume:
        run_name = _latest_unfinished(sc)
        if run_name is None:
            raise InputError(f"{sc.root}: no GGDS checkpoint to resume")
        state = torch.load(sc.root / "ggds" / run_name / "state.pt", weights_only=False)
        cfg = GGDSConfig.from_dict(state["config"])
        cfg.steps = max(cfg.steps, o.steps) if o.steps else cfg.steps
    else:
        w, h = o.resolution
        cfg = GGDSConfig(steps=o.steps, width=w, height=h, n_views=o.views, seed=o.seed,
                         checkpoint_every=o.checkpoint_every,
                         w_perceptual=perceptual_weight(o) if o.perceptual else 0.0)
        run_name = sc.new_run_name()
    views = sample_views(layout, cfg.n_views, cfg.width, cfg.height, seed=cfg.seed,
                         novel_frac=cfg.novel_frac, fov_deg=cfg.fov_deg)
    held_out = sample_views(layout, 8, cfg.width, cfg.height, seed=cfg.seed + 7919,
                            novel_frac=0.5, fov_deg=cfg.fov_deg)
    perceptual = None
    if cfg.w_perceptual > 0 and o.lpips is not None:
        perceptual = o.extra.get("lpips_loss")
        if perceptual is None:  # options not checked by check_options
            from lsd3d_usd.ggds.lpips import LPIPSLoss
            perceptual = LPIPSLoss.from_files(o.lpips, o.lpips_lin, linear=True)
        o.log(f"ggds: perceptual term = LPIPS ({perceptual.net}, {o.lpips})")
    elif cfg.w_perceptual > 0:
        from lsd3d_usd.ggds.perceptual import EffNetPerceptualLoss
        perceptual = EffNetPerceptualLoss()
    shadow = shadow_map(proxy[0], proxy[1], light.sun_direction)
    run = GGDSRun(field, proxy, views, prior, light.prior_env, cfg, background_fn=light.background,
                  shadow=shadow, face_index=face, perceptual=perceptual)
    if state is not None:
        run.load_state_dict(state)
    elif cfg.world_init and run.world_init():
        o.log("ggds: surfel colours initialised from the world-space prior")
    views_json = [v.to_json() for v in views]
    out_dir = sc.root / "ggds" / run_name
    out_dir.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():  # "before" = the initial surfels as authored in surfels.usdc
        init = GGDSRun(field, proxy, [], prior, light.prior_env, cfg) if state is None else None
        before = [init.render(v.camera, background=light.background(v.camera))["rgb"]
                  for v in held_out[:2]] if init is not None else []
    interrupted = False
    bar = None
    if o.progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.steps, initial=run.step_index, desc="GGDS", unit="step")
    try:
        while run.step_index < cfg.steps:
            rec = run.step()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr_target']:.1f}")
            if run.step_index % cfg.checkpoint_every == 0 and run.step_index < cfg.steps:
                _write_run(sc, run_name, run, views_json, prior, params)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if bar is not None:
            bar.close()
    if interrupted:
        # Ctrl-C leaves a valid scene: the run so far as a layer, resumable with --resume.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        _write_run(sc, run_name, run, views_json, prior, params)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        raise KeyboardInterrupt
    metrics = run.evaluate(held_out)
    _write_run(sc, run_name, run, views_json, prior, params, metrics=metrics, final=True)
    with torch.no_grad():
        after = []
        for i, v in enumerate(held_out[:2]):
            bg = light.background(v.camera)
            x = run.render(v.camera, background=bg)["rgb"]
            from lsd3d_usd.ggds.conditioning import view_gbuffer
            gb = view_gbuffer(v.camera, proxy[0], proxy[1], proxy[2], shadow)
            tgt = prior.target(x.clamp(0, None), gb, light.prior_env, 1.0, seed=i)
            after.append((before[i] if before else x, x, tgt))
    _plots(run, out_dir, after)
    summary = {"run": run_name, "steps": run.step_index, "seconds": round(run.seconds, 1),
               "s_per_step": round(run.seconds / max(run.step_index, 1), 3),
               "surfels": int(field.n), **metrics}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


# --------------------------------------------------------------------------- driver
def generate(o: GenerateOptions) -> dict:
    """Run the whole pipeline; returns a summary dict (also written to ggds/<run>/)."""
    check_options(o)
    t0 = time.perf_counter()
    layout, source = read_layout_for(o)
    from lsd3d_usd.proxy.usdio import layout_hash
    lhash = layout_hash(layout)
    if o.steps > 0 or o.resume:
        make_prior_check = o.prior  # fail on a bad prior before writing anything
        if make_prior_check != "procedural":
            make_prior(make_prior_check)
    sc = prepare_scene(o, lhash)
    root = S.Sdf.Layer.FindOrOpen(str(sc.root_layer_path))
    if S.read_provenance(root).get("layoutHash") != lhash:
        data = dict(root.customLayerData)
        lsd = dict(data.get("lsd3d", {}))
        lsd["layoutHash"] = lhash
        data["lsd3d"] = lsd
        root.customLayerData = data
        S.save_layer(root, sc.root_layer_path)
    timings = {}
    o.log(f"scene: {sc.root}")
    t = time.perf_counter(); _layout_step(sc, layout, source, o); timings["layout_s"] = time.perf_counter() - t
    o.log(f"layout: {sum(layout.counts().values())} features ({len(layout.lanes)} lanes)")
    t = time.perf_counter(); prep = _proxy_step(sc, layout, o); timings["proxy_s"] = time.perf_counter() - t
    o.log(f"proxy: {prep['built']} chunk(s) built, {prep['skipped']} reused")
    t = time.perf_counter(); params, light = _env_step(sc, o); timings["env_s"] = time.perf_counter() - t
    o.log(f"env: {params.resolved().variant_name()} (display exposure {light.exposure:.4g})")
    proxy = _proxy_arrays(sc)
    t = time.perf_counter(); field, face, sinfo = _surfel_step(sc, proxy, light, layout, o)
    timings["surfels_s"] = time.perf_counter() - t
    o.log(f"surfels: {field.n:,} ({'reused' if sinfo['reused'] else 'initialised'})")
    summary = {"scene": str(sc.root), "proxy": prep, "surfels": sinfo}
    if o.parked or o.moving:
        t = time.perf_counter(); summary["actors"] = _actors_step(sc, layout, o)
        timings["actors_s"] = time.perf_counter() - t
        o.log(f"actors: {summary['actors']['parked']} parked, {summary['actors']['moving']} moving")
    if o.steps > 0 or o.resume:
        summary["ggds"] = _ggds_step(sc, layout, proxy, field, face, light, params, o)
        g = summary["ggds"]
        o.log(f"ggds: {g['run']}: {g['steps']} steps, {g['s_per_step']} s/step, held-out PSNR "
              f"{g['psnr_novel']:.2f} dB, depth err {100 * g['depth_rel_err']:.2f} %, normal err "
              f"{g['normal_err_deg']:.2f} deg, off-surface {100 * g['off_surface_frac']:.2f} %")
    timings["total_s"] = time.perf_counter() - t0
    summary["timings"] = {k: round(v, 2) for k, v in timings.items()}
    return summary
