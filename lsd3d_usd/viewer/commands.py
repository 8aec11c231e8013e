"""`lsd3d-usd view SCENE`: the browser viewer (a local HTTP server)."""
from __future__ import annotations

import argparse
import sys
import time
import webbrowser

from lsd3d_usd import configtree as ct
from lsd3d_usd.errors import InputError
from lsd3d_usd.viewer.config import ViewConfig


def _view(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.viewer.server import is_loopback, make_server
    from lsd3d_usd.viewer.service import ViewerService

    c, _ = ct.from_command_line(args, ViewConfig)
    if not 0 <= c.port <= 65535:
        raise InputError(f"--port {c.port}: must be 0-65535 (0 = any free port)")

    if not is_loopback(c.host) and not c.allow_remote:
        raise InputError(f"--host {c.host}: not a loopback address; serving a scene to other machines "
                         "needs --allow-remote (anyone who can reach the port can read the scene)")

    def log(msg):
        print(f"view: {msg}", file=sys.stderr, flush=True)

    if not is_loopback(c.host) and c.allow_remote:
        print(f"lsd3d-usd view: warning: serving {args.scene} on {c.host}: anyone who can reach "
              f"port {c.port} can read this scene's surfels, layout and plots", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    service = ViewerService(args.scene, validate=c.validate, log=log)
    server = make_server(service, c.host, c.port, allow_remote=c.allow_remote, quiet=c.quiet)
    try:
        cfg = service.config()  # the first page load then finds the chunk buffers ready
        log(f"{sum(c.n for c in cfg.chunks.values())} surfels in {len(cfg.chunks)} chunks "
            f"({cfg.describe()['bytesPerSurfel']} bytes/surfel, {'cached' if cfg.cached else 'built'}) "
            f"ready in {time.perf_counter() - t0:.2f} s")
    except InputError as e:
        log(f"surfels: {e} (the page lists it)")
    host, port = server.server_address[:2]
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown}:{port}/"
    print(url, flush=True)
    if c.open:
        webbrowser.open(url)
    try:
        server.serve_forever(poll_interval=0.25)
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    print("lsd3d-usd view: stopped", file=sys.stderr, flush=True)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view", help="open a scene in the browser viewer (local HTTP server)",
        description="Serve a single-page WebGL2 viewer of a scene folder: its surfels (streamed in "
                    "100 m chunks), env map, layers (GGDS runs toggled in the viewer only), actors over "
                    "time, cameras, proxy/lane/chunk overlays. Prints the URL; Ctrl-C stops it. Packed "
                    "chunk buffers are cached under SCENE/viewer_cache/. See docs/viewer.md.")
    p.add_argument("scene", help="scene folder (holding scene.usda), or its scene.usda")
    ct.add_arguments(p, ViewConfig)
    p.set_defaults(func=_view)
