"""The procedural prior's surface kernel against its torch reference (materials.py)."""
import numpy as np
import pytest
import torch

from lsd3d_usd.ggds.priors import materials as mat
from lsd3d_usd.ggds.priors.surface_kernel import VEGETATION, surface_properties
from lsd3d_usd.semantics import CLASSES


def _points(n, seed, far=0.0):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-300, 300, (n, 3)) + far
    p[:, 2] = rng.uniform(-1.0, 30.0, n)
    # walls on round coordinates and storey boundaries, where a cell or window edge falls
    p[: n // 8, 0] = np.round(p[: n // 8, 0])
    p[n // 8: n // 4, 2] = 3.2 * np.round(p[n // 8: n // 4, 2] / 3.2)
    nrm = rng.normal(size=(n, 3))
    nrm[: n // 4] = (1.0, 0.0, 0.0)           # a wall facing +x
    nrm[n // 4: n // 2] = (0.0, 0.0, 1.0)     # ground and roofs
    nrm[n // 2: n // 2 + 8] = 0.0             # a degenerate normal
    n_t = torch.nn.functional.normalize(torch.from_numpy(nrm).float(), dim=-1)
    return torch.from_numpy(p), n_t


@pytest.mark.parametrize("settings", [
    mat.MaterialSettings(seed=3),
    mat.MaterialSettings(seed=11, wetness=0.8, vegetation="autumn"),
    mat.MaterialSettings(seed=0, snow_cover=0.6, vegetation="snow", floor_height=4.1, ground_z=-2.5),
    mat.MaterialSettings(seed=7, wetness=0.3, snow_cover=0.3, vegetation="bare", window_spacing=1.9),
])
def test_kernel_matches_the_reference_bit_for_bit_in_every_class(settings):
    p, n = _points(6000, settings.seed)
    for cid in [-1, *range(len(CLASSES))]:       # -1: unlabelled, the default material
        cls = torch.full((len(p),), cid)
        ref = mat.surface_reference(p, n, cls, settings)
        got = surface_properties(p, n, cls, settings)
        assert torch.equal(got, ref), (CLASSES[cid] if cid >= 0 else "unlabelled",
                                       float((got - ref).abs().max()))


def test_mixed_classes_far_from_the_origin_and_uncovered_pixels():
    s = mat.MaterialSettings(seed=5, wetness=0.5)
    p, n = _points(10000, 1, far=40_000.0)        # 40 km out: lattice coordinates in float64
    cls = torch.from_numpy(np.random.default_rng(2).integers(-1, len(CLASSES), len(p)))
    assert torch.equal(surface_properties(p, n, cls, s), mat.surface_reference(p, n, cls, s))
    # an uncovered pixel gets the prior's empty value, whatever its position holds
    valid = torch.ones(len(p), dtype=torch.bool)
    valid[::3] = False
    p[::6] = float("nan")
    got = surface_properties(p, n, cls, s, valid)
    assert torch.equal(got[::3], torch.tensor([[0.0, 0, 0, 0, 1, 0]]).expand(len(got[::3]), 6))
    keep = valid.nonzero()[:, 0]
    assert torch.equal(got[keep], mat.surface_reference(p[keep], n[keep], cls[keep], s))
    assert surface_properties(p[:0], n[:0], cls[:0], s).shape == (0, 6)


def test_kernel_bad_input_is_a_clear_error():
    p, n = _points(10, 0)
    with pytest.raises(ValueError, match="vegetation state 'purple'"):
        surface_properties(p, n, torch.zeros(10), mat.MaterialSettings(vegetation="purple"))
    with pytest.raises(ValueError, match="10 points, 10 normals, 9 classes"):
        surface_properties(p, n, torch.zeros(9), mat.MaterialSettings())
    assert set(VEGETATION) == set(mat.FOLIAGE) == set(mat.GRASS)


@pytest.mark.parametrize("env_kw", [
    {},
    {"wetness": 0.8, "sky": True},                                  # mirror-like wet road
    {"snow_cover": 0.5, "vegetation": "snow", "exposure": 2.5},
    {"fog_density": 0.02, "sun_direction": [0.3, 0.2, 0.05]},       # fog, the sun at the horizon
    {"sun_direction": [0.3, 0.2, -0.3], "sky": True},               # the sun below it
])
def test_lit_render_matches_the_torch_reference(env_kw):
    from lsd3d_usd.conditioning.light import PriorEnv
    from lsd3d_usd.env.lookup import EnvMap
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    from lsd3d_usd.ggds.priors.synthetic import street_gbuffer
    kw = dict(env_kw)
    if kw.pop("sky", False):
        img = np.random.default_rng(3).random((32, 64, 3)).astype(np.float32)
        kw["sky_lookup"] = EnvMap(img, np.eye(3))
    env = PriorEnv(**kw)
    gb = street_gbuffer(160, 90)
    gb.normal[:3, :3] = 0.0           # degenerate normals: both keep them zero
    prior = ProceduralPrior(seed=4)
    got, ref = prior.render(gb, env), prior.render_reference(gb, env)
    assert got.shape == ref.shape == (90, 160, 3) and got.dtype == torch.float32
    assert float((got - ref).abs().max()) <= 1e-6
    assert float(got.std()) > 0.01


def test_lighting_slices_are_the_whole():
    import numba
    from lsd3d_usd.ggds.priors.lighting_kernel import MIN_SLICE, _light, light
    if numba.get_num_threads() < 2:
        pytest.skip("one numba thread: nothing is sliced")
    rng = np.random.default_rng(0)
    P = 3 * MIN_SLICE + 17
    surf = rng.random((P, 6)).astype(np.float32)
    surf[:, 4] = np.maximum(surf[:, 4], 0.02)
    valid = rng.random(P) > 0.1
    f32 = [np.ascontiguousarray(a, np.float32) for a in (
        rng.normal(size=(P, 3)), rng.normal(size=(P, 3)), rng.random(P),
        np.array([0.3, -0.4, 0.866]), np.array([2.0, 1.9, 1.7]), rng.normal(size=(9, 3)))]
    col, refl = light(surf, valid, *f32)
    # the kernel over every row in one call: what the threads' slices must add up to
    whole_c, whole_r = np.zeros((P, 3), np.float32), np.zeros((P, 4), np.float32)
    _light(surf, valid, *f32, whole_c, whole_r)
    assert np.array_equal(col, whole_c) and np.array_equal(refl, whole_r)
    assert col[valid].any(axis=1).mean() > 0.5 and not col[~valid].any() and not refl[~valid].any()


def test_sharp_highlights_agree_within_the_lobe_power_rounding():
    """shade_at's points of every class under a low sun, glossy classes included (the
    street image has few sharp highlights): the kernel against the torch lighting."""
    from lsd3d_usd.conditioning.gbuffer import GBuffer
    from lsd3d_usd.conditioning.light import PriorEnv
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    rng = np.random.default_rng(5)
    n = 20000
    p, nrm = _points(n, 5)
    cls = torch.from_numpy(rng.integers(0, len(CLASSES), n))
    view = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(n, 3))).float(), dim=-1)
    gb = GBuffer(depth=torch.ones(n, 1), normal=nrm.reshape(n, 1, 3), semantic=cls.reshape(n, 1),
                 world_pos=p.reshape(n, 1, 3), view_dirs=view.reshape(n, 1, 3),
                 camera_position=torch.zeros(3), sun_visibility=None)
    env = PriorEnv(sun_direction=[0.3, -0.2, 0.4], wetness=0.6)
    prior = ProceduralPrior(seed=2)
    got, ref = prior.render(gb, env), prior.render_reference(gb, env)
    d = (got - ref).abs()
    assert float(d.max()) <= 1e-5 and float((d > 1e-6).float().mean()) < 1e-3
    assert float(got.max()) > 0.5           # some highlights are there to compare
