"""glibc malloc tuning: large buffers freed by one frame are reused by the next without
page faults (the renderer's per-frame arrays)."""
import resource
import sys

import numpy as np
import pytest
from numba import njit

from lsd3d_usd.memtune import reuse_large_buffers


@njit(cache=False)
def _touch(nbytes):
    # numba arrays come from malloc (numpy's own arrays get madvise'd huge pages instead),
    # as the kernels' outputs do
    a = np.empty(nbytes, np.uint8)
    for i in range(0, nbytes, 4096):
        a[i] = 1
    return a[0]


def _faults_of_touching(nbytes):
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    _touch(nbytes)
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_large_buffers_are_reused_without_page_faults(monkeypatch):
    monkeypatch.delenv("LSD3D_MALLOC_TUNE", raising=False)
    if not reuse_large_buffers():
        pytest.skip("not glibc")
    nbytes = 96 << 20  # one frame's per-pair parameters at 1 M surfels
    _faults_of_touching(nbytes)  # first use may fault
    pages = nbytes // 4096
    assert _faults_of_touching(nbytes) < pages // 10


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and glibc only")
def test_peak_memory_of_a_spawned_process_is_its_own_and_freed_memory_goes_back():
    """A process started by a large one reports its own peak (VmHWM), not the parent's
    (getrusage's ru_maxrss survives exec); release_free_memory hands freed heap back."""
    import subprocess

    from lsd3d_usd.memtune import peak_rss_mb, release_free_memory
    code = ("import resource; from lsd3d_usd.memtune import peak_rss_mb; "
            "print(peak_rss_mb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)")
    big = np.ones(600 * 2 ** 20 // 8)          # 600 MB resident in this process
    assert peak_rss_mb() >= 600
    own, inherited = map(float, subprocess.run([sys.executable, "-c", code], capture_output=True,
                                               text=True, check=True).stdout.split())
    del big
    assert own < 400 and inherited >= 600      # the old measure reported this process's peak

    def rss_mb():
        with open("/proc/self/status") as fh:
            return next(int(ln.split()[1]) for ln in fh if ln.startswith("VmRSS:")) / 1024
    reuse_large_buffers()                       # keeps up to 1 GiB of freed heap resident
    _touch(300 * 2 ** 20)                       # 300 MB from malloc, freed on return
    before = rss_mb()
    assert release_free_memory()
    assert rss_mb() < before - 200
