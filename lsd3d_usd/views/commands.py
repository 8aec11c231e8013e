"""`lsd3d-usd render`: frames of a scene from a USD camera, or a sensor rig's clips."""
from __future__ import annotations

import argparse
import re
import sys

from lsd3d_usd.cliutil import parse_size
from lsd3d_usd.render.camera import DEFAULT_WIDTH as SINGLE_WIDTH
from lsd3d_usd.views.rig import DEFAULT_STREAM_RADIUS, DEFAULT_WIDTH as RIG_WIDTH
from lsd3d_usd.views.rigs import RIGS


def _parse_times(args):
    import numpy as np

    from lsd3d_usd.errors import InputError

    if args.frames is None:
        return [args.time]
    m = re.fullmatch(r"\s*(-?[\d.]+)\s*:\s*(-?[\d.]+)\s*(?::\s*([\d.]+))?\s*", args.frames)
    if not m:
        raise InputError(f"--frames {args.frames!r}: use START:END or START:END:STEP (inclusive)")
    a, b = float(m.group(1)), float(m.group(2))
    step = float(m.group(3)) if m.group(3) else 1.0
    if step <= 0 or b < a:
        raise InputError(f"--frames {args.frames!r}: need END >= START and STEP > 0")
    n = int(np.floor((b - a) / step + 1e-9)) + 1
    return [a + i * step for i in range(n)]


def deferred_flags_given(args) -> list[str]:
    return [f for f, v in (("--deferred-strength", args.deferred_strength),
                           ("--deferred-steps", args.deferred_steps),
                           ("--deferred-prior", args.deferred_prior),
                           ("--deferred-controlnet", args.deferred_controlnet),
                           ("--deferred-device", args.deferred_device),
                           ("--deferred-seed", args.deferred_seed)) if v is not None]


def check_deferred_args(args) -> None:
    """Flag checks before anything is loaded or written."""
    from lsd3d_usd.errors import InputError
    from lsd3d_usd.ggds.priors.registry import check_device, check_prior_name
    from lsd3d_usd.views.deferred import check_steps, check_strength
    given = deferred_flags_given(args)
    if given and not args.deferred:
        raise InputError(f"{given[0]} needs --deferred")
    if args.deferred_strength is not None:
        check_strength(args.deferred_strength)
    if args.deferred_steps is not None:
        check_steps(args.deferred_steps)
    if args.deferred_prior is not None:
        check_prior_name(args.deferred_prior)
    if args.deferred_device is not None:
        check_device(args.deferred_device)


def make_deferrer(scene, args, log=None):
    """The Deferrer of the deferred flags (None without --deferred)."""
    if not args.deferred:
        return None
    from lsd3d_usd.ggds.priors.scene import load_scene_prior
    from lsd3d_usd.views.deferred import DEFAULT_STEPS, DEFAULT_STRENGTH, Deferrer
    sp = load_scene_prior(scene, args.deferred_prior, args.deferred_controlnet, args.deferred_device)
    if log is not None:
        log(f"deferred: prior {sp.spec} ({sp.source}), T {args.deferred_strength or DEFAULT_STRENGTH}"
            f", N {args.deferred_steps or DEFAULT_STEPS}")
        if sp.note():
            log(f"note: {sp.note()}")
    return Deferrer(sp, DEFAULT_STRENGTH if args.deferred_strength is None else args.deferred_strength,
                    DEFAULT_STEPS if args.deferred_steps is None else args.deferred_steps,
                    args.deferred_seed)


def add_deferred_arguments(p: argparse.ArgumentParser, what: str) -> None:
    from lsd3d_usd.views.deferred import DEFAULT_STEPS, DEFAULT_STRENGTH
    g = p.add_argument_group("deferred rendering (docs/render.md)")
    g.add_argument("--deferred", action="store_true",
                   help=f"also pass {what} through the scene's image prior from a low noise level "
                        "(the paper's deferred rendering), conditioned on the proxy G-buffer")
    g.add_argument("--deferred-strength", type=float, metavar="T",
                   help=f"noise level T in (0, 1] (default {DEFAULT_STRENGTH}, chosen by measurement)")
    g.add_argument("--deferred-steps", type=int, metavar="N",
                   help=f"denoising steps N of a diffusion prior (default {DEFAULT_STEPS})")
    g.add_argument("--deferred-prior", metavar="PRIOR",
                   help="prior to use instead of the one the scene's GGDS run recorded: "
                        "'procedural', 'diffusers:DIR' or another registered prior")
    g.add_argument("--deferred-controlnet", metavar="DIR",
                   help="local depth ControlNet directory for a diffusers prior (overrides the "
                        "recorded one)")
    g.add_argument("--deferred-device", metavar="DEV", help="torch device of the prior (cpu, cuda[:N])")
    g.add_argument("--deferred-seed", type=int, metavar="S",
                   help="seed handed to the prior for every frame (default: the scene's seed; "
                        "the built-in priors are deterministic and do not use it)")


def _render(args) -> int:
    from lsd3d_usd.errors import InputError

    progress = not args.no_progress and sys.stderr.isatty()
    size = parse_size(args.resolution, width_only=True)
    check_deferred_args(args)
    if args.rig:
        from lsd3d_usd.views.rig import render_rig
        log = (lambda m: print(m, file=sys.stderr))
        res = render_rig(args.scene, args.output, args.rig, args.route, args.trajectory, args.fps,
                         args.seconds, size[0] if size else RIG_WIDTH, args.speed,
                         overview=not args.no_overview, video=not args.no_video,
                         use_env=not args.no_env, exposure=args.exposure,
                         tonemap_method=args.tonemap, progress=progress,
                         stream_radius=args.stream_radius,
                         deferrer=make_deferrer(args.scene, args, log))
        print(res.rig_layer)
        for name, fr in res.frames.items():
            print(f"{name}: {len(fr)} frames" + (f", {res.videos[name]}" if name in res.videos else ""))
            if res.deferred_frames is not None:
                print(f"{name}: {len(res.deferred_frames[name])} deferred frames"
                      + (f", {res.deferred_videos[name]}" if name in res.deferred_videos else ""))
        if res.deferred is not None:
            d = res.deferred
            print(f"deferred: prior {d['prior']}, T {d['strength']}, N {d['steps']}, "
                  f"{d.get('s_per_frame', 0):.2f} s/frame")
        return 0
    if not args.camera:
        raise InputError("render: give --camera PRIM_PATH, or --rig (driving --route, --trajectory "
                         "or by default the longest drivable route)")
    from lsd3d_usd.views.preview import render_preview
    from lsd3d_usd.views.stage_data import camera_prim
    if args.deferred:   # a wrong camera fails before the prior is loaded
        from lsd3d_usd import scene
        camera_prim(scene.open_stage(args.scene, load=False), args.camera)
    files = render_preview(args.scene, args.camera, args.output, times=_parse_times(args),
                           resolution=size, fmt=args.format, exposure=args.exposure,
                           tonemap_method=args.tonemap, use_env=not args.no_env,
                           sh_degree=args.sh_degree, progress=progress,
                           deferrer=make_deferrer(args.scene, args,
                                                  lambda m: print(m, file=sys.stderr)))
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
                    "multi-camera rig driven through the scene instead (same rendering).")
    p.add_argument("scene", help="scene folder (holding scene.usda) or any USD file")
    p.add_argument("--camera", help="camera prim path, e.g. /World/Cameras/Front (required unless --rig)")
    p.add_argument("-o", "--output", required=True, help="output folder (created if missing)")
    p.add_argument("--resolution", help="WIDTHxHEIGHT, or WIDTH with the height from the camera's "
                                        f"aperture aspect (default {SINGLE_WIDTH} wide); with --rig "
                                        f"only the width counts (default {RIG_WIDTH}), heights follow "
                                        "each rig camera")
    p.add_argument("--format", choices=("png", "exr"), default="png",
                   help="png: 8-bit sRGB after exposure and tone map; exr: float linear RGBA + Z")
    p.add_argument("--time", type=float, help="time code of a single frame (default: the stage's "
                                              "earliest time)")
    p.add_argument("--frames", help="render a range of time codes START:END[:STEP] (inclusive)")
    p.add_argument("--exposure", type=float, default=0.0, help="exposure in stops applied before the "
                                                              "tone map (and to EXR pixels); default 0")
    p.add_argument("--tonemap", choices=("aces", "reinhard", "clamp"), default="aces",
                   help="PNG tone map (default aces: a filmic curve)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3),
                   help="use only SH up to this degree (default: all the surfels have)")
    p.add_argument("--no-env", action="store_true", help="black background instead of the env map")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    g = p.add_argument_group("sensor rig (instead of --camera)")
    g.add_argument("--rig", choices=sorted(RIGS), help="render a multi-camera rig driven along --route or "
                   "--trajectory: every camera's frames under OUT/<camera>/, an MP4 per camera, a "
                   "third-person Overview, and OUT/rig.usda (the scene + the animated rig)")
    g.add_argument("--route", help="comma-separated lane ids the ego drives, each a successor of the one "
                   "before (IDM speed on an empty road unless --speed); `lsd3d-usd layout lanes SCENE` "
                   "lists them. Default (without --trajectory): the longest drivable successor path, "
                   "printed so it can be reused")
    g.add_argument("--trajectory", help="poses.json: a list of {t, x, y, z, yaw (degrees)} or "
                   "{t, matrix (4x4 world-from-ego)}; see docs/actors.md")
    g.add_argument("--fps", type=float, default=10.0, help="rig frames per second (default 10)")
    g.add_argument("--seconds", type=float, default=8.0, help="rig clip length in seconds (default 8)")
    g.add_argument("--speed", type=float, help="constant ego speed along --route in m/s (default: IDM)")
    g.add_argument("--stream-radius", type=float, default=DEFAULT_STREAM_RADIUS, metavar="M",
                   help="load only the scene chunks within M metres of the cameras and unload "
                        f"those left behind (default {DEFAULT_STREAM_RADIUS:g}; 0 = load the "
                        "whole scene)")
    g.add_argument("--no-video", action="store_true", help="PNG frames only, no MP4")
    g.add_argument("--no-overview", action="store_true", help="skip the third-person overview camera")
    add_deferred_arguments(p, "every frame")
    p.set_defaults(func=_render, compiles_kernels=True)
