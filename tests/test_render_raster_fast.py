"""The fast path's building blocks against plain versions: trig-free screen bounds, compacted
projection, per-tile depth sort binning, pair lists of the backward, input validation, and
the driving-scene render against the float64 reference."""
import math

import numpy as np
import pytest
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.render import kernels
from lsd3d_usd.render import kernels_prep as kprep
from lsd3d_usd.render import projection as proj
from lsd3d_usd.render.benchmark import driving_camera, driving_scene, reference_on_crops
from lsd3d_usd.render.checks import first_bad, first_bad_array
from lsd3d_usd.render.raster_types import RasterSettings
from lsd3d_usd.render.rasterize import rasterize


def _sampled_extent(A, B, C, D, E, F, near, n=50_001):
    th = np.linspace(0, 2 * np.pi, n)
    z = D + E * np.cos(th) + F * np.sin(th)
    x = (A + B * np.cos(th) + C * np.sin(th)) / z
    x = x[z >= near]
    return x.min(), x.max()


def test_quadratic_extent_matches_arc_and_sampling():
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(300):
        A, B, C = rng.normal(0, 50, 3)
        D = rng.uniform(0.5, 20)
        E, F = rng.normal(0, D / 3, 2)
        near = 0.05
        lo, hi = kprep._extent(A, B, C, D, E, F, near)
        alo, ahi = kprep._arc(A, B, C, D, E, F, near)
        assert lo == pytest.approx(alo, rel=1e-9, abs=1e-9)
        assert hi == pytest.approx(ahi, rel=1e-9, abs=1e-9)
        if D - math.hypot(E, F) > near:
            checked += 1
            slo, shi = _sampled_extent(A, B, C, D, E, F, near)
            # exact extremes contain every sample and are attained to sampling accuracy
            assert lo <= slo + 1e-9 and hi >= shi - 1e-9
            assert slo - lo < 1e-3 * (1 + abs(lo)) and hi - shi < 1e-3 * (1 + abs(hi))
    assert checked > 200  # the closed form was really exercised


def test_tiny_far_splat_bounds_keep_precision():
    # a 1 mm disk 500 m away: the tangents sit ~1e-3 px from the centre, far from any
    # cancellation in the quadratic
    A, B, C, D, E, F = 500.0 * 800, 0.001 * 800, 0.0, 500.0, 0.0, 0.0005
    lo, hi = kprep._extent(A, B, C, D, E, F, 0.05)
    slo, shi = _sampled_extent(A, B, C, D, E, F, 0.05)
    assert lo <= slo and hi >= shi and hi - lo < 2 * (shi - slo) + 1e-9


def _projected(n=3000, w=320, h=180, seed=1):
    arrs = driving_scene(n, seed=seed, sh_degree=1)
    vm, K = driving_camera(w, h)
    rot, centre = proj.camera_frame(torch.from_numpy(vm))
    args = (*arrs, 1, rot.numpy(), centre.numpy(), K.astype(np.float64), w, h, 0.05, 1e4,
            1.0 / 255.0, -1.0)
    return args, w, h


def test_project_visible_is_the_compacted_full_projection():
    args, _, _ = _projected()
    prm, vis, rect, zc, _ = kprep.project(*args)
    idx, prm_c, rect_c, zc_c = kprep.project_visible(*args)
    assert 0 < len(idx) < len(vis)
    np.testing.assert_array_equal(idx, np.flatnonzero(vis))
    np.testing.assert_array_equal(prm_c, prm[idx])
    np.testing.assert_array_equal(rect_c, rect[idx])
    np.testing.assert_array_equal(zc_c, zc[idx])


def test_bin_sorted_matches_global_stable_sort_and_pair_arrays():
    args, w, h = _projected()
    idx, prm, rect, zc = kprep.project_visible(*args)
    # equal depths must keep index order, as a stable sort does
    zc = zc.copy()
    zc[10:40] = zc[10]
    tile = 16
    ntx, nty = (w + tile - 1) // tile, (h + tile - 1) // tile
    start_ref, splats_ref = kernels.bin_tiles(rect, np.argsort(zc, kind="stable"), tile, ntx, nty)
    start, splats, pprm, prect, soff = kernels.bin_sorted(rect, zc.view(np.int32), prm, tile, ntx, nty)
    np.testing.assert_array_equal(start, start_ref)
    np.testing.assert_array_equal(splats, splats_ref)
    np.testing.assert_array_equal(pprm, prm[splats])
    np.testing.assert_array_equal(prect, rect[splats])
    # pair lists per surfel: exactly the positions of that surfel, ascending
    pairs = kernels.surfel_pairs(start, splats, prect, soff, tile, ntx)
    np.testing.assert_array_equal(np.diff(soff), np.bincount(splats, minlength=len(idx)))
    order = np.argsort(splats, kind="stable")
    np.testing.assert_array_equal(pairs, order)
    # summing rows through the lists equals the plain per-pair reduction
    rows = np.random.default_rng(0).normal(size=(len(splats), 16)).astype(np.float32)
    ref = kernels.reduce_pairs(rows, splats, len(idx))
    got = np.add.reduceat(rows[pairs], soff[:-1], axis=0)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)


def test_validation_names_array_and_index():
    arrs = [torch.from_numpy(a) for a in driving_scene(50, seed=0)]
    vm, K = driving_camera(64, 48)
    kw = dict(viewmat=torch.from_numpy(vm), K=torch.from_numpy(K), width=64, height=48)
    means, quats, scales, op, sh = arrs
    bad = scales.clone()
    bad[31, 0] = -0.1
    with pytest.raises(InputError, match=r"scales has a negative value at index 31"):
        rasterize(means, quats, bad, op, sh, **kw)
    badq = quats.clone()
    badq[12] = 0
    with pytest.raises(InputError, match=r"quats has a zero quaternion at index 12"):
        rasterize(means, badq, scales, op, sh, **kw)
    bads = sh.clone()
    bads[44, 1, 2] = float("nan")
    with pytest.raises(InputError, match=r"sh has a non-finite.*index 44"):
        rasterize(means, quats, scales, op, bads, **kw)
    flat = np.zeros(300_000, np.float32)
    flat[[200_001, 250_000]] = np.inf  # first bad element across parallel chunks
    inf = np.float32(np.inf)
    assert first_bad(flat, -inf, inf) == 200_001
    assert first_bad(np.zeros(0, np.float32), np.float32(0), inf) == -1


def test_driving_scene_within_1e3_of_float64_reference():
    # the benchmark's accuracy criterion at default settings, on a scene small enough for a test
    arrays = driving_scene(20_000, seed=3, sh_degree=1)
    w, h = 240, 136
    vm, K = driving_camera(w, h)
    out = rasterize(*(torch.from_numpy(a) for a in arrays), viewmat=torch.from_numpy(vm),
                    K=torch.from_numpy(K), width=w, height=h, settings=RasterSettings(sh_degree=1))
    pix, ref, n_ref = reference_on_crops(arrays, vm, K, w, h, sh_degree=1)
    assert n_ref > 100
    rgb = out.rgb[pix[:, 1], pix[:, 0]].double()
    assert (rgb - ref["rgb"]).abs().max().item() <= 1e-3


def test_exp_neg_against_float64():
    from numba import njit

    @njit
    def run(y):
        out = np.empty_like(y)
        for i in range(y.shape[0]):
            out[i] = kernels.exp_neg(y[i])
        return out

    y = np.concatenate([np.linspace(0, 20, 400_001), [0.0, 1e-30, 15.9999, 16.0, 1e30, np.inf]])
    y = y.astype(np.float32)
    got = run(y).astype(np.float64)
    want = np.exp(-np.minimum(y.astype(np.float64), 16.0))
    assert got[0] == 1.0  # alpha at a surfel centre is exactly its opacity
    assert np.abs(got - want).max() < 2e-7
    small = y <= 8  # where alpha can exceed 1/255: relative accuracy
    assert (np.abs(got - want) / want)[small].max() < 1e-6
    assert np.isfinite(run(np.array([np.nan], np.float32))).all()  # never a NaN alpha


def test_tile_must_be_a_multiple_of_the_lane_block_and_sizes_agree():
    arrays = [torch.from_numpy(a) for a in driving_scene(3000, seed=1)]
    vm, K = driving_camera(100, 60)
    kw = dict(viewmat=torch.from_numpy(vm), K=torch.from_numpy(K), width=100, height=60)
    with pytest.raises(InputError, match=r"tile must be a positive multiple of 8, not 12"):
        rasterize(*arrays, **kw, settings=RasterSettings(tile=12))
    a = rasterize(*arrays, **kw, settings=RasterSettings(tile=16))
    b = rasterize(*arrays, **kw, settings=RasterSettings(tile=32))
    assert a.stats.evals_rect <= a.stats.evals
    for k in ("rgb", "alpha", "depth_median", "normal"):
        assert torch.allclose(getattr(a, k), getattr(b, k), atol=1e-6), k


def test_too_many_surfels_in_one_tile_is_refused(monkeypatch):
    # list positions are held in float32 in the kernel: exact only below MAX_TILE_PAIRS
    arrays = [torch.from_numpy(a) for a in driving_scene(3000, seed=1)]
    vm, K = driving_camera(100, 60)
    monkeypatch.setattr(kernels, "MAX_TILE_PAIRS", 50)
    with pytest.raises(InputError, match=r"more than 50 surfels overlap one 16x16 tile"):
        rasterize(*arrays, viewmat=torch.from_numpy(vm), K=torch.from_numpy(K), width=100,
                  height=60)


def test_validation_of_strided_and_float64_inputs():
    # the one-scan check takes any layout; float64 inputs take the per-array path
    means, quats, scales, op, sh = [torch.from_numpy(a) for a in driving_scene(500, seed=0)]
    vm, K = driving_camera(64, 48)
    kw = dict(viewmat=torch.from_numpy(vm), K=torch.from_numpy(K), width=64, height=48)
    strided = torch.stack([op, op], 1)[:, 0]
    assert not strided.is_contiguous()
    ok = rasterize(means, quats, scales, strided, sh, **kw)
    assert torch.equal(ok.rgb, rasterize(means, quats, scales, op, sh, **kw).rgb)
    bad = strided.clone()
    bad[7] = float("nan")
    with pytest.raises(InputError, match=r"opacities has a non-finite value \(NaN or Inf\) at index 7$"):
        rasterize(means, quats, scales, bad, sh, **kw)
    m64 = means.double()
    m64[3, 1] = float("inf")
    with pytest.raises(InputError, match=r"means has a non-finite value .* at index 3$"):
        rasterize(m64, quats, scales, op, sh, **kw)
    lo = np.array([-np.inf, 0.0], np.float32)
    hi = np.full(2, np.inf, np.float32)
    assert first_bad_array((np.zeros(3, np.float32), np.full(2, -1.0, np.float32)), lo, hi) == 1


@pytest.mark.parametrize("deg", [1, 2, 3])
def test_sh_direction_gradient_against_float64_autograd(deg):
    """project_backward's SH colour derivative along the view direction (sh_grad_dot) is the
    gradient of render.sh.sh_basis's polynomials, taken by torch in float64 — including at the
    poles and on the axes, where an angle-based derivative would break down."""
    from lsd3d_usd.render.sh import sh_basis
    rng = np.random.default_rng(deg)
    dirs = rng.normal(size=(64, 3))
    dirs = np.concatenate([dirs, np.eye(3), -np.eye(3), [[0.0, 0.0, 0.0]]])
    nk = (deg + 1) ** 2
    for d in dirs:
        w = np.zeros(16)
        w[1:nk] = rng.normal(size=nk - 1)
        x = torch.tensor(d, dtype=torch.float64, requires_grad=True)
        (sh_basis(x[None], deg)[0] @ torch.tensor(w[:nk])).backward()
        got = kprep.sh_grad_dot(d[0], d[1], d[2], deg, w)
        assert np.allclose(got, x.grad.numpy(), rtol=1e-12, atol=1e-12)
