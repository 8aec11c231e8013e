"""Batch generation: many scenes (and the proxy chunks of large ones) as independent tasks
on a local process pool or a Ray cluster. See docs/batch.md."""
