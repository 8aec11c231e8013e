"""The world-space colour start (ggds/colour_start/worldfit.py): the SH solves against plain
float64 least squares, the 3D fit of unseen surfels, ViewFit on direction-dependent targets
and occlusion, and the zonal prior."""

import numpy as np
import torch

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


def plane_view(cam):
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
        depth, target = plane_view(c)
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
        fit.A[i] = (B.T @ B)[np.triu_indices(4)]    # packed: the upper triangle
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
    A = fit.matrices(np.arange(30))
    w = A[:, 0, 0]
    info = (np.einsum("ns,nst,nt->n", U, A, U)
            - np.einsum("ns,ns->n", U, A[:, :, 0]) ** 2 / w)
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
        M = np.linalg.cholesky(A[i] + 1e-12 * np.eye(4)).T
        y = np.linalg.solve(M.T, fit.b[i])
        mean = U[i][:, None] * zbar[None, :]
        ref = np.linalg.lstsq(np.vstack([M, L]), np.vstack([y, L @ mean]), rcond=None)[0]
        np.testing.assert_allclose(got[i], ref, atol=2e-5)
    few = zonal_slopes([(fit, nrm, groups)], 0.01, 0.5, min_members=28)
    assert not few.any()
    np.testing.assert_array_equal(fit.solve(nrm, 0.01, 0.5, slopes=(groups, few))[0], plain)
