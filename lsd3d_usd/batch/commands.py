"""`lsd3d-usd batch SPEC.toml`: generate many scenes as independent tasks."""
from __future__ import annotations

import argparse
import sys

from lsd3d_usd import configtree as ct
from lsd3d_usd.batch.config import BatchRunConfig


def _batch(args) -> int:
    # local import: not loaded for --help
    from lsd3d_usd.execution import make_executor

    # local import: not loaded for --help
    from .runner import DEFAULT_RETRIES, format_report, run_batch
    from .spec import load_spec
    # local import: not loaded for --help
    from .tasks import plan_batch

    run, _ = ct.from_command_line(args, BatchRunConfig)
    spec = load_spec(args.spec)
    spec.executor, spec.address = run.executor, run.address
    retries = run.retries if run.retries is not None else (
        spec.retries if spec.retries is not None else DEFAULT_RETRIES)
    workers = run.workers if run.workers is not None else spec.workers
    if args.dry_run:
        print(f"output: {spec.output}")
        for sc in spec.scenes:
            print(f"scene {sc.name}: {sc.output}")
        for plan in plan_batch(spec):
            for t in plan.tasks:
                names = (list(t.deps) if len(t.deps) <= 3
                         else [*t.deps[:2], f"... {len(t.deps)} tasks"])
                deps = f" (after {', '.join(names)})" if t.deps else ""
                print(f"{t.id:40s} {t.kind:6s} {t.inputs_hash}{deps}")
        return 0
    ex = make_executor(run.executor, workers, run.address)
    err = lambda *a: print(*a, file=sys.stderr)  # noqa: E731
    progress = not args.no_progress and sys.stderr.isatty()
    try:
        report = run_batch(spec, ex, retries=retries, progress=progress, log=err)
    except KeyboardInterrupt:
        err(f"lsd3d-usd: batch interrupted; finished tasks are recorded in {spec.state_path}: "
            "run the same command again to continue")
        return 130
    finally:
        ex.close(cancel=True)
    for line in format_report(report):
        print(line, file=sys.stdout if line.startswith("batch:") else sys.stderr)
    print(f"state: {spec.state_path}")
    return 0 if report.ok else 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch", help="generate many scenes from a TOML spec, on local processes or Ray",
        description="Generate every scene of a TOML batch spec (docs/batch.md). Scenes run as "
                    "independent tasks; a large scene (8+ proxy chunks, or split_chunks = true) is "
                    "split: one task per chunk, then a scene task for the rest of `generate`. A failed "
                    "task is retried, the others continue; re-running the command skips tasks "
                    "already done with the same inputs (state in <output>/batch-state.json). "
                    "A [dataset] table makes the scenes into a dataset, a [scenarios] table "
                    "runs `sim run --scenario` on each scene. "
                    "Exit 0 when every task succeeded, 1 with one line per failed task.")
    p.add_argument("spec", help="batch spec (.toml)")
    ct.add_arguments(p, BatchRunConfig)
    p.add_argument("--dry-run", action="store_true",
                   help="check the spec and list the tasks with their input hashes; run nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_batch, compiles_kernels=True)
