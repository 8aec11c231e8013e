"""Named, pluggable parts (priors, loss terms, map importers, renderer backends) looked up in
one registry each.

A registry holds the project's built-in entries (``"module:attribute"`` targets, imported only
when used, so listing names stays cheap) and the Python entry points of its group, so a
third-party package adds a part by declaring, in its own pyproject.toml::

    [project.entry-points."lsd3d_usd.priors"]
    myprior = "mypkg.prior:MY_PRIOR"

A name that is registered twice (an entry point shadowing a built-in) is an error rather
than a silent override: which one runs must never depend on install order.
"""
from __future__ import annotations

import difflib
import importlib
from importlib import metadata
from typing import Any

from lsd3d_usd.errors import InputError


class Registry:
    """Entries of one kind: ``names()``, ``get(name)``; ``what`` names the kind in errors."""

    def __init__(self, group: str, what: str, builtins: dict[str, str]):
        self.group = group
        self.what = what
        self._targets: dict[str, str] = dict(builtins)
        self._loaded: dict[str, Any] = {}
        self._scanned = False

    def _scan(self) -> None:
        if self._scanned:
            return
        self._scanned = True
        for ep in metadata.entry_points(group=self.group):
            if ep.name in self._targets and self._targets[ep.name] != ep.value:
                raise InputError(f"{self.what} {ep.name!r} is registered twice: {self._targets[ep.name]} "
                                 f"and the entry point {ep.value} ({self.group}); uninstall one")
            self._targets[ep.name] = ep.value

    def register(self, name: str, obj: Any) -> None:
        """Register an object directly (tests, notebooks)."""
        self._scan()
        if name in self._targets or name in self._loaded:
            raise InputError(f"{self.what} {name!r} is already registered")
        self._loaded[name] = obj

    def unregister(self, name: str) -> None:
        self._loaded.pop(name, None)
        self._targets.pop(name, None)

    def names(self) -> list[str]:
        self._scan()
        return sorted(set(self._targets) | set(self._loaded))

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
        try:
            obj = importlib.import_module(module)
            for part in attr.split(".") if attr else ():
                obj = getattr(obj, part)
        except (ImportError, AttributeError) as e:
            raise InputError(f"{self.what} {name!r}: cannot load {target}: {e}") from None
        self._loaded[name] = obj
        return obj
