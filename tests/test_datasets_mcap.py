"""`lsd3d-usd dataset --format mcap` read back with the `mcap` reader and Foxglove's protobuf
schemas (mcap-protobuf-support decodes them): messages per topic, schema names, and the
transform chain world -> ego -> camera projecting the boxes where the rig's USD camera does."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import generate_small

pytest.importorskip("mcap_protobuf", reason="mcap-protobuf-support")

ROUTE = "w_in,j_we,e_out"
ARGS = ["--format", "mcap", "--route", ROUTE, "--seconds", "1", "--camera-hz", "4",
        "--lidar-hz", "2", "--keyframe-hz", "2", "--width", "160", "--no-progress"]
CAMERAS = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT",
           "CAM_BACK_RIGHT")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from lsd3d_usd.cli import main
    root = tmp_path_factory.mktemp("mcap")
    generate_small(root / "scene", steps=0, actors=True, surfels=100_000, pedestrians=0, cyclists=0)
    assert main(["dataset", str(root / "scene"), "-o", str(root / "ds"), *ARGS]) == 0
    files = sorted((root / "ds").glob("*.mcap"))
    assert [f.name for f in files] == ["lsd3d-0000-scene.mcap"]
    msgs = []
    with open(files[0], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, proto in reader.iter_decoded_messages():
            msgs.append((channel.topic, schema.name, message.log_time, proto))
    return root, msgs


def test_topics_counts_and_schemas(recording):
    _, msgs = recording
    per = {}
    for topic, schema, _, _ in msgs:
        per.setdefault(topic, [0, schema])[0] += 1
    frames, sweeps = 4, 2          # 1 s at 4 Hz cameras and 2 Hz LiDAR
    want = {"/tf_static": (len(CAMERAS) + 1, "foxglove.FrameTransform"),
            "/tf": (frames + 0, "foxglove.FrameTransform"),     # every tick (sweeps on frames)
            "/LIDAR_TOP": (sweeps, "foxglove.PointCloud"),
            "/markers/annotations": (frames, "foxglove.SceneUpdate")}
    for c in CAMERAS:
        want[f"/{c}/image"] = (frames, "foxglove.CompressedImage")
        want[f"/{c}/camera_info"] = (frames, "foxglove.CameraCalibration")
    assert {k: tuple(v) for k, v in per.items()} == want
    times = [t for _, _, t, _ in msgs]
    assert times == sorted(times)
    cloud = next(p for t, _, _, p in msgs if t == "/LIDAR_TOP")
    assert len(cloud.data) // cloud.point_stride > 10_000
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "intensity", "ring", "class_id"]
    img = next(p for t, _, _, p in msgs if t == "/CAM_FRONT/image")
    assert img.format == "jpeg" and bytes(img.data[:2]) == b"\xff\xd8"


def _matrix(tf) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    M = np.eye(4)
    q = tf.rotation
    M[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    M[:3, 3] = [tf.translation.x, tf.translation.y, tf.translation.z]
    return M


def test_transforms_chain_boxes_into_the_cameras(recording):
    """Box centres (world) through /tf (world -> ego) and /tf_static (ego -> camera) and the
    CameraCalibration land on the pixel the rig's USD camera (rig.usda) projects them to."""
    from pxr import Usd

    from lsd3d_usd.render.camera import from_usd
    root, msgs = recording
    stage = Usd.Stage.Open(str(root / "ds" / ".lsd3d" / "work" / "0000" / "rig.usda"))
    tcps = stage.GetTimeCodesPerSecond()
    static = {p.child_frame_id: _matrix(p) for t, _, _, p in msgs if t == "/tf_static"}
    t0 = min(lt for _, _, lt, _ in msgs)
    seen = 0
    for topic, _, lt, upd in msgs:
        if topic != "/markers/annotations":
            continue
        ego = _matrix(next(p for t, _, tl, p in msgs if t == "/tf" and tl == lt))
        for cam_name in CAMERAS:
            cal = next(p for t, _, tl, p in msgs if t == f"/{cam_name}/camera_info" and tl == lt)
            K = np.array(cal.K).reshape(3, 3)
            usd_cam = from_usd(stage.GetPrimAtPath(f"/World/Cameras/Ego/{cam_name}"),
                               round((lt - t0) * 1e-9 * tcps, 6), cal.width, cal.height)
            cam_from_world = np.linalg.inv(ego @ static[cam_name])
            for ent in upd.entities:
                p = ent.cubes[0].pose.position
                X = np.array([p.x, p.y, p.z, 1.0])
                a = cam_from_world @ X
                b = usd_cam.viewmat @ X
                np.testing.assert_allclose(a[:3], b[:3], atol=1e-3)
                if a[2] > 1.0:
                    uv = (K @ a[:3])[:2] / a[2]
                    uv_usd = (usd_cam.K @ b[:3])[:2] / b[2]
                    np.testing.assert_allclose(uv, uv_usd, atol=0.05)
                    seen += int(0 <= uv[0] < cal.width and 0 <= uv[1] < cal.height)
    assert seen >= 4


def test_same_command_gives_the_same_recording(recording):
    from lsd3d_usd.cli import main
    root, _ = recording
    assert main(["dataset", str(root / "scene"), "-o", str(root / "again"), *ARGS]) == 0
    name = "lsd3d-0000-scene.mcap"
    assert (root / "again" / name).read_bytes() == (root / "ds" / name).read_bytes()


def _messages(path):
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        return [(ch.topic, sc.name, m.log_time, m.sequence, bytes(m.data))
                for sc, ch, m in make_reader(f).iter_messages()]


def test_resume_after_kill_continues_the_recording(recording, tmp_path, monkeypatch):
    """kill -9 after the second of the two keyframes (ticks 0, 2 of 0..3); --resume reads the
    unfinished file back to its checkpoint (a torn tail after it is dropped), renders only
    tick 3 again and gives the uninterrupted recording: the same messages per topic, the same
    payloads, the same bytes."""
    import json
    import signal
    import subprocess
    import sys
    from pathlib import Path

    from lsd3d_usd.cli import main
    from lsd3d_usd.datasets import drive
    root, _ = recording
    out = root / "killed"
    here = Path(__file__).parent
    r = subprocess.run([sys.executable, str(here / "dataset_faults.py"), "2", "dataset",
                        str(root / "scene"), "-o", str(out), *ARGS],
                       check=False, capture_output=True, text=True, timeout=600)
    assert r.returncode == -signal.SIGKILL, r.stderr
    name = "lsd3d-0000-scene.mcap"
    partial = out / f".{name}.partial"
    assert not (out / name).exists() and partial.is_file()
    part = json.loads((out / ".lsd3d" / "logs" / "0000.partial.json").read_text())
    assert part["next_tick"] == 3
    with open(partial, "ab") as f:          # a chunk torn by the kill
        f.write(b"\x06" + (10_000).to_bytes(8, "little") + b"\x00" * 300)
    renders = [0]
    render = drive.render_scene

    def counting(*a, **k):
        renders[0] += 1
        return render(*a, **k)

    monkeypatch.setattr(drive, "render_scene", counting)
    assert main(["dataset", str(root / "scene"), "-o", str(out), *ARGS, "--resume",
                 "--json", str(tmp_path / "summary.json")]) == 0
    assert json.loads((tmp_path / "summary.json").read_text())["resumed_at_tick"] == {"0": 3}
    assert renders[0] == len(CAMERAS)       # tick 3 only
    assert not partial.exists() and not list(out.glob(".*.mcap.*"))
    a, b = _messages(root / "ds" / name), _messages(out / name)
    per = {}
    for t, *_ in b:
        per[t] = per.get(t, 0) + 1
    assert per["/CAM_FRONT/image"] == 4 and per["/LIDAR_TOP"] == 2 and per["/tf"] == 4
    assert len(a) == len(b) and a == b
    assert (out / name).read_bytes() == (root / "ds" / name).read_bytes()
