"""The 2DGS depth-distortion output of the numba backend (RasterSettings(distortion=True)):
analytic cases, the float64 reference (forward and autograd gradients), finite differences,
degenerate surfels, and that asking for it leaves the other outputs and gradients alone."""
import pytest
import torch

from lsd3d_usd.render.reference import render_reference
from test_render_raster import _loss, _loss_weights, degenerate_params, rast, scene

NAMES = ("means", "quats", "scales", "opacities", "sh")
NEAR, FAR = 0.5, 50.0  # a depth range where m spreads over [0, 1) in the test scenes


def ndc(z, near=NEAR, far=FAR):
    return far / (far - near) * (1 - near / z)


def _flat(zs, ops, xy=None, w=16, h=12):
    """Fronto-parallel surfels (identity rotation) at depths zs, centred on pixel (8, 6)'s
    centre unless xy offsets are given, so the Gaussian there is exactly 1."""
    n = len(zs)
    z = torch.tensor(zs, dtype=torch.float64)
    means = torch.zeros(n, 3, dtype=torch.float64)
    means[:, 2] = z
    if xy is not None:
        means[:, :2] = torch.tensor(xy, dtype=torch.float64)
    quats = torch.tensor([[0.0, 0.0, 0.0, 1.0]]).repeat(n, 1)
    K = torch.tensor([[20.0, 0.0, 8.5], [0.0, 20.0, 6.5], [0.0, 0.0, 1.0]])
    return dict(means=means.float(), quats=quats, scales=torch.full((n, 2), 1.5),
                opacities=torch.tensor(ops), sh=torch.zeros(n, 1, 3), viewmat=torch.eye(4),
                K=K, width=w, height=h, near=NEAR, far=FAR)


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_two_surfels_analytic(order):
    a, b = (float(torch.tensor(v)) for v in (0.6, 0.7))  # the float32 opacities rendered
    z1, z2 = 2.0, 5.0
    zs, ops = [z1, z2], [a, b]
    s = _flat([zs[i] for i in order], [ops[i] for i in order])  # list order must not matter
    d = rast(s, distortion=True).distortion
    want = a * b * (1 - a) * (ndc(z1) - ndc(z2)) ** 2  # w1 = a, w2 = b (1 - a)
    assert d[6, 8].item() == pytest.approx(want, rel=1e-5)
    ref = render_reference(**s, distortion=True)["distortion"]
    assert ref[6, 8].item() == pytest.approx(want, rel=1e-12)
    assert (d.double() - ref).abs().max() < 1e-5 * want


def test_zero_for_one_surfel_and_for_equal_depths():
    one = rast(_flat([3.0], [0.8]), distortion=True)
    assert one.alpha.max() > 0.5
    assert (one.distortion == 0).all()
    # overlapping surfels at one depth, shifted sideways, different opacities
    same = _flat([3.0] * 4, [0.5, 0.9, 0.3, 1.0], xy=[[0, 0], [0.3, 0.1], [-0.2, 0.2], [0.1, -0.3]])
    out = rast(same, distortion=True)
    assert (out.alpha > 0.9).float().mean() > 0.3
    assert out.distortion.abs().max() < 1e-12
    assert render_reference(**same, distortion=True)["distortion"].abs().max() < 1e-15


@pytest.mark.parametrize("near,far", [(0.05, 1e4), (NEAR, FAR)])
def test_forward_matches_float64_reference(near, far):
    s, _, _ = scene(n=60, seed=3, w=48, h=40, deg=2)
    out = rast(s, near=near, far=far, distortion=True)
    ref = render_reference(**s, near=near, far=far, t_min=1e-4, distortion=True)
    d, rd = out.distortion.double(), ref["distortion"]
    assert out.distortion.dtype == torch.float32 and d.shape == (40, 48)
    assert (rd > 0.1 * rd.max()).float().mean() > 0.05  # the scene has layered pixels
    assert (d - rd).abs().max() < 1e-4 * rd.max(), ((d - rd).abs().max(), rd.max())
    # the other outputs are those of the default path, exactly
    plain = rast(s, near=near, far=far)
    assert plain.distortion is None
    for k in ("rgb", "alpha", "depth_expected", "depth_median", "normal"):
        assert torch.equal(getattr(plain, k), getattr(out, k)), k


def _dist_loss(out, wd, scale, wts=None):
    d = out["distortion"] if isinstance(out, dict) else out.distortion  # reference dict / RasterResult
    loss = (d.double() * wd).sum() * scale
    return loss if wts is None else loss + _loss(out, wts)


@pytest.mark.parametrize("seed,with_image", [(1, False), (2, False), (1, True)])
def test_gradients_match_reference_autograd(seed, with_image):
    s, _, _ = scene(n=20, seed=seed)
    s = {**s, "near": NEAR, "far": FAR}
    g = torch.Generator().manual_seed(seed + 100)
    wd = torch.randn(24, 32, generator=g, dtype=torch.float64)
    wts = _loss_weights(24, 32, seed) if with_image else None
    bg = torch.tensor([0.3, 0.2, 0.1])
    fast = {k: s[k].clone().requires_grad_(True) for k in NAMES}
    out = rast({**s, **fast}, background=bg, distortion=True)
    scale = 1.0 / out.distortion.abs().max().item()  # distortion and image terms comparable
    _dist_loss(out, wd, scale, wts).backward()
    ref = {k: s[k].double().clone().requires_grad_(True) for k in NAMES}
    _dist_loss(render_reference(**{**s, **ref}, background=bg, t_min=1e-4, distortion=True),
               wd, scale, wts).backward()
    for k in NAMES:
        ga, gb = fast[k].grad.double(), ref[k].grad
        assert torch.isfinite(ga).all()
        if k == "sh" and not with_image:
            assert ga.abs().max() == 0 and gb is None  # colour does not move depth
            continue
        rel = ((ga - gb).norm() / gb.norm()).item()
        assert rel < 2e-4, (k, rel)


def test_gradients_match_finite_differences_float64():
    """Directional central differences of the float64 reference's distortion vs the fast
    path's gradient (checks the reference's autograd is not the only witness)."""
    s, _, _ = scene(n=20, seed=4)
    s = {**s, "near": NEAR, "far": FAR}
    g = torch.Generator().manual_seed(5)
    wd = torch.randn(24, 32, generator=g, dtype=torch.float64)
    fast = {k: s[k].clone().requires_grad_(True) for k in NAMES[:4]}
    out = rast({**s, **fast}, distortion=True)
    scale = 1.0 / out.distortion.abs().max().item()
    _dist_loss(out, wd, scale).backward()
    base = {k: s[k].double() for k in NAMES[:4]}
    for k in NAMES[:4]:
        for _ in range(2):
            d = torch.randn(base[k].shape, generator=g, dtype=torch.float64)
            eps = 1e-6
            ls = [_dist_loss(render_reference(**{**s, **base, k: base[k] + sgn * eps * d},
                                              t_min=1e-4, distortion=True), wd, scale)
                  for sgn in (1, -1)]
            fd = ((ls[0] - ls[1]) / (2 * eps)).item()
            an = (fast[k].grad.double() * d).sum().item()
            assert abs(fd - an) <= 2e-3 * max(1.0, abs(fd)), (k, fd, an)


def test_zero_distortion_weight_leaves_the_other_gradients_unchanged():
    s, _, _ = scene(n=20, seed=7)
    wts = _loss_weights(24, 32, 7)
    grads = []
    for dist in (False, True):
        p = {k: s[k].clone().requires_grad_(True) for k in NAMES}
        out = rast({**s, **p}, distortion=dist)
        loss = _loss(out, wts) + (0.0 * out.distortion.sum() if dist else 0.0)
        loss.backward()
        grads.append([p[k].grad for k in NAMES])
    for k, a, b in zip(NAMES, *grads):
        assert torch.equal(a, b), k


def test_degenerate_surfels_give_finite_distortion_and_gradients():
    s, _, _ = scene(n=12, seed=6)
    p = degenerate_params(s)
    out = rast({**s, **p}, distortion=True)
    assert torch.isfinite(out.distortion).all() and (out.distortion >= 0).all()
    assert out.distortion.max() > 0
    (out.distortion.sum() / out.distortion.max().detach() + _loss(out, _loss_weights(24, 32, 3))).backward()
    for k, v in p.items():
        assert torch.isfinite(v.grad).all(), k
    ref = render_reference(**{**s, **{k: v.detach() for k, v in p.items()}}, t_min=1e-4,
                           distortion=True)["distortion"]
    assert (out.distortion.double() - ref).abs().max() < 1e-4 * ref.max()
