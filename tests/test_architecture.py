"""The package layering holds (import-linter contracts in pyproject.toml) and no `_private`
name crosses a package boundary."""
import ast
import subprocess
import sys
from pathlib import Path

from conftest import ROOT

PKG = ROOT / "lsd3d_usd"


def test_import_layers_hold():
    exe = Path(sys.executable).parent / "lint-imports"
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-m", "importlinter.cli"]
    res = subprocess.run(cmd + ["--no-cache"], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "BROKEN" not in res.stdout and "0 broken" in res.stdout


def _package(module: str) -> str:
    """lsd3d_usd.<top> of a dotted module name (top-level modules are their own package)."""
    parts = module.split(".")
    return ".".join(parts[:2])


def private_crossings(root: Path = PKG) -> list[str]:
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).with_suffix("")
        module = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        here = _package(module)
        tree = ast.parse(path.read_text(encoding="utf-8"))
        aliases = {}   # local name -> imported lsd3d_usd module
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 \
                    and node.module.startswith("lsd3d_usd"):
                for a in node.names:
                    target = f"{node.module}.{a.name}"
                    if a.name.startswith("_") and not a.name.startswith("__") \
                            and _package(node.module) != here:
                        out.append(f"{path.relative_to(root.parent)}:{node.lineno}: {target}")
                    aliases[a.asname or a.name] = target
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("lsd3d_usd") and a.asname:
                        aliases[a.asname] = a.name
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                    and node.value.id in aliases and node.attr.startswith("_") \
                    and not node.attr.startswith("__"):
                target = aliases[node.value.id]
                if _package(target) != here:
                    out.append(f"{path.relative_to(root.parent)}:{node.lineno}: {target}.{node.attr}")
    return out


def test_no_private_names_cross_packages():
    assert private_crossings() == []


def test_the_private_name_check_finds_a_crossing(tmp_path):
    pkg = tmp_path / "lsd3d_usd"
    (pkg / "a").mkdir(parents=True)
    (pkg / "b").mkdir()
    (pkg / "a" / "m.py").write_text("def _hidden():\n    pass\n")
    (pkg / "b" / "n.py").write_text("from lsd3d_usd.a.m import _hidden\n"
                                    "import lsd3d_usd.a.m as mm\nmm._hidden()\n")
    (pkg / "a" / "ok.py").write_text("from lsd3d_usd.a.m import _hidden\n")
    found = private_crossings(pkg)
    assert len(found) == 2 and all("b/n.py" in f for f in found)
