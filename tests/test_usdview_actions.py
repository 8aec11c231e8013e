"""usdview actions as plain functions: cameras (prim and free camera), rendering that follows
layer muting, GGDS run listing / muting / solo cycling, surfel statistics of a selection."""
from dataclasses import replace

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, from_usd, look_at, to_usd
from lsd3d_usd.splats.field import SurfelField, rgb_to_sh_dc
from lsd3d_usd.splats.usdio import write_surfel_file, write_surfels
from lsd3d_usd.usdview import actions
from lsd3d_usd.views.frame import render_scene
from lsd3d_usd.views.images import read_image
from lsd3d_usd.views.stage_data import SceneReader

RUNS = ("ggds_20260101-000000", "ggds_20260102-000000", "ggds_20260103-000000")


def grey_wall(n_side=40):
    """A 4 m x 4 m wall of surfels at x = 10 facing the origin, grey; semantic 'building'."""
    from lsd3d_usd.semantics import CLASSES, CLASS_ID
    g = (np.arange(n_side) + 0.5) / n_side * 4.0 - 2.0
    yy, zz = np.meshgrid(g, g + 2.0)
    n = yy.size
    pos = np.stack([np.full(n, 10.0), yy.ravel(), zz.ravel()], 1).astype(np.float32)
    # normal along -x: rotate local z (0,0,1) onto -x: 90 deg about y -> quaternion xyzw
    q = np.tile(np.array([0.0, -np.sqrt(0.5), 0.0, np.sqrt(0.5)], np.float32), (n, 1))
    sh = np.zeros((n, 1, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(np.full((n, 3), 0.5, np.float32))
    return SurfelField(positions=pos, orientations=q, scales=np.full((n, 2), 0.08, np.float32),
                       opacities=np.full(n, 0.95, np.float32), sh=sh,
                       semantic_ids=np.full(n, CLASS_ID["building"], np.int32),
                       semantic_classes=CLASSES)


@pytest.fixture
def scene(tmp_path):
    """A scene folder: surfels + three GGDS runs tinting the wall red, green, blue (newest
    = blue), and a camera looking at the wall."""
    sc = S.Scene.create(tmp_path / "scene")
    base = grey_wall()
    write_surfel_file(str(sc.layer_path("surfels")), base)
    sc.add_layer("surfels")
    for name, rgb in zip(RUNS, ((0.9, 0.05, 0.05), (0.05, 0.9, 0.05), (0.05, 0.05, 0.9))):
        stage = S.new_stage()
        sh = base.sh.copy()
        sh[:, 0] = rgb_to_sh_dc(np.tile(np.array(rgb, np.float32), (base.n, 1)))
        write_surfels(stage, S.SURFELS_PATH, replace(base, sh=sh), over=True, attributes=("sh",))
        sc.write_layer(f"{name}.usdc", stage, S.provenance("ggds", {}, stepsDone=7, complete=True))
    cams = S.new_stage()
    cam = Camera.from_fov(64, 48, 40.0, pose=look_at((0, 0, 2), (10, 0, 2)))
    to_usd(cams, "/World/Cameras/Front", cam)
    sc.write_layer("actors", cams)   # a step layer that may hold cameras
    return sc


def mean_rgb(stage, time=None):
    cam = actions.view_camera(stage.GetPrimAtPath("/World/Cameras/Front"), size=(64, 48))
    res = actions.render_view(stage, cam, time, use_env=False)
    c = res.frame.rgb[16:32, 24:40].reshape(-1, 3).mean(0)
    return c, res


def test_view_camera_prim_and_free_camera_agree(scene):
    stage = scene.open_stage()
    prim = stage.GetPrimAtPath("/World/Cameras/Front")
    a = actions.view_camera(prim, size=(1280, 960))
    ref = from_usd(prim, None, 640, 480)
    assert (a.width, a.height) == (640, 480)           # capped at 640 wide, aspect kept
    np.testing.assert_allclose(a.K, ref.K)
    np.testing.assert_allclose(a.pose, ref.pose, atol=1e-9)
    gf = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default())
    b = actions.view_camera(None, gf, Usd.TimeCode.Default(), size=(320, 240))
    np.testing.assert_allclose(b.K, from_usd(prim, None, 320, 240).K, rtol=1e-6)
    np.testing.assert_allclose(b.pose, ref.pose, atol=1e-6)
    with pytest.raises(InputError, match="no camera"):
        actions.view_camera(None, None)


def test_render_matches_preview_and_follows_muting(scene):
    stage = scene.open_stage()
    c_all, res = mean_rgb(stage)
    assert res.image.dtype == np.uint8 and res.image.shape == (48, 64, 3)
    assert res.surfels == 1600
    # Identical to `lsd3d-usd render`'s own path on the same inputs.
    ref = render_scene(SceneReader(stage, use_env=False), res_camera(stage))
    np.testing.assert_array_equal(ref.rgb, res.frame.rgb)
    assert c_all[2] > 3 * c_all[0]                       # the newest run (blue) wins
    actions.set_run_muted(stage, RUNS[2], True)
    c_green, _ = mean_rgb(stage)
    assert c_green[1] > 3 * c_green[2]                   # next newest shows through
    for r in RUNS[:2]:
        actions.set_run_muted(stage, r, True)
    c_base, _ = mean_rgb(stage)
    assert np.ptp(c_base) < 0.02 * c_base.mean()          # grey initial surfels
    assert actions.unmute_all_runs(stage) == 3
    np.testing.assert_allclose(mean_rgb(stage)[0], c_all)


def res_camera(stage):
    return actions.view_camera(stage.GetPrimAtPath("/World/Cameras/Front"), size=(64, 48))


def test_png_written(scene, tmp_path):
    stage = scene.open_stage()
    _, res = mean_rgb(stage)
    p = actions.save_png(res, tmp_path / "shots" / "r.png")
    img = read_image(str(p))
    assert img.shape[:2] == (48, 64)


def test_runs_listing_solo_cycle_and_no_file_changes(scene):
    stage = scene.open_stage()
    root = scene.root_layer_path.read_bytes()
    runs = actions.ggds_runs(stage)
    assert [r.name for r in runs] == list(reversed(RUNS))
    assert all(not r.muted and r.steps == 7 and r.complete for r in runs)
    seen = [actions.solo_next_run(stage) for _ in range(5)]
    assert seen == [f"only {RUNS[2]}", f"only {RUNS[1]}", f"only {RUNS[0]}",
                    "no GGDS run: initial surfels", "all 3 GGDS run(s) active"]
    actions.solo_next_run(stage)
    assert [r.muted for r in actions.ggds_runs(stage)] == [False, True, True]
    assert set(stage.GetMutedLayers()) == {str(scene.layer_path(f"{r}.usdc")) for r in RUNS[:2]}
    assert scene.root_layer_path.read_bytes() == root    # session muting writes nothing
    with pytest.raises(InputError, match="no GGDS run 'ggds_nope'"):
        actions.set_run_muted(stage, "ggds_nope", True)


def test_persistently_muted_run_is_listed_not_toggled(scene):
    scene.mute(RUNS[1])
    stage = scene.open_stage()
    runs = {r.name: r for r in actions.ggds_runs(stage)}
    assert runs[RUNS[1]].persistent and runs[RUNS[1]].muted
    assert "muted in scene file" in runs[RUNS[1]].label()
    with pytest.raises(InputError, match="lsd3d-usd scene unmute"):
        actions.set_run_muted(stage, RUNS[1], False)
    # The cycle skips it: two toggleable runs.
    assert actions.solo_next_run(stage) == f"only {RUNS[2]}"
    assert actions.solo_next_run(stage) == f"only {RUNS[0]}"


def test_one_run_toggles_and_none_is_reported(tmp_path, scene):
    stage = Usd.Stage.CreateInMemory()
    assert actions.solo_next_run(stage) == "no GGDS runs to compare"
    for r in RUNS[:2]:
        scene.remove_layer(r)
    stage = scene.open_stage()
    assert actions.solo_next_run(stage) == "no GGDS run: initial surfels"
    assert actions.solo_next_run(stage) == "all 1 GGDS run(s) active"


def test_selection_statistics(scene):
    stage = scene.open_stage()
    world = stage.GetPrimAtPath("/World")
    stats = actions.selection_stats(stage, [world])          # found beneath the selection
    assert [s["path"] for s in stats] == ["/World/Surfels"]
    assert stats[0]["count"] == 1600 and stats[0]["classes"] == {"building": 1600}
    assert actions.selection_stats(stage, [])[0]["path"] == "/World/Surfels"   # none: all
    text = actions.format_stats(stats)
    assert "/World/Surfels (Lsd3dSurfelField): 1,600 surfels, SH degree 0" in text
    assert "building 1,600" in text and "opacity     min 0.95" in text
    with pytest.raises(InputError, match="no surfel .* in /World/Cameras"):
        actions.selection_stats(stage, [stage.GetPrimAtPath("/World/Cameras")])


def test_render_without_surfels_is_a_clear_error():
    stage = S.new_stage()
    cam = Camera.from_fov(32, 24, 60.0)
    with pytest.raises(InputError, match="no surfels to render"):
        actions.render_view(stage, cam)
