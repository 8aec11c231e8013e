"""Figures of maps read whole (docs/layout.md): the proxy of samples/maps/town_objects.xodr
(OpenDRIVE objects and signals) and of samples/maps/bounds_city.osm (clipped to its bounds,
signals, barriers), as the proxy preview draws them.

    python tools/make_map_figures.py [--out docs/images]
"""
from __future__ import annotations

import argparse
import tempfile
import warnings
from pathlib import Path

import numpy as np

import lsd3d_usd  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]


def _meshes(layout):
    from lsd3d_usd.proxy import build_proxy, merge_parts
    parts = build_proxy(layout)
    return [cm for ps in parts.values() for cm in merge_parts(ps).values()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"))
    args = ap.parse_args()
    from lsd3d_usd.layout import importers
    from lsd3d_usd.proxy.preview import render, save_png
    out = Path(args.out)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        town = importers.read_map(ROOT / "samples/maps/town_objects.xodr")[0]
        city = importers.read_map(ROOT / "samples/maps/bounds_city.osm")[0]
    # the street runs east along y = -20 from x = -80: look along it from its south-west end
    a = render(_meshes(town), 1400, 700, eye=(-95.0, -58.0, 24.0), target=(5.0, -14.0, 0.0),
               fov_deg=55.0)
    b = render(_meshes(city), 1400, 700, eye=(-150.0, -175.0, 95.0), target=(0.0, 0.0, 0.0),
               fov_deg=50.0)
    for img, name in ((a, "map_objects_proxy.png"), (b, "osm_bounds_proxy.png")):
        print(save_png(img, out / name))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
