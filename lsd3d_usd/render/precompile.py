"""Compile the rasteriser's backward kernels in a second process while a first `generate`
does everything before them.

numba compiles a kernel the first time it is called and caches it on disk; compiling is
serial, so on a fresh install `generate` spends most of its first minute compiling one
kernel after another on one core. The backward kernels (`kernels_prep.project_backward`,
`kernels.backward`: ~19 of ~51 s) are first called by GGDS's first step, after the proxy,
the surfels, the G-buffers and the colour start. `start` launches a process that renders a
tiny field forward and backward, with the settings GGDS renders with, and exits: numba
writes what it compiled to the same on-disk cache (its writes are atomic), so when GGDS
reaches its first step the main process loads the kernels instead of compiling them. The
second process also compiles the forward kernels it needs on the way; where both
processes compile one, the main process is no slower than alone.

Nothing happens when the backward kernels are already cached (every run after the first),
when numba's cache cannot be located, or with ``LSD3D_PRECOMPILE=0``.
"""
from __future__ import annotations

import os
import subprocess
import sys

ENV_SWITCH = "LSD3D_PRECOMPILE"


def _cached(dispatcher) -> bool | None:
    """Whether numba's on-disk cache holds any compiled version of ``dispatcher`` (None:
    unknown, e.g. caching off or a numba whose cache layout differs)."""
    try:
        path = dispatcher._cache._cache_file._index_path
    except AttributeError:
        return None
    return os.path.exists(path)


def backward_cold() -> bool:
    """True when the rasteriser's backward kernels are known not to be cached yet."""
    from lsd3d_usd.render import kernels, kernels_prep
    got = [_cached(kernels_prep.project_backward), _cached(kernels.backward)]
    return all(g is not None for g in got) and not all(got)


def start() -> subprocess.Popen | None:
    """Launch the background compile if it is useful (see the module doc); the process, or
    None. Its output is discarded: the main process reports compiling as before."""
    if os.environ.get(ENV_SWITCH, "1") == "0" or not backward_cold():
        return None
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", **{ENV_SWITCH: "0"})
    try:
        return subprocess.Popen([sys.executable, "-m", "lsd3d_usd.render.precompile"],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, env=env, close_fds=True)
    except OSError:
        return None


def finish(proc: subprocess.Popen | None, timeout: float = 1.0) -> None:
    """Stop the background compile if it still runs (the main process needs it no more)."""
    if proc is None:
        return
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def compile_backward() -> None:
    """Render a tiny field forward and backward (the signatures GGDS's steps use: float32
    tensors, SH; without the depth-distortion output, whose loss weight is 0 by default)."""
    import numpy as np
    import torch

    from lsd3d_usd.render.raster_types import RasterSettings
    from lsd3d_usd.render.rasterize import rasterize
    rng = np.random.default_rng(0)
    n = 64
    means = rng.uniform(-1.0, 1.0, (n, 3))
    means[:, 2] += 4.0
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    arrays = [means, q, rng.uniform(0.05, 0.2, (n, 2)), rng.uniform(0.2, 0.9, n),
              rng.normal(size=(n, 16, 3)) * 0.1]
    K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    ts = [torch.tensor(a, dtype=torch.float32, requires_grad=True) for a in arrays]
    out = rasterize(*ts, torch.eye(4), K, 32, 32, settings=RasterSettings(),
                    background=torch.full((3,), 0.5))
    (out.rgb.sum() + out.depth_median.sum() + out.normal.sum() + out.alpha.sum()).backward()


if __name__ == "__main__":
    compile_backward()
