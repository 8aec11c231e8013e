"""`RemoteDriveEnv`: the Gymnasium API over `lsd3d-usd sim serve` (gRPC, proto/sim.proto), so
one policy runs in-process (`DriveEnv`) or in its own process and virtual environment.

This module imports only grpcio, protobuf, numpy, gymnasium and the generated stubs (no torch,
no USD): a client needs ``pip install grpcio protobuf numpy gymnasium`` and the files
lsd3d_usd/sim/remote.py + lsd3d_usd/sim/proto/ (docs/sim.md, "Remote stacks"). The codec here
(arrays <-> Tensor, spaces <-> Space) is the server's too, so both ends agree by construction.
"""
from __future__ import annotations

import json

import grpc
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lsd3d_usd.sim.proto import sim_pb2, sim_pb2_grpc

# numeric kinds only: bool, signed, unsigned, float (an "O" dtype could smuggle objects)
DTYPE_KINDS = "biuf"
MAX_DIMS = 8
REQUEST_LIMIT = 1 << 20     # bytes: a request is an action and reset options, never larger
DEFAULT_REPLY_LIMIT = 256 << 20


class TensorError(ValueError):
    """A Tensor that does not decode; the message names the field."""


# ---- arrays
def encode(name: str, a, png: bool = False) -> sim_pb2.Tensor:
    a = np.asarray(a)
    if png and a.dtype == np.uint8 and (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        import io

        from PIL import Image            # server side only (pillow is a project dependency)
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(a)).save(buf, "PNG", compress_level=1)
        return sim_pb2.Tensor(name=name, dtype=a.dtype.str, shape=a.shape, data=buf.getvalue(),
                              encoding=sim_pb2.Tensor.PNG)
    # asarray, not ascontiguousarray: that one turns a scalar (shape ()) into shape (1,)
    a = np.asarray(a, a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else None, order="C")
    return sim_pb2.Tensor(name=name, dtype=a.dtype.str, shape=a.shape, data=a.tobytes())


def decode(t: sim_pb2.Tensor, field: str = "tensor") -> np.ndarray:
    """The array of a Tensor; TensorError naming ``field`` when it is not a sound one."""
    try:
        dt = np.dtype(t.dtype)
    except TypeError:
        raise TensorError(f"{field}.dtype: {t.dtype[:40]!r} is not a numpy dtype") from None
    if dt.kind not in DTYPE_KINDS or dt.subdtype is not None or dt.names:
        raise TensorError(f"{field}.dtype: {t.dtype[:40]!r} is not a plain numeric dtype")
    shape = tuple(int(s) for s in t.shape)
    if len(shape) > MAX_DIMS or any(s < 0 for s in shape):
        raise TensorError(f"{field}.shape: {list(shape)[:MAX_DIMS + 1]} is not a shape")
    if t.encoding == sim_pb2.Tensor.PNG:
        import io

        from PIL import Image            # only a client asking for PNG needs pillow
        try:
            a = np.asarray(Image.open(io.BytesIO(t.data)))
        except Exception:
            raise TensorError(f"{field}.data: not a PNG image") from None
        if a.shape != shape or a.dtype != dt:
            raise TensorError(f"{field}.data: a PNG of {a.shape} {a.dtype}, expected {shape} {dt}")
        return a
    if t.encoding != sim_pb2.Tensor.RAW:
        raise TensorError(f"{field}.encoding: unknown {t.encoding}")
    n = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    if len(t.data) != n:
        raise TensorError(f"{field}.data: {len(t.data)} bytes, shape {list(shape)} of "
                          f"{dt.name} needs {n}")
    return np.frombuffer(t.data, dt.newbyteorder("<")).astype(dt.newbyteorder("="), copy=True) \
        .reshape(shape)


def _leaves(space: spaces.Space, prefix: str = ""):
    if isinstance(space, spaces.Dict):
        for k, sub in space.spaces.items():
            yield from _leaves(sub, f"{prefix}{k}/")
    else:
        yield prefix[:-1], space


def encode_obs(space: spaces.Dict, obs: dict, png: bool = False) -> sim_pb2.Observation:
    out = sim_pb2.Observation()
    for name, sub in _leaves(space):
        v = obs
        for k in name.split("/"):
            v = v[k]
        dtype = np.int64 if isinstance(sub, spaces.Discrete) else None
        out.tensors.append(encode(name, np.asarray(v, dtype), png))
    return out


def decode_obs(space: spaces.Dict, msg: sim_pb2.Observation) -> dict:
    """The nested dict of an Observation, its leaves typed as the in-process env's: numpy
    arrays, numpy scalars for shape (), int for a Discrete."""
    got = {t.name: t for t in msg.tensors}
    obs: dict = {}
    for name, sub in _leaves(space):
        if name not in got:
            raise TensorError(f"observation: no tensor {name!r}")
        a = decode(got[name], f"observation[{name}]")
        v = int(a) if isinstance(sub, spaces.Discrete) else (a[()] if a.shape == () else a)
        d = obs
        *parents, leaf = name.split("/")
        for k in parents:
            d = d.setdefault(k, {})
        d[leaf] = v
    return obs


# ---- spaces
def _bound(name: str, a: np.ndarray) -> sim_pb2.Tensor:
    flat = a.reshape(-1)
    # most bounds are one value (an image's 0 .. 255): send it once, broadcast on arrival
    if flat.size and np.array_equal(flat, np.full_like(flat, flat[0]), equal_nan=True):
        return encode(name, flat[0])
    return encode(name, a)


def space_to_msg(space: spaces.Space) -> sim_pb2.Space:
    if isinstance(space, spaces.Dict):
        return sim_pb2.Space(dict=sim_pb2.DictSpace(children=[
            sim_pb2.NamedSpace(name=k, space=space_to_msg(s)) for k, s in space.spaces.items()]))
    if isinstance(space, spaces.Discrete):
        return sim_pb2.Space(discrete=sim_pb2.Discrete(n=int(space.n), start=int(space.start)))
    if isinstance(space, spaces.Box):
        return sim_pb2.Space(box=sim_pb2.Box(shape=space.shape, dtype=space.dtype.str,
                                             low=_bound("low", space.low),
                                             high=_bound("high", space.high)))
    raise TypeError(f"space {type(space).__name__}: only Box, Discrete and Dict travel")


def msg_to_space(msg: sim_pb2.Space, field: str = "space") -> spaces.Space:
    kind = msg.WhichOneof("kind")
    if kind == "dict":
        return spaces.Dict({c.name: msg_to_space(c.space, f"{field}/{c.name}")
                            for c in msg.dict.children})
    if kind == "discrete":
        return spaces.Discrete(int(msg.discrete.n), start=int(msg.discrete.start))
    if kind == "box":
        b = msg.box
        shape = tuple(int(s) for s in b.shape)
        dt = np.dtype(b.dtype)
        low = np.broadcast_to(decode(b.low, f"{field}.low"), shape).astype(dt)
        high = np.broadcast_to(decode(b.high, f"{field}.high"), shape).astype(dt)
        return spaces.Box(low, high, shape, dt)
    raise TensorError(f"{field}: no kind")


def _json_default(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"{type(v).__name__} is not JSON")


def to_json(d) -> str:
    return json.dumps(d, default=_json_default)


# ---- the client
class RemoteDriveEnv(gym.Env):
    """`DriveEnv` in another process: ``RemoteDriveEnv("127.0.0.1:50051")`` against
    `lsd3d-usd sim serve`. reset/step/close as the in-process env, the same spaces,
    observations and info (info travels as JSON: tuples arrive as lists).

    ``deadline``: seconds a call may take (a step renders every sensor); ``png``: images as
    PNG (less traffic, needs pillow here); ``max_message_mb``: the largest reply accepted."""

    metadata = {"render_modes": [], "render_fps": 10}

    def __init__(self, target: str = "127.0.0.1:50051", deadline: float = 300.0,
                 png: bool = False, max_message_mb: float = DEFAULT_REPLY_LIMIT / 2**20):
        self.target, self.deadline, self.png = target, float(deadline), bool(png)
        self.render_mode = None
        self._channel = grpc.insecure_channel(target, options=[
            ("grpc.max_receive_message_length", int(max_message_mb * 2**20)),
            ("grpc.max_send_message_length", REQUEST_LIMIT)])
        self._stub = sim_pb2_grpc.DriveStub(self._channel)
        self._session = ""
        r = self._stub.Spaces(sim_pb2.SpacesRequest(), timeout=self.deadline)
        self.observation_space = msg_to_space(r.observation, "observation")
        self.action_space = msg_to_space(r.action, "action")
        self.settings = json.loads(r.settings_json) if r.settings_json else {}
        self.metadata = dict(self.metadata, render_fps=r.hz)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = sorted(set(options) - {"route", "start", "speed"})
        if unknown:
            raise ValueError(f"reset options: unknown key {unknown[0]!r} (route, start, speed)")
        route = options.get("route") or []
        if isinstance(route, str):
            route = [r for r in route.split(",")]
        req = sim_pb2.ResetRequest(session=self._session, route=[str(r).strip() for r in route
                                                                  if str(r).strip()],
                                   png=self.png)
        if seed is not None:
            req.seed = int(seed)
        for k in ("start", "speed"):
            if options.get(k) is not None:
                setattr(req, k, float(options[k]))
        r = self._stub.Reset(req, timeout=self.deadline)
        self._session = r.session
        return decode_obs(self.observation_space, r.observation), json.loads(r.info_json)

    def step(self, action):
        a = np.asarray(action, self.action_space.dtype)
        r = self._stub.Step(sim_pb2.StepRequest(session=self._session, action=encode("action", a),
                                                png=self.png), timeout=self.deadline)
        info = json.loads(r.info_json)
        info["scores"] = json.loads(r.scores_json)
        return (decode_obs(self.observation_space, r.observation), float(r.reward),
                bool(r.terminated), bool(r.truncated), info)

    def close(self):
        ch, self._channel = getattr(self, "_channel", None), None
        if ch is None:
            return
        try:
            if self._session:
                self._stub.Close(sim_pb2.CloseRequest(session=self._session), timeout=10.0)
        except grpc.RpcError:
            pass                     # the server is gone or already ended the session
        finally:
            self._session = ""
            ch.close()
