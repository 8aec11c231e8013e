#!/usr/bin/env python
"""Render benchmark (same as `lsd3d-usd bench render`): time vs error of the CPU 2DGS rasteriser.

    python tools/bench_render.py --json out.json [--quick] [--png plot.png]
"""
import sys

from lsd3d_usd.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "render", *sys.argv[1:]]))
