"""`lsd3d-usd layout ...`: generate a procedural layout, import OpenDRIVE, show a summary."""
from __future__ import annotations

import sys
import time


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "layout", help="map layouts: generate procedurally, import OpenDRIVE, inspect",
        description="Map layouts: the USD layer under /World/Layout (lanes, road lines, road edges, "
                    "crosswalks, buildings, vegetation, parking). See docs/layout.md.")
    sub = p.add_subparsers(dest="layout_command", metavar="SUBCOMMAND")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    g = sub.add_parser(
        "generate", help="generate a procedural road network",
        description="Generate a road network of parameterised blocks (straights, curves, 4-way and T "
                    "junctions, roundabouts) with city blocks, buildings, trees and parking, chunk by "
                    "chunk (100 m). Deterministic per seed; the block description is stored in the "
                    "layer so it can be replayed.")
    g.add_argument("--seed", type=int, default=0, help="master seed (default 0)")
    g.add_argument("--extent", default="400x400",
                   help="WIDTHxHEIGHT in metres, from the origin (default 400x400)")
    g.add_argument("--style", default="urban", choices=("urban", "suburban", "highway"),
                   help="road/building style (default urban)")
    g.add_argument("-o", "--output", required=True, help="output layer (.usda or .usdc)")
    g.set_defaults(func=_generate)

    i = sub.add_parser(
        "import", help="import an ASAM OpenDRIVE (.xodr) map",
        description="Import an ASAM OpenDRIVE 1.4-1.8 map: reference lines (line, arc, spiral, poly3, "
                    "paramPoly3), lane offsets and sections, lane types, road marks, elevation, "
                    "junctions. Curves are sampled within 2 cm of the exact geometry. Roads that "
                    "cannot be read are skipped with a warning naming them.")
    i.add_argument("input", help="OpenDRIVE file (.xodr)")
    i.add_argument("-o", "--output", required=True, help="output layer (.usda or .usdc)")
    i.add_argument("--tolerance", type=float, default=0.02,
                   help="max distance of the sampled polylines from the exact curves, m (default 0.02)")
    i.add_argument("--strict", action="store_true",
                   help="fail on the first bad road instead of skipping it with a warning")
    i.set_defaults(func=_import)

    s = sub.add_parser("info", help="summarise a layout layer",
                       description="Print feature counts, bounds and the lane graph size of a layout.")
    s.add_argument("input", help="layout layer or scene")
    s.set_defaults(func=_info)


def _tqdm(total, desc):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="chunk", disable=not sys.stderr.isatty(), leave=False)


def _generate(args) -> int:
    from lsd3d_usd.layout import generator, usdio
    from lsd3d_usd.scene import provenance

    _check_output(args.output)
    t0 = time.perf_counter()
    extent = generator.parse_extent(args.extent)
    desc = generator.plan(args.seed, extent, args.style)
    n_chunks = len(desc["chunks"])
    with _tqdm(n_chunks, "layout") as bar:
        layout = generator.build(desc, progress=bar)
    t1 = time.perf_counter()
    path = usdio.write_layout(layout, args.output, provenance(
        "layout.generate", {"extent": list(extent), "style": args.style}, seed=args.seed,
        timings={"generate_s": round(t1 - t0, 3), "write_s": round(time.perf_counter() - t1, 3)}))
    _print_summary(layout, path)
    return 0


def _import(args) -> int:
    import warnings

    from lsd3d_usd.layout import opendrive, usdio
    from lsd3d_usd.scene import provenance

    _check_output(args.output)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", opendrive.OpenDriveWarning)
        layout = opendrive.read_opendrive(args.input, tolerance=args.tolerance, strict=args.strict)
    for w in caught:
        if issubclass(w.category, opendrive.OpenDriveWarning):
            print(f"lsd3d-usd: warning: {w.message}", file=sys.stderr)
    path = usdio.write_layout(layout, args.output, provenance(
        "layout.import", {"source": str(args.input), "tolerance": args.tolerance},
        timings={"import_s": round(time.perf_counter() - t0, 3)}))
    _print_summary(layout, path)
    return 0


def _check_output(path) -> None:
    """Before any work: -o names a USD file that can be written (not a folder, not below a file)."""
    from lsd3d_usd.cliutil import check_output_path
    check_output_path(path, "-o", suffixes=(".usda", ".usdc", ".usd"), what="layout layer")


def _info(args) -> int:
    from lsd3d_usd.layout import usdio
    layout = usdio.read_layout(args.input)
    _print_summary(layout, args.input)
    return 0


def _print_summary(layout, path) -> None:
    (x0, y0), (x1, y1) = layout.bounds()
    counts = ", ".join(f"{v} {k}" for k, v in layout.counts().items() if v)
    print(f"{path}: {counts or 'no features'}; bounds ({x0:.1f}, {y0:.1f})-({x1:.1f}, {y1:.1f}) m")
