"""`bench ggds` quality run: the issue's JSON keys, finite and in range, from a real (tiny)
generate on the README sample, and the before/after strip."""
import math

import pytest

from lsd3d_usd.benchmarks.ggds import SAMPLES, quality


def test_quality_run_reports_the_issue_keys(tmp_path):
    strip = tmp_path / "strip.png"
    res = quality(SAMPLES / "hand_crossing.usda", steps=2, surfels=2000, resolution=(64, 36),
                  out=tmp_path / "scene", fd=False, strip=strip, log=lambda *a: None)
    assert res["steps"] == 2 and res["surfels"] == 2000
    for key in ("s_per_step", "psnr_novel", "psnr_heldout", "psnr_heldout_2x", "depth_rel_err",
                "normal_err_deg", "off_surface_frac"):
        assert math.isfinite(res[key]), key
    assert 5.0 < res["psnr_novel"] < 60.0
    # the scene read back from USD renders what the run evaluated
    assert abs(res["psnr_heldout"] - res["psnr_novel"]) < 0.05
    assert 5.0 < res["psnr_heldout_2x"] < 60.0
    assert 0.0 <= res["off_surface_frac"] <= 1.0 and res["normal_err_deg"] >= 0.0
    assert (tmp_path / "scene" / "scene.usda").is_file()
    from PIL import Image
    assert Image.open(strip).size[0] > 100


@pytest.mark.slow
def test_quality_run_reports_fd_over_content(tmp_path):
    res = quality(SAMPLES / "hand_crossing.usda", steps=2, surfels=2000, resolution=(64, 36),
                  out=tmp_path / "scene", fd=True, log=lambda *a: None)
    ratios = res["fd_novel_over_content_per_bin"]
    assert set(ratios) == {"0.5", "1", "2", "4", "8"}
    assert res["fd_novel_over_content"] == pytest.approx(max(ratios.values()), abs=1e-3)
    assert res["fd_novel_over_content"] > 0 and res["fd_seeds"] == 1
    prior = res["fd_prior_novel_over_content_per_bin"]
    assert set(prior) == set(ratios) and res["fd_prior_novel_over_content"] == pytest.approx(
        max(prior.values()), abs=1e-3)
    assert all(len(v) == 1 for v in res["fd_prior_novel_over_content_per_seed"].values())
    assert res["fd_novel_over_prior"] == pytest.approx(
        max(ratios[b] / prior[b] for b in ratios), rel=1e-2)
    heights = res["elevated_fd_over_prior_per_height"]
    assert set(heights) == {"5", "15", "30", "overview"}
    assert res["elevated_fd_over_prior"] == pytest.approx(max(heights.values()), abs=1e-3)
    assert set(res["psnr_overview_per_camera"]) == {"Top", "SouthWest", "SouthEast", "NorthEast",
                                                   "NorthWest"}
    assert math.isfinite(res["psnr_overview"])


def test_fd_seeds_below_one_is_refused_before_any_work(capsys, monkeypatch):
    from lsd3d_usd.benchmarks import ggds as B
    from lsd3d_usd.cli import main

    def no_work(*a, **k):
        raise AssertionError("bench ggds started work before checking --fd-seeds")
    monkeypatch.setattr(B, "time_steps", no_work)
    monkeypatch.setattr(B, "quality", no_work)
    assert main(["bench", "ggds", "--quick", "--fd-seeds", "0"]) == 1
    assert "--fd-seeds 0: must be >= 1" in capsys.readouterr().err


def _result(d: dict):
    """An eval result (eval.result.EvalResult's attributes that bench ggds reads) of a
    JSON-shaped dict."""
    from types import SimpleNamespace
    return SimpleNamespace(distances=SimpleNamespace(to_json=lambda: d["fd_effnet_lite0"]),
                           geometry=SimpleNamespace(seen=d["geometry"]["seen"]),
                           novel_elevated=d.get("novel_elevated", {}),
                           novel_off_path=d.get("novel_off_path", {}),
                           seen_views=d.get("seen_views", {}), novel_views=d.get("novel_views", {}),
                           temporal=d.get("temporal_warp_err", {}))


def test_fd_ratios_are_seed_means(monkeypatch, tmp_path):
    """bench ggds's FD keys: each ratio is the mean over the eval seeds of FD / content, the
    prior's likewise, and fd_novel_over_prior the largest bin's quotient of the two means."""
    from lsd3d_usd.benchmarks import ggds as B
    canned = {0: ({"0.5": 10.0, "8": 120.0}, 100.0, {"0.5": 0.2, "8": 1.5}),
              1: ({"0.5": 30.0, "8": 80.0}, 50.0, {"0.5": 0.4, "8": 1.1})}
    seeds = []

    def fake(o):
        seeds.append(o.cfg.seed)
        per, content, prior = canned[o.cfg.seed]
        return _result({"fd_effnet_lite0": {
                    "seen_vs_novel": {"per_bin": {b: {"value": v} for b, v in per.items()}},
                    "seen_vs_heldout_lane": {"value": content},
                    "prior_baseline": {"prior_novel_over_content": prior}},
                "geometry": {"seen": {"all": {"seed": o.cfg.seed}}}})
    monkeypatch.setattr(B, "evaluate", fake)
    res = B.fd_ratios(tmp_path, 2)
    assert seeds == [0, 1] and res["fd_seeds"] == 2
    assert res["fd_novel_over_content_per_seed"] == {"0.5": [0.1, 0.6], "8": [1.2, 1.6]}
    assert res["fd_novel_over_content_per_bin"] == {"0.5": 0.35, "8": 1.4}
    assert res["fd_novel_over_content"] == pytest.approx(1.4)
    assert res["fd_prior_novel_over_content_per_bin"] == {"0.5": 0.3, "8": 1.3}
    assert res["fd_novel_over_prior"] == pytest.approx(max(0.35 / 0.3, 1.4 / 1.3))
    assert res["fd_content"] == 100.0 and res["eval_geometry_seen"] == {"seed": 0}


def test_fd_ratios_carry_novel_elevated(monkeypatch, tmp_path):
    """eval's novel_elevated in bench ggds: its ratios are seed means, the scene's over the
    prior's the largest over the groups; the Overview cameras' PSNR is seed 0's."""
    from lsd3d_usd.benchmarks import ggds as B

    def elevated(seed):
        return {"5": {"fd": 1.0, "fd_over_content": 1.0 + seed, "prior_fd_over_content": 1.0,
                      "psnr_db": {"mean": 20.0 + seed}},
                "overview": {"fd": 1.0, "fd_over_content": 3.0, "prior_fd_over_content": 2.0,
                             "psnr_db": {"mean": 18.0},
                             "psnr_db_per_camera": {"Top": 17.0 + seed, "SouthWest": 19.0}},
                "heldout_lane": {"psnr_db": {"mean": 25.0}}}

    def fake(o):
        return _result({"fd_effnet_lite0": {"seen_vs_novel": {"per_bin": {"1": {"value": 1.0}}},
                                            "seen_vs_heldout_lane": {"value": 1.0}},
                        "geometry": {"seen": {"all": {}}}, "novel_elevated": elevated(o.cfg.seed)})
    monkeypatch.setattr(B, "evaluate", fake)
    res = B.fd_ratios(tmp_path, 2)
    assert res["novel_elevated"] == elevated(0)
    assert res["elevated_psnr_db_per_height"] == {"5": 20.5, "overview": 18.0}
    assert res["elevated_fd_over_content_per_height"] == {"5": 1.5, "overview": 3.0}
    assert res["elevated_fd_over_prior_per_height"] == {"5": 1.5, "overview": 1.5}
    assert res["elevated_fd_over_prior"] == pytest.approx(1.5)
    assert res["psnr_overview_per_camera"] == {"Top": 17.0, "SouthWest": 19.0}
    assert res["psnr_overview"] == pytest.approx(18.0) and res["elevated_psnr_heldout_lane"] == 25.0


def test_fd_ratios_carry_novel_off_path_and_per_class_psnr(monkeypatch, tmp_path):
    """eval's novel_off_path and psnr_db_per_class in bench ggds: the off-path bins' PSNR and
    FD over the prior are seed means, off_path_fd_over_prior the largest bin's; the families'
    per-class PSNR is seed 0's."""
    from lsd3d_usd.benchmarks import ggds as B

    def cls(v):
        return {"road": v, "sidewalk": None, "building": v - 2, "vegetation": v, "terrain": v}

    def fake(o):
        s = o.cfg.seed
        return _result({"fd_effnet_lite0": {"seen_vs_novel": {"per_bin": {"1": {"value": 1.0}}},
                                            "seen_vs_heldout_lane": {"value": 1.0}},
                        "geometry": {"seen": {"all": {}}},
                        "seen_views": {"psnr_db_per_class": cls(30.0 + s)},
                        "novel_views": {"1": {"psnr_db_per_class": cls(28.0)}},
                        "novel_off_path": {"psnr_db_per_bin": {"lateral_0": 30.0 + s,
                                                               "height_3": 26.0},
                                           "fd_over_prior_per_bin": {"lateral_0": 1.0,
                                                                     "height_3": 1.2 + s},
                                           "psnr_db_per_class": cls(27.0 + 2 * s)}})
    monkeypatch.setattr(B, "evaluate", fake)
    res = B.fd_ratios(tmp_path, 2)
    assert res["off_path_psnr_db_per_bin"] == {"lateral_0": 30.5, "height_3": 26.0}
    assert res["off_path_fd_over_prior_per_bin"] == {"lateral_0": 1.0, "height_3": 1.7}
    assert res["off_path_fd_over_prior"] == pytest.approx(1.7)
    assert res["off_path_psnr_db_per_class"] == {"road": 28.0, "building": 26.0,
                                                 "vegetation": 28.0, "terrain": 28.0}
    assert res["psnr_db_per_class"]["seen"] == cls(30.0)
    assert res["psnr_db_per_class"]["novel_1"] == cls(28.0)
    assert res["psnr_db_per_class"]["off_path"] == cls(27.0)
