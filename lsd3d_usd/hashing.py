"""Content hashes that decide whether work can be reused (scene layers, batch tasks).

One definition so that two places hashing the same inputs agree: SHA-256 over the canonical
JSON of each part (sorted keys; bytes hashed as they are), hex digest cut to ``length``."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

DEFAULT_LENGTH = 16


def content_hash(*parts, length: int = DEFAULT_LENGTH) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else
                 json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()[:length]


def file_hash(path, length: int = DEFAULT_LENGTH, chunk: int = 1 << 20) -> str:
    """SHA-256 of a file's bytes, read in chunks (bounded memory for large files)."""
    h = hashlib.sha256()
    with open(Path(path), "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()[:length]
