"""Deterministic identifiers and times of a dataset: a token is the first 128 bits (32 hex
digits, nuScenes' form) of SHA-256 over what identifies the record (the dataset version, the
log's key -- scene name and route --, the table, and the record's time and sensor), so the
same command gives the same tokens on any machine, and a resumed run the same as an
uninterrupted one. Timestamps are integer microseconds since the Unix epoch: log k starts at
EPOCH_US + k hours (logs never overlap in time)."""
from __future__ import annotations

import hashlib

EPOCH_US = 1_767_225_600_000_000      # 2026-01-01T00:00:00Z
LOG_SPACING_US = 3_600_000_000


def token(*parts) -> str:
    h = hashlib.sha256("\x1f".join(str(p) for p in parts).encode())
    return h.hexdigest()[:32]


def timestamp_us(log_index: int, seconds: float) -> int:
    return EPOCH_US + int(log_index) * LOG_SPACING_US + round(float(seconds) * 1e6)
