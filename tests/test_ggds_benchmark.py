"""`bench ggds` quality run: the issue's JSON keys, finite and in range, from a real (tiny)
generate on the README sample."""
import math

from lsd3d_usd.benchmarks.ggds import SAMPLES, quality


def test_quality_run_reports_the_issue_keys(tmp_path):
    res = quality(SAMPLES / "hand_crossing.usda", steps=2, surfels=2000, resolution=(64, 36),
                  out=tmp_path / "scene", log=lambda *a: None)
    assert res["steps"] == 2 and res["surfels"] == 2000
    for key in ("s_per_step", "psnr_novel", "depth_rel_err", "normal_err_deg", "off_surface_frac"):
        assert math.isfinite(res[key]), key
    assert 5.0 < res["psnr_novel"] < 60.0
    assert 0.0 <= res["off_surface_frac"] <= 1.0 and res["normal_err_deg"] >= 0.0
    assert (tmp_path / "scene" / "scene.usda").is_file()
