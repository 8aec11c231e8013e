"""Typed configuration trees: nested dataclasses whose leaves carry their help text, CLI flag,
flat alias and limits, so that CLI flags, config-file / batch TOML keys, ``--set`` overrides,
``--help`` defaults and provenance are all derived from one definition and cannot drift.

A leaf is declared with :func:`option`::

    @dataclass
    class Sizes:
        steps: int = option(250, help="GGDS steps", flag="--steps", lo=0)

Keys are dotted paths from the root (``ggds.lr.sh_dc``). A leaf may also have a flat
``alias`` (``steps``), accepted at the top level of a TOML table: batch specs and
``generate --config`` files use the short names users already know, or nested tables /
TOML dotted keys for everything else. A ``dict`` leaf (e.g. loss weights by name) takes
sub-keys (``ggds.weights.tv``), checked against the names its ``keys`` callable allows.

Values from TOML arrive typed; values from the command line and ``--set`` arrive as text and
are parsed by the leaf's type. Every error is one line naming the key and where it came from.
"""
from __future__ import annotations

import argparse
import dataclasses
import difflib
import functools
import math
import sys
import types
import typing
from dataclasses import MISSING, dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any, Callable

import tomllib

from lsd3d_usd.errors import InputError

_META = "lsd3d_option"


def option(default: Any = MISSING, *, help: str, flag: str | None = None,
           alias: str | None = None, choices: tuple | None = None, lo: float | None = None,
           hi: float | None = None, check: Callable[[Any, str], Any] | None = None,
           keys: Callable[[], dict] | None = None, default_factory: Callable | None = None,
           metavar: str | None = None, negate: str | None = None, recorded: Any = MISSING):
    """A configuration leaf.

    help: one sentence (the default is appended automatically in --help).
    flag: the CLI flag (``--steps``) or None (reachable by --set / config file only).
    negate: for a bool leaf defaulting to True, a ``--no-...`` flag that sets it False.
    alias: the flat key accepted at the top level of a TOML table.
    choices / lo / hi: allowed values (inclusive bounds).
    check: ``check(value, where) -> value`` for anything else (raise InputError).
    keys: for a dict leaf, ``keys() -> {name: default}``, the allowed sub-keys.
    recorded: what a stored configuration without this leaf meant (one written before the
        leaf existed, when the code behaved as this value does): from_dict fills it in, so
        resuming or re-measuring an older run keeps its behaviour.
    """
    meta = {"help": help, "flag": flag, "alias": alias, "choices": choices, "lo": lo, "hi": hi,
            "check": check, "keys": keys, "metavar": metavar, "negate": negate,
            "recorded": recorded}
    if default_factory is not None:
        return dataclasses.field(default_factory=default_factory, metadata={_META: meta})
    return dataclasses.field(default=default, metadata={_META: meta})


@dataclass(frozen=True)
class Leaf:
    path: tuple[str, ...]
    type: Any                 # the resolved annotation
    default: Any
    meta: dict

    @property
    def key(self) -> str:
        return ".".join(self.path)

    @property
    def help(self) -> str:
        return self.meta["help"]

    @property
    def base(self):
        """The leaf's type without Optional."""
        return _unwrap_optional(self.type)[0]


# ------------------------------------------------------------------------------ the tree
@functools.lru_cache(maxsize=None)
def _hints(cls) -> dict:
    # cached: get_type_hints re-evaluates every annotation string, and a batch spec checks
    # its scenes' tables against the same tree thousands of times
    return typing.get_type_hints(cls)


def _default(f: dataclasses.Field):
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:  # type: ignore[misc]
        return f.default_factory()        # type: ignore[misc]
    return MISSING


def leaves(cls, prefix: tuple[str, ...] = ()) -> list[Leaf]:
    """Every leaf of the tree rooted at dataclass ``cls``, depth first in field order."""
    return list(_leaves(cls, tuple(prefix)))


@functools.lru_cache(maxsize=None)
def _leaves(cls, prefix: tuple[str, ...]) -> tuple[Leaf, ...]:
    out = []
    hints = _hints(cls)
    for f in fields(cls):
        t = hints[f.name]
        if is_dataclass(t) and isinstance(t, type):
            out.extend(leaves(t, prefix + (f.name,)))
        elif _META in f.metadata:
            out.append(Leaf(prefix + (f.name,), t, _default(f), f.metadata[_META]))
    return tuple(out)


@functools.lru_cache(maxsize=None)
def _index(cls) -> tuple[dict, dict]:
    by_key = {lf.key: lf for lf in leaves(cls)}
    by_alias = {lf.meta["alias"]: lf for lf in by_key.values() if lf.meta["alias"]}
    return by_key, by_alias


def _did_you_mean(key: str, known) -> str:
    near = difflib.get_close_matches(key, list(known), n=1)
    return f" (did you mean {near[0]!r}?)" if near else ""


class UnknownKey(InputError):
    """A key that is not in the tree (``.key`` holds it, as written)."""

    def __init__(self, message: str, key: str):
        super().__init__(message)
        self.key = key


def unknown_key(key: str, known, where: str) -> UnknownKey:
    known = sorted(known)
    near = difflib.get_close_matches(key, known, n=12, cutoff=0.0) if len(known) > 40 else known
    shown = ", ".join(near) + (f" (and {len(known) - len(near)} more)" if len(near) < len(known)
                               else "")
    return UnknownKey(f"{where}unknown key {key!r}{_did_you_mean(key, known)}; known keys: "
                      f"{shown}", key)


# ------------------------------------------------------------------------------ values
def _unwrap_optional(t) -> tuple[Any, bool]:
    origin = typing.get_origin(t)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(t) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(t)) == 2:
            return args[0], True
    return t, False


def _type_name(t) -> str:
    base, _ = _unwrap_optional(t)
    if typing.get_origin(base) is tuple:
        return "WxH"
    return getattr(base, "__name__", str(base))


def _parse_scalar(base, value, where: str):
    if base is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in ("true", "yes", "on", "1", "false",
                                                                 "no", "off", "0"):
            return value.strip().lower() in ("true", "yes", "on", "1")
        raise InputError(f"{where}: expected true or false, got {value!r}")
    if base is int:
        if isinstance(value, bool):
            raise InputError(f"{where}: expected an integer, got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip().replace("_", ""))
            except ValueError:
                pass
        raise InputError(f"{where}: expected an integer, got {value!r}")
    if base is float:
        if isinstance(value, bool):
            raise InputError(f"{where}: expected a number, got {value!r}")
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{where}: expected a number, got {value!r}") from None
        if not math.isfinite(v):
            raise InputError(f"{where}: must be a finite number, got {value!r}")
        return v
    if base is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: expected a string, got {value!r}")
        return value
    if base is Path:
        if not isinstance(value, (str, Path)) or not str(value):
            raise InputError(f"{where}: expected a path, got {value!r}")
        return Path(value).expanduser()
    raise TypeError(f"configtree: unsupported leaf type {base!r} at {where}")


def _parse_pair(base, value, where: str):
    kinds = typing.get_args(base)
    kind = kinds[0] if kinds else float
    parts = None
    if isinstance(value, str):
        bits = value.lower().replace(" ", "").split("x")
        try:
            parts = [kind(b) for b in bits]
        except ValueError:
            parts = None
    elif isinstance(value, (list, tuple)) and all(
            isinstance(p, (int, float)) and not isinstance(p, bool) for p in value):
        parts = [kind(p) for p in value]
        if kind is int and any(p != q for p, q in zip(parts, value)):
            parts = None
    if parts is None or len(parts) != 2 or not all(math.isfinite(p) and p > 0 for p in parts):
        what = "integers" if kind is int else "numbers"
        eg = "480x270" if kind is int else "200x200"
        raise InputError(f"{where}: expected two positive {what} as WxH (e.g. {eg}) or "
                         f"[w, h], got {value!r}")
    return tuple(parts)


def _bounds(leaf: Leaf, v, where: str):
    m = leaf.meta
    lo, hi = m["lo"], m["hi"]
    items = v if isinstance(v, tuple) else (v,)
    for x in items:
        if lo is not None and hi is not None and not lo <= x <= hi:
            raise InputError(f"{where}: must be in [{lo}, {hi}], got {x}")
        if lo is not None and x < lo:
            raise InputError(f"{where}: must be >= {lo}, got {x}")
        if hi is not None and x > hi:
            raise InputError(f"{where}: must be <= {hi}, got {x}")
    if m["choices"] is not None and v not in m["choices"]:
        raise InputError(f"{where}: expected one of {', '.join(map(str, m['choices']))}, "
                         f"got {v!r}")
    return v


def coerce(leaf: Leaf, value, where: str):
    """Parse / check one value for ``leaf`` (text from the CLI, or a typed TOML value)."""
    base, optional = _unwrap_optional(leaf.type)
    if value is None or (optional and isinstance(value, str)
                         and value.strip().lower() in ("none", "null", "")):
        if not optional:
            raise InputError(f"{where}: a value is required")
        return None
    if typing.get_origin(base) is dict:
        raise InputError(f"{where}: is a table; set its entries, e.g. {leaf.key}.NAME=VALUE")
    if typing.get_origin(base) is tuple:
        v = _parse_pair(base, value, where)
    else:
        v = _parse_scalar(base, value, where)
    v = _bounds(leaf, v, where)
    if leaf.meta["check"] is not None:
        v = leaf.meta["check"](v, where)
    return v


def _coerce_entry(leaf: Leaf, name: str, value, where: str):
    """One entry of a dict leaf (e.g. a loss weight): a float >= 0, or none for the default."""
    allowed = leaf.meta["keys"]() if leaf.meta["keys"] else None
    if allowed is not None and name not in allowed:
        raise unknown_key(name, allowed, f"{where.rsplit('.', 1)[0]}: ")
    val_t = typing.get_args(_unwrap_optional(leaf.type)[0])[1]
    sub = Leaf(leaf.path + (name,), val_t, None, {**leaf.meta, "check": None, "keys": None})
    return coerce(sub, value, where)


# ------------------------------------------------------------------------------ building
def _get(cfg, path):
    for p in path:
        cfg = getattr(cfg, p)
    return cfg


def _set(cfg, path, value):
    """A copy of ``cfg`` with the leaf at ``path`` replaced (dataclasses stay immutable-safe)."""
    head, rest = path[0], path[1:]
    if not rest:
        return dataclasses.replace(cfg, **{head: value})
    return dataclasses.replace(cfg, **{head: _set(getattr(cfg, head), rest, value)})


def flatten(data: dict, cls, where: str, written: dict | None = None) -> dict[str, Any]:
    """A TOML table (nested tables, dotted keys and flat aliases mixed) → {leaf key: value},
    values not yet checked. Unknown keys are refused with a did-you-mean. ``written``, if
    given, receives {leaf key: the key as the user wrote it} (for error messages)."""
    by_key, by_alias = _index(cls)
    groups = {lf.path[:i] for lf in by_key.values() for i in range(1, len(lf.path))}
    known = sorted(set(by_key) | set(by_alias))
    out: dict[str, Any] = {}
    names = {} if written is None else written

    def walk(table: dict, prefix: tuple[str, ...]):
        for k, v in table.items():
            path = prefix + (str(k),)
            key = ".".join(path)
            if not prefix and k in by_alias and not (isinstance(v, dict) and path in groups):
                out[by_alias[k].key] = v
                names[by_alias[k].key] = k
            elif key in by_key:
                lf = by_key[key]
                if typing.get_origin(lf.base) is dict and isinstance(v, dict):
                    for name, val in v.items():
                        out[f"{key}.{name}"] = val
                        names[f"{key}.{name}"] = f"{key}.{name}"
                else:
                    out[key] = v
                    names[key] = key
            elif path in groups and isinstance(v, dict):
                walk(v, path)
            elif prefix and ".".join(prefix) in by_key:   # entry of a dict leaf
                out[key] = v
                names[key] = key
            else:
                raise unknown_key(key, known, where)
    walk(data, ())
    return out


def apply(cfg, values: dict[str, Any], where: str = "", display: dict | None = None):
    """``cfg`` with ``values`` ({leaf key or dict-leaf entry key: value}) applied and checked.
    Errors read "<where><name>: ..." with name = display.get(key, key) (e.g. the flag)."""
    by_key, _ = _index(type(cfg))
    display = display or {}
    for key, value in values.items():
        name = f"{where}{display.get(key, key)}"
        if key in by_key:
            lf = by_key[key]
            cfg = _set(cfg, lf.path, coerce(lf, value, name))
            continue
        parent, _, entry = key.rpartition(".")
        lf = by_key.get(parent)
        if lf is None or typing.get_origin(lf.base) is not dict:
            raise unknown_key(key, by_key, where)
        entries = dict(_get(cfg, lf.path))
        entries[entry] = _coerce_entry(lf, entry, value, name)
        cfg = _set(cfg, lf.path, entries)
    return cfg


def check_table(cls, data: dict, where: str, base: Callable[[dict], dict] | None = None) -> dict:
    """{leaf key: checked value} of a TOML table; errors name each key as written
    ("<where>.steps: expected an integer"). ``base`` may rewrite the raw values first (e.g.
    resolve relative paths)."""
    written: dict = {}
    values = flatten(data, cls, f"{where}: ", written)
    if base is not None:
        values = base(values)
    cfg = cls()
    checked = {}
    for key, v in values.items():
        cfg = apply(cfg, {key: v}, f"{where}.", {key: written.get(key, key)})
        checked[key] = _get_key(cfg, key)
    return checked


def _get_key(cfg, key: str):
    by_key, _ = _index(type(cfg))
    if key in by_key:
        return _get(cfg, by_key[key].path)
    parent, _, entry = key.rpartition(".")
    return _get(cfg, by_key[parent].path)[entry]


def flag_names(cls) -> dict[str, str]:
    """{leaf key: its CLI flag} for error messages of values that came from flags."""
    return {lf.key: lf.meta["flag"] or lf.meta["negate"] or lf.key for lf in leaves(cls)}


def parse_assignments(items, cls, where: str = "--set ") -> dict[str, str]:
    """["ggds.lr.sh_dc=0.01", ...] → {key: text}; keys checked against the tree."""
    out = {}
    for item in items or ():
        key, sep, value = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise InputError(f"{where}{item!r}: use KEY=VALUE, e.g. ggds.steps=100")
        out[key] = value.strip()
    by_key, by_alias = _index(cls)
    resolved = {}
    for key, value in out.items():
        if key in by_alias and key not in by_key:
            key = by_alias[key].key
        resolved[key] = value
    return resolved


def from_table(cls, data: dict, where: str = "", base=None):
    """An instance of ``cls`` (or ``base`` updated) from a TOML-like table."""
    cfg = cls() if base is None else base
    return apply(cfg, flatten(data, cls, where), where)


def to_dict(cfg) -> dict:
    """Plain JSON-able nested dict of the tree (Paths as strings, tuples as lists)."""
    def conv(v):
        if is_dataclass(v) and not isinstance(v, type):
            return {f.name: conv(getattr(v, f.name)) for f in fields(v)}
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {str(k): conv(x) for k, x in v.items()}
        return v
    return conv(cfg)


def from_dict(cls, data: dict):
    """Inverse of :func:`to_dict` (for stored configurations; unknown keys are an error;
    plain dataclass fields that are not options, set per run by the caller, are skipped)."""
    def options_only(c, d):
        hints = _hints(c)
        out = {}
        for f in fields(c):
            if f.name not in d:
                if _META in f.metadata and f.metadata[_META].get("recorded", MISSING) is not MISSING:
                    out[f.name] = f.metadata[_META]["recorded"]
                continue
            t = hints[f.name]
            if is_dataclass(t) and isinstance(t, type) and isinstance(d[f.name], dict):
                out[f.name] = options_only(t, d[f.name])
            elif _META in f.metadata:
                out[f.name] = d[f.name]
        retired = set(getattr(c, "RETIRED", ()))   # keys that are no longer options: dropped
        out.update({k: v for k, v in d.items()
                    if k not in {f.name for f in fields(c)} and k not in retired})
        return out
    return from_table(cls, options_only(cls, data), "stored configuration: ")


def diff(a, b) -> dict[str, tuple]:
    """{leaf key: (value in a, value in b)} for the leaves where two trees differ."""
    out = {}
    for lf in leaves(type(a)):
        va, vb = _get(a, lf.path), _get(b, lf.path)
        if va != vb:
            out[lf.key] = (va, vb)
    return out


def value(cfg, key: str):
    by_key, by_alias = _index(type(cfg))
    lf = by_key.get(key) or by_alias.get(key)
    if lf is None:
        raise unknown_key(key, by_key, "")
    return _get(cfg, lf.path)


# ------------------------------------------------------------------------------ argparse
def _show(v) -> str:
    if isinstance(v, tuple) and len(v) == 2:
        return f"{v[0]:g}x{v[1]:g}" if isinstance(v[0], float) else f"{v[0]}x{v[1]}"
    if isinstance(v, dict):
        return ", ".join(f"{k}={_show(x)}" for k, x in v.items())
    return str(v)


def default_text(lf: Leaf) -> str:
    if lf.default is MISSING:
        return ""
    return _show(lf.default)


def add_arguments(parser, cls, dest_prefix: str = "cfg:", titles: dict | None = None,
                  flags: dict | None = None, required: tuple = (),
                  exclusive: tuple[tuple[str, ...], ...] = ()) -> dict:
    """One argparse flag per leaf that has ``flag`` (and a ``--no-x`` for ``negate``), in one
    argument group per subtree (``titles`` names them). Defaults are suppressed so only flags
    given on the command line reach :func:`from_args`; --help shows each leaf's default.
    ``flags`` ({key: "--flag" or "--no-flag"}) gives flags to leaves of a tree another command
    also uses without them (a bool leaf's "--no-..." flag turns it off), or "" to leave a
    leaf without its flag on this command. Returns the groups by subtree name ("" = the parser
    itself). ``required`` keys' flags must be given; the keys of each ``exclusive`` tuple
    are flags of one mutually exclusive group (argparse refuses two of them together, as it
    would hand-declared ones)."""
    groups: dict = {"": parser}
    excl: dict = {}     # a tuple of keys -> its group, made at the first of its keys
    for lf in leaves(cls):
        m = lf.meta
        given = (flags or {}).get(lf.key)
        if given == "":
            continue
        if given:
            m = {**m, "negate": given, "flag": None} if given.startswith("--no-") and \
                lf.base is bool else {**m, "flag": given}
        if not (m["flag"] or m["negate"]):
            continue
        head = lf.path[0] if len(lf.path) > 1 else ""
        if head not in groups:
            title = (titles or {}).get(head)
            groups[head] = parser.add_argument_group(title) if head and title else parser
        target = groups[head]
        together = next((t for t in exclusive if lf.key in t), None)
        if together is not None:
            if together not in excl:
                excl[together] = target.add_mutually_exclusive_group()
            target = excl[together]
        dest = dest_prefix + lf.key
        shown = default_text(lf).replace("%", "%%")   # argparse formats help with %
        m = {**m, "help": m["help"].replace("%", "%%")}
        if m["negate"]:
            target.add_argument(m["negate"], dest=dest, action="store_const", const="false",
                                default=argparse.SUPPRESS, help=f"{m['help']}: off "
                                                                "(default: on)")
        if not m["flag"]:
            continue
        suffix = f" (default: {shown})" if shown not in ("", "None") else ""
        kw: dict[str, Any] = {"dest": dest, "default": argparse.SUPPRESS,
                              "help": m["help"] + suffix}
        if lf.key in required:
            kw.update(required=True, help=m["help"])   # given every time: no default to show
        if lf.base is bool:
            kw.update(action="store_const", const="true")
        elif m["choices"] is not None:
            kw["choices"] = [str(c) for c in m["choices"]]
        else:
            kw["metavar"] = m["metavar"] or _type_name(lf.type).upper()
        target.add_argument(m["flag"], **kw)
    return groups


def add_entry_flag(parser, flag: str, key: str, help: str, metavar: str = "W",
                   dest_prefix: str = "cfg:") -> None:
    """A flag for one entry of a dict leaf (e.g. --perceptual-weight → ggds.weights.perceptual)."""
    parser.add_argument(flag, dest=dest_prefix + key, default=argparse.SUPPRESS, metavar=metavar,
                        help=help)


def from_args(args, dest_prefix: str = "cfg:") -> dict[str, str]:
    """{key: text} for the configuration flags actually given on the command line."""
    return {k[len(dest_prefix):]: v for k, v in vars(args).items() if k.startswith(dest_prefix)}


def describe(cls) -> list[dict]:
    """Every leaf as {key, alias, flag, type, default, help} (for docs and --list-options)."""
    rows = []
    for lf in leaves(cls):
        rows.append({"key": lf.key, "alias": lf.meta["alias"], "flag": lf.meta["flag"] or
                     lf.meta["negate"], "type": _type_name(lf.type),
                     "default": default_text(lf), "help": lf.help})
    return rows


# ------------------------------------------------------------------------------ a command's tree
def read_toml(path, missing: str) -> dict:
    """The table of a TOML file; one InputError line (``missing`` when there is no file)."""
    p = Path(path)
    if p.exists() and not p.is_file() and not p.is_dir():
        raise InputError(f"{p}: not a regular file (a FIFO, socket or device); refusing to "
                         "read it")
    if not p.is_file():
        raise InputError(missing)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8-sig"))   # a leading BOM is fine
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{p}: not valid TOML: {e}") from None
    except UnicodeDecodeError as e:
        raise InputError(f"{p}: not UTF-8 text: {e}") from None
    except RecursionError:
        raise InputError(f"{p}: tables or arrays nested too deeply") from None


def load_file(path, cls, where: str = "--config") -> dict:
    """A TOML file → {leaf key: value} of ``cls`` (keys checked; relative path values made
    absolute against the file's folder)."""
    p = Path(path)
    data = read_toml(p, f"{where} {path}: no such file")
    return resolve_paths(flatten(data, cls, f"{p.name}: "), cls, p.parent.absolute())


def resolve_paths(values: dict, cls, base: Path) -> dict:
    """Relative path values of ``cls``'s Path leaves made absolute against ``base``."""
    paths = {lf.key for lf in leaves(cls) if lf.base is Path}
    out = dict(values)
    for k, v in values.items():
        if k in paths and isinstance(v, str) and v and not Path(v).expanduser().is_absolute():
            out[k] = str((base / Path(v).expanduser()).resolve())
    return out


def add_tree_options(parser, what: str) -> None:
    """--config FILE.toml, --set KEY=VALUE and --list-options for a command whose settings are
    a configuration tree."""
    parser.add_argument("--config", metavar="FILE.toml",
                        help=f"{what} settings from a TOML file: flat keys or tables / dotted "
                             "keys; flags and --set win over it")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="set any setting by key (repeatable; wins over flags and "
                             "--config; --list-options lists the keys)")
    parser.add_argument("--list-options", action="store_true",
                        help="print every setting's key, type, default and flag, and exit")


def print_options(cls, out=None) -> None:
    """--list-options: one line per leaf (key, type, default, help, flag / alias)."""
    out = out or sys.stdout
    for row in describe(cls):
        names = " / ".join(x for x in (row["flag"], row["alias"]) if x)
        print(f"{row['key']:32s} {row['type']:6s} {row['default'] or '-':>14s}  "
              f"{row['help']}" + (f"  [{names}]" if names else ""), file=out)


def layers_from_args(args, cls, dest_prefix: str = "cfg:") -> list[tuple[str, dict]]:
    """(where, {key: value}) of a command line in the order they apply: --config file, flags,
    --set (each later one wins)."""
    layers = []
    if getattr(args, "config", None):
        layers.append((f"{Path(args.config).name}: ", load_file(args.config, cls)))
    layers.append(("", resolve_paths(from_args(args, dest_prefix), cls, Path.cwd())))
    layers.append(("--set ", parse_assignments(getattr(args, "set", None), cls)))
    return layers


def build(cls, layers, display: dict | None = None):
    """Defaults of ``cls`` updated by each (where, {key: value}) layer; values from flags
    (where "") are named by their flag in errors."""
    cfg = cls()
    flags = {**flag_names(cls), **(display or {})}
    for where, values in layers:
        cfg = apply(cfg, values, where, flags if where == "" else None)
    return cfg


def command_config(args, cls, *, needs: dict | None = None, display: dict | None = None):
    """A command's tree from its parsed command line: None after printing it for
    --list-options; else InputError for the first of ``needs`` ({argument: message}) that is
    missing, else (the tree, the keys given explicitly)."""
    if getattr(args, "list_options", False):
        print_options(cls)
        return None
    for name, message in (needs or {}).items():
        if not getattr(args, name, None):
            raise InputError(message)
    return from_command_line(args, cls, display)


def from_command_line(args, cls, display: dict | None = None):
    """(the tree of ``cls`` from a parsed command line, the keys given explicitly)."""
    layers = layers_from_args(args, cls)
    return build(cls, layers, display), frozenset(k for _, v in layers for k in v)
