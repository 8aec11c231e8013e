"""Regenerate the procedural vehicle assets in samples/assets/ (car, van, truck, bus).

    python tools/make_assets.py [OUT_DIR]
"""
from __future__ import annotations

import sys
from pathlib import Path

from lsd3d_usd.actors.assets import write_library


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).resolve().parents[1] / "samples" / "assets"
    for kind, path in write_library(out).items():
        print(f"{kind}: {path} ({path.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
