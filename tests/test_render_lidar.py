"""render.lidar: the LiDAR kernel against its float64 per-ray reference and against geometry
with a known answer (a plane), rolling shutter, degenerate surfels and rays, and the model's
checks."""
from __future__ import annotations

import numpy as np
import pytest

from lsd3d_usd.errors import InputError
from lsd3d_usd.render import lidar as L
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.views.lidar_sweep import sweep
from lsd3d_usd.sensors.lidar import LidarModel, model_from_table, presets

PRESETS = presets()


def _random_surfels(n, seed=0, extent=12.0):
    rng = np.random.default_rng(seed)
    means = rng.uniform(-extent, extent, (n, 3))
    means[:, 2] = rng.uniform(-2.0, 4.0, n)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return L.surfel_frames(means, q, rng.uniform(0.02, 0.5, (n, 2)), rng.uniform(0.05, 1.0, n))


def _plane(extent=40.0, spacing=0.25, z=0.0, opacity=0.9):
    g = np.arange(-extent, extent + 1e-9, spacing)
    x, y = np.meshgrid(g, g)
    n = x.size
    pos = np.stack([x.ravel(), y.ravel(), np.full(n, z)], 1)
    return SurfelField(positions=pos, orientations=np.tile([0, 0, 0, 1.0], (n, 1)),
                       scales=np.full((n, 2), spacing * 1.2), opacities=np.full(n, opacity),
                       sh=np.zeros((n, 1, 3)), semantic_ids=np.zeros(n, np.int32),
                       semantic_classes=("road",))


def _assert_same(t, k, tr, kr, tol=1e-9):
    assert np.array_equal(np.isfinite(t), np.isfinite(tr))
    both = np.isfinite(t)
    assert both.sum() > 100
    assert np.max(np.abs(t[both] - tr[both])) <= tol
    assert np.mean(k[both] == kr[both]) > 0.999     # the same surfel (ties at equal t aside)


def test_kernel_matches_float64_reference_on_20k_surfels():
    surf = _random_surfels(20_000)
    model = PRESETS["waymo_top"]
    d = model.directions()[:, 400:416]                 # a block of the sweep, every ring
    o = np.zeros((d.shape[1], 3))
    o[:, 0] = np.linspace(0.0, 0.3, d.shape[1])        # the origin moving along the block
    t, k, stats = L.cast_surfels(surf, o, d, min_range=0.5, max_range=30.0)
    tr, kr = L.cast_reference(surf, o, d, min_range=0.5, max_range=30.0)
    _assert_same(t, k, tr, kr, tol=1e-3)               # the bound: 1 mm ...
    _assert_same(t, k, tr, kr, tol=1e-9)               # ... and in fact float64 round-off
    assert stats["pairs"] > 0


def test_rays_in_any_order_are_exact():
    """Rays not in sweep order (here a random draw of the sweep's directions) take the
    kernel's unordered path and still give the reference's returns."""
    surf = _random_surfels(5_000, seed=2)
    d_all = PRESETS["hdl32"].directions().reshape(-1, 3)
    pick = np.random.default_rng(3).choice(len(d_all), 600, replace=False)
    d = d_all[pick][None]
    o = np.zeros((d.shape[1], 3))
    t, k, _ = L.cast_surfels(surf, o, d, min_range=0.3, max_range=30.0)
    tr, kr = L.cast_reference(surf, o, d, min_range=0.3, max_range=30.0)
    _assert_same(t, k, tr, kr)


def test_plane_ranges_are_analytic():
    f = _plane()
    surf = L.surfel_frames(f.positions, f.orientations, f.scales, f.opacities)
    model = PRESETS["hdl32"]
    h = 1.8
    d = model.directions()
    o = np.tile([0.3, -0.2, h], (d.shape[1], 1))
    t, _, _ = L.cast_surfels(surf, o, d, min_range=model.min_range, max_range=model.max_range)
    down = d[..., 2] < 0
    expect = np.where(down, h / np.where(down, -d[..., 2], 1.0), np.inf)
    expect[expect > model.max_range] = np.inf
    np.testing.assert_array_equal(np.isfinite(t), np.isfinite(expect))
    hit = np.isfinite(t)
    assert hit.sum() > 10_000
    # float32 surfel centres (the ParticleField's type) on z = 0 exactly: the plane's range
    assert np.max(np.abs(t[hit] - expect[hit])) < 1e-9


class _Reader:
    """The surfels a sweep asks a stage_data.SceneReader for."""

    def __init__(self, field_):
        self.field_ = field_

    def surfels(self, time=None, near=None):
        return self.field_


def _ego(v):
    def world_from_ego(times):
        M = np.tile(np.eye(4), (len(np.atleast_1d(times)), 1, 1))
        M[:, 0, 3] = v * np.atleast_1d(times)
        return M
    return world_from_ego


def test_rolling_shutter_differs_from_static_by_the_ego_motion_per_column():
    from lsd3d_usd.views.labels import Instances
    f = _plane()
    model = PRESETS["hdl32"]
    v = 15.0                                            # m/s along x
    inst = Instances.of(None)
    static = sweep(_Reader(f), model, _ego(0.0), 0.0, 24.0, inst)
    moving = sweep(_Reader(f), model, _ego(v), 0.0, 24.0, inst)
    a = {(r, c): i for i, (r, c) in enumerate(zip(static.ring, static.column))}
    pairs = np.array([(a[(r, c)], j) for j, (r, c) in enumerate(zip(moving.ring, moving.column))
                      if (r, c) in a])
    assert len(pairs) > 0.99 * len(static.range) > 10_000
    s, m = pairs[:, 0], pairs[:, 1]
    shift = moving.xyz_world[m] - static.xyz_world[s]
    expect = np.zeros_like(shift)
    expect[:, 0] = v * model.column_times()[moving.column[m]]
    np.testing.assert_allclose(shift, expect, atol=1e-6)
    np.testing.assert_allclose(moving.origin_world[m] - static.origin_world[s], expect, atol=1e-9)
    # the sensor frame is the one at the sweep's start: the same shift there
    np.testing.assert_allclose(moving.xyz[m] - static.xyz[s], expect, atol=1e-4)
    np.testing.assert_allclose(moving.range[m], static.range[s], atol=1e-5)
    # the last column fires one sweep (1/20 s) after the first: the clouds differ by ~v/20
    assert np.ptp(shift[:, 0]) == pytest.approx(v * model.sweep_seconds, rel=0.01)


def test_transmittance_rule_and_degenerate_surfels():
    """One opaque-enough surfel stops a ray; a stack of faint ones returns where their
    transmittance first falls below 0.5; edge-on, zero-opacity, zero-scale and non-finite
    surfels return nothing (and do not disturb the rest)."""
    d = np.array([[[1.0, 0.0, 0.0]]])
    o = np.zeros((1, 3))
    q_face_x = [0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)]   # normal along x
    xs = np.array([5.0, 6.0, 7.0, 8.0])
    # alphas 0.3 each: T = 0.7, 0.49 -> the second surfel is the return
    surf = L.surfel_frames(np.c_[xs, np.zeros(4), np.zeros(4)], np.tile(q_face_x, (4, 1)),
                           np.full((4, 2), 0.5), np.full(4, 0.3))
    t, k, _ = L.cast_surfels(surf, o, d, min_range=0.1, max_range=50.0)
    assert t[0, 0] == pytest.approx(6.0) and k[0, 0] == 1
    # below 0.5 only after all four? alphas 0.15: T = .85, .72, .61, .52 -> no return
    faint = L.surfel_frames(np.c_[xs, np.zeros(4), np.zeros(4)], np.tile(q_face_x, (4, 1)),
                            np.full((4, 2), 0.5), np.full(4, 0.15))
    t, k, _ = L.cast_surfels(faint, o, d, min_range=0.1, max_range=50.0)
    assert not np.isfinite(t[0, 0]) and k[0, 0] == -1
    # degenerate ones in front of a good one
    pos = np.array([[2.0, 0, 0], [3.0, 0, 0], [4.0, 0, 0], [4.5, 0, 0], [9.0, 0, 0]])
    quats = np.array([[0, 0, 0, 1.0], q_face_x, q_face_x, q_face_x, q_face_x])  # 1st edge-on
    scales = np.array([[0.5, 0.5], [0.5, 0.5], [0.0, 0.0], [0.5, 0.5], [0.5, 0.5]])
    opac = np.array([0.9, 0.0, 0.9, np.nan, 0.9])
    surf = L.surfel_frames(pos, quats, scales, opac)
    t, k, _ = L.cast_surfels(surf, o, d, min_range=0.1, max_range=50.0)
    tr, kr = L.cast_reference(surf, o, d, min_range=0.1, max_range=50.0)
    assert t[0, 0] == pytest.approx(9.0) and k[0, 0] == 4
    assert tr[0, 0] == pytest.approx(9.0) and kr[0, 0] == 4
    # nothing at all, and a surfel around the origin itself
    empty = L.surfel_frames(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 2)), np.zeros(0))
    t, k, _ = L.cast_surfels(empty, o, d, min_range=0.1, max_range=50.0)
    assert not np.isfinite(t).any() and (k == -1).all()
    around = L.surfel_frames([[0.5, 0, 0]], [q_face_x], [[2.0, 2.0]], [0.95])
    t, k, _ = L.cast_surfels(around, o, d, min_range=0.1, max_range=50.0)
    assert t[0, 0] == pytest.approx(0.5)
    t, k, _ = L.cast_surfels(around, o, d, min_range=0.6, max_range=50.0)
    assert not np.isfinite(t[0, 0])                    # nearer than min_range: no return


def test_beams_straight_up_and_down():
    """Elevations near ±90° (every azimuth at once) against surfels around the sensor."""
    surf = _random_surfels(3000, seed=7, extent=4.0)
    model = LidarModel("poles", (-89.9, -60.0, 0.0, 60.0, 89.9), 64).check()
    d = model.directions()
    o = np.zeros((d.shape[1], 3))
    t, k, _ = L.cast_surfels(surf, o, d, min_range=0.1, max_range=20.0)
    tr, kr = L.cast_reference(surf, o, d, min_range=0.1, max_range=20.0)
    _assert_same(t, k, tr, kr)


def test_sweep_directions_and_times():
    m = PRESETS["waymo_top"]
    d = m.directions()
    assert d.shape == (64, 2650, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    el = np.degrees(np.arcsin(d[:, 0, 2]))
    np.testing.assert_allclose(el[[0, -1]], [-17.6, 2.4], atol=1e-9)     # ring 0 lowest
    az = m.azimuths_deg()
    assert az[0] == pytest.approx(180.0 - 360.0 / 2650 / 2)               # starts behind
    assert np.all(np.diff(az) < 0)                                         # clockwise
    ct = m.column_times()
    assert ct[0] > 0 and ct[-1] < 0.1 and np.all(np.diff(ct) > 0)


@pytest.mark.parametrize("table,key", [
    ({"beams": 0, "elevation_min": -10, "elevation_max": 10, "columns": 100}, "beams"),
    ({"beams": 8, "elevation_min": -95, "elevation_max": 10, "columns": 100}, "elevation_min"),   # the key as given (issue 60)
    ({"elevations": [-10.0, 90.0], "columns": 100}, "elevations"),
    ({"beams": 8, "elevation_min": -10, "elevation_max": 10, "columns": 100,
      "min_range": 5.0, "max_range": 5.0}, "max_range"),
    ({"beams": 8, "elevation_min": -10, "elevation_max": 10, "columns": 10**9}, "columns"),
    ({"beams": 8, "elevation_min": -10, "elevation_max": 10, "columns": 100, "hfov": 0},
     "hfov"),
    ({"beams": 8, "elevation_min": -10, "elevation_max": 10, "columns": 100, "beam": 3},
     "beam"),
    ({"beams": 8, "elevation_min": -10, "elevation_max": 10, "columns": 100,
      "drop_prob": 1.0}, "drop_prob"),
    ({"beams": 8, "elevation_min": -10, "elevation_max": 10, "columns": 100,
      "mount": {"x": 1, "height": 2}}, "mount"),
])
def test_bad_lidar_tables_name_the_key(table, key):
    with pytest.raises(InputError) as e:
        model_from_table(table, "my.toml")
    msg = str(e.value)
    assert msg.startswith("my.toml: ") and key in msg and "\n" not in msg


def test_presets_are_valid_and_as_documented():
    w, h = PRESETS["waymo_top"], PRESETS["hdl32"]
    assert (w.rings, w.columns, w.max_range, w.rotation_hz) == (64, 2650, 75.0, 10.0)
    assert (h.rings, h.rotation_hz) == (32, 20.0)
    assert h.elevations_deg[0] == pytest.approx(-30.67) and h.elevations_deg[-1] == pytest.approx(10.67)
    for m in PRESETS.values():
        assert m.check() is m


def test_surfels_above_every_beam_are_never_paired_and_order_does_not_matter():
    """A canopy in front of the sensor but above its top beam (waymo_top looks at most 2.4°
    up) adds no pairs and changes no return; surfels straddling the top beam, seen from a
    moving and turning origin, return exactly what the float64 reference gives. The
    surfels' order (the bin's parallel blocks are scattered over the threads) changes
    neither the returns nor the pairs."""
    model = PRESETS["waymo_top"]
    C = model.columns
    d = model.directions()[:, C // 2 - 32:C // 2 + 32]        # facing +x (azimuth ~0)
    assert np.all(np.abs(np.degrees(np.arctan2(d[0, :, 1], d[0, :, 0]))) < 5.0)
    o = np.zeros((d.shape[1], 3))
    rng = np.random.default_rng(5)
    n = 6000
    canopy_c = np.column_stack([rng.uniform(5, 25, n), rng.uniform(-2, 2, n),
                                rng.uniform(8.0, 12.0, n)])
    canopy = L.surfel_frames(canopy_c, np.tile([0, 0, 0, 1.0], (n, 1)), np.full((n, 2), 0.05),
                             np.full(n, 0.9))
    dist = np.linalg.norm(canopy.c, axis=1)
    assert np.all(np.arcsin(canopy.c[:, 2] / dist) - np.arcsin(canopy.rad / dist)
                  > np.radians(2.4))                           # wholly above the top beam
    ground = _random_surfels(6000, seed=4)
    both = L.LidarSurfels(*(np.concatenate([getattr(ground, f), getattr(canopy, f)])
                            for f in ("c", "tu", "tv", "n", "s", "a", "rad", "packed")))
    t0, k0, s0 = L.cast_surfels(ground, o, d, min_range=0.5, max_range=40.0)
    t1, k1, s1 = L.cast_surfels(both, o, d, min_range=0.5, max_range=40.0)
    assert s1["pairs"] == s0["pairs"] > 0
    np.testing.assert_array_equal(t1, t0)
    # disks whose spheres straddle the top beam's elevation, from a moving, turning origin
    m = 1500
    r = rng.uniform(3.0, 20.0, m)
    el = np.radians(2.4) + rng.uniform(-1.0, 1.0, m) * np.arcsin(0.3 / r)
    az = rng.uniform(-0.1, 0.1, m)
    edge = L.surfel_frames(np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                                            r * np.sin(el)]),
                           np.tile([0.0, 0.7071068, 0.0, 0.7071068], (m, 1)),
                           np.full((m, 2), 0.1), np.full(m, 0.8))
    top = d[-16:]                                              # the highest 16 beams
    yaw = np.linspace(0.0, 0.05, d.shape[1])
    turned = top.copy()
    turned[..., 0] = top[..., 0] * np.cos(yaw) - top[..., 1] * np.sin(yaw)
    turned[..., 1] = top[..., 0] * np.sin(yaw) + top[..., 1] * np.cos(yaw)
    moving = np.column_stack([np.linspace(0.0, 0.8, d.shape[1]), np.linspace(0.0, 0.3, d.shape[1]),
                              np.zeros(d.shape[1])])
    te, ke, se = L.cast_surfels(edge, moving, turned, min_range=0.5, max_range=40.0)
    tr, kr = L.cast_reference(edge, moving, turned, min_range=0.5, max_range=40.0)
    _assert_same(te, ke, tr, kr, tol=1e-9)
    assert se["pairs"] > 0 and np.isfinite(te[-1]).any()      # the top beam meets some
    perm = rng.permutation(len(both))
    t2, k2, s2 = L.cast_surfels(both.subset(perm), o, d, min_range=0.5, max_range=40.0)
    assert s2["pairs"] == s1["pairs"]
    np.testing.assert_array_equal(t2, t1)
    hit = k2 >= 0
    np.testing.assert_array_equal(perm[k2[hit]], k1[hit])


def test_no_rays_no_work():
    """A sweep with no rings or no columns returns empty arrays, not an error."""
    surf = _random_surfels(100)
    for shape in ((0, 8, 3), (4, 0, 3)):
        t, k, stats = L.cast_surfels(surf, np.zeros((shape[1], 3)), np.zeros(shape),
                                     min_range=0.5, max_range=30.0)
        assert t.shape == shape[:2] and k.shape == shape[:2] and stats["pairs"] == 0


def test_opacity_bound_of_each_surfel_keeps_every_return():
    """The trace skips a ray once u² + v² passes the surfel's own q_max (its alpha below
    ALPHA_MIN there); opacities at the edges of the alpha clamp (1, just under and over
    ALPHA_MAX, just over ALPHA_MIN) return exactly what the float64 reference does, and a
    surfel that can never reach ALPHA_MIN has no q_max."""
    rng = np.random.default_rng(8)
    n = 8000
    means = rng.uniform(-12.0, 12.0, (n, 3))
    means[:, 2] = rng.uniform(-2.0, 4.0, n)
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    levels = np.array([1.0, 0.995, 0.99, 0.985, 0.5, 2.0 / 255.0, 1.0001 / 255.0])
    a = levels[rng.integers(0, len(levels), n)]
    surf = L.surfel_frames(means, quat, rng.uniform(0.02, 0.5, (n, 2)), a)
    np.testing.assert_allclose(surf.packed[:, 15], 2.0 * np.log(a * 255.0) * (1 + 1e-9) + 1e-9,
                               rtol=1e-12)
    model = PRESETS["waymo_top"]
    d = model.directions()[:, 1000:1024]
    o = np.zeros((d.shape[1], 3))
    t, k, _ = L.cast_surfels(surf, o, d, min_range=0.5, max_range=30.0)
    tr, kr = L.cast_reference(surf, o, d, min_range=0.5, max_range=30.0)
    _assert_same(t, k, tr, kr, tol=1e-9)
    never = L.surfel_frames(np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1)), np.ones((2, 2)),
                            np.array([0.5 / 255.0, 0.0]))
    assert np.all(never.packed[:, 15] == -1.0)
