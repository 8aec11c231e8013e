"""Fit-quality machinery of GGDS (issue 19): what the training views see of each surfel
(sampling.py), the 3D smoothing filter (antialias.py) and the view-dependent world-space start
(worldfit.py), each against a plain float64 computation, on degenerate inputs, and inside a
run (baked into the written field, restored by a resume)."""
import json

import numpy as np
import pytest
import torch

from lsd3d_usd.ggds.optim import params as P
from lsd3d_usd.ggds.optim.antialias import filter_sigma, smooth
from lsd3d_usd.conditioning.visibility import footprint, pick_views
from lsd3d_usd.ggds.colour_start.worldfit import disk_pattern, fit_sh, solve_sh
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.render.sh import sh_basis
from lsd3d_usd.splats.field import SurfelField


def cams():
    """Three cameras looking at the origin region from different distances and sides."""
    out = []
    for eye, w in (((0, -10, 2), 64), ((0, -3, 1.5), 64), ((12, 0, 3), 32)):
        out.append(Camera.from_fov(w, w * 3 // 4, 60.0, pose=look_at(np.array(eye, float),
                                                                      np.zeros(3)), near=0.1,
                                   far=100.0))
    return out


# ------------------------------------------------------------------ sampling
def test_footprint_matches_per_camera_projection():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-6, 6, (300, 3))
    pts[:5] = [0, 40, 0]            # behind the first two cameras, beside the third
    cs = cams()
    got = footprint(pts, cs)
    want = np.full(len(pts), np.inf)
    for c in cs:
        uv, z = c.project(pts)
        inside = (z >= c.near) & (z <= c.far) & (uv[:, 0] >= 0) & (uv[:, 0] <= c.width) \
            & (uv[:, 1] >= 0) & (uv[:, 1] <= c.height)
        want = np.minimum(want, np.where(inside, z / min(c.fx, c.fy), np.inf))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert np.isinf(got).any() and np.isfinite(got).any()
    assert footprint(np.zeros((0, 3)), cs).shape == (0,)
    assert np.isinf(footprint(pts[:3], [])).all()
    # a margin only ever adds views
    assert np.all(footprint(pts, cs, margin=20) <= got)


def test_project_matches_each_camera_with_margin_and_bad_points():
    from lsd3d_usd.conditioning.visibility import CameraSet, project
    rng = np.random.default_rng(3)
    pts = rng.uniform(-8, 8, (500, 3))
    pts[0] = np.nan                     # a non-finite point is in no view
    cs = cams()
    z, ok = project(pts, CameraSet.of(cs), margin=7.5)
    assert z.shape == ok.shape == (len(pts), len(cs))
    for m, c in enumerate(cs):
        uv, zc = c.project(pts)
        want = (zc >= c.near) & (zc <= c.far) & (uv[:, 0] >= -7.5) & (uv[:, 0] <= c.width + 7.5) \
            & (uv[:, 1] >= -7.5) & (uv[:, 1] <= c.height + 7.5)
        np.testing.assert_array_equal(ok[:, m], want)
        np.testing.assert_allclose(z[1:, m], zc[1:], rtol=1e-12)
    assert not ok[0].any() and ok.any() and not ok.all()


def test_pick_views_only_visible_cameras_weighted_by_pixel_density():
    cs = cams()
    rng = np.random.default_rng(1)
    p = np.array([[0.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, -200.0, 0.0]])
    idx = pick_views(p, cs, 4, rng)
    assert idx.shape == (3, 4)
    _, ok = zip(*(c.project(p[:1]) for c in cs))
    seen0 = {i for i, c in enumerate(cs) if 0 <= c.project(p[:1])[0][0, 0] <= c.width}
    assert set(idx[0]) <= seen0 and len(set(idx[0])) == len(seen0)
    assert (idx[2] == -1).all()          # behind every camera
    # Frequencies of the first pick follow (f/z)^2 over the cameras that see the point.
    first = np.array([pick_views(p[:1], cs, 1, rng)[0, 0] for _ in range(3000)])
    w = np.zeros(len(cs))
    for i in seen0:
        _, z = cs[i].project(p[:1])
        w[i] = cs[i].fx * cs[i].fy / z[0] ** 2
    freq = np.bincount(first, minlength=len(cs)) / len(first)
    np.testing.assert_allclose(freq, w / w.sum(), atol=0.03)


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


# ------------------------------------------------------------------ view-dependent start
def test_solve_sh_recovers_a_function_in_its_span_and_ridge_limits():
    rng = np.random.default_rng(2)
    for deg in (1, 2):
        S = (deg + 1) ** 2
        d = rng.normal(size=(5, 3 * S, 3))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        B = sh_basis(torch.from_numpy(d.reshape(-1, 3)), deg).numpy().reshape(5, 3 * S, S)
        x = rng.normal(size=(5, S, 3)) * 0.2
        c = 0.5 + np.einsum("nks,nsc->nkc", B, x)
        np.testing.assert_allclose(solve_sh(B, c, 0.0), x, atol=1e-8)
        # against a plain float64 least-squares solve with the ridge written out as rows
        lam = 0.3
        got = solve_sh(B, c, lam)
        K = B.shape[1]
        reg = np.sqrt(lam * K) * 0.28209479177387814 * np.eye(S)[1:]
        for i in range(5):
            A = np.vstack([B[i], reg])
            b = np.vstack([c[i] - 0.5, np.zeros((S - 1, 3))])
            np.testing.assert_allclose(got[i], np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-9)
    # Ridge in the surfel's frame: with no zonal ridge and a huge azimuthal one, a colour that
    # depends on the angle to the normal only is recovered exactly, the azimuthal part dropped.
    n = np.array([[0.0, 0.6, 0.8]])
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    B = sh_basis(torch.from_numpy(d), 2).numpy()[None]
    cos = d @ n[0]
    zonal = 0.4 + 0.2 * cos + 0.1 * (1.5 * cos ** 2 - 0.5)
    t = np.cross(n[0], [1.0, 0, 0])
    azim = 0.05 * (d @ t)
    got = solve_sh(B, np.repeat(zonal[None, :, None], 3, 2), 0.0, normals=n, ridge_tangent=1e9)
    np.testing.assert_allclose(0.5 + np.einsum("nks,nsc->nkc", B, got)[0, :, 0], zonal, atol=1e-6)
    got = solve_sh(B, np.repeat((zonal + azim)[None, :, None], 3, 2), 0.0, normals=n,
                   ridge_tangent=1e9)
    # the fit is a function of the angle to the normal: the same at every azimuth
    u = np.cross(n[0], t)
    ring = np.stack([0.6 * n[0] + 0.8 * (np.cos(a) * t + np.sin(a) * u) for a in np.linspace(0, 6, 7)])
    vals = 0.5 + sh_basis(torch.from_numpy(ring), 2).numpy() @ got[0, :, 0]
    assert np.ptp(vals) < 1e-6
    # One direction only, with a ridge: the DC term reproduces the colour seen, the rest is 0.
    B1 = sh_basis(torch.tensor([[0.0, 0.6, -0.8]]), 1).numpy()[None]
    x1 = solve_sh(np.repeat(B1, 4, 1), np.full((1, 4, 3), 0.3), 0.1)
    np.testing.assert_allclose(0.5 + 0.28209479177387814 * x1[0, 0], 0.3, atol=1e-9)
    np.testing.assert_allclose(x1[0, 1:], 0.0, atol=1e-9)


def test_pooled_solve_matches_one_big_least_squares():
    from lsd3d_usd.ggds.colour_start.worldfit import cell_ids, ridge_matrix, solve_sh_pooled
    rng = np.random.default_rng(6)
    N, K, S = 7, 5, 4
    d = rng.normal(size=(N, K, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    B = sh_basis(torch.from_numpy(d.reshape(-1, 3)), 1).numpy().reshape(N, K, S)
    c = rng.uniform(0, 1, (N, K, 3))
    groups = np.array([0, 0, 0, 1, 1, 2, 2])
    nrm = rng.normal(size=(N, 3))
    got = solve_sh_pooled(B, c, groups, nrm, 0.05, 2.0)
    # Reference: unknowns [x0_0..x0_6, y_0 (3), y_1 (3), y_2 (3)], one row per sample plus
    # ridge rows sqrt(cnt K C0² Λ_g) on each group's y.
    G = 3
    rows, rhs = [], []
    for i in range(N):
        for k in range(K):
            r = np.zeros(N + G * (S - 1))
            r[i] = B[i, k, 0]
            r[N + groups[i] * (S - 1): N + (groups[i] + 1) * (S - 1)] = B[i, k, 1:]
            rows.append(r)
            rhs.append(c[i, k] - 0.5)
    for g in range(G):
        m = groups == g
        lam = ridge_matrix(nrm[m].sum(0)[None], 1, 0.05, 2.0)[0, 1:, 1:] * m.sum() * K * 0.28209479177387814 ** 2
        w, v = np.linalg.eigh(lam)
        L = (v * np.sqrt(np.maximum(w, 0))).T
        for r_ in L:
            r = np.zeros(N + G * (S - 1))
            r[N + g * (S - 1): N + (g + 1) * (S - 1)] = r_
            rows.append(r)
            rhs.append(np.zeros(3))
    sol = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    np.testing.assert_allclose(got[:, 0], sol[:N], atol=1e-8)
    for i in range(N):
        g = groups[i]
        np.testing.assert_allclose(got[i, 1:], sol[N + g * (S - 1): N + (g + 1) * (S - 1)], atol=1e-8)
    # groups: same cell, class and normal axis/sign
    pos = np.array([[0.1, 0.1, 0], [0.9, 0.2, 0], [1.1, 0.1, 0], [0.2, 0.2, 0], [0.3, 0.1, 0]])
    nr = np.array([[0, 0, 1.0], [0, 0, 1], [0, 0, 1], [0, 0, -1], [0, 0, 1]])
    ids = cell_ids(pos, nr, np.array([1, 1, 1, 1, 2]), 1.0)
    assert ids[0] == ids[1] and len(set(ids.tolist())) == 4


class ViewDependentPrior:
    """shade_at: grey 0.3 + 0.4 × the view direction's z (linear in d: SH degree 1 exact)."""

    def shade_at(self, points, normals, semantic, env, view_dirs=None, sun_visibility=None):
        d = torch.as_tensor(view_dirs, dtype=torch.float64)
        d = d / d.norm(dim=1, keepdim=True)
        return (0.3 + 0.4 * d[:, 2:3]).expand(-1, 3).float()


def test_fit_sh_recovers_view_dependent_colour():
    rng = np.random.default_rng(3)
    n = 50
    field = SurfelField(rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                        np.tile([0, 0, 0, 1.0], (n, 1)).astype(np.float32),
                        np.full((n, 2), 1e-4, np.float32), np.full(n, 0.8, np.float32),
                        np.zeros((n, 4, 3), np.float32), semantic_ids=np.zeros(n, np.int32))
    cs = cams()
    for sh in (fit_sh(ViewDependentPrior(), None, field, cs, degree=1, samples=6, ridge=0.0),
               fit_sh(ViewDependentPrior(), None, field, cs, degree=1, samples=3, ridge=0.0,
                      ridge_tangent=0.0, cell=1.0)):
        _check_colour_per_camera(field, sh, cs)
    assert fit_sh(ViewDependentPrior(), None, SurfelField.concat([field]).subset(np.arange(0)),
                  cs, degree=1).shape == (0, 4, 3)
    no_sem = SurfelField(field.positions, field.orientations, field.scales, field.opacities, field.sh)
    assert fit_sh(ViewDependentPrior(), None, no_sem, cs, degree=1) is None


def _check_colour_per_camera(field, sh, cs):
    for c in cs:
        d = field.positions.astype(np.float64) - c.center
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        _, seen = c.project(field.positions)
        col = 0.5 + np.einsum("ns,nsc->nc", sh_basis(torch.from_numpy(d), 1).numpy(), sh)
        # every surfel every camera sees gets its colour from that direction
        uv, z = c.project(field.positions)
        vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= c.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= c.height)
        np.testing.assert_allclose(col[vis, 0], 0.3 + 0.4 * d[vis, 2], atol=2e-3)


def test_disk_pattern_fills_the_disk():
    p = disk_pattern(16, 0.7)
    r = np.linalg.norm(p, axis=1)
    assert r.max() <= 0.7 + 1e-12 and abs(p.mean(0)).max() < 0.1


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


# ------------------------------------------------------------------ off-lane training views
def test_displaced_views_cover_eval_novel_positions_in_the_given_proportion():
    from lsd3d_usd.conditioning.views import sample_views
    from lsd3d_usd.layout.model import Building, LaneCenter, Layout
    lay = Layout(lanes=[LaneCenter(id="l0", points=[[0, 0, 0], [60, 0, 0]])],
                 buildings=[Building(id="b0", footprint=np.array(
                     [[10, 3], [50, 3], [50, 20], [10, 20], [10, 3]], float))])
    for frac in (0.0, 0.3, 1.0):
        views = sample_views(lay, 40, 32, 24, seed=1, novel_frac=frac, novel_style="displaced")
        novel = [v for v in views if v.kind == "novel"]
        assert len(novel) == round(40 * frac)
    views = sample_views(lay, 200, 32, 24, seed=2, novel_frac=1.0, novel_style="displaced",
                         novel_max_m=8.0)
    d = np.array([v.offset_m for v in views])
    assert d.min() >= 0.5 and d.max() <= 8.0 and np.median(d) < 3.0   # log-uniform: 2 m median
    c = np.array([v.camera.center for v in views])
    # within d of a lane view (|y| <= 3 sd of jitter, eye 1.6 m), never in the building
    assert np.all(np.abs(c[:, 1]) <= d + 1.5 + 1e-9)
    assert np.all((c[:, 2] >= 1.6 - 0.5 - 1e-9) & (c[:, 2] <= 1.6 + 0.25 * d + 1e-9))
    inside = (c[:, 0] > 10) & (c[:, 0] < 50) & (c[:, 1] > 3) & (c[:, 1] < 20)
    assert not inside.any()
    assert (c[:, 1] > 3).any()          # but they do leave the road beside it
    from lsd3d_usd.errors import InputError
    with pytest.raises(InputError, match="novel_style"):
        sample_views(lay, 3, 32, 24, novel_style="nope")


def _plane_view(cam):
    """Depth of the plane z = 0 seen by cam and a target whose colour is 0.3 + 0.4·(ray z)."""
    from lsd3d_usd.render.camera import pixel_rays
    o, d = pixel_rays(cam)
    t = -o[..., 2] / np.where(np.abs(d[..., 2]) > 1e-9, d[..., 2], np.nan)
    fwd = cam.pose[:3, 2]
    depth = np.where(t > 0, t * (d @ fwd), np.inf)
    target = np.repeat((0.3 + 0.4 * d[..., 2])[..., None], 3, axis=2)
    return depth, target


def test_view_fit_recovers_direction_dependent_targets_and_skips_occluded():
    from lsd3d_usd.ggds.colour_start.worldfit import ViewFit
    rng = np.random.default_rng(7)
    n = 60
    pos = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    scales = np.full((n, 2), 1e-3)
    cs = [Camera.from_fov(400, 300, 60.0, pose=look_at(np.array(e, float), np.zeros(3)),
                          near=0.1, far=100.0)
          for e in ((0, -6, 2), (0, -3, 1.5), (5, 0, 3), (-4, 3, 2.5))]
    fit = ViewFit(n + 1, 1)
    allpos = np.vstack([pos, [[0.0, 0.0, 0.5]]])       # the last one floats above the plane
    for c in cs:
        depth, target = _plane_view(c)
        fit.add_view(allpos, np.vstack([scales, scales[:1]]), np.vstack([nrm, nrm[:1]]), c,
                     target, depth, max_radius=0)
    sh, seen = fit.solve(np.vstack([nrm, nrm[:1]]), 0.0, 0.0)
    assert not seen[-1] and fit.count[-1] == 0          # never on the visible surface
    assert seen[:-1].all()
    for c in cs:
        d = pos - c.center
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        col = 0.5 + np.einsum("ns,nsc->nc", sh_basis(torch.from_numpy(d), 1).numpy(), sh[:-1])
        uv, _ = c.project(pos)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        # where the camera saw it, the fit gives its colour (pixel-centre quantisation of the
        # direction: about 1e-3 at 400 px)
        np.testing.assert_allclose(col[inside, 0], 0.3 + 0.4 * d[inside, 2], atol=5e-3)


def _zonal_fit(cos_rows, colour, rng):
    """A ViewFit over ground surfels (normal +z) whose samples look down at the given |cos|
    values (one row per surfel, random azimuths), with colours from ``colour(|cos|)``."""
    from lsd3d_usd.ggds.colour_start.worldfit import ViewFit
    fit = ViewFit(len(cos_rows), 1)
    for i, cs in enumerate(cos_rows):
        cs = np.asarray(cs, np.float64)
        az = rng.uniform(0, 2 * np.pi, len(cs))
        s = np.sqrt(1 - cs ** 2)
        d = np.stack([s * np.cos(az), s * np.sin(az), -cs], 1)
        B = sh_basis(torch.from_numpy(d), 1).numpy()
        c = np.repeat(colour(cs)[:, None], 3, 1)
        fit.A[i] = B.T @ B
        fit.b[i] = B.T @ (c - 0.5)
        fit.count[i] = len(cs)
    return fit


def test_view_fit_zonal_prior_borrows_the_slope_of_well_seen_peers():
    """A surfel seen at one angle only cannot tell its slope with the angle from its DC term:
    towards zero it keeps its grazing colour from a steep view, towards its group's median
    slope it dims as its well-seen peers do; the well-seen ones barely move."""
    from lsd3d_usd.ggds.colour_start.worldfit import (facing_ids, zonal_directions, zonal_slopes)
    rng = np.random.default_rng(3)
    colour = lambda cs: 0.62 - 0.5 * cs          # road sheen: brighter at grazing angles
    rows = [rng.uniform(0.03, 0.6, 12) for _ in range(40)] + [np.full(12, 0.08)]
    fit = _zonal_fit(rows, colour, rng)
    nrm = np.tile([0.0, 0.0, 1.0], (len(rows), 1))
    groups = facing_ids(nrm, np.full(len(rows), 3))
    plain, _ = fit.solve(nrm, 0.003, 1.0)
    table = zonal_slopes([(fit, nrm, groups)], 0.003, 1.0)
    prior, seen = fit.solve(nrm, 0.003, 1.0, slopes=(groups, table))
    assert seen.all()
    steep = np.array([[0.3, 0.0, -np.sqrt(1 - 0.09)]])              # |cos| 0.95
    B = sh_basis(torch.from_numpy(steep), 1).numpy()[0]
    truth = colour(np.array([0.95]))[0]
    assert abs(0.5 + B @ plain[-1, :, 0] - truth) > 0.3             # stays at its grazing 0.58
    assert abs(0.5 + B @ prior[-1, :, 0] - truth) < 0.03
    # its zonal coefficient is the group's median (of the first, plain solve)
    U = zonal_directions(nrm, 1)[:, 1:4]
    z = np.einsum("ns,ns->n", U, plain[:, 1:4, 0].astype(np.float64))
    assert abs(U[-1] @ prior[-1, 1:4, 0] - np.median(z[:-1])) < 1e-3
    # the well-seen ones' colours over the angles they were seen at stay as close to the truth
    cs = np.linspace(0.03, 0.6, 8)
    d = np.stack([np.sqrt(1 - cs ** 2), 0 * cs, -cs], 1)
    Bs = sh_basis(torch.from_numpy(d), 1).numpy()
    err = lambda x: np.abs(0.5 + Bs @ x[:-1, :, 0].T - colour(cs)[:, None]).max()
    assert err(prior) <= err(plain) + 1e-3 and err(prior) < 0.02
    # the grazing colour it was seen at is kept either way
    g = np.array([[0.0, np.sqrt(1 - 0.0064), -0.08]])
    Bg = sh_basis(torch.from_numpy(g), 1).numpy()[0]
    assert abs(0.5 + Bg @ prior[-1, :, 0] - colour(np.array([0.08]))[0]) < 0.01


def test_view_fit_zonal_prior_against_a_plain_least_squares():
    """The second solve is ridge regression centred on the group's slope: the same as one
    float64 least squares with ridge rows sqrt(w·Λ)(x − mean); groups too small to trust
    (fewer than min_members well-seen surfels) keep the plain solve."""
    from lsd3d_usd.ggds.colour_start.worldfit import (ridge_matrix, zonal_directions, zonal_slopes)
    rng = np.random.default_rng(5)
    nrm = rng.normal(size=(30, 3)) * 0.05 + [0.0, 0.0, 1.0]
    colour = lambda cs: 0.5 - 0.3 * cs
    rows = [rng.uniform(0.05, 0.7, 10) for _ in range(29)] + [np.full(10, 0.2)]
    fit = _zonal_fit(rows, colour, rng)
    groups = np.zeros(30, np.int64)
    groups[:3] = -1                              # unlabelled: no group, the plain ridge
    plain, _ = fit.solve(nrm, 0.01, 0.5)
    table = zonal_slopes([(fit, nrm, groups)], 0.01, 0.5, min_members=5)
    got, _ = fit.solve(nrm, 0.01, 0.5, slopes=(groups, table))
    U = zonal_directions(nrm, 1)
    w = fit.A[:, 0, 0]
    info = (np.einsum("ns,nst,nt->n", U, fit.A, U)
            - np.einsum("ns,ns->n", U, fit.A[:, :, 0]) ** 2 / w)
    good = (info / (info + 0.01 * w) >= 0.8) & (groups == 0)
    assert 5 <= good.sum() < 27
    zbar = np.median(np.einsum("ns,nsc->nc", U, plain.astype(np.float64))[good], axis=0)
    np.testing.assert_allclose(table[0, 0], zbar, atol=1e-6)
    np.testing.assert_array_equal(got[:3], plain[:3])
    for i in range(3, 30):
        lam = w[i] * ridge_matrix(nrm[i:i + 1], 1, 0.01, 0.5)[0]
        ev, V = np.linalg.eigh(lam)
        L = (V * np.sqrt(np.maximum(ev, 0))).T
        # rows: data (A = MᵀM, b = Mᵀy) and the ridge about U_i·zbar
        M = np.linalg.cholesky(fit.A[i] + 1e-12 * np.eye(4)).T
        y = np.linalg.solve(M.T, fit.b[i])
        mean = U[i][:, None] * zbar[None, :]
        ref = np.linalg.lstsq(np.vstack([M, L]), np.vstack([y, L @ mean]), rcond=None)[0]
        np.testing.assert_allclose(got[i], ref, atol=2e-5)
    few = zonal_slopes([(fit, nrm, groups)], 0.01, 0.5, min_members=28)
    assert not few.any()
    np.testing.assert_array_equal(fit.solve(nrm, 0.01, 0.5, slopes=(groups, few))[0], plain)
