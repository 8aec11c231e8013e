#!/usr/bin/env python
"""Render benchmark (same as `lsd3d-usd bench render`): time vs error of the CPU 2DGS rasteriser.

    python tools/bench_render.py --json out.json [--quick] [--png plot.png]
"""
import os
import sys

# torch's and numba's OpenMP pools otherwise spin-wait after each parallel region and steal
# the 2 cores from each other (small renders were 3-5x slower); must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from lsd3d_usd.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(["bench", "render", *sys.argv[1:]]))
