"""`eval` on a tiny generated scene: the JSON's documented keys, the report files, seen views
from the GGDS run's provenance, the --steps 0 fallback, the missing-weights path and bad
input (one clear error, nothing half-written)."""
import json
import shutil

import numpy as np
import pytest

from conftest import ROOT, SMALL_SCENE
from lsd3d_usd import scene as S
from lsd3d_usd.errors import InputError
from lsd3d_usd.eval import models
from lsd3d_usd.eval import lane_views as V
from lsd3d_usd.eval.evaluate import eval_options, evaluate
from lsd3d_usd.conditioning.view_sampling import sample_views
from lsd3d_usd.layout.usdio import read_layout

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"




def _opts(scene, **kw):
    base = dict(scene=scene, n_seen=3, per_bin=2, bins=(0.5, 4.0), resolution=(64, 48), frames=4,
                progress=False, log=lambda *a: None)
    base.update(kw)
    return eval_options(**base)


def _write_png(path, rgb):
    import OpenImageIO as oiio
    px = np.ascontiguousarray((np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(px.shape[1], px.shape[0], 3, "uint8"))
    out.write_image(px)
    out.close()


def test_eval_end_to_end(small_scene, tmp_path):
    ref = tmp_path / "ref"
    ref.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        _write_png(ref / f"r{i}.png", rng.uniform(size=(40, 50, 3)))
    (ref / "notes.txt").write_text("not an image")
    weights = tmp_path / "weights"
    weights.mkdir()
    (weights / "dinov2_vits14_pretrain.pth").write_bytes(b"not really weights")
    res = evaluate(_opts(small_scene, reference=ref, weights=weights)).to_json()

    runs = S.Scene.open(small_scene).runs()
    assert res["run"] == runs[0].name and "training cameras" in res["seen_views_source"]
    assert res["counts"] == {"train_views": 4, "seen": 3, "novel": 4, "novel_per_bin": 2,
                             "heldout_lane": 3, "trajectory_frames": 4, "reference": 3,
                             "elevated": 17, "elevated_per_height": 4, "overview": 5,
                             "off_path": 27, "off_path_per_bin": 3}
    fd = res["fd_effnet_lite0"]
    for r in [fd["seen_vs_novel"]["overall"], *fd["seen_vs_novel"]["per_bin"].values(),
              fd["vs_reference"]["seen"], fd["vs_reference"]["novel"], fd["seen_vs_heldout_lane"]]:
        assert np.isfinite(r["value"]) and r["value"] >= 0 and r["dims"] == 1280
    assert set(fd["seen_vs_novel"]["per_bin"]) == {"0.5", "4"}
    assert fd["seen_vs_novel"]["per_bin"]["4"]["n"] == [3, 2]
    # Random noise images are far from street renders; the renders are closer to each other.
    assert fd["vs_reference"]["seen"]["value"] > fd["seen_vs_novel"]["overall"]["value"]
    assert res["warnings"] and "fewer samples than feature dimensions" in res["warnings"][0]
    # Geometry: the surfels were initialised on the proxy, so the road agrees closely.
    road = res["geometry"]["seen"]["per_class"]["road"]
    assert road["pixels"] > 0 and road["depth_rel_err_median"] < 0.05
    assert set(res["multiview_depth_err"]["per_bin"]) == {"0.5", "4"}
    t = res["temporal_warp_err"]
    assert t["pairs"] == 3 and t["warp_err"] is not None and 0 <= t["warp_err"] < 1
    # Weight-based metrics: never computed here, always with a reason.
    un = {u["metric"]: u["reason"] for u in res["unavailable"]}
    assert set(un) == {"fid_inception", "fd_dinov2", "clip_score", "fvd"}
    assert "not implemented" in un["fd_dinov2"] and "none of" in un["fid_inception"]
    # Report files: HTML referencing PNGs next to it, JSON equal to what was returned.
    out = small_scene / "eval"
    html = (out / "report.html").read_text()
    for name in ("eval_contact_sheet.png", "eval_fd.png", "eval_geometry.png", "eval_temporal.png",
                 "loss.png"):
        assert (out / name).is_file() and f'src="{name}"' in html
    assert "fd_effnet_lite0" in html and "FID" not in html.replace("not FID", "")
    assert json.loads((out / "eval.json").read_text())["fd_effnet_lite0"] == json.loads(json.dumps(fd))
    assert not list(out.glob(".*tmp*"))


def test_seen_views_come_from_the_run_record(small_scene):
    sc = S.Scene.open(small_scene)
    info = sc.runs()[0]
    stored = json.loads((small_scene / "ggds" / info.name / "views.json").read_text())
    seen = V.seen_views(sc, read_layout(sc.layer_path("layout")), None, 128, 96)
    assert seen.run == info.name and len(seen.views) == len(stored)
    for v, d in zip(seen.views, stored):
        np.testing.assert_allclose(v.camera.pose.reshape(-1), d["pose"])
        assert (v.camera.width, v.camera.height) == (128, 96)
        assert v.camera.fx == pytest.approx(2 * d["intrinsics"][2])   # same field of view
    with pytest.raises(InputError, match="no GGDS run 'ggds_nope'"):
        V.seen_views(sc, None, "ggds_nope", 64, 48)


def test_scene_without_ggds_run_uses_sampled_views(small_scene, tmp_path):
    copy = tmp_path / "scene"
    shutil.copytree(small_scene, copy, ignore=shutil.ignore_patterns("eval"))
    sc = S.Scene.open(copy)
    sc.remove_layer(sc.runs()[0].name)   # as after `generate --steps 0`
    layout = read_layout(sc.layer_path("layout"))
    seen = V.seen_views(sc, layout, None, 64, 48)
    seed = SMALL_SCENE["seed"]
    assert seen.run is None and "no GGDS run" in seen.source and f"seed {seed}" in seen.source
    want = sample_views(layout, V.GGDS_N_VIEWS, 64, 48, seed=seed, novel_frac=V.GGDS_NOVEL_FRAC,
                        fov_deg=V.GGDS_FOV_DEG)
    assert all(np.array_equal(a.camera.pose, b.camera.pose) for a, b in zip(seen.views, want))
    res = evaluate(_opts(copy, bins=(1.0,), per_bin=1, frames=2, n_seen=2, n_heldout=0)).to_json()
    assert res["run"] is None and "no GGDS run" in res["seen_views_source"]
    assert "seen_vs_heldout_lane" not in res["fd_effnet_lite0"] and res["counts"]["heldout_lane"] == 0
    assert "loss.png" not in res["files"] and "fd_effnet_lite0" in res
    assert res["unavailable"][0] == {"metric": "fd_effnet_lite0.vs_reference",
                                     "reason": "no --reference DIR of images given"}


def test_prior_baseline_measures_the_views_not_the_scene(small_scene, tmp_path):
    """The prior's own images of eval's cameras: the same for the GGDS surfels and for the
    initial ones seen from the same cameras (the run muted, its cameras kept), while the
    scene's distances differ; each ratio is its FD over its content change."""
    copy = tmp_path / "scene"
    shutil.copytree(small_scene, copy, ignore=shutil.ignore_patterns("eval"))
    sc = S.Scene.open(copy)
    run = sc.runs()[0].name
    after = evaluate(_opts(copy, out_dir=tmp_path / "a")).to_json()
    sc.mute(run)
    before = evaluate(_opts(copy, run=run, out_dir=tmp_path / "b")).to_json()
    pa, pb = (r["fd_effnet_lite0"]["prior_baseline"] for r in (after, before))
    assert pa["prior"] == pb["prior"] == "procedural"
    # the muted run's own recorded prior, not a default
    assert pa["prior_source"] == pb["prior_source"] == f"recorded by GGDS run {run}"
    assert set(pa["prior_novel_over_content"]) == {"0.5", "4"}
    for k in ("0.5", "4"):
        assert pa["seen_vs_novel"]["per_bin"][k]["value"] == pytest.approx(
            pb["seen_vs_novel"]["per_bin"][k]["value"], rel=1e-6)
    assert pa["seen_vs_heldout_lane"]["value"] == pytest.approx(pb["seen_vs_heldout_lane"]["value"],
                                                                rel=1e-6)
    fa, fb = after["fd_effnet_lite0"], before["fd_effnet_lite0"]
    assert fa["seen_vs_novel"]["per_bin"]["4"]["value"] != fb["seen_vs_novel"]["per_bin"]["4"]["value"]
    for res, p in ((after, pa), (before, pb)):
        f = res["fd_effnet_lite0"]
        for k in ("0.5", "4"):
            scene = f["seen_vs_novel"]["per_bin"][k]["value"] / f["seen_vs_heldout_lane"]["value"]
            prior = p["seen_vs_novel"]["per_bin"][k]["value"] / p["seen_vs_heldout_lane"]["value"]
            assert p["scene_novel_over_content"][k] == pytest.approx(scene, abs=1e-4)
            assert p["prior_novel_over_content"][k] == pytest.approx(prior, abs=1e-4)
            assert p["scene_over_prior"][k] == pytest.approx(scene / prior, rel=1e-3)
    assert res["timings"]["prior_baseline_s"] > 0


def test_prior_baseline_skipped_with_a_reason(small_scene, tmp_path, monkeypatch):
    from lsd3d_usd.eval.prior_baseline import open_baseline
    assert open_baseline(small_scene, False, 3, None) == (None, "turned off (--no-prior-baseline)")
    assert open_baseline(small_scene, None, 0, None)[1] == "no held-out lane views (--heldout 0)"
    monkeypatch.setattr("lsd3d_usd.ggds.priors.scene.recorded_prior_name", lambda p, run: "diffusers")
    base, why = open_baseline(small_scene, None, 3, None)
    assert base is None and "'diffusers' is slow on the CPU" in why and "--prior-baseline" in why
    res = evaluate(_opts(small_scene, out_dir=tmp_path / "e", bins=(1.0,), per_bin=1, frames=2)).to_json()
    assert "prior_baseline" not in res["fd_effnet_lite0"]
    assert {"metric": "fd_effnet_lite0.prior_baseline", "reason": why} in res["unavailable"]


def test_missing_weights_path():
    st = models.status(None)
    assert [s["metric"] for s in st] == ["fid_inception", "fd_dinov2", "clip_score", "fvd"]
    assert all(s["reason"].startswith("no --weights DIR given") for s in st)
    with pytest.raises(InputError, match="--weights /nonexistent/w: no such directory"):
        models.check_weights_dir("/nonexistent/w")


@pytest.mark.parametrize("kind,match", [
    ("missing_scene", "not an lsd3d-usd scene folder"),
    ("missing_ref", "--reference .*: no such directory"),
    ("one_ref", "needs at least 2 images"),
    ("bad_ref", "cannot read image"),
    ("bad_run", "no GGDS run 'nope'"),
    ("bins", "--bins"),
    ("weights", "no such directory"),
    ("baseline", "--prior-baseline needs held-out lane views"),
])
def test_bad_input_is_one_clear_error(small_scene, tmp_path, kind, match):
    ref = tmp_path / "ref"
    ref.mkdir()
    kw = {}
    scene = small_scene
    if kind == "missing_scene":
        scene = tmp_path / "nothing"
    elif kind == "missing_ref":
        kw["reference"] = tmp_path / "nope"
    elif kind == "one_ref":
        _write_png(ref / "a.png", np.zeros((20, 20, 3)))
        kw["reference"] = ref
    elif kind == "bad_ref":
        (ref / "a.png").write_bytes(b"garbage")
        (ref / "b.jpg").write_bytes(b"garbage")
        kw["reference"] = ref
    elif kind == "bad_run":
        kw["run"] = "nope"
    elif kind == "bins":
        kw["bins"] = (1.0, 0.0)
    elif kind == "weights":
        kw["weights"] = tmp_path / "no_weights"
    elif kind == "baseline":
        kw.update(prior_baseline=True, n_heldout=0)
    out = tmp_path / "evalout"
    with pytest.raises(InputError, match=match):
        evaluate(_opts(scene, out_dir=out, **kw))
    assert not out.exists()


def test_cli_eval_json(small_scene, tmp_path, capsys):
    from lsd3d_usd.cli import main
    js = tmp_path / "o.json"
    code = main(["eval", str(small_scene / "scene.usda"), "--json", str(js),  # the root layer, as
                                                                          # every command takes "--seen", "2", "--per-bin", "1",
                 "--bins", "2", "--resolution", "64x48", "--frames", "2", "-o", str(tmp_path / "r"),
                 "--no-progress"])
    assert code == 0
    data = json.loads(js.read_text())
    for key in ("fd_effnet_lite0", "geometry", "multiview_depth_err", "temporal_warp_err",
                "unavailable", "counts", "timings"):
        assert key in data
    out = capsys.readouterr().out
    assert "fd_effnet_lite0 seen vs novel" in out and "unavailable" in out
    assert "scene / the prior's own images: 2 m" in out
    assert "prior_baseline" in data["fd_effnet_lite0"]
    assert main(["eval", str(tmp_path / "none")]) == 1


def test_reference_images_resized_on_load_give_the_same_features(tmp_path):
    import torch

    from lsd3d_usd.eval.evaluate import load_reference, reference_images
    from lsd3d_usd.ggds.losses.effnet import EffNetFeatureExtractor
    rng = np.random.default_rng(1)
    full = [rng.uniform(size=(300, 410, 3)), np.repeat(rng.uniform(size=(90, 120, 1)), 3, axis=2)]
    for i, im in enumerate(full):
        _write_png(tmp_path / f"{i}.png", im)
    files = reference_images(tmp_path, 10)
    small = load_reference(files)
    assert all(s.shape == (224, 224, 3) for s in small)
    ext = EffNetFeatureExtractor()
    q = [(np.clip(im, 0, 1) * 255).astype(np.uint8) / 255.0 for im in full]   # as in the 8-bit PNG
    direct = torch.cat([ext.embed(torch.from_numpy(im).float().permute(2, 0, 1)[None]) for im in q])
    pre = ext.embed(torch.from_numpy(np.stack(small)).permute(0, 3, 1, 2))
    np.testing.assert_allclose(pre.numpy(), direct.numpy(), rtol=1e-4, atol=1e-4)
