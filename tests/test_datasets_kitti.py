"""`lsd3d-usd dataset --format kitti` read as the KITTI object devkit documents its files:
labels and calibration parsed from text, every fully visible 3D box re-projected into image_2
onto its 2D box, LiDAR points inside the boxes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import generate_small

ROUTE = "w_in,j_we,e_out"
ARGS = ["--format", "kitti", "--route", ROUTE, "--seconds", "1.5", "--camera-hz", "2",
        "--lidar-hz", "2", "--keyframe-hz", "2", "--width", "160", "--no-progress"]
# boxes nearer than this hold LiDAR returns: hdl32's beams are 1.33 deg apart, 0.9 m at 40 m
# (a car's height 1.4 m), and it reaches 70 m
NEAR_M = 40.0


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    from lsd3d_usd.cli import main
    root = tmp_path_factory.mktemp("kitti")
    generate_small(root / "scene", steps=0, actors=True, surfels=100_000, pedestrians=0, cyclists=0)
    assert main(["dataset", str(root / "scene"), "-o", str(root / "ds"), *ARGS]) == 0
    return root / "ds"


def read_calib(path: Path) -> dict:
    out = {}
    for line in path.read_text().splitlines():
        if line.strip():
            k, v = line.split(":", 1)
            out[k] = np.array([float(x) for x in v.split()])
    return out


def read_labels(path: Path) -> list[dict]:
    rows = []
    for line in path.read_text().splitlines():
        f = line.split()
        rows.append({"type": f[0], "truncated": float(f[1]), "occluded": int(f[2]),
                     "alpha": float(f[3]), "bbox": np.array(f[4:8], float),
                     "hwl": np.array(f[8:11], float), "xyz": np.array(f[11:14], float),
                     "ry": float(f[14])})
    return rows


def corners(lab: dict) -> np.ndarray:
    """(3, 8) corners in the camera frame, as the KITTI devkit's computeBox3D builds them."""
    h, w, l = lab["hwl"]
    c, s = np.cos(lab["ry"]), np.sin(lab["ry"])
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    x = [l / 2, l / 2, -l / 2, -l / 2, l / 2, l / 2, -l / 2, -l / 2]
    y = [0, 0, 0, 0, -h, -h, -h, -h]
    z = [w / 2, -w / 2, -w / 2, w / 2, w / 2, -w / 2, -w / 2, w / 2]
    return R @ np.array([x, y, z]) + lab["xyz"][:, None]


def test_layout_and_formats(kitti):
    from PIL import Image
    ids = (kitti / "ImageSets" / "train.txt").read_text().split()
    assert ids == ["000000", "000001", "000002"]
    for i in ids:
        img = Image.open(kitti / "training" / "image_2" / f"{i}.png")
        assert img.size == (160, 90) and img.mode == "RGB"
        pts = np.fromfile(kitti / "training" / "velodyne" / f"{i}.bin", np.float32)
        assert pts.size % 4 == 0 and pts.size // 4 > 10_000
        cal = read_calib(kitti / "training" / "calib" / f"{i}.txt")
        assert {k: v.size for k, v in cal.items()} == {
            "P0": 12, "P1": 12, "P2": 12, "P3": 12, "R0_rect": 9, "Tr_velo_to_cam": 12,
            "Tr_imu_to_velo": 12}
        for lab in read_labels(kitti / "training" / "label_2" / f"{i}.txt"):
            assert lab["type"] in {"Car", "Van", "Truck", "Misc"}
            assert 0 <= lab["truncated"] <= 1 and lab["occluded"] in (0, 1, 2, 3)
            pi = np.pi + 1e-4                     # written with four decimals
            assert -pi <= lab["alpha"] <= pi and -pi <= lab["ry"] <= pi


def test_boxes_reproject_onto_their_2d_boxes_and_hold_lidar_points(kitti):
    """Every fully visible, untruncated object: its 3D box (computeBox3D's corners through P2
    and R0_rect) spans its 2D box within 3 px; those within NEAR_M hold velodyne points
    (through Tr_velo_to_cam)."""
    checked = with_points = 0
    for i in (kitti / "ImageSets" / "train.txt").read_text().split():
        cal = read_calib(kitti / "training" / "calib" / f"{i}.txt")
        P2 = cal["P2"].reshape(3, 4)
        R0 = np.eye(4)
        R0[:3, :3] = cal["R0_rect"].reshape(3, 3)
        V2C = np.vstack([cal["Tr_velo_to_cam"].reshape(3, 4), [0, 0, 0, 1]])
        pts = np.fromfile(kitti / "training" / "velodyne" / f"{i}.bin", np.float32).reshape(-1, 4)
        cam = (R0 @ V2C @ np.c_[pts[:, :3], np.ones(len(pts))].T)[:3]      # rectified camera
        for lab in read_labels(kitti / "training" / "label_2" / f"{i}.txt"):
            if lab["occluded"] != 0 or lab["truncated"] > 0:
                continue
            X = corners(lab)
            uv = P2 @ R0 @ np.vstack([X, np.ones(8)])
            uv = uv[:2] / uv[2]
            np.testing.assert_allclose([*uv.min(1), *uv.max(1)], lab["bbox"], atol=3.0)
            checked += 1
            if np.linalg.norm(lab["xyz"]) > NEAR_M:
                continue
            # LiDAR points in the box (its own frame: x along the length, y up to the roof)
            h, w, l = lab["hwl"]
            c, s = np.cos(lab["ry"]), np.sin(lab["ry"])
            R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
            loc = R.T @ (cam - lab["xyz"][:, None])
            inside = (np.abs(loc[0]) <= l / 2) & (np.abs(loc[2]) <= w / 2) & \
                (loc[1] <= 0) & (loc[1] >= -h)
            assert inside.sum() > 0
            with_points += 1
    assert checked >= 2 and with_points >= 1


def _files(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and ".lsd3d" not in p.parts}


def test_same_command_gives_the_same_files(kitti):
    from lsd3d_usd.cli import main
    again = kitti.parent / "again"
    assert main(["dataset", str(kitti.parent / "scene"), "-o", str(again), *ARGS]) == 0
    a, b = _files(kitti), _files(again)
    assert len(a) == 13 and a.keys() == b.keys() and [k for k in a if a[k] != b[k]] == []


def test_resume_after_kill_continues_and_gives_the_same_files(kitti, tmp_path, monkeypatch):
    """kill -9 after two of the three keyframes: the journal holds one frame id per
    checkpoint, --resume renders only the third again and ends as the uninterrupted run."""
    import json
    import signal
    import subprocess
    import sys

    from lsd3d_usd.cli import main
    from lsd3d_usd.datasets import drive
    out = kitti.parent / "killed"
    r = subprocess.run([sys.executable, str(Path(__file__).parent / "dataset_faults.py"), "2",
                        "dataset", str(kitti.parent / "scene"), "-o", str(out), *ARGS],
                       check=False, capture_output=True, text=True, timeout=600)
    assert r.returncode == -signal.SIGKILL, r.stderr
    logs = out / ".lsd3d" / "logs"
    journal = (logs / "0000.journal.jsonl").read_text().splitlines()
    assert [json.loads(ln) for ln in journal] == [{"ids": ["000000"]}, {"ids": ["000001"]}]
    renders = [0]
    render = drive.render_scene

    def counting(*a, **k):
        renders[0] += 1
        return render(*a, **k)

    monkeypatch.setattr(drive, "render_scene", counting)
    assert main(["dataset", str(kitti.parent / "scene"), "-o", str(out), *ARGS,
                 "--resume"]) == 0
    assert renders[0] == 6                   # the third keyframe's six cameras
    a, b = _files(kitti), _files(out)
    assert len(a) == 13 and a.keys() == b.keys() and [k for k in a if a[k] != b[k]] == []
    assert not (logs / "0000.journal.jsonl").exists()
