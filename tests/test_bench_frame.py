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
    assert 0.0 <= r["hidden_fraction"] <= 1.0


def test_hidden_fraction_counts_the_surfels_behind_an_opaque_wall():
    """Two parallel walls of opaque surfels facing the camera, 10 m and 20 m away: the far
    wall's surfels are all hidden, the near wall's none (a plain count to compare with)."""
    import numpy as np
    from lsd3d_usd.benchmarks.frame import hidden_fraction
    from lsd3d_usd.render.camera import Camera, look_at
    from lsd3d_usd.splats.field import SurfelField, rgb_to_sh_dc
    g = np.stack(np.meshgrid(np.arange(-30, 31) * 0.5, np.arange(-20, 21) * 0.5), -1).reshape(-1, 2)
    walls = [np.c_[g[:, 0], np.full(len(g), y), g[:, 1]] for y in (10.0, 20.0)]
    pos = np.concatenate(walls)
    # disks in the x-z plane (normal along y): quaternion of +90 degrees about x
    q = np.tile([np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)], (len(pos), 1))
    n = len(pos)
    f = SurfelField(pos, q, np.full((n, 2), 0.5), np.full(n, 0.99),
                    rgb_to_sh_dc(np.full((n, 3), 0.5))[:, None, :])
    cam = Camera.from_fov(160, 90, 60.0, look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
                          near=0.1, far=100.0)
    far = pos[:, 1] == 20.0
    uv, _ = cam.project(pos)
    u, v = uv[:, 0], uv[:, 1]
    # far surfels whose centre lands where the near wall (which covers the whole view) is
    on = far & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    assert on.sum() > 100
    got = hidden_fraction(f, cam)
    assert abs(got - on.sum() / n) < 0.02 * on.sum() / n, (got, on.sum() / n)
    assert hidden_fraction(SurfelField(pos[~far], q[~far], f.scales[~far], f.opacities[~far],
                                       f.sh[~far]), cam) == 0.0
