"""Compile the rasteriser's kernels in a second process while a first `generate` does
everything before them.

numba compiles a kernel the first time it is called and caches it on disk; compiling is
serial, so on a fresh install `generate` would spend its first ~50 s compiling one kernel
after another on one core. The rasteriser's kernels (the forward's `project_visible`,
`bin_sorted`, `forward`, the backward's `project_backward`, `backward`: ~31 of those s,
docs/render.md "First run") are first called after the proxy, the surfels and the
conditioning's own kernels. `start` (called by `generate` as soon as it has read its
options) launches a process that renders a tiny field forward, says so on its
stdout, then backward, says so, and exits; numba writes what it compiled to the same
on-disk cache (its writes are atomic). The main process, meanwhile compiling the other
kernels on the other core, waits at its first rasterisation for the second process's
forward (`wait_until`, called by the numba backend) and at its first backward for its
backward, then loads the kernels from the cache instead of compiling them again. If the
second process fails or ends early, the main process compiles as it would alone.

Nothing happens when the backward kernels are already cached (every run after the first),
when numba's cache cannot be located, on Windows (no select on pipes), in a pool worker
(`execution` sets the switch there: the pool already shares the cores), or with
``LSD3D_PRECOMPILE=0``. A wait that times out gives the second process up (it is stopped):
the main process then compiles what it still needs, as it would alone.
"""
from __future__ import annotations

import os
import selectors
import subprocess
import sys
import time

ENV_SWITCH = "LSD3D_PRECOMPILE"
STAGES = ("forward", "backward")     # what the second process reports, in order
WAIT_S = 90.0      # the longest the main process waits (~2x compiling those kernels itself)

_running: subprocess.Popen | None = None     # this process's second process, if any
_reported: set = set()                       # the stages it has reported
_waited = 0.0                                # seconds this process has waited for it


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


def start(distortion: bool = False) -> subprocess.Popen | None:
    """Launch the background compile if it is useful (see the module doc); the process, or
    None. ``distortion``: the run renders the depth-distortion output (other kernel
    signatures). The process's stdout is the pipe `wait_until` reads; its stderr is
    discarded (the main process reports compiling as before). One this process started and
    has not finished yet (running or ended) is returned as it is."""
    global _running, _waited
    if _running is not None:
        return _running
    if os.name == "nt" or os.environ.get(ENV_SWITCH, "1") == "0" or not backward_cold():
        return None
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", **{ENV_SWITCH: "0"})
    argv = [sys.executable, "-m", "lsd3d_usd.render.precompile"]
    try:
        proc = subprocess.Popen(argv + (["--distortion"] if distortion else []),
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, env=env, close_fds=True)
    except OSError:
        return None
    _running, _waited = proc, 0.0
    _reported.clear()
    return proc


def start_for_ggds(steps: int, weights: dict) -> subprocess.Popen | None:
    """`start` for a GGDS run of ``steps`` steps with these loss weights (None without
    steps). The `generate` command calls it as soon as its options are read, before it
    imports the pipeline and plans the run, and pipeline.generate again (for callers that
    start there), which then takes over the process already started."""
    if steps <= 0:
        return None
    return start(distortion=(weights.get("distortion") or 0) > 0)


def wait_until(stage: str, timeout: float = WAIT_S) -> None:
    """Block until this process's second process has compiled ``stage`` ("forward",
    "backward"), ended, or ``timeout`` passed (then it is given up and stopped); at once
    when there is none."""
    global _waited
    proc = _running
    if proc is None or stage in _reported:
        return
    t0 = time.monotonic()
    end = t0 + timeout
    try:
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            while stage not in _reported:
                left = end - time.monotonic()
                if left <= 0 or not sel.select(left):
                    finish(proc, timeout=0.0)     # too slow: compile here from now on
                    return
                line = proc.stdout.readline()
                if not line:        # ended (or failed): nothing more will come
                    finish(proc, timeout=0.0)
                    return
                word = line.decode(errors="replace").strip()
                if word in STAGES:
                    _reported.add(word)
    except (OSError, ValueError):
        finish(proc, timeout=0.0)
    finally:
        _waited += time.monotonic() - t0


def waited_s() -> float:
    """Seconds this process has waited for its second process's kernels."""
    return _waited


def finish(proc: subprocess.Popen | None, timeout: float = 1.0) -> None:
    """Stop the background compile if it still runs (the main process needs it no more)."""
    global _running
    if proc is None:
        return
    if proc is _running:
        _running = None
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


def compile_kernels(distortion: bool = False) -> None:
    """Render a tiny field forward, say so on stdout, then backward, say so: the signatures
    GGDS's steps use (float32 tensors, SH; the depth-distortion output when
    ``distortion``)."""
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
    # values_checked: the per-value scans are the main process's to compile (it runs them
    # on the scene's surfels first); this process goes straight to the kernels it waits for
    out = rasterize(*ts, torch.eye(4), K, 32, 32, settings=RasterSettings(distortion=distortion),
                    background=torch.full((3,), 0.5), values_checked=True)
    print("forward", flush=True)
    loss = out.rgb.sum() + out.depth_median.sum() + out.normal.sum() + out.alpha.sum()
    if distortion:
        loss = loss + out.distortion.sum()
    loss.backward()
    print("backward", flush=True)


if __name__ == "__main__":
    compile_kernels(distortion="--distortion" in sys.argv[1:])
