"""bench scale's quality-against-extent measure: the same views in chunk 0_0, paired per view."""
import numpy as np

from lsd3d_usd.benchmarks.scale import paired, same_view_cameras


def test_same_view_cameras_are_fixed_and_inside_chunk_0_0():
    a, b = same_view_cameras(11, 12), same_view_cameras(11, 12)
    assert len(a) == 12
    for ca, cb in zip(a, b):   # the same positions in every configuration
        assert np.array_equal(ca.viewmat, cb.viewmat)
        # camera centre from the world-to-camera matrix
        R, t = np.asarray(ca.viewmat)[:3, :3], np.asarray(ca.viewmat)[:3, 3]
        x, y, _ = -R.T @ t
        assert -20 <= x <= 120 and -20 <= y <= 120, (x, y)


def _errs(psnrs, n=1000):
    """(sum of squared errors, values) of views of n values at the given PSNRs."""
    return [(n * 10 ** (-p / 10), n) for p in psnrs]


def test_paired_difference_and_its_interval():
    base = np.linspace(15, 30, 40)   # views differ a lot; their paired difference does not
    mean, (lo, hi) = paired(_errs(base - 0.3), _errs(base))
    assert abs(mean + 0.3) < 1e-3 and abs(lo + 0.3) < 1e-3 and abs(hi + 0.3) < 1e-3
    rng = np.random.default_rng(1)
    noisy = base + rng.normal(0, 1.0, base.size)
    mean, (lo, hi) = paired(_errs(noisy), _errs(base))
    assert lo < mean < hi and hi - lo < 1.5


def test_views_count_by_their_pixels():
    """A view with a sliver of the surface weighs as little as its pixels: its PSNR swinging
    by 10 dB hardly moves the pooled difference."""
    big = _errs([20.0] * 10, n=10_000)
    a = big + _errs([10.0], n=10)
    b = big + _errs([20.0], n=10)
    mean, _ = paired(a, b)
    assert -0.05 < mean < 0
    from lsd3d_usd.eval.seams_eval import pooled_psnr
    assert pooled_psnr(big + [(0.0, 0)]) == pooled_psnr(big)   # a view without pixels: nothing
    assert np.isnan(pooled_psnr([(0.0, 0)]))


def test_paired_over_seeds():
    """Several GGDS seeds: the mean of the per-seed differences, an interval that holds the
    seeds' spread (one seed alone is the per-view interval, draw for draw)."""
    from lsd3d_usd.benchmarks.scale import paired_seeds
    base = np.linspace(15, 30, 40)
    one = paired(_errs(base - 0.3), _errs(base))
    assert paired_seeds([(_errs(base - 0.3), _errs(base))]) == one
    pairs = [(_errs(base + d), _errs(base)) for d in (-1.0, 0.0, 1.0, 0.4)]
    mean, (lo, hi) = paired_seeds(pairs)
    assert abs(mean - 0.1) < 1e-3
    assert lo < -0.5 and hi > 0.5          # the spread between seeds, not 0 width


def _seam_stats(border_factor, views=6):
    """SeamStats of one-row views across the border x = 100 of chunks (0,0) and (1,0), the
    band's error ``border_factor`` × the interiors'."""
    from lsd3d_usd.eval.seams import SeamStats
    from lsd3d_usd.render.gbuffer import GBuffer
    st = SeamStats(100.0, {(0, 0), (1, 0)})
    xs = np.linspace(60.0, 140.0, 81)
    n = len(xs)
    gb = GBuffer(depth=np.full((1, n), 10.0, np.float32),
                 normal=np.tile(np.array([0, 0, 1], np.float32), (1, n, 1)),
                 semantic=np.ones((1, n), np.int32),
                 position=np.stack([xs, np.full(n, 50.0), np.zeros(n)], 1)[None],
                 face_index=np.zeros((1, n), np.int32))
    err = 1e-3 * np.where(np.abs(xs - 100) <= 5, border_factor, 1.0)
    target = np.full((1, n, 3), 0.5)
    for _ in range(views):
        st.add(target + np.sqrt(err)[None, :, None], target, np.ones((1, n)),
               np.full((1, n), 10.0), gb.normal, gb)
    return st


def test_seams_against_the_one_region_scene_pair_configs_by_name_and_seed():
    """bench scale pairs each chunk-wise 4-chunk scene with its one-region run of the same
    GGDS seed (run_config's names), and reports nothing for a pair it does not have."""
    from lsd3d_usd.benchmarks.scale import seams_vs_one_region
    stats = {"corridor4": _seam_stats(4.0), "corridor4_scene": _seam_stats(2.0),
             "grid4": _seam_stats(1.0), "grid4_scene": _seam_stats(1.0),
             "corridor4_s12": _seam_stats(3.0), "corridor4_scene_s12": _seam_stats(3.0),
             "grid4_s12": _seam_stats(2.0)}
    out = seams_vs_one_region(stats, 11, [11, 12])
    assert set(out) == {"11", "12"}
    assert abs(out["11"]["corridor4"]["difference_db"] - 10 * np.log10(2)) < 1e-3
    assert out["11"]["grid4"]["difference_db"] == 0.0
    assert out["12"]["corridor4"]["difference_db"] == 0.0
    assert out["12"]["grid4"]["difference_db"] is None     # no one-region run of seed 12
