"""`bench frame`'s measurement on a small scene: every key, level of detail drawing fewer
surfels than full detail and close to it in PSNR."""
from lsd3d_usd.benchmarks.frame import frames


def test_frames_report_times_counts_and_psnr(sim_scene):
    r = frames(sim_scene, poses=1, repeats=1, lod_px=4.0, log=lambda *a: None)
    for k in ("frame_480x270_s", "frame_480x270_s_no_lod", "frame_960x540_s",
              "frame_960x540_s_no_lod"):
        assert r[k] > 0
    assert 0 < r["drawn_surfels"] <= r["drawn_surfels_no_lod"]
    assert r["lod_psnr_db"] >= 35.0 and r["lod_psnr_db_median"] >= r["lod_psnr_db"]
    assert r["lod_psnr_db_overview"] >= 30.0
    assert r["lod_psnr_db_lane_views"] is None or r["lod_psnr_db_lane_views"] >= 35.0
    assert "lod_psnr_db_overview_cameras" in r
