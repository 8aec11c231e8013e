"""Training views placed off the lanes (conditioning/view_sampling.py) against eval's novel views."""

import numpy as np
import pytest


# ------------------------------------------------------------------ off-lane training views
def test_displaced_views_cover_eval_novel_positions_in_the_given_proportion():
    from lsd3d_usd.conditioning.view_sampling import sample_views
    from lsd3d_usd.layout.model import Building, LaneCenter, Layout
    lay = Layout(lanes=[LaneCenter(id="l0", points=[[0, 0, 0], [60, 0, 0]])],
                 buildings=[Building(id="b0", footprint=np.array(
                     [[10, 3], [50, 3], [50, 20], [10, 20], [10, 3]], float))])
    for frac in (0.0, 0.3, 1.0):
        views = sample_views(lay, 40, 32, 24, seed=1, novel_frac=frac, novel_style="displaced")
        novel = [v for v in views if v.kind == "novel"]
        assert len(novel) == round(40 * frac)
    views = sample_views(lay, 200, 32, 24, seed=2, novel_frac=1.0, novel_style="displaced",
                         novel_max_m=8.0)
    d = np.array([v.offset_m for v in views])
    assert d.min() >= 0.5 and d.max() <= 8.0 and np.median(d) < 3.0   # log-uniform: 2 m median
    c = np.array([v.camera.center for v in views])
    # within d of a lane view (|y| <= 3 sd of jitter, eye 1.6 m), never in the building
    assert np.all(np.abs(c[:, 1]) <= d + 1.5 + 1e-9)
    assert np.all((c[:, 2] >= 1.6 - 0.5 - 1e-9) & (c[:, 2] <= 1.6 + 0.25 * d + 1e-9))
    inside = (c[:, 0] > 10) & (c[:, 0] < 50) & (c[:, 1] > 3) & (c[:, 1] < 20)
    assert not inside.any()
    assert (c[:, 1] > 3).any()          # but they do leave the road beside it
    from lsd3d_usd.errors import InputError
    with pytest.raises(InputError, match="novel_style"):
        sample_views(lay, 3, 32, 24, novel_style="nope")
