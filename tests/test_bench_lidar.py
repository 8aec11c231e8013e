"""bench lidar --quick: the JSON keys the issue names, and accuracy figures that hold on a scene
whose surfels lie on the proxy (steps 0): the LiDAR meets the proxy's surfaces, agrees with the
float64 reference and with a pinhole camera at its pose."""
import json

import pytest

from lsd3d_usd.benchmarks.lidar import main


@pytest.mark.slow
def test_bench_lidar_quick_reports_speed_and_accuracy(tmp_path):
    out = tmp_path / "lidar.json"
    res = main(out, quick=True, log=lambda *a: None)
    data = json.loads(out.read_text())
    assert data == json.loads(json.dumps(res))
    for key in ("rays", "s_per_sweep", "camera_s", "sweep_over_camera", "memory_mb_beyond_scene",
                "vs_reference_max_m", "vs_camera_within_1pct", "vs_camera_smooth_within_1pct"):
        assert key in data, key
    assert data["rays"] == 64 * 2650
    assert data["s_per_sweep"] > 0 and data["camera_s"] > 0
    assert data["vs_reference_same_returns"] and data["vs_reference_max_m"] <= 1e-3
    # steps 0: surfels lie on the proxy, so same-class returns sit on its faces
    for c in ("road", "sidewalk", "building"):
        assert data[f"range_err_{c}_same_class_points"] > 100, c
        assert data[f"range_err_{c}_same_class_median_m"] < 0.02, c
    assert data["vs_camera_rel_median"] < 0.01
    assert data["vs_camera_smooth_within_1pct"] > 0.9
