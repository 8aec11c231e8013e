"""Process-wide glibc malloc tuning for the renderer's large per-frame buffers, handing freed
memory back, and this process's peak memory.

glibc serves allocations above its mmap threshold (at most 32 MB by its own adjustment) with
fresh mmap()s and unmaps them on free, so every frame's 16-100 MB arrays (projected surfels,
per-pair parameters, gradient rows) are page-faulted in again: about 55k minor faults and
0.05-0.08 s of a 1 M-surfel 960x540 forward. Raising the mmap and trim thresholds keeps freed
blocks in the heap for the next frame. The CLI calls `reuse_large_buffers` once; library
users may call it too. LSD3D_MALLOC_TUNE=0 turns it off; on a non-glibc system it does
nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import resource

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_LIMIT = 1 << 30  # blocks up to 1 GiB come from the heap; up to 1 GiB of free heap is kept
_done = False


def reuse_large_buffers() -> bool:
    """Apply the tuning once per process; True when glibc accepted it."""
    global _done
    if _done:
        return True
    if os.environ.get("LSD3D_MALLOC_TUNE", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 - raises AttributeError off glibc
        ok = (libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(_LIMIT)) == 1
              and libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(_LIMIT)) == 1)
    except (OSError, AttributeError):
        return False
    _done = ok
    return ok


def _libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim  # noqa: B018 - raises AttributeError off glibc
        return libc
    except (OSError, AttributeError):
        return None


def release_free_memory() -> bool:
    """Return the heap's free memory to the system (glibc malloc_trim): a step that built
    large temporary arrays (surfel initialisation) would otherwise keep up to the trim
    threshold above (1 GiB) resident for the rest of the process."""
    libc = _libc()
    return bool(libc is not None and libc.malloc_trim(0))


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB): VmHWM of /proc/self/status, which starts
    afresh at exec. getrusage's ru_maxrss does not: Linux carries it across exec, so a worker
    spawned by a 2 GB driver reported 2 GB before doing anything. ru_maxrss elsewhere."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
