"""GGDS losses: simple cases against float64 reference values, degenerate masks, gradients."""
import math

import numpy as np
import pytest
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.priors.ddim import DDIMSchedule
from lsd3d_usd.ggds.losses.image import disparity_loss, l1_loss, normal_loss, omega, tv_loss


def test_omega_kinds():
    assert omega(0.3) == 1.0
    s = DDIMSchedule()
    ab = s.alpha_bar(s.level(0.5))
    assert omega(0.5, "sds") == pytest.approx(2 * math.sqrt(ab * (1 - ab)))
    assert omega(0.5, "signal") == pytest.approx(math.sqrt(ab))
    w = [omega(t, "sds") for t in np.linspace(0.01, 1.0, 200)]
    assert max(w) == pytest.approx(1.0, abs=1e-2) and min(w) >= 0
    sig = [omega(t, "signal") for t in np.linspace(0.01, 1.0, 50)]
    assert all(a >= b for a, b in zip(sig[:-1], sig[1:]))
    with pytest.raises(InputError):
        omega(0.5, "nope")


def test_l1_and_mask():
    x = torch.zeros(4, 5, 3)
    y = torch.zeros(4, 5, 3)
    y[0, 0] = torch.tensor([3.0, 0.0, 0.0])
    assert float(l1_loss(x, y)) == pytest.approx(1.0 / 20)
    m = torch.zeros(4, 5, dtype=torch.bool)
    m[0, 0] = True
    assert float(l1_loss(x, y, m)) == pytest.approx(1.0)
    # NaN outside the mask does not leak
    y[3, 4] = float("nan")
    assert float(l1_loss(x, y, m)) == pytest.approx(1.0)


def test_empty_masks_give_zero_not_nan_with_finite_grads():
    x = torch.rand(6, 7, 3, requires_grad=True)
    d = (torch.rand(6, 7) + 1).requires_grad_(True)
    n = torch.randn(6, 7, 3, requires_grad=True)
    empty = torch.zeros(6, 7, dtype=torch.bool)
    terms = [l1_loss(x, torch.rand(6, 7, 3), empty), tv_loss(x, empty),
             normal_loss(n, torch.randn(6, 7, 3), empty), disparity_loss(d, torch.rand(6, 7) + 1, empty),
             disparity_loss(d, torch.full((6, 7), float("inf")))]  # all sky
    for v in terms:
        assert float(v.detach()) == 0.0
    sum(terms).backward()
    for p in (x, d, n):
        assert torch.isfinite(p.grad).all() and float(p.grad.abs().sum()) == 0.0


def test_tv_reference():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(5, 6, 2, generator=g, dtype=torch.float64)
    a = x.numpy()
    dy = np.abs(np.diff(a, axis=0)).mean(-1)
    dx = np.abs(np.diff(a, axis=1)).mean(-1)
    ref = (dy.sum() + dx.sum()) / (dy.size + dx.size)
    assert float(tv_loss(x)) == pytest.approx(ref, rel=1e-12)
    assert float(tv_loss(torch.ones(5, 6, 3))) == 0.0
    # a mask holding one pixel has no neighbour pairs
    m = torch.zeros(5, 6)
    m[2, 2] = 1
    assert float(tv_loss(x, m)) == 0.0


def test_normal_loss_angles():
    up = torch.tensor([0.0, 0.0, 1.0]).expand(3, 3, 3).clone()
    tilt = torch.tensor([math.sin(math.radians(60)), 0.0, math.cos(math.radians(60))])
    r = (tilt * 0.3).expand(3, 3, 3).clone()  # short (alpha-blended) but 60 degrees off
    assert float(normal_loss(r, up)) == pytest.approx(0.5, abs=1e-6)
    assert float(normal_loss(-up, up)) == pytest.approx(2.0)
    assert float(normal_loss(-up, up, two_sided=True)) == pytest.approx(0.0, abs=1e-7)
    # zero-length rendered normals (no surfel) are skipped
    r2 = up.clone()
    r2[0] = 0
    r2[1, 1] = torch.tensor([1.0, 0, 0])
    assert float(normal_loss(r2, up)) == pytest.approx(1.0 / 6)
    # gradient is finite even on zero-length normals
    r3 = torch.zeros(3, 3, 3, requires_grad=True)
    normal_loss(r3, up).backward()
    assert torch.isfinite(r3.grad).all()


def test_disparity_loss_relative_and_absolute():
    dp = torch.tensor([[5.0, 80.0], [float("inf"), 10.0]])
    dr = dp * 1.01
    dr[1, 1] = 0.0  # no surfel
    # relative: |d_p/d_r - 1| = 1 - 1/1.01 on the two valid pixels
    assert float(disparity_loss(dr, dp)) == pytest.approx(1 - 1 / 1.01, rel=1e-5)
    ab = (abs(1 / 5.05 - 1 / 5) + abs(1 / 80.8 - 1 / 80)) / 2
    assert float(disparity_loss(dr, dp, relative=False)) == pytest.approx(ab, rel=1e-5)
    # scale-free: scaling the scene leaves the relative loss unchanged
    assert float(disparity_loss(dr * 7, dp * 7)) == pytest.approx(float(disparity_loss(dr, dp)), rel=1e-5)  # float32
    # gradient pushes the render depth towards the proxy
    d = torch.tensor([[6.0]], requires_grad=True)
    disparity_loss(d, torch.tensor([[5.0]])).backward()
    assert float(d.grad) > 0  # a descent step lowers the depth from 6 m towards 5 m


def test_l2_term_is_off_by_default_and_is_the_mean_squared_error():
    from types import SimpleNamespace

    from lsd3d_usd.ggds.settings import GGDSConfig
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    from lsd3d_usd.ggds.losses.terms import LOSSES, StepContext, active_terms
    prior = ProceduralPrior()
    assert "l2" not in [t.name for t, _ in active_terms(GGDSConfig(), prior)]
    cfg = GGDSConfig()
    cfg.weights["l2"] = 10.0
    assert ("l2", 10.0) in [(t.name, w) for t, w in active_terms(cfg, prior)]
    x, y = torch.rand(5, 4, 3, dtype=torch.float64), torch.rand(5, 4, 3, dtype=torch.float64)
    ctx = StepContext(x=x, target=y, render=SimpleNamespace(), gbuffer=None, camera=None, t=1.0,
                      config=cfg)
    ref = sum(float(a - b) ** 2 for a, b in zip(x.flatten(), y.flatten())) / x.numel()
    assert abs(float(LOSSES.get("l2").fn(ctx)) - ref) < 1e-12
