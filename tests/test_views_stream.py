"""Chunk streaming for renders: only the chunks near the cameras are loaded, those behind are
unloaded, and a frame is the same as with everything loaded when the radius covers the view."""
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd

from conftest import ROOT
from lsd3d_usd import scene as S
from lsd3d_usd.config import generate_config
from lsd3d_usd.pipeline import RunOptions, generate
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.views.frame import render_scene
from lsd3d_usd.views.stage_data import SceneReader

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"   # chunks (-1|0, -1|0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("stream") / "scene"
    generate(generate_config(layout=LAYOUT, steps=0, surfels=6000, env_resolution=(64, 32),
                             parked=2, moving=2),
             RunOptions(out=Path(out), progress=False, log=lambda *a: None))
    return out


def _camera(eye, target):
    return Camera.from_fov(96, 64, 70.0, pose=look_at(np.array(eye, float), np.array(target, float)),
                           near=0.1, far=2000.0)


def test_streamed_frame_equals_the_fully_loaded_frame(scene):
    cam = _camera((-30.0, -2.0, 1.6), (30.0, -2.0, 1.0))
    full = render_scene(SceneReader(S.open_stage(scene)), cam)
    stage = Usd.Stage.Open(str(Path(scene) / "scene.usda"), Usd.Stage.LoadNone)
    reader = SceneReader(stage, stream_radius=500.0)
    streamed = render_scene(reader, cam)
    assert len(reader.stream.loaded) == 4
    np.testing.assert_allclose(streamed.rgb, full.rgb, atol=1e-6)
    np.testing.assert_allclose(streamed.alpha, full.alpha, atol=1e-6)


def test_only_nearby_chunks_are_loaded_and_those_behind_unloaded(scene):
    stage = Usd.Stage.Open(str(Path(scene) / "scene.usda"), Usd.Stage.LoadNone)
    reader = SceneReader(stage, stream_radius=20.0, actors=False)
    reader.surfels(near=np.array([[-60.0, -60.0, 1.6]]))        # deep inside chunk (-1, -1)
    assert reader.stream.loaded == {(-1, -1)}
    loaded = {str(p) for p in stage.GetLoadSet()}
    assert f"{S.SURFELS_PATH}/Chunk_m1_m1" in loaded and f"{S.PROXY_PATH}/Chunk_m1_m1" in loaded
    assert f"{S.SURFELS_PATH}/Chunk_0_0" not in loaded
    f = reader.surfels(near=np.array([[95.0, 95.0, 1.6]]))      # 134 m away: the old one goes
    assert reader.stream.loaded == {(0, 0)}
    assert f"{S.SURFELS_PATH}/Chunk_m1_m1" not in {str(p) for p in stage.GetLoadSet()}
    assert f is not None and np.all(f.positions[:, :2] >= -5.0)
    # hysteresis: a camera just beyond the radius of a loaded chunk keeps it
    reader.surfels(near=np.array([[-10.0, 95.0, 1.6]]))          # 10 m from (0, 0), in (-1, 0)
    assert reader.stream.loaded == {(0, 0), (-1, 0)}
    reader.surfels(near=np.array([[-90.0, 95.0, 1.6]]))          # 90 m: inside radius + chunk
    assert (0, 0) in reader.stream.loaded and (-1, 0) in reader.stream.loaded


def test_rig_render_streams_by_default(scene, tmp_path, run_cli):
    r = run_cli("render", scene, "--rig", "waymo5", "--route", "w_in,j_we,e_out", "--seconds", "0.5",
                "--fps", "4", "--resolution", "64", "--no-video", "--no-overview", "-o",
                tmp_path / "rig", "--stream-radius", "150")
    assert r.returncode == 0, r.stderr
    assert len(list((tmp_path / "rig" / "Front").glob("*.png"))) == 2
    bad = run_cli("render", scene, "--rig", "waymo5", "--route", "w_in", "-o", tmp_path / "x",
                  "--stream-radius", "-1")
    assert bad.returncode == 1 and "--stream-radius -1" in bad.stderr
