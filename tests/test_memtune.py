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
