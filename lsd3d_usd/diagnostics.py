"""Capture USD's C++ diagnostics (printed straight to fd 2) so commands can turn
them into one clear line, and show them only with --debug."""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time

from numba.core import event


@contextlib.contextmanager
def captured_stderr():
    """Redirect the process's fd 2 into a buffer; yields a list that receives the text."""
    out: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield out
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            out.append(tmp.read().decode("utf-8", "replace"))


class KernelCompileNotice:
    """Says once, when numba starts compiling a kernel, that it does (a cache miss: the first
    run after an install or after the kernels' source changed; later runs load the compiled
    kernels from numba's on-disk cache), and adds up the seconds spent compiling.

    numba reports a "numba:compile" event only when it compiles, not when it loads a cached
    kernel; nested events (kernels calling kernels) count once."""

    def __init__(self, log):
        self._log, self._clock, self._event = log, time.perf_counter, event
        self.seconds, self.kernels, self._depth, self._t0 = 0.0, 0, 0, 0.0
        notice = self

        class _Listener(event.Listener):
            def on_start(self, ev):
                if notice._depth == 0:
                    if notice.kernels == 0:
                        notice._log("compiling kernels (first run only: numba caches them for "
                                    "later runs) ...")
                    notice.kernels += 1
                    notice._t0 = notice._clock()
                notice._depth += 1

            def on_end(self, ev):
                notice._depth -= 1
                if notice._depth == 0:
                    notice.seconds += notice._clock() - notice._t0

        self._listener = _Listener()
        event.register("numba:compile", self._listener)

    def close(self) -> None:
        """Stop listening; say how long compiling took, if it happened."""
        self._event.unregister("numba:compile", self._listener)
        if self.kernels:
            self._log(f"compiled {self.kernels} kernel(s) in {self.seconds:.1f} s (cached for "
                      "later runs)")
