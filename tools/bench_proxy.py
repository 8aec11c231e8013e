"""Benchmark: layout -> proxy layer (seconds, seconds per chunk, peak memory, triangles per class).

    python tools/bench_proxy.py [--case city|straight|both] [--extent 1000] [--style urban]
                                [--seed 0] [--synthetic] [--length 3000] [--json OUT]

Cases:
- ``city``: a generated layout of --extent x --extent metres (default 1 km x 1 km urban);
  target (issue 4): under 60 s and 4 GB.
- ``straight``: one straight road of --length metres (default 3 km) with three lanes each
  way, broken and solid lane lines and sidewalk lanes, written as OpenDRIVE and imported
  (as a real map is); target (issue 38): under 3 s, and a time per chunk within 2x of the
  city's (a chunk's cost follows what it holds, not the length of the lanes through it).
- ``both``: the two, and the ratio of their times per chunk.
"""
from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import lsd3d_usd  # noqa: F401  (registers the schema first)


def straight_road_xodr(path: Path, length: float, lanes: int = 3, width: float = 3.5) -> Path:
    """One straight OpenDRIVE road: ``lanes`` driving lanes each way, broken lines between
    them, solid outer lines, a 2 m sidewalk lane on each side."""
    def lane(lid, typ="driving", w=width, mark="broken"):
        return (f'<lane id="{lid}" type="{typ}" level="false"><width sOffset="0" a="{w}" b="0" '
                f'c="0" d="0"/><roadMark sOffset="0" type="{mark}" weight="standard" '
                f'color="standard" width="0.12"/></lane>')
    left = "".join(lane(k, mark="solid" if k == lanes else "broken") for k in range(1, lanes + 1))
    right = "".join(lane(-k, mark="solid" if k == lanes else "broken") for k in range(1, lanes + 1))
    left += lane(lanes + 1, "sidewalk", 2.0, "none")
    right += lane(-lanes - 1, "sidewalk", 2.0, "none")
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header revMajor="1" revMinor="7" '
        f'name="straight"/><road id="1" length="{length}" junction="-1"><link/><planView>'
        f'<geometry s="0" x="0" y="0" hdg="0" length="{length}"><line/></geometry></planView>'
        f'<lanes><laneSection s="0"><left>{left}</left><center><lane id="0" type="none" '
        'level="false"><roadMark sOffset="0" type="solid solid" weight="standard" color="yellow" '
        f'width="0.12"/></lane></center><right>{right}</right></laneSection></lanes></road>'
        '</OpenDRIVE>\n')
    return path


def run_case(name: str, layout, out_dir: Path) -> dict:
    from lsd3d_usd.proxy.usdio import build_proxy_layer
    out = out_dir / name / "proxy.usdc"
    c0 = time.process_time()
    rep = build_proxy_layer(layout, out)
    cpu = time.process_time() - c0
    t0 = time.perf_counter()
    again = build_proxy_layer(layout, out)
    t_rebuild = time.perf_counter() - t0
    size = sum(f.stat().st_size for f in out.parent.rglob("*.usdc"))
    n = max(len(rep.built), 1)
    return {"case": name, "seconds": round(rep.seconds, 3), "cpu_seconds": round(cpu, 3),
            "chunks": len(rep.built), "seconds_per_chunk": round(rep.seconds / n, 4),
            "triangles": int(sum(rep.triangles.values())),
            "triangles_by_class": dict(sorted(rep.triangles.items(), key=lambda kv: -kv[1])),
            "unchanged_rebuild_seconds": round(t_rebuild, 3), "rebuilt": len(again.built),
            "files_mb": round(size / 1e6, 2)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=("city", "straight", "both"), default="city")
    ap.add_argument("--extent", type=float, default=1000.0, help="city: square side in metres (default 1000)")
    ap.add_argument("--style", default="urban", help="city: generator style (urban, suburban, highway)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--synthetic", action="store_true",
                    help="city: use the proxy's synthetic grid layout instead of the layout generator")
    ap.add_argument("--length", type=float, default=3000.0, help="straight: road length in metres (default 3000)")
    ap.add_argument("--out", default=None, help="folder for the proxy layers (default: a temp dir)")
    ap.add_argument("--json", default=None, help="also write the results to this JSON file")
    args = ap.parse_args()

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        out_dir = Path(args.out or tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        if args.case in ("city", "both"):
            t0 = time.perf_counter()
            if args.synthetic:
                from lsd3d_usd.proxy.synthetic import grid_layout
                n = max(1, int(round(args.extent / 100)))
                layout = grid_layout(n, n)
            else:
                from lsd3d_usd.layout.generator import generate
                layout = generate(args.seed, (args.extent, args.extent), args.style)
            counts = layout.counts()
            print(f"city: {args.extent:.0f} m x {args.extent:.0f} m "
                  f"{'synthetic grid' if args.synthetic else f'{args.style} seed {args.seed}'}, "
                  f"{sum(counts.values())} features ({counts['Building']} buildings, "
                  f"{counts['LaneCenter']} lanes, {counts['Tree']} trees), "
                  f"{time.perf_counter() - t0:.2f} s to make")
            results.append(run_case("city", layout, out_dir))
        if args.case in ("straight", "both"):
            from lsd3d_usd.layout.opendrive import read_opendrive
            xodr = straight_road_xodr(out_dir / "straight.xodr", args.length)
            layout = read_opendrive(xodr)
            counts = layout.counts()
            print(f"straight: one {args.length:.0f} m road, 3 lanes each way, "
                  f"{counts['LaneCenter']} lanes, {counts['RoadLine']} lines, "
                  f"{sum(len(ln.points) for ln in layout.lanes)} lane vertices (imported OpenDRIVE)")
            results.append(run_case("straight", layout, out_dir))
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    for r in results:
        print(f"{r['case']}: proxy build {r['seconds']:.2f} s wall, {r['cpu_seconds']:.2f} s CPU for "
              f"{r['chunks']} chunks ({r['seconds_per_chunk']:.3f} s/chunk), {r['triangles']} triangles, "
              f"files {r['files_mb']:.1f} MB; unchanged rebuild {r['unchanged_rebuild_seconds']:.2f} s "
              f"({r['rebuilt']} chunks rebuilt)")
        for cls, n in r["triangles_by_class"].items():
            print(f"  {cls:14s} {n:10d}")
    summary = {"results": results, "peak_rss_gb": round(peak_gb, 3)}
    if len(results) == 2:
        ratio = results[1]["seconds_per_chunk"] / max(results[0]["seconds_per_chunk"], 1e-9)
        summary["straight_over_city_per_chunk"] = round(ratio, 3)
        print(f"time per chunk, straight road / city: {ratio:.2f}")
    print(f"peak RSS: {peak_gb:.2f} GB")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
