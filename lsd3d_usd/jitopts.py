"""numba options shared by the parallel kernels, and a runner for serial ones on threads."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import get_num_threads
from numba.core.cpu import ParallelOptions


def prange_only() -> ParallelOptions:
    """``njit(parallel=...)`` for kernels whose parallelism is their prange loops alone.

    With ``parallel=True`` numba also turns every numpy call and array expression (each
    np.zeros of a tile's scratch arrays, each ``a[:] = 0``) into a parallel loop of its own
    and lowers it as a separate function: in the rasteriser that was a third of the first
    run's compiling, for loops that mostly ran inside a prange body, where they are serial
    anyway. Here they stay plain serial code; an array large enough to matter is filled in the
    kernel's own prange. An options object, not a dict: numba reads a dict's keys by popping
    them, at every signature it compiles, so a second signature would get the defaults.
    numba's cache does not key on these options: a change here needs the cache cleared."""
    return ParallelOptions({"prange": True, "numpy": False, "fusion": False,
                            "comprehension": False, "stencil": False, "setitem": False,
                            "inplace_binop": False})


def run_in_slices(kernel, n: int, sliced: tuple, rest: tuple = (), out: tuple = (),
                  min_slice: int = 4096) -> None:
    """Run a serial kernel compiled with ``nogil=True`` (without it the slices take turns)
    over n rows on numba's thread count: each thread calls
    ``kernel(*row slices of sliced, *rest, *row slices of out)`` on its share of the rows.
    For kernels whose rows are independent: a prange kernel does the same, but its parallel
    lowering took seconds more to compile on a first run (the procedural prior's kernels:
    2.8 s) for the same speed."""
    parts = min(get_num_threads(), n // max(int(min_slice), 1))
    if parts <= 1:
        if n:
            kernel(*sliced, *rest, *out)
        return
    cuts = np.linspace(0, n, parts + 1).astype(np.int64)

    def run(i):
        lo, hi = cuts[i], cuts[i + 1]
        kernel(*(a[lo:hi] for a in sliced), *rest, *(o[lo:hi] for o in out))

    with ThreadPoolExecutor(parts) as pool:
        list(pool.map(run, range(parts)))
