"""`lsd3d-usd proxy ...`: build the proxy layer from a layout or a point cloud, preview it."""
from __future__ import annotations

import argparse
import sys

from lsd3d_usd import configtree as ct
from lsd3d_usd import limits
from lsd3d_usd.cliutil import (
    accept_negative_values,
    add_limit_option,
    check_output_path,
    size_type,
)
from lsd3d_usd.errors import InputError

from .chunks import ProxyParams
from .usdio import build_proxy_layer

# the flags `proxy build` gives the proxy tree's leaves (generate reaches them by --set proxy.*)
PROXY_FLAGS = {"margin": "--margin", "street_light_spacing": "--street-light-spacing",
               "traffic_lights": "--no-traffic-lights", "building.windows": "--no-windows"}

USD_SUFFIXES = (".usdc", ".usda", ".usd")


def parse_chunk(text: str) -> tuple[int, int]:
    try:
        i, j = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--chunk {text!r}: expected I,J (two integers, e.g. 0,-1)")
    return i, j


def _progress() -> bool:
    return sys.stderr.isatty()


def _build(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.layout.usdio import read_layout

    got = ct.command_config(args, ProxyParams, needs={
        "layout": "proxy build: --layout LAYOUT is required",
        "output": "proxy build: -o PROXY.usdc is required"})
    if got is None:
        return 0
    params, _ = got
    check_output_path(args.output, "-o", suffixes=USD_SUFFIXES, what="proxy layer")
    layout = read_layout(args.layout)
    if args.chunk:
        ri, rj = layout.chunk_range()
        outside = [k for k in args.chunk if k[0] not in ri or k[1] not in rj]
        if outside:
            raise InputError(f"--chunk {outside[0][0]},{outside[0][1]}: outside the layout "
                             f"{args.layout} (chunks i in {ri.start}..{ri.stop - 1}, "
                             f"j in {rj.start}..{rj.stop - 1})")
    rep = build_proxy_layer(layout, args.output, chunks=args.chunk or None, params=params,
                            force=args.force, progress=_progress(), max_chunks=args.max_chunks)
    tris = sum(rep.triangles.values())
    print(f"{rep.path}: built {len(rep.built)} chunk(s), {len(rep.skipped)} unchanged, "
          f"{tris} triangles, {rep.seconds:.1f} s"
          + ("" if rep.root_written else " (root layer unchanged)"))
    return 0


def _from_points(args) -> int:
    # local import: not loaded for --help
    from .pointcloud import PointProxyParams, proxy_from_points

    params = PointProxyParams(voxel=args.voxel, closing=args.closing,
                              simplify=args.simplify, chunk_size=args.chunk_size)
    check_output_path(args.output, "-o", suffixes=USD_SUFFIXES, what="proxy layer")
    rep = proxy_from_points(args.cloud, args.output, params, progress=_progress(),
                            max_chunks=args.max_chunks, max_vertices=args.max_vertices)
    print(f"{args.output}: {rep['chunks']} chunk(s), {rep['triangles']} triangles from "
          f"{rep['points']} points ({rep['labels']}), {rep['seconds']:.1f} s")
    return 0


def _preview(args) -> int:
    # local import: not loaded for --help
    from .preview import render_proxy_file

    w, h = args.size
    limits.check_image_size(w, h, "--size")
    check_output_path(args.output, "-o", what="image")
    render_proxy_file(args.proxy, args.output, view=args.view, width=w, height=h,
                      chunks=args.chunk or None)
    print(f"{args.output}: {args.view} view of {args.proxy}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "proxy", help="coarse proxy geometry (meshes with semantic labels), chunk by chunk",
        description="Build the proxy layer: road, curbs, sidewalks, markings, buildings, "
                    "vegetation, parked vehicles, street furniture and terrain as UsdGeom.Mesh "
                    "prims with UsdSemantics labels, one payload per 100 m chunk.")
    sub = p.add_subparsers(dest="proxy_command", metavar="ACTION")

    b = sub.add_parser(
        "build", help="layout layer -> proxy layer (only changed chunks are rebuilt)",
        description="Build proxy meshes from a layout layer. Writes OUT (root layer with a "
                    "payload per chunk) and OUT_STEM_chunks/chunk_<i>_<j>.usdc beside it. A chunk "
                    "whose layout inputs did not change (content hash) is not rebuilt.")
    b.add_argument("--layout", metavar="LAYOUT.usda",
                   help="the layout layer (as written by the layout tools)")
    b.add_argument("-o", "--output", metavar="PROXY.usdc",
                   help="proxy root layer to write (.usdc recommended)")
    b.add_argument("--chunk", type=parse_chunk, action="append", metavar="I,J",
                   help="build only this chunk (repeatable); default: every chunk of the layout")
    b.add_argument("--force", action="store_true", help="rebuild chunks even if unchanged")
    add_limit_option(b, limits.CHUNKS)
    ct.add_tree_options(b, "proxy (generate: --set proxy.KEY=VALUE)")
    ct.add_arguments(b, ProxyParams, flags=PROXY_FLAGS)
    b.set_defaults(func=_build)
    accept_negative_values(b)

    f = sub.add_parser(
        "from-points", help="point cloud (.ply/.npz) -> proxy layer",
        description="Reconstruct a proxy from a point cloud: voxelise, close holes, marching "
                    "cubes, simplify. Semantic classes come from per-point labels when the cloud "
                    "has them (PLY property 'label'/'class'/'semantic', NPZ array 'labels', as "
                    "ids into lsd3d_usd.semantics.CLASSES), else from height above a fitted "
                    "ground plane. NPZ: array 'points' (N,3) [+ 'labels' (N,)].")
    f.add_argument("cloud", metavar="CLOUD", help="point cloud: .ply (ascii or binary) or .npz")
    f.add_argument("-o", "--output", required=True, metavar="PROXY.usdc", help="proxy layer to write")
    f.add_argument("--voxel", type=float, default=0.2, metavar="M", help="voxel size (default 0.2 m)")
    f.add_argument("--closing", type=int, default=2, metavar="N",
                   help="binary closing iterations to fill holes (default 2)")
    f.add_argument("--simplify", type=float, default=2.0, metavar="K",
                   help="vertex-clustering cell size in voxels; 0 keeps the marching-cubes "
                        "mesh (default 2)")
    f.add_argument("--chunk-size", type=float, default=100.0, metavar="M",
                   help="chunk size in metres (default 100)")
    add_limit_option(f, limits.CHUNKS)
    add_limit_option(f, limits.PLY_VERTICES)
    f.set_defaults(func=_from_points)

    v = sub.add_parser(
        "preview", help="render a proxy layer to a PNG (top-down or perspective)",
        description="Render proxy meshes coloured by semantic class with simple shading "
                    "(a small painter's-algorithm rasteriser; for docs and quick looks).")
    v.add_argument("proxy", metavar="PROXY", help="proxy layer or scene")
    v.add_argument("-o", "--output", required=True, metavar="IMAGE.png", help="PNG to write")
    v.add_argument("--view", choices=("top", "perspective"), default="perspective",
                   help="camera (default perspective)")
    v.add_argument("--size", type=size_type("--size", minimum=16), default=(1600, 1000), metavar="WxH",
                   help="image size in pixels (default 1600x1000)")
    v.add_argument("--chunk", type=parse_chunk, action="append", metavar="I,J",
                   help="only these chunks (repeatable)")
    v.set_defaults(func=_preview)
    accept_negative_values(v)

    def _no_action(args) -> int:
        p.print_help()
        return 2
    p.set_defaults(func=_no_action)
