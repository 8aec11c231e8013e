"""Fréchet distance: closed forms on Gaussians, scipy's sqrtm on full-rank features, the
nuclear-norm feature path against the covariance path, degenerate and rank-deficient inputs."""
import warnings

import numpy as np
import pytest
import scipy.linalg

from lsd3d_usd.errors import InputError
from lsd3d_usd.eval.metrics import (FewSamplesWarning, feature_stats, frechet_distance,
                                    frechet_distance_features, psd_sqrt, trace_sqrt_product)


def _random_spd(rng, d, rank=None):
    a = rng.normal(size=(d, rank or d))
    return a @ a.T / d


def _fd_scipy(mu1, s1, mu2, s2):
    covmean = scipy.linalg.sqrtm(s1 @ s2)
    covmean = np.real(covmean)
    diff = mu1 - mu2
    return diff @ diff + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean)


def test_closed_form_diagonal_gaussians():
    # Commuting (diagonal) covariances: FD = |mu1-mu2|^2 + sum (sqrt(a_i) - sqrt(b_i))^2.
    mu1, mu2 = np.array([1.0, -2.0, 0.5]), np.array([0.0, 1.0, 0.5])
    a, b = np.array([4.0, 1.0, 0.25]), np.array([1.0, 9.0, 0.25])
    want = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    assert frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(want, rel=1e-12)


def test_closed_form_general_gaussians():
    # Non-commuting covariances, 2-d: tr((S1 S2)^1/2) = sqrt(tr(S1 S2) + 2 sqrt(det(S1 S2))).
    s1 = np.array([[2.0, 0.7], [0.7, 1.0]])
    s2 = np.array([[0.5, -0.2], [-0.2, 3.0]])
    m = s1 @ s2
    tr_sqrt = np.sqrt(np.trace(m) + 2 * np.sqrt(np.linalg.det(m)))
    mu1, mu2 = np.array([0.3, 0.1]), np.array([-1.0, 2.0])
    want = np.sum((mu1 - mu2) ** 2) + np.trace(s1) + np.trace(s2) - 2 * tr_sqrt
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(want, rel=1e-12)
    assert trace_sqrt_product(s1, s2) == pytest.approx(tr_sqrt, rel=1e-12)


def test_matches_scipy_sqrtm_on_random_features():
    rng = np.random.default_rng(3)
    for d, n in ((8, 200), (32, 400)):
        x1 = rng.normal(size=(n, d)) @ rng.normal(size=(d, d))
        x2 = rng.normal(size=(n, d)) @ rng.normal(size=(d, d)) + 0.5
        (m1, s1), (m2, s2) = feature_stats(x1), feature_stats(x2)
        want = _fd_scipy(m1, s1, m2, s2)
        assert frechet_distance(m1, s1, m2, s2) == pytest.approx(want, rel=1e-8)
        assert frechet_distance_features(x1, x2).value == pytest.approx(want, rel=1e-8)
        # float64 reference of the covariance itself
        np.testing.assert_allclose(s1, np.cov(x1, rowvar=False), rtol=1e-12)


def test_feature_path_equals_covariance_path_when_rank_deficient():
    # 10 and 7 samples of 64-d features: the nuclear-norm form must equal the eigh form.
    rng = np.random.default_rng(5)
    x1, x2 = rng.normal(size=(10, 64)), rng.normal(size=(7, 64)) + 0.2
    (m1, s1), (m2, s2) = feature_stats(x1), feature_stats(x2)
    with pytest.warns(FewSamplesWarning, match="fewer samples than dimensions"):
        r = frechet_distance_features(x1, x2)
    assert r.warning and r.n1 == 10 and r.n2 == 7 and r.dims == 64
    assert r.value == pytest.approx(frechet_distance(m1, s1, m2, s2), rel=1e-9)
    # scipy's sqrtm of the singular, non-symmetric product drifts; ours stays real and >= 0.
    assert r.value > 0


def test_no_warning_with_enough_samples():
    rng = np.random.default_rng(0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = frechet_distance_features(rng.normal(size=(50, 4)), rng.normal(size=(60, 4)))
    assert r.warning is None


def test_identical_sets_give_zero():
    rng = np.random.default_rng(1)
    for n, d in ((300, 16), (12, 256)):
        x = rng.normal(size=(n, d)) * rng.uniform(0.1, 10, size=d)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FewSamplesWarning)
            v = frechet_distance_features(x, x.copy()).value
        assert abs(v) < 1e-8 * np.trace(np.cov(x, rowvar=False))
        m, s = feature_stats(x)
        assert abs(frechet_distance(m, s, m, s)) < 1e-8 * np.trace(s)


def test_one_sample_and_constant_features():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(1, 32))
    b = rng.normal(size=(20, 32))
    with pytest.warns(FewSamplesWarning):
        r = frechet_distance_features(a, b)
    # One sample: zero covariance, FD = |mu1-mu2|^2 + tr(S2).
    m2, s2 = feature_stats(b)
    assert r.value == pytest.approx(np.sum((a[0] - m2) ** 2) + np.trace(s2), rel=1e-10)
    # Constant features on both sides: zero covariances, FD is the squared mean distance.
    c1, c2 = np.full((5, 8), 2.0), np.full((9, 8), -1.0)
    with pytest.warns(FewSamplesWarning):
        assert frechet_distance_features(c1, c2).value == pytest.approx(8 * 9.0, rel=1e-12)
    assert frechet_distance_features(c1[:, :3], c1[:, :3], warn=False).value == 0.0


def test_psd_sqrt_clips_round_off_negative_eigenvalues():
    rng = np.random.default_rng(4)
    s = _random_spd(rng, 20, rank=3)
    s_noisy = s - 1e-14 * np.eye(20)  # slightly indefinite
    r = psd_sqrt(s_noisy)
    assert np.all(np.isfinite(r))
    np.testing.assert_allclose(r @ r, s, atol=1e-10)


def test_rank_deficient_covariances_are_stable():
    rng = np.random.default_rng(6)
    s1, s2 = _random_spd(rng, 50, rank=4), _random_spd(rng, 50, rank=6)
    mu = np.zeros(50)
    v = frechet_distance(mu, s1, mu, s2)
    assert np.isfinite(v) and v >= 0
    # Symmetry of the distance.
    assert v == pytest.approx(frechet_distance(mu, s2, mu, s1), rel=1e-8)
    # Same Gaussian, rank-deficient: zero.
    assert frechet_distance(mu, s1, mu, s1) < 1e-9


@pytest.mark.parametrize("x1,x2,match", [
    (np.zeros((0, 4)), np.zeros((3, 4)), "non-empty"),
    (np.zeros((3, 4)), np.zeros((3, 5)), "same d"),
    (np.full((3, 4), np.nan), np.zeros((3, 4)), "non-finite"),
])
def test_bad_feature_sets(x1, x2, match):
    with pytest.raises(InputError, match=match):
        frechet_distance_features(x1, x2)
