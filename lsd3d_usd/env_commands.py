"""`lsd3d-usd env`: write an environment EXR (and optionally its DomeLight layer).

Above the pipeline (not in env/): a variant added to a scene's own env layer is authored as
`generate` authors its variant (pipeline.author_scene_variant: the display exposure and the
ground beyond the scene in the colour of the scene's prior), which needs the scene's prior."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from lsd3d_usd import configtree as ct
from lsd3d_usd.cliutil import check_output_path
from lsd3d_usd.env.config import SKY_FLAGS, SkyConfig
from lsd3d_usd.errors import InputError


def _env(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.env.exr import write_env
    from lsd3d_usd.env.mapping import check_resolution
    # local import: not loaded for --help
    from lsd3d_usd.env.prompt import build_params, unknown_words

    cfg, _ = ct.from_command_line(args, SkyConfig, ct.flag_names(SkyConfig) | SKY_FLAGS)
    e = cfg.env
    w, h = e.resolution
    check_resolution(w, h)
    out = check_output_path(args.output, "-o", suffixes=(".exr",), what="environment map")
    sc = None
    if args.usd:
        check_output_path(args.usd, "--usd", suffixes=(".usda", ".usdc", ".usd"), what="env layer")
        sc = _scene_of_env_layer(args.usd)
        if sc is not None and args.replace:     # refused before anything is written
            raise InputError(f"--replace {args.usd}: that is the scene's own env layer, which "
                             "generate makes (its GGDS runs rest on it); add a variant without "
                             "--replace, or generate the scene with another --prompt")
    fields = dict(seed=cfg.seed, turbidity=cfg.turbidity, cloud_coverage=cfg.cloud_coverage,
                  fog_density=cfg.fog_density, north_deg=cfg.north, color_space=cfg.color_space)
    params, unknown = build_params(e.prompt, when=e.when, lat=e.lat, lon=e.lon,
                                   weather=e.weather, season=e.season,
                                   time_of_day=cfg.time_of_day, **fields)
    if unknown:
        print(f"lsd3d-usd: warning: prompt words not understood (ignored): {unknown_words(unknown)}",
              file=sys.stderr)
    if sc is not None:
        made = _made_variant(sc)
        if made is not None and (args.variant or params.variant_name()) == made:
            raise InputError(f"--usd {args.usd}: the variant {made!r} is the one generate made "
                             "for the scene (its GGDS runs rest on it); name the new one with "
                             "--variant")
    r = params.resolved()
    t0 = time.perf_counter()
    timings: dict = {}
    path = write_env(params, out, w, h, force=args.force, timings=timings)
    cached = "cached" in timings
    where = r.place or f"{r.latitude:.2f}, {r.longitude:.2f}"
    print(f"{'reused' if cached else 'wrote'} {path}  ({w}x{h}, {r.weather}, {r.season}, "
          f"{r.when.isoformat()} at {where}, {r.color_space})"
          + ("" if cached else f" in {time.perf_counter() - t0:.2f} s"))
    if args.usd:
        # local import: not loaded for --help
        from lsd3d_usd.env.usdlayer import write_env_layer
        item = (args.variant, path) if args.variant else path
        if sc is not None:      # the name checked against generate's above
            item = (args.variant or params.variant_name(), path)
        extras = None if sc is None else _scene_variant(sc, params, path)
        layer = write_env_layer(args.usd, [item], append=not args.replace, variant_extras=extras)
        print(f"wrote {layer}  (/World/Env, DomeLight_1 poleAxis=Z"
              + (", the scene's display exposure and far field)" if sc is not None else ")"))
    return 0


def _scene_of_env_layer(layer):
    """The scene whose env layer ``layer`` is (SCENE/layers/env.usda), or None; found from
    the path as given and from its real path (symlinked folders either way)."""
    from lsd3d_usd import scene as S
    real = Path(layer).resolve()
    for p in dict.fromkeys((Path(layer).absolute(), real)):
        root = p.parent.parent
        if p.parent.name == S.LAYERS_DIR and (root / S.ROOT_FILE).is_file():
            sc = S.Scene.open(root)
            if sc.layer_path("env").resolve() == real:
                return sc
    return None


def _made_variant(sc):
    """The name of the environment variant generate made for the scene, or None."""
    from lsd3d_usd.conditioning.scene import made_environment
    made = made_environment(sc)
    return None if made is None else made.variant_name()


def _scene_variant(sc, params, exr):
    """The variant_extras that author a new variant of the scene's env layer as generate
    authors its own: exposure from this environment's light, the far field at the proxy's
    ground level in the colour of the scene's recorded prior."""
    from lsd3d_usd.conditioning.light import scene_light
    from lsd3d_usd.ggds.priors.scene import recorded_prior_config
    from lsd3d_usd.pipeline import author_scene_variant
    prior_cfg, seed, *_ = recorded_prior_config(sc)
    light = scene_light(params, exr)
    return lambda stage, _name, _exr: author_scene_variant(stage, sc, prior_cfg, seed, params,
                                                           light)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "env", help="write an environment map (sky EXR) and optionally its DomeLight layer",
        description="Render an analytic sky (Preetham clear sky, CIE overcast, procedural clouds, "
                    "twilight and night with the moon) as a 2:1 latlong half-float EXR, top row = "
                    "zenith, in scene-linear kcd/m^2. Controls come from --prompt (e.g. \"rainy autumn "
                    "evening in Seattle\"; the words understood are listed in docs/env.md) and the "
                    "explicit flags, which override the prompt. The EXR is reused when its parameters "
                    "are unchanged.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ct.add_arguments(p, SkyConfig, flags=SKY_FLAGS)
    p.add_argument("-o", "--output", required=True, help="output .exr path")
    p.add_argument("--usd", help="also write (or add a variant to) this env layer, e.g. "
                                 "scene/layers/env.usda: /World/Env with a DomeLight_1 (a "
                                 "scene's own env layer: the variant also gets the scene's "
                                 "display exposure and ground beyond the scene, as generate's)")
    p.add_argument("--variant", help="variant name in the env layer (default: weather_time_season)")
    p.add_argument("--replace", action="store_true",
                   help="rewrite the --usd layer instead of adding a variant to it")
    p.add_argument("--force", action="store_true", help="re-render even if the EXR is up to date")
    p.set_defaults(func=_env, compiles_kernels=True)
