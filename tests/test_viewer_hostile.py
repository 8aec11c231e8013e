"""The viewer against hostile clients (issue 40, cases 5 and 12): Host header checked
(DNS rebinding), idle connections closed, connections and the problem list bounded."""
import http.client
import json
import socket
import threading
import time

import pytest

from lsd3d_usd.viewer import server as srvmod
from lsd3d_usd.viewer.server import make_server
from lsd3d_usd.viewer.service import MAX_PROBLEMS, ViewerService
from tests.test_viewer_server import make_scene


@pytest.fixture
def viewer(tmp_path, monkeypatch):
    monkeypatch.setattr(srvmod.Handler, "timeout", 0.5)
    make_scene(tmp_path / "scene")
    svc = ViewerService(tmp_path / "scene", validate=False)
    srv = make_server(svc, "127.0.0.1", 0, quiet=True)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    yield svc, srv
    srv.shutdown()
    srv.server_close()


def _get(srv, path, host=None):
    c = http.client.HTTPConnection("127.0.0.1", srv.server_address[1], timeout=10)
    c.putrequest("GET", path, skip_host=host is not None)
    if host is not None:
        c.putheader("Host", host)
    c.endheaders()
    r = c.getresponse()
    body = r.read()
    c.close()
    return r.status, body


def test_host_header_must_name_the_server(viewer):
    _, srv = viewer
    port = srv.server_address[1]
    for host in ("evil.example.com", f"evil.example.com:{port}", "127.0.0.1.evil.example", ""):
        status, body = _get(srv, "/api/scene", host)
        assert status == 403 and b"layers" not in body, host
    for host in (None, f"localhost:{port}", f"127.0.0.1:{port}", "LOCALHOST"):
        assert _get(srv, "/api/scene", host)[0] == 200, host


def test_remote_hosts_need_allow_remote():
    s = srvmod.ViewerServer.__new__(srvmod.ViewerServer)
    s.names, s.allow_remote = {"localhost", "127.0.0.1"}, False
    assert s.host_allowed("[::1]:8021") and not s.host_allowed("192.168.1.5:8021")
    s.allow_remote = True
    assert s.host_allowed("192.168.1.5:8021") and not s.host_allowed("rebind.evil.example")


def test_idle_connections_are_closed_and_connections_bounded(viewer, monkeypatch):
    _, srv = viewer
    idle = socket.create_connection(srv.server_address, timeout=10)
    t0 = time.monotonic()
    assert idle.recv(1) == b""                      # closed by the server after its timeout
    assert time.monotonic() - t0 < 5
    idle.close()
    srv.max_connections = 2
    held = [socket.create_connection(srv.server_address, timeout=10) for _ in range(2)]
    deadline = time.monotonic() + 5     # both held connections accepted (a loaded machine
    while srv._active < 2 and time.monotonic() < deadline:     # took more than 0.1 s)
        time.sleep(0.01)
    assert srv._active == 2
    extra = socket.create_connection(srv.server_address, timeout=10)
    assert extra.recv(64).startswith(b"HTTP/1.1 503")
    for s in held + [extra]:
        s.close()
    time.sleep(0.8)                                 # the held slots are given back
    assert _get(srv, "/api/problems")[0] == 200


def test_bad_requests_do_not_grow_the_problem_list(viewer):
    svc, srv = viewer
    for k in range(50):
        assert _get(srv, f"/api/config?runs=ggds_nope{k}")[0] == 400
    assert json.loads(_get(srv, "/api/problems")[1])["problems"] == []
    for k in range(3 * MAX_PROBLEMS):
        svc._problem(f"where{k}", "x" * 10_000)
    probs = svc.problem_list()["problems"]
    assert len(probs) == MAX_PROBLEMS + 1 and "not listed" in probs[-1]["message"]
    assert all(len(p["message"]) <= 1000 for p in probs)
