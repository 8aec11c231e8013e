"""Which numba kernels a command compiles, and how long each takes, on a cold cache.

    python tools/profile_compile.py [--cache-dir D] -- generate --layout L -o OUT --steps 2

Runs the lsd3d-usd command in this process with NUMBA_CACHE_DIR set to a fresh (or the given)
folder, records numba's "numba:compile" events (one per function and signature, nested
compiles of inlined or called kernels counted inside their caller's) and prints them by time,
with the command's wall time. Run it twice with the same --cache-dir to see what a warm cache
still costs (cache loads are not compile events)."""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache-dir", help="numba cache folder (default: a new temporary one)")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then the lsd3d-usd command")
    a = ap.parse_args(argv)
    cmd = a.command[1:] if a.command[:1] == ["--"] else a.command
    os.environ["NUMBA_CACHE_DIR"] = a.cache_dir or tempfile.mkdtemp(prefix="numba-cache-")
    from numba.core import event
    from lsd3d_usd.cli import main as cli_main

    starts, rows, depth = {}, [], [0]

    class Compiles(event.Listener):
        def on_start(self, ev):
            starts[id(ev.data["dispatcher"]), str(ev.data["args"])] = (time.perf_counter(),
                                                                        depth[0])
            depth[0] += 1

        def on_end(self, ev):
            depth[0] -= 1
            key = id(ev.data["dispatcher"]), str(ev.data["args"])
            d = ev.data["dispatcher"]
            name = f"{d.py_func.__module__}.{d.py_func.__qualname__}"
            t, level = starts.pop(key)
            rows.append((time.perf_counter() - t, name, str(ev.data["args"]), level))

    listener = Compiles()
    event.register("numba:compile", listener)
    t0 = time.perf_counter()
    try:
        rc = cli_main(cmd)
    finally:
        wall = time.perf_counter() - t0
        event.unregister("numba:compile", listener)
    rows.sort(reverse=True)
    print(f"\n{len(rows)} compiles (nested ones inside their callers), cache {os.environ['NUMBA_CACHE_DIR']}")
    for s, name, args, level in rows:
        print(f"{s:8.2f} s  {'  ' * level}{name}  {args[:90]}")
    outer = sum(r[0] for r in rows if r[3] == 0)
    print(f"compiling {outer:.1f} s (outermost compiles) of wall {wall:.1f} s; "
          f"{len({r[1] for r in rows})} functions")
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
