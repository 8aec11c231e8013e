import os
import signal
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (see lsd3d_usd/__init__)
# the test workers compile the kernels themselves: a background compile per cold `generate`
# would only add processes (tests/test_precompile.py checks it)
os.environ.setdefault("LSD3D_PRECOMPILE", "0")
# as lsd3d_usd.sim does, before any test module imports grpc: a worker that ran the gRPC tests
# forks ffmpeg and other subprocesses later (grpc/grpc#43055)
os.environ.setdefault("GRPC_ENABLE_FORK_SUPPORT", "false")

# A shell without job control starts background jobs with SIGINT ignored, and children inherit
# that: the tests that stop a child with SIGINT (Ctrl-C) would wait forever. Caught signals
# are reset to their default on exec, so catching it here gives every child Python's
# KeyboardInterrupt again.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402,F401

import lsd3d_usd  # registers the schema before any stage is opened  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"   # the README sample

# A small scene: what most tests that need a generated scene can live with (seconds to make).
SMALL_SCENE = dict(layout=LAYOUT, steps=2, surfels=3000, env_resolution=(128, 64),
                   resolution=(64, 48), views=4, perceptual=False, actors=False, seed=5)


def generate_small(out, run=None, **settings):
    """`generate` a small scene of the README sample into ``out`` (SMALL_SCENE updated by
    ``settings``; ``run``: RunOptions fields). Returns generate's summary."""
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.pipeline import RunOptions, generate
    return generate(generate_config(**{**SMALL_SCENE, **settings}),
                    RunOptions(out=Path(out), progress=False, log=lambda *a: None,
                               **(run or {})))


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory):
    """One small generated scene (SMALL_SCENE) shared by the tests that only read it."""
    out = tmp_path_factory.mktemp("small") / "scene"
    generate_small(out)
    return out


@pytest.fixture(scope="session")
def sim_scene(tmp_path_factory):
    """One small scene with traffic and people assets for the closed-loop tests that only
    read it (sim env, CLI, remote service)."""
    out = tmp_path_factory.mktemp("sim") / "scene"
    generate_small(out, steps=0, actors=True, pedestrians=2, cyclists=1)
    return out


def error_line(result, *needles) -> str:
    """The one error line of a failed command: ``result`` a CompletedProcess, or (exit code,
    stderr). Exit 1, exactly one "lsd3d-usd: error: " line and it is the last line printed
    (progress lines before it are fine), no traceback, every needle in it."""
    code, err = (result.returncode, result.stderr) if hasattr(result, "returncode") else result
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("lsd3d-usd: error: ")]
    assert code == 1 and len(errors) == 1 and lines[-1] == errors[0], err
    assert "Traceback" not in err, err
    for n in needles:
        assert n in errors[0], (n, errors[0])
    return errors[0]


@pytest.fixture
def cli_error(capsys):
    """cli_error(argv, *needles): run the CLI in this process; its one error line."""
    from lsd3d_usd.cli import main

    def run(argv, *needles):
        capsys.readouterr()
        code = main([str(a) for a in argv])
        return error_line((code, capsys.readouterr().err), *needles)
    return run


def random_field(n=1000, sh_degree=1, seed=0, semantic=True):
    from lsd3d_usd.semantics import CLASSES
    from lsd3d_usd.splats.field import SurfelField, sh_coeff_count

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return SurfelField(
        positions=rng.normal(size=(n, 3)) * 50,
        orientations=q,
        scales=rng.uniform(0.01, 1.0, (n, 2)),
        opacities=rng.uniform(0, 1, n),
        sh=rng.normal(size=(n, sh_coeff_count(sh_degree), 3)) * 0.3,
        semantic_ids=rng.integers(-1, len(CLASSES), n) if semantic else None,
        semantic_classes=CLASSES if semantic else (),
    )


@pytest.fixture
def field_factory():
    return random_field


@pytest.fixture
def run_cli():
    """Run the CLI in a subprocess (as a user would); returns CompletedProcess."""
    import subprocess

    def run(*args, cwd=None, check=False):
        env = dict(os.environ)
        return subprocess.run([sys.executable, "-m", "lsd3d_usd", *map(str, args)],
                              capture_output=True, text=True, cwd=cwd, env=env, check=check)
    return run


# colour-science keeps OpenImageIO TypeDesc objects in module globals; with torch loaded,
# interpreter teardown then makes OIIO's nanobind module print pages of "leaked instances"
# after pytest's closing summary line. End the process right after pytest is done, with
# pytest's own exit status, so the summary stays the last thing printed.
_EXIT_STATUS: dict = {}


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS["code"] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    if "code" in _EXIT_STATUS and "OpenImageIO" in sys.modules:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS["code"])
