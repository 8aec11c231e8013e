"""`lsd3d-usd sim serve`: a `DriveEnv` behind gRPC (proto/sim.proto) for a driving stack in
its own process; `sim.remote.RemoteDriveEnv` is the Gymnasium client (docs/sim.md).

One episode at a time: Reset without a session opens one (refused as RESOURCE_EXHAUSTED
"busy" while another client's runs); every later call carries the session id. A client
silent for ``timeout`` seconds loses its session, so a killed client frees the server.
Requests are bounded (REQUEST_LIMIT bytes, grpc refuses larger ones) and checked field by
field; a bad one gets INVALID_ARGUMENT naming the field and the server keeps serving. The
client sends lane ids and numbers only: no path it sends is ever opened.
"""
from __future__ import annotations

import ipaddress
import math
import re
import secrets
import sys
import threading
import time
from concurrent import futures
from dataclasses import asdict

import grpc

from lsd3d_usd.errors import InputError
from lsd3d_usd.sim.proto import sim_pb2, sim_pb2_grpc
from lsd3d_usd.sim.remote import (REQUEST_LIMIT, TensorError, decode, encode_obs, space_to_msg,
                                  to_json)

LANE_ID = re.compile(r"^[A-Za-z0-9_.:\-]{1,128}$")   # lane ids: never a path separator
MAX_ROUTE = 1000


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class _Refused(Exception):
    def __init__(self, code, text):
        super().__init__(text)
        self.code, self.text = code, text


class DriveServicer(sim_pb2_grpc.DriveServicer):
    def __init__(self, env, timeout: float = 60.0, reply_limit: int = 64 << 20, log=None,
                 live=None):
        self.env = env
        self.live, self._stream, self._episodes = live, None, 0   # sim.live.LiveView
        self.timeout = float(timeout)
        self.reply_limit = int(reply_limit)
        self.log = log or (lambda m: print(m, file=sys.stderr, flush=True))
        self.lock = threading.Lock()          # the env is one episode, one caller at a time
        self.env_lock = threading.Lock()      # one env call at a time, even from one client
        self.session = ""
        self.last = 0.0                       # monotonic time of the session's last call
        self.busy_calls = 0                   # calls of the session in flight
        self._spaces = sim_pb2.SpacesReply(
            observation=space_to_msg(env.observation_space), action=space_to_msg(env.action_space),
            hz=float(env.settings.hz),
            settings_json=to_json({k: v for k, v in asdict(env.settings).items()}))
        self._stop = threading.Event()
        threading.Thread(target=self._watch, daemon=True, name="sim-serve-timeout").start()

    # ---- sessions
    def _watch(self):
        while not self._stop.wait(min(1.0, self.timeout / 4)):
            with self.lock:
                self._expire()

    def _expire(self):
        # called with self.lock held
        if self.session and not self.busy_calls and time.monotonic() - self.last > self.timeout:
            self.log(f"sim serve: session {self.session[:8]} silent for {self.timeout:g} s: "
                     "its episode ends")
            self.session = ""

    def _enter(self, session: str, opening: bool = False):
        with self.lock:
            self._expire()
            if opening and not session:
                if self.session:
                    raise _Refused(grpc.StatusCode.RESOURCE_EXHAUSTED,
                                   "busy: another client's episode is running (a silent client "
                                   f"loses it after {self.timeout:g} s)")
                self.session = secrets.token_hex(16)
                self.log(f"sim serve: session {self.session[:8]} opened")
            elif not session or session != self.session:
                raise _Refused(grpc.StatusCode.FAILED_PRECONDITION,
                               "session: not the running session (closed, timed out, or "
                               "never opened: call Reset first)")
            self.busy_calls += 1
            self.last = time.monotonic()
            return self.session

    def _leave(self):
        with self.lock:
            self.busy_calls -= 1
            self.last = time.monotonic()

    def _call(self, context, fn):
        try:
            return fn()
        except _Refused as e:
            context.abort(e.code, e.text)
        except (InputError, TensorError) as e:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
        except Exception as e:                        # the server keeps serving
            self.log(f"sim serve: {type(e).__name__}: {e}")
            context.abort(grpc.StatusCode.INTERNAL, f"{type(e).__name__}: {e}")

    def _reply(self, msg):
        n = msg.ByteSize()
        if n > self.reply_limit:
            raise _Refused(grpc.StatusCode.RESOURCE_EXHAUSTED,
                           f"observation: {n} bytes exceed --max-message-mb "
                           f"({self.reply_limit / 2**20:g} MB); fewer cameras or a smaller --width")
        return msg

    # ---- rpcs
    def Spaces(self, request, context):
        return self._spaces

    def Reset(self, request, context):
        def run():
            options = {}
            if request.route:
                if len(request.route) > MAX_ROUTE:
                    raise InputError(f"route: {len(request.route)} lane ids (at most {MAX_ROUTE})")
                bad = [r for r in request.route if not LANE_ID.match(r)]
                if bad:
                    raise InputError(f"route: {bad[0][:40]!r} is not a lane id")
                options["route"] = list(request.route)
            for k in ("start", "speed"):
                if request.HasField(k):
                    v = getattr(request, k)
                    if not math.isfinite(v):
                        raise InputError(f"{k}: {v} is not a finite number")
                    options[k] = v
            seed = request.seed if request.HasField("seed") else None
            if seed is not None and seed < 0:
                raise InputError(f"seed: {seed} must be >= 0")
            session = self._enter(request.session, opening=True)
            try:
                with self.env_lock:
                    obs, info = self.env.reset(seed=seed, options=options)
                    if self.live is not None:
                        self._stream = self.live.episode(self.env, self._episodes)
                        self._episodes += 1
                        self._stream.write(obs, info)
                return self._reply(sim_pb2.ResetReply(
                    session=session, observation=encode_obs(self.env.observation_space, obs,
                                                            request.png),
                    info_json=to_json(info)))
            except Exception:
                if not request.session:        # a session that never started is not kept
                    with self.lock:
                        if self.session == session:
                            self.session = ""
                raise
            finally:
                self._leave()
        return self._call(context, run)

    def Step(self, request, context):
        def run():
            if not request.HasField("action"):
                raise InputError("action: missing")
            a = decode(request.action, "action")
            shape = self.env.action_space.shape
            if a.shape != shape:
                raise InputError(f"action.shape: {list(a.shape)}, expected {list(shape)} "
                                 f"({self.env.settings.action} mode)")
            if a.dtype.kind not in "iuf":
                raise InputError(f"action.dtype: {a.dtype.name}, expected a number type")
            self._enter(request.session)
            try:
                with self.env_lock:
                    obs, reward, term, trunc, info = self.env.step(a)
                    if self._stream is not None:
                        self._stream.write(obs, info)
                info = dict(info)
                scores = info.pop("scores")
                return self._reply(sim_pb2.StepReply(
                    observation=encode_obs(self.env.observation_space, obs, request.png),
                    reward=float(reward), terminated=bool(term), truncated=bool(trunc),
                    scores_json=to_json(scores), info_json=to_json(info)))
            finally:
                self._leave()
        return self._call(context, run)

    def Close(self, request, context):
        def run():
            with self.lock:
                if request.session and request.session == self.session:
                    self.log(f"sim serve: session {self.session[:8]} closed")
                    self.session = ""
            return sim_pb2.CloseReply()
        return self._call(context, run)

    def stop(self):
        self._stop.set()


def check_options(host: str, allow_remote: bool, timeout: float, max_message_mb: float,
                  log=None) -> None:
    """Refuse a listening address beyond loopback without ``allow_remote`` (warn with it)."""
    if not is_loopback(host):
        if not allow_remote:
            raise InputError(f"--host {host}: not a loopback address; add --allow-remote to "
                             "serve other machines")
        if log:
            log(f"sim serve: WARNING: listening on {host}: any machine that reaches it can "
                "drive (no authentication, no encryption)")
    if not (0.0 < timeout <= 86400.0):
        raise InputError(f"--timeout {timeout}: must be within (0, 86400] s")
    if not (1.0 <= max_message_mb <= 2047.0):
        raise InputError(f"--max-message-mb {max_message_mb}: must be within 1 .. 2047")


def serve(env, host: str = "127.0.0.1", port: int = 50051, allow_remote: bool = False,
          timeout: float = 60.0, max_message_mb: float = 64.0, log=None, workers: int = 4,
          live=None):
    """Start the service on (host, port); returns (grpc server, servicer, bound port).
    ``port`` 0 picks a free one."""
    log = log or (lambda m: print(m, file=sys.stderr, flush=True))
    check_options(host, allow_remote, timeout, max_message_mb, log)
    limit = int(max_message_mb * 2**20)
    servicer = DriveServicer(env, timeout, limit, log, live)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=workers), options=[
        ("grpc.max_receive_message_length", REQUEST_LIMIT),
        ("grpc.max_send_message_length", limit)])
    sim_pb2_grpc.add_DriveServicer_to_server(servicer, server)
    addr = f"[{host}]" if ":" in host and not host.startswith("[") else host
    try:
        bound = server.add_insecure_port(f"{addr}:{port}")
    except RuntimeError:
        bound = 0
    if bound == 0:
        servicer.stop()
        raise InputError(f"--port {port}: cannot listen on {host}:{port} (in use?)")
    server.start()
    return server, servicer, bound
