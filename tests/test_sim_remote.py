"""`sim serve` + `RemoteDriveEnv`: the closed-loop env over gRPC (sim.service, sim.remote).
An episode through the service equals the same seed in-process, array for array and score for
score; check_env passes on the client; the limits (busy, silent client, oversized or malformed
requests, loopback) answer with a status naming the field and the server keeps serving; a
client in its own venv (grpcio, protobuf, numpy, gymnasium only) drives an episode."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time

import grpc
import numpy as np
import pytest
from conftest import ROOT

SETTINGS = dict(rig="nuscenes6", width=64, seconds=1.0, vehicles=2, pedestrians=2, cyclists=1)
ACTION = np.array([1.5, 0.05], np.float32)


@pytest.fixture(scope="module")
def scene(sim_scene):
    return sim_scene          # conftest: one scene shared by the sim tests


@pytest.fixture(scope="module")
def server(scene):
    """(target, servicer) of a service in this process on a free loopback port."""
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.service import serve
    env = DriveEnv(scene, **SETTINGS)
    logs = []
    srv, servicer, port = serve(env, port=0, timeout=30.0, log=logs.append)
    servicer.logs = logs
    yield f"127.0.0.1:{port}", servicer
    servicer.stop()
    srv.stop(0).wait()
    env.close()


@pytest.fixture
def free_server(server):
    """The server with no session running (a test that leaves one would block the next)."""
    target, servicer = server
    servicer.session = ""
    yield target, servicer
    servicer.session = ""


def _same(a, b, where=""):
    if isinstance(a, dict):
        assert isinstance(b, dict) and sorted(a) == sorted(b), where   # Dict spaces sort keys
        for k in a:
            _same(a[k], b[k], f"{where}/{k}")
    else:
        assert type(a) is type(b), (where, type(a), type(b))
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape, where
            assert a.tobytes() == b.tobytes(), where
        else:
            assert np.asarray(a).tobytes() == np.asarray(b).tobytes(), where


def test_episode_equals_in_process(scene, free_server):
    """Byte-identical observations, the same rewards, flags, scores and info."""
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.remote import RemoteDriveEnv
    target, _ = free_server
    local = DriveEnv(scene, **SETTINGS)
    remote = RemoteDriveEnv(target)
    try:
        assert remote.observation_space == local.observation_space
        assert remote.action_space == local.action_space
        o1, i1 = local.reset(seed=7)
        o2, i2 = remote.reset(seed=7)
        _same(o1, o2)
        assert json.loads(json.dumps(i1)) == i2
        assert "lidar" in o2 and int(o2["lidar"]["count"]) > 0 and "CAM_FRONT" in o2["cameras"]
        steps = 0
        while True:
            r1, r2 = local.step(ACTION), remote.step(ACTION)
            steps += 1
            _same(r1[0], r2[0])
            assert r1[1:4] == r2[1:4]
            assert json.loads(json.dumps(r1[4]["scores"])) == r2[4]["scores"]
            assert json.loads(json.dumps(r1[4])) == r2[4]
            if r1[2] or r1[3]:
                break
        assert steps >= 5
    finally:
        remote.close()
        local.close()


def test_png_images_equal_raw(free_server):
    from lsd3d_usd.sim.remote import RemoteDriveEnv
    target, _ = free_server
    raw = RemoteDriveEnv(target)
    o1, _ = raw.reset(seed=3)
    raw.close()
    png = RemoteDriveEnv(target, png=True)
    o2, _ = png.reset(seed=3)
    png.close()
    _same(o1, o2)


def test_check_env_passes(free_server):
    from gymnasium.utils.env_checker import check_env

    from lsd3d_usd.sim.remote import RemoteDriveEnv
    env = RemoteDriveEnv(free_server[0])
    try:
        check_env(env, skip_render_check=True)
    finally:
        env.close()


def _stub(target, send_limit=None):
    from lsd3d_usd.sim.proto import sim_pb2_grpc
    opts = [("grpc.max_send_message_length", send_limit)] if send_limit else []
    ch = grpc.insecure_channel(target, options=opts)
    return ch, sim_pb2_grpc.DriveStub(ch)


def _status(fn):
    with pytest.raises(grpc.RpcError) as e:
        fn()
    return e.value.code(), e.value.details()


def test_busy_then_free_after_a_silent_client(free_server):
    """A second client is told "busy"; a client that goes silent (killed) loses its episode
    after the timeout and the next client drives."""
    from lsd3d_usd.sim.proto import sim_pb2
    target, servicer = free_server
    ch, stub = _stub(target)
    first = stub.Reset(sim_pb2.ResetRequest(seed=1))            # then never heard of again
    code, text = _status(lambda: stub.Reset(sim_pb2.ResetRequest(seed=2)))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "busy" in text
    servicer.timeout = 1.0
    try:
        time.sleep(2.5)
        second = stub.Reset(sim_pb2.ResetRequest(seed=2))
        assert second.session != first.session
        code, text = _status(lambda: stub.Step(sim_pb2.StepRequest(
            session=first.session, action=_action(ACTION))))
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "session" in text
        stub.Close(sim_pb2.CloseRequest(session=second.session))
        assert any("silent" in m for m in servicer.logs)
    finally:
        servicer.timeout = 30.0
        ch.close()


KILLED_CLIENT = """
import sys, time
import grpc
from lsd3d_usd.sim.proto import sim_pb2, sim_pb2_grpc
stub = sim_pb2_grpc.DriveStub(grpc.insecure_channel(sys.argv[1]))
print(stub.Reset(sim_pb2.ResetRequest(seed=3)).session, flush=True)
time.sleep(600)
"""


def test_a_killed_client_process_frees_the_server(free_server):
    """A client process killed (SIGKILL) mid-episode: the server is ready for the next client
    within --timeout."""
    from lsd3d_usd.sim.proto import sim_pb2
    target, servicer = free_server
    servicer.timeout = 1.0
    proc = subprocess.Popen([sys.executable, "-c", KILLED_CLIENT, target], stdout=subprocess.PIPE,
                            text=True)
    ch, stub = _stub(target)
    try:
        killed = proc.stdout.readline().strip()
        assert killed
        code, text = _status(lambda: stub.Reset(sim_pb2.ResetRequest(seed=4)))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "busy" in text
        proc.kill()
        proc.wait(10)
        time.sleep(2.5)                              # > the timeout
        nxt = stub.Reset(sim_pb2.ResetRequest(seed=4))
        assert nxt.session and nxt.session != killed
        ok = stub.Step(sim_pb2.StepRequest(session=nxt.session, action=_action(ACTION)))
        assert len(ok.observation.tensors) > 0
        stub.Close(sim_pb2.CloseRequest(session=nxt.session))
    finally:
        servicer.timeout = 30.0
        if proc.poll() is None:
            proc.kill()
        ch.close()


def test_a_1_gb_message_is_refused_and_the_server_serves_on(free_server):
    from lsd3d_usd.sim.proto import sim_pb2
    target, _ = free_server
    ch, stub = _stub(target, send_limit=2**31 - 1)
    try:
        s = stub.Reset(sim_pb2.ResetRequest(seed=0)).session
        huge = _action(np.zeros((1 << 28,), np.float32))          # 1 GiB of action
        code, text = _status(lambda: stub.Step(sim_pb2.StepRequest(session=s, action=huge)))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, text
        del huge
        ok = stub.Step(sim_pb2.StepRequest(session=s, action=_action(ACTION)))
        assert len(ok.observation.tensors) > 0
        stub.Close(sim_pb2.CloseRequest(session=s))
    finally:
        ch.close()


def _action(a, **fields):
    from lsd3d_usd.sim.remote import encode
    t = encode("action", a)
    for k, v in fields.items():
        setattr(t, k, v) if k != "shape" else (t.ClearField("shape"), t.shape.extend(v))
    return t


def test_malformed_and_oversized_requests(free_server):
    """Each bad request gets a status naming its field; the episode goes on after them."""
    from lsd3d_usd.sim.proto import sim_pb2
    target, _ = free_server
    ch, stub = _stub(target, send_limit=64 << 20)
    try:
        s = stub.Reset(sim_pb2.ResetRequest(seed=0)).session
        bad = {
            "action.shape": _action(np.zeros((3,), np.float32)),
            "action.dtype": _action(ACTION, dtype="|O"),
            "action.data": _action(ACTION, data=b"\x00" * 5),
        }
        for field, t in bad.items():
            code, text = _status(lambda: stub.Step(sim_pb2.StepRequest(session=s, action=t)))
            assert code == grpc.StatusCode.INVALID_ARGUMENT and field in text, (field, text)
        code, text = _status(lambda: stub.Step(sim_pb2.StepRequest(session=s, action=_action(
            ACTION, dtype="<U2"))))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "action.dtype" in text
        code, text = _status(lambda: stub.Step(sim_pb2.StepRequest(session=s)))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "action" in text
        # 8 MB of action: refused by the receive limit before it is parsed
        big = _action(np.zeros((1 << 21,), np.float32))
        code, text = _status(lambda: stub.Step(sim_pb2.StepRequest(session=s, action=big)))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, text
        # bytes that are not a StepRequest at all
        raw = ch.unary_unary("/lsd3d_usd.sim.v1.Drive/Step")
        code, text = _status(lambda: raw(b"\xff\xff\xff\xff"))
        assert code in (grpc.StatusCode.INTERNAL, grpc.StatusCode.INVALID_ARGUMENT), text
        # a client's route is lane ids only: a path is refused, never opened
        code, text = _status(lambda: stub.Reset(sim_pb2.ResetRequest(session=s, route=["../x/y"])))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "route" in text
        code, text = _status(lambda: stub.Reset(sim_pb2.ResetRequest(session=s, speed=float("nan"))))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "speed" in text
        code, text = _status(lambda: stub.Reset(sim_pb2.ResetRequest(session=s, route=["nolane"])))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "nolane" in text
        # still serving: the episode steps on
        ok = stub.Step(sim_pb2.StepRequest(session=s, action=_action(ACTION)))
        assert len(ok.observation.tensors) > 0
        stub.Close(sim_pb2.CloseRequest(session=s))
    finally:
        ch.close()


def test_loopback_unless_allowed(scene, cli_error):
    from lsd3d_usd.errors import InputError
    from lsd3d_usd.sim.service import check_options, is_loopback
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.4")
    with pytest.raises(InputError, match="--allow-remote"):
        check_options("0.0.0.0", False, 60.0, 64.0)
    said = []
    check_options("0.0.0.0", True, 60.0, 64.0, said.append)
    assert "WARNING" in said[0]
    cli_error(["sim", "serve", scene, "--host", "0.0.0.0"], "--host 0.0.0.0", "--allow-remote")
    cli_error(["sim", "serve", scene, "--timeout", "0"], "--timeout")


CLIENT = r"""
import json, sys
import numpy as np
from gymnasium.utils.env_checker import check_env
from lsd3d_usd.sim.remote import RemoteDriveEnv
for banned in ("torch", "pxr", "numba"):
    assert banned not in sys.modules, banned
env = RemoteDriveEnv(sys.argv[1])
check_env(env, skip_render_check=True)
obs, info = env.reset(seed=4)
steps, done = 0, False
while not done:
    obs, reward, term, trunc, info = env.step(np.array([1.0, 0.0], np.float32))
    steps += 1
    done = term or trunc
env.close()
for banned in ("torch", "pxr", "numba"):
    assert banned not in sys.modules, banned
print(json.dumps({"steps": steps, "scores": info["scores"], "rgb": list(obs["cameras"]["CAM_FRONT"]["rgb"].shape)}))
"""


def test_client_in_its_own_venv(scene, tmp_path):
    """A policy in a venv with only grpcio, protobuf, numpy and gymnasium (from PyPI) drives
    an episode against `lsd3d-usd sim serve` started from this venv."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    pip = subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                          "grpcio", "protobuf", "numpy", "gymnasium"],
                         capture_output=True, text=True, timeout=600)
    if pip.returncode:
        pytest.skip(f"PyPI not reachable: {pip.stderr.strip().splitlines()[-1:]}")
    probe = subprocess.run([str(py), "-c", "import torch"], capture_output=True)
    assert probe.returncode != 0                      # really not this project's venv
    # the client's files only, in the package layout (the package's own __init__ needs USD)
    lib = tmp_path / "client"
    src = ROOT / "lsd3d_usd"
    for rel in ("sim/remote.py", "sim/proto/__init__.py", "sim/proto/sim_pb2.py",
                "sim/proto/sim_pb2_grpc.py"):
        (lib / "lsd3d_usd" / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(src / rel, lib / "lsd3d_usd" / rel)
    for pkg in ("lsd3d_usd", "lsd3d_usd/sim"):
        (lib / pkg / "__init__.py").write_text("")
    srv = subprocess.Popen([sys.executable, "-m", "lsd3d_usd.cli", "sim", "serve", str(scene),
                            "--port", "0", "--no-reference", "--rig", "nuscenes6", "--width", "64",
                            "--seconds", "1", "--vehicles", "2", "--pedestrians", "2",
                            "--cyclists", "1", "--timeout", "20"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        line = srv.stdout.readline()
        assert " on 127.0.0.1:" in line, (line, srv.stderr.read() if srv.poll() is not None else "")
        target = line.split(" on ")[1].split()[0]
        out = subprocess.run([str(py), "-c", CLIENT, target], capture_output=True, text=True,
                             timeout=300, env={"PYTHONPATH": str(lib), "PATH": os.environ["PATH"]},
                             cwd=tmp_path)
        assert out.returncode == 0, out.stderr
        got = json.loads(out.stdout.strip().splitlines()[-1])
        assert 1 <= got["steps"] <= 10 and got["scores"] and got["rgb"][1:] == [64, 3]
    finally:
        srv.terminate()
        srv.wait(30)


# ---- the live view: a WebSocket client in a few lines (no client library in the project)
def _ws_connect(port: int):
    import base64
    import socket
    s = socket.create_connection(("127.0.0.1", port), timeout=20)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
               "Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    assert b" 101 " in head.split(b"\r\n")[0], head
    return s


def _recv_exact(s, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = s.recv(n - len(out))
        assert chunk, "connection closed"
        out += chunk
    return out


def _ws_recv(s):
    """(opcode, payload) of the next data frame (server frames: unmasked, unfragmented)."""
    while True:
        b0, b1 = _recv_exact(s, 2)
        n = b1 & 0x7F
        if n == 126:
            n = int.from_bytes(_recv_exact(s, 2), "big")
        elif n == 127:
            n = int.from_bytes(_recv_exact(s, 8), "big")
        data = _recv_exact(s, n)
        if b0 & 0x0F in (1, 2):
            return b0 & 0x0F, data


def _ws_send_text(s, text: str):
    data = text.encode()
    mask = os.urandom(4)
    head = bytes([0x81]) + (bytes([0x80 | len(data)]) if len(data) < 126
                            else bytes([0x80 | 126]) + len(data).to_bytes(2, "big"))
    s.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))


def _decoder(channel: dict):
    import base64

    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def test_live_view_streams_foxglove_messages(scene):
    """A WebSocket client subscribes to the live view and receives images, a point cloud,
    transforms, boxes and the scores, each decoding with its advertised Foxglove schema."""
    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.live import LiveView
    env = DriveEnv(scene, **SETTINGS)
    view = LiveView(port=0)
    ws = _ws_connect(view.port)
    try:
        obs, info = env.reset(seed=2)
        stream = view.episode(env, 0)
        stream.write(obs, info)
        channels = {}
        while not {"/tf", "/LIDAR_TOP", "/CAM_FRONT/image", "/sim/scores"} <= \
                {c["topic"] for c in channels.values()}:
            op, data = _ws_recv(ws)
            if op == 1:
                m = json.loads(data)
                if m.get("op") == "advertise":
                    channels.update({c["id"]: c for c in m["channels"]})
        subs = {k + 1: c for k, c in enumerate(channels.values())}
        _ws_send_text(ws, json.dumps({"op": "subscribe", "subscriptions": [
            {"id": sid, "channelId": c["id"]} for sid, c in subs.items()]}))
        time.sleep(0.5)                       # the server takes the subscription
        for _ in range(2):
            obs, _, _, _, info = env.step(ACTION)
            stream.write(obs, info)
        got = {}
        deadline = time.monotonic() + 20
        want = {"/tf", "/LIDAR_TOP", "/CAM_FRONT/image", "/sim/scores", "/markers/annotations"}
        while not want <= set(got) and time.monotonic() < deadline:
            op, data = _ws_recv(ws)
            if op == 2 and data[0] == 1:      # messageData: subscription id, log time, payload
                c = subs[int.from_bytes(data[1:5], "little")]
                payload = data[13:]
                if c["encoding"] == "json":
                    got[c["topic"]] = json.loads(payload)
                else:
                    got[c["topic"]] = _decoder(c).FromString(payload)
        assert want <= set(got), sorted(got)
        assert got["/tf"].child_frame_id == "ego" and got["/tf"].parent_frame_id
        assert got["/CAM_FRONT/image"].format in ("jpeg", "png") and got["/CAM_FRONT/image"].data
        cloud = got["/LIDAR_TOP"]
        assert cloud.point_stride > 0 and len(cloud.data) % cloud.point_stride == 0
        assert [f.name for f in cloud.fields][:3] == ["x", "y", "z"] and len(cloud.data) > 0
        assert "pdms" in got["/sim/scores"] and got["/sim/scores"]["step"] >= 1
    finally:
        ws.close()
        view.close()
        env.close()


def test_importing_the_simulator_turns_grpc_fork_handlers_off_unless_told():
    """grpcio's fork handlers kill subprocesses forked beside live channels (grpc#43055):
    `import lsd3d_usd.sim` turns them off before grpc loads, and leaves a user's own setting."""
    import subprocess
    import sys
    code = "import lsd3d_usd.sim, os, grpc; print(os.environ['GRPC_ENABLE_FORK_SUPPORT'])"
    env = {k: v for k, v in os.environ.items() if k != "GRPC_ENABLE_FORK_SUPPORT"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and out.stdout.split()[-1] == "false", out.stderr[-500:]
    out = subprocess.run([sys.executable, "-c", code], env={**env, "GRPC_ENABLE_FORK_SUPPORT": "1"},
                         capture_output=True, text=True, timeout=120)
    assert out.stdout.split()[-1] == "1"
