"""`eval`'s elevated family: poses (heights, pitch, looking down at the layout, seeded), the
scene's Overview cameras, option errors, and `novel_elevated` of an eval of the small scene."""
import json

import numpy as np
import pytest

from conftest import LAYOUT
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.eval import elevated_views as E
from lsd3d_usd.eval.evaluate import eval_options, evaluate
from lsd3d_usd.conditioning.view_sampling import building_paths, inside_paths
from lsd3d_usd.layout.usdio import read_layout


@pytest.fixture(scope="module")
def layout():
    return read_layout(LAYOUT)


def _pitch(cam) -> float:
    return float(np.degrees(np.arcsin(-cam.pose[2, 2])))


def test_poses_heights_pitch_and_looking_down_at_the_layout(layout):
    views = E.elevated_views(layout, (5.0, 15.0, 30.0), 6, (20.0, 60.0), 3, 64, 48, 70.0)
    assert [v.group for v in views] == ["5"] * 6 + ["15"] * 6 + ["30"] * 6
    ground = float(np.median(np.concatenate([ln.points[:, 2] for ln in layout.drivable_lanes()])))
    (x0, y0), (x1, y1) = layout.bounds()
    fps = building_paths(layout)
    solids = [(fp, b.height_hint) for fp, b in zip(fps, layout.buildings)]
    for v in views:
        c = v.camera.center
        assert c[2] - ground == pytest.approx(v.height_m, abs=0.5)
        assert 20.0 - 1e-6 <= _pitch(v.camera) <= 60.0 + 1e-6
        assert _pitch(v.camera) == pytest.approx(v.pitch_deg, abs=1e-6)
        assert x0 <= c[0] <= x1 and y0 <= c[1] <= y1 and not inside_paths(c, fps)
        # the optical axis meets the ground inside the layout: the camera looks at the scene
        f = v.camera.pose[:3, 2]
        hit = c + f * (ground - c[2]) / f[2]
        assert x0 <= hit[0] <= x1 and y0 <= hit[1] <= y1
        assert (v.camera.width, v.camera.height) == (64, 48)
        # no building stands between the camera and the point it looks at
        for t in np.linspace(0.05, 0.95, 19):
            p = c + t * (hit - c)
            assert not any(p[2] < top and inside_paths(p, [fp]) for fp, top in solids)
    # view k of every height looks at the same lane point
    for k in range(6):
        hits = []
        for v in views[k::6]:
            f, c = v.camera.pose[:3, 2], v.camera.center
            hits.append(c + f * (ground - c[2]) / f[2])
        np.testing.assert_allclose(hits[0], hits[1], atol=0.5)
        np.testing.assert_allclose(hits[0], hits[2], atol=0.5)


def test_poses_are_seeded(layout):
    def poses(seed):
        return np.stack([v.camera.pose for v in
                         E.elevated_views(layout, (5.0, 30.0), 3, (20.0, 60.0), seed, 32, 24, 70.0)])
    np.testing.assert_array_equal(poses(1), poses(1))
    assert not np.allclose(poses(1), poses(2))
    assert E.elevated_views(layout, (5.0,), 0, (20.0, 60.0), 0, 32, 24, 70.0) == []


def test_overview_cameras_of_the_scene(small_scene, layout):
    stage = S.Scene.open(small_scene).open_stage()
    views = E.overview_views(stage, layout, 64, 36)
    assert {v.name for v in views} == {"Top", "SouthWest", "SouthEast", "NorthEast", "NorthWest"}
    assert all(v.group == E.OVERVIEW and v.camera.width == 64 for v in views)
    top = next(v for v in views if v.name == "Top")
    assert top.pitch_deg == pytest.approx(90.0, abs=1e-3) and top.height_m > 30.0
    assert all(v.pitch_deg == pytest.approx(35.0, abs=0.1) for v in views if v.name != "Top")
    from pxr import Usd
    assert E.overview_views(Usd.Stage.CreateInMemory(), layout, 64, 36) == []


@pytest.mark.parametrize("key,value,needle", [
    ("heights", "5,-1", "--heights"), ("heights", "5,x", "--heights"),
    ("heights", "5,5", "distinct"), ("pitch", "60,20", "--pitch"), ("pitch", "0,60", "--pitch"),
    ("pitch", "20,90", "--pitch"), ("pitch", "a,b", "--pitch"),
])
def test_bad_elevated_options(key, value, needle):
    with pytest.raises(InputError, match=needle):
        eval_options("x", **{key: value})


@pytest.mark.parametrize("argv,needle", [
    (["--heights", "0"], "--heights"), (["--pitch", "10,95"], "--pitch"),
    (["--per-height", "-1"], "--per-height"),
])
def test_bad_elevated_flags_are_one_error_line(cli_error, small_scene, tmp_path, argv, needle):
    cli_error(["eval", small_scene, "-o", tmp_path / "e", *argv], needle)
    assert not (tmp_path / "e").exists()


def test_eval_novel_elevated(small_scene, tmp_path):
    res = evaluate(eval_options(small_scene, n_seen=3, per_bin=1, bins=(1.0,), resolution=(64, 36),
                                frames=2, per_height=2, out_dir=tmp_path / "e", progress=False,
                                log=lambda *a: None)).to_json()
    ne = res["novel_elevated"]
    assert set(ne) == {"5", "15", "30", "overview", "heldout_lane"}
    assert res["heights_m"] == [5.0, 15.0, 30.0] and res["pitch_deg"] == [20.0, 60.0]
    assert res["counts"]["elevated"] == 11 and res["counts"]["overview"] == 5
    for g in ("5", "15", "30", "overview"):
        r = ne[g]
        assert r["views"] == (5 if g == "overview" else 2)
        for k in ("fd", "fd_over_content", "prior_fd_over_content", "fd_over_prior",
                  "fd_vs_prior_images"):
            assert np.isfinite(r[k]) and r[k] >= 0, (g, k)
        assert all(np.isfinite(r["psnr_db"][k]) for k in ("mean", "median", "min", "max"))
        assert r["psnr_db"]["views"] == r["views"]
    cams = ne["overview"]["psnr_db_per_camera"]
    assert set(cams) == {"Top", "SouthWest", "SouthEast", "NorthEast", "NorthWest"}
    assert all(np.isfinite(v) for v in cams.values())
    assert ne["heldout_lane"]["psnr_db"]["views"] == res["counts"]["heldout_lane"]
    pb = res["fd_effnet_lite0"]["prior_baseline"]["elevated"]
    assert set(pb["prior_elevated_over_content"]) == {"5", "15", "30", "overview"}
    html = (tmp_path / "e" / "report.html").read_text()
    assert "Elevated views" in html and "SouthWest" in html and 'src="eval_elevated.png"' in html
    assert (tmp_path / "e" / "eval_elevated.png").is_file()
    assert json.loads((tmp_path / "e" / "eval.json").read_text())["novel_elevated"] == \
        json.loads(json.dumps(ne))


def test_cli_no_overview(small_scene, tmp_path, capsys):
    from lsd3d_usd.cli import main
    js = tmp_path / "o.json"
    code = main(["eval", str(small_scene), "--json", str(js), "--seen", "2", "--per-bin", "1",
                 "--bins", "2", "--resolution", "64x36", "--frames", "2", "-o", str(tmp_path / "r"),
                 "--heights", "10", "--per-height", "1", "--pitch", "45,45", "--no-overview",
                 "--no-progress", "--no-prior-baseline"])
    assert code == 0
    ne = json.loads(js.read_text())["novel_elevated"]
    assert set(ne) == {"10", "heldout_lane"} and ne["10"]["views"] == 1
    assert ne["10"]["pitch_deg_median"] == pytest.approx(45.0)
    assert "elevated views: 10 m PSNR" in capsys.readouterr().out
