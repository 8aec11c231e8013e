"""`lsd3d-usd view`'s server without a browser: the scene description, per-chunk buffers of
each GGDS-run configuration, the content-hash cache, path refusal, damaged scenes and the CLI
(loopback only by default, Ctrl-C)."""
import http.client
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from lsd3d_usd import scene as S
from lsd3d_usd.viewer import pack
from lsd3d_usd.viewer.server import make_server
from lsd3d_usd.viewer.service import ViewerService

RUN = "ggds_20261201-000000"


def ground_field(chunks, n=300, seed=0, colour=(0.2, 0.3, 0.4), chunk=100.0, sh_degree=1, high=0.05):
    """Flat ground surfels (normal +Z) spread over the given chunks, SH degree 1 (or
    sh_degree, the bands above 1 drawn with standard deviation `high`)."""
    from lsd3d_usd.semantics import CLASSES
    from lsd3d_usd.splats.field import SurfelField, rgb_to_sh_dc

    rng = np.random.default_rng(seed)
    pos = np.concatenate([np.c_[rng.uniform(i * chunk + 2, (i + 1) * chunk - 2, n),
                                rng.uniform(j * chunk + 2, (j + 1) * chunk - 2, n), np.zeros(n)]
                          for i, j in chunks])
    m = len(pos)
    sh = np.zeros((m, (sh_degree + 1) ** 2, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(np.tile(np.asarray(colour, np.float32), (m, 1)) + rng.uniform(-0.05, 0.05, (m, 3)))
    sh[:, 1:4] = rng.normal(0, 0.05, (m, 3, 3))[:, :sh.shape[1] - 1]
    if sh_degree >= 2:   # from a stream of their own: degree-1 fields stay as they were
        sh[:, 4:] = np.random.default_rng(seed + 1000).normal(0, high, (m, sh.shape[1] - 4, 3))
    return SurfelField(pos.astype(np.float32), np.tile(np.float32([0, 0, 0, 1]), (m, 1)),
                       rng.uniform(0.8, 2.0, (m, 2)).astype(np.float32), np.full(m, 0.9, np.float32), sh,
                       rng.integers(0, len(CLASSES), m), CLASSES)


def make_scene(root, chunks=((0, 0), (1, 0)), n=300, run=True, cameras=None, colour=(0.2, 0.3, 0.4),
               sh_degree=1, high=0.05):
    """A scene folder written through the library: a surfels layer (ground_field), optionally
    a GGDS-run layer (overs of the optimised attributes, as `generate` writes them: here the
    surfels raised by 0.5 m and recoloured), and cameras {name: (eye, target)} in the root layer."""
    from dataclasses import replace

    from pxr import Usd

    from lsd3d_usd.render.camera import Camera, look_at, to_usd
    from lsd3d_usd.splats.usdio import write_surfels

    sc = S.Scene.create(root, chunk_size=100.0)
    f = ground_field(chunks, n, colour=colour, sh_degree=sh_degree, high=high)
    st = S.new_stage()
    write_surfels(st, S.SURFELS_PATH, f)
    sc.write_layer("surfels", st, S.provenance("splats"))
    if run:
        g = replace(f, positions=f.positions + np.float32([0, 0, 0.5]), sh=f.sh.copy())
        g.sh[:, 0] = g.sh[:, 0] * -1.0 + 1.0
        st = S.new_stage()
        write_surfels(st, S.SURFELS_PATH, g, over=True,
                      attributes=("positions", "orientations", "scales", "opacities", "sh"))
        sc.write_layer(f"{RUN}.usdc", st, S.provenance("ggds", stepsDone=3))
        (root / "ggds" / RUN).mkdir(parents=True)
        (root / "ggds" / RUN / "summary.json").write_text('{"steps": 3}')
    if cameras:
        stage = Usd.Stage.Open(str(root / S.ROOT_FILE))
        stage.SetEditTarget(stage.GetRootLayer())
        for name, (eye, target) in cameras.items():
            to_usd(stage, f"{S.CAMERAS_PATH}/{name}", Camera.from_fov(320, 180, 60, look_at(eye, target),
                                                                      near=0.1, far=2000.0))
        stage.GetRootLayer().Save()
    return f


@pytest.fixture
def served(tmp_path):
    """Start a server on a fresh scene; yields (root, get) with get(path) -> (status, headers, body)."""
    servers = []

    def start(**kw):
        root = tmp_path / "scene"
        make_scene(root, **kw)
        svc = ViewerService(root, validate=False)
        srv = make_server(svc, "127.0.0.1", 0, quiet=True)
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        servers.append(srv)

        def get(path):
            c = http.client.HTTPConnection("127.0.0.1", srv.server_address[1], timeout=30)
            c.request("GET", path)   # sent as given: no client-side normalisation
            r = c.getresponse()
            body = r.read()
            c.close()
            return r.status, dict(r.getheaders()), body
        return root, svc, get

    yield start
    for s in servers:
        s.shutdown()
        s.server_close()


def test_scene_configurations_and_chunk_buffers(served):
    root, svc, get = served(chunks=((0, 0), (1, 0), (-1, 2)), cameras={"Top": ((50, 40, 80), (50, 50, 0))})
    status, _, body = get("/api/scene")
    info = json.loads(body)
    assert status == 200 and info["chunkSize"] == 100.0 and info["defaultRuns"] == [RUN]
    assert [(L["name"], L["kind"]) for L in info["layers"]] == [(RUN, "ggds"), ("surfels", "step")]
    assert info["layers"][0]["files"] == [f"ggds/{RUN}/summary.json"]
    assert [c["path"] for c in info["cameras"]] == ["/World/Cameras/Top"]
    assert np.allclose(info["cameras"][0]["poses"][0][12:15], [50, 40, 80])

    on = json.loads(get("/api/config")[2])
    off = json.loads(get("/api/config?runs=")[2])
    assert on["runs"] == [RUN] and off["runs"] == [] and on["id"] != off["id"]
    assert on["surfels"] == off["surfels"] == 900 and on["shDegree"] == 1
    assert sorted((c["i"], c["j"]) for c in on["chunks"]) == [(-1, 2), (0, 0), (1, 0)]
    for cfg, dz in ((on, 0.5), (off, 0.0)):
        for c in cfg["chunks"]:
            status, headers, buf = get(c["url"])
            assert status == 200 and "immutable" in headers["Cache-Control"] and len(buf) == c["bytes"]
            d = pack.decode_chunk(buf)
            assert d["key"] == (c["i"], c["j"]) and len(d["positions"]) == c["n"] == 300
            assert np.all(np.floor(d["positions"][:, :2] / 100.0) == [c["i"], c["j"]])
            assert np.allclose(d["positions"][:, 2], dz, atol=1e-6)
    assert get("/api/config?runs=ggds_nope")[0] == 400
    assert get(f"/api/chunk/{on['id']}/7_7")[0] == 404
    assert get("/api/chunk/zzzz/0_0")[0] == 404


def test_cache_is_reused_and_follows_content(served):
    root, svc, get = served()
    first = svc.config()
    assert not first.cached and (root / "viewer_cache" / f"surfels_{first.id}" / "index.json").is_file()
    again = ViewerService(root, validate=False).config()
    assert again.cached and again.id == first.id
    # a rewritten run layer (new content) is a new configuration
    from lsd3d_usd.splats.usdio import write_surfels
    st = S.new_stage()
    write_surfels(st, S.SURFELS_PATH, ground_field(((0, 0), (1, 0)), seed=5), over=True, attributes=("sh",))
    S.save_layer(st.GetRootLayer(), root / "layers" / f"{RUN}.usdc")
    changed = ViewerService(root, validate=False).config()
    assert changed.id != first.id and not changed.cached
    # the scene itself is untouched by viewing: same stack, nothing muted
    assert [(i.name, i.muted) for i in S.Scene.open(root).layers()] == [(RUN, False), ("surfels", False)]


def test_cache_of_another_packing_version_is_rebuilt(served):
    root, svc, get = served()
    first = svc.config()
    index = root / "viewer_cache" / f"surfels_{first.id}" / "index.json"
    data = json.loads(index.read_text())
    assert data["version"] == pack.CHUNK_VERSION
    data["version"] = pack.CHUNK_VERSION - 1                 # e.g. written by an older viewer
    index.write_text(json.dumps(data))
    again = ViewerService(root, validate=False).config()
    assert not again.cached and again.id == first.id
    assert json.loads(index.read_text())["version"] == pack.CHUNK_VERSION


@pytest.mark.parametrize("degree", [2, 3])
def test_sh_degree_two_is_served_and_higher_bands_dropped(served, degree):
    root, svc, get = served(run=False, sh_degree=degree, high=0.3)
    f = ground_field(((0, 0), (1, 0)), sh_degree=degree, high=0.3)
    cfg = json.loads(get("/api/config")[2])
    assert cfg["shDegree"] == 2 and cfg["surfels"] == 600
    assert cfg["bytesPerSurfel"] == pytest.approx(6 + 48, abs=0.5)
    for c in cfg["chunks"]:
        d = pack.decode_chunk(get(c["url"])[2])
        assert d["sh_degree"] == 2 and d["sh"].shape == (c["n"], 9, 3)
        # the chunk's surfels, matched by position, keep bands 0-2 within the i8 quantisation
        near = np.abs(d["positions"][:, None, :2] - f.positions[None, :, :2]).sum(2).argmin(1)
        band2 = np.abs(f.sh[near, 4:9]).reshape(c["n"], -1).max(1)
        err = np.abs(d["sh"][:, 4:9] - f.sh[near, 4:9]).reshape(c["n"], -1).max(1)
        assert np.all(err <= band2 * (0.5 / 127 + 2 ** -10) + 1e-6)


def test_paths_outside_the_scene_are_refused(served, tmp_path):
    root, svc, get = served()
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP SECRET")
    (root / "ggds" / RUN / "plot.png").write_bytes(b"\x89PNG fake")
    os.symlink(secret, root / "ggds" / RUN / "link.txt")
    assert get(f"/files/ggds/{RUN}/plot.png")[:3:2] == (200, b"\x89PNG fake")
    assert get(f"/files/ggds/{RUN}/summary.json")[0] == 200
    attempts = [
        "/files/../secret.txt", "/files/ggds/../../secret.txt", "/../secret.txt", "/static/../../secret.txt",
        "/files/%2e%2e/secret.txt", "/files/%2E%2E%2Fsecret.txt", "/files/.%2e/secret.txt",
        "/files/%252e%252e/secret.txt", "/files/%252e%252e%252fsecret.txt", "/files/..%5csecret.txt",
        "/files/..\\secret.txt", f"/files/{secret}", f"/files/%2F{str(secret)[1:]}", "//etc/passwd",
        "/files//etc/passwd", "/files/%2fetc%2fpasswd", "/static/%2e%2e/%2e%2e/secret.txt",
        "/files/./scene.usda", "/files/C:/secret.txt", "/files/%00", f"/files/ggds/{RUN}/link.txt",
        "/files/layers/surfels.usdc", "/files/%ff%fe", "/api/envmap/..%2f..%2fsecret.txt",
    ]
    for path in attempts:
        status, _, body = get(path)
        assert status in (403, 404), path
        assert b"SECRET" not in body, path
    assert get("/files/../secret.txt")[0] == 403 and get("/files/%2e%2e/secret.txt")[0] == 403


def test_damaged_scene_opens_with_its_problems(tmp_path):
    root = tmp_path / "scene"
    make_scene(root, run=False)
    (root / "layers" / "surfels.usdc").write_bytes(b"PXR-USDC" + os.urandom(300))
    svc = ViewerService(root, validate=True)
    srv = make_server(svc, "127.0.0.1", 0, quiet=True)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        port = srv.server_address[1]

        def get(path):
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
            c.request("GET", path)
            r = c.getresponse()
            return r.status, r.read()
        assert get("/")[0] == 200
        status, body = get("/api/scene")
        problems = json.loads(body)["problems"]
        assert status == 200 and [p["where"] for p in problems] == ["layers/surfels.usdc"]
        assert "cannot be read as USD" in problems[0]["message"]
        status, body = get("/api/config")             # the rest of the scene still opens
        assert status == 200 and json.loads(body)["surfels"] == 0
        assert svc.validation_done.wait(120)
        problems = json.loads(get("/api/problems")[1])["problems"]
        assert any(p["severity"] == "error" for p in problems)
        assert all(set(p) == {"severity", "where", "message"} for p in problems)
    finally:
        srv.shutdown()
        srv.server_close()


def _view(*args, **kw):
    return subprocess.Popen([sys.executable, "-m", "lsd3d_usd", "view", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def test_cli_loopback_by_default_and_ctrl_c(tmp_path):
    root = tmp_path / "scene"
    make_scene(root, run=False)
    r = subprocess.run([sys.executable, "-m", "lsd3d_usd", "view", str(root), "--host", "0.0.0.0"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "--allow-remote" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run([sys.executable, "-m", "lsd3d_usd", "view", str(tmp_path / "nope")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stderr.strip().splitlines() == [f"lsd3d-usd: error: {tmp_path / 'nope'}: no such scene folder"]

    p = _view(root, "--host", "0.0.0.0", "--allow-remote", "--port", "0", "--no-validate")
    try:
        url = p.stdout.readline().strip()
        assert url.startswith("http://0.0.0.0:")
        port = int(url.rsplit(":", 1)[1].strip("/"))
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        c.request("GET", "/api/scene")
        assert c.getresponse().status == 200
        c.close()
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0
    assert "warning" in err and "0.0.0.0" in err and "stopped" in err
    assert "Traceback" not in err
