"""Closed loop: a driving policy drives in a generated scene (docs/sim.md).

``import lsd3d_usd.sim`` registers the Gymnasium environment ``lsd3d_usd/Drive-v0``
(`env.DriveEnv`): ``gymnasium.make("lsd3d_usd/Drive-v0", scene="out/crossing")``.
`RemoteDriveEnv` (sim.remote) is the same API over `lsd3d-usd sim serve` (gRPC).
"""
from __future__ import annotations

import os

ENV_ID = "lsd3d_usd/Drive-v0"

# Before grpc loads (sim.service, sim.remote): with a gRPC server or channel alive, grpcio's fork
# handlers (1.80 on, grpc/grpc#43055) restart its poller in a subprocess forked before exec, on
# an epoll descriptor Popen has closed, and the child dies: ffmpeg writing an episode's video
# ended with a broken pipe and "epoll_wait error: Bad file descriptor". Nothing here forks a
# process that uses gRPC, so the handlers are off unless the environment says otherwise.
os.environ.setdefault("GRPC_ENABLE_FORK_SUPPORT", "false")


def _register() -> None:
    import gymnasium   # the env's API; imported here, not by `lsd3d-usd --help`
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="lsd3d_usd.sim.env:DriveEnv",
                           disable_env_checker=False)


_register()


def __getattr__(name):
    if name == "RemoteDriveEnv":      # grpc is imported only by who uses it
        from lsd3d_usd.sim.remote import RemoteDriveEnv
        return RemoteDriveEnv
    raise AttributeError(name)
