"""The numba kernel of ViewFit.add_view against a plain float64 reference of the same model."""
import numpy as np
import pytest
import torch

from lsd3d_usd.ggds.colour_start.worldfit import ViewFit
from lsd3d_usd.ggds.colour_start.kernels import summed_area
from lsd3d_usd.render.camera import Camera, look_at
from lsd3d_usd.render.sh import sh_basis


def reference_add_view(A, b, count, positions, scales, normals, camera, target, depth, *,
                       rel_tol=0.02, abs_tol=0.02, max_radius=4, min_weight=0.05, weight=1.0):
    """ViewFit's model surfel by surfel in float64, the box mean by explicit window sums."""
    H, W = depth.shape
    degree = int(round(np.sqrt(A.shape[1]))) - 1
    f = np.sqrt(camera.fx * camera.fy)
    seen = 0
    for n in range(len(positions)):
        p = positions[n].astype(np.float64)
        (u, v), z = camera.project(p[None])[0][0], camera.project(p[None])[1][0]
        if not (z > camera.near and 0 <= u < W and 0 <= v < H):
            continue
        i, j = int(np.floor(u)), int(np.floor(v))
        zd = depth[j, i]
        if not (np.isfinite(zd) and abs(z - zd) <= rel_tol * zd + abs_tol):
            continue
        d = p - camera.center
        d = d / np.linalg.norm(d)
        s = scales[n].astype(np.float64)
        cos = abs(float(normals[n].astype(np.float64) @ d))
        sigma_px = np.sqrt(s[0] * s[1]) * f / z
        w = max(np.pi * s[0] * s[1] * cos * f * f / z ** 2, min_weight) * weight
        r = int(np.clip(np.round(0.7 * sigma_px), 0, max_radius))
        win = target[max(j - r, 0):j + r + 1, max(i - r, 0):i + r + 1].astype(np.float64)
        col = win.reshape(-1, 3).mean(0)
        B = sh_basis(torch.from_numpy(d[None]), degree).numpy()[0]
        A[n] += w * np.outer(B, B)
        b[n] += w * np.outer(B, col - 0.5)
        count[n] += 1
        seen += 1
    return seen


def _scene(rng, n, degree):
    cam = Camera.from_fov(64, 48, 70.0, pose=look_at(np.array([0.0, -6.0, 3.0]), np.zeros(3)),
                          near=0.1, far=100.0)
    # the plane z = 0 as the view's depth, with a hole (inf) and a box in front (occluder)
    from lsd3d_usd.render.camera import pixel_rays
    o, d = pixel_rays(cam)
    t = -o[..., 2] / np.where(np.abs(d[..., 2]) > 1e-9, d[..., 2], np.nan)
    depth = np.where(t > 0, t * (d @ cam.pose[:3, 2]), np.inf)
    depth[:5, :] = np.inf
    depth[20:26, 30:40] *= 0.7
    pos = np.c_[rng.uniform(-4, 4, (n, 2)), rng.normal(0, 0.005, n)].astype(np.float32)
    pos[: n // 10, 2] = 0.8                                   # above the surface: occluded test
    scales = np.exp(rng.uniform(np.log(1e-3), np.log(0.3), (n, 2))).astype(np.float32)
    nrm = rng.normal(size=(n, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    target = rng.uniform(0, 1, (48, 64, 3)).astype(np.float32)
    return cam, depth, pos, scales, nrm, target


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_kernel_matches_float64_reference(degree):
    rng = np.random.default_rng(degree)
    cam, depth, pos, scales, nrm, target = _scene(rng, 3000, degree)
    fit = ViewFit(len(pos), degree)
    S = (degree + 1) ** 2
    A, b, count = np.zeros((len(pos), S, S)), np.zeros((len(pos), S, 3)), np.zeros(len(pos), int)
    for weight in (1.0, 0.25):   # accumulates across views, each view's samples weighted
        got = fit.add_view(pos, scales, nrm, cam, torch.from_numpy(target), depth, weight=weight)
        want = reference_add_view(A, b, count, pos, scales, nrm, cam, target, depth,
                                  weight=weight)
        assert got == want
    assert 0 < want < len(pos)                     # some seen, some not (off-image, occluded)
    np.testing.assert_array_equal(fit.count, count)
    np.testing.assert_allclose(fit.matrices(np.arange(len(pos))), A, rtol=1e-9, atol=1e-12)
    assert fit.A.shape == (len(pos), S * (S + 1) // 2)   # stored packed: the upper triangle
    np.testing.assert_allclose(fit.b, b, rtol=1e-9, atol=1e-12)
    assert fit.count[: len(pos) // 10].sum() == 0  # floating above the surface: never seen


def test_kernel_degenerate_views():
    rng = np.random.default_rng(0)
    cam, depth, pos, scales, nrm, target = _scene(rng, 200, 1)
    fit = ViewFit(len(pos), 1)
    assert fit.add_view(pos[:0], scales[:0], nrm[:0], cam, target, depth) == 0
    assert fit.add_view(pos, scales, nrm, cam, target, np.full_like(depth, np.inf)) == 0
    bad = pos.copy()
    bad[:, 0] = np.nan                                      # non-finite positions see nothing
    assert fit.add_view(bad, scales, nrm, cam, target, depth) == 0
    assert not fit.A.any() and not fit.count.any()
    with pytest.raises(ValueError, match="target"):
        fit.add_view(pos, scales, nrm, cam, target[:, :10], depth)


def test_summed_area_box_sums():
    img = np.random.default_rng(1).uniform(size=(7, 9, 3))
    T = summed_area(img)
    np.testing.assert_allclose(T[5, 7] - T[2, 7] - T[5, 3] + T[2, 3], img[2:5, 3:7].sum((0, 1)))
