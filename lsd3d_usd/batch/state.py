"""The batch state file: which tasks finished, with which inputs; and the batch lock.

``<batch output>/batch-state.json`` maps task id -> {hash, status, attempts, error, result,
finished}. Only the driver writes it, atomically, after every finished task, so an
interrupted batch loses at most the tasks that were running.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from lsd3d_usd.errors import InputError
from lsd3d_usd.scene import atomic_write_bytes, process_alive

STATE_VERSION = 1


class BatchState:
    def __init__(self, path: Path):
        self.path = Path(path)
        self.tasks: dict[str, dict] = {}
        if self.path.is_file():
            try:
                data = json.loads(self.path.read_text(encoding="utf-8"))
            except (json.JSONDecodeError, UnicodeDecodeError) as e:
                raise InputError(f"{self.path}: batch state is not valid JSON ({e}); delete it to "
                                 "start the batch afresh") from None
            if data.get("version") != STATE_VERSION:
                raise InputError(f"{self.path}: batch state version {data.get('version')!r} is not "
                                 f"{STATE_VERSION}; delete it to start the batch afresh")
            self.tasks = dict(data.get("tasks", {}))

    def is_done(self, task) -> bool:
        """Done with the same inputs, and its outputs are still there."""
        rec = self.tasks.get(task.id)
        return bool(rec and rec.get("status") == "done" and rec.get("hash") == task.inputs_hash
                    and all(Path(p).exists() for p in task.outputs))

    def record(self, task, status: str, attempts: int, error: str | None = None,
               result=None, seconds: float | None = None) -> None:
        self.tasks[task.id] = {"hash": task.inputs_hash, "scene": task.scene, "kind": task.kind,
                               "status": status, "attempts": attempts, "error": error,
                               "result": result, "seconds": seconds,
                               "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}
        self.save()

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = {"version": STATE_VERSION, "tasks": self.tasks}
        atomic_write_bytes(self.path, json.dumps(data, indent=1, sort_keys=True,
                                                 default=str).encode())


class BatchLock:
    """One driver per batch output folder (a second one would race on the state file)."""

    def __init__(self, folder: Path):
        self.path = Path(folder) / ".batch.lock"

    def __enter__(self):
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                try:
                    pid = int(self.path.read_text().strip() or 0)
                except (OSError, ValueError):
                    pid = 0
                if pid and process_alive(pid) and pid != os.getpid():
                    raise InputError(f"{self.path}: another batch (pid {pid}) is running on this "
                                     "output folder") from None
                self.path.unlink(missing_ok=True)  # stale: its driver is gone
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(str(os.getpid()))
            return self
        raise InputError(f"{self.path}: cannot take the batch lock")

    def __exit__(self, *exc):
        self.path.unlink(missing_ok=True)
        return False
