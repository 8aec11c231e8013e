"""Where tasks run: a local process pool (default) or a Ray cluster. Used by `batch` (scene
and proxy-chunk tasks) and by chunk-wise GGDS (region tasks).

Both executors run the function a payload names (``payload["target"] = "module:function"``,
set by our own code, never read from a file) on plain-dict payloads and give the driver the
same three outcomes per task:

- ``OK``: the task returned;
- ``ERROR``: the task raised (the message names the exception);
- ``LOST``: the worker process died (segfault, OOM kill, ``os._exit``).

A process pool cannot say *which* task killed it: every task in flight fails with
BrokenProcessPool. Those are reported as ``SUSPECT``, not charged an attempt, and re-run
one per private single-worker pool, where a death is attributed exactly (then ``LOST``).
Ray reports a dead worker per task (WorkerCrashedError), so it never needs that step; its own
automatic retries are turned off so the driver's retry count holds for both executors.
"""
from __future__ import annotations

import atexit
import importlib
import multiprocessing as mp
import os
import signal
import socket
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor
from concurrent.futures import wait as futures_wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from pathlib import Path

from lsd3d_usd.errors import InputError
from lsd3d_usd.memtune import peak_rss_mb

OK, ERROR, LOST, SUSPECT = "ok", "error", "lost", "suspect"


@contextmanager
def task_log(path, label: str):
    """A worker task's log: appends to ``path`` (folders made), a header line with the time,
    pid and ``label``; yields log(*args), which writes a line and flushes (the driver and
    `tail -f` see it at once)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "a", encoding="utf-8") as fh:
        def log(*a):
            fh.write(" ".join(str(x) for x in a) + "\n")
            fh.flush()
        log(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} pid {os.getpid()} {label}")
        yield log


def probe(payload: dict) -> dict:
    """A task that reports where it ran: the worker's host, pid and peak memory (checks a pool
    or a cluster before sending it real work); ``payload["sleep"]`` seconds first, if given
    (a task that is still running when the tests need one), after creating the file
    ``payload["started"]`` names, if given (how a test knows the task has begun)."""
    if payload.get("started"):
        Path(payload["started"]).touch()
    time.sleep(float(payload.get("sleep", 0.0)))
    return {"host": socket.gethostname(), "pid": os.getpid(), "peak_rss_mb": peak_rss_mb(),
            "threads": int(os.environ.get("OMP_NUM_THREADS", "0") or 0)}


def describe(exc: BaseException) -> str:
    msg = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


def _init_worker(threads: int, driver: int | None = None) -> None:
    """Runs first in every pool worker (spawned, so nothing heavy is imported yet): share the
    cores between workers, leave Ctrl-C to the driver (which stops the pool), and end with the
    driver (pid ``driver``, given by it: a worker whose driver died while it was starting must
    not take that for its parent)."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[var] = str(threads)
    os.environ["LSD3D_PRECOMPILE"] = "0"    # no compile process per task: the pool has the cores
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    atexit.register(_quiet_exit)
    threading.Thread(target=_exit_with_driver, args=(driver or os.getppid(),), daemon=True,
                     name="exit-with-driver").start()


def _exit_with_driver(driver: int, every_s: float = 0.5) -> None:
    """A pool worker ends within ``every_s`` of its driver's death (killed, crashed): a pool
    worker only notices when its task returns, and an orphan would go on writing into the
    output that the next run of the same command is already redoing."""
    while True:
        time.sleep(every_s)
        if os.getppid() != driver:
            os._exit(1)


def _quiet_exit() -> None:
    """At worker exit, silence stderr: native libraries' teardown chatter (OpenImageIO's
    nanobind "leaked instances" once torch is loaded) would otherwise bury the batch report."""
    try:
        sys.stderr.flush()
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, 2)
    except OSError:
        pass


def _call(payload: dict) -> dict:
    module, _, name = payload["target"].partition(":")
    return getattr(importlib.import_module(module), name)(payload)


class LocalExecutor:
    """concurrent.futures.ProcessPoolExecutor with the spawn start method (no fork: torch,
    numba and USD hold threads and locks that fork would copy half-way)."""

    name = "local"

    def __init__(self, workers: int | None = None, tasks_per_worker: int | None = None):
        self.workers = max(1, int(workers or os.cpu_count() or 1))
        self.tasks_per_worker = tasks_per_worker   # None: workers live as long as the pool
        self.threads = max(1, (os.cpu_count() or 1) // self.workers)
        self._ctx = mp.get_context("spawn")
        self._pool: ProcessPoolExecutor | None = None
        self._futures: dict = {}          # future -> (key, pool)
        self._private: set = set()        # single-worker pools of isolated tasks
        self._retired: list = []          # broken or finished pools, joined at close()

    @property
    def capacity(self) -> int:
        return self.workers

    def _new_pool(self, n: int, threads: int | None = None) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=n, mp_context=self._ctx, initializer=_init_worker,
                                   initargs=(threads or self.threads, os.getpid()),
                                   max_tasks_per_child=self.tasks_per_worker)

    def submit(self, key, payload: dict, isolated: bool = False,
               threads: int | None = None) -> None:
        """``isolated``: in a fresh single-worker pool (a retry); ``threads``: likewise, with
        that many threads instead of the pool's share (a task that runs with fewer
        neighbours than workers can use their cores)."""
        if isolated or (threads and threads != self.threads):
            pool = self._new_pool(1, threads)
            self._private.add(pool)
        else:
            if self._pool is None:
                self._pool = self._new_pool(self.workers)
            pool = self._pool
        try:
            fut = pool.submit(_call, payload)
        except BrokenProcessPool:
            # A worker died after the last poll: the shared pool is retired here (its tasks
            # are reported by the next poll) and this task goes to a fresh one.
            if pool is not self._pool:
                raise
            self._pool = self._new_pool(self.workers)
            self._retired.append(pool)
            pool = self._pool
            fut = pool.submit(_call, payload)
        self._futures[fut] = (key, pool)

    def poll(self, timeout: float) -> list[tuple]:
        """Outcomes of the tasks that finished within ``timeout`` s: [(key, status, value)]."""
        if not self._futures:
            return []
        done, _ = futures_wait(list(self._futures), timeout=timeout, return_when=FIRST_COMPLETED)
        out = []
        broken = set()
        for fut in done:
            key, pool = self._futures.pop(fut)
            exc = fut.exception()
            if exc is None:
                out.append((key, OK, fut.result()))
            elif isinstance(exc, BrokenProcessPool):
                broken.add(pool)
                private = pool in self._private
                out.append((key, LOST if private else SUSPECT,
                            "worker process died (killed, crashed or out of memory)"))
            else:
                out.append((key, ERROR, describe(exc)))
        for fut, (key, pool) in list(self._futures.items()):
            if pool in broken:  # the rest of a broken pool's tasks fail too; collect them now
                self._futures.pop(fut)
                out.append((key, SUSPECT, "worker process died (killed, crashed or out of memory)"))
        for pool in broken:
            pool.shutdown(wait=False, cancel_futures=True)
            if pool is self._pool:
                self._pool = None
            self._private.discard(pool)
            self._retired.append(pool)
        for pool in list(self._private):  # finished private pools
            if not any(p is pool for _, p in self._futures.values()):
                # wait: shutdown(wait=False) clears the pool's process table while its manager
                # thread may still be replacing the worker that max_tasks_per_child retired
                # (a TypeError traceback from that thread); its one task is done anyway
                pool.shutdown(wait=True)
                self._private.discard(pool)
                self._retired.append(pool)
        return out

    def close(self, cancel: bool = False) -> None:
        pools = ([self._pool] if self._pool else []) + list(self._private)
        for pool in pools:
            if cancel:
                # Running tasks are abandoned (their writes are atomic); stop their processes.
                procs = list(getattr(pool, "_processes", {}).values())
                pool.shutdown(wait=False, cancel_futures=True)
                for p in procs:
                    if p.is_alive():
                        p.terminate()
                for p in procs:
                    p.join(timeout=10)
            else:
                pool.shutdown(wait=True)
        for pool in self._retired:
            pool.shutdown(wait=True)
        self._pool, self._private, self._futures, self._retired = None, set(), {}, []


class RayExecutor:
    """The same tasks on Ray: ``address=None`` starts a local instance with ``num_cpus``
    (default: this machine's); otherwise connects (``auto``, ``ray://host:10001``, ...).
    Workers must be able to import lsd3d_usd and see the spec's input and output paths."""

    name = "ray"

    def __init__(self, address: str | None = None, workers: int | None = None,
                 num_cpus: int | None = None, tasks_per_worker: int | None = None):
        try:
            # local import: optional dependency
            import ray
        except ImportError:
            # local import: heavy, or only on this path
            from lsd3d_usd.errors import InputError
            raise InputError("--executor ray: Ray is not installed (pip install 'lsd3d-usd[ray]' "
                             "or pip install ray)") from None
        self.ray = ray
        self._owns = not ray.is_initialized()
        if self._owns:
            kw = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
            if address and address != "auto":
                _check_reachable(address)
            try:
                if address:
                    ray.init(address=address, **kw)
                else:
                    ray.init(num_cpus=num_cpus or os.cpu_count() or 1, **kw)
            except Exception as e:  # unreachable address, version mismatch, ...
                # local import: heavy, or only on this path
                from lsd3d_usd.errors import InputError
                where = f"--address {address}" if address else "local Ray instance"
                raise InputError(f"--executor ray: {where}: cannot start or connect: "
                                 f"{describe(e)}") from None
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.workers = max(1, int(workers or cpus))
        opts = dict(num_cpus=1, max_retries=0, retry_exceptions=False)
        if tasks_per_worker:
            opts["max_calls"] = int(tasks_per_worker)
        self._remote = ray.remote(_call).options(**opts)
        self._refs: dict = {}

    @property
    def capacity(self) -> int:
        return self.workers

    def submit(self, key, payload: dict, isolated: bool = False,
               threads: int | None = None) -> None:
        self._refs[self._remote.remote(payload)] = key   # Ray places it on a core it has

    def poll(self, timeout: float) -> list[tuple]:
        if not self._refs:
            return []
        ray = self.ray
        done, _ = ray.wait(list(self._refs), num_returns=1, timeout=timeout)
        if done:  # collect everything else already finished too
            more, _ = ray.wait([r for r in self._refs if r not in done],
                               num_returns=len(self._refs) - len(done), timeout=0)
            done = done + more
        out = []
        for ref in done:
            key = self._refs.pop(ref)
            try:
                out.append((key, OK, ray.get(ref)))
            except ray.exceptions.RayTaskError as e:
                cause = getattr(e, "cause", None)
                out.append((key, ERROR, describe(cause) if cause is not None else describe(e)))
            except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                    ray.exceptions.OutOfMemoryError) as e:
                out.append((key, LOST, f"worker process died ({type(e).__name__})"))
            except ray.exceptions.RayError as e:
                out.append((key, ERROR, describe(e)))
        return out

    def close(self, cancel: bool = False) -> None:
        if cancel:
            for ref in list(self._refs):
                try:
                    self.ray.cancel(ref, force=True)
                except Exception:
                    pass
        self._refs = {}
        if self._owns:
            self.ray.shutdown()


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """Fail fast (one line) when a Ray address's host:port does not answer: ray.init itself
    keeps retrying for a minute or more."""

    hostport = address.split("://", 1)[-1].rsplit("/", 1)[0]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise InputError(f"--address {address!r}: expected HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise InputError(f"--executor ray: --address {address}: not reachable "
                         f"({e.strerror or e})") from None


def make_executor(kind: str, workers: int | None = None, address: str | None = None,
                  tasks_per_worker: int | None = None):
    """``tasks_per_worker``: a worker process is replaced after this many tasks (None: never).
    1 gives every task the memory of a fresh process: an allocator keeps the arenas a large
    task grew, so a long-lived worker's footprint is the largest of all its tasks and more."""
    if kind == "local":
        if address:
            raise InputError("--address is for --executor ray")
        return LocalExecutor(workers, tasks_per_worker)
    if kind == "ray":
        return RayExecutor(address, workers, tasks_per_worker=tasks_per_worker)
    raise InputError(f"--executor {kind!r}: choose local or ray")
