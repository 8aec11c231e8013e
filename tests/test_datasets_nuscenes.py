"""`lsd3d-usd dataset --format nuscenes` read by the real nuscenes-devkit: the tables load,
boxes projected by the devkit land on the actors' pixels, sweeps and lidarseg labels load
with matching counts, velocities match the actors' motion in the stage, the map mask holds
the ego's road, and the devkit's renderers draw the data."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import generate_small

nuscenes = pytest.importorskip("nuscenes", reason="nuscenes-devkit (pip install --no-deps "
                                                  "nuscenes-devkit==1.2.0; docs/datasets.md)")

VERSION = "v1.0-lsd3d"
STATE = ".lsd3d"          # the dataset's own state (settings, log records, rig stages)
ROUTE = "w_in,j_we,e_out"
ARGS = ["--format", "nuscenes", "--route", ROUTE, "--seconds", "1.5", "--camera-hz", "4",
        "--lidar-hz", "4", "--keyframe-hz", "2", "--width", "160"]


def make(scene, out, *extra):
    from lsd3d_usd.cli import main
    assert main(["dataset", str(scene), "-o", str(out), "--no-progress", *ARGS, *extra]) == 0
    return out


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A scene whose surfels lie on the proxy, with traffic, as a nuScenes dataset: one log,
    1.5 s, cameras and LiDAR at 4 Hz, keyframes at 2 Hz, 160 px wide images."""
    root = tmp_path_factory.mktemp("nuscenes")
    generate_small(root / "scene", steps=0, actors=True, surfels=100_000, pedestrians=0, cyclists=0)
    make(root / "scene", root / "ds")
    return root


@pytest.fixture(scope="module")
def nusc(data):
    from nuscenes.nuscenes import NuScenes
    return NuScenes(version=VERSION, dataroot=str(data / "ds"), verbose=False)


def test_tables_load_and_link(nusc, data, capsys):
    root = data / "ds" / VERSION
    for t in ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map",
              "sample", "sample_annotation", "sample_data", "scene", "sensor", "visibility",
              "lidarseg"):
        assert (root / f"{t}.json").is_file(), t
    nusc.list_scenes()
    assert "scene-0000" in capsys.readouterr().out
    scene = nusc.scene[0]
    assert scene["nbr_samples"] == 3 == len(nusc.sample)
    chain, tok = [], scene["first_sample_token"]
    while tok:
        chain.append(nusc.get("sample", tok))
        tok = chain[-1]["next"]
    assert len(chain) == 3 and chain[-1]["token"] == scene["last_sample_token"]
    assert np.all(np.diff([c["timestamp"] for c in chain]) == 500_000)
    channels = {"CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT",
                "CAM_BACK_RIGHT", "LIDAR_TOP"}
    for s in nusc.sample:
        assert set(s["data"]) == channels
        assert all(nusc.get("sample_data", t)["timestamp"] == s["timestamp"]
                   for t in s["data"].values())
    # 4 Hz cameras and LiDAR over 1.5 s: 6 frames per channel, 3 keyframes, 3 sweeps between
    for ch in channels:
        sds = [sd for sd in nusc.sample_data if sd["channel"] == ch]
        assert len(sds) == 6 and sum(sd["is_key_frame"] for sd in sds) == 3
        ts = sorted(sd["timestamp"] for sd in sds)
        assert np.all(np.diff(ts) == 250_000)                       # microseconds
        for sd in sds:
            folder = "samples" if sd["is_key_frame"] else "sweeps"
            assert sd["filename"].startswith(f"{folder}/{ch}/")
            assert (data / "ds" / sd["filename"]).is_file()
    # tracks: prev/next chains per instance, in time order
    for inst in nusc.instance:
        chain, tok = [], inst["first_annotation_token"]
        while tok:
            a = nusc.get("sample_annotation", tok)
            chain.append(a)
            tok = a["next"]
        assert len(chain) == inst["nbr_annotations"] and chain[-1]["token"] == \
            inst["last_annotation_token"]
        ts = [nusc.get("sample", a["sample_token"])["timestamp"] for a in chain]
        assert ts == sorted(ts)
    assert len(nusc.sample_annotation) >= 3
    cats = {c["name"]: c["index"] for c in nusc.category}
    assert cats["vehicle.car"] == 17 and cats["flat.driveable_surface"] == 24


def test_devkit_boxes_land_on_the_actors_pixels(nusc):
    """For every camera of every keyframe: each actor at least 80 % visible in it and inside
    the image — the tight box of its instance pixels (image_annotations.json) — is where the
    devkit's own projection of the annotation's 3D box puts it, within 3 px."""
    from nuscenes.utils.geometry_utils import view_points
    by_sd = {}
    for ia in nusc.image_annotations:
        by_sd.setdefault(ia["sample_data_token"], {})[ia["sample_annotation_token"]] = ia
    checked = 0
    for s in nusc.sample:
        for ch, sd_tok in s["data"].items():
            if not ch.startswith("CAM"):
                continue
            path, boxes, K = nusc.get_sample_data(sd_tok)
            assert Path(path).is_file()
            sd = nusc.get("sample_data", sd_tok)
            for box in boxes:
                ia = by_sd.get(sd_tok, {}).get(box.token)
                if ia is None or ia["visible_fraction"] < 0.8 or ia["truncated"] > 0:
                    continue
                uv = view_points(box.corners(), K, normalize=True)[:2]
                x0, y0 = np.clip(uv.min(1), 0, [sd["width"], sd["height"]])
                x1, y1 = np.clip(uv.max(1), 0, [sd["width"], sd["height"]])
                np.testing.assert_allclose([x0, y0, x1, y1], ia["bbox_corners"], atol=3.0,
                                           err_msg=f"{ch} {box.name}")
                checked += 1
    assert checked >= 2, checked


def test_sweeps_and_lidarseg_load_with_matching_counts(nusc, data):
    from nuscenes.utils.data_classes import LidarPointCloud
    from nuscenes.utils.data_io import load_bin_file
    from nuscenes.utils.geometry_utils import points_in_box
    names = {c["index"]: c["name"] for c in nusc.category}
    assert len(nusc.lidarseg) == len(nusc.sample)
    inside = 0
    for s in nusc.sample:
        sd_tok = s["data"]["LIDAR_TOP"]
        path = nusc.get_sample_data_path(sd_tok)
        pc = LidarPointCloud.from_file(path)
        n = pc.points.shape[1]
        assert n == Path(path).stat().st_size // 20 > 10_000
        assert np.all(pc.points[3] >= 0) and np.all(pc.points[3] <= 255)
        rec = next(r for r in nusc.lidarseg if r["sample_data_token"] == sd_tok)
        labels = load_bin_file(str(data / "ds" / rec["filename"]))
        assert labels.shape == (n,)
        got = {names[i] for i in np.unique(labels)}
        assert {"flat.driveable_surface", "static.manmade"} <= got
        # points inside an annotated vehicle's box are labelled as vehicles (the box and the
        # per-point labels come from the same geometry)
        _, boxes, _ = nusc.get_sample_data(sd_tok)
        for box in boxes:
            # above the bottom 0.3 m of the box (the road under a car is not the car)
            local = box.rotation_matrix.T @ (pc.points[:3] - box.center[:, None])
            m = points_in_box(box, pc.points[:3]) & (local[2] > 0.3 - box.wlh[2] / 2)
            if m.sum() >= 5:
                frac = np.mean([names[i].startswith("vehicle.") for i in labels[m]])
                assert frac > 0.9, (box.name, frac)
                inside += 1
        anns = [nusc.get("sample_annotation", a) for a in s["anns"]]
        assert all(a["num_lidar_pts"] >= 0 for a in anns)
    assert inside >= 1


def test_box_velocity_matches_the_actors_motion(nusc, data):
    """box_velocity (the devkit's finite difference over the track) against the actor prim's
    motion as USD composes it (±10 ms around the annotation's time), for annotations with a
    neighbour on each side."""
    from pxr import Usd, UsdGeom
    stage = Usd.Stage.Open(str(next((data / "ds" / ".lsd3d" / "work").iterdir()) / "rig.usda"))
    tcps = stage.GetTimeCodesPerSecond()
    t0 = nusc.sample[0]["timestamp"]
    checked = 0
    for a in nusc.sample_annotation:
        if not (a["prev"] and a["next"]):      # the devkit's central difference
            continue
        v = nusc.box_velocity(a["token"])
        prim = stage.GetPrimAtPath(nusc.get("instance", a["instance_token"])["prim"])
        t = (nusc.get("sample", a["sample_token"])["timestamp"] - t0) * 1e-6
        c = np.append(a["translation"], 1.0)

        def M(sec, prim=prim):
            return np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(sec * tcps)).T
        # the annotation's centre as a point of the actor (global and world differ by a shift)
        local = np.linalg.solve(M(t), c + np.append(nusc_shift(nusc, stage, data), 0.0))
        true = ((M(t + 0.01) @ local) - (M(t - 0.01) @ local))[:3] / 0.02
        assert abs(np.linalg.norm(v[:2]) - np.linalg.norm(true[:2])) < 0.1, (v, true)
        checked += 1
    assert checked >= 2


def nusc_shift(nusc, stage, data):
    """World position of the global frame's origin: ego_pose (global) vs the ego prim (world)."""
    from pxr import UsdGeom
    ego = stage.GetPrimAtPath("/World/Cameras/Ego")
    pose = nusc.ego_pose[0]
    t = (pose["timestamp"] - nusc.sample[0]["timestamp"]) * 1e-6
    W = np.asarray(UsdGeom.Xformable(ego).ComputeLocalToWorldTransform(
        t * stage.GetTimeCodesPerSecond())).T
    return W[:3, 3] - np.asarray(pose["translation"])


def test_map_mask_holds_the_road_the_ego_drives(nusc):
    log = nusc.log[0]
    mask = nusc.get("map", log["map_token"])["mask"]
    xy = np.array([p["translation"][:2] for p in nusc.ego_pose])
    assert mask.is_on_mask(xy[:, 0], xy[:, 1]).all()
    assert 0.02 < (mask.mask() > 0).mean() < 0.5
    far = xy + np.array([0.0, 30.0])          # 30 m to the side of an east-west road
    assert not mask.is_on_mask(far[:, 0], far[:, 1]).any()


def test_devkit_renderers_draw_the_data(nusc, tmp_path):
    """render_sample_data (camera; LiDAR with lidarseg) and render_pointcloud_in_image. The
    LiDAR view is drawn without the map underlay: the devkit's underlay (crop_image) fails on
    numpy 2, which the devkit itself pins below (docs/datasets.md)."""
    import matplotlib
    matplotlib.use("Agg")
    from PIL import Image
    s = nusc.sample[0]
    outs = [tmp_path / n for n in ("cam.png", "lidar.png", "pc.png")]
    nusc.render_sample_data(s["data"]["CAM_FRONT"], out_path=str(outs[0]), verbose=False)
    nusc.render_sample_data(s["data"]["LIDAR_TOP"], show_lidarseg=True, underlay_map=False,
                            out_path=str(outs[1]), verbose=False)
    nusc.render_pointcloud_in_image(s["token"], out_path=str(outs[2]), verbose=False)
    for p in outs:
        img = np.asarray(Image.open(p).convert("RGB"))
        assert img.shape[0] > 100 and img.std() > 10, p


def _files(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and STATE not in p.parts}


def test_same_command_gives_the_same_dataset(data):
    """Tokens, timestamps, tables, images, sweeps and labels: byte for byte."""
    again = make(data / "scene", data / "again")
    a, b = _files(data / "ds"), _files(again)
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []
    assert any(k.endswith("sample_annotation.json") for k in a)


def test_bad_input_is_one_error_line_and_writes_nothing(data, cli_error, tmp_path):
    scene = data / "scene"
    base = ["dataset", scene, "--route", ROUTE, "--seconds", "0.5", "--width", "32"]
    out = tmp_path / "out"
    cli_error([*base, "-o", out, "--format", "coco"], "unknown dataset format 'coco'",
              "nuscenes")
    cli_error([*base[:3], "w_in,j_xx", *base[4:], "-o", out, "--format", "nuscenes"],
              "'j_xx'", str(scene))
    cli_error([*base[:3], "w_in,e_out", *base[4:], "-o", out, "--format", "nuscenes"],
              "'e_out' does not follow lane 'w_in'")
    cli_error([*base, "-o", scene / "ds", "--format", "nuscenes"], "inside the scene folder")
    cli_error([*base, "-o", data, "--format", "nuscenes"], "lies inside it")
    cli_error(["dataset", tmp_path / "nope", "-o", out, "--format", "nuscenes"],
              "not a scene folder")
    cli_error([*base, "-o", out, "--format", "nuscenes", "--keyframe-hz", "5"],
              "--keyframe-hz 5 must divide --camera-hz 12")
    assert not out.exists() and not (scene / "ds").exists()
    full = tmp_path / "full"
    full.mkdir()
    (full / "mine.txt").write_text("keep")
    cli_error([*base, "-o", full, "--format", "nuscenes"], "not empty", "--resume",
              "--overwrite")
    cli_error([*base, "-o", full, "--format", "nuscenes", "--overwrite"],
              "not an lsd3d-usd dataset")
    cli_error([*base, "-o", full, "--format", "nuscenes", "--resume"], "no lsd3d-usd dataset")
    assert [p.name for p in full.iterdir()] == ["mine.txt"]
    # a dataset made with other settings is not resumed into
    cli_error(["dataset", scene, "-o", data / "ds", *ARGS, "--resume", "--seed", "3"],
              "other settings", "seed")


def test_resume_after_kill_continues_and_gives_the_same_dataset(data, tmp_path, monkeypatch):
    """kill -9 after two of the three keyframes; --resume continues after the second (the
    ticks before it are not rendered again) and the dataset is the uninterrupted one. Each
    checkpoint journals only its keyframe's rows; a torn journal line after the last
    checkpoint is cut off."""
    import signal
    import subprocess
    import sys

    from lsd3d_usd.datasets import drive
    out = data / "killed"
    here = Path(__file__).parent
    r = subprocess.run([sys.executable, str(here / "dataset_faults.py"), "2", "dataset",
                        str(data / "scene"), "-o", str(out), "--no-progress", *ARGS],
                       check=False, capture_output=True, text=True, timeout=600)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert not (out / VERSION / "sample.json").exists()
    logs = out / STATE / "logs"
    part = json.loads((logs / "0000.partial.json").read_text())
    assert part["next_tick"] == 3            # ticks at 4 Hz, keyframes at ticks 0, 2, 4
    journal = (logs / "0000.journal.jsonl").read_bytes()
    assert len(journal) == part["journal_bytes"]
    deltas = [json.loads(ln) for ln in journal.splitlines()]
    assert [len(d["sample"]) for d in deltas] == [1, 1]        # a keyframe's rows, not all
    assert len(deltas[1]["calibrated_sensor"]) == 0 < len(deltas[0]["calibrated_sensor"])
    with open(logs / "0000.journal.jsonl", "ab") as f:
        f.write(b'{"sample": [{"tok')                          # a line torn by a kill
    renders = [0]
    render = drive.render_scene

    def counting(*a, **k):
        renders[0] += 1
        return render(*a, **k)

    monkeypatch.setattr(drive, "render_scene", counting)
    make(data / "scene", out, "--resume", "--json", str(tmp_path / "summary.json"))
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["resumed_at_tick"] == {"0": 3}
    assert renders[0] == 3 * 6               # ticks 3, 4, 5 of the six cameras
    a, b = _files(data / "ds"), _files(out)
    assert a.keys() == b.keys() and [k for k in a if a[k] != b[k]] == []
    assert not (logs / "0000.partial.json").exists()
    assert not (logs / "0000.journal.jsonl").exists()


def test_routes_make_logs_of_one_dataset(data, tmp_path):
    """--routes 2: two distinct seeded routes, two scenes and logs in one dataset sharing the
    scene's map; another rig and no LiDAR load as well."""
    from nuscenes.nuscenes import NuScenes

    from lsd3d_usd.cli import main
    out = tmp_path / "two"
    assert main(["dataset", str(data / "scene"), "-o", str(out), "--format", "nuscenes",
                 "--routes", "2", "--seconds", "0.5", "--camera-hz", "2", "--lidar-hz", "2",
                 "--width", "32", "--rig", "waymo5", "--lidar", "none", "--no-progress"]) == 0
    nusc = NuScenes(version=VERSION, dataroot=str(out), verbose=False)
    assert [s["name"] for s in nusc.scene] == ["scene-0000", "scene-0001"]
    routes = [s["description"].split("route ")[1].split(",")[0] for s in nusc.scene]
    assert len(set(routes)) == 2
    assert len(nusc.log) == 2 and len(nusc.map) == 1
    assert sorted(nusc.map[0]["log_tokens"]) == sorted(lg["token"] for lg in nusc.log)
    assert {s["channel"] for s in nusc.sensor} == {"Front", "FrontLeft", "FrontRight",
                                                   "SideLeft", "SideRight"}
    ts = [nusc.get("sample", s["first_sample_token"])["timestamp"] for s in nusc.scene]
    assert ts[1] - ts[0] == 3_600_000_000          # logs an hour apart, never overlapping
