"""render.precompile: the background compile of the rasteriser's backward kernels that a
first `generate` starts — when it starts, that it stops, and (slow) that what it compiles is
what GGDS then loads from numba's cache."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from lsd3d_usd.render import precompile

from conftest import LAYOUT


class _Proc:
    """A stand-in second process (ended: poll() gives its exit code)."""

    def poll(self):
        return 0


def test_start_only_when_switched_on_and_the_kernels_are_not_cached(monkeypatch):
    monkeypatch.setattr(precompile, "_running", None)      # start() sets it: restored after
    started = []
    proc = _Proc()
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append((a, k)) or proc)
    monkeypatch.setenv(precompile.ENV_SWITCH, "0")
    monkeypatch.setattr(precompile, "backward_cold", lambda: True)
    assert precompile.start() is None
    monkeypatch.setenv(precompile.ENV_SWITCH, "1")
    monkeypatch.setattr(precompile, "backward_cold", lambda: False)
    assert precompile.start() is None and not started
    monkeypatch.setattr(precompile, "backward_cold", lambda: True)
    assert precompile.start() is proc
    (args,), kw = started[0]
    assert args == [sys.executable, "-m", "lsd3d_usd.render.precompile"]
    assert precompile.start(distortion=True) is proc     # not finished: the same one
    assert len(started) == 1
    precompile._running = None                               # finished (finish() does this)
    assert precompile.start(distortion=True) is proc
    assert started[1][0][0][-1] == "--distortion"           # the run's other signatures
    assert kw["env"][precompile.ENV_SWITCH] == "0"        # the child never starts another
    assert kw["env"]["NUMBA_NUM_THREADS"] == "1"           # one core: the other is the main's


def test_a_running_compile_is_not_started_twice(monkeypatch):
    """generate_command starts the compile before it imports the pipeline; pipeline.generate's
    own start then finds it running and takes it, with what it has reported so far."""
    class Running:
        def poll(self):
            return None

    running = Running()
    monkeypatch.setattr(precompile, "_running", running)
    monkeypatch.setattr(precompile, "_reported", {"forward"})
    monkeypatch.setattr(precompile, "backward_cold", lambda: True)
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: pytest.fail("started again"))
    assert precompile.start_for_ggds(250, {"distortion": 0.0}) is running
    assert precompile._reported == {"forward"}
    assert precompile.start_for_ggds(0, {}) is None       # no GGDS steps: nothing to compile


def test_generate_starts_the_compile_before_importing_the_pipeline(monkeypatch, tmp_path):
    """The command line's generate launches the second process first and stops it when the
    command fails before pipeline.generate takes it over."""
    from lsd3d_usd import commands
    from lsd3d_usd.cli import build_parser
    calls = []
    monkeypatch.setattr(precompile, "start_for_ggds",
                        lambda steps, weights: calls.append(("start", steps)) or "early")
    monkeypatch.setattr(precompile, "finish", lambda proc, timeout=1.0: calls.append(("finish", proc)))

    def fail(*a):
        calls.append(("generate",))
        raise RuntimeError("stop here")
    monkeypatch.setattr(commands, "_generate", fail)
    args = build_parser().parse_args(["generate", "--layout", str(LAYOUT), "-o",
                                      str(tmp_path / "s"), "--steps", "7"])
    with pytest.raises(RuntimeError, match="stop here"):
        commands.generate_command(args)
    assert calls == [("start", 7), ("generate",), ("finish", "early")]


def test_cache_state_read_from_numba_index(tmp_path):
    class NoCache:
        pass

    def dispatcher(path):
        d = type("D", (), {})()
        d._cache = type("C", (), {})()
        d._cache._cache_file = type("F", (), {"_index_path": str(path)})()
        return d
    assert precompile._cached(NoCache()) is None            # unknown: never counted as cold
    assert precompile._cached(dispatcher(tmp_path / "f.nbi")) is False
    (tmp_path / "f.nbi").write_bytes(b"x")
    assert precompile._cached(dispatcher(tmp_path / "f.nbi")) is True


def test_the_numba_backend_waits_for_forward_then_backward(monkeypatch):
    import torch

    from lsd3d_usd.render.rasterize import rasterize
    calls = []
    monkeypatch.setattr(precompile, "wait_until", lambda stage, **k: calls.append(stage))
    rng = np.random.default_rng(0)
    n = 50
    means = rng.uniform(-1, 1, (n, 3)) + [0, 0, 4]
    q = rng.normal(size=(n, 4))
    ts = [torch.tensor(a, dtype=torch.float32, requires_grad=True) for a in
          (means, q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(0.05, 0.2, (n, 2)),
           rng.uniform(0.2, 0.9, n), rng.normal(size=(n, 1, 3)))]
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    out = rasterize(*ts, torch.eye(4), K, 32, 32)
    assert calls == ["forward"]
    out.rgb.sum().backward()
    assert calls == ["forward", "backward"]


def _fake(monkeypatch, script):
    """A stand-in second process running ``script``, registered as this process's."""
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
    monkeypatch.setattr(precompile, "_running", proc)
    monkeypatch.setattr(precompile, "_reported", set())
    return proc


def test_wait_until_returns_when_the_stage_is_reported_or_the_process_ends(monkeypatch):
    proc = _fake(monkeypatch, "import time\ntime.sleep(0.3)\nprint('forward', flush=True)\n"
                              "time.sleep(0.3)")
    t = time.perf_counter()
    precompile.wait_until("forward", timeout=30)
    assert "forward" in precompile._reported and time.perf_counter() - t >= 0.25
    precompile.wait_until("backward", timeout=30)        # it ends without reporting it
    assert precompile._running is None and "backward" not in precompile._reported
    assert proc.stdout.closed
    precompile.wait_until("backward", timeout=30)        # nothing to wait for: at once
    proc.wait()


def test_a_wait_that_times_out_gives_the_process_up(monkeypatch):
    """Once: the next render does not wait again (GGDS renders hundreds of times)."""
    proc = _fake(monkeypatch, "import time\ntime.sleep(30)")
    t = time.perf_counter()
    precompile.wait_until("forward", timeout=0.2)
    assert time.perf_counter() - t < 5 and "forward" not in precompile._reported
    assert proc.returncode is not None and precompile._running is None    # stopped
    t = time.perf_counter()
    precompile.wait_until("forward", timeout=30)
    assert time.perf_counter() - t < 0.1


def test_finish_stops_a_compile_still_running():
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    t = time.perf_counter()
    precompile.finish(proc, timeout=0.1)
    assert proc.returncode is not None and time.perf_counter() - t < 10
    precompile.finish(None)


@pytest.mark.slow
def test_background_compile_fills_the_cache_the_main_process_reads(tmp_path):
    """In a fresh numba cache the backward kernels are cold; after the background process
    they are cached, and a process rendering forward and backward compiles neither."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    cold = [sys.executable, "-c", "from lsd3d_usd.render import precompile as p; "
            "print(p.backward_cold())"]
    assert subprocess.run(cold, env=env, capture_output=True, text=True).stdout.split()[-1] == "True"
    subprocess.run([sys.executable, "-m", "lsd3d_usd.render.precompile"], env=env, check=True,
                   timeout=600)
    assert subprocess.run(cold, env=env, capture_output=True, text=True).stdout.split()[-1] == "False"
    # a small generate in that cache (GGDS's own calls, not the background's) then compiles
    # neither backward kernel: their signatures are the ones the background compiled
    probe = ("import pathlib\n"
             "from numba.core import event\n"
             "names = []\n"
             "class L(event.Listener):\n"
             "    def on_start(self, ev): names.append(ev.data['dispatcher'].py_func.__name__)\n"
             "    def on_end(self, ev): pass\n"
             "event.register('numba:compile', L())\n"
             "from lsd3d_usd.config import generate_config\n"
             "from lsd3d_usd.pipeline import RunOptions, generate\n"
             f"generate(generate_config(layout=pathlib.Path({str(LAYOUT)!r}), steps=2, "
             "surfels=3000, env_resolution=(128, 64), resolution=(64, 48), views=4, "
             "perceptual=False, actors=False, seed=5), "
             f"RunOptions(out=pathlib.Path({str(tmp_path / 'scene')!r}), progress=False, "
             "log=lambda *a: None))\n"
             "print(sorted(set(names)))\n")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True,
                         check=True, timeout=900).stdout
    assert "accumulate_view" in out             # the listener saw what GGDS compiled itself
    assert "project_backward" not in out and "'backward'" not in out, out
