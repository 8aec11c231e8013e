"""`sim run --mcap`: an episode's MCAP log (sim.record over datasets.mcap) read back with the
`mcap` reader and Foxglove's protobuf schemas: per step the ego transform, every camera's
image and calibration, the LiDAR cloud, the agents' boxes and the scores as JSON, matching
what the env returned."""
from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import generate_small

pytest.importorskip("mcap_protobuf", reason="mcap-protobuf-support")

CAMERAS = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT",
           "CAM_BACK_RIGHT")
STEPS = 11                      # reset + 1 s at 10 Hz


def _json_decoders():
    from mcap.decoder import DecoderFactory

    class Json(DecoderFactory):
        def decoder_for(self, message_encoding, schema):
            return json.loads if message_encoding == "json" and schema is None else None
    return Json()


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    """(what the env returned per step, the episode's result, decoded MCAP messages)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from lsd3d_usd.sim.env import DriveEnv
    from lsd3d_usd.sim.episodes import run_episode
    root = tmp_path_factory.mktemp("simrec")
    generate_small(root / "scene", steps=0, actors=True, pedestrians=4, cyclists=1)
    env = DriveEnv(root / "scene", rig="nuscenes6", width=64, seconds=1.0, vehicles=2,
                   pedestrians=2, cyclists=1)
    seen = []

    def keep(obs, info):
        seen.append({"count": int(obs["lidar"]["count"]), "pose": env.ego.matrix(),
                     "boxes": [dict(b) for b in info["boxes"]]})
    reset, step = env.reset, env.step

    def reset_(**kw):
        obs, info = reset(**kw)
        keep(obs, info)
        return obs, info

    def step_(action):
        out = step(action)
        keep(out[0], out[4])
        return out
    env.reset, env.step = reset_, step_
    try:
        result = run_episode(env, "planner", 0, 0, None, root / "out", mcap=True)
    finally:
        env.close()
    path = result.folder / result.files["mcap"]
    msgs = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), _json_decoders()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            msgs.append((channel.topic, schema.name if schema else None, message.log_time,
                         decoded))
    return seen, result, msgs


def _topic(msgs, topic):
    return [m for t, _, _, m in msgs if t == topic]


def test_every_step_has_every_channel(episode):
    seen, result, msgs = episode
    assert result.files["mcap"] == "episode_000.mcap" and result.steps == STEPS - 1
    assert len(seen) == STEPS
    per = {}
    for topic, schema, _, _ in msgs:
        per.setdefault(topic, [0, schema])[0] += 1
    want = {"/tf_static": (len(CAMERAS) + 1, "foxglove.FrameTransform"),
            "/tf": (STEPS, "foxglove.FrameTransform"),
            "/LIDAR_TOP": (STEPS, "foxglove.PointCloud"),
            "/markers/annotations": (STEPS, "foxglove.SceneUpdate"),
            "/sim/scores": (STEPS, None)}
    for c in CAMERAS:
        want[f"/{c}/image"] = (STEPS, "foxglove.CompressedImage")
        want[f"/{c}/camera_info"] = (STEPS, "foxglove.CameraCalibration")
    assert {k: tuple(v) for k, v in per.items()} == want
    times = [t for _, _, t, _ in msgs]
    assert times == sorted(times)


def test_ego_images_and_clouds_are_the_env_s(episode):
    import io

    from PIL import Image
    seen, _, msgs = episode
    for tf, s in zip(_topic(msgs, "/tf"), seen):
        assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "ego")
        p = tf.translation
        np.testing.assert_allclose([p.x, p.y, p.z], s["pose"][:3, 3], atol=1e-6)
    for c in CAMERAS:
        for img, cal in zip(_topic(msgs, f"/{c}/image"), _topic(msgs, f"/{c}/camera_info")):
            assert img.format == "jpeg" and img.frame_id == c
            assert Image.open(io.BytesIO(bytes(img.data))).size == (64, cal.height)
            assert cal.width == 64 and np.array(cal.K).reshape(3, 3)[2, 2] == 1.0
    clouds = _topic(msgs, "/LIDAR_TOP")
    assert [len(m.data) // m.point_stride for m in clouds] == [s["count"] for s in seen]
    assert all(m.frame_id == "LIDAR_TOP" for m in clouds) and seen[0]["count"] > 100


def test_boxes_and_scores_per_step(episode):
    from lsd3d_usd.sim.metrics import AgentBox
    seen, _, msgs = episode
    assert any(len(s["boxes"]) >= 3 for s in seen)
    # info["boxes"] stays plain dicts (the Gymnasium info API), each an AgentBox's JSON
    assert all(type(b) is dict and AgentBox.from_json(b).to_json() == b
               for s in seen for b in s["boxes"])
    kinds = set()
    for upd, s in zip(_topic(msgs, "/markers/annotations"), seen):
        assert [e.id for e in upd.entities] == [b["id"] for b in s["boxes"]]
        for e, b in zip(upd.entities, s["boxes"]):
            cube = e.cubes[0]
            np.testing.assert_allclose([cube.pose.position.x, cube.pose.position.y],
                                       b["center"], atol=1e-6)
            np.testing.assert_allclose([cube.size.x, cube.size.y], [b["length"], b["width"]])
            assert 0.5 < cube.size.z < 5.0 and e.frame_id == "world"
            kinds.add(b["kind"])
    assert {"vehicle", "pedestrian"} <= kinds
    scores = _topic(msgs, "/sim/scores")
    assert [m["step"] for m in scores] == list(range(STEPS))
    assert all("nc" in m and "progress_m" in m for m in scores)
