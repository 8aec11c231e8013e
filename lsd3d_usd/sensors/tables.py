"""The checks the sensors' TOML readers share: every value is checked, and a bad one is one
InputError line naming where (the file, the sensor) and the key."""
from __future__ import annotations

import math

from lsd3d_usd.errors import InputError


def number(table: dict, key: str, where: str, default=None, integer: bool = False):
    """``table[key]`` as a finite float (an int with ``integer``), or ``default``."""
    v = table.get(key, default)
    if v is None:
        raise InputError(f"{where}: {key}: required")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{where}: {key}: expected a number, got {v!r}")
    try:
        f = float(v)
    except OverflowError:                   # a TOML integer past the float range
        raise InputError(f"{where}: {key}: {str(v)[:20]}... is out of range") from None
    if integer and (not f.is_integer()):
        raise InputError(f"{where}: {key}: expected an integer, got {v!r}")
    if not math.isfinite(f):
        raise InputError(f"{where}: {key}: must be finite, got {v!r}")
    return int(v) if integer else float(v)


def known_keys(table: dict, keys, where: str) -> None:
    unknown = sorted(set(table) - set(keys))
    if unknown:
        raise InputError(f"{where}: unknown key {unknown[0]!r}; known: {', '.join(sorted(keys))}")


def mount(table: dict, keys: tuple, where: str) -> tuple:
    """The ``mount`` sub-table as a tuple in the order of ``keys`` (missing ones 0)."""
    m = table.get("mount", {})
    if not isinstance(m, dict) or set(m) - set(keys):
        raise InputError(f"{where}: mount: a table of {', '.join(keys)}")
    return tuple(number(m, k, f"{where}: mount", 0.0) for k in keys)
