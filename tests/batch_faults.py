"""Fault injection for the batch tests, kept out of the product: a test re-targets chosen
scenes' tasks (the plan's payload "target") to ``run_task`` here, which fails as the payload's
"fault" says and otherwise runs the real task. Spawned pool workers import this module by the
same name (multiprocessing hands them the parent's sys.path, tests/ included)."""
import os
from pathlib import Path

from lsd3d_usd.batch import tasks

MODES = ("raise-once", "exit-once", "raise", "exit")


def run_task(payload: dict) -> dict:
    mode = payload["fault"]
    if mode.endswith("-once"):
        marker = Path(payload["log"]).parent / f"crashed.{payload['scene']}"
        if not marker.exists():
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.write_text(str(os.getpid()))
            _fail(mode)
    else:
        _fail(mode)
    return tasks.run_task(payload)


def _fail(mode: str) -> None:
    if mode.startswith("exit"):
        os._exit(17)  # the worker process dies, as on a segfault or OOM kill
    raise RuntimeError(f"injected test crash ({mode})")


def inject(monkeypatch, faults: dict) -> None:
    """Make the scene tasks of the scenes named in ``faults`` ({scene: mode}) fail so."""
    plan_scene = tasks.plan_scene

    def planned(sc, *a, **k):
        plan = plan_scene(sc, *a, **k)
        if sc.name in faults:
            for t in plan.tasks:
                if t.payload["kind"] == "scene":
                    t.payload.update(target="batch_faults:run_task", fault=faults[sc.name])
        return plan
    monkeypatch.setattr(tasks, "plan_scene", planned)
