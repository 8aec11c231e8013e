"""Hostile input, third campaign (issue 60), the rest: defect 12 (a resume against changed
inputs), 10 (a log record of the wrong shape), 16 (LiDAR keys, MCAP resume, PLY) and the fuzz
test of the resume state files and the LiDAR TOML keys. One small dataset of a layout-only
scene is made per module (nuScenes, finished) and one killed (MCAP, after its first
keyframe); each case works on a copy."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import LAYOUT
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError

ROUTE = ["--route", "w_in,j_we,e_out", "--seconds", "1", "--camera-hz", "4", "--lidar-hz", "4",
         "--keyframe-hz", "2", "--width", "64", "--no-progress"]
LIDAR = ("[lidar]\nname = \"tiny\"\nbeams = 8\nelevation_min = -20.0\nelevation_max = 5.0\n"
         "columns = 90\nrotation_hz = 10\nmount = {x = 0.5, y = 0.0, z = 1.8}\n")
HERE = Path(__file__).parent


def _argv(scene, out, fmt, lidar, *extra):
    return ["dataset", str(scene), "-o", str(out), "--format", fmt, "--lidar", str(lidar),
            *ROUTE, *extra]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(scene, lidar file, finished nuScenes dataset, MCAP dataset killed after keyframe 1)."""
    root = tmp_path_factory.mktemp("resume")
    scene = root / "scene"
    (scene / "layers").mkdir(parents=True)
    shutil.copy(LAYOUT, scene / "layers" / "layout.usda")
    (scene / S.ROOT_FILE).write_text('#usda 1.0\n(\n    subLayers = [@./layers/layout.usda@]\n)\n')
    lidar = root / "tiny.toml"
    lidar.write_text(LIDAR)
    from lsd3d_usd.cli import main
    assert main(_argv(scene, root / "done", "nuscenes", lidar)) == 0
    r = subprocess.run([sys.executable, str(HERE / "dataset_faults.py"), "1",
                        *_argv(scene, root / "killed", "mcap", lidar)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode < 0, r.stderr
    assert (root / "killed" / ".lsd3d" / "logs" / "0000.partial.json").is_file()
    return scene, lidar, root / "done", root / "killed"


def _copy(made, tmp, which):
    """A private copy of the scene, LiDAR file and one prepared dataset under ``tmp``."""
    scene, lidar, done, killed = made
    shutil.copytree(scene, tmp / "scene", symlinks=True)
    shutil.copy(lidar, tmp / "tiny.toml")
    shutil.copytree(done if which == "done" else killed, tmp / "ds", symlinks=True)
    # the dataset records the scene and LiDAR paths it was made from: point them here
    rec = tmp / "ds" / ".lsd3d" / "dataset.json"
    rec.write_text(rec.read_text().replace(str(scene), str(tmp / "scene"))
                   .replace(str(lidar), str(tmp / "tiny.toml")))
    return tmp / "scene", tmp / "tiny.toml", tmp / "ds"


def _snapshot(folder, skip=None):
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() and not p.is_symlink()
                                         else os.readlink(p) if p.is_symlink() else None)
            for p in sorted(folder.rglob("*"))
            if skip is None or not (p == skip or skip in p.parents)}


# ------------------------------------------ 12. a resume against changed inputs is refused
@pytest.mark.parametrize("change, needle", [
    ("layer", "scene/layers/layout.usda changed since the dataset began"),
    ("root", "scene/scene.usda changed since the dataset began"),
    ("lidar", "tiny.toml changed since the dataset began"),
    ("removed", "scene/layers/extra.usda is missing now"),
])
def test_resume_refuses_changed_inputs(made, tmp_path, cli_error, change, needle):
    scene, lidar, ds = _copy(made, tmp_path, "done")
    rec = json.loads((ds / ".lsd3d" / "dataset.json").read_text())
    assert set(rec["inputs"]) >= {"scene/scene.usda", "scene/layers/layout.usda"}
    if change == "layer":
        with open(scene / "layers" / "layout.usda", "a") as f:
            f.write("\n# an actor more\n")
    elif change == "root":
        with open(scene / S.ROOT_FILE, "a") as f:
            f.write("\n")
    elif change == "lidar":
        lidar.write_text(LIDAR.replace("columns = 90", "columns = 91"))
    else:
        # a sublayer recorded at the start and gone now (deleted between kill and resume)
        rec["inputs"]["scene/layers/extra.usda"] = "sha256 0123456789abcdef"
        (ds / ".lsd3d" / "dataset.json").write_text(json.dumps(rec))
    before = _snapshot(ds)
    cli_error(_argv(scene, ds, "nuscenes", lidar, "--resume"), needle, "--overwrite")
    assert _snapshot(ds) == before


def test_resume_of_unchanged_inputs_goes_on(made, tmp_path):
    from lsd3d_usd.cli import main
    scene, lidar, ds = _copy(made, tmp_path, "done")
    os.utime(scene / "layers" / "layout.usda", (1, 1))      # touched, not changed
    assert main(_argv(scene, ds, "nuscenes", lidar, "--resume")) == 0


def test_a_record_without_digests_is_refused(made, tmp_path, cli_error):
    scene, lidar, ds = _copy(made, tmp_path, "done")
    rec = json.loads((ds / ".lsd3d" / "dataset.json").read_text())
    del rec["inputs"]
    (ds / ".lsd3d" / "dataset.json").write_text(json.dumps(rec))
    cli_error(_argv(scene, ds, "nuscenes", lidar, "--resume"), "records no digests")


# --------------------------------- 10. a log record of valid JSON but the wrong contents
@pytest.mark.parametrize("edit", [
    lambda r: r.pop("sample"), lambda r: r.update(sample="text"),
    lambda r: r.update(log=[{"no": "token"}]), lambda r: r.update(channels=[1]),
    lambda r: r.update(map=[{"token": 3}]),
])
def test_a_log_record_of_the_wrong_shape_is_one_line(made, tmp_path, cli_error, edit):
    scene, lidar, ds = _copy(made, tmp_path, "done")
    f = ds / ".lsd3d" / "logs" / "0000.json"
    rec = json.loads(f.read_text())
    edit(rec)
    f.write_text(json.dumps(rec))
    cli_error(_argv(scene, ds, "nuscenes", lidar, "--resume"), "0000.json",
              "not a log record of the nuscenes writer")


def test_record_shapes_of_every_writer():
    from lsd3d_usd.datasets.build import record_problem
    from lsd3d_usd.datasets.kitti import KittiWriter
    from lsd3d_usd.datasets.mcap import McapWriter
    assert record_problem({"ids": ["a"]}, KittiWriter.record_shape) is None
    assert record_problem({"ids": [1]}, KittiWriter.record_shape) == "ids[0] is int, not str"
    assert record_problem({"file": "x.mcap", "messages": {"/a": True}},
                          McapWriter.record_shape) == "messages./a is bool, not int"


# ------------------------------------------------------------- 16. LiDAR keys
@pytest.mark.parametrize("extra, needle", [
    ("elevations = [-1.0, 1.0]\n", "elevations and beams exclude each other"),
    ("mount = {x = 1e308}\n", "mount: x"),
    ("mount = {z = -101.0}\n", "mount: z"),
])
def test_lidar_conflicts_and_mounts_are_refused(tmp_path, extra, needle):
    from lsd3d_usd.sensors.lidar import read_lidar_file
    base = "[lidar]\nbeams = 8\nelevation_min = -10\nelevation_max = 10\ncolumns = 100\n"
    f = tmp_path / "l.toml"
    f.write_text(base + extra)
    with pytest.raises(InputError, match=needle) as e:
        read_lidar_file(f)
    assert str(f) in str(e.value)


@pytest.mark.parametrize("table, needle", [
    ({"elevations": [1.0], "elevation_min": -3.0}, "elevations and elevation_min"),
    ({"beams": 8, "elevation_min": -10, "elevation_max": 95}, "elevation_max: 95 deg"),
    ({"beams": 8, "elevation_min": -90, "elevation_max": 5}, "elevation_min: -90 deg"),
    ({"beams": 10 ** 400, "elevation_min": -1, "elevation_max": 5}, "beams"),
])
def test_lidar_keys_reported_as_given(table, needle):
    from lsd3d_usd.sensors.lidar import model_from_table
    with pytest.raises(InputError, match=needle):
        model_from_table({**table, "columns": 100}, "l.toml")


def test_lidar_unknown_top_level_table(tmp_path):
    from lsd3d_usd.sensors.lidar import read_lidar_file
    f = tmp_path / "l.toml"
    f.write_text(LIDAR + "[extra]\nx = 1\n")
    with pytest.raises(InputError, match="top level: unknown key 'extra'"):
        read_lidar_file(f)


# ------------------------------------------------------------- 16. MCAP resume
@pytest.mark.parametrize("damage", ["garbage", "empty", "journal"])
def test_mcap_resume_errors_with_a_reason_and_leaves_no_new_file(made, tmp_path, cli_error,
                                                                 damage):
    scene, lidar, ds = _copy(made, tmp_path, "killed")
    part = next(ds.glob(".*.mcap.partial"))
    if damage == "garbage":
        part.write_bytes(b"\x89MCAP0\r\n" + b"\xff" * 64)
    elif damage == "empty":
        part.write_bytes(b"")
    else:
        j = ds / ".lsd3d" / "logs" / "0000.journal.jsonl"
        j.write_text('{"messages": 99999}\n')
        p = ds / ".lsd3d" / "logs" / "0000.partial.json"
        p.write_text(json.dumps({"next_tick": 1, "journal_bytes": len(j.read_bytes())}))
    line = cli_error(_argv(scene, ds, "mcap", lidar, "--resume"), part.name, "--overwrite")
    assert "()" not in line
    assert not list(ds.glob(".*.partial.new"))


# ------------------------------------------------------------- 16. PLY files
def _ply(path, field, tail=b""):
    from lsd3d_usd.splats.ply import splat_vertex_array, write_ply_vertices
    write_ply_vertices(path, splat_vertex_array(field))
    if tail:
        data = path.read_bytes()
        head, body = data.split(b"end_header\n", 1)
        path.write_bytes(head + tail + b"end_header\n" + body)


def test_ply_semantic_id_is_reported_against_the_file(tmp_path, field_factory):
    from lsd3d_usd.splats.ply import read_ply
    field = field_factory(50, sh_degree=0)
    field.semantic_ids[7] = -5          # no class has it (and -1 is "unlabelled")
    f = tmp_path / "s.ply"
    _ply(f, field)
    with pytest.raises(InputError, match=r"s\.ply: semantic_id .* of vertex 7"):
        read_ply(f)


def test_ply_trailing_element_is_checked_against_the_file_size(tmp_path, field_factory):
    from lsd3d_usd.splats.ply import read_ply
    f = tmp_path / "t.ply"
    _ply(f, field_factory(50, sh_degree=0),
         tail=b"element face 1000000000\nproperty list uchar int vertex_indices\n")
    with pytest.raises(InputError, match="t.ply: PLY body truncated in element 'face'"):
        read_ply(f)


# ----------------------------------------- the fuzz test: resume state and LiDAR keys
JSON = st.recursive(st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
                    | st.floats(allow_nan=False) | st.text(max_size=8),
                    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=4), c,
                                                                        max_size=3),
                    max_leaves=6)


def _kind(v):
    return "int" if type(v) is int else type(v).__name__


def _mutate(data: bytes, how, draw, structural: bool, jsonl: bool) -> bytes:
    """A state file damaged so that no resume may accept it: cut short, replaced by bytes,
    or (JSON) a value of another type, or (``structural``) a key removed."""
    if how == "cut":
        return data[:draw(st.integers(0, max(len(data) - 2, 0)))]
    if how == "bytes":
        return draw(st.binary(max_size=64).filter(lambda b: b != data))
    text = data.decode()
    lines = text.splitlines() if jsonl else [text]      # a journal: one object a line
    n = draw(st.integers(0, len(lines) - 1))
    obj = json.loads(lines[n])
    key = draw(st.sampled_from(sorted(obj)))
    if how == "drop" and structural:
        del obj[key]
    else:
        obj[key] = draw(JSON.filter(lambda v, old=obj[key]: _kind(v) != _kind(old)))
    lines[n] = json.dumps(obj)
    return ("\n".join(lines) + "\n").encode()


def _fresh(base: Path) -> Path:
    tmp = base / "case"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    return tmp


TARGETS = {   # file -> (prepared dataset, format, JSON mutations allowed)
    "dataset.json": ("done", "nuscenes", ("type", "drop")),
    "logs/0000.json": ("done", "nuscenes", ("drop",)),
    "logs/0000.partial.json": ("killed", "mcap", ("type",)),
    "logs/0000.journal.jsonl": ("killed", "mcap", ("type", "drop")),
}
N_EXAMPLES = 30
SETTINGS = settings(max_examples=N_EXAMPLES, deadline=None, derandomize=True,
                    suppress_health_check=list(HealthCheck))


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_fuzz_resume_state(made, tmp_path_factory, target):
    """Every damaged state file: one error line, exit 1, nothing outside the folder touched
    (the whole parent folder, scene and LiDAR file included, compared before and after)."""
    from conftest import error_line

    from lsd3d_usd.cli import main
    which, fmt, kinds = TARGETS[target]
    base = tmp_path_factory.mktemp("fuzz")

    @SETTINGS
    @given(st.data())
    def run(data):
        import contextlib
        import io
        tmp = _fresh(base)      # one path for every example: replays draw the same
        scene, lidar, ds = _copy(made, tmp, which)
        f = ds / ".lsd3d" / target
        how = data.draw(st.sampled_from(["cut", "bytes", *kinds]))
        # the log record's lists of rows may be emptied by a type-preserving edit: only
        # removing a key or damaging the bytes is sure to be refused
        f.write_bytes(_mutate(f.read_bytes(), how, data.draw, "drop" in kinds,
                             target.endswith(".jsonl")))
        before = _snapshot(tmp, skip=ds)
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(_argv(scene, ds, fmt, lidar, "--resume"))
        error_line((code, err.getvalue()))
        assert _snapshot(tmp, skip=ds) == before
        assert not list(ds.glob(".*.partial.new"))

    run()


LIDAR_KEYS = ["name", "beams", "elevation_min", "elevation_max", "elevations", "columns", "hfov",
              "min_range", "max_range", "rotation_hz", "range_sigma", "drop_prob", "mount",
              "mount.x", "mount.z", "mount.yaw", "[table]"]
TOML_VALUE = st.recursive(
    st.booleans() | st.integers(-2 ** 80, 2 ** 80) | st.floats() | st.text(max_size=12),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(
        st.from_regex(r"[a-z]{1,4}", fullmatch=True), c, max_size=3), max_leaves=8)


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v > 0 else "-inf") if abs(v) == float("inf") \
            else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(map(_toml, v)) + "]"
    return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"


@pytest.mark.parametrize("key", LIDAR_KEYS)
def test_fuzz_lidar_keys(made, tmp_path_factory, key):
    """Any value at any LiDAR key (and an extra table): one line, exit 1, nothing written.
    --seconds -1 makes a run refused after the LiDAR passes, so no case renders."""
    from conftest import error_line

    from lsd3d_usd.cli import main
    scene = made[0]
    base = tmp_path_factory.mktemp("lidarfuzz")

    @SETTINGS
    @given(TOML_VALUE)
    def run(value):
        import contextlib
        import io
        tmp = _fresh(base)      # one path for every example: replays draw the same
        lines = [ln for ln in LIDAR.splitlines()
                 if not ln.startswith(key.split(".")[0] + " ")]
        if key == "[table]":
            lines += ["[extra]", f"v = {_toml(value)}"]
        elif key.startswith("mount."):
            lines.append(f"mount = {{{key.split('.')[1]} = {_toml(value)}}}")
        else:
            lines.insert(1, f"{key} = {_toml(value)}")
        (tmp / "l.toml").write_text("\n".join(lines) + "\n", errors="surrogatepass")
        before = _snapshot(tmp)
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(_argv(scene, tmp / "ds", "nuscenes", tmp / "l.toml", "--seconds", "-1"))
        line = error_line((code, err.getvalue()))
        assert "l.toml" in line or "--seconds -1" in line, line
        assert _snapshot(tmp) == before and not (tmp / "ds").exists()

    run()


def test_fuzz_counts():
    """The number of hostile cases the fuzz tests try (reported in docs/limits.md)."""
    assert N_EXAMPLES * (len(TARGETS) + len(LIDAR_KEYS)) == 630


def test_resume_into_a_new_or_empty_folder_starts_the_dataset(made, tmp_path):
    """`dataset --resume` (and a batch's dataset, which always resumes) into a folder that
    does not exist yet or is empty makes the dataset; a second --resume goes on."""
    from lsd3d_usd.cli import main
    scene, lidar, _ = _copy(made, tmp_path, "done")
    for ds in (tmp_path / "new", tmp_path / "empty"):
        if ds.name == "empty":
            ds.mkdir()
        assert main(_argv(scene, ds, "nuscenes", lidar, "--resume")) == 0
        assert (ds / ".lsd3d" / "dataset.json").is_file()
        assert main(_argv(scene, ds, "nuscenes", lidar, "--resume")) == 0


def test_a_start_killed_before_its_record_resumes(made, tmp_path, cli_error):
    """A folder holding only an empty .lsd3d tree (killed between making it and writing
    dataset.json) resumes as a new dataset; a link inside that tree is still refused."""
    from lsd3d_usd.cli import main
    scene, lidar, _ = _copy(made, tmp_path, "done")
    ds = tmp_path / "killed"
    (ds / ".lsd3d" / "logs").mkdir(parents=True)
    assert main(_argv(scene, ds, "nuscenes", lidar, "--resume")) == 0
    assert (ds / ".lsd3d" / "dataset.json").is_file()
    bad = tmp_path / "linked"
    (bad / ".lsd3d").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    (bad / ".lsd3d" / "logs").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    cli_error(_argv(scene, bad, "nuscenes", lidar, "--resume"), "no lsd3d-usd dataset")
    assert not any((tmp_path / "elsewhere").iterdir())
