"""Sensor rig: geometry, trajectories, depth-order compositing, determinism, occlusion."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from pxr import Usd, UsdGeom

from lsd3d_usd.views.options import RigOptions
from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import from_usd
from lsd3d_usd.sensors.camera import camera_in_ego, rig_camera
from lsd3d_usd.sensors.rigs import load_rig
from lsd3d_usd.views import ego, frame, rig, rig_stage
from lsd3d_usd.views.stage_data import ActorFrame, SceneReader

SAMPLES = Path(__file__).resolve().parents[1] / "samples" / "layouts"
WAYMO5 = load_rig("waymo5").cameras


def _box_surfels(lo, hi, count=8000, color=(0.6, 0.3, 0.2), seed=0):
    from lsd3d_usd.proxy.shapes import box
    from lsd3d_usd.splats.init import mesh_to_surfels
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v, f = box(hi[0] - lo[0], hi[1] - lo[1], lo[2], hi[2])
    v[:, :2] += (lo[:2] + hi[:2]) / 2
    return mesh_to_surfels(v, f, count=count, color=color, opacity=0.98, scale_factor=1.6, seed=seed)


def _car_at(x, y, yaw=0.0):
    from lsd3d_usd.actors.assets import vehicle_meshes
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    ms = vehicle_meshes("car")
    vs, fs, cs, n = [], [], [], 0
    for m in ms:
        vs.append(m.vertices @ Rz.T + [x, y, 0.0])
        fs.append(m.faces + n)
        cs.append(m.colors)
        n += len(m.vertices)
    return ActorFrame(np.concatenate(vs), np.concatenate(fs), np.concatenate(cs), None)


def _ego(x, y, yaw_deg):
    M = np.eye(4)
    M[:3, :3] = ego.yaw_rotations(np.radians(yaw_deg))[0]
    M[:3, 3] = (x, y, 0.0)
    return M


def test_waymo5_geometry():
    names = [c.name for c in WAYMO5]
    assert names == ["Front", "FrontLeft", "FrontRight", "SideLeft", "SideRight"]
    for c in WAYMO5:
        P = camera_in_ego(c)
        fwd = P[:3, 2]
        assert np.isclose(np.degrees(np.arctan2(fwd[1], fwd[0])), c.yaw_deg, atol=1e-9)
        assert np.allclose(P[:3, 3], c.mount) and 1.8 <= c.mount[2] <= 2.1
        assert 45.0 <= c.hfov_deg <= 55.0
        cam = rig_camera(c, np.eye(4), 192)
        assert np.isclose(2 * np.degrees(np.arctan(cam.width / 2 / cam.fx)), c.hfov_deg)
        assert np.isclose(P[:3, 1] @ [0, 0, 1.0], -1.0)   # image down = world down (no roll)


@pytest.fixture()
def rig_scene(tmp_path, monkeypatch):
    """A scene with a surfel 'building', one parked and one moving car (referenced assets,
    in a library outside the scene that LSD3D_ASSET_ROOTS allows)."""
    from lsd3d_usd.actors.assets import write_library
    from lsd3d_usd.actors.usdio import ActorSpec, actors_layer
    from lsd3d_usd.scene import Scene, new_stage
    from lsd3d_usd.splats.usdio import write_surfels
    lib = write_library(tmp_path / "lib", ("car",))
    monkeypatch.setenv("LSD3D_ASSET_ROOTS", str(tmp_path / "lib"))
    sc = Scene.create(tmp_path / "scene")
    st = new_stage()
    write_surfels(st, "/World/Surfels", _box_surfels((5, -8, 0), (25, 2, 8)))
    sc.write_layer("surfels", st)
    rel = "../../lib/car.usda"
    times = np.arange(11) / 10.0
    moving = np.stack([40.0 + 5 * times, np.full_like(times, -12.0), np.zeros_like(times)], 1)
    specs = [ActorSpec("Car_000", "parked", rel, np.array([15.0, 40.0, 0.0]), 0.3),
             ActorSpec("Car_001", "moving", rel, moving, np.zeros_like(times), times=times)]
    sc.write_layer("actors", actors_layer(specs, 24.0, 1.0, {}))
    traj = tmp_path / "poses.json"
    traj.write_text(json.dumps([{"t": 0.0, "x": 10.0, "y": -20.0, "yaw": 0.0},
                                {"t": 1.0, "x": 40.0, "y": -20.0, "z": 0.0, "yaw": 0.0}]))
    return sc, lib["car"], traj


def test_rig_stage_cameras_follow_ego(rig_scene, tmp_path):
    sc, _, traj = rig_scene
    stage, paths, track, tcps, notes, _ = rig_stage.build_rig_stage(sc.root, tmp_path / "out", trajectory=traj,
                                                         fps=10.0, seconds=1.0)
    assert not notes and len(paths) == 6
    # the rig file references the scene, it does not copy it
    assert (tmp_path / "out" / "rig.usda").stat().st_size < 20000
    assert stage.GetPrimAtPath("/World/Surfels")
    for k in (0, 4, 9):
        code = track.times[k] * tcps
        ego = np.array(UsdGeom.Xformable(stage.GetPrimAtPath(rig_stage.EGO_PATH))
                       .ComputeLocalToWorldTransform(Usd.TimeCode(code))).T
        assert np.allclose(ego[:3, 3], [10.0 + 30.0 * track.times[k], -20.0, 0.0], atol=1e-9)
        for spec, path in zip(WAYMO5, paths):
            cam = from_usd(stage.GetPrimAtPath(path), code, 96)
            rel = np.linalg.inv(ego) @ cam.pose
            assert np.allclose(rel, camera_in_ego(spec), atol=1e-5)
            assert np.isclose(2 * np.degrees(np.arctan(cam.width / 2 / cam.fx)), spec.hfov_deg, atol=1e-3)


def test_trajectory_formats_and_errors(tmp_path):
    p = tmp_path / "m.json"
    M = np.eye(4)
    M[:3, 3] = (1, 2, 3)
    p.write_text(json.dumps({"poses": [{"t": 0, "matrix": M.tolist()}, {"t": 2, "x": 5, "y": 2, "yaw": 90}]}))
    tr, clamped = ego.resample(ego.load_trajectory(p), [0.0, 1.0, 3.0])
    assert clamped == 1
    assert np.allclose(tr.positions[1], [3.0, 2.0, 1.5])
    assert np.isclose(np.degrees(tr.yaws()[1]), 45.0)
    for text, msg in [("[]", "non-empty list"), ('[{"x": 1}]', "pose 0"),
                      ('[{"t": 1, "x": 0, "y": 0, "yaw": 0}, {"t": 0, "x": 0, "y": 0, "yaw": 0}]',
                       "strictly increasing"), ("{", "not valid JSON"),
                      ('[{"t": 0, "matrix": [[1, 0], [0, 1]]}]', "4x4")]:
        p.write_text(text)
        with pytest.raises(InputError, match=msg):
            ego.load_trajectory(p)
    with pytest.raises(InputError, match="no such file"):
        ego.load_trajectory(tmp_path / "missing.json")


def test_occluded_actor_appears_past_the_corner():
    """A car behind a surfel building is hidden from the side camera while the ego is beside
    the building and seen once the ego has driven past its corner."""
    building = _box_surfels((5, -8, 0), (25, 2, 8))
    car = _car_at(15.0, 40.0, 0.3)
    side = WAYMO5[3]
    seen = {}
    for x in (15.0, 35.0):
        cam = rig_camera(side, _ego(x, -20.0, 0.0), 96)
        alone = frame.composite(None, car, cam)
        assert alone.actor_mask.sum() > 0             # the car is in the field of view
        out = frame.composite(building, car, cam)
        seen[x] = int(out.actor_mask.sum())
    assert seen[15.0] == 0 and seen[35.0] > 0


def test_surfels_in_front_composite_over_actor():
    """Per pixel the nearer wins: a thin surfel wall in front hides the car, one behind doesn't."""
    car = _car_at(10.0, 0.0, np.pi / 2)
    cam = rig_camera(WAYMO5[0], _ego(0.0, 0.0, 0.0), 64)
    front_wall = _box_surfels((6, -6, 0), (6.2, 6, 4), color=(0.0, 0.8, 0.0))
    back_wall = _box_surfels((16, -6, 0), (16.2, 6, 4), color=(0.0, 0.8, 0.0))
    a = frame.composite(back_wall, car, cam)
    b = frame.composite(front_wall, car, cam)
    assert a.actor_mask.sum() > 20 and b.actor_mask.sum() == 0
    # where the car shows, its colour (not the green wall) is in the image
    m = a.actor_mask
    assert a.rgb[m][:, 1].mean() < 0.5 and b.rgb[m][:, 1].mean() > 0.5


def test_rendering_is_stateless_and_writes_clips(rig_scene, tmp_path):
    sc, _, traj = rig_scene
    stage, paths, track, tcps, *_ = rig_stage.build_rig_stage(sc.root, tmp_path / "o", trajectory=traj,
                                                     fps=10.0, seconds=1.0)
    reader = SceneReader(stage, use_env=False)
    assert len(reader.actors) == 3                 # parked, moving and the ego body

    def rgb_at(code, path):
        cam = from_usd(stage.GetPrimAtPath(path), code, 64, 48)
        return frame.render_scene(reader, cam, code).rgb

    first = rgb_at(12.0, paths[0])
    rgb_at(3.0, paths[3])                      # something else in between
    rgb_at(20.0, paths[5])
    assert np.array_equal(first, rgb_at(12.0, paths[0]))
    assert np.array_equal(first, frame.render_scene(SceneReader(stage, use_env=False),
                                                    from_usd(stage.GetPrimAtPath(paths[0]), 12.0, 64, 48),
                                                    12.0).rgb)  # a fresh reader: the same frame
    # the moving car moves between time codes, the parked one does not
    M0, M1 = reader.actors.transforms(0.0), reader.actors.transforms(24.0)
    moved = [not np.allclose(a, b) for a, b in zip(M0, M1)]
    roles = [a.role for a in reader.actors.actors]
    assert moved[roles.index("moving")] and not moved[roles.index("parked")]

    res = rig.render_rig(sc.root, tmp_path / "clip", RigOptions(trajectory=traj, fps=2.0, seconds=1.0),
                         width=64, use_env=False, progress=False, log=lambda *_: None)
    assert set(res.frames) == {c.name for c in WAYMO5} | {"Overview"}
    assert all(len(v) == 2 and all(p.is_file() for p in v) for v in res.frames.values())
    # an MP4 per camera (imageio-ffmpeg is a dependency): decoded, it has every frame at the
    # PNGs' size (padded to even for yuv420p) and the rig's rate
    from lsd3d_usd.views.images import read_image
    from lsd3d_usd.views.video import read_mp4
    assert set(res.videos) == set(res.frames)
    for name, mp4 in res.videos.items():
        decoded, fps = read_mp4(mp4)
        png = read_image(res.frames[name][1])[..., :3] * 255.0
        h, w = png.shape[:2]
        assert decoded.shape == (2, h + h % 2, w + w % 2, 3) and fps == 2.0
        assert np.abs(decoded[1, :h, :w].astype(np.float32) - png).mean() < 8.0  # lossy H.264


def test_render_command_rig_errors(rig_scene, tmp_path, capsys):
    from lsd3d_usd.cli import main
    sc, _, traj = rig_scene
    assert main(["render", str(sc.root), "-o", str(tmp_path / "x"), "--rig", "waymo5", "--route", "a",
                 "--trajectory", str(traj)]) == 1
    assert "not both" in capsys.readouterr().err
    assert main(["render", str(sc.root), "-o", str(tmp_path / "x"), "--rig", "waymo5", "--route", "a"]) == 1
    assert "needs the scene's layout" in capsys.readouterr().err
    assert main(["render", str(sc.root), "-o", str(tmp_path / "x"), "--rig", "waymo5"]) == 1
    assert "needs the scene's layout" in capsys.readouterr().err   # no layout: no default route


def test_rig_default_route_is_printed_and_reusable(tmp_path, capsys):
    """Without --route / --trajectory the rig drives the longest drivable successor path,
    says which, and that --route gives the very same drive."""
    import shutil

    from lsd3d_usd.cli import main
    from lsd3d_usd.scene import Scene
    sc = Scene.create(tmp_path / "scene")
    shutil.copy(SAMPLES / "hand_crossing.usda", sc.layer_path("layout"))
    sc.add_layer("layout")
    args = ["render", str(sc.root), "--rig", "waymo5", "--seconds", "0.3", "--fps", "10",
            "--resolution", "16", "--no-video", "--no-overview", "--no-progress"]
    assert main(args + ["-o", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    route = out.split("reuse it with --route ", 1)[1].split()[0]
    lanes = route.split(",")
    from lsd3d_usd.layout.usdio import read_layout
    layout = read_layout(SAMPLES / "hand_crossing.usda")
    assert all(b in layout.lane_by_id(a).successors for a, b in zip(lanes, lanes[1:]))
    assert sum(layout.lane_by_id(x).length() for x in lanes) >= 0.3 * 13.9   # covers the clip
    assert main(args + ["-o", str(tmp_path / "b"), "--route", route]) == 0
    assert "no --route given" not in capsys.readouterr().out

    def track(folder):
        st = Usd.Stage.Open(str(folder / "rig.usda"))
        op = UsdGeom.Xformable(st.GetPrimAtPath(rig_stage.EGO_PATH)).GetOrderedXformOps()[0]
        return [tuple(op.Get(t)) for t in op.GetTimeSamples()]
    assert track(tmp_path / "a") == track(tmp_path / "b") and len(track(tmp_path / "a")) == 3


def test_camera_render_draws_actors_like_the_rig(rig_scene, tmp_path):
    """`render --camera` at a time where an actor is in view shows it: the very frame the rig
    writes for that camera and time (one rendering path for both)."""
    from lsd3d_usd.cli import main
    from lsd3d_usd.views.images import read_image
    sc, _, traj = rig_scene
    res = rig.render_rig(sc.root, tmp_path / "clip",
                         RigOptions(trajectory=traj, fps=10.0, seconds=1.0, overview=False,
                                    video=False), width=64, progress=False, log=lambda *_: None)
    k, code = 9, 21.6                 # t = 0.9 s at 24 codes/s: the ego is past the building
    side = WAYMO5[3]
    out = tmp_path / "cam"
    assert main(["render", str(res.rig_layer), "--camera", f"{rig_stage.EGO_PATH}/{side.name}",
                 "--time", str(code), "--resolution", f"64x{side.height_for(64)}", "-o", str(out),
                 "--no-progress"]) == 0
    single = read_image(out / f"{side.name}.png")
    np.testing.assert_array_equal(single, read_image(res.frames[side.name][k]))
    # the parked car is in that frame: without actors the picture differs where it stands
    stage = Usd.Stage.Open(str(res.rig_layer))
    cam = from_usd(stage.GetPrimAtPath(f"{rig_stage.EGO_PATH}/{side.name}"), code, 64, side.height_for(64))
    with_actors = frame.render_scene(SceneReader(stage), cam, code)
    without = frame.render_scene(SceneReader(stage, actors=False), cam, code)
    assert with_actors.actor_mask.sum() > 0
    assert np.abs(with_actors.rgb - without.rgb)[with_actors.actor_mask].max() > 0.05


def test_rig_output_references_the_scene_not_the_checkout_and_is_quiet(rig_scene, tmp_path, capfd):
    """rig.usda points at the scene's own assets/car.usda, or at a car written into the
    output folder; never into samples/. A normal rig render prints no USD warning."""
    from lsd3d_usd.actors.assets import write_vehicle_asset
    from pxr import Sdf
    sc, _, traj = rig_scene
    capfd.readouterr()

    def ego_reference(rig_file):
        layer = Sdf.Layer.FindOrOpen(str(rig_file))
        spec = layer.GetPrimAtPath("/World/Actors/Ego/Ego_000")
        refs = list(spec.referenceList.prependedItems)
        assert len(refs) == 1 and "samples" not in layer.ExportToString()
        return (Path(rig_file).parent / refs[0].assetPath).resolve()

    res = rig.render_rig(sc.root, tmp_path / "a",
                         RigOptions(trajectory=traj, fps=2.0, seconds=1.0, video=False),
                         width=32, progress=False, log=lambda *_: None)
    assert ego_reference(res.rig_layer) == (tmp_path / "a" / "assets" / "car.usda").resolve()
    err = capfd.readouterr().err
    assert "Warning" not in err and "Could not open asset" not in err, err
    own = write_vehicle_asset("car", sc.root / "assets" / "car.usda")   # as generate's actors step
    res = rig.render_rig(sc.root, tmp_path / "b",
                         RigOptions(trajectory=traj, fps=2.0, seconds=1.0, video=False),
                         width=32, progress=False, log=lambda *_: None)
    assert ego_reference(res.rig_layer) == own.resolve()
    assert not (tmp_path / "b" / "assets").exists()
    err = capfd.readouterr().err
    assert "Warning" not in err and "Could not open asset" not in err, err


def test_mp4_encoded_again_when_ffmpeg_ends_early(tmp_path, monkeypatch):
    """Frames that can be read again (a list, a re-iterable) are encoded a second time when
    ffmpeg ends before its input (a broken pipe; no file written); a generator's failure is
    raised; a bad frame is never retried."""
    import imageio_ffmpeg
    from lsd3d_usd.views.video import read_mp4, write_mp4
    real = imageio_ffmpeg.write_frames
    calls = {"n": 0, "fail": 0}

    def flaky(path, *a, **k):
        calls["n"] += 1
        if calls["n"] <= calls["fail"]:
            def dead():
                yield
                raise BrokenPipeError(32, "Broken pipe")
            return dead()
        return real(path, *a, **k)
    monkeypatch.setattr(imageio_ffmpeg, "write_frames", flaky)
    frames = [np.full((8, 10, 3), 40 * i, np.uint8) for i in range(3)]
    calls.update(n=0, fail=1)
    out = write_mp4(tmp_path / "a.mp4", frames, 2.0)
    assert calls["n"] == 2 and read_mp4(out)[0].shape == (3, 8, 10, 3)
    assert not list(tmp_path.glob(".*tmp*"))                    # nothing half-written left
    calls.update(n=0, fail=1)
    with pytest.raises(OSError):
        write_mp4(tmp_path / "b.mp4", (f for f in frames), 2.0)
    assert calls["n"] == 1 and not (tmp_path / "b.mp4").exists()
    class Again:                                                # re-readable, not a list
        def __iter__(self):
            return iter(frames)
    calls.update(n=0, fail=1)
    assert read_mp4(write_mp4(tmp_path / "e.mp4", Again(), 2.0))[0].shape == (3, 8, 10, 3)
    assert calls["n"] == 2
    calls.update(n=0, fail=2)                                   # twice: the second raises
    with pytest.raises(OSError):
        write_mp4(tmp_path / "c.mp4", frames, 2.0)
    calls.update(n=0, fail=0)
    with pytest.raises(ValueError, match="uint8"):
        write_mp4(tmp_path / "d.mp4", [frames[0].astype(np.float32)], 2.0)
