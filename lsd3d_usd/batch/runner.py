"""The batch driver: plan, skip what is done, run the rest with retries, record, report."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from tqdm import tqdm

from lsd3d_usd.execution import OK, SUSPECT

from .spec import BatchSpec
from .state import BatchLock, BatchState
from .tasks import ScenePlan, finalize_chunks, plan_batch, prepare_scene

DEFAULT_RETRIES = 2


@dataclass
class Failure:
    task_id: str
    scene: str
    error: str
    attempts: int

    def line(self) -> str:
        tries = f" (after {self.attempts} attempts)" if self.attempts > 1 else ""
        return f"failed: scene {self.scene!r} task {self.task_id}{tries}: {self.error}"


@dataclass
class BatchReport:
    total: int = 0
    skipped: list[str] = field(default_factory=list)     # done in an earlier run
    done: list[str] = field(default_factory=list)
    retried: dict[str, list[str]] = field(default_factory=dict)   # task -> errors before success
    failed: list[Failure] = field(default_factory=list)
    blocked: list[Failure] = field(default_factory=list)  # not run: a task it needs failed
    interrupted: bool = False
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.failed and not self.blocked and not self.interrupted


def run_batch(spec: BatchSpec, executor, retries: int = DEFAULT_RETRIES, progress: bool = False,
              on_event=None, log=None) -> BatchReport:
    """Run every task of ``spec`` not yet done on ``executor``.

    ``on_event(kind, task_id, info)`` is called in the driver for "done", "retry", "failed"
    (tests use it; raising KeyboardInterrupt from it behaves like Ctrl-C).
    """
    t0 = time.perf_counter()
    log = log or (lambda *a: None)
    plans = plan_batch(spec)                     # bad input is refused here, nothing written
    tasks = {t.id: t for p in plans for t in p.tasks}
    plan_of = {t.id: p for p in plans for t in p.tasks}
    report = BatchReport(total=len(tasks))
    with BatchLock(spec.output):
        state = BatchState(spec.state_path)
        finished = {tid for tid, t in tasks.items() if state.is_done(t)}
        report.skipped = sorted(finished)
        todo = [tid for tid in tasks if tid not in finished]
        prepared: set[str] = set()
        for p in {id(plan_of[t]): plan_of[t] for t in todo}.values():
            if hasattr(p, "check"):              # a refused dataset prepares no scene
                p.check()
        for tid in todo:
            plan = plan_of[tid]
            if hasattr(plan, "prepare"):             # the dataset, the scenario runs
                if id(plan) not in prepared:
                    plan.prepare()
                    prepared.add(id(plan))
            elif plan.scene.name not in prepared:
                prepare_scene(plan)
                prepared.add(plan.scene.name)
        bar = None
        if progress:
            bar = tqdm(total=len(tasks), initial=len(finished), desc="batch", unit="task")
        attempts = {tid: 0 for tid in todo}
        errors: dict[str, list[str]] = {tid: [] for tid in todo}
        waiting = list(todo)                     # in plan order: chunks before their scene
        isolated: set[str] = set()
        in_flight: set[str] = set()
        dead: set[str] = set()                   # failed or blocked

        def ready(tid):
            return all(d in finished for d in tasks[tid].deps)

        def blocked_by(tid):
            return next((d for d in tasks[tid].deps if d in dead), None)

        def submit(tid):
            task = tasks[tid]
            plan: ScenePlan = plan_of[tid]
            if task.kind == "scene" and task.deps and attempts[tid] == 0:
                finalize_chunks(plan)            # the driver writes the proxy root layer
            attempts[tid] += 1
            executor.submit(tid, task.payload, isolated=tid in isolated)
            in_flight.add(tid)

        try:
            while waiting or in_flight:
                for tid in list(waiting):
                    d = blocked_by(tid)
                    if d is not None:
                        waiting.remove(tid)
                        dead.add(tid)
                        report.blocked.append(Failure(tid, tasks[tid].scene,
                                                      f"not run: {d} failed", 0))
                        if bar is not None:
                            bar.update(1)
                for tid in list(waiting):
                    if len(in_flight) >= executor.capacity:
                        break
                    if ready(tid):
                        waiting.remove(tid)
                        submit(tid)
                if not in_flight:
                    if waiting:  # nothing runnable and nothing running: dependency cycle
                        raise RuntimeError(f"batch: tasks cannot start: {', '.join(waiting)}")
                    break
                for tid, status, value in executor.poll(timeout=0.5):
                    in_flight.discard(tid)
                    task = tasks[tid]
                    if status == OK:
                        finished.add(tid)
                        report.done.append(tid)
                        if errors[tid]:
                            report.retried[tid] = list(errors[tid])
                        state.record(task, "done", attempts[tid], result=value.get("result"),
                                     seconds=value.get("seconds"))
                        if bar is not None:
                            bar.update(1)
                        if on_event:
                            on_event("done", tid, value)
                        continue
                    errors[tid].append(value)
                    if status == SUSPECT:
                        # Its pool died with other tasks in it; not charged: re-run alone.
                        attempts[tid] -= 1
                        isolated.add(tid)
                        waiting.insert(0, tid)
                        continue
                    if attempts[tid] <= retries:
                        log(f"retry {attempts[tid]}/{retries}: {tid}: {value}")
                        waiting.insert(0, tid)
                        if on_event:
                            on_event("retry", tid, value)
                        continue
                    dead.add(tid)
                    report.failed.append(Failure(tid, task.scene, value, attempts[tid]))
                    state.record(task, "failed", attempts[tid], error=value)
                    if bar is not None:
                        bar.update(1)
                        bar.set_postfix(failed=len(report.failed))
                    if on_event:
                        on_event("failed", tid, value)
        except KeyboardInterrupt:
            report.interrupted = True
            executor.close(cancel=True)
            raise
        finally:
            if bar is not None:
                bar.close()
            report.seconds = time.perf_counter() - t0
        executor.close()
    return report


def format_report(report: BatchReport) -> list[str]:
    lines = [f"batch: {len(report.done)} task(s) done, {len(report.skipped)} already done, "
             f"{len(report.failed)} failed, {len(report.blocked)} not run "
             f"({report.seconds:.1f} s)"]
    for tid, errs in report.retried.items():
        lines.append(f"retried: {tid} succeeded after {len(errs)} failure(s); first: {errs[0]}")
    lines += [f.line() for f in report.failed]
    lines += [f"not run: scene {f.scene!r} task {f.task_id}: {f.error}" for f in report.blocked]
    return lines
