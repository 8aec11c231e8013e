import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from lsd3d_usd.errors import InputError
from lsd3d_usd.render.camera import Camera, look_at, pixel_rays
from lsd3d_usd.render.gbuffer import render_gbuffer


def reference_gbuffer(V, F, cam):
    """Plain float64 per-pixel ray-triangle intersection (Moller-Trumbore), nearest hit
    with camera depth in [near, far]; returns (depth with inf, face index with -1)."""
    o, d = pixel_rays(cam)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    fwd = cam.pose[:3, 2]
    best = np.full(len(d), np.inf)
    fid = np.full(len(d), -1)
    for f, (a, b, c) in enumerate(V[F]):
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = p @ e1
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - a
            u = np.einsum("ij,ij->i", s, p) * inv
            q = np.cross(s, e1)
            v = np.einsum("ij,ij->i", d, q) * inv
            t = (q @ e2) * inv
        z = t * (d @ fwd)
        ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (z >= cam.near) & (z <= cam.far)
        closer = ok & (z < best)
        best[closer] = z[closer]
        fid[closer] = f
    return best.reshape(cam.height, cam.width), fid.reshape(cam.height, cam.width)


def _compare(V, F, cam, ids=None):
    g = render_gbuffer(V, F, cam, ids)
    zr, fr = reference_gbuffer(V, F, cam)
    assert np.array_equal(g.mask, fr >= 0), f"{np.sum(g.mask != (fr >= 0))} pixels differ in coverage"
    m = g.mask
    np.testing.assert_allclose(g.depth[m], zr[m], rtol=1e-4)
    assert np.all(np.isinf(g.depth[~m]))
    return g, zr, fr


def test_random_triangles_match_ray_tracing_reference():
    rng = np.random.default_rng(0)
    cam = Camera.from_fov(64, 48, 70.0, look_at([0, -10, 3], [0, 0, 1]), near=0.5, far=100)
    centres = rng.uniform([-5, -3, -1], [5, 8, 4], (40, 1, 3))
    V = (centres + rng.normal(scale=1.5, size=(40, 3, 3))).reshape(-1, 3)
    F = np.arange(120).reshape(40, 3)
    ids = rng.integers(0, 12, 40)
    g, zr, fr = _compare(V, F, cam, ids)
    m = g.mask
    assert m.mean() > 0.2  # the scene actually covers the image
    # Faces agree except where two faces are at equal depth within float noise.
    assert np.mean(g.face_index[m] == fr[m]) > 0.999
    assert np.array_equal(g.semantic[m], ids[g.face_index[m]])
    n_ref = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n_ref /= np.linalg.norm(n_ref, axis=1, keepdims=True)
    np.testing.assert_allclose(g.normal[m], n_ref[g.face_index[m]], atol=1e-6)
    # positions lie on their face's plane and re-project to their pixel
    a = V[F[g.face_index[m], 0]]
    dist = np.einsum("ij,ij->i", g.position[m] - a, n_ref[g.face_index[m]])
    assert np.abs(dist).max() < 1e-9
    uv, z = cam.project(g.position[m])
    jj, ii = np.nonzero(m)
    np.testing.assert_allclose(uv, np.stack([ii + 0.5, jj + 0.5], 1), atol=1e-8)


@pytest.mark.parametrize("V", [
    np.array([[-3, 1, -5], [3, 1, -5], [0, 1, 20.0]]),   # one vertex in front: clipped to a triangle
    np.array([[-3, 1, 8], [3, 1, 8], [0, 1, -5.0]]),     # two in front: clipped to a quad
], ids=["one-in-front", "two-in-front"])
def test_triangle_crossing_near_plane_is_clipped_not_dropped(V):
    cam = Camera(40, 30, 30.0, 30.0, 20.0, 15.0, np.eye(4), near=1.0, far=50.0)  # looks down +z
    F = np.array([[0, 1, 2]])
    g, zr, _ = _compare(V, F, cam)
    assert g.mask.sum() > 20
    assert g.depth[g.mask].min() >= 1.0


def test_behind_camera_and_beyond_far_cover_nothing():
    cam = Camera(20, 20, 20.0, 20.0, 10.0, 10.0, np.eye(4), near=0.1, far=10.0)
    V = np.array([[-1, -1, -2], [1, -1, -2], [0, 1, -2], [-1, -1, 20], [1, -1, 20], [0, 1, 20]], float)
    g = render_gbuffer(V, np.array([[0, 1, 2], [3, 4, 5]]), cam)
    assert not g.mask.any()
    assert np.all(np.isnan(g.position)) and np.all(g.semantic == -1)


def test_edge_on_and_degenerate_triangles_cover_nothing():
    cam = Camera(20, 20, 20.0, 20.0, 10.0, 10.0, np.eye(4))
    V = np.array([[0, -1, 1], [0, 1, 1], [0, 0, 5],     # in the plane x=0 through the eye: edge-on
                  [1, 1, 3], [1, 1, 3], [2, 2, 3]], float)  # repeated vertex
    g = render_gbuffer(V, np.array([[0, 1, 2], [3, 4, 5]]), cam)
    assert not g.mask.any()


def test_occlusion_and_far_from_origin():
    # Two parallel quads 10 km from the origin; the nearer must win everywhere it covers.
    off = np.array([10000.0, -7000.0, 50.0])
    pose = look_at(off + [0, -5, 0], off, up=[0, 0, 1])
    cam = Camera.from_fov(32, 32, 60.0, pose, near=0.1, far=100)
    quad = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], float)
    V = np.vstack([quad * 3 + off + [0, 2, 0], quad + off])
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    g, zr, fr = _compare(V, F, cam)
    centre = g.face_index[12:20, 12:20]
    assert np.all(centre >= 2)
    np.testing.assert_allclose(g.depth[16, 16], 5.0, rtol=1e-6)


def test_bad_input():
    cam = Camera(4, 4, 4.0, 4.0, 2.0, 2.0)
    with pytest.raises(InputError, match="NaN"):
        render_gbuffer(np.full((3, 3), np.nan), np.array([[0, 1, 2]]), cam)
    with pytest.raises(InputError, match="out of range"):
        render_gbuffer(np.zeros((3, 3)), np.array([[0, 1, 3]]), cam)
