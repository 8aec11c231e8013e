"""The viewer's HTTP server (stdlib): the single-page viewer, the scene's data, nothing else.

Routes (GET only):
    /                          the page (static/index.html)
    /static/<file>             the viewer's own files, from a table built at start-up
    /api/scene                 layers, cameras, env variants, time range, problems (JSON)
    /api/problems              validation problems (JSON; validation runs in the background)
    /api/config?runs=a,b       a GGDS-run configuration: its id and chunk table (JSON)
    /api/chunk/<id>/<i>_<j>    one chunk's surfels (LSDV, see pack.py)
    /api/env?variant=V         an environment variant: map URL, dome frame, lighting (JSON)
    /api/envmap/<variant>      its latlong map (LSDE)
    /api/layout                lanes and features (JSON)
    /api/actors                actor meshes and transforms over time (JSON)
    /api/proxy/<i>_<j>         one chunk's proxy meshes (LSDM)
    /files/<path>              a document or image of the scene folder (GGDS plots)

No route maps a request onto the file system except /files, and that one takes only plain
relative paths: any '..', '.', empty, absolute, backslash or still-%-encoded segment (after one
decoding) is refused with 403 before anything is looked up, and the resolved file must lie
inside the scene folder (symlinks resolved).
"""
from __future__ import annotations

import ipaddress
import json
import re
import socket
import sys
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, unquote

from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import VIEWER_CONNECTIONS, VIEWER_IDLE_SECONDS

STATIC_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml", ".png": "image/png"}
FILE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".json": "application/json",
              ".txt": "text/plain; charset=utf-8", ".md": "text/plain; charset=utf-8",
              ".usda": "text/plain; charset=utf-8", ".csv": "text/plain; charset=utf-8",
              ".html": "text/plain; charset=utf-8"}
_KEY = r"(-?\d{1,6})_(-?\d{1,6})"
ROUTES = {
    "chunk": re.compile(rf"^/api/chunk/([0-9a-f]{{8,64}})/{_KEY}$"),
    "proxy": re.compile(rf"^/api/proxy/{_KEY}$"),
    "envmap": re.compile(r"^/api/envmap/([^/]{1,200})$"),
}


def static_files() -> dict[str, bytes]:
    """The viewer's own files (package data), by their path under static/."""
    out = {}

    def walk(node, prefix):
        for child in node.iterdir():
            name = prefix + child.name
            if child.is_dir():
                walk(child, name + "/")
            elif child.name.rsplit(".", 1)[-1] in ("html", "js", "css", "svg", "png"):
                out[name] = child.read_bytes()

    walk(resources.files("lsd3d_usd.viewer") / "static", "")
    return out


def plain_relative(raw: str) -> str | None:
    """The decoded relative path of a URL path tail, or None when it is not a plain relative
    path (empty, '.', '..' segments, absolute, drive letters, backslashes, NUL, or anything
    left %-encoded after one decoding, i.e. a double-encoded request)."""
    try:
        text = unquote(raw, errors="strict") if raw else ""
    except UnicodeDecodeError:
        return None
    if not text or "%" in text or "\\" in text or "\0" in text or text.startswith("/"):
        return None
    if re.match(r"^[A-Za-z]:", text):
        return None
    parts = text.split("/")
    if any(p in ("", ".", "..") for p in parts):
        return None
    return text


def _has_dot_segment(path: str) -> bool:
    """Any '.'/'..' segment in the raw or once-decoded path (also spelled %2e, %2f, \\)."""
    for text in (path, unquote(path)):
        for seg in re.split(r"[/\\]", text):
            if seg in (".", ".."):
                return True
    return False


class Handler(BaseHTTPRequestHandler):
    server_version = "lsd3d-usd-viewer"
    protocol_version = "HTTP/1.1"
    timeout = VIEWER_IDLE_SECONDS.value   # an idle keep-alive connection is closed

    # ----------------------------------------------------------------------- replies
    def _send(self, status: int, body: bytes, ctype: str, cache: str = "no-store") -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", cache)
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, data, status: int = 200) -> None:
        self._send(status, json.dumps(data, separators=(",", ":"), allow_nan=False).encode(),
                   "application/json")

    def _error(self, status: int, message: str) -> None:
        self._send(status, (message + "\n").encode(), "text/plain; charset=utf-8")

    def _binary(self, data: bytes | None, immutable: bool = False) -> None:
        if data is None:
            return self._error(404, "not found")
        self._send(200, data, "application/octet-stream",
                   "public, max-age=31536000, immutable" if immutable else "no-store")

    # ------------------------------------------------------------------------ routing
    def do_HEAD(self):
        self.do_GET()

    def do_POST(self):
        self._error(405, "the viewer serves GET requests only")

    do_PUT = do_DELETE = do_PATCH = do_POST

    def do_GET(self):
        if not self.server.host_allowed(self.headers.get("Host")):
            # DNS rebinding: a page of evil.example.com resolving to 127.0.0.1 sends its own
            # name; only our own names may read the scene
            return self._error(403, "refused: unknown Host header")
        path, _, query = self.path.partition("?")
        if _has_dot_segment(path) or not path.startswith("/"):
            return self._error(403, "refused: path outside the scene folder")
        try:
            self._route(path, parse_qs(query, keep_blank_values=True))
        except InputError as e:
            self._json({"error": str(e)}, 400)
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as e:  # a damaged file deep in the scene: one line, the page lists it
            msg = f"{type(e).__name__}: {' '.join(str(e).split())[:400]}"
            self.log_message("%s: %s", path, msg)
            self._json({"error": msg}, 500)

    def _route(self, path: str, q: dict) -> None:
        svc = self.server.service
        if path in ("/", "/index.html"):
            return self._send(200, self.server.static["index.html"], STATIC_TYPES[".html"])
        if path.startswith("/static/"):
            name = plain_relative(path[len("/static/"):])
            if name is None:
                return self._error(403, "refused: not a plain relative path")
            body = self.server.static.get(name)
            if body is None:
                return self._error(404, "not found")
            return self._send(200, body, STATIC_TYPES.get("." + name.rsplit(".", 1)[-1],
                                                          "application/octet-stream"))
        if path.startswith("/files/"):
            rel = plain_relative(path[len("/files/"):])
            if rel is None:
                return self._error(403, "refused: path outside the scene folder")
            f = svc.scene_file(rel)
            if f is None:
                return self._error(404, "not found")
            return self._send(200, f.read_bytes(), FILE_TYPES.get(f.suffix.lower(), "application/octet-stream"))
        if path == "/api/scene":
            return self._json(svc.scene_info())
        if path == "/api/problems":
            return self._json(svc.problem_list())
        if path == "/api/config":
            runs = None
            if "runs" in q:
                runs = [r for r in q["runs"][0].split(",") if r]
            return self._json(svc.config_info(runs))
        if path == "/api/env":
            return self._json(svc.env_info(q.get("variant", [None])[0] or None))
        if path == "/api/layout":
            return self._json(svc.layout_info())
        if path == "/api/actors":
            return self._json(svc.actors_info())
        m = ROUTES["chunk"].match(path)
        if m:
            return self._binary(svc.chunk_bytes(m.group(1), (int(m.group(2)), int(m.group(3)))), True)
        m = ROUTES["proxy"].match(path)
        if m:
            return self._binary(svc.proxy_bytes((int(m.group(1)), int(m.group(2)))))
        m = ROUTES["envmap"].match(path)
        if m:
            return self._binary(svc.env_bytes(unquote(m.group(1))))
        return self._error(404, "not found")

    # ----------------------------------------------------------------------- logging
    def log_message(self, fmt, *args):
        if self.server.quiet:
            return
        sys.stderr.write(f"{self.log_date_time_string()} {fmt % args}\n")
        sys.stderr.flush()


class ViewerServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, service, quiet: bool = False, allow_remote: bool = False):
        host = address[0]
        self.address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        super().__init__(address, Handler)
        self.service = service
        self.static = static_files()
        self.quiet = quiet
        self.allow_remote = allow_remote
        self.names = {"localhost", host.lower().strip("[]")}
        if allow_remote:
            self.names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        self.max_connections = int(VIEWER_CONNECTIONS.value)
        self._active = 0                 # connections being served (at most max_connections)
        self._active_lock = threading.Lock()

    def host_allowed(self, header: str | None) -> bool:
        """Whether a request's Host header names this server: loopback names and addresses,
        the bound host; with --allow-remote also IP literals and this machine's names (DNS
        rebinding needs a domain name of the attacker's)."""
        if not header:
            return False
        h = header.strip().lower()
        if h.startswith("["):
            name = h[1:h.find("]")] if "]" in h else h[1:]
        else:
            name = h.rsplit(":", 1)[0] if h.count(":") == 1 else h
        if name in self.names:
            return True
        try:
            ip = ipaddress.ip_address(name)
        except ValueError:
            return False
        return ip.is_loopback or self.allow_remote

    # bounded workers: one thread per connection, at most VIEWER_CONNECTIONS of them
    def process_request(self, request, client_address):
        if not self._take_slot():
            try:
                request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n"
                                b"Connection: close\r\n\r\n")
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._give_slot()
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._give_slot()

    def _take_slot(self) -> bool:
        with self._active_lock:
            if self._active >= self.max_connections:
                return False
            self._active += 1
            return True

    def _give_slot(self) -> None:
        # a counter: the bound can change while connections are open (the tests lower it)
        with self._active_lock:
            self._active = max(0, self._active - 1)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def make_server(service, host: str = "127.0.0.1", port: int = 8021, *, allow_remote: bool = False,
                quiet: bool = False) -> ViewerServer:
    """Bind the server. A host other than loopback needs ``allow_remote`` (anyone who can reach
    it can read the scene's surfels, layout and plots)."""
    if not is_loopback(host) and not allow_remote:
        raise InputError(f"--host {host}: not a loopback address; serving a scene to other machines "
                         "needs --allow-remote (anyone who can reach the port can read the scene)")
    try:
        return ViewerServer((host, port), service, quiet, allow_remote)
    except OSError as e:
        raise InputError(f"cannot listen on {host}:{port}: {e.strerror or e} "
                         "(try another --port, or --port 0 for any free one)") from None
