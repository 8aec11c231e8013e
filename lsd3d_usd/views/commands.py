"""`lsd3d-usd render`: frames of a scene from a USD camera, or a sensor rig's clips. Its
settings are one configuration tree (views.options.RenderConfig): every flag has a key for
--config FILE.toml and --set KEY=VALUE."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lsd3d_usd import configtree as ct
from lsd3d_usd import safepaths
from lsd3d_usd.cliutil import check_output_folder
from lsd3d_usd import scene
from lsd3d_usd.errors import InputError
from lsd3d_usd.views.deferred import Deferrer
from lsd3d_usd.views.options import RIG_WIDTH, DeferredConfig, RenderConfig

GROUP_TITLES = {"rig": "sensor rig (instead of --camera)",
                "deferred": "deferred rendering (docs/render.md)"}


def check_deferred(d: DeferredConfig, explicit, prefix: str = "deferred.") -> None:
    """A deferred setting given without --deferred is refused (before anything is loaded)."""
    given = sorted(k for k in explicit if k.startswith(prefix) and k != prefix + "enabled")
    if given and not d.enabled:
        flag = ct.flag_names(DeferredConfig).get(given[0][len(prefix):], given[0])
        raise InputError(f"{flag} needs --deferred")


def make_deferrer(scene, d: DeferredConfig, log=None):
    """The Deferrer of the deferred settings (None without --deferred)."""
    if not d.enabled:
        return None
    # heavy (torch, the prior): only once deferral is asked for
    from lsd3d_usd.ggds.priors.scene import load_scene_prior
    sp = load_scene_prior(scene, d.prior, d.controlnet, device=d.device)
    if log is not None:
        log(f"deferred: prior {sp.spec} ({sp.source}), T {d.strength}, N {d.steps}")
        if sp.note():
            log(f"note: {sp.note()}")
    return Deferrer(sp, d.strength, d.steps, d.seed)


def _render(args) -> int:
    got = ct.command_config(args, RenderConfig, needs={"scene": "render: give the SCENE",
                                                         "output": "render: give -o OUT"})
    if got is None:
        return 0
    cfg, explicit = got
    check_output_folder(args.output, "-o", scene=args.scene)   # before the scene loads
    progress = not args.no_progress and sys.stderr.isatty()
    size = cfg.width_height()
    check_deferred(cfg.deferred, explicit)
    log = (lambda m: print(m, file=sys.stderr))
    # heavy (torch, numba): the renderer only once a render is asked for
    if cfg.rig.name:
        # local import: not loaded for --help
        from lsd3d_usd.views.ground_truth import parse_outputs
        from lsd3d_usd.views.rig import render_rig
        with safepaths.removed_on_error(args.output):   # a refused run leaves nothing
            res = render_rig(args.scene, args.output, cfg.rig,
                             width=size[0] if size else RIG_WIDTH,
                             use_env=cfg.env, exposure=cfg.exposure, tonemap_method=cfg.tonemap,
                             outputs=parse_outputs(cfg.outputs),
                             progress=progress,   # its notes (the default route) on stdout
                             deferrer=make_deferrer(args.scene, cfg.deferred, log))
        print(res.rig_layer)
        for name, fr in res.frames.items():
            print(f"{name}: {len(fr)} frames" + (f", {res.videos[name]}" if name in res.videos else ""))
            if res.deferred_frames is not None:
                print(f"{name}: {len(res.deferred_frames[name])} deferred frames"
                      + (f", {res.deferred_videos[name]}" if name in res.deferred_videos else ""))
        if res.sweeps:
            print(f"LIDAR_TOP: {len(res.sweeps)} sweeps under {Path(args.output) / 'LIDAR_TOP'}")
        if res.deferred is not None:
            d = res.deferred
            print(f"deferred: prior {d['prior']}, T {d['strength']}, N {d['steps']}, "
                  f"{d.get('s_per_frame', 0):.2f} s/frame")
        return 0
    if cfg.rig.lidar != "auto":
        raise InputError(f"--lidar {cfg.rig.lidar}: a LiDAR rides a rig; give --rig too "
                         "(a single-camera render has none)")
    if not cfg.camera:
        raise InputError("render: give --camera PRIM_PATH, or --rig (driving --route, --trajectory "
                         "or by default the longest drivable route)")
    # local import: not loaded for --help
    from lsd3d_usd.views.ground_truth import parse_outputs
    from lsd3d_usd.views.preview import parse_times, render_preview
    from lsd3d_usd.views.stage_data import camera_prim
    if cfg.deferred.enabled:   # a wrong camera fails before the prior is loaded
        camera_prim(scene.open_stage(args.scene, load=False), cfg.camera)
    with safepaths.removed_on_error(args.output):       # a refused run leaves nothing
        files = render_preview(args.scene, cfg.camera, args.output,
                               times=parse_times(cfg.frames, cfg.time), resolution=size,
                               fmt=cfg.format, exposure=cfg.exposure, tonemap_method=cfg.tonemap,
                               use_env=cfg.env, sh_degree=cfg.sh_degree, progress=progress,
                               outputs=parse_outputs(cfg.outputs),
                               deferrer=make_deferrer(args.scene, cfg.deferred, log))
    for f in files:
        print(f)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", help="render frames (PNG/EXR) of a scene from a camera prim, or a sensor rig's clips",
        description="Render the composed stage as seen from a UsdGeom.Camera: its surfels (every "
                    "Lsd3dSurfelField and official ParticleField3DGaussianSplat, the latter flattened "
                    "to surfels) rasterised, its actors at the frame's time (relit by the env) "
                    "z-buffered, and the DomeLight's latlong env map behind. Writes PNG (tone-mapped, "
                    "sRGB) or EXR (scene-linear RGBA + Z depth) frames named after the camera: "
                    "OUT/<camera>.png, or OUT/<camera>.<frame>.png with --frames. With --rig, a "
                    "multi-camera rig driven through the scene instead (same rendering). Every "
                    "setting has a key (--list-options) for --config FILE.toml and --set KEY=VALUE.")
    p.add_argument("scene", nargs="?", help="scene folder (holding scene.usda) or any USD file")
    p.add_argument("-o", "--output", help="output folder (created if missing)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    ct.add_tree_options(p, "render")
    ct.add_arguments(p, RenderConfig, titles=GROUP_TITLES)
    p.set_defaults(func=_render, compiles_kernels=True)
