"""What the training views see of each surfel (conditioning/visibility.py) against plain
per-camera projections."""

import numpy as np

from lsd3d_usd.conditioning.visibility import footprint, pick_views
from lsd3d_usd.render.camera import Camera, look_at

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
