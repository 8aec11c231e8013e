"""Hostile input, third campaign (issue 60): resume state, dataset folders and batch dataset
outputs. Every reproduction is built here (links, tampered state files, specs); none needs a
generated scene: the checks run before a scene is opened."""
from __future__ import annotations

import json
import os

import pytest
from conftest import LAYOUT

from lsd3d_usd import scene as S
from lsd3d_usd.datasets import build
from lsd3d_usd.datasets.options import DatasetOptions
from lsd3d_usd.errors import InputError

RECORD = {"format": "nuscenes", "version": "v1.0-lsd3d", "logs": []}


def _snapshot(folder):
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(folder.rglob("*"))}


@pytest.fixture
def fake(tmp_path):
    """A fake scene folder (just its root file: the folder checks come first), a dataset
    folder with a state record, and an OUTSIDE folder holding precious data."""
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / S.ROOT_FILE).write_text("#usda 1.0\n")
    ds = tmp_path / "ds"
    (ds / ".lsd3d" / "logs").mkdir(parents=True)
    (ds / ".lsd3d" / "dataset.json").write_text(json.dumps(RECORD))
    outside = tmp_path / "OUTSIDE"
    outside.mkdir()
    (outside / "precious.txt").write_bytes(b"precious data " * 100)
    return scene, ds, outside


def _dataset(scene, ds, *extra):
    return ["dataset", scene, "-o", ds, "--format", "nuscenes", "--no-progress", *extra]


# -------------------------------------------------- 1. --resume follows planted links
@pytest.mark.parametrize("planted", [".lsd3d/logs/0000.journal.jsonl", ".lsd3d/work/0000",
                                     "samples/CAM_FRONT", ".lsd3d/logs",
                                     ".lsd3d-0000-scene.mcap.partial"])
def test_resume_refuses_a_link_in_the_dataset_folder(fake, cli_error, planted):
    scene, ds, outside = fake
    before = _snapshot(outside)
    link = ds / planted
    if planted == ".lsd3d/logs":
        (ds / ".lsd3d" / "logs").rmdir()
    link.parent.mkdir(parents=True, exist_ok=True)
    target = outside / "precious.txt" if planted.endswith(("l", "partial")) else outside
    os.symlink(target, link)
    cli_error(_dataset(scene, ds, "--resume"), "symbolic link", str(link))
    assert _snapshot(outside) == before


def test_checkpoint_load_does_not_truncate_through_a_link(fake):
    _, ds, outside = fake
    logs = ds / ".lsd3d" / "logs"
    (logs / "0000.partial.json").write_text('{"next_tick": 1, "journal_bytes": 3}')
    os.symlink(outside / "precious.txt", logs / "0000.journal.jsonl")
    before = _snapshot(outside)
    with pytest.raises(InputError, match="symbolic link"):
        build.Checkpoints(logs, 0).load()
    with pytest.raises(InputError, match="symbolic link"):
        build.Checkpoints(logs, 0).clear()
    assert _snapshot(outside) == before


# ------------------------------------------------- 2. batch [dataset] output held in
SPEC = f"""
[batch]
output = "out"
[defaults]
layout = "{LAYOUT}"
steps = 0
[[scene]]
name = "crossing"
[dataset]
output = "{{out}}"
format = "nuscenes"
seconds = 1.0
"""


@pytest.mark.parametrize("kind", ["absolute", "dotdot", "link", "scene", "batch"])
def test_batch_dataset_output_stays_in_the_spec_folder(tmp_path, cli_error, kind):
    spec_dir = tmp_path / "spec"
    spec_dir.mkdir()
    outside = tmp_path / "OUTSIDE"
    outside.mkdir()
    out = {"absolute": str(outside / "ds"), "dotdot": "../../OUTSIDE/ds", "link": "lnk/ds",
           "scene": "crossing/ds", "batch": ".."}[kind]
    if kind == "link":
        (spec_dir / "out").mkdir()
        os.symlink(outside, spec_dir / "out" / "lnk")
    p = spec_dir / "spec.toml"
    p.write_text(SPEC.format(out=out))
    for extra in (["--dry-run"], []):
        cli_error(["batch", p, *extra], "spec.toml: dataset.output")
    assert list(outside.iterdir()) == []


# ---------------------------------- 3. --overwrite deletes only the dataset's own files
@pytest.mark.parametrize("record", ["{}", "[1]", "garbage{", json.dumps(RECORD)])
def test_overwrite_refuses_a_foreign_file(fake, cli_error, record):
    scene, ds, _ = fake
    (ds / ".lsd3d" / "dataset.json").write_text(record)
    (ds / "samples" / "CAM_FRONT").mkdir(parents=True)
    (ds / "samples" / "CAM_FRONT" / "a.jpg").write_bytes(b"jpg")
    (ds / "my_notes.txt").write_text("mine")
    before = _snapshot(ds)
    line = cli_error(_dataset(scene, ds, "--overwrite"), str(ds))
    assert "my_notes.txt" in line or "dataset.json" in line
    assert _snapshot(ds) == before


def test_overwrite_deletes_the_datasets_own_files(fake):
    _, ds, _ = fake
    for f in ("samples/CAM_FRONT/a.jpg", "v1.0-lsd3d/sample.json", ".lsd3d/work/0000/rig.usda",
              "maps/m.png", "lidarseg/v1.0-lsd3d/x_lidarseg.bin"):
        (ds / f).parent.mkdir(parents=True, exist_ok=True)
        (ds / f).write_bytes(b"x")
    build.start_dataset(ds, DatasetOptions(overwrite=True), [])
    assert sorted(str(p.relative_to(ds)) for p in ds.rglob("*")) == [
        ".lsd3d", ".lsd3d/dataset.json", ".lsd3d/logs"]


def test_overwrite_refuses_a_link_anywhere(fake, cli_error):
    scene, ds, outside = fake
    os.symlink(outside, ds / "samples")
    cli_error(_dataset(scene, ds, "--overwrite"), "symbolic link")
    assert (ds / "samples").is_symlink() and (outside / "precious.txt").exists()


# ----------------------------------------------- 10. resume state read with validation
@pytest.mark.parametrize("state", ["", "garbage{", "[]", "[" * 100_000, '"text"'])
def test_resume_refuses_a_tampered_dataset_record(fake, cli_error, state):
    scene, ds, _ = fake
    (ds / ".lsd3d" / "dataset.json").write_text(state)
    with pytest.raises(InputError) as e:
        build.check_resume(ds / ".lsd3d", RECORD, ds)
    assert "dataset.json" in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("part, journal", [
    ("", b""), ("{", b""), ('{"journal_bytes": 0}', b""),
    ('{"next_tick": "3", "journal_bytes": 0}', b""),
    ('{"next_tick": 3, "journal_bytes": -5}', b""),
    ('{"next_tick": 3, "journal_bytes": 1e300}', b""),
    ('{"next_tick": 3, "journal_bytes": 4}', b"[1]\n"),
    ('{"next_tick": 3, "journal_bytes": 6}', b"garbag"),
])
def test_checkpoint_load_refuses_tampered_state(tmp_path, part, journal):
    logs = tmp_path / "ds" / ".lsd3d" / "logs"
    logs.mkdir(parents=True)
    (logs / "0000.partial.json").write_text(part)
    (logs / "0000.journal.jsonl").write_bytes(journal)
    with pytest.raises(InputError) as e:
        build.Checkpoints(logs, 0).load()
    assert "\n" not in str(e.value) and "0000." in str(e.value)


def test_a_tampered_log_record_is_one_line(tmp_path):
    ds = tmp_path / "ds"
    (ds / ".lsd3d" / "logs").mkdir(parents=True)
    (ds / ".lsd3d" / "logs" / "0000.json").write_text("{trunc")
    with pytest.raises(InputError, match="0000.json"):
        build.merge(ds, DatasetOptions(), type("W", (), {"finish": lambda self, r: r})(), 1)


# ------------------------------------------- 4. render -o the scene folder (or a file)
@pytest.mark.parametrize("where", ["scene", "inside", "parent", "file"])
def test_render_refuses_an_output_in_the_scene_or_a_file(fake, cli_error, where):
    scene, _, _ = fake
    (scene / "frames").mkdir()
    (scene / "note.txt").write_text("x")
    out = {"scene": scene, "inside": scene / "frames", "parent": scene.parent,
           "file": scene / "note.txt"}[where]
    before = _snapshot(scene)
    for extra in (["--camera", "/World/Cam"], ["--rig", "waymo5"]):
        cli_error(["render", scene, "-o", out, *extra, "--no-progress"],
                  {"file": "exists and is not a folder", "parent": "lies inside it"}.get(
                      where, "inside the scene folder"))
    assert _snapshot(scene) == before


# ------------------------------ 5. export-ply and inspect compose layers outside the scene
@pytest.mark.parametrize("argv", [["inspect"], ["inspect", "--flatten"],
                                  ["splats", "export-ply", "{scene}", "-o", "{tmp}/o.ply"]])
def test_commands_refuse_a_scene_composing_outside_layers(tmp_path, cli_error, argv):
    scene, outside = tmp_path / "scene", tmp_path / "OUTSIDE"
    scene.mkdir()
    outside.mkdir()
    (outside / "secret.usda").write_text('#usda 1.0\ndef Xform "Secret" {}\n')
    (scene / S.ROOT_FILE).write_text('#usda 1.0\n(\n    subLayers = [@../OUTSIDE/secret.usda@]\n)\n')
    argv = [a.format(scene=scene, tmp=tmp_path) for a in argv]
    if argv[0] == "inspect":
        argv.insert(1, str(scene))
    cli_error(argv, "outside the scene folder", "secret.usda")
    assert not (tmp_path / "o.ply").exists()


# ------------------------------------------------- 15. refused runs leave no files
@pytest.fixture
def layout_scene(tmp_path):
    """A scene folder of the README layout alone (no surfels): routes plan, rigs drive."""
    import shutil
    scene = tmp_path / "lscene"
    (scene / "layers").mkdir(parents=True)
    shutil.copy(LAYOUT, scene / "layers" / "layout.usda")
    (scene / S.ROOT_FILE).write_text('#usda 1.0\n(\n    subLayers = [@./layers/layout.usda@]\n)\n')
    return scene


def _refuse(*a, **k):
    raise InputError("planted: the scene is refused here")


@pytest.mark.parametrize("empty_dir", [False, True])
def test_dataset_refused_after_its_checks_leaves_nothing(layout_scene, tmp_path, cli_error,
                                                         monkeypatch, empty_dir):
    from lsd3d_usd.datasets import drive
    monkeypatch.setattr(drive, "drive", _refuse)
    ds = tmp_path / "ds"
    if empty_dir:
        ds.mkdir()
    argv = _dataset(layout_scene, ds, "--route", "w_in,j_we,e_out", "--seconds", "0.5")
    cli_error(argv, "planted")
    assert list(ds.iterdir()) == [] if empty_dir else not ds.exists()
    monkeypatch.undo()
    # the next plain run is not refused as "not empty" (refused here again, by the seconds)
    cli_error([*argv, "--seconds", "-1"], "--seconds -1")


@pytest.mark.parametrize("mode", [["--rig", "waymo5", "--no-video"],
                                  ["--camera", "/World/Cam"]])
def test_render_refused_after_its_checks_leaves_nothing(layout_scene, tmp_path, cli_error,
                                                        monkeypatch, mode):
    from lsd3d_usd.views import preview, rig
    monkeypatch.setattr(rig, "SceneReader", _refuse)
    monkeypatch.setattr(preview, "camera_prim", _refuse)
    out = tmp_path / "frames"
    cli_error(["render", layout_scene, "-o", out, *mode, "--no-progress"], "planted")
    assert not out.exists()


def test_batch_refuses_the_dataset_output_before_preparing_scenes(tmp_path, cli_error):
    spec_dir = tmp_path / "spec"
    (spec_dir / "out" / "ds").mkdir(parents=True)
    (spec_dir / "out" / "ds" / "mine.txt").write_text("mine")
    p = spec_dir / "spec.toml"
    p.write_text(SPEC.format(out="ds"))
    cli_error(["batch", p], "dataset.output", "no lsd3d-usd dataset")
    assert not (spec_dir / "out" / "crossing").exists()


# ---------------------------------- 8. FIFOs in a scene folder, or given as --lidar FILE
def _cli_subprocess(*args, timeout=120):
    import subprocess
    import sys
    return subprocess.run([sys.executable, "-m", "lsd3d_usd", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("cmd", ["validate", "render", "dataset"])
def test_a_fifo_in_the_scene_folder_is_refused_not_read(layout_scene, tmp_path, cmd):
    from conftest import error_line
    fifo = layout_scene / "layers" / "extra.usda"
    os.mkfifo(fifo)
    root = layout_scene / S.ROOT_FILE
    root.write_text(root.read_text().replace("@./layers/layout.usda@",
                                             "@./layers/layout.usda@, @./layers/extra.usda@"))
    argv = {"validate": ["validate", layout_scene],
            "render": ["render", layout_scene, "-o", tmp_path / "o", "--rig", "waymo5"],
            "dataset": _dataset(layout_scene, tmp_path / "ds", "--seconds", "0.5")}[cmd]
    error_line(_cli_subprocess(*argv), "extra.usda", "FIFO")
    assert not (tmp_path / "o").exists() and not (tmp_path / "ds").exists()


def test_lidar_at_a_fifo_is_named_as_such(layout_scene, tmp_path, cli_error):
    os.mkfifo(tmp_path / "l.toml")
    cli_error(["render", layout_scene, "-o", tmp_path / "o", "--rig", "waymo5",
               "--lidar", tmp_path / "l.toml"], "l.toml", "not a regular file")


# ------------------------------------------ 9. file sizes of LiDAR TOML and trajectories
def test_lidar_toml_and_trajectory_sizes_are_limited(layout_scene, tmp_path, cli_error):
    from lsd3d_usd import limits
    big = tmp_path / "big.toml"
    big.write_text("[lidar]\nbeams = 8\nelevation_min = -10\nelevation_max = 10\ncolumns = 100\n"
                   + "# pad\n" * (limits.LIDAR_FILE_BYTES.value // 6 + 1))
    base = ["render", layout_scene, "-o", tmp_path / "o", "--rig", "waymo5"]
    cli_error([*base, "--lidar", big], "big.toml", "exceeds the limit")
    named = tmp_path / "named.toml"
    named.write_text(f'[lidar]\nname = "{"x" * 5000}"\nbeams = 8\nelevation_min = -10\n'
                     'elevation_max = 10\ncolumns = 100\n')
    cli_error([*base, "--lidar", named], "named.toml", "name", "exceeds the limit")
    traj = tmp_path / "poses.json"
    with open(traj, "wb") as f:
        f.truncate(limits.TRAJECTORY_FILE_BYTES.value + 1)
    cli_error([*base, "--trajectory", traj], "poses.json", "exceeds the limit")
    assert not (tmp_path / "o").exists()


# ------------------------------------------------- 11. trajectories: NaN, deep nesting
@pytest.mark.parametrize("text, needle", [
    ('[{"t": 0, "x": NaN, "y": 0, "yaw": 0}, {"t": 1, "x": 1, "y": 0, "yaw": 0}]', "finite"),
    ('[{"t": 0, "x": 0, "y": 0, "yaw": Infinity}, {"t": 1, "x": 1, "y": 0, "yaw": 0}]',
     "finite"),
    ("[" * 100_000 + "]" * 100_000, "nested"),
])
def test_trajectory_nan_and_nesting_are_one_line(layout_scene, tmp_path, cli_error, text,
                                                 needle):
    traj = tmp_path / "poses.json"
    traj.write_text(text)
    cli_error(["render", layout_scene, "-o", tmp_path / "o", "--rig", "waymo5",
               "--trajectory", traj, "--no-progress"], "poses.json", needle)
    assert not (tmp_path / "o").exists()


# --------------------------------------- 6. a width alone counts with the camera's height
def test_a_width_alone_is_counted_with_its_height(layout_scene, tmp_path, cli_error):
    cli_error(_dataset(layout_scene, tmp_path / "ds", "--width", "8192"), "--width 8192",
              "8192x4608", "exceed the limit")
    cli_error(["render", layout_scene, "-o", tmp_path / "o", "--rig", "waymo5",
               "--resolution", "8192", "--no-video"], "--resolution 8192", "exceed the limit")
    assert not (tmp_path / "ds").exists() and not (tmp_path / "o").exists()


def test_a_width_alone_is_counted_for_a_usd_camera():
    from pxr import Usd, UsdGeom

    from lsd3d_usd.render.camera import from_usd
    stage = Usd.Stage.CreateInMemory()
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateHorizontalApertureAttr(10.0)
    cam.CreateVerticalApertureAttr(10.0)          # square: 8192 wide is 8192 high
    with pytest.raises(InputError, match="exceed the limit"):
        from_usd(cam.GetPrim(), width=8192)


# ----------------------------------------------- 7. seconds and rate x seconds products
@pytest.mark.parametrize("argv, needle", [
    (["--seconds", "1e9"], "--seconds"),
    (["--seconds", "80000", "--camera-hz", "12"], "ticks of a log"),
])
def test_dataset_seconds_are_bounded(layout_scene, tmp_path, cli_error, argv, needle):
    cli_error(_dataset(layout_scene, tmp_path / "ds", *argv), needle, "exceeds the limit")
    assert not (tmp_path / "ds").exists()


def test_render_rig_frames_are_bounded(layout_scene, tmp_path, cli_error):
    cli_error(["render", layout_scene, "-o", tmp_path / "o", "--rig", "waymo5", "--fps", "1000",
               "--seconds", "80000", "--no-video"], "--fps x --seconds", "exceeds the limit")
    assert not (tmp_path / "o").exists()


# --seconds and --fps are bounded by the configuration tree (actors.config, as for generate),
# the samples they make together by limits.ACTOR_SAMPLES
@pytest.mark.parametrize("argv, needle, why", [
    (["--seconds", "1e9"], "--seconds", "must be in"),
    (["--seconds", "80000", "--fps", "100"], "--seconds", "must be in"),
    (["--moving", "500", "--seconds", "3600", "--fps", "100"], "--moving", "exceeds the limit"),
])
def test_actors_add_seconds_and_samples_are_bounded(layout_scene, cli_error, argv, needle, why):
    before = _snapshot(layout_scene)
    cli_error(["actors", "add", layout_scene, *argv], needle, why)
    assert _snapshot(layout_scene) == before


# -------------------------------------------- 13. next_tick out of range or inconsistent
@pytest.mark.parametrize("tick, lines", [(99, 1), (3, 1), (3, 3), (2, 1), (0, 0)])
def test_resume_refuses_an_inconsistent_next_tick(tmp_path, monkeypatch, tick, lines):
    from lsd3d_usd.datasets import drive
    from lsd3d_usd.datasets.drive import LogPlan
    from lsd3d_usd.datasets.timeline import Timeline
    monkeypatch.setattr(drive, "drive", _refuse)     # never reached: the checkpoint is refused
    logs = tmp_path / "ds" / ".lsd3d" / "logs"
    logs.mkdir(parents=True)
    journal = b"".join(b'{"sample": []}\n' for _ in range(lines))
    (logs / "0000.journal.jsonl").write_bytes(journal)
    (logs / "0000.partial.json").write_text(json.dumps({"next_tick": tick,
                                                        "journal_bytes": len(journal)}))
    writer = type("W", (), {"checkpoint": None, "restore": None})()
    plan = LogPlan(0, tmp_path, "scene", ["w_in"], "scene:w_in")
    with pytest.raises(InputError, match="next_tick"):
        build.run_log(tmp_path / "ds", DatasetOptions(resume=True), plan, writer, None,
                      Timeline(4.0, 4.0, 2.0, 1.5))     # 6 ticks, keyframes at 0, 2, 4


# ------------------------------------ 14. temp files of a killed writer do not survive
def test_resume_removes_temp_files_of_a_killed_writer(tmp_path):
    ds = tmp_path / "ds"
    (ds / ".lsd3d" / "logs").mkdir(parents=True)
    opt = DatasetOptions(resume=True)
    (ds / ".lsd3d" / "dataset.json").write_text(json.dumps(build.dataset_record(opt, [])))
    tmp = ds / "samples" / "CAM_FRONT" / ".x__CAM_FRONT__1.tmp-4242-0123abcd.jpg"
    tmp.parent.mkdir(parents=True)
    tmp.write_bytes(b"torn")
    (tmp.parent / "x__CAM_FRONT__0.jpg").write_bytes(b"kept")
    build.start_dataset(ds, opt, [])
    assert [p.name for p in tmp.parent.iterdir()] == ["x__CAM_FRONT__0.jpg"]


# ------------------------------------------------ 16 (part). unclear or silent inputs
def test_lidar_on_a_single_camera_render_is_refused(layout_scene, tmp_path, cli_error):
    cli_error(["render", layout_scene, "-o", tmp_path / "o", "--camera", "/World/Cam",
               "--lidar", "hdl32"], "--lidar hdl32", "--rig")
    assert not (tmp_path / "o").exists()


def test_lidar_toml_may_start_with_a_bom(tmp_path):
    from lsd3d_usd.sensors.lidar import lidar_model
    f = tmp_path / "bom.toml"
    f.write_bytes(b"\xef\xbb\xbf[lidar]\nbeams = 8\nelevation_min = -10\nelevation_max = 10\n"
                  b"columns = 100\n")
    assert len(lidar_model(str(f)).elevations_deg) == 8
