"""`lsd3d-usd scenario ...`: OpenSCENARIO scenarios (docs/sim.md "Scenarios")."""
from __future__ import annotations

import sys
import tempfile
import time
import warnings
from pathlib import Path

from lsd3d_usd.errors import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "scenario", help="OpenSCENARIO 1.x scenarios: build a scene around one's road network",
        description="OpenSCENARIO XML 1.0-1.3 scenarios (docs/sim.md \"Scenarios\").")
    sub = p.add_subparsers(dest="scenario_command", metavar="SUBCOMMAND")
    b = sub.add_parser(
        "build", help="generate a scene around a scenario's OpenDRIVE road network",
        description="Read FILE.xosc (safely: no entities, nothing outside its folder), import its "
                    "RoadNetwork/LogicFile OpenDRIVE file as the layout (road and lane ids stay "
                    "addressable for LanePositions) and run `generate` around it; every "
                    "generate option applies.")
    b.add_argument("scenario", help="OpenSCENARIO file (.xosc)")
    b.add_argument("--tolerance", type=float, default=0.02,
                   help="OpenDRIVE polyline tolerance in metres (default 0.02)")
    from lsd3d_usd.commands import add_generate_arguments
    add_generate_arguments(b)
    b.set_defaults(func=_build, compiles_kernels=True)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _build(args) -> int:
    # local imports: not loaded for --help
    from lsd3d_usd.commands import generate_command
    from lsd3d_usd.layout import importers, usdio
    from lsd3d_usd.scene import provenance
    from lsd3d_usd.sim.scenario.reader import read_scenario

    if getattr(args, "list_options", False):
        return generate_command(args)
    if getattr(args, "cfg:layout", None) is not None:
        raise InputError("scenario build: the layout is the scenario's OpenDRIVE file; drop --layout")
    if not args.output:
        raise InputError("scenario build: -o/--output SCENE is required")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sc = read_scenario(args.scenario)
        if sc.road_file is None:
            raise InputError(f"{args.scenario}: no RoadNetwork/LogicFile: a scene needs the "
                             "scenario's OpenDRIVE road network")
        t0 = time.perf_counter()
        layout, imp = importers.read_map(sc.road_file, importers.ImportOptions(tolerance=args.tolerance),
                                         format="opendrive")
    for w in caught:
        if issubclass(w.category, UserWarning):
            print(f"lsd3d-usd: warning: {w.message}", file=sys.stderr)
    layout.metadata["scenario"] = {"file": Path(args.scenario).name, "version": sc.version,
                                   "entities": list(sc.entities), "ego": sc.ego}
    with tempfile.TemporaryDirectory(prefix="lsd3d-scenario-") as tmp:
        path = usdio.write_layout(layout, Path(tmp) / "layout.usda", provenance(
            "scenario.build", {"scenario": str(args.scenario), "source": str(sc.road_file),
                               "tolerance": args.tolerance},
            timings={"import_s": round(time.perf_counter() - t0, 3)}))
        setattr(args, "cfg:layout", str(path))
        return generate_command(args)
