"""Batch spec: a TOML file listing scenes to generate (docs/batch.md).

    [batch]                 # optional
    output = "out"          # base folder of relative scene outputs and of the batch state
    workers = 2             # optional; the CLI's --workers wins
    retries = 2             # optional; the CLI's --retries wins

    [defaults]              # optional: generate settings shared by every scene
    steps = 50
    resolution = "480x270"
    ggds.lr.sh_dc = 0.01    # any setting by its key (lsd3d-usd generate --list-options)

    [[scene]]
    name = "crossing"
    layout = "../layouts/hand_crossing.usda"   # relative to the spec file
    prompt = "rainy autumn evening in Seattle"

    [dataset]               # optional: the scenes as one dataset (batch/dataset.py)
    format = "nuscenes"
    routes = 10

    [[scene]]
    name = "generated-3"
    seed = 3                # no layout: one is generated from seed/extent/style
    extent = [300, 300]
    style = "suburban"

Every error names the file and the key (``scene[2] ("crossing").steps``), so a
bad spec is refused before any work starts.
"""
from __future__ import annotations

import difflib
import re
from dataclasses import dataclass, field
from pathlib import Path


from lsd3d_usd import configtree as ct
from lsd3d_usd.config import GenerateConfig
from lsd3d_usd.configtree import read_toml, resolve_paths
from lsd3d_usd.errors import InputError
from lsd3d_usd.limits import BATCH_SCENES, BATCH_SPEC_BYTES

SPLIT_CHOICES = ("auto", "always", "never")
# Injected failures, for tests of retry and reporting only (documented as such).
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


# ---------------------------------------------------------------- value checkers
# Each takes (value, where, base_dir) and returns the normalised value or raises InputError.
def _int(lo=None):
    def check(v, where, base):
        if isinstance(v, bool) or not isinstance(v, int):
            raise InputError(f"{where}: expected an integer, got {v!r}")
        if lo is not None and v < lo:
            raise InputError(f"{where}: must be >= {lo}, got {v}")
        return v
    return check


def _float(positive=False, lo=None, hi=None):
    def check(v, where, base):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(f"{where}: expected a number, got {v!r}")
        v = float(v)
        if positive and not v > 0:
            raise InputError(f"{where}: must be > 0, got {v}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise InputError(f"{where}: must be in [{lo}, {hi}], got {v}")
        return v
    return check


def _str(v, where, base):
    if not isinstance(v, str):
        raise InputError(f"{where}: expected a string, got {v!r}")
    return v


def _bool(v, where, base):
    if not isinstance(v, bool):
        raise InputError(f"{where}: expected true or false, got {v!r}")
    return v


def _choice(choices):
    def check(v, where, base):
        if v not in choices:
            raise InputError(f"{where}: expected one of {', '.join(map(str, choices))}, got {v!r}")
        return v
    return check


def _path(v, where, base):
    v = _str(v, where, base)
    p = Path(v).expanduser()
    return p if p.is_absolute() else (base / p).resolve()


def _paths(v, where, base):
    if not isinstance(v, list):
        raise InputError(f"{where}: expected a list of folders, got {v!r}")
    return [_path(x, f"{where}[{k}]", base) for k, x in enumerate(v)]


def _split(v, where, base):
    if isinstance(v, bool):
        return "always" if v else "never"
    return _choice(SPLIT_CHOICES)(v, where, base)


# Run control a scene (or [defaults]) may set besides the generate settings of the
# configuration tree (lsd3d_usd.config.GenerateConfig: flat keys such as steps, tables).
RUN_KEYS = {"force": _bool, "region_workers": _int(1)}
# batch-only keys of a scene (and of [defaults], except name/output)
SCENE_KEYS = {"name": _str, "output": _path, "split_chunks": _split}
BATCH_KEYS = {"output": _path, "workers": _int(1), "retries": _int(0), "allowed_outputs": _paths}
TOP_KEYS = ("batch", "defaults", "scene", "dataset", "scenarios")


@dataclass
class SceneSpec:
    name: str
    output: Path                     # absolute scene folder
    options: dict                    # {setting key: value} given for this scene (config tree)
    force: bool = False
    region_workers: int = 1          # GGDS regions of this scene in parallel (docs/batch.md)
    split_chunks: str = "auto"       # auto: split large layouts (tasks.AUTO_SPLIT_MIN_CHUNKS)
    index: int = 0

    def config(self):
        """The scene's GenerateConfig (defaults + the spec's settings)."""
        return ct.apply(GenerateConfig(), self.options, f"{self.where}.")

    @property
    def where(self) -> str:
        return f"scene[{self.index}] ({self.name!r})"


@dataclass
class BatchSpec:
    path: Path
    output: Path
    scenes: list[SceneSpec] = field(default_factory=list)
    workers: int | None = None
    retries: int | None = None
    dataset: object = None           # batch.dataset.DatasetSpec of a [dataset] table, or None
    scenarios: object = None         # batch.scenarios.ScenariosSpec of a [scenarios] table
    executor: str = "local"          # where tasks run (set by the command); a scene's GGDS
    address: str | None = None       # regions use the same executor

    @property
    def state_path(self) -> Path:
        return self.output / "batch-state.json"


def _unknown(key: str, known, where: str) -> InputError:
    near = difflib.get_close_matches(key, list(known), n=1)
    hint = f" (did you mean {near[0]!r}?)" if near else ""
    return InputError(f"{where}: unknown key {key!r}{hint}; known keys: {', '.join(sorted(known))}")


def _table(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise InputError(f"{where}: expected a table, got {type(value).__name__}")
    return value


def _options(table: dict, where: str, base: Path, allowed: dict) -> dict:
    out = {}
    for key, value in table.items():
        check = allowed.get(key)
        if check is None:
            raise _unknown(key, allowed, where)
        out[key] = check(value, f"{where}.{key}", base)
    return out


def _settings(table: dict, where: str, base: Path, extra: dict) -> tuple[dict, dict]:
    """Split a [defaults] / [[scene]] table into (generate settings checked against the
    configuration tree, {key: value} of the batch-only keys in ``extra``)."""
    own = _options({k: v for k, v in table.items() if k in extra}, where, base, extra)
    rest = {k: v for k, v in table.items() if k not in extra}
    try:
        settings = ct.check_table(GenerateConfig, rest, where,
                                  base=lambda vals: resolve_paths(vals, GenerateConfig, base))
    except ct.UnknownKey as e:   # name the batch-only keys too
        flat = {lf.meta["alias"] for lf in ct.leaves(GenerateConfig) if lf.meta["alias"]}
        every = flat | set(extra) | {lf.key for lf in ct.leaves(GenerateConfig)}
        near = difflib.get_close_matches(e.key, sorted(every), n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise InputError(f"{where}: unknown key {e.key!r}{hint}; known keys: "
                         f"{', '.join(sorted(flat | set(extra)))}, or any setting by its "
                         "dotted key (lsd3d-usd generate --list-options)") from None
    return settings, own


def _check_output(p: Path, roots: list[Path], where: str, strict: bool) -> Path:
    """``p``'s real path, refused (one line) unless it lies inside the spec's folder or an
    ``allowed_outputs`` folder (``roots``, real paths; ``strict``: not equal to one) and is
    no ancestor of the spec's folder (a scene folder is rewritten and pruned)."""
    real = p.resolve()
    spec_dir = roots[0]
    if spec_dir.is_relative_to(real) and (strict or real != spec_dir):
        raise InputError(f"{where}: {p} resolves to {real}, which holds the spec's folder "
                         f"{spec_dir}; refusing to write there")
    for r in roots:
        if real.is_relative_to(r) and (real != r or not strict):
            return real
    shown = f" (resolves to {real})" if real != p else ""
    raise InputError(f"{where}: {p}{shown} lies outside the spec's folder {spec_dir}; list a "
                     "folder holding it in [batch] allowed_outputs to write there")


def parse_spec(data: dict, path: Path) -> BatchSpec:
    """Validate a parsed TOML document; ``path`` is the spec file (relative paths resolve
    against its folder)."""
    path = Path(path).absolute()
    base = path.parent
    w = path.name
    for key in data:
        if key not in TOP_KEYS:
            raise _unknown(key, TOP_KEYS, w)
    batch = _options(_table(data.get("batch", {}), f"{w}: [batch]"), f"{w}: batch", base, BATCH_KEYS)
    output = batch.get("output", base / f"{path.stem}_out")
    roots = [base.resolve()] + [r.resolve() for r in batch.get("allowed_outputs", [])]
    output = _check_output(output, roots, f"{w}: batch.output", strict=False)
    default_keys = {**RUN_KEYS, "split_chunks": _split}
    defaults, default_own = _settings(_table(data.get("defaults", {}), f"{w}: [defaults]"),
                                      f"{w}: defaults", base, default_keys)
    scenes_raw = data.get("scene", [])
    if not isinstance(scenes_raw, list) or not scenes_raw:
        raise InputError(f"{w}: no scenes: add at least one [[scene]] table with a name")
    BATCH_SCENES.check(len(scenes_raw), w)
    spec = BatchSpec(path, output, workers=batch.get("workers"), retries=batch.get("retries"))
    names, outputs = {}, {}
    for i, raw in enumerate(scenes_raw):
        where = f"{w}: scene[{i}]"
        raw = _table(raw, where)
        if "name" in raw and isinstance(raw["name"], str):
            where = f"{w}: scene[{i}] ({raw['name']!r})"
        # layout is relative to the spec file, output to [batch].output.
        settings, own = _settings(raw, where, base, {**RUN_KEYS, **SCENE_KEYS,
                                                     "output": lambda v, wh, b: _path(v, wh, output)})
        name = own.pop("name", None)
        if name is None:
            raise InputError(f"{where}: missing key 'name' (a short folder-safe scene name)")
        if not NAME_RE.match(name):
            raise InputError(f"{where}.name: {name!r} must start with a letter or digit and hold only "
                             "letters, digits, '_', '-' or '.'")
        if name in names:
            raise InputError(f"{where}.name: {name!r} already used by scene[{names[name]}]")
        names[name] = i
        merged = {**defaults, **settings}
        if "layout" in settings:  # a scene's own layout wins over generator defaults
            for k in ("extent", "style"):
                if k not in settings:
                    merged.pop(k, None)
        own = {**default_own, **own}
        out_dir = own.pop("output", output / name)
        out_dir = _check_output(out_dir, roots, f"{where}.output", strict=True)
        if out_dir in outputs:
            raise InputError(f"{where}.output: {out_dir} is also the output of scene "
                             f"{outputs[out_dir]!r}")
        outputs[out_dir] = name
        if out_dir == output or output.is_relative_to(out_dir):
            raise InputError(f"{where}.output: a scene cannot be written into the batch output "
                             f"folder itself ({output}); use a subfolder")
        split = own.pop("split_chunks", "auto")
        force = own.pop("force", False)
        region_workers = own.pop("region_workers", 1)
        if "layout" in merged and not Path(merged["layout"]).is_file():
            raise InputError(f"{where}.layout: no such file: {merged['layout']}")
        spec.scenes.append(SceneSpec(name, out_dir, merged, force, region_workers, split, i))
    if "dataset" in data:
        from lsd3d_usd.batch.dataset import parse_dataset
        spec.dataset = parse_dataset(data["dataset"], f"{w}: dataset", output)
        # held to the spec's folder like batch.output and the scenes' outputs
        d_out = _check_output(spec.dataset.output, roots, f"{w}: dataset.output", strict=True)
        for sc in spec.scenes:
            if d_out == sc.output or d_out.is_relative_to(sc.output) \
                    or sc.output.is_relative_to(d_out):
                raise InputError(f"{w}: dataset.output: {d_out} overlaps the output of scene "
                                 f"{sc.name!r} ({sc.output}); use a folder of its own")
        if output.is_relative_to(d_out):
            raise InputError(f"{w}: dataset.output: {d_out} holds the batch output {output}; "
                             "use a subfolder of it")
        spec.dataset.output = d_out
    if "scenarios" in data:
        from lsd3d_usd.batch.scenarios import parse_scenarios
        spec.scenarios = parse_scenarios(data["scenarios"], f"{w}: scenarios", base, output)
        s_out = _check_output(spec.scenarios.output, roots, f"{w}: scenarios.output", strict=True)
        for sc in spec.scenes:
            if s_out == sc.output or s_out.is_relative_to(sc.output) or sc.output.is_relative_to(s_out):
                raise InputError(f"{w}: scenarios.output: {s_out} overlaps the output of scene "
                                 f"{sc.name!r} ({sc.output}); use a folder of its own")
        spec.scenarios.output = s_out
    return spec


def load_spec(path: str | Path) -> BatchSpec:
    path = Path(path)
    if path.is_file():
        BATCH_SPEC_BYTES.check(path.stat().st_size, str(path))
    return parse_spec(read_toml(path, f"{path}: no such batch spec file"), path)
