"""GGDS's elevated views (conditioning.elevated_sampling): seeded, at the heights and pitches
asked, looking at lane points past no building, clipped to a chunk region, a share framing the
layout; they join a region's training views after the eye-height ones."""
from dataclasses import replace

import numpy as np
import pytest

from conftest import LAYOUT
from lsd3d_usd.conditioning.elevated_sampling import ELEVATED, Obstacles, sample_elevated_views
from lsd3d_usd.conditioning.view_sampling import inside_paths
from lsd3d_usd.layout.usdio import read_layout
from test_eval_elevated import _pitch


@pytest.fixture(scope="module")
def layout():
    return read_layout(LAYOUT)


def _aim(v):
    """Where the optical axis meets the plane of the lane point the view looks at."""
    c, f = v.camera.center, v.camera.pose[:3, 2]
    z = c[2] - v.offset_m
    return c + f * (z - c[2]) / f[2]


def test_views_over_lanes_heights_pitch_and_clear_sight(layout):
    views = sample_elevated_views(layout, 24, 64, 36, seed=3, heights=(4.0, 40.0),
                                  pitch_deg=(25.0, 70.0))
    assert len(views) == 24 and all(v.kind == ELEVATED for v in views)
    obstacles = Obstacles(layout)
    lanes = {ln.id: ln for ln in layout.drivable_lanes()}
    for v in views:
        assert 4.0 - 1e-9 <= v.offset_m <= 40.0 + 1e-9
        assert 25.0 - 1e-6 <= _pitch(v.camera) <= 70.0 + 1e-6
        aim = _aim(v)
        # the point looked at lies on the lane the view names (within its sampling step)
        pts = lanes[v.lane_id].points
        seg_d = min(np.linalg.norm(pts[:, :2] - aim[:2], axis=1))
        assert seg_d < np.max(np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)) + 1e-6
        assert obstacles.clear(v.camera.center, aim)
        assert not inside_paths(v.camera.center, obstacles.paths)
    # heights spread over the range (log-uniform): some low, some high
    h = np.array([v.offset_m for v in views])
    assert h.min() < 10.0 and h.max() > 20.0


def test_seeded(layout):
    def poses(seed):
        return np.stack([v.camera.pose for v in
                         sample_elevated_views(layout, 8, 64, 36, seed=seed, overview_frac=0.25)])
    np.testing.assert_array_equal(poses(1), poses(1))
    assert not np.allclose(poses(1), poses(2))


def test_a_share_frames_the_layout_and_none_in_a_chunk_region(layout):
    views = sample_elevated_views(layout, 16, 64, 36, seed=0, overview_frac=0.25)
    frame = [v for v in views if v.lane_id == ""]
    assert len(frame) == 4
    (x0, y0), (x1, y1) = layout.bounds()
    diag = np.hypot(x1 - x0, y1 - y0)
    for v in frame:     # far above, looking at the middle of the layout
        c = v.camera.center
        assert c[2] > 0.25 * diag
        aim = _aim(v)
        assert abs(aim[0] - (x0 + x1) / 2) <= 0.25 * (x1 - x0) + 1e-6
        assert abs(aim[1] - (y0 + y1) / 2) <= 0.25 * (y1 - y0) + 1e-6
    box = (0.0, 0.0, 40.0, 40.0)
    clipped = sample_elevated_views(layout, 12, 64, 36, seed=0, overview_frac=0.25, region=box,
                                    clip=True)
    assert len(clipped) == 12 and all(v.lane_id for v in clipped)
    for v in clipped:
        x, y = _aim(v)[:2]
        assert -0.6 <= x <= 40.6 and -0.6 <= y <= 40.6


def test_with_elevated_train_they_join_the_training_views_held_out_views_stay_at_eye_height(
        layout):
    from lsd3d_usd.ggds.regions.plan import Region
    from lsd3d_usd.ggds.regions.region_views import region_views
    from lsd3d_usd.ggds.settings import GGDSConfig
    g = GGDSConfig(resolution=(48, 32), views=32, elevated_train=True, elevated_frac=0.125)
    whole = Region(((0, 0),), "")
    views, held = region_views(layout, g, 0, whole)
    kinds = [v.kind for v in views]
    assert kinds.count(ELEVATED) == 4 and len(views) == 36        # 32 + 0.125 x 32
    assert ELEVATED not in {v.kind for v in held}
    none, _ = region_views(layout, replace(g, elevated_frac=0.0), 0, whole)
    assert [v.camera.pose.tolist() for v in none] == [v.camera.pose.tolist() for v in views[:32]]


def test_without_elevated_train_the_colour_start_fits_to_the_same_views(layout):
    from lsd3d_usd.ggds.regions.plan import Region
    from lsd3d_usd.ggds.regions.region_views import region_fit_views, region_views
    from lsd3d_usd.ggds.settings import GGDSConfig
    g = GGDSConfig(resolution=(48, 32), views=32, world_init_views=0.5, elevated_train=True,
                   elevated_frac=0.125)
    whole = Region(((0, 0),), "")
    trained, _ = region_views(layout, g, 0, whole)
    fit_only = replace(g, elevated_train=False)
    assert GGDSConfig().elevated_train is False              # the default
    views, _ = region_views(layout, fit_only, 0, whole)
    assert [v.kind for v in views].count(ELEVATED) == 0 and len(views) == 32
    fits = [v for v in region_fit_views(layout, fit_only, 0, whole) if v.kind == ELEVATED]
    # the 4 views it would have trained on, then 0.5 x 0.125 x 32 = 2 more for the fit
    assert len(fits) == 6
    assert [v.camera.pose.tolist() for v in fits[:4]] == \
        [v.camera.pose.tolist() for v in trained if v.kind == ELEVATED]
    assert [v.camera.pose.tolist() for v in fits[4:]] == \
        [v.camera.pose.tolist() for v in region_fit_views(layout, g, 0, whole)
         if v.kind == ELEVATED]


def test_heights_the_wrong_way_round_are_one_error_naming_the_key():
    from lsd3d_usd.config import generate_config
    from lsd3d_usd.errors import InputError
    from lsd3d_usd.pipeline import check_config
    cfg = generate_config(layout=LAYOUT, ggds={"elevated_heights": (40.0, 4.0)})
    with pytest.raises(InputError, match=r"ggds\.elevated_heights 40x4"):
        check_config(cfg)


def test_a_region_with_no_lane_inside_is_an_input_error(layout):
    from lsd3d_usd.errors import InputError
    with pytest.raises(InputError, match="lane"):
        sample_elevated_views(layout, 4, 64, 36, seed=0, region=(5000.0, 5000.0, 5010.0, 5010.0),
                              clip=True)
