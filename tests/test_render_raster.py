"""The numba 2DGS rasteriser against the float64 reference: forward, gradients, screen bounds,
degenerate surfels, input errors."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.render import kernels_prep as kprep
from lsd3d_usd.render import projection as proj
from lsd3d_usd.render.raster_types import RasterSettings
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.render.reference import render_reference, splat_alpha_maps
from lsd3d_usd.render.sh import sh_basis

OUTS = ("rgb", "alpha", "depth_expected", "depth_median", "normal")
SETTINGS = {f.name for f in dataclasses.fields(RasterSettings)}


def rast(s, backend="numba", **kw):
    """rasterize() of a test scene dict (the reference's keyword style): the RasterSettings
    fields among the keywords go into one RasterSettings."""
    kw = {**s, **kw}
    settings = RasterSettings(**{k: v for k, v in kw.items() if k in SETTINGS})
    return rasterize(**{k: v for k, v in kw.items() if k not in SETTINGS}, settings=settings,
                     backend=backend)


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    """world->camera OpenCV viewmat (x right, y down, z forward)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    vm = np.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    return torch.tensor(vm, dtype=torch.float32)


def scene(n=20, seed=0, w=32, h=24, deg=1, offset=(0.0, 0.0, 0.0)):
    g = torch.Generator().manual_seed(seed)
    off = torch.tensor(offset, dtype=torch.float64)
    means = (torch.randn(n, 3, generator=g) * torch.tensor([1.0, 0.6, 0.5])
             + torch.tensor([0.0, 0.0, 4.0])).double() + off
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 2, generator=g) * 0.3 + 0.1
    op = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, (deg + 1) ** 2, 3, generator=g) * 0.3
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, 3] = -off
    f = 0.95 * w
    K = torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    return dict(means=means.float(), quats=quats, scales=scales, opacities=op, sh=sh,
                viewmat=vm.float(), K=K, width=w, height=h), means, vm


def test_forward_matches_float64_reference():
    s, _, _ = scene(n=60, seed=3, w=48, h=40, deg=2)
    bg = torch.tensor([0.2, 0.4, 0.9])
    out = rast(s, background=bg)
    ref = render_reference(**s, background=bg, t_min=1e-4)  # same early stop, float64
    assert out.stats.n_visible > 40
    assert (ref["alpha"] > 0.5).float().mean() > 0.2  # the scene covers the image
    tol = dict(rgb=2e-5, alpha=2e-5, depth_expected=5e-4, depth_median=2e-5, normal=2e-5)
    for k in OUTS:
        err = (getattr(out, k).double() - ref[k]).abs().max().item()
        assert err < tol[k], (k, err)
    # without early stop in the reference: the residual behind T < t_min stays below ~t_min
    ref0 = render_reference(**s, background=bg)
    assert (out.rgb.double() - ref0["rgb"]).abs().max() < 2e-4


def test_tile_size_and_image_edges_do_not_change_the_image():
    s, _, _ = scene(n=40, seed=5, w=37, h=29)  # not a multiple of the tile
    a = rast(s, tile=16)
    b = rast(s, tile=8)
    assert torch.allclose(a.rgb, b.rgb, atol=1e-6)
    ref = render_reference(**s, t_min=1e-4)
    assert (a.rgb.double() - ref["rgb"]).abs().max() < 2e-5


def _loss_weights(h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    shapes = dict(rgb=(h, w, 3), alpha=(h, w), depth_expected=(h, w), normal=(h, w, 3),
                  depth_median=(h, w))
    return {k: torch.randn(*v, generator=g, dtype=torch.float64) for k, v in shapes.items()}


def _loss(out, wts):
    """A weighted sum of the outputs of a RasterResult or of the reference's dict."""
    get = out.get if isinstance(out, dict) else (lambda k: getattr(out, k))
    return sum((get(k).double() * wts[k]).sum() for k in wts)


@pytest.mark.parametrize("seed", [1, 2])
def test_gradients_match_reference_autograd(seed):
    s, _, _ = scene(n=20, seed=seed)
    wts = _loss_weights(24, 32, seed)
    names = ("means", "quats", "scales", "opacities", "sh")
    bg = torch.tensor([0.3, 0.2, 0.1])
    fast = {k: s[k].clone().requires_grad_(True) for k in names}
    _loss(rast({**s, **fast}, background=bg), wts).backward()
    ref = {k: s[k].double().clone().requires_grad_(True) for k in names}
    _loss(render_reference(**{**s, **ref}, background=bg, t_min=1e-4), wts).backward()
    for k in names:
        ga, gb = fast[k].grad.double(), ref[k].grad
        assert torch.isfinite(ga).all()
        rel = ((ga - gb).norm() / gb.norm()).item()
        assert rel < 1e-3, (k, rel)


def test_gradients_match_finite_differences_float64():
    """Directional central differences of the float64 reference vs the fast path's gradient."""
    s, _, _ = scene(n=20, seed=4)
    wts = _loss_weights(24, 32, 7)
    names = ("means", "quats", "scales", "opacities", "sh")
    fast = {k: s[k].clone().requires_grad_(True) for k in names}
    _loss(rast({**s, **fast}), wts).backward()
    g = torch.Generator().manual_seed(11)
    base = {k: s[k].double() for k in names}
    for k in names:
        for _ in range(2):
            d = torch.randn(base[k].shape, generator=g, dtype=torch.float64)
            eps = 1e-6
            lp = _loss(render_reference(**{**s, **base, k: base[k] + eps * d}, t_min=1e-4), wts)
            lm = _loss(render_reference(**{**s, **base, k: base[k] - eps * d}, t_min=1e-4), wts)
            fd = ((lp - lm) / (2 * eps)).item()
            an = (fast[k].grad.double() * d).sum().item()
            assert abs(fd - an) <= 2e-3 * max(1.0, abs(fd)), (k, fd, an)


def _hard_splats():
    """Near, large and oblique surfels in front of a 64x48 camera (the cases where a plain
    3-sigma box misses visible alpha)."""
    g = torch.Generator().manual_seed(0)
    n = 24
    z = torch.rand(n, generator=g) * 1.5 + 0.3
    xy = (torch.rand(n, 2, generator=g) - 0.5) * z[:, None] * 1.5
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g)
    quats[:8] = torch.tensor([0.7071, 0.0, 0.0, 0.7071])  # normal along y: oblique to the view
    quats[:8] += 0.05 * torch.randn(8, 4, generator=g)
    scales = torch.rand(n, 2, generator=g) * 0.6 + 0.05
    op = torch.ones(n)
    op[::3] = 0.5
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    return means, quats, scales, op, torch.eye(4), K


def _misses(bound_sigma):
    """Largest alpha of any surfel outside its own screen rectangle (the fast path's bounds)."""
    means, quats, scales, op, vm, K = _hard_splats()
    w, h, amin = 64, 48, 1.0 / 255.0
    amap = splat_alpha_maps(means, quats, scales, op, vm, K, w, h, near=0.05)
    rot, centre = proj.camera_frame(vm)
    sh = np.zeros((means.shape[0], 1, 3), np.float32)
    _, vis, rect, _, _ = kprep.project(
        means.numpy(), quats.numpy(), scales.numpy(), op.numpy(), sh, 0, rot.numpy(),
        centre.numpy(), K.double().numpy(), w, h, 0.05, 1e4, amin,
        -1.0 if bound_sigma is None else bound_sigma)
    worst = 0.0
    for i in range(means.shape[0]):
        inside = np.zeros((h, w), bool)
        if vis[i]:
            inside[rect[i, 2]:rect[i, 3] + 1, rect[i, 0]:rect[i, 1] + 1] = True
        outside = amap[i].numpy()[~inside]
        worst = max(worst, float(outside.max(initial=0.0)))
    return worst, amap


def test_screen_bounds_are_conservative_for_near_large_oblique_splats():
    worst, amap = _misses(None)
    assert (amap.amax(dim=(1, 2)) > 0.5).sum() >= 10  # the splats are really on screen
    assert worst < 1.0 / 255.0, worst
    # the same check catches a plain 3-sigma box (not opacity-aware): the test has teeth
    worst3, _ = _misses(3.0)
    assert worst3 >= 1.0 / 255.0


def degenerate_params(s):
    """Leaf copies of scene s's surfel parameters with surfels 0-8 made degenerate (shared by
    the distortion tests)."""
    m, q, sc, op = s["means"].clone(), s["quats"].clone(), s["scales"].clone(), s["opacities"].clone()
    sc[0] = 0.0                                   # zero scale
    sc[1, 0] = 0.0                                # zero along one axis
    m[2] = torch.tensor([0.0, 0.0, 3.0])          # exactly edge-on: normal along x, seen along z
    q[2] = torch.tensor([0.0, 0.7071068, 0.0, 0.7071068])
    m[3] = 0.0                                    # centre on the camera
    m[4] = torch.tensor([0.2, 0.1, -2.0])         # behind the camera
    m[5] = torch.tensor([0.0, 0.0, 0.3])          # large surfel crossing the camera plane
    sc[5] = 2.0
    op[6] = 0.0
    op[7] = 1.0
    sc[7] = 5.0                                   # opaque, covering the view
    m[8] = torch.tensor([0.0, 0.0, 0.0501])       # just beyond near
    p = dict(means=m, quats=q, scales=sc, opacities=op, sh=s["sh"].clone())
    p = {k: v.requires_grad_(True) for k, v in p.items()}
    return p


def test_degenerate_surfels_give_finite_outputs_and_gradients():
    s, means64, _ = scene(n=12, seed=6)
    p = degenerate_params(s)
    out = rast({**s, **p}, background=torch.tensor([0.5, 0.5, 0.5]))
    wts = _loss_weights(24, 32, 3)
    _loss(out, wts).backward()
    for k in OUTS:
        assert torch.isfinite(getattr(out, k)).all(), k
    for k, v in p.items():
        assert torch.isfinite(v.grad).all(), k
    ref = render_reference(**{**s, **{k: v.detach() for k, v in p.items()}},
                           background=torch.tensor([0.5, 0.5, 0.5]), t_min=1e-4)
    assert (out.rgb.double() - ref["rgb"]).abs().max() < 1e-4


def test_scene_10km_from_origin_renders_like_at_origin():
    s0, _, _ = scene(n=40, seed=8)
    s1, _, _ = scene(n=40, seed=8, offset=(10000.0, -7000.0, 30.0))
    a, b = rast(s0), rast(s1)
    # float32 positions 10 km out are quantised to ~1 mm; the image must still agree closely
    assert (a.rgb - b.rgb).abs().mean() < 2e-3
    assert (a.depth_expected - b.depth_expected).abs().max() < 0.05
    ref = render_reference(**s1, t_min=1e-4)
    assert (b.rgb.double() - ref["rgb"]).abs().max() < 1e-4


def test_nan_input_names_array_and_index():
    s, _, _ = scene(n=10)
    s["scales"] = s["scales"].clone()
    s["scales"][7, 1] = float("nan")
    with pytest.raises(InputError, match=r"scales.*index 7"):
        rast(s)
    s2, _, _ = scene(n=10)
    s2["means"] = s2["means"].clone()
    s2["means"][3, 0] = float("inf")
    with pytest.raises(InputError, match=r"means.*index 3"):
        rast(s2)
    with pytest.raises(InputError, match="quats has shape"):
        rast({**scene(n=10)[0], "quats": torch.zeros(10, 3)})


def test_semantic_is_largest_weight_contributor_and_background_shows_through():
    s, _, _ = scene(n=30, seed=9)
    sem = torch.arange(30, dtype=torch.int32) % 5
    bg = torch.rand(24, 32, 3)
    out = rast(s, semantic_ids=sem, background=bg)
    ref = render_reference(**s, t_min=1e-4, background=bg)
    want = torch.where(ref["weight_argmax"] >= 0, sem.long()[ref["weight_argmax"].clamp_min(0)],
                       torch.full_like(ref["weight_argmax"], -1))
    assert (out.semantic == want).float().mean() > 0.99
    empty = ref["alpha"] == 0
    assert empty.any()
    assert torch.allclose(out.rgb[empty], bg[empty])
    assert (out.semantic[empty] == -1).all()


def test_world_space_normals_and_driving_camera():
    s, _, _ = scene(n=30, seed=10)
    vm = look_at((0.3, -0.5, 0.2), (0.0, 0.0, 4.0), up=(0.0, -1.0, 0.0))
    s["viewmat"] = vm
    cam = rast(s)
    world = rast(s, normal_space="world")
    R = vm[:3, :3]
    assert torch.allclose(world.normal, cam.normal @ R, atol=1e-5)
    ref = render_reference(**s, t_min=1e-4, normal_space="world")
    assert (world.normal.double() - ref["normal"]).abs().max() < 5e-5


def test_sh_basis_is_orthonormal_on_the_sphere():
    # Fibonacci sphere quadrature: integral of Y_i Y_j over the sphere = delta_ij
    n = 40000
    k = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.arccos(1 - 2 * k / n)
    theta = math.pi * (1 + 5 ** 0.5) * k
    d = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi),
                     torch.cos(phi)], 1)
    Y = sh_basis(d, 3)
    gram = Y.T @ Y * (4 * math.pi / n)
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-3)


def test_view_dependent_colour_changes_with_viewpoint():
    s, _, _ = scene(n=1, seed=12, deg=3)
    s["means"] = torch.tensor([[0.0, 0.0, 4.0]])
    s["quats"] = torch.tensor([[0.0, 0.0, 0.0, 1.0]])
    s["scales"] = torch.tensor([[1.0, 1.0]])
    s["opacities"] = torch.tensor([0.9])
    a = rast(s).rgb[12, 16]
    s["viewmat"] = look_at((1.5, 0.0, 0.0), (0.0, 0.0, 4.0), up=(0.0, -1.0, 0.0))
    b = rast(s)
    ref = render_reference(**s, t_min=1e-4)
    assert (b.rgb.double() - ref["rgb"]).abs().max() < 2e-5
    assert (a - b.rgb[12, 16]).abs().max() > 1e-3
    c = rast(s, sh_degree=0)
    ref0 = render_reference(**s, t_min=1e-4, sh_degree=0)
    assert (c.rgb.double() - ref0["rgb"]).abs().max() < 2e-5
