"""numba options shared by the parallel kernels."""
from __future__ import annotations

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
