"""render.lidar's binning bounds: a surfel's cone (the sines of its elevation range, its
azimuth range, its nearest distance) against points of its bounding sphere computed in plain
float64, poles and origins inside the sphere included; and the tiles' bucket order."""
from __future__ import annotations

import math

import numpy as np

from lsd3d_usd.render import lidar as L


def _sphere_points(c, r, rng, n=4000):
    """Points on and inside the sphere (c, r): the surface where the extremes are."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return c + r * d * np.concatenate([np.ones(n // 2), rng.uniform(0, 1, n - n // 2)])[:, None]


def test_cone_bounds_every_point_of_the_sphere():
    rng = np.random.default_rng(3)
    cases = [((5.0, 0.0, 0.0), 0.3, 0.0), ((0.1, 0.0, 4.0), 0.5, 0.2),     # near the zenith
             ((0.0, 0.2, -3.0), 0.4, 0.0), ((0.0, 0.0, 0.0), 0.1, 0.0),      # nadir; inside
             ((2.0, -1.0, 0.5), 0.05, 3.0), ((40.0, 30.0, -1.7), 0.36, 0.55)]  # grown by dm
    cases += [(tuple(rng.uniform(-20, 20, 3)), float(rng.uniform(0.01, 2.0)),
               float(rng.uniform(0, 1.0))) for _ in range(200)]
    for centre, rad, dm in cases:
        c = np.array([centre])
        near, lo, hi, az, w, every = L._cone(c, np.array([rad]), 0, np.zeros(3), dm)
        p = _sphere_points(c[0], rad + dm, rng)
        dist = np.linalg.norm(p, axis=1)
        ok = dist > 1e-9
        s = p[ok, 2] / dist[ok]                     # sine of each point's elevation
        assert np.all(dist >= near - 1e-12)
        assert np.all(s >= lo) and np.all(s <= hi), (centre, rad, dm)
        if not every:
            daz = np.arctan2(p[ok, 1], p[ok, 0]) - az
            daz = (daz + math.pi) % (2 * math.pi) - math.pi
            assert np.all(np.abs(daz) <= w + 1e-12), (centre, rad, dm)
        else:
            assert w >= math.pi


def test_cone_elevation_bounds_are_the_exact_sines():
    """Away from the poles the bounds are sin(el -+ h), h = asin(r / dist), as asin gives them."""
    c = np.array([[10.0, 3.0, 2.0]])
    near, lo, hi, az, w, every = L._cone(c, np.array([0.5]), 0, np.zeros(3), 0.0)
    dist = np.linalg.norm(c[0])
    el, h = math.asin(c[0, 2] / dist), math.asin(0.5 / dist)
    assert not every
    assert abs(lo - math.sin(el - h)) < 1e-11 and abs(hi - math.sin(el + h)) < 1e-11
    assert near == dist - 0.5


def test_bucket_tiles_orders_by_floors_of_the_keys():
    rng = np.random.default_rng(0)
    sizes = [0, 1, 2, 7, 300, 1000]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    m = int(offsets[-1])
    key = np.concatenate([rng.choice([0.0, 1e-3, 0.3, 0.5, 0.51, 40.0, 74.9, 2000.0], m // 4),
                          rng.uniform(0.0, 120.0, m - m // 4)])
    rng.shuffle(key)
    idx = np.arange(m, dtype=np.int64)
    orig = key.copy()
    L._bucket_tiles(offsets, idx, key)
    for t in range(len(sizes)):
        a, b = offsets[t], offsets[t + 1]
        assert sorted(idx[a:b]) == list(range(a, b))            # the same pairs, in place
        k, kept = key[a:b], orig[idx[a:b]]
        assert np.all(np.diff(k) >= 0) if b - a > 1 else True     # in order of the floors
        assert np.all(k <= kept)                                  # a floor: still a lower bound
        mid = (kept >= 0.5) & (kept < 1024.0)
        assert np.all(k[mid] >= kept[mid] / (1 + 1 / 32) - 1e-12)  # 1/32 of an octave below
        assert np.all(k[kept < 0.5] == 0.0) if b - a > 1 else True
        # ties (one bucket) keep the pairs' order
        for v in np.unique(k):
            run = idx[a:b][k == v]
            assert np.all(np.diff(run) > 0)
