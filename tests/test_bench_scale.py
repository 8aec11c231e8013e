"""bench scale's quality-against-extent measure: the same views in chunk 0_0, paired per view."""
import numpy as np

from lsd3d_usd.benchmarks.scale import _paired, same_view_cameras


def test_same_view_cameras_are_fixed_and_inside_chunk_0_0():
    a, b = same_view_cameras(11, 12), same_view_cameras(11, 12)
    assert len(a) == 12
    for ca, cb in zip(a, b):   # the same positions in every configuration
        assert np.array_equal(ca.viewmat, cb.viewmat)
        # camera centre from the world-to-camera matrix
        R, t = np.asarray(ca.viewmat)[:3, :3], np.asarray(ca.viewmat)[:3, 3]
        x, y, _ = -R.T @ t
        assert -20 <= x <= 120 and -20 <= y <= 120, (x, y)


def test_paired_difference_and_its_interval():
    base = np.linspace(15, 30, 40)   # views differ a lot; their paired difference does not
    mean, (lo, hi) = _paired(list(base - 0.3), list(base))
    assert mean == -0.3 and lo == hi == -0.3
    rng = np.random.default_rng(1)
    noisy = base + rng.normal(0, 1.0, base.size)
    mean, (lo, hi) = _paired(list(noisy), list(base))
    assert lo < mean < hi and hi - lo < 1.0   # ±1 dB per view: ≈ ±0.3 dB over 40 views


def test_paired_difference_skips_views_missing_on_either_side():
    mean, (lo, hi) = _paired([20.0, None, 22.0, 25.0], [19.0, 18.0, float("nan"), 24.0])
    assert mean == 1.0 and lo == hi == 1.0
