"""Pedestrians and cyclists in the sensor ground truth: a camera looking at one gets pixels of
its class and instance id where it stands, and a LiDAR beside it returns points labelled with
its class and instance, inside its box (5 cm)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import generate_small


@pytest.fixture(scope="module")
def people_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("people") / "scene"
    generate_small(out, steps=0, actors=True, parked=0, moving=2, pedestrians=6, cyclists=2,
                   surfels=20_000)
    return out


def _look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """camera-to-world of a camera at ``eye`` looking at ``target`` (x right, y down, z fwd)."""
    f = np.asarray(target, float) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, d, f, eye
    return m


@pytest.mark.parametrize("label", ["pedestrian", "cyclist"])
def test_people_in_camera_labels_and_lidar(people_scene, label):
    from pxr import Usd

    from lsd3d_usd import scene as S
    from lsd3d_usd.render.camera import Camera
    from lsd3d_usd.semantics import CLASS_ID
    from lsd3d_usd.views.boxes import local_boxes
    from lsd3d_usd.views.ego import EgoTrack
    from lsd3d_usd.views.frame import render_scene
    from lsd3d_usd.views.labels import Instances
    from lsd3d_usd.views.lidar_sweep import mesh_actors, sweep
    from lsd3d_usd.sensors.lidar import model_from_table
    from lsd3d_usd.views.stage_data import SceneReader

    stage = Usd.Stage.Open(str(S.Scene.open(people_scene).root_layer_path))
    reader = SceneReader(stage, use_env=False)
    actors = reader.actors
    tcps = stage.GetTimeCodesPerSecond()
    code = stage.GetStartTimeCode()
    instances = Instances.of(actors)
    lboxes = local_boxes(actors)
    qs = [q for q, a in enumerate(actors.actors) if a.label == label]
    assert qs, f"no {label} in the scene"
    q = qs[0]
    M = actors.transforms(code)[q]
    lo, hi = lboxes[q]
    centre = (M @ np.append((lo + hi) / 2, 1.0))[:3]
    # a camera 6 m away along the actor's own left, at chest height, looking at it
    side = M[:3, 1] / np.linalg.norm(M[:3, 1])
    eye = centre + 6.0 * side + np.array([0.0, 0.0, 0.3])
    cam = Camera.from_fov(160, 120, 60.0, _look_at(eye, centre), near=0.1, far=200.0)
    frame = render_scene(reader, cam, code, instances=instances)
    mine = frame.labels.instance_id == instances.ids[q]
    assert mine.sum() > 30, "the actor is not drawn"
    assert (frame.labels.class_id[mine] == CLASS_ID[label]).all()
    # what is drawn there is the actor, at about its distance
    z = frame.labels.z[mine]
    assert abs(float(np.median(z)) - 6.0) < 1.0

    # a small LiDAR at the camera's place, level, facing the actor
    model = model_from_table({"beams": 32, "elevation_min": -25, "elevation_max": 15,
                              "columns": 720, "min_range": 0.3, "max_range": 40.0,
                              "mount": {"z": 0.0}}, "people.toml")
    yaw = np.arctan2(-side[1], -side[0])
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0, 0, 1.0]])
    t0 = code / tcps
    track = EgoTrack(np.array([t0, t0 + 1.0]), np.array([eye, eye]), np.stack([R, R]))
    sw = sweep(reader, model, track.at, t0, tcps, instances, actors=mesh_actors(actors, tcps))
    pts = sw.instance_id == instances.ids[q]
    assert pts.sum() > 10, "the LiDAR does not see the actor"
    assert (sw.class_id[pts] == CLASS_ID[label]).all()
    # inside its box at each point's own time (5 cm)
    for k in np.flatnonzero(pts):
        Mk = actors.transforms(round((t0 + float(sw.t[k])) * tcps, 6))[q]
        local = np.linalg.solve(Mk, np.append(sw.xyz_world[k], 1.0))[:3]
        assert np.all(local >= lo - 0.05) and np.all(local <= hi + 0.05), (local, lo, hi)
