"""env_lookup: bilinear, agrees with the numpy convention, continuous at the seam and poles."""
import math

import numpy as np
import pytest
import torch

from lsd3d_usd.env import EnvMap, env_lookup, pixel_directions, uv_to_direction


def _smooth_map(H=32, W=64):
    # a smooth function of direction (continuous on the sphere), sampled at pixel centres
    d = pixel_directions(W, H, np.float64)
    img = np.stack([1 + d[..., 0], 1 + 0.5 * d[..., 1] * d[..., 2], 2 + d[..., 2]], -1)
    return torch.from_numpy(img), d


def test_lookup_at_pixel_centres_returns_pixels():
    img, d = _smooth_map()
    out = env_lookup(img, torch.from_numpy(d))
    torch.testing.assert_close(out, img, rtol=1e-9, atol=1e-9)


def test_lookup_interpolates_a_smooth_function_closely():
    img, _ = _smooth_map(64, 128)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(500, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    out = env_lookup(img, torch.from_numpy(v)).numpy()
    exact = np.stack([1 + v[:, 0], 1 + 0.5 * v[:, 1] * v[:, 2], 2 + v[:, 2]], -1)
    assert np.abs(out - exact).max() < 0.02


def _jump(img, a, b):
    return float((env_lookup(img, a) - env_lookup(img, b)).abs().max())


def test_continuous_across_longitude_seam():
    # random (non-smooth) image: continuity must come from the wrap, not from the content
    img = torch.rand(32, 64, 3, dtype=torch.float64)
    eps = 1e-7
    for lat in np.linspace(-1.3, 1.3, 9):
        # the seam is at u = 0 / 1, i.e. direction +Y (longitude +-pi)
        left = uv_to_direction(np.array([eps, 0.5 - lat / math.pi]))
        right = uv_to_direction(np.array([1 - eps, 0.5 - lat / math.pi]))
        assert _jump(img, torch.from_numpy(left), torch.from_numpy(right)) < 1e-4


@pytest.mark.parametrize("pole", [1.0, -1.0])
def test_continuous_at_the_poles(pole):
    img = torch.rand(32, 64, 3, dtype=torch.float64)
    eps = 1e-6
    vals = []
    for phi in np.linspace(0, 2 * math.pi, 17):
        d = np.array([eps * math.cos(phi), eps * math.sin(phi), pole])
        vals.append(env_lookup(img, torch.from_numpy(d / np.linalg.norm(d))))
    vals = torch.stack(vals)
    # every azimuth converges to the same pole value
    assert float((vals - vals[0]).abs().max()) < 1e-3
    # and approaching the pole along one meridian vs. the opposite one agrees
    a = torch.tensor([1e-6, 0.0, pole], dtype=torch.float64)
    b = torch.tensor([-1e-6, 0.0, pole], dtype=torch.float64)
    assert _jump(img, a, b) < 1e-3


def test_envmap_shapes_and_gradient():
    img = torch.rand(16, 32, 3, requires_grad=True)
    m = EnvMap(img)
    d = torch.randn(4, 5, 3)
    out = m(d)
    assert out.shape == (4, 5, 3)
    out.sum().backward()
    assert img.grad is not None and float(img.grad.sum()) == pytest.approx(60.0, rel=1e-4)
    with pytest.raises(ValueError):
        EnvMap(torch.rand(16, 16, 3))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_path_equals_the_differentiable_path(dtype):
    """Without gradients env_lookup runs a numba kernel; with them, torch ops: same values,
    including the seam, the poles, unnormalised and non-finite directions."""
    g = torch.Generator().manual_seed(0)
    img = torch.rand(16, 32, 3, generator=g, dtype=dtype)
    d = torch.randn(2000, 3, generator=g, dtype=dtype) * 3
    d[:4] = torch.tensor([[0, 0, 1], [0, 0, -1], [0, 1, 0], [1e-9, 1, 1e-9]], dtype=dtype)
    d[4] = float("nan")
    fast = env_lookup(img, d)
    slow = env_lookup(img.clone().requires_grad_(True), d).detach()
    assert fast.dtype == dtype and fast.shape == (2000, 3)
    # float32: the torch path rounds the pixel coordinate to float32 (slope here up to 1/px)
    tol = 1e-4 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(fast[5:], slow[5:], rtol=tol, atol=tol)
    torch.testing.assert_close(fast[:4], slow[:4], rtol=tol, atol=tol)
    assert torch.isnan(fast[4]).all() and torch.isnan(slow[4]).all()


def test_no_grad_lookup_of_an_image_that_requires_grad():
    img = torch.rand(8, 16, 3, requires_grad=True)
    d = torch.randn(10, 3)
    with torch.no_grad():
        out = env_lookup(img, d)
    torch.testing.assert_close(out, env_lookup(img, d).detach(), rtol=1e-4, atol=1e-4)
