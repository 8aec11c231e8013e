"""docs/extending.md's examples run: each `# file:` code block is written into a throw-away
package, its entry points are declared in a dist-info folder on PYTHONPATH, and the parts are
used through the command line and the registries."""
import json
import os
import re
import subprocess
import sys

import pytest

from conftest import ROOT

DOC = ROOT / "docs" / "extending.md"
LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"


def doc_blocks():
    """(files {relative path: code}, entry points {group: [line, ...]}) of the doc."""
    text = DOC.read_text(encoding="utf-8")
    files, groups = {}, {}
    for lang, body in re.findall(r"```(\w+)\n(.*?)```", text, flags=re.S):
        if lang == "python" and body.startswith("# file: "):
            first, _, code = body.partition("\n")
            files[first[len("# file: "):].strip()] = code
        elif lang == "toml" and "entry-points" in body:
            group = re.search(r'entry-points\."([^"]+)"', body).group(1)
            groups.setdefault(group, []).extend(   # TOML string -> entry_points.txt value
                ln.replace('"', "") for ln in body.splitlines()[1:] if "=" in ln)
    return files, groups


@pytest.fixture
def plugin_path(tmp_path):
    files, groups = doc_blocks()
    for rel, code in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        (p.parent / "__init__.py").touch()
        p.write_text(code)
    dist = tmp_path / "lsd3d_doc_examples-0.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: lsd3d-doc-examples\n"
                                   "Version: 0.0\n")
    (dist / "entry_points.txt").write_text("".join(
        f"[{g}]\n" + "\n".join(lines) + "\n" for g, lines in groups.items()))
    return tmp_path, files, groups


def test_the_doc_has_the_examples():
    files, groups = doc_blocks()
    assert {"lsd3d_usd.priors", "lsd3d_usd.losses"} <= set(groups)
    assert len(files) >= 2


def test_prior_and_loss_from_entry_points_run_in_generate(plugin_path, tmp_path):
    path, _, _ = plugin_path
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(path), str(ROOT)]))
    out = tmp_path / "scene"
    r = subprocess.run([sys.executable, "-m", "lsd3d_usd", "generate", "--layout", LAYOUT,
                        "-o", out, "--prior", "flat:0.8", "--set", "ggds.weights.sky_alpha=0.5",
                        "--steps", "3", "--surfels", "2000", "--resolution", "64x48",
                        "--views", "4", "--env-resolution", "128x64", "--no-actors",
                        "--set", "ggds.held_out=1", "--keep-checkpoint", "--no-progress"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    from lsd3d_usd import scene as S
    sc = S.Scene.open(out)
    run = sc.runs()[0]
    params = run.provenance["params"]
    params = json.loads(params) if isinstance(params, str) else params
    assert params["prior"] == "flat" and params["gain"] == 0.8
    meta = json.loads((sc.run_files(run.name).dir / "state.json").read_text())
    assert all("sky_alpha" in rec for rec in meta["history"])
    plan = json.loads((sc.run_files(run.name).dir / "run.json").read_text())
    assert plan["generate"]["ggds"]["weights"]["sky_alpha"] == 0.5
    bad = subprocess.run([sys.executable, "-m", "lsd3d_usd", "generate", "-o", tmp_path / "x",
                          "--prior", "flat:abc", "--steps", "1", "--layout", LAYOUT],
                         capture_output=True, text=True, env=env, timeout=300)
    assert bad.returncode == 1 and "the argument is a gain" in bad.stderr
    assert not (tmp_path / "x").exists()
