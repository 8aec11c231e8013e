"""DDIM schedule, sampling and inversion against analytic oracles (float64)."""
import math

import numpy as np
import pytest
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.priors.ddim import DDIMSchedule, eps_from_model_output


def point_oracle(sched, z_star):
    """Exact eps for data concentrated at z*: eps = (z - sqrt(ab) z*) / sqrt(1 - ab)."""
    def eps(z, k):
        a = sched.alpha_bar(k)
        return (z - math.sqrt(a) * z_star) / math.sqrt(1 - a)
    return eps


def gaussian_oracle(sched, mu, s):
    """Exact eps for data ~ N(mu, s^2 I): E[eps | z] = sqrt(1-ab)(z - sqrt(ab) mu) / (ab s^2 + 1 - ab)."""
    def eps(z, k):
        a = sched.alpha_bar(k)
        return math.sqrt(1 - a) * (z - math.sqrt(a) * mu) / (a * s * s + 1 - a)
    return eps


def test_schedule_matches_numpy_reference():
    s = DDIMSchedule()
    betas = np.linspace(np.sqrt(0.00085), np.sqrt(0.012), 1000) ** 2
    ref = np.cumprod(1 - betas)
    np.testing.assert_allclose(s.alphas_cumprod.numpy(), ref, rtol=1e-12)
    assert s.alphas_cumprod.dtype == torch.float64
    assert s.alpha_bar(-1) == 1.0
    # SD's terminal signal level is ~0.0047: a (nearly) but not fully destroyed signal
    assert 0.004 < s.alpha_bar(999) < 0.006


def test_levels_and_t_mapping():
    s = DDIMSchedule()
    assert s.level(1.0) == 999 and s.level(0.0) == -1 and s.level(0.0004) == -1
    assert s.level(0.5) == 499
    ks = s.levels(999, 5)
    assert ks[0] == 999 and ks[-1] == -1 and len(ks) == 6
    assert all(a > b for a, b in zip(ks[:-1], ks[1:]))
    # more steps than levels: no repeated level
    assert s.levels(3, 50) == [3, 2, 1, 0, -1]
    assert s.levels(-1, 5) == [-1]
    with pytest.raises(InputError):
        s.levels(10, 0)
    with pytest.raises(InputError):
        s.level(1.5)


@pytest.mark.parametrize("k_start", [0, 37, 400, 999])
@pytest.mark.parametrize("n", [1, 2, 5, 20])
def test_denoise_returns_data_point_from_any_z(k_start, n):
    s = DDIMSchedule()
    g = torch.Generator().manual_seed(k_start * 100 + n)
    z_star = torch.randn(4, 8, 8, generator=g, dtype=torch.float64)
    z_t = torch.randn(4, 8, 8, generator=g, dtype=torch.float64) * 3.0  # arbitrary, not on the path
    out = s.denoise(z_t, point_oracle(s, z_star), k_start, n)
    assert torch.allclose(out, z_star, atol=1e-10)


@pytest.mark.parametrize("t", [0.02, 0.3, 0.7, 1.0])
@pytest.mark.parametrize("n", [1, 5, 50])
def test_inversion_then_denoising_is_identity(t, n):
    s = DDIMSchedule()
    z_star = torch.randn(2, 4, 16, 16, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    eps = point_oracle(s, z_star)
    k = s.level(t)
    z_t = s.invert(z_star, eps, k, n)
    # the inverted latent is a genuinely noisy latent, not z*
    assert not torch.allclose(z_t, z_star, atol=1e-2)
    back = s.denoise(z_t, eps, k, n)
    assert (back - z_star).abs().max() < 1e-4


def test_gaussian_oracle_matches_probability_flow_map():
    """For N(mu, s^2) data the ODE maps z_k to mu + s (z_k - sqrt(ab) mu) / sqrt(ab s^2 + 1 - ab).
    Many-step DDIM must approach it (catches wrong signs / swapped coefficients)."""
    s = DDIMSchedule()
    mu, sd = 0.7, 0.4
    eps = gaussian_oracle(s, mu, sd)
    z = torch.linspace(-3, 3, 101, dtype=torch.float64)
    k = 999
    a = s.alpha_bar(k)
    exact = mu + sd * (z - math.sqrt(a) * mu) / math.sqrt(a * sd * sd + 1 - a)
    errs = [float((s.denoise(z, eps, k, n) - exact).abs().max()) for n in (10, 100, 999)]
    # first-order convergence: error ~ 1/N (measured 0.35, 0.056, 0.0076)
    assert errs[0] > 4 * errs[1] > 16 * errs[2]
    assert errs[2] < 1e-2
    # inversion is the inverse flow: from data to the level, then back
    x = torch.linspace(-1, 2, 31, dtype=torch.float64)
    rts = [float((s.denoise(s.invert(x, eps, 600, n), eps, 600, n) - x).abs().max()) for n in (5, 50, 600)]
    assert rts[0] > rts[1] > rts[2] and rts[2] < 2e-2


def test_step_reference_formula():
    s = DDIMSchedule()
    z = torch.tensor([0.3, -1.2], dtype=torch.float64)
    e = torch.tensor([0.5, 0.1], dtype=torch.float64)
    a1, a2 = s.alpha_bar(500), s.alpha_bar(300)
    x0 = (z - np.sqrt(1 - a1) * e) / np.sqrt(a1)
    ref = np.sqrt(a2) * x0 + np.sqrt(1 - a2) * e
    assert torch.allclose(s.step(z, e, 500, 300), ref, atol=1e-14)
    # add_noise and predict_x0 are inverse for a known eps
    assert torch.allclose(s.predict_x0(s.add_noise(z, e, 700), e, 700), z, atol=1e-12)


def test_v_prediction_conversion():
    s = DDIMSchedule()
    a = s.alpha_bar(400)
    x0 = torch.randn(10, dtype=torch.float64)
    e = torch.randn(10, dtype=torch.float64)
    z = math.sqrt(a) * x0 + math.sqrt(1 - a) * e
    v = math.sqrt(a) * e - math.sqrt(1 - a) * x0
    assert torch.allclose(eps_from_model_output(v, z, a, "v_prediction"), e, atol=1e-12)
    assert torch.allclose(eps_from_model_output(x0, z, a, "sample"), e, atol=1e-10)
    with pytest.raises(InputError):
        eps_from_model_output(v, z, a, "bogus")
