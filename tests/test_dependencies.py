"""Every third-party module the package imports is a declared dependency (or an optional
extra's), so the documented install runs it: no module may arrive only because a test extra
happens to pull it in."""
import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions

from conftest import ROOT


def _name(req: str) -> str:
    return re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0].lower().replace("_", "-")


def test_imports_are_declared_dependencies():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = dict(meta["optional-dependencies"])
    extras.pop("test")   # test tools are not the package's dependencies
    declared = {_name(r) for r in meta["dependencies"]}
    declared |= {_name(r) for reqs in extras.values() for r in reqs}
    modules = set()
    for f in (ROOT / "lsd3d_usd").rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                modules |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules.add(node.module.split(".")[0])
    dists = packages_distributions()
    missing = {}
    for m in sorted(modules - set(sys.stdlib_module_names) - {"lsd3d_usd"}):
        names = {d.lower().replace("_", "-") for d in dists.get(m, [m])}
        if not names & declared:
            missing[m] = sorted(names)
    assert not missing, f"imported but not declared in pyproject.toml: {missing}"
