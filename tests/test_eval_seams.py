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


def _view(xs, classes, rng):
    """A one-row 'view' whose pixels lie on the ground at x = xs with the given classes."""
    n = len(xs)
    pos = np.stack([xs, np.full(n, 50.0), np.zeros(n)], 1)[None]
    return GBuffer(depth=np.full((1, n), 10.0, np.float32),
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
