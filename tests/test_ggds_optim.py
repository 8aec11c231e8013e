"""The optimisation parts of GGDS (ggds/optim/): the 3D smoothing filter (antialias.py) against
a float64 convolution, on degenerate inputs and inside a run (baked into the written field,
restored by a resume), and error-driven densification of the MCMC strategy."""
import json

import numpy as np
import pytest
import torch

from lsd3d_usd.ggds.optim import params as P
from lsd3d_usd.ggds.optim.antialias import filter_sigma, smooth
from lsd3d_usd.conditioning.visibility import footprint
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.splats.field import SurfelField

def cams():
    """Three cameras looking at the origin region from different distances and sides."""
    out = []
    for eye, w in (((0, -10, 2), 64), ((0, -3, 1.5), 64), ((12, 0, 3), 32)):
        out.append(Camera.from_fov(w, w * 3 // 4, 60.0, pose=look_at(np.array(eye, float),
                                                                      np.zeros(3)), near=0.1,
                                   far=100.0))
    return out


# ------------------------------------------------------------------ 3D smoothing filter
def _disk(su, sv, o, x, y):
    return o * np.exp(-0.5 * (x ** 2 / su ** 2 + y ** 2 / sv ** 2))


def test_smooth_equals_numerical_convolution_in_float64():
    su, sv, o, sig = 0.05, 0.02, 0.7, 0.03
    h = 0.004
    g = np.arange(-0.4, 0.4 + h / 2, h)
    X, Y = np.meshgrid(g, g, indexing="ij")
    disk = _disk(su, sv, o, X, Y)
    k = np.exp(-0.5 * (X ** 2 + Y ** 2) / sig ** 2)
    k /= k.sum()
    from scipy.signal import fftconvolve
    conv = fftconvolve(disk, k, mode="same")
    s2, o2 = smooth(torch.tensor([[su, sv]], dtype=torch.float64),
                    torch.tensor([o], dtype=torch.float64), torch.tensor([sig], dtype=torch.float64))
    analytic = _disk(float(s2[0, 0]), float(s2[0, 1]), float(o2[0]), X, Y)
    assert np.abs(conv - analytic).max() < 1e-5
    # the integral (what the disk contributes to a pixel much larger than it) is kept
    assert abs(float(o2[0] * s2[0, 0] * s2[0, 1]) - o * su * sv) < 1e-15


def test_smooth_degenerate_inputs_and_gradients():
    s = torch.tensor([[0.1, 0.2], [0.0, 0.0], [1e-9, 1e-9]], dtype=torch.float64)
    o = torch.tensor([0.5, 0.9, 0.9], dtype=torch.float64)
    s0, o0 = smooth(s, o, torch.zeros(3, dtype=torch.float64))
    assert torch.equal(s0[:1], s[:1]) and torch.equal(o0[:1], o[:1])
    assert o0[1] == 0.9                 # zero scale, zero filter: left alone
    s1, o1 = smooth(s, o, torch.full((3,), 0.05, dtype=torch.float64))
    assert torch.allclose(s1[1], torch.tensor([0.05, 0.05], dtype=torch.float64))
    assert o1[1] == 0.0                 # a point of zero area contributes nothing once filtered
    assert torch.isfinite(s1).all() and torch.isfinite(o1).all()
    assert smooth(s, o, None) == (s, o)
    ls = torch.log(torch.tensor([[0.1, 0.2], [0.01, 0.03]], dtype=torch.float64)).requires_grad_()
    op = torch.tensor([0.5, 0.8], dtype=torch.float64, requires_grad=True)
    sig = torch.tensor([0.02, 0.05], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, b: smooth(a.exp(), b, sig), (ls, op))


def test_filter_sigma_from_the_finest_view():
    cs = cams()
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 300.0, 0.0]])
    sig = filter_sigma(pts, cs, 0.5, margin_frac=0.0)
    t = footprint(pts[:1], cs)[0]
    assert sig[0] == pytest.approx(0.5 * t, rel=1e-6)
    assert sig[1] == sig[0]             # unseen: the largest seen value
    assert (filter_sigma(pts, cs, 0.5, margin_frac=0.0, fallback="zero")[1]) == 0.0
    assert (filter_sigma(pts, cs, 0.0) == 0).all() and filter_sigma(pts, [], 1.0).sum() == 0


# ------------------------------------------------------------------ inside a run
def test_run_bakes_the_filter_into_its_field_and_resumes_it():
    from test_ggds_run import make_run
    run = make_run(steps=12, filter_3d=0.5)
    sigma = run.state.filter3d                  # from the initial surfels and training views
    assert sigma is not None and (sigma > 0).all()
    for _ in range(6):
        run.step()
    f = run.field()
    raw = P.activated(run.params)
    s, o = smooth(raw["scales"].detach(), raw["opacities"].detach(), sigma)
    np.testing.assert_allclose(f.scales, s.numpy(), rtol=1e-6)
    np.testing.assert_allclose(f.opacities, o.numpy(), rtol=1e-6)
    assert np.all(f.scales >= sigma.numpy()[:, None] * (1 - 1e-6))
    tensors, meta = run.checkpoint()
    from safetensors.torch import load, save
    tensors, meta = load(save(tensors)), json.loads(json.dumps(meta))
    with torch.no_grad():
        run.state.filter3d.mul_(3.0)
    run.restore(tensors, meta)
    np.testing.assert_allclose(run.field().scales, f.scales)


# ------------------------------------------------------------------ error-driven densification
def test_densify_moves_redundant_surfels_to_high_residual_within_the_budget():
    from lsd3d_usd.ggds.optim.adam import SelectiveAdam
    from lsd3d_usd.ggds.optim.strategy import MCMCStrategy
    n = 200
    rng = np.random.default_rng(4)
    pos = rng.normal(size=(n, 3)) * [10, 10, 0]
    scales = np.full((n, 2), 0.1)
    scales[:40] = 0.005                       # 40 tiny ones: redundant under a 0.05 m filter
    field = SurfelField(pos, np.tile([0, 0, 0, 1.0], (n, 1)), scales, np.full(n, 0.7),
                        rng.normal(size=(n, 4, 3)) * 0.1)
    params = P.to_params(field)
    opt = SelectiveAdam(params, {k: 0.01 for k in P.KEYS})
    strat = MCMCStrategy(relocate_every=10, noise_scale=0.0, densify_frac=0.1,
                         redundant_coef=0.25)
    resid = torch.full((n,), 0.01)
    resid[150:155] = 1.0                      # five surfels with a large residual
    strat.observe(torch.arange(n), resid, n)
    sigma = torch.full((n,), 0.05)
    coef = lambda: smooth(params["scales"].exp(), torch.ones(n), sigma)[1]  # noqa: E731
    info = strat.step_post_backward(params, opt, 10, 1e-3, torch.arange(n), filter_coef=coef)
    assert info["densified"] == 20            # densify_frac × n, all from the tiny ones
    donors, src = strat.last_relocation
    assert set(donors.tolist()) <= set(range(40))
    assert params["means"].shape[0] == n      # the budget: the count never changes
    # nearly all targets are the high-residual ones (residual 100x larger, same opacity)
    assert ((src >= 150) & (src < 155)).float().mean() > 0.8
    assert (src >= 40).all()                  # a redundant surfel is never a target
    # a split target and its copies share its area and sit on its plane
    s = params["scales"].exp().prod(1)
    for t in torch.unique(src):
        group = torch.cat([t[None], donors[src == t]])
        was = float(field.scales[int(t)].prod())
        assert abs(float(s[group].sum()) - was) < 1e-6
        np.testing.assert_allclose(params["means"][group][:, 2].numpy(), pos[int(t), 2], atol=1e-6)
    # without residuals or without a filter nothing is densified
    fresh = MCMCStrategy(relocate_every=10, noise_scale=0.0, densify_frac=0.1)
    assert fresh.step_post_backward(params, opt, 10, 1e-3, torch.arange(n),
                                    filter_coef=coef)["densified"] == 0
    strat2 = MCMCStrategy(relocate_every=10, noise_scale=0.0, densify_frac=0.1)
    strat2.observe(torch.arange(n), resid, n)
    assert strat2.step_post_backward(params, opt, 10, 1e-3, torch.arange(n))["densified"] == 0


def test_run_with_densification_resumes_exactly():
    from test_ggds_run import make_run

    from lsd3d_usd.ggds.settings import StrategyConfig

    def build():
        return make_run(steps=12, filter_3d=2.0,
                        strategy=StrategyConfig(relocate_every=10, densify_frac=0.05))
    a = build()
    for _ in range(12):
        a.step()
    assert sum(h["densified"] for h in a.history) > 0
    b = build()
    for _ in range(6):
        b.step()
    tensors, meta = b.checkpoint()
    from safetensors.torch import load, save
    tensors, meta = load(save(tensors)), json.loads(json.dumps(meta))
    c = build()
    c.restore(tensors, meta)
    for _ in range(6):
        c.step()
    for k in P.KEYS:
        torch.testing.assert_close(c.params[k], a.params[k], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(c.state.filter3d, a.state.filter3d)
    np.testing.assert_array_equal(c.state.face_index, a.state.face_index)
