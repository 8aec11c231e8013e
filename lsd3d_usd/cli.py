"""`lsd3d-usd` command line. Thin: parses, calls the library, prints.

Each command lives in a module with ``register(subparsers)``, which adds its
parser and sets ``func`` (taking the parsed args, returning an exit code), and
``compiles_kernels=True`` when it runs numba kernels (the first run then says
that it compiles them).
Heavy imports (torch, numba, ...) stay inside the handlers so --help is fast.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

import lsd3d_usd
from lsd3d_usd.errors import Lsd3dError

# Modules contributing commands; each defines register(subparsers).
COMMAND_MODULES = (
    "lsd3d_usd.commands",
    "lsd3d_usd.layout.commands",
    "lsd3d_usd.proxy.commands",
    "lsd3d_usd.splats.commands",
    "lsd3d_usd.views.commands",
    "lsd3d_usd.datasets.commands",
    "lsd3d_usd.sim_commands",
    "lsd3d_usd.scenario_commands",
    "lsd3d_usd.env_commands",
    "lsd3d_usd.actors.commands",
    "lsd3d_usd.bench",
    "lsd3d_usd.batch.commands",
    "lsd3d_usd.eval.commands",
    "lsd3d_usd.viewer.commands",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lsd3d-usd",
        description="Generate large 3D driving scenes (LSD-3D) as OpenUSD stages: layout, "
                    "proxy geometry, environment map, 2D Gaussian surfels, GGDS.")
    parser.add_argument("--version", action="version", version=f"lsd3d-usd {lsd3d_usd.__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    _negative_values_everywhere(parser)
    return parser


def _negative_values_everywhere(parser) -> None:
    """Every (sub)parser takes '-23.36,119.73' or '-0.001,...' as a value: southern
    latitudes, western longitudes, negative chunk indices and pitches were read as unknown
    flags ("expected one argument"); only the '--origin=-23.36,...' form worked."""
    from lsd3d_usd.cliutil import accept_negative_values
    seen, todo = set(), [parser]
    while todo:
        p = todo.pop()
        if id(p) in seen:
            continue
        seen.add(id(p))
        accept_negative_values(p)
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                todo.extend(a.choices.values())


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
    except Lsd3dError as e:   # e.g. a broken third-party plugin (lsd3d_usd.registry)
        if "--debug" in (sys.argv[1:] if argv is None else argv):
            raise
        print(f"lsd3d-usd: error: {e}", file=sys.stderr)
        return 1
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # local import: not loaded for --help
    from lsd3d_usd.memtune import reuse_large_buffers
    reuse_large_buffers()  # per-frame render buffers reused, not page-faulted in again
    notice = None
    if getattr(args, "compiles_kernels", False):   # numba is imported by these anyway
        # local import: not loaded for --help
        from lsd3d_usd.diagnostics import KernelCompileNotice
        notice = KernelCompileNotice(lambda m: print(f"lsd3d-usd: {m}", file=sys.stderr, flush=True))
    try:
        return int(args.func(args) or 0)
    except Lsd3dError as e:
        if args.debug:
            raise
        print(f"lsd3d-usd: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("lsd3d-usd: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:       # `... | head`: the reader left; not an error of ours
        _silence_stdout()
        return 141                # 128 + SIGPIPE, as a shell tool killed by it
    except OSError as e:          # a folder made read-only, a file where a folder goes, ...
        if args.debug:
            raise
        print(f"lsd3d-usd: error: {os_error_line(e)}", file=sys.stderr)
        return 1
    finally:
        if notice is not None:
            notice.close()


def os_error_line(e: OSError) -> str:
    """'<file>: <reason>' of an OSError, one line."""
    reason = e.strerror or " ".join(str(e).split()) or type(e).__name__
    files = [f for f in (e.filename, e.filename2) if f is not None]
    where = " -> ".join(str(f) for f in files)
    return f"{where}: {reason}" if where else f"{type(e).__name__}: {reason}"


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def run() -> None:
    """Console entry point. Exits with os._exit after flushing: OpenImageIO's nanobind module
    otherwise prints spurious "leaked instances" warnings at interpreter teardown once torch
    is also loaded, which would bury our one-line messages."""
    code = main()
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()
        code = code or 141
    try:
        sys.stderr.flush()
    except BrokenPipeError:
        pass
    os._exit(code)


if __name__ == "__main__":
    run()
