"""Batch spec parsing (errors name the key), task planning and hashing, state file, lock."""
import json
import os
from pathlib import Path

import pytest

from conftest import ROOT
from lsd3d_usd.batch.spec import load_spec, parse_spec
from lsd3d_usd.batch.state import BatchLock, BatchState
from lsd3d_usd.batch.tasks import plan_batch
from lsd3d_usd.errors import InputError

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"


def write_spec(tmp_path, text, name="spec.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_sample_spec_parses_and_plans():
    spec = load_spec(ROOT / "samples" / "batch" / "small.toml")
    assert [s.name for s in spec.scenes] == ["crossing-morning", "crossing-rain", "suburb-7"]
    assert spec.output == (ROOT / "samples" / "batch" / "small_out").resolve()
    morning = spec.scenes[0]
    assert morning.options["layout"] == LAYOUT.resolve()
    assert morning.options["ggds.steps"] == 20 and morning.options["ggds.resolution"] == (240, 135)
    assert spec.scenes[2].split_chunks == "always" and "layout" not in spec.scenes[2].options
    plans = plan_batch(spec)
    # hand_crossing spans 4 chunks: below the auto threshold, so one scene task each;
    # the generated scene is split on request: 4 chunk tasks + a scene task after them.
    assert [len(p.tasks) for p in plans] == [1, 1, 5]
    scene_task = plans[2].tasks[-1]
    assert scene_task.kind == "scene" and set(scene_task.deps) == {t.id for t in plans[2].tasks[:4]}
    assert all(t.kind == "chunk" and not t.deps for t in plans[2].tasks[:4])


def test_corridor_dataset_sample_plans_ten_logs_after_its_scene():
    """samples/batch/corridor_dataset.toml (docs/datasets.md's measured batch): the README's
    1 km corridor, its chunks, the scene after them, ten logs after the scene, one merge."""
    spec = load_spec(ROOT / "samples" / "batch" / "corridor_dataset.toml")
    tasks = [t for p in plan_batch(spec) for t in p.tasks]
    kinds = [t.kind for t in tasks]
    assert kinds.count("chunk") == 10 and kinds.count("scene") == 1
    assert kinds.count("dataset_log") == 10 and kinds.count("dataset_merge") == 1
    logs = [t for t in tasks if t.kind == "dataset_log"]
    assert all(tuple(t.deps) == ("corridor/scene",) for t in logs)
    assert set(tasks[-1].deps) == {t.id for t in logs}


def test_defaults_merge_relative_paths_and_output(tmp_path):
    (tmp_path / "lay").mkdir()
    (tmp_path / "lay" / "x.usda").write_bytes(LAYOUT.read_bytes())
    p = write_spec(tmp_path, f"""
[batch]
output = "res"
[defaults]
steps = 3
resolution = [64, 48]
extent = "300x200"
[[scene]]
name = "one"
layout = "lay/x.usda"
[[scene]]
name = "two"
steps = 0
output = "/{tmp_path.as_posix().strip('/')}/elsewhere"
""")
    spec = load_spec(p)
    one, two = spec.scenes
    assert spec.output == tmp_path / "res"
    assert one.output == tmp_path / "res" / "one"
    assert one.options == {"ggds.steps": 3, "ggds.resolution": (64, 48),
                           "layout": tmp_path / "lay" / "x.usda"}
    assert two.options == {"ggds.steps": 0, "ggds.resolution": (64, 48), "extent": (300.0, 200.0)}
    assert one.config().ggds.steps == 3 and one.config().layout == tmp_path / "lay" / "x.usda"
    assert two.output == tmp_path / "elsewhere"
    assert spec.state_path == tmp_path / "res" / "batch-state.json"


@pytest.mark.parametrize("body,match", [
    ('[[scene]]\nname = "a"\nsteps = "ten"', r"scene\[0\] \('a'\)\.steps: expected an integer"),
    ('[[scene]]\nname = "a"\nstesp = 3', r"unknown key 'stesp' \(did you mean 'steps'\?\)"),
    ('[[scene]]\nname = "a"\nresolution = "64by48"', r"scene\[0\] \('a'\)\.resolution: expected two"),
    ('[[scene]]\nname = "a"\nstyle = "rural"', r"\.style: expected one of urban, suburban, highway"),
    ('[[scene]]\nsteps = 1', r"scene\[0\]: missing key 'name'"),
    ('[[scene]]\nname = "a b"', r"scene\[0\] \('a b'\)\.name: 'a b' must start"),
    ('[[scene]]\nname = "a"\n[[scene]]\nname = "a"', r"scene\[1\] \('a'\)\.name: 'a' already used"),
    ('[[scene]]\nname = "a"\nlayout = "nope.usda"', r"scene\[0\] \('a'\)\.layout: no such file"),
    ('[defaults]\nsurfels = 0\n[[scene]]\nname = "a"', r"defaults\.surfels: must be in \[1, 4000000\], got 0"),
    ('[batch]\nworkers = 0\n[[scene]]\nname = "a"', r"batch\.workers: must be >= 1"),
    ('[batch]\noutput = "o"\n[[scene]]\nname = "a"\noutput = "."', r"into the batch output folder"),
    ('[scenes]\nname = "a"', r"unknown key 'scenes' \(did you mean 'scene'\?\)"),
    ('[batch]\nretries = 1', r"no scenes"),
    ('[[scene]\nname = "a"', r"not valid TOML"),
    ('[[scene]]\nname = "a"\nlat = 91', r"\.lat: must be in \[-90.0, 90.0\]"),
    ('[[scene]]\nname = "a"\nprior = "magic"', r"\.prior 'magic': use 'procedural' or 'diffusers:DIR'"),
    ('[[scene]]\nname = "a"\nggds.lr.sh_dcc = 0.1', r"unknown key 'ggds.lr.sh_dcc' \(did you mean 'ggds.lr.sh_dc'\?\)"),
    ('[[scene]]\nname = "a"\nggds.weights.tv = -1', r"\.ggds.weights.tv: must be >= 0.0"),
    ('[[scene]]\nname = "a"\nweather = "sunny"', r"\.weather: expected one of clear, "),
    ('[[scene]]\nname = "a"\nresume = true', r"unknown key 'resume'"),
])
def test_bad_specs_name_the_key(tmp_path, body, match):
    p = write_spec(tmp_path, body)
    with pytest.raises(InputError, match=match) as e:
        load_spec(p)
    assert "spec.toml" in str(e.value)


def test_layout_errors_found_at_planning_name_the_scene(tmp_path):
    lay = tmp_path / "nolanes.usda"
    lay.write_text('#usda 1.0\n(\n defaultPrim = "World"\n metersPerUnit = 1\n upAxis = "Z"\n)\n'
                   'def Xform "World" {\n def Scope "Layout" {\n }\n}\n')
    p = write_spec(tmp_path, f'[[scene]]\nname = "a"\nlayout = "{LAYOUT}"\n'
                             f'[[scene]]\nname = "b"\nlayout = "{lay}"\n')
    spec = load_spec(p)
    with pytest.raises(InputError, match=r"scene\[1\] \('b'\): .*nolanes.usda: the layout has no drivable"):
        plan_batch(spec)
    assert not spec.output.exists()         # planning writes nothing


def test_task_hash_follows_inputs(tmp_path):
    def hashes(extra=""):
        p = write_spec(tmp_path, f'[batch]\noutput = "o"\n[[scene]]\nname = "a"\nlayout = "{LAYOUT}"\n'
                                 f'split_chunks = true\nsteps = 0\n{extra}')
        return {t.id: t.inputs_hash for plan in plan_batch(load_spec(p)) for t in plan.tasks}
    base = hashes()
    assert base == hashes()                               # stable
    prompt = hashes('prompt = "rain"')
    assert prompt["a/scene"] != base["a/scene"]           # a scene option changes the scene task
    assert {k: v for k, v in prompt.items() if k != "a/scene"} == \
        {k: v for k, v in base.items() if k != "a/scene"}  # ... but not the chunk tasks
    assert len(base) == 5


def test_state_done_needs_same_hash_and_outputs(tmp_path):
    from lsd3d_usd.batch.tasks import Task
    out = tmp_path / "file.usda"
    out.write_text("x")
    t = Task("s/scene", "scene", "s", "h1", {}, outputs=(str(out),))
    st = BatchState(tmp_path / "state.json")
    assert not st.is_done(t)
    st.record(t, "done", 1, result={"k": 1})
    again = BatchState(tmp_path / "state.json")           # persisted
    assert again.is_done(t)
    assert not again.is_done(Task("s/scene", "scene", "s", "h2", {}, outputs=(str(out),)))
    out.unlink()
    assert not again.is_done(t)                           # outputs gone: redo
    again.record(t, "failed", 3, error="boom")
    assert not BatchState(tmp_path / "state.json").is_done(t)
    assert [p.name for p in tmp_path.iterdir() if "tmp" in p.name] == []   # atomic, no leftovers
    (tmp_path / "state.json").write_text("{broken")
    with pytest.raises(InputError, match="state.json: batch state is not valid JSON"):
        BatchState(tmp_path / "state.json")


def test_lock_refuses_a_second_live_driver_and_clears_a_stale_one(tmp_path):
    lock = tmp_path / ".batch.lock"
    lock.write_text("1")          # pid 1 is alive (init): a running driver
    with pytest.raises(InputError, match="another batch"):
        with BatchLock(tmp_path):
            pass
    lock.write_text("999999999")  # no such process: stale
    with BatchLock(tmp_path):
        assert lock.read_text() == str(os.getpid())
    assert not lock.exists()
