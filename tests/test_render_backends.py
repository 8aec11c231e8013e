"""Renderer backends: "numba" and "torch" agree on the render test scenes (images, gradients,
visible sets), the registry, the torch backend's budget, and the input checks every backend
shares (including the gradient-breaking finite inputs of issue 17)."""
import numpy as np
import pytest
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.render import backends
from lsd3d_usd.render.raster_types import BackendOutput, RasterSettings
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.render.reference import TorchBackend
from test_render_raster import _loss, _loss_weights, degenerate_params, look_at, rast, scene

NAMES = ("means", "quats", "scales", "opacities", "sh")
IMAGES = ("rgb", "alpha", "depth_acc", "depth_median", "normal")
TORCH64 = TorchBackend(dtype=torch.float64)


def _scenes():
    """The scenes of test_render_raster / test_render_distortion, with their settings."""
    bg = torch.tensor([0.2, 0.4, 0.9])
    out = {"layered": (scene(n=60, seed=3, w=48, h=40, deg=2)[0], dict(background=bg)),
           "odd_size": (scene(n=40, seed=5, w=37, h=29)[0], {}),
           "far_away": (scene(n=40, seed=8, offset=(10000.0, -7000.0, 30.0))[0], {}),
           "semantic": (scene(n=30, seed=9)[0],
                        dict(semantic_ids=torch.arange(30) % 5, background=torch.rand(24, 32, 3))),
           "distortion": (scene(n=60, seed=3, w=48, h=40, deg=2)[0],
                          dict(near=0.5, far=50.0, distortion=True))}
    s, _, _ = scene(n=30, seed=10)
    s["viewmat"] = look_at((0.3, -0.5, 0.2), (0.0, 0.0, 4.0), up=(0.0, -1.0, 0.0))
    out["world_normals"] = (s, dict(normal_space="world"))
    s, _, _ = scene(n=12, seed=6)
    out["degenerate"] = (s | {k: v.detach() for k, v in degenerate_params(s).items()},
                         dict(background=torch.tensor([0.5, 0.5, 0.5])))
    s, _, _ = scene(n=1, seed=12, deg=3)
    s.update(means=torch.tensor([[0.0, 0.0, 4.0]]), quats=torch.tensor([[0.0, 0.0, 0.0, 1.0]]),
             scales=torch.tensor([[1.0, 1.0]]), opacities=torch.tensor([0.9]),
             viewmat=look_at((1.5, 0.0, 0.0), (0.0, 0.0, 4.0), up=(0.0, -1.0, 0.0)))
    out["view_dependent"] = (s, {})
    return out


SCENES = _scenes()


@pytest.mark.parametrize("name", sorted(SCENES))
@pytest.mark.parametrize("torch_backend", ["torch", TORCH64], ids=["float32", "float64"])
def test_backends_agree_on_the_test_scenes(name, torch_backend):
    s, kw = SCENES[name]
    a = rast(s, **kw)
    b = rast(s, backend=torch_backend, **kw)
    assert b.rgb.dtype == (torch.float32 if torch_backend == "torch" else torch.float64)
    for k in IMAGES + (("distortion",) if kw.get("distortion") else ()):
        err = (getattr(a, k).double() - getattr(b, k).double()).abs().max().item()
        assert err < 1e-4, (k, err)
    # expected depth divides by alpha: compare where the pixel is not almost empty
    m = a.alpha > 0.05
    assert (a.depth_expected - b.depth_expected.float())[m].abs().max() < 1e-4
    if "semantic_ids" in kw:
        assert (a.semantic == b.semantic).float().mean() > 0.99
    else:
        assert a.semantic is None and b.semantic is None
    # every surfel the numba backend drew passed the torch backend's culling too
    assert set(a.visible_index.tolist()) <= set(b.visible_index.tolist())
    assert a.stats.n_visible == a.visible_index.numel() > 0


@pytest.mark.parametrize("seed", [1, 2])
def test_backends_agree_on_gradients(seed):
    s, _, _ = scene(n=20, seed=seed)
    wts = _loss_weights(24, 32, seed)
    bg = torch.tensor([0.3, 0.2, 0.1])
    grads = []
    for backend in ("numba", "torch"):
        p = {k: s[k].clone().requires_grad_(True) for k in NAMES}
        _loss(rast({**s, **p}, background=bg, backend=backend), wts).backward()
        grads.append(p)
    for k in NAMES:
        ga, gb = grads[0][k].grad.double(), grads[1][k].grad.double()
        assert torch.isfinite(gb).all()
        assert ((ga - gb).norm() / gb.norm()).item() < 1e-3, k


def test_registry_names_and_plugging_in_a_backend():
    assert {"numba", "torch"} <= set(backends.BACKENDS.names())
    s, _, _ = scene(n=10)
    with pytest.raises(InputError, match=r"^rasterize: unknown backend 'gsplat'; known: numba, torch"):
        rast(s, backend="gsplat")

    class Halved:
        """A stand-in for a new backend: the torch backend's accumulations, halved."""
        name = "halved"

        def forward(self, inputs, settings):
            o = TorchBackend().forward(inputs, settings)
            return BackendOutput(o.rgb / 2, o.alpha / 2, o.depth_acc / 2, o.depth_median,
                                 o.normal / 2, None, o.argmax, o.visible_index, o.stats)

    backends.register_backend(Halved())
    try:
        bg = torch.tensor([1.0, 1.0, 1.0])
        a = rast(s, backend="halved", background=bg)
        b = rast(s, backend="torch", background=bg)
        # rasterize composes the shared outputs for any backend: background and expected depth
        acc = b.rgb - (1 - b.alpha[..., None]) * bg  # the torch backend's own accumulation
        assert torch.allclose(a.rgb, acc / 2 + (1 - b.alpha[..., None] / 2) * bg, atol=1e-6)
        m = b.alpha > 0.05
        assert torch.allclose(a.depth_expected[m], b.depth_expected[m], rtol=1e-5)
        assert rast(s, backend=Halved()).alpha.max() <= 0.5  # objects work without registering
    finally:
        backends.BACKENDS.unregister("halved")


def test_torch_backend_refuses_scenes_over_its_budget():
    s, _, _ = scene(n=20, seed=1)  # 32x24 pixels
    with pytest.raises(InputError, match=r"backend 'torch' evaluates every surfel at every pixel: "
                                         r"\d+ surfels in view x 768 pixels is more than its budget of 1,000"):
        rast(s, backend=TorchBackend(max_pairs=1000))


def test_numba_backend_takes_float64_inputs_and_returns_float32():
    s, _, _ = scene(n=20, seed=1)
    s64 = {k: (v.double() if k in NAMES else v) for k, v in s.items()}
    a, b = rast(s), rast(s64)
    assert b.rgb.dtype == torch.float32 and torch.equal(a.rgb, b.rgb)


def test_settings_for_camera_and_setting_errors():
    from lsd3d_usd.render.camera import Camera
    cam = Camera.from_fov(32, 24, 60.0, near=0.3, far=80.0)
    st = RasterSettings.for_camera(cam, distortion=True)
    assert (st.near, st.far, st.distortion, st.tile) == (0.3, 80.0, True, 16)
    s, _, _ = scene(n=5)
    for kw, msg in [(dict(near=2.0, far=1.0), "need 0 < near < far"),
                    (dict(normal_space="ndc"), "normal_space must be"),
                    (dict(alpha_max=1.0), "alpha_min < alpha_max < 1"),
                    (dict(bound_sigma=0.0), "bound_sigma must be None"),
                    (dict(sh_degree=2), "sh_degree 2 needs more than the 4 coefficients")]:
        for backend in ("numba", "torch"):
            with pytest.raises(InputError, match=msg):
                rast(s, backend=backend, **kw)
    K = s["K"].clone()
    K[2, 0] = 0.1
    with pytest.raises(InputError, match=r"K must be a pinhole intrinsics matrix with last row \(0, 0, 1\)"):
        rast({**s, "K": K})
    with pytest.raises(InputError, match=r"^rasterize: viewmat has a non-finite value \(NaN or Inf\) at index \(1, 3\)$"):
        rast({**s, "viewmat": s["viewmat"].index_put((torch.tensor(1), torch.tensor(3)), torch.tensor(float("nan")))})
    with pytest.raises(InputError, match="settings must be a RasterSettings"):
        rasterize(*(s[k] for k in NAMES), s["viewmat"], s["K"], 32, 24, settings={"near": 1.0})


# ------------------------------------------------------------ issue 17: finite but fatal inputs
@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_tiny_quaternions_and_huge_sh_are_refused_by_name_and_index(backend):
    s, _, _ = scene(n=10, seed=2)
    q = s["quats"].clone()
    q[6] = torch.tensor([1e-45, 0.0, 0.0, 0.0])
    with pytest.raises(InputError, match=r"^rasterize: quats has a near-zero quaternion \(norm 1\.4e-45, "
                                         r"below 1e-20\) at index 6$"):
        rast({**s, "quats": q}, backend=backend)
    q[6] = 0.0
    with pytest.raises(InputError, match=r"quats has a zero quaternion at index 6$"):
        rast({**s, "quats": q}, backend=backend)
    sh = s["sh"].clone()
    sh[4, 2, 1] = 3e38
    with pytest.raises(InputError, match=r"^rasterize: sh has a value of magnitude 3e\+38 \(more than "
                                         r"1e\+06\) at index 4$"):
        rast({**s, "sh": sh}, backend=backend)
    sh[4, 2, 1] = -2e6
    with pytest.raises(InputError, match=r"sh has a value of magnitude 2e\+06 .* at index 4$"):
        rast({**s, "sh": sh.double()}, backend=backend)  # the per-array (float64) path too


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_gradients_stay_finite_at_the_accepted_limits(backend):
    """Just inside the bounds the gradients are finite: the checks refuse exactly what breaks."""
    s, _, _ = scene(n=10, seed=2)
    q = s["quats"].clone()
    q[:3] *= 2e-20 / q[:3].norm(dim=1, keepdim=True)
    sh = s["sh"].clone()
    sh[:5] = 1e6 * torch.sign(sh[:5])
    p = {k: v.clone().requires_grad_(True) for k, v in (s | {"quats": q, "sh": sh}).items() if k in NAMES}
    out = rast({**s, **p}, backend=backend)
    assert out.visible_index.numel() >= 5
    _loss(out, _loss_weights(24, 32, 1)).backward()
    for k in NAMES:
        assert torch.isfinite(p[k].grad).all(), k


def test_check_names_index_for_cpu_float32_float64_and_torch_scan_alike():
    """The numba scan (CPU float32/float64) and the torch scan (other devices) find the same
    first bad element."""
    from lsd3d_usd.render import checks
    x = torch.zeros(5000, 3)
    x[4321, 1] = float("nan")
    x[4400, 0] = -1.0
    for t in (x, x.double()):
        assert checks.first_bad_flat(t, 0.0, np.inf) == 4321 * 3 + 1
    y = x.clone()
    y[4321, 1] = 0.0
    assert checks.first_bad_flat(y, 0.0, np.inf) == 4400 * 3
    assert checks.first_bad_flat(y.to(torch.float16), 0.0, np.inf) == 4400 * 3  # torch path


def test_docs_backend_example_plugs_in_and_matches_the_torch_backend():
    """The "Adding a backend" example of docs/render.md, run as written."""
    import re
    from pathlib import Path
    text = (Path(__file__).parents[1] / "docs" / "render.md").read_text()
    section = text[text.index("## Adding a backend"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    try:
        exec(compile(code, "docs/render.md", "exec"), {})
        s, kw = SCENES["semantic"]
        a = rast(s, backend="torch64", **kw)
        b = rast(s, backend=TORCH64, **kw)
        for k in IMAGES + ("depth_expected", "semantic"):
            assert torch.equal(getattr(a, k), getattr(b, k)), k
        assert a.stats.n_visible == b.stats.n_visible > 0
    finally:
        backends.BACKENDS.unregister("torch64")
