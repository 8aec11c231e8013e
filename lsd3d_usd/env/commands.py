"""`lsd3d-usd env`: write an environment EXR (and optionally its DomeLight layer)."""
from __future__ import annotations

import argparse
import sys
import time

from lsd3d_usd.cliutil import check_output_path, size_type

WEATHERS = ("clear", "partly-cloudy", "overcast", "fog", "rain", "snow")
SEASONS = ("spring", "summer", "autumn", "winter")


def _env(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.env.exr import write_env
    from lsd3d_usd.env.mapping import check_resolution
    # local import: not loaded for --help
    from lsd3d_usd.env.prompt import build_params, unknown_words

    w, h = args.resolution
    check_resolution(w, h)
    out = check_output_path(args.output, "-o", suffixes=(".exr",), what="environment map")
    if args.usd:
        check_output_path(args.usd, "--usd", suffixes=(".usda", ".usdc", ".usd"), what="env layer")
    fields = dict(seed=args.seed, turbidity=args.turbidity, cloud_coverage=args.cloud_coverage,
                  fog_density=args.fog_density, north_deg=args.north, color_space=args.color_space)
    params, unknown = build_params(args.prompt, when=args.when, lat=args.lat, lon=args.lon,
                                   weather=args.weather, season=args.season,
                                   time_of_day=args.time_of_day, **fields)
    if unknown:
        print(f"lsd3d-usd: warning: prompt words not understood (ignored): {unknown_words(unknown)}",
              file=sys.stderr)
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
        layer = write_env_layer(args.usd, [item], append=not args.replace)
        print(f"wrote {layer}  (/World/Env, DomeLight_1 poleAxis=Z)")
    return 0


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
    p.add_argument("--prompt", help="free text: weather, season, month, time of day, city")
    p.add_argument("--when", help="local date-time, ISO 8601, e.g. 2026-06-21T13:00+02:00 (without an "
                                  "offset: the place's standard time)")
    p.add_argument("--time-of-day", dest="time_of_day",
                   help="a time word solved for the place and date (dawn, sunrise, morning, noon, "
                        "afternoon, evening, golden hour, sunset, dusk, night, ...)")
    p.add_argument("--lat", type=float, help="latitude in degrees (north positive); with --lon")
    p.add_argument("--lon", type=float, help="longitude in degrees (east positive); with --lat")
    p.add_argument("--weather", choices=WEATHERS, help="weather (default: from the prompt, else clear)")
    p.add_argument("--season", choices=SEASONS,
                   help="season: sets the date (hemisphere-aware) unless --when is given, and the "
                        "ground / vegetation hints")
    p.add_argument("--resolution", type=size_type("--resolution"), default=(2048, 1024),
                   help="WIDTHxHEIGHT, 2:1")
    p.add_argument("--seed", type=int, default=0, help="seed of the cloud noise")
    p.add_argument("--turbidity", type=float, help="atmospheric turbidity 1.7..10 (default per weather)")
    p.add_argument("--cloud-coverage", dest="cloud_coverage", type=float,
                   help="fraction of the sky covered by clouds, 0..1 (default per weather)")
    p.add_argument("--fog-density", dest="fog_density", type=float,
                   help="fog extinction in 1/m (visibility = 3.912 / density; default per weather)")
    p.add_argument("--north", type=float, default=0.0,
                   help="angle (deg, counter-clockwise about +Z) from +Y to north in the stage")
    p.add_argument("--color-space", dest="color_space", choices=("lin_rec709", "acescg"),
                   default="lin_rec709", help="colour space of the EXR (tagged in the file and on the "
                                              "USD texture)")
    p.add_argument("-o", "--output", required=True, help="output .exr path")
    p.add_argument("--usd", help="also write (or add a variant to) this env layer, e.g. "
                                 "scene/layers/env.usda: /World/Env with a DomeLight_1")
    p.add_argument("--variant", help="variant name in the env layer (default: weather_time_season)")
    p.add_argument("--replace", action="store_true",
                   help="rewrite the --usd layer instead of adding a variant to it")
    p.add_argument("--force", action="store_true", help="re-render even if the EXR is up to date")
    p.set_defaults(func=_env, compiles_kernels=True)
