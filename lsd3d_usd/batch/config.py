"""`lsd3d-usd batch`'s configuration tree (lsd3d_usd.configtree): where and how the tasks run.
What to make comes from the spec (batch.spec); its [batch] workers and retries are the
defaults of the two leaves left unset here."""
from __future__ import annotations

from dataclasses import dataclass

from lsd3d_usd.configtree import option


@dataclass
class BatchRunConfig:
    executor: str = option("local", help="local: a process pool on this machine; "
                                         "ray: a Ray cluster (needs `pip install ray`)",
                           flag="--executor", choices=("local", "ray"))
    address: str | None = option(None, help="Ray cluster address (e.g. auto or "
                                             "ray://head:10001); without it a local Ray "
                                             "instance is started", flag="--address",
                                 metavar="ADDRESS")
    workers: int | None = option(None, help="tasks at once (default: the spec's "
                                            "[batch].workers, else all CPUs)", flag="--workers",
                                 lo=1, metavar="WORKERS")
    retries: int | None = option(None, help="re-runs of a failed task before it is reported "
                                            "(default: the spec's [batch].retries, else 2)",
                                 flag="--retries", lo=0, metavar="RETRIES")
