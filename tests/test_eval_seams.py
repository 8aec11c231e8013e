"""The seam measure: border bands against interiors, raw and class-matched."""
import math

import numpy as np
import pytest

from lsd3d_usd.eval.seams import SeamStats, border_distance
from lsd3d_usd.render.gbuffer import GBuffer

KEYS = {(0, 0), (1, 0)}          # two chunks of 100 m side by side: one border at x = 100


def test_border_distance_only_between_chunks_that_hold_surfels():
    pts = np.array([[97.0, 50, 0], [104.0, 20, 0], [50.0, 99, 0], [150.0, 1, 0], [250.0, 50, 0]])
    d = border_distance(pts, 100.0, KEYS)
    # x = 100 separates (0,0) and (1,0); y = 0, y = 100 and x = 200 border empty chunks
    np.testing.assert_allclose(d, [3.0, 4.0, 50.0, 50.0, np.inf])


def test_a_border_runs_only_where_both_chunks_hold_surfels_along_it():
    # chunk (0,1) holds only a building overhanging y = 100 at x in [40, 45]
    keys = {(0, 0), (0, 1)}
    bounds = {(0, 0): (0.0, 0.0, 100.0, 100.0), (0, 1): (40.0, 100.0, 45.0, 101.0)}
    pts = np.array([[42.0, 98, 0], [48.0, 97, 0], [51.0, 97, 0], [80.0, 99, 0], [42.0, 100.5, 0]])
    np.testing.assert_allclose(border_distance(pts, 100.0, keys), [2, 3, 3, 1, 0.5])
    np.testing.assert_allclose(border_distance(pts, 100.0, keys, bounds, reach=5.0),
                               [2, 3, np.inf, np.inf, 0.5])
    assert np.isinf(border_distance(pts, 100.0, set())).all()


def _view(xs, classes, rng, depth=None):
    """A one-row 'view' whose pixels lie on the ground at x = xs with the given classes."""
    n = len(xs)
    pos = np.stack([xs, np.full(n, 50.0), np.zeros(n)], 1)[None]
    depth = np.full(n, 10.0) if depth is None else depth
    return GBuffer(depth=np.asarray(depth, np.float32)[None],
                   normal=np.tile(np.array([0, 0, 1], np.float32), (1, n, 1)),
                   semantic=np.asarray(classes, np.int32)[None], position=pos,
                   face_index=np.zeros((1, n), np.int32))


def _add(stats, gb, err_of):
    """Render = target + a per-pixel error whose squared mean per channel is err_of(pixel)."""
    n = gb.depth.shape[1]
    target = np.full((1, n, 3), 0.5)
    e = np.array([math.sqrt(err_of(gb.position[0, k, 0], gb.semantic[0, k])) for k in range(n)])
    rgb = target + e[None, :, None]
    stats.add(rgb, target, np.ones((1, n)), np.full((1, n), 10.0), gb.normal, gb)


def test_class_mix_alone_is_no_seam_but_a_worse_border_is():
    rng = np.random.default_rng(0)
    # border band (|x - 100| <= 5) is all class 3; interiors mostly class 1, some class 3
    xs = np.concatenate([rng.uniform(95, 105, 400), rng.uniform(10, 90, 800), rng.uniform(110, 190, 800)])
    cls = np.where(np.abs(xs - 100) <= 5, 3, np.where(rng.random(len(xs)) < 0.25, 3, 1))
    gb = _view(xs, cls, rng)
    by_class = {1: 1e-4, 3: 1e-2}                                     # class 3 fits 20 dB worse

    no_seam = SeamStats(100.0, KEYS)
    _add(no_seam, gb, lambda x, c: by_class[int(c)])
    r = no_seam.result()
    assert r["psnr_drop_db"] > 5                       # the raw drop is the class mix
    assert abs(r["psnr_drop_class_matched_db"]) < 1e-6
    assert r["classes"][next(iter(r["classes"]))]["border"]["pixels"] >= 0

    seam = SeamStats(100.0, KEYS)                      # the same, with the border 2x worse
    _add(seam, gb, lambda x, c: by_class[int(c)] * (2.0 if abs(x - 100) <= 5 else 1.0))
    assert seam.result()["psnr_drop_class_matched_db"] == pytest.approx(10 * math.log10(2), abs=1e-3)


def test_no_border_pixels_gives_no_drop():
    rng = np.random.default_rng(1)
    gb = _view(rng.uniform(10, 90, 100), np.ones(100, int), rng)
    st = SeamStats(100.0, KEYS)
    _add(st, gb, lambda x, c: 1e-3)
    r = st.result()
    assert r["border"]["psnr_db"] is None and r["psnr_drop_db"] is None
    assert r["psnr_drop_class_matched_db"] is None
    assert r["interior"]["psnr_db"] == pytest.approx(30.0, abs=1e-3)


def test_distance_alone_is_no_seam_once_matched():
    rng = np.random.default_rng(2)
    # one class; the border band is seen from far away, the interiors near, and error grows
    # with distance: the class-matched drop shows it, the class-and-depth-matched does not
    xs = np.concatenate([rng.uniform(95, 105, 400), rng.uniform(10, 90, 1600)])
    far = np.abs(xs - 100) <= 5
    depth = np.where(far, np.where(rng.random(len(xs)) < 0.8, 60.0, 8.0),
                     np.where(rng.random(len(xs)) < 0.2, 60.0, 8.0))
    gb = _view(xs, np.ones(len(xs), int), rng, depth)
    by_depth = {8.0: 1e-4, 60.0: 1e-2}
    st = SeamStats(100.0, KEYS)
    n = len(xs)
    target = np.full((1, n, 3), 0.5)
    e = np.sqrt([by_depth[float(d)] for d in depth])
    st.add(target + e[None, :, None], target, np.ones((1, n)), depth[None], gb.normal, gb)
    r = st.result()
    assert r["psnr_drop_class_matched_db"] > 3
    assert abs(r["psnr_drop_matched_db"]) < 1e-6 and r["matched_border_frac"] == 1.0

    seam = SeamStats(100.0, KEYS)                      # the same, with the border 2x worse
    e2 = e * np.where(far, math.sqrt(2.0), 1.0)
    seam.add(target + e2[None, :, None], target, np.ones((1, n)), depth[None], gb.normal, gb)
    assert seam.result()["psnr_drop_matched_db"] == pytest.approx(10 * math.log10(2), abs=1e-3)


def _seam_views(factors, rng):
    """One view per factor: its border band's error is ``factor`` × the interiors'."""
    st = SeamStats(100.0, KEYS)
    for f in factors:
        xs = np.concatenate([rng.uniform(95, 105, 100), rng.uniform(10, 90, 300)])
        gb = _view(xs, np.ones(len(xs), int), rng)
        _add(st, gb, lambda x, c: 1e-3 * (f if abs(x - 100) <= 5 else 1.0))
    return st.result()


def test_the_interval_over_views_is_tight_for_a_steady_seam_and_wide_for_one_bad_view():
    rng = np.random.default_rng(3)
    steady = _seam_views([2.0] * 20, rng)
    lo, hi = steady["psnr_drop_matched_ci95_db"]
    assert lo <= steady["psnr_drop_matched_db"] <= hi
    assert lo == pytest.approx(10 * math.log10(2), abs=0.05) and hi - lo < 0.1

    one_view = _seam_views([1.0] * 19 + [20.0], rng)
    lo, hi = one_view["psnr_drop_matched_ci95_db"]
    assert one_view["psnr_drop_matched_db"] > 2.5     # the point figure alone looks like a seam
    assert lo < 1.0 < 4 < hi                          # the interval says it rests on one view
    assert _seam_views([2.0], rng)["psnr_drop_matched_ci95_db"] is None


def _stats(view_errs, xs_per_view, cls_per_view):
    """SeamStats over views whose pixel errors are view_errs[v](x, class)."""
    st = SeamStats(100.0, KEYS)
    for err_of, xs, cls in zip(view_errs, xs_per_view, cls_per_view):
        _add(st, _view(xs, cls, None), err_of)
    return st


def _plain_matched_drop(views):
    """float64, loop by loop: interior MSE per class at the border's class mix over all views,
    against the border's MSE (one depth bin here), in dB."""
    b_sq, b_n, i_sq, i_n = {}, {}, {}, {}
    for err_of, xs, cls in views:
        for x, c in zip(xs, cls):
            e = err_of(x, c)
            sq, nn = (b_sq, b_n) if abs(x - 100) <= 5 else (i_sq, i_n)
            sq[c] = sq.get(c, 0.0) + e
            nn[c] = nn.get(c, 0) + 1
    common = [c for c in b_n if c in i_n]
    nb = sum(b_n[c] for c in common)
    mse_b = sum(b_sq[c] for c in common) / nb
    mse_i = sum(b_n[c] / nb * i_sq[c] / i_n[c] for c in common)
    return 10 * math.log10(mse_b / mse_i)


def test_paired_drop_removes_what_the_layout_puts_in_its_border_bands():
    from lsd3d_usd.eval.seams import paired_matched_drop
    rng = np.random.default_rng(7)
    xs = [np.concatenate([rng.uniform(95, 105, 80), rng.uniform(10, 90, 200)]) for _ in range(24)]
    cls = [np.where(rng.random(len(x)) < 0.3, 3, 1) for x in xs]
    hard = [float(rng.uniform(1.5, 4.0)) for _ in xs]      # the band's content: hard per view

    def reference_err(h):
        return lambda x, c: (1e-3 if c == 1 else 3e-3) * (h if abs(x - 100) <= 5 else 1.0)

    def chunked_err(h):         # the same content, and the chunk border twice as bad again
        return lambda x, c: reference_err(h)(x, c) * (2.0 if abs(x - 100) <= 5 else 1.0)
    ref = _stats([reference_err(h) for h in hard], xs, cls)
    scene = _stats([chunked_err(h) for h in hard], xs, cls)
    out = paired_matched_drop(scene, ref)
    assert out["reference_db"] > 1.5                     # the content alone reads as a "seam"
    assert out["views"] == 24
    # the difference is the chunking's own factor 2, against a plain float64 computation
    plain = (_plain_matched_drop(zip([chunked_err(h) for h in hard], xs, cls))
             - _plain_matched_drop(zip([reference_err(h) for h in hard], xs, cls)))
    assert out["difference_db"] == pytest.approx(plain, abs=2e-3)
    assert out["difference_db"] == pytest.approx(10 * math.log10(2), abs=2e-3)
    lo, hi = out["ci95_db"]                # every view has the same factor: a tight interval
    assert lo <= out["difference_db"] <= hi and hi - lo < 0.05
    same = paired_matched_drop(ref, ref)
    assert same["difference_db"] == 0.0 and same["ci95_db"] == [0.0, 0.0]


def test_paired_drop_needs_the_same_views():
    from lsd3d_usd.eval.seams import paired_matched_drop
    rng = np.random.default_rng(8)
    xs = [np.concatenate([rng.uniform(95, 105, 20), rng.uniform(10, 90, 40)]) for _ in range(3)]
    cls = [np.ones(len(x), int) for x in xs]
    flat = [lambda x, c: 1e-3] * 3
    with pytest.raises(ValueError, match="3 views against 2"):
        paired_matched_drop(_stats(flat, xs, cls), _stats(flat[:2], xs[:2], cls[:2]))


def test_paired_drop_counts_each_scene_over_its_own_cells():
    """Cells only one scene holds (another class in its border band) stay in that scene's
    drop: the difference is the two matched drops' difference."""
    from lsd3d_usd.eval.seams import paired_matched_drop
    rng = np.random.default_rng(9)
    xs = [np.concatenate([rng.uniform(95, 105, 40), rng.uniform(10, 90, 80)]) for _ in range(5)]
    ones = [np.ones(len(x), int) for x in xs]
    mixed = [np.where(rng.random(len(x)) < 0.5, 3, 1) for x in xs]
    scene = _stats([lambda x, c: 1e-3 * (2.0 if abs(x - 100) <= 5 else 1.0)] * 5, xs, ones)
    ref = _stats([lambda x, c: (1e-3 if c == 1 else 4e-3) * (3.0 if abs(x - 100) <= 5 and c == 3
                                                            else 1.0)] * 5, xs, mixed)
    out = paired_matched_drop(scene, ref)
    assert out["reference_db"] > 0.5
    assert out["difference_db"] == pytest.approx(out["scene_db"] - out["reference_db"], abs=2e-3)
