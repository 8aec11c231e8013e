"""`eval`'s off-path family (cameras where a driving stack drives: off the lane centre, higher
or lower, turned) and the PSNR per semantic class of every family: poses against a float64
lane frame, regions, per-class PSNR on a case with a known answer, and the JSON keys."""
import json

import numpy as np
import pytest

from conftest import LAYOUT
from lsd3d_usd.conditioning.view_sampling import building_paths, inside_paths
from lsd3d_usd.eval import class_psnr as CP
from lsd3d_usd.eval import off_path_views as OP
from lsd3d_usd.eval.evaluate import eval_options, evaluate
from lsd3d_usd.layout.usdio import read_layout
from lsd3d_usd.semantics import CLASS_ID

KEYS = ["lateral_-3.5", "lateral_-1.75", "lateral_0", "lateral_1.75", "lateral_3.5",
        "height_0.6", "height_1.6", "height_3", "yaw_15", "yaw_-15"]
POSES = {"lateral_-3.5": (-3.5, 1.6, 0), "lateral_-1.75": (-1.75, 1.6, 0), "lateral_0": (0, 1.6, 0),
         "lateral_1.75": (1.75, 1.6, 0), "lateral_3.5": (3.5, 1.6, 0), "height_0.6": (0, 0.6, 0),
         "height_1.6": (0, 1.6, 0), "height_3": (0, 3.0, 0), "yaw_15": (0, 1.6, 15),
         "yaw_-15": (0, 1.6, -15)}
CLASSES = ["road", "sidewalk", "building", "vegetation", "terrain"]


@pytest.fixture(scope="module")
def layout():
    return read_layout(LAYOUT)


def _lane_frame64(layout, lane_id, s):
    """Centre-line point and heading (chord over s ± 1 m) of a lane, in plain float64."""
    lane = next(ln for ln in layout.lanes if ln.id == lane_id)
    pts = np.array(lane.points, np.float64)
    if lane.direction == "backward":
        pts = pts[::-1]
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])

    def at(t):
        t = min(max(t, 0.0), cum[-1])
        return np.array([np.interp(t, cum, pts[:, k]) for k in range(3)])
    a, b = at(s - 1.0), at(s + 1.0)
    return at(s), np.arctan2(b[1] - a[1], b[0] - a[0])


def test_bin_cameras_stand_where_the_bins_say(layout):
    off = OP.off_path_views(layout, 4, 320, seed=7)
    assert list(off.bins) == KEYS and off.stations == 4
    assert off.bins["lateral_0"] == off.bins["height_1.6"]      # the same cameras, once
    assert len(off.views) == 4 * 9
    fx = 160.0 / np.tan(np.radians(64.6) / 2)                   # nuscenes6 CAM_FRONT
    fps = building_paths(layout)
    for key, idx in off.bins.items():
        lat, h, yaw = POSES[key]
        assert [off.views[i].station for i in idx] == [0, 1, 2, 3]
        for i in idx:
            v = off.views[i]
            cam = v.camera
            p, hd = _lane_frame64(layout, v.lane, v.s_m)
            left = np.array([-np.sin(hd), np.cos(hd), 0.0])
            np.testing.assert_allclose(cam.center, p + lat * left + [0, 0, h], atol=1e-9)
            fwd = np.array([np.cos(hd + np.radians(yaw)), np.sin(hd + np.radians(yaw)), 0.0])
            np.testing.assert_allclose(cam.pose[:3, 2], fwd, atol=1e-9)     # level, turned
            np.testing.assert_allclose(cam.pose[:3, 1], [0, 0, -1], atol=1e-9)
            assert (cam.width, cam.height) == (320, 180)
            assert cam.fx == pytest.approx(fx, rel=1e-12) and cam.fy == pytest.approx(fx, rel=1e-12)
            assert (v.lateral_m, v.height_m, v.yaw_deg) == (lat, h, yaw)
            assert not inside_paths(cam.center, fps)
    # every bin shows the same stations
    stations = {(off.views[i].lane, off.views[i].s_m) for i in off.bins["yaw_15"]}
    assert stations == {(off.views[i].lane, off.views[i].s_m) for i in off.bins["height_3"]}
    again = OP.off_path_views(layout, 4, 320, seed=7)
    assert all(np.array_equal(a.camera.pose, b.camera.pose) for a, b in zip(off.views, again.views))
    assert OP.off_path_views(layout, 0, 320, seed=7).views == []


def test_stations_spread_over_the_regions(layout):
    size = float(layout.chunk_size)
    regions = [[[-1, -1], [-1, 0]], [[0, -1], [0, 0]]]
    off = OP.off_path_views(layout, 6, 64, seed=1, regions=regions)
    assert off.regions == 2
    for i in off.bins["lateral_0"]:
        v = off.views[i]
        p, _ = _lane_frame64(layout, v.lane, v.s_m)
        key = [int(np.floor(p[0] / size)), int(np.floor(p[1] / size))]
        assert key in regions[v.station % 2]


def test_per_class_psnr_drops_only_for_the_perturbed_class():
    rng = np.random.default_rng(0)
    H, W = 24, 32
    sem = np.full((H, W), -1)
    ids = [CLASS_ID[c] for c in CLASSES]
    for k, cid in enumerate(ids):
        sem[:, k * 6:(k + 1) * 6] = cid                  # five stripes, the rest is sky
    target = rng.uniform(0.2, 0.8, (H, W, 3))
    rgb = target + rng.normal(0, 0.01, (H, W, 3))
    before = CP.per_class([CP.view_error(rgb, target, sem)])
    worse = rgb.copy()
    bld = sem == CLASS_ID["building"]
    worse[bld] += 0.1
    after = CP.per_class([CP.view_error(worse, target, sem)])
    for c in CLASSES:
        m = sem == CLASS_ID[c]
        want = -10 * np.log10(np.mean((np.clip(worse[m], 0, 1) - target[m]) ** 2))
        assert after[c] == pytest.approx(want, abs=1e-3)
        if c != "building":
            assert after[c] == before[c]
    assert after["building"] < before["building"] - 10
    # a class no pixel shows has no PSNR; views pool by their pixels
    empty = CP.per_class([CP.view_error(rgb, target, np.full((H, W), -1))])
    assert set(empty) == set(CLASSES) and all(v is None for v in empty.values())
    two = CP.per_class([CP.view_error(rgb, target, sem), CP.view_error(worse, target, sem)])
    m = bld
    sse = ((rgb[m] - target[m]) ** 2).sum() + ((worse[m] - target[m]) ** 2).sum()
    assert two["building"] == pytest.approx(-10 * np.log10(sse / (2 * 3 * m.sum())), abs=1e-3)


def test_baseline_image_is_the_scorers_target(small_scene, tmp_path):
    """The prior baseline takes the scorer's target instead of making it again: the same
    image for the procedural prior, whatever the render."""
    from lsd3d_usd import scene as S
    from lsd3d_usd.eval.prior_baseline import PriorImages
    from lsd3d_usd.proxy.usdio import proxy_arrays
    sc = S.Scene.open(small_scene)
    scorer = CP.Scorer(sc, sc.runs()[0].name, proxy_arrays(sc.layer_path("proxy")))
    base = PriorImages(small_scene, lambda x: x)
    assert base.same_images(scorer.sp) and not base.same_images(None)
    cam = OP.off_path_views(read_layout(sc.layer_path("layout")), 1, 64, seed=0).views[0].camera
    rgb = np.random.default_rng(0).uniform(size=(cam.height, cam.width, 3)).astype(np.float32)
    tgt = scorer.add("x", cam, rgb)
    own = base.deferrer.images(rgb, cam, (1.0,), fine=True)[0]
    np.testing.assert_allclose(tgt, own, atol=1e-6)


def test_eval_json_off_path_and_per_class_keys(small_scene, tmp_path):
    res = evaluate(eval_options(scene=small_scene, out_dir=tmp_path / "e", n_seen=3, per_bin=2,
                                bins=(0.5, 4.0), resolution=(64, 48), frames=3, per_height=1,
                                off_path_per_bin=2, progress=False, log=lambda *a: None))
    js = json.loads((tmp_path / "e" / "eval.json").read_text())
    op = js["novel_off_path"]
    assert list(op["psnr_db_per_bin"]) == KEYS and list(op["fd_over_prior_per_bin"]) == KEYS
    assert all(np.isfinite(v) for v in op["psnr_db_per_bin"].values())
    assert all(v > 0 for v in op["fd_over_prior_per_bin"].values())
    assert op["psnr_db_per_bin"]["lateral_0"] == op["psnr_db_per_bin"]["height_1.6"]
    assert op["bins"]["yaw_-15"] == {"lateral_m": 0.0, "height_m": 1.6, "yaw_deg": -15.0}
    assert js["counts"]["off_path"] == 18 and js["counts"]["off_path_per_bin"] == 2
    pb = js["fd_effnet_lite0"]["prior_baseline"]["off_path"]
    assert list(pb["prior_off_path_over_content"]) == KEYS
    families = [js["seen_views"], *js["novel_views"].values(), js["temporal_warp_err"], op,
                *js["novel_elevated"].values()]
    for fam in families:
        assert list(fam["psnr_db_per_class"]) == CLASSES
    assert js["novel_elevated"]["heldout_lane"]["psnr_db"]["views"] == 3
    road = js["seen_views"]["psnr_db_per_class"]["road"]
    assert road is not None and 5 < road < 99
    assert res.novel_off_path == op
    html = (tmp_path / "e" / "report.html").read_text()
    assert 'src="eval_off_path.png"' in html and (tmp_path / "e" / "eval_off_path.png").is_file()
    assert "PSNR per class" in html


def test_off_path_needs_lanes(layout):
    from dataclasses import replace
    from lsd3d_usd.errors import InputError
    with pytest.raises(InputError, match="no drivable lanes"):
        OP.off_path_views(replace(layout, lanes=[]), 1, 64, seed=0)
