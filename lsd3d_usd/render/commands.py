"""`lsd3d-usd render`: preview frames of a scene from a USD camera."""
from __future__ import annotations

import argparse
import re
import sys

from lsd3d_usd.cliutil import parse_size


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


def _render(args) -> int:
    from lsd3d_usd.errors import InputError
    from lsd3d_usd.render.preview import render_preview

    if args.rig:
        from lsd3d_usd.render.rig import run_rig_from_args
        return run_rig_from_args(args)
    if not args.camera:
        raise InputError("render: give --camera PRIM_PATH (or --rig with --route/--trajectory)")

    files = render_preview(args.scene, args.camera, args.output, times=_parse_times(args),
                           resolution=parse_size(args.resolution, width_only=True), fmt=args.format,
                           exposure=args.exposure, tonemap_method=args.tonemap, use_env=not args.no_env,
                           sh_degree=args.sh_degree, progress=sys.stderr.isatty())
    for f in files:
        print(f)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", help="render preview frames (PNG/EXR) of a scene from a camera prim",
        description="Rasterise the surfels of the composed stage (every Lsd3dSurfelField and official "
                    "ParticleField3DGaussianSplat, the latter flattened to surfels) as seen from a "
                    "UsdGeom.Camera, with the DomeLight's latlong env map composited behind, and write "
                    "PNG (tone-mapped, sRGB) or EXR (scene-linear RGBA + Z depth) frames named after the "
                    "camera: OUT/<camera>.png, or OUT/<camera>.<frame>.png with --frames.")
    p.add_argument("scene", help="scene folder (holding scene.usda) or any USD file")
    p.add_argument("--camera", help="camera prim path, e.g. /World/Cameras/Front (required unless --rig)")
    p.add_argument("-o", "--output", required=True, help="output folder (created if missing)")
    p.add_argument("--resolution", help="WIDTHxHEIGHT, or WIDTH with the height from the camera's "
                                        "aperture aspect (default 960 wide)")
    p.add_argument("--format", choices=("png", "exr"), default="png",
                   help="png: 8-bit sRGB after exposure and tone map; exr: float linear RGBA + Z")
    p.add_argument("--time", type=float, help="time code of a single frame (default: the default time)")
    p.add_argument("--frames", help="render a range of time codes START:END[:STEP] (inclusive)")
    p.add_argument("--exposure", type=float, default=0.0, help="exposure in stops applied before the "
                                                              "tone map (and to EXR pixels); default 0")
    p.add_argument("--tonemap", choices=("aces", "reinhard", "clamp"), default="aces",
                   help="PNG tone map (default aces: a filmic curve)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3),
                   help="use only SH up to this degree (default: all the surfels have)")
    p.add_argument("--no-env", action="store_true", help="black background instead of the env map")
    from lsd3d_usd.render.rig import add_rig_arguments
    add_rig_arguments(p)
    p.set_defaults(func=_render)
