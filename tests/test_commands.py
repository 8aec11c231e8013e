"""inspect and validate on missing or corrupt files: one clear line, exit 1, nothing written."""
import os

import pytest

from lsd3d_usd import scene
from lsd3d_usd.splats import usdio


def _bad_files(tmp_path, field_factory):
    good = tmp_path / "good.usdc"
    usdio.write_surfel_file(str(good), field_factory(2000))
    trunc = tmp_path / "trunc.usdc"
    trunc.write_bytes(good.read_bytes()[: good.stat().st_size // 3])
    syntax = tmp_path / "syntax.usda"
    syntax.write_text('#usda 1.0\ndef Xform "A" {\n  float x = \n}\n')
    notusd = tmp_path / "notes.txt"
    notusd.write_text("hello")
    garbage = tmp_path / "garbage.usda"
    garbage.write_text("this is not usd")
    return {"missing": tmp_path / "missing.usdc", "truncated": trunc, "syntax": syntax,
            "not-usd": notusd, "garbage": garbage}


@pytest.mark.parametrize("command", ["validate", "inspect"])
def test_bad_input_gives_one_clear_line(tmp_path, field_factory, run_cli, command):
    files = _bad_files(tmp_path, field_factory)
    before = sorted(os.listdir(tmp_path))
    for kind, path in files.items():
        r = run_cli(command, path)
        assert r.returncode == 1, (kind, r.stdout, r.stderr)
        lines = [l for l in r.stderr.splitlines() if l.strip()]
        assert len(lines) == 1, (kind, r.stderr)
        assert lines[0].startswith("lsd3d-usd: error: ") and path.name in lines[0], lines[0]
        assert "Traceback" not in r.stderr
    assert sorted(os.listdir(tmp_path)) == before  # nothing written


def test_debug_shows_traceback(tmp_path, run_cli):
    r = run_cli("--debug", "inspect", tmp_path / "missing.usda")
    assert r.returncode != 0 and "Traceback" in r.stderr


def test_inspect_reports_stack_tree_and_stats(tmp_path, field_factory, run_cli):
    sc = scene.Scene.create(tmp_path / "s", seed=11)
    st = scene.new_stage()
    usdio.write_surfels(st, scene.SURFELS_PATH, field_factory(300))
    sc.write_layer("surfels", st, scene.provenance("surfels", seed=11))
    r = run_cli("inspect", sc.root)
    assert r.returncode == 0, r.stderr
    assert "surfels.usdc (usdc, " in r.stdout and "step=surfels" in r.stdout
    assert "Surfels [Lsd3dSurfelField] particles=300" in r.stdout
    assert "300 surfels, SH degree 1" in r.stdout


def test_inspect_flatten_is_parseable_usda(tmp_path, field_factory, run_cli):
    from pxr import Sdf

    sc = scene.Scene.create(tmp_path / "s")
    st = scene.new_stage()
    usdio.write_surfels(st, scene.SURFELS_PATH, field_factory(50))
    sc.write_layer("surfels", st)
    r = run_cli("inspect", "--flatten", sc.root)
    assert r.returncode == 0
    layer = Sdf.Layer.CreateAnonymous(".usda")
    assert layer.ImportFromString(r.stdout)
    assert layer.GetPrimAtPath("/World/Surfels").typeName == "Lsd3dSurfelField"


def test_scene_command_mutes_and_lists(tmp_path, run_cli):
    sc = scene.Scene.create(tmp_path / "s")
    sc.write_layer("ggds_20260101-000000.usdc", scene.new_stage())
    r = run_cli("scene", "mute", sc.root, "ggds_20260101-000000")
    assert r.returncode == 0, r.stderr
    r = run_cli("scene", "layers", sc.root)
    assert "ggds_20260101-000000" in r.stdout and "muted" in r.stdout
    r = run_cli("scene", "mute", sc.root, "nonexistent")
    assert r.returncode == 1 and "no layer 'nonexistent'" in r.stderr


def test_inspect_reports_disk_use_and_the_plugin_path(tmp_path, field_factory, capsys):
    """Sizes per layer (with its per-chunk files) and per folder, human-readable and in
    --json; the schema note names `lsd3d-usd plugin-path`'s folder."""
    import json

    import lsd3d_usd
    from lsd3d_usd import inspection
    from lsd3d_usd.cli import main
    sc = scene.Scene.create(tmp_path / "s")
    st = scene.new_stage()
    usdio.write_surfels(st, scene.SURFELS_PATH, field_factory(300))
    surfels = sc.write_layer("surfels", st)
    chunks = surfels.with_name("surfels_chunks")
    chunks.mkdir()
    (chunks / "chunk_0_0.usdc").write_bytes(b"x" * 2_500_000)
    run = sc.root / "ggds" / "ggds_20260101-000000"
    run.mkdir(parents=True)
    (run / "summary.json").write_bytes(b"y" * 1234)
    assert main(["inspect", str(sc.root), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    layer = next(x for x in info["layers"] if x["identifier"].endswith("surfels.usdc"))
    assert layer["bytes"] == surfels.stat().st_size + 2_500_000
    size = info["size"]
    assert size["folders"]["layers/surfels_chunks/"] == 2_500_000
    assert size["folders"]["ggds/ggds_20260101-000000/"] == 1234
    files = [p for p in sc.root.rglob("*") if p.is_file()]
    assert size["total_bytes"] == sum(p.stat().st_size for p in files)
    assert size["total_bytes"] == sum(v for k, v in size["folders"].items() if k.rstrip("/").count("/") == 0)
    assert info["schema"] == {"type": "Lsd3dSurfelField", "plugin_path": str(lsd3d_usd.SCHEMA_DIR),
                              "fallback": ["ParticleField"]}
    assert main(["inspect", str(sc.root)]) == 0
    text = capsys.readouterr().out
    assert f"Disk use: {inspection.human_size(size['total_bytes'])}" in text
    assert "    layers/surfels_chunks/" in text and "2.5 MB" in text
    assert f"PXR_PLUGINPATH_NAME={lsd3d_usd.SCHEMA_DIR} (`lsd3d-usd plugin-path`)" in text
    assert [inspection.human_size(n) for n in (999, 1000, 159_234_567, 3_500_000_000)] == [
        "999 B", "1.0 kB", "159.2 MB", "3.5 GB"]
