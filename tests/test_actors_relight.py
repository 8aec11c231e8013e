"""Actor relighting and the per-frame composite against plain float64 references: shadow rays
(Occluder), actors placed and lit (SceneReader.actors_at), the env background and the
composite's depth-order rule, including the degenerate cases (no occluder, no actors, an
actor behind the camera, the sun below the horizon)."""
from __future__ import annotations

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from pxr import Usd

from lsd3d_usd.actors.assets import MeshData, vehicle_meshes
from lsd3d_usd.actors.relight import Lighting, Occluder, actor_sample_points, default_lighting
from lsd3d_usd.actors.usdio import PlacedActor
from lsd3d_usd.render.camera import Camera, pixel_directions
from lsd3d_usd.render.gbuffer import render_gbuffer
from lsd3d_usd.views import frame
from lsd3d_usd.views import stage_data
from lsd3d_usd.views.stage_data import ActorFrame, EnvMap, SceneReader


# ---------------------------------------------------------------- plain references
_GRIDS: dict = {}


def _ref_grid(tri, cell):
    key = (tri.tobytes(), cell)
    if key not in _GRIDS:
        grid = {}
        lo = np.floor(tri[..., :2].min(1) / cell).astype(int)
        hi = np.floor(tri[..., :2].max(1) / cell).astype(int)
        for f in range(len(tri)):
            for i in range(lo[f, 0], hi[f, 0] + 1):
                for j in range(lo[f, 1], hi[f, 1] + 1):
                    grid.setdefault((i, j), []).append(f)
        _GRIDS[key] = grid
    return _GRIDS[key]


def _ref_hit(tri, cell, o, d, tmax=500.0):
    """One shadow ray, the obvious way: candidate triangles from a dict grid, Moller-Trumbore
    over all of them with numpy (the computation Occluder did before it was compiled)."""
    grid = _ref_grid(tri, cell)
    d = np.asarray(d, float) / np.linalg.norm(d)
    if not len(tri):
        return False
    if d[2] > 1e-9:
        tmax = min(tmax, max(0.0, (tri[..., 2].max() - o[2]) / d[2]))
    n = max(2, int(np.ceil(tmax * np.linalg.norm(d[:2]) / (0.5 * cell))) + 1)
    cells = set()
    for p in o[None, :2] + np.linspace(0.0, tmax, n)[:, None] * d[None, :2]:
        ci, cj = int(np.floor(p[0] / cell)), int(np.floor(p[1] / cell))
        cells |= {(ci + a, cj + b) for a in (-1, 0, 1) for b in (-1, 0, 1)}
    idx = sorted({f for c in cells for f in grid.get(c, [])})
    if not idx:
        return False
    T = tri[idx]
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - T[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    return bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-4) & (t < tmax)))


def _ref_visibility(tri, cell, points, s):
    if s[2] <= 0:
        return 0.0
    return float(np.mean([not _ref_hit(tri, cell, p, s) for p in points]))


def _random_triangles(rng, n, spread=40.0):
    c = rng.uniform(-spread, spread, (n, 1, 3))
    c[..., 2] = rng.uniform(0.0, 12.0, (n, 1))
    return c + rng.normal(0.0, 2.5, (n, 3, 3))


# ---------------------------------------------------------------- shadow rays
def test_shadow_rays_match_the_plain_reference():
    rng = np.random.default_rng(3)
    tri = _random_triangles(rng, 600)
    tri[0] = [[-200, -200, 0.0], [200, -200, 0.0], [0, 300, 0.0]]   # one triangle over many cells
    occ = Occluder(tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3), cell=8.0)
    o = rng.uniform(-50, 50, (300, 3))
    o[:, 2] = rng.uniform(-2.0, 14.0, 300)
    d = rng.normal(size=(300, 3))
    d[:40, 2] = np.abs(d[:40, 2]) + 2.0            # steep rising rays: cut at the tallest triangle
    d[40:60, :2] = 0.0                             # straight up / down: one cell
    got = occ.hits(o, d)
    ref = np.array([_ref_hit(occ.tri, 8.0, a, b) for a, b in zip(o, d)])
    assert 0.2 < ref.mean() < 0.8                  # both outcomes are exercised
    np.testing.assert_array_equal(got, ref)
    assert [occ.hit(a, b) for a, b in zip(o[:20], d[:20])] == list(ref[:20])
    # a short tmax: hits beyond it do not count
    np.testing.assert_array_equal(occ.hits(o, d, tmax=3.0),
                                  [_ref_hit(occ.tri, 8.0, a, b, 3.0) for a, b in zip(o, d)])


def test_visibility_per_actor_and_degenerate_cases():
    rng = np.random.default_rng(4)
    tri = _random_triangles(rng, 300, spread=25.0)
    occ = Occluder(tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3))
    pts = rng.uniform(-30, 30, (12, 5, 3))
    pts[..., 2] = rng.uniform(0.0, 6.0, (12, 5))
    sun = np.array([0.4, -0.3, 0.8])
    got = occ.visibility_many(pts, sun)
    ref = [_ref_visibility(occ.tri, 8.0, p, sun) for p in pts]
    np.testing.assert_array_equal(got, ref)
    assert len(set(ref)) > 2
    assert occ.visibility(pts[3], sun) == ref[3]
    # the sun below (or on) the horizon: nothing sees it
    np.testing.assert_array_equal(occ.visibility_many(pts, [0.5, 0.2, -0.1]), np.zeros(12))
    assert occ.visibility(pts[0], [1.0, 0.0, 0.0]) == 0.0
    # no occluder: everything sees the sun; no rays: an empty answer
    empty = Occluder(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    np.testing.assert_array_equal(empty.visibility_many(pts, sun), np.ones(12))
    assert not empty.hit([0, 0, 0], [0, 0, 1]) and occ.hits(np.zeros((0, 3)), sun).shape == (0,)


# ---------------------------------------------------------------- actors placed and lit
class _Actors:
    """An actor set (the interface SceneReader uses: ActorSet, sim.scene.SimActors)."""

    def __init__(self, actors, poses, shown, parts):
        self.actors, self.poses, self.shown, self.parts = actors, poses, shown, parts

    def __len__(self):
        return len(self.actors)

    def transforms(self, t):
        return self.poses[_step(t)]

    def visible(self, t):
        return self.shown

    def part_transforms(self, q, t):
        return self.parts[_step(t)].get(q, [])


def _step(t):
    return int(t.GetValue() if hasattr(t, "GetValue") else t)


def _pose(x, y, yaw, z=0.0):
    M = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    M[:2, :2] = [[c, -s], [s, c]]
    M[:3, 3] = (x, y, z)
    return M


def _ref_actors(actors, light: Lighting, occ: Occluder, t) -> ActorFrame:
    """The actors placed and lit mesh by mesh (float64), as SceneReader did per actor."""
    vs, fs, cs, fa, n = [], [], [], [], 0
    for q, (a, M, shown) in enumerate(zip(actors.actors, actors.transforms(t), actors.shown)):
        if not shown:
            continue
        V = _ref_visibility(occ.tri, occ.cell, actor_sample_points(M, a.dims), light.sun_dir)
        parts = dict((mi, part @ W[:3, :3].T + W[:3, 3])
                     for (mi, _, part), W in zip(a.animated, actors.part_transforms(q, t)))
        for mi, m in enumerate(a.meshes):
            v = parts[mi] if mi in parts else m.vertices @ M[:3, :3].T + M[:3, 3]
            tri = v[m.faces]
            nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            vs.append(v)
            fs.append(m.faces + n)
            cs.append(m.colors.astype(np.float64) * light.irradiance(nrm, V) / light.reference)
            fa.append(np.full(len(m.faces), q))
            n += len(v)
    return ActorFrame(np.concatenate(vs), np.concatenate(fs), np.concatenate(cs), None,
                      np.concatenate(fa))


@pytest.mark.parametrize("sun_z", [0.8, -0.2])
def test_actors_placed_and_lit_match_the_plain_reference(sun_z):
    car = vehicle_meshes("car")
    wheel = MeshData("wheel", car[0].vertices * 0.3, car[0].faces, car[0].colors)
    walker = PlacedActor("/A/walker", "moving", [car[1], wheel], None, np.array([0.6, 0.5, 1.8]),
                         animated=[(1, "/A/walker/leg", wheel.vertices + [0.0, 0.0, 0.4])])
    actors = [PlacedActor(f"/A/car{i}", "moving", car, None, np.array([4.5, 1.8, 1.5]))
              for i in range(4)]
    actors += [walker, PlacedActor("/A/empty", "parked", [], None, np.array([1.0, 1.0, 1.0]))]
    rng = np.random.default_rng(5)
    poses = [[_pose(*rng.uniform(-20, 20, 2), rng.uniform(0, 6.3)) for _ in actors] for _ in range(3)]
    # under the roof (in shadow), in the open, at the roof's edge (partly shadowed)
    poses[0][:3] = [_pose(0.0, 10.0, 0.0), _pose(30.0, -20.0, 0.5), _pose(8.5, 10.0, 0.0)]
    poses[2][:4] = poses[1][:4]                    # some actors stand still: the cached answer
    parts = [{4: [_pose(*poses[k][4][:2, 3], 0.3 * k, z=0.2)]} for k in range(3)]
    shown = [True, True, False, True, True, True]
    reader = SceneReader(Usd.Stage.CreateInMemory(), use_env=False, actors=False)
    reader.actors = _Actors(actors, poses, shown, parts)
    # a roof over part of the street casts the shadows
    roof = np.array([[-30, -5, 4.0], [10, -5, 4.0], [10, 30, 4.0], [-30, 30, 4.0]])
    occ = Occluder(np.vstack([roof, _random_triangles(rng, 40, 20.0).reshape(-1, 3)]),
                   np.vstack([[[0, 1, 2], [0, 2, 3]], 4 + np.arange(120).reshape(-1, 3)]))
    base = default_lighting()
    sun = np.array([0.3, 0.2, sun_z]) / np.linalg.norm([0.3, 0.2, sun_z])
    light = Lighting(base.sh, sun, np.full(3, 0.7), base.sun_residual)
    seen = [_ref_visibility(occ.tri, occ.cell, actor_sample_points(M, a.dims), sun)
            for a, M in zip(actors, poses[0])]
    if sun_z > 0:
        assert seen[0] == 0.0 and seen[1] == 1.0 and 0.0 < seen[2] < 1.0
    else:                                          # the sun below the horizon
        assert seen[:3] == [0.0, 0.0, 0.0]
    reader.actors_at(0.0)                          # builds lighting and occluder: replace them
    reader._lighting, reader._occluder, reader._sun_seen = light, occ, {}
    for t in (0.0, 1.0, 2.0):
        reader._last.clear()
        got, ref = reader.actors_at(t), _ref_actors(reader.actors, light, occ, t)
        np.testing.assert_array_equal(got.vertices, ref.vertices)
        np.testing.assert_array_equal(got.faces, ref.faces)
        np.testing.assert_array_equal(got.face_actor, ref.face_actor)
        assert got.colors.dtype == np.float32
        np.testing.assert_allclose(got.colors, ref.colors, rtol=2e-7, atol=1e-9)
    # a full cache of sun answers is emptied with still actors among the shown ones: every
    # one is cast again, the frame unchanged (it raised KeyError for the still ones)
    want = reader.actors_at(2.0)
    reader._sun_seen, reader._last = {}, {}
    reader.actors_at(1.0)                          # t = 2: cars 0-3 still, the walker moved
    reader._last.clear()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(stage_data, "SUN_SEEN_MAX", len(reader._sun_seen) + 1)
        got = reader.actors_at(2.0)
    np.testing.assert_array_equal(got.colors, want.colors)
    assert len(reader._sun_seen) == sum(shown)
    # no actor shown: the empty frame
    reader.actors.shown = [False] * len(actors)
    reader._last.clear()
    none = reader.actors_at(0.0)
    assert none.faces.shape == (0, 3) and none.vertices.shape == (0, 3) and none.surfels is None


# ---------------------------------------------------------------- env background, composite
def _camera(yaw=0.4, pitch=0.1, w=64, h=40):
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    fwd = np.array([cy * cp, sy * cp, sp])
    right = np.array([sy, -cy, 0.0])
    P = np.eye(4)
    P[:3, :3] = np.stack([right, np.cross(fwd, right), fwd], 1)
    P[:3, 3] = (0.0, 0.0, 1.5)
    return Camera(w, h, 50.0, 52.0, w / 2 + 0.3, h / 2 - 0.7, P)


@pytest.mark.parametrize("pole", ["Z", "Y"])
def test_env_background_matches_lookup_of_pixel_directions(pole):
    rng = np.random.default_rng(6)
    img = rng.random((32, 64, 3)).astype(np.float32)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    env = EnvMap(img, R, pole)
    for cam in (_camera(), _camera(0.0, np.pi / 2 - 1e-3), _camera(2.0, -1.2)):   # incl. near a pole
        got = frame.env_background(env, cam)
        ref = env.lookup(pixel_directions(cam))
        assert got.dtype == np.float32 and got.shape == (cam.height, cam.width, 3)
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7)
    assert frame.env_background(None, _camera()) is None


def test_env_background_is_looked_up_again_only_when_the_rotation_or_intrinsics_change(monkeypatch):
    rng = np.random.default_rng(7)
    env = EnvMap(rng.random((32, 64, 3)).astype(np.float32), np.eye(3))
    calls = []
    real = stage_data.env_lookup_pinhole
    monkeypatch.setattr(stage_data, "env_lookup_pinhole", lambda *a: calls.append(1) or real(*a))
    cam = _camera()
    first = frame.env_background(env, cam)
    first[:] = -1.0                                  # callers draw into it: a fresh array each
    moved = _camera()
    moved.pose[:3, 3] += (5.0, -2.0, 0.3)            # the sky does not move with the camera
    again = frame.env_background(env, moved)
    assert len(calls) == 1
    np.testing.assert_array_equal(again, real(env.image, moved.width, moved.height, moved.fx,
                                              moved.fy, moved.cx, moved.cy, moved.pose[:3, :3],
                                              env.world_from_dome))
    for other in (_camera(yaw=0.4 + 1e-9), _camera(w=65)):
        got = frame.env_background(env, other)
        np.testing.assert_allclose(got, env.lookup(pixel_directions(other)), rtol=1e-6, atol=1e-7)
    env.image = env.image * 0.5                      # another texture: looked up again
    np.testing.assert_allclose(frame.env_background(env, cam), 0.5 * again, rtol=1e-6)
    assert len(calls) == 4
    # a rig's cameras take turns every step: each camera's background is kept
    rig = [_camera(yaw=0.1 * (k + 1)) for k in range(3)]
    for _ in range(3):
        for c in rig:
            frame.env_background(env, c)
    assert len(calls) == 4 + 3
    for k in range(stage_data.ENV_PIXELS_KEPT):      # beyond the kept number: the oldest goes
        frame.env_background(env, _camera(yaw=1.0 + 0.1 * k))
    frame.env_background(env, rig[0])
    assert len(calls) == 4 + 3 + stage_data.ENV_PIXELS_KEPT + 1


def _ref_composite(surfels, actors, camera, env):
    """Frame.composite's rule written with whole-image np.where and the full G-buffer."""
    H, W = camera.height, camera.width
    if surfels is not None:
        out = frame.render_surfels(surfels, camera)
        s_rgb, s_a = out.rgb.numpy(), out.alpha.numpy()
        dmed, dexp = out.depth_median.numpy(), out.depth_expected.numpy()
        s_depth = np.where(dmed > 0, dmed, np.where(s_a > 1e-4, dexp, np.inf)).astype(np.float32)
    else:
        s_rgb, s_a = np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32)
        dexp = np.zeros((H, W), np.float32)
        s_depth = np.full((H, W), np.inf, np.float32)
    under = np.zeros((H, W, 3), np.float32) if env is None else env.lookup(pixel_directions(camera))
    a_mask, a_depth = np.zeros((H, W), bool), np.full((H, W), np.inf, np.float32)
    if len(actors.faces):
        g = render_gbuffer(actors.vertices, actors.faces, camera)
        a_mask = g.face_index >= 0
        a_depth = np.where(a_mask, g.depth, np.inf).astype(np.float32)
        a_rgb = np.zeros((H, W, 3), np.float32)
        a_rgb[a_mask] = actors.colors[g.face_index[a_mask]]
        under = np.where(a_mask[..., None], a_rgb, under)
    front = a_mask & (a_depth < s_depth)
    rgb = np.where(front[..., None], under, s_rgb + (1.0 - s_a)[..., None] * under)
    alpha = np.where(front | a_mask, 1.0, s_a)
    depth_exp = np.where(front, a_depth, np.where(dexp > 0, dexp, np.where(a_mask, a_depth, 0.0)))
    return rgb, alpha, np.minimum(a_depth, s_depth), depth_exp, front


def _car(x, y, yaw):
    vs, fs, cs, n = [], [], [], 0
    for m in vehicle_meshes("car"):
        vs.append(m.vertices @ _pose(0, 0, yaw)[:3, :3].T + [x, y, 0.0])
        fs.append(m.faces + n)
        cs.append(m.colors)
        n += len(m.vertices)
    return ActorFrame(np.concatenate(vs), np.concatenate(fs), np.concatenate(cs).astype(np.float32),
                      None, np.zeros(n, np.int64))


def _join(*frames):
    n = np.cumsum([0] + [len(f.vertices) for f in frames])
    return ActorFrame(np.concatenate([f.vertices for f in frames]),
                      np.concatenate([f.faces + k for f, k in zip(frames, n)]),
                      np.concatenate([f.colors for f in frames]), None)


def test_composite_matches_the_plain_rule():
    from lsd3d_usd.proxy.shapes import box
    from lsd3d_usd.splats.init import mesh_to_surfels
    v, f = box(0.3, 10.0, 0.0, 4.0)               # a thin surfel wall 9 m ahead, across the view
    wall = mesh_to_surfels(v + [9.0, 0.0, 0.0], f, count=4000, color=(0.2, 0.7, 0.3), opacity=0.6,
                           scale_factor=1.6, seed=0)
    rng = np.random.default_rng(7)
    env = EnvMap(rng.random((32, 64, 3)).astype(np.float32), np.eye(3))
    cam = _camera(0.0, 0.0, 96, 64)
    near, far, behind = _car(6.0, 1.0, 0.3), _car(16.0, -1.5, 1.2), _car(-8.0, 0.0, 0.0)
    cases = {"no actors": ActorFrame.empty(), "behind the camera": behind,
             "in front and behind the wall": _join(near, far, behind)}
    for name, actors in cases.items():
        for surf, e in ((wall, env), (None, env), (wall, None)):
            got = frame.composite(surf, actors, cam, e)
            ref = _ref_composite(surf, actors, cam, e)
            for a, b in zip((got.rgb, got.alpha, got.depth, got.depth_expected, got.actor_mask), ref):
                assert a.dtype == (bool if b.dtype == bool else np.float32), name
                np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7, err_msg=name)
    _, alpha, _, _, front = _ref_composite(wall, cases["in front and behind the wall"], cam, env)
    assert front.any() and ((alpha == 1) & ~front).any()   # a car before the wall, one behind it
    assert not frame.composite(wall, behind, cam, env).actor_mask.any()
