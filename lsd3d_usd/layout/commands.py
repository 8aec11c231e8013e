"""`lsd3d-usd layout ...`: generate a procedural layout, import a map (OpenDRIVE, Lanelet2,
OpenStreetMap, or a registered importer), export OpenDRIVE, show a summary."""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings

from lsd3d_usd import configtree as ct
from lsd3d_usd.cliutil import check_output_path
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import importers
from lsd3d_usd.layout.config import LayoutExportConfig, LayoutGenerateConfig, LayoutImportConfig
from lsd3d_usd.scene import provenance

import numpy as np


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "layout", help="map layouts: generate procedurally, import maps, export OpenDRIVE, inspect",
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
    ct.add_arguments(g, LayoutGenerateConfig)
    g.add_argument("-o", "--output", required=True, help="output layer (.usda or .usdc)")
    g.set_defaults(func=_generate)

    i = sub.add_parser(
        "import", help="import a map (OpenDRIVE, Lanelet2, OpenStreetMap, ...)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Import a map as a layout layer. The format is chosen by the file's content "
                    "(--format forces one). Formats:\n" + importers.formats_help() +
                    "\n\nOpenDRIVE curves and Lanelet2/OSM lines are kept within --tolerance. Parts "
                    "that cannot be read are skipped with a warning naming them. See docs/layout.md.")
    i.add_argument("input", help="map file (.xodr, .osm, .osm.pbf, ...)")
    i.add_argument("-o", "--output", required=True, help="output layer (.usda or .usdc)")
    ct.add_arguments(i, LayoutImportConfig)
    i.set_defaults(func=_import)

    gr = sub.add_parser(
        "georef", help="show a layout's geoReference; with a second layout, where its frame lies",
        description="Print the layout's frame (projection and offset, where its origin and "
                    "centre lie in longitude/latitude). With B: the offset of B's frame in A's "
                    "(translation, rotation, scale of the rigid motion mapping B coordinates to "
                    "A coordinates over B's area, and how far the exact reprojection departs "
                    "from it). `layout import --frame A` writes a map in A's frame.")
    gr.add_argument("input", help="layout layer or scene (A)")
    gr.add_argument("other", nargs="?", default=None, help="a second layout (B)")
    gr.add_argument("--json", action="store_true", help="print JSON")
    gr.set_defaults(func=_georef)

    x = sub.add_parser(
        "export", help="export a layout as ASAM OpenDRIVE (.xodr)",
        description="Write a layout (generated, imported or hand-written) as ASAM OpenDRIVE 1.7: "
                    "each lane a road whose reference line is the lane centre fitted with lines, "
                    "arcs and paramPoly3 within --tolerance, lane widths, links and junctions.")
    x.add_argument("input", help="layout layer or scene")
    x.add_argument("-o", "--output", required=True, help="output file (.xodr)")
    ct.add_arguments(x, LayoutExportConfig)
    x.set_defaults(func=_export)

    s = sub.add_parser("info", help="summarise a layout layer",
                       description="Print feature counts, bounds and the lane graph size of a layout.")
    s.add_argument("input", help="layout layer or scene")
    s.set_defaults(func=_info)

    ln = sub.add_parser(
        "lanes", help="list the drivable lanes (ids, lengths, successors) and draw them",
        description="List the lanes a car drives (types driving, bus, entry, exit) with length, "
                    "speed limit and drivable successors, and the longest route along them "
                    "(a ready `--route` for `render --rig`). --png draws a top view with the "
                    "lane ids.")
    ln.add_argument("input", help="layout layer or scene")
    ln.add_argument("--png", help="also write a top view with lane ids to this PNG file")
    ln.add_argument("--json", action="store_true", help="print JSON instead of text")
    ln.set_defaults(func=_lanes)


def _tqdm(total, desc):
    # local import: not loaded for --help
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="chunk", disable=not sys.stderr.isatty(), leave=False)


def _generate(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.layout import generator, usdio

    c, _ = ct.from_command_line(args, LayoutGenerateConfig)
    _check_output(args.output)
    t0 = time.perf_counter()
    extent = generator.parse_extent(c.extent)
    desc = generator.plan(c.seed, extent, c.style)
    n_chunks = len(desc["chunks"])
    with _tqdm(n_chunks, "layout") as bar:
        layout = generator.build(desc, progress=bar)
    t1 = time.perf_counter()
    path = usdio.write_layout(layout, args.output, provenance(
        "layout.generate", {"extent": list(extent), "style": c.style}, seed=c.seed,
        timings={"generate_s": round(t1 - t0, 3), "write_s": round(time.perf_counter() - t1, 3)}))
    _print_summary(layout, path)
    return 0


def _parse_floats(text: str | None, n: int, flag: str, example: str) -> tuple | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != n or not all(abs(v) < 1e6 for v in vals):
        raise InputError(f"{flag} {text!r}: expected {example}")
    return vals


def _import(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.layout import usdio

    c, _ = ct.from_command_line(args, LayoutImportConfig)
    _check_output(args.output)
    origin = _parse_floats(c.origin, 2, "--origin", "LAT,LON in degrees, e.g. 48.137,11.575")
    bbox = _parse_floats(c.bbox, 4, "--bbox", "MINLON,MINLAT,MAXLON,MAXLAT in degrees")
    opts = importers.ImportOptions(tolerance=c.tolerance, strict=c.strict, origin=origin,
                                   bbox=bbox, clip=c.clip)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        layout, imp = importers.read_map(args.input, opts, format=c.format)
    for w in caught:
        if issubclass(w.category, UserWarning):
            print(f"lsd3d-usd: warning: {w.message}", file=sys.stderr)
    if c.frame:
        from lsd3d_usd.layout import georef
        target = georef.of_layout(usdio.read_layout(c.frame))
        if target is None:
            from lsd3d_usd.errors import InputError
            raise InputError(f"--frame {c.frame}: that layout has no geoReference")
        layout = georef.reproject(layout, target)
    src = layout.metadata.get("source", {})
    params = {"source": str(args.input), "format": imp.name, "tolerance": c.tolerance}
    if c.frame:
        params["frame"] = str(c.frame)
    for key in ("origin", "originFrom", "bbox", "clip"):
        if key in src:
            params[key] = src[key]
    path = usdio.write_layout(layout, args.output, provenance(
        "layout.import", params, timings={"import_s": round(time.perf_counter() - t0, 3)}))
    _print_summary(layout, path)
    print(importers.reach_line(layout))
    if "origin" in src:
        print(_origin_line(src))
    return 0


_ORIGIN_FROM = {
    "flag": "from --origin",
    "bbox": "the centre of --bbox",
    "file bounds": "the centre of the file's <bounds>",
    # the case that surprises: another layout of the same map can sit hundreds of metres away
    "node extent": "the centre of its nodes' extent: the file has no <bounds>; pass --origin "
                   "LAT,LON to share another layout's origin",
}


def _origin_line(src: dict) -> str:
    """Where the layout's (0, 0) lies on the Earth and where that origin came from."""
    lat, lon = src["origin"][:2]
    how = src.get("originFrom", "")
    return f"origin lat {lat:.7f}, lon {lon:.7f} ({_ORIGIN_FROM.get(how, how or 'unknown')})"


def _export(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.layout import opendrive_export, usdio

    c, _ = ct.from_command_line(args, LayoutExportConfig)
    check_output_path(args.output, "-o", suffixes=(".xodr",), what="OpenDRIVE file")
    layout = usdio.read_layout(args.input)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rep = opendrive_export.write_opendrive(layout, args.output, tolerance=c.tolerance)
    for w in caught:
        if issubclass(w.category, UserWarning):
            print(f"lsd3d-usd: warning: {w.message}", file=sys.stderr)
    geoms = ", ".join(f"{v} {k}" for k, v in sorted(rep.geometries.items()))
    print(f"{args.output}: {sum(len(v) for v in rep.roads.values())} roads from "
          f"{len(rep.roads)} lanes, {rep.junctions} junctions; geometry {geoms}; fit within "
          f"{rep.max_curve_deviation * 100:.2f} cm ({time.perf_counter() - t0:.2f} s)")
    if c.validate:
        errors = opendrive_export.validate(args.output)
        if errors:
            raise InputError(f"{args.output}: not valid against the OpenDRIVE XSD: {errors[0]}"
                             + (f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""))
        print(f"{args.output}: valid against the ASAM OpenDRIVE 1.7 XSD")
    return 0


def _georef(args) -> int:
    import json

    from lsd3d_usd.errors import InputError
    from lsd3d_usd.layout import georef, usdio
    a = usdio.read_layout(args.input)
    ra = georef.of_layout(a)
    if ra is None:
        raise InputError(f"{args.input}: the layout has no geoReference")
    (x0, y0), (x1, y1) = a.bounds()
    centre = np.array([[(x0 + x1) / 2, (y0 + y1) / 2]])
    lon, lat = ra.to_lonlat(np.vstack([[0.0, 0.0], centre]))
    out = {"path": str(args.input), "geoReference": ra.to_json(),
           "origin_lonlat": [float(lon[0]), float(lat[0])],
           "centre_lonlat": [float(lon[1]), float(lat[1])]}
    if args.other:
        b = usdio.read_layout(args.other)
        rb = georef.of_layout(b)
        if rb is None:
            raise InputError(f"{args.other}: the layout has no geoReference")
        (bx0, by0), (bx1, by1) = b.bounds()
        at = ((bx0 + bx1) / 2, (by0 + by1) / 2)
        off = georef.frame_offset(ra, rb, at=at, radius=max(50.0, np.hypot(bx1 - bx0, by1 - by0) / 2))
        out["other"] = str(args.other)
        out["offset"] = off.to_json()
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{args.input}: {ra.proj}; offset {list(ra.offset)} ({ra.source}); origin at lon "
          f"{out['origin_lonlat'][0]:.7f}, lat {out['origin_lonlat'][1]:.7f}; centre at lon "
          f"{out['centre_lonlat'][0]:.7f}, lat {out['centre_lonlat'][1]:.7f}")
    if args.other:
        print(f"{args.other} (B) in {args.input} (A): {off.line()}")
    return 0


def _check_output(path) -> None:
    """Before any work: -o names a USD file that can be written (not a folder, not below a file)."""
    check_output_path(path, "-o", suffixes=(".usda", ".usdc", ".usd"), what="layout layer")


def _info(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.layout import usdio
    layout = usdio.read_layout(args.input)
    _print_summary(layout, args.input)
    return 0


def _lanes(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.layout import lanes, usdio
    from lsd3d_usd.layout.routes import longest_route
    if args.png:
        check_output_path(args.png, "--png", suffixes=(".png",), what="PNG file")
    layout = usdio.read_layout(args.input)
    rows = lanes.lane_graph(layout)
    route = longest_route(layout)
    if args.png:
        lanes.draw_lanes(layout, args.png, title=f"{args.input}: drivable lanes")
    if args.json:
        print(json.dumps({"path": str(args.input), "lanes": [r.to_json() for r in rows],
                          "longest_route": {"lanes": route[0], "length_m": round(route[1], 2)},
                          "png": args.png}, indent=2))
    else:
        print(lanes.format_lanes(rows, route, args.input))
        if args.png:
            print(f"top view: {args.png}")
    return 0


def _print_summary(layout, path) -> None:
    # local import: not loaded for --help
    from lsd3d_usd.layout.lanes import lane_graph
    (x0, y0), (x1, y1) = layout.bounds()
    counts = ", ".join(f"{v} {k}" for k, v in layout.counts().items() if v)
    graph = lane_graph(layout)
    print(f"{path}: {counts or 'no features'}; bounds ({x0:.1f}, {y0:.1f})-({x1:.1f}, {y1:.1f}) m; "
          f"lane graph: {len(graph)} drivable lanes, {sum(len(r.successors) for r in graph)} "
          "successor links (`layout lanes` lists them)")
