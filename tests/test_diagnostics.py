"""The first-run notice: numba compiling kernels is said (once, with the time it took); a
later run loads them from numba's cache and says nothing."""
import os
import subprocess
import sys

SNIPPET = """
import sys
sys.path.insert(0, sys.argv[1])
from lsd3d_usd.diagnostics import KernelCompileNotice
notice = KernelCompileNotice(lambda m: print("LOG", m))
import kern
kern.twice(3.0); kern.twice(4.0); kern.plus(1, 2)
notice.close()
"""

KERNELS = """
from numba import njit

@njit(cache=True)
def _inner(x):
    return x + x

@njit(cache=True)
def twice(x):
    return _inner(x)

@njit(cache=True)
def plus(a, b):
    return a + b
"""


def test_compile_notice_first_run_only(tmp_path):
    from conftest import ROOT
    (tmp_path / "kern.py").write_text(KERNELS)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(tmp_path))

    def run():
        r = subprocess.run([sys.executable, "-c", SNIPPET, str(ROOT)], capture_output=True,
                           text=True, env=env, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        return [line[4:] for line in r.stdout.splitlines() if line.startswith("LOG ")]

    first = run()
    assert first[0].startswith("compiling kernels (first run only")
    assert len(first) == 2 and first[1].startswith("compiled 2 kernel(s) in ")  # twice (+ inner), plus
    assert run() == []                                                             # from the cache
