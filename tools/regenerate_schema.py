#!/usr/bin/env python
"""Regenerate lsd3d_usd/schemas/{generatedSchema.usda,plugInfo.json} from schema.usda.

usd-core ships ``pxr.Usd.usdGenSchema`` but its
``_GetAPISchemaOverridePropertyNames`` indexes ``propStack[0]`` for every
property of a class prim; properties that come only from built-in API schemas
(e.g. ``positions`` from ParticleFieldPositionAttributeAPI) have no local spec,
so the stack is empty and it raises IndexError. We wrap that function to skip
properties without specs — they cannot be API-schema overrides anyway.

Usage:
    python tools/regenerate_schema.py            # write the generated files
    python tools/regenerate_schema.py --check    # exit 1 if they are stale
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "lsd3d_usd" / "schemas"
GENERATED = ("generatedSchema.usda", "plugInfo.json")
PLUG_INFO_SUBST = {
    "@PLUG_INFO_LIBRARY_PATH@": "",
    "@PLUG_INFO_RESOURCE_PATH@": ".",
    "@PLUG_INFO_ROOT@": ".",
}


def _load_gen_namespace() -> dict:
    """Execute usdGenSchema's definitions (not its __main__ block) and patch them."""
    import importlib.util
    spec = importlib.util.find_spec("pxr.Usd.usdGenSchema")
    path = spec.origin
    src = Path(path).read_text()
    head, sep, tail = src.partition("\nif __name__ == '__main__':\n")
    if not sep:
        raise RuntimeError(f"unexpected layout of {path}: no __main__ block")
    import types
    module = types.ModuleType("_lsd3d_usdGenSchema")
    module.__file__ = path
    sys.modules[module.__name__] = module  # dataclasses look their module up
    ns = module.__dict__
    # The definitions set USD_DISABLE_PRIM_DEFINITIONS_FOR_USDGENSCHEMA before
    # importing pxr, so this must run before any other pxr import in-process.
    exec(compile(head, path, "exec"), ns)
    original = ns["_GetAPISchemaOverridePropertyNames"]
    Usd = ns["Usd"]

    class _PrimView:
        # Hide properties with an empty spec stack (built-in API properties).
        def __init__(self, prim):
            self._prim = prim

        def GetProperties(self):
            return [p for p in self._prim.GetProperties()
                    if p.GetPropertyStack(Usd.TimeCode.Default())]

        def __getattr__(self, name):
            return getattr(self._prim, name)

    ns["_GetAPISchemaOverridePropertyNames"] = (
        lambda prim, namespace: original(_PrimView(prim), namespace))
    ns["__main_block__"] = compile("if True:\n" + tail, path, "exec")
    return ns


def generate(out_dir: Path) -> None:
    ns = _load_gen_namespace()
    argv = sys.argv
    sys.argv = ["usdGenSchema", "--quiet", str(SCHEMA_DIR / "schema.usda"), str(out_dir)]
    import contextlib
    import io
    log = io.StringIO()
    try:
        # usdGenSchema warns about C++ build files a codeless schema never has.
        with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
            exec(ns["__main_block__"], ns)
    except SystemExit as e:
        if e.code not in (0, None):
            raise RuntimeError(f"usdGenSchema failed:\n{log.getvalue()}") from None
    finally:
        sys.argv = argv
    # A codeless schema has no library: fill the placeholders CMake would.
    plug = out_dir / "plugInfo.json"
    text = plug.read_text()
    for key, value in PLUG_INFO_SUBST.items():
        text = text.replace(key, value)
    plug.write_text(text)
    for name in GENERATED:
        if not (out_dir / name).is_file():
            raise RuntimeError(f"usdGenSchema did not write {name}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="only compare; exit 1 when the committed files are stale")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        generate(tmp)
        stale = [n for n in GENERATED
                 if not (SCHEMA_DIR / n).is_file()
                 or (SCHEMA_DIR / n).read_bytes() != (tmp / n).read_bytes()]
        if args.check:
            for n in stale:
                print(f"stale: lsd3d_usd/schemas/{n} (run tools/regenerate_schema.py)")
            return 1 if stale else 0
        for n in GENERATED:
            shutil.copyfile(tmp / n, SCHEMA_DIR / n)
            print(f"wrote lsd3d_usd/schemas/{n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
