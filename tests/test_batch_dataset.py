"""`batch` producing a dataset: a spec's [dataset] table becomes one task per scene x route
(after the scene's task) and one merge; the result loads with the nuScenes devkit and is the
dataset `lsd3d-usd dataset` makes of the same scene, byte for byte; a re-run does nothing."""
from __future__ import annotations

from pathlib import Path

import pytest
from conftest import ROOT

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"
SPEC = f"""
[batch]
output = "out"
[defaults]
layout = "{LAYOUT}"
steps = 0
surfels = 20000
resolution = [64, 48]
views = 2
env_resolution = [64, 32]
perceptual = false
parked = 1
moving = 2
[[scene]]
name = "crossing"
[dataset]
output = "ds"
format = "nuscenes"
routes = 2
seconds = 1.0
camera_hz = 2.0
lidar_hz = 2.0
keyframe_hz = 2.0
width = 48
"""


def _files(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and ".lsd3d" not in p.parts}


@pytest.mark.slow        # ~100 s on 2 cores: four process-pool tasks, then the command
def test_batch_makes_the_dataset_the_command_makes(tmp_path):
    from lsd3d_usd.batch.runner import run_batch
    from lsd3d_usd.batch.spec import load_spec
    from lsd3d_usd.cli import main
    from lsd3d_usd.execution import make_executor
    p = tmp_path / "spec.toml"
    p.write_text(SPEC)
    spec = load_spec(p)
    rep = run_batch(spec, make_executor("local", 2))
    assert rep.ok, [f.line() for f in rep.failed + rep.blocked]
    assert sorted(rep.done) == ["crossing/scene", "dataset/log_0000", "dataset/log_0001",
                                "dataset/merge"]
    ds = tmp_path / "out" / "ds"
    direct = tmp_path / "direct"
    assert main(["dataset", str(tmp_path / "out" / "crossing"), "-o", str(direct), "--format",
                 "nuscenes", "--routes", "2", "--seconds", "1", "--camera-hz", "2",
                 "--lidar-hz", "2", "--keyframe-hz", "2", "--width", "48", "--no-progress"]) == 0
    a, b = _files(ds), _files(direct)
    assert a.keys() == b.keys() and [k for k in a if a[k] != b[k]] == []
    nusc = pytest.importorskip("nuscenes.nuscenes").NuScenes(version="v1.0-lsd3d",
                                                            dataroot=str(ds), verbose=False)
    assert len(nusc.scene) == 2 and len(nusc.sample) == 4
    again = run_batch(load_spec(p), make_executor("local", 2))
    assert again.done == [] and len(again.skipped) == 4


def test_a_bad_dataset_table_is_refused_before_any_task(tmp_path, cli_error):
    p = tmp_path / "spec.toml"
    p.write_text(SPEC.replace('routes = 2', 'route = "w_in,j_zz"'))
    cli_error(["batch", p], "dataset", "'j_zz'")
    p.write_text(SPEC.replace('format = "nuscenes"', 'format = "coco"'))
    cli_error(["batch", p], "unknown dataset format 'coco'")
    p.write_text(SPEC.replace('routes = 2', 'routs = 2'))
    cli_error(["batch", p], "dataset: unknown key 'routs'")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow        # ~90 s on 2 cores: two batches, one on a fresh Ray instance
def test_ray_local_cluster_makes_the_same_dataset(tmp_path):
    """The same spec on a local Ray instance (two CPUs): the same tables as the process pool
    (tokens and files do not depend on where a log was rendered)."""
    ray = pytest.importorskip("ray", reason="ray is not installed (optional extra [ray])")
    from lsd3d_usd.batch.runner import run_batch
    from lsd3d_usd.batch.spec import load_spec
    from lsd3d_usd.execution import RayExecutor, make_executor
    runs = {}
    for kind in ("ray", "local"):
        d = tmp_path / kind
        d.mkdir()
        (d / "spec.toml").write_text(SPEC)
        ex = RayExecutor(num_cpus=2) if kind == "ray" else make_executor("local", 2)
        try:
            rep = run_batch(load_spec(d / "spec.toml"), ex)
        finally:
            ex.close()
        assert rep.ok, [f.line() for f in rep.failed + rep.blocked]
        runs[kind] = _files(d / "out" / "ds")
    assert not ray.is_initialized()
    a, b = runs["ray"], runs["local"]
    assert a.keys() == b.keys() and [k for k in a if a[k] != b[k]] == []
