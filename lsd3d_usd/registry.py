"""Named, pluggable parts looked up in one registry each: priors, loss terms, map importers,
renderer backends, layout blocks, benchmarks (and the sensor models and dataset writers).

A registry holds the project's built-in entries (``"module:attribute"`` targets, imported only
when used, so listing names stays cheap) and the Python entry points of its group, so a
third-party package adds a part by declaring, in its own pyproject.toml::

    [project.entry-points."lsd3d_usd.priors"]
    myprior = "mypkg.prior:MY_PRIOR"

At run time ``register(name, "module:attribute")`` adds an entry by target: such entries
travel to worker processes (``portable()`` in the parent, ``adopt()`` in the worker; the
region workers of GGDS do this), since a worker imports the target itself. An object
registered directly (``register(name, obj)``) lives in this process only.

A target whose attribute ends in ``.toml`` (``"package:rigs/city.toml"``) names a data file
inside the package rather than an attribute: its entry is that file's ``Path`` (how sensor
rigs and LiDAR presets ship as data, not code).

A name that is registered twice (an entry point shadowing a built-in) is an error rather
than a silent override: which one runs must never depend on install order.
"""
from __future__ import annotations

import difflib
import importlib
import importlib.resources
from importlib import metadata
from pathlib import Path
from typing import Any

from lsd3d_usd.errors import InputError

REGISTRIES: dict[str, "Registry"] = {}   # by entry-point group, every registry of the process


def _is_target(obj: Any) -> bool:
    return isinstance(obj, str) and ":" in obj and all(obj.partition(":")[::2])


class Registry:
    """Entries of one kind: ``names()``, ``get(name)``; ``what`` names the kind in errors."""

    def __init__(self, group: str, what: str, builtins: dict[str, str]):
        self.group = group
        self.what = what
        self._targets: dict[str, str] = dict(builtins)
        self._runtime: dict[str, str] = {}     # targets registered at run time (portable)
        self._loaded: dict[str, Any] = {}
        self._order: list[str] = list(builtins)   # built-ins, entry points, then registrations
        self._scanned = False
        REGISTRIES.setdefault(group, self)   # the project's own (the first made)

    def _scan(self) -> None:
        if self._scanned:
            return
        self._scanned = True
        for ep in metadata.entry_points(group=self.group):
            if ep.name in self._targets and self._targets[ep.name] != ep.value:
                raise InputError(f"{self.what} {ep.name!r} is registered twice: {self._targets[ep.name]} "
                                 f"and the entry point {ep.value} ({self.group}); uninstall one")
            if ep.name not in self._order:
                self._order.append(ep.name)
            self._targets[ep.name] = ep.value

    def register(self, name: str, obj: Any, *, before: str | None = None) -> None:
        """Register ``obj``: a ``"module:attribute"`` target (portable to worker processes)
        or the object itself (this process only); in ``ordered()`` last, or before ``before``."""
        self._scan()
        if name in self._targets or name in self._loaded:
            raise InputError(f"{self.what} {name!r} is already registered")
        if before is not None and before not in self._order:
            raise InputError(f"{self.what} {before!r} (register before it) is not registered")
        if _is_target(obj):
            self._targets[name] = self._runtime[name] = obj
        else:
            self._loaded[name] = obj
        self._order.insert(self._order.index(before) if before else len(self._order), name)

    def unregister(self, name: str) -> None:
        self._loaded.pop(name, None)
        self._targets.pop(name, None)
        self._runtime.pop(name, None)
        if name in self._order:
            self._order.remove(name)

    def ordered(self) -> list[str]:
        """The names in registration order (built-ins first, as declared)."""
        self._scan()
        return list(self._order)

    def names(self) -> list[str]:
        self._scan()
        return sorted(set(self._targets) | set(self._loaded))

    def __contains__(self, name: str) -> bool:
        return name in self.names()

    def get(self, name: str) -> Any:
        self._scan()
        if name in self._loaded:
            return self._loaded[name]
        target = self._targets.get(name)
        if target is None:
            near = difflib.get_close_matches(name, self.names(), n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise InputError(f"unknown {self.what} {name!r}{hint}; known: {', '.join(self.names())}")
        module, _, attr = target.partition(":")
        if attr.endswith(".toml"):
            self._loaded[name] = _package_file(self.what, name, module, attr)
            return self._loaded[name]
        try:
            obj = importlib.import_module(module)
            for part in attr.split(".") if attr else ():
                obj = getattr(obj, part)
        except (ImportError, AttributeError) as e:
            raise InputError(f"{self.what} {name!r}: cannot load {target}: {e}") from None
        self._loaded[name] = obj
        return obj

    def items(self):
        """(name, entry) of every entry in registration order, loading each."""
        return [(n, self.get(n)) for n in self.ordered()]


def _package_file(what: str, name: str, module: str, rel: str) -> Path:
    try:
        path = Path(str(importlib.resources.files(module) / rel))
    except (ImportError, TypeError) as e:
        raise InputError(f"{what} {name!r}: cannot load {module}:{rel}: {e}") from None
    if not path.is_file():
        raise InputError(f"{what} {name!r}: {module}:{rel}: no such file ({path})")
    return path


def portable() -> dict[str, dict[str, str]]:
    """The run-time target registrations of every registry of this process, by group: what a
    worker process needs to resolve the same names (``adopt``)."""
    return {g: dict(r._runtime) for g, r in REGISTRIES.items() if r._runtime}


def adopt(registrations: dict[str, dict[str, str]]) -> None:
    """Apply a parent's ``portable()`` registrations in this (worker) process; names already
    registered with the same target are left as they are."""
    for group, entries in (registrations or {}).items():
        reg = REGISTRIES.get(group)
        if reg is None:   # a registry defined by a plugin module: import it by its group
            continue
        for name, target in entries.items():
            if reg._targets.get(name) != target:
                reg.register(name, target)
