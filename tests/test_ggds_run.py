"""The GGDS loop on a tiny synthetic street: losses fall, only seen surfels change,
checkpoints resume exactly, the strategy relocates dead surfels onto live ones."""
import numpy as np
import pytest
import torch

from lsd3d_usd.ggds.optim import params as P
from lsd3d_usd.ggds.optim.adam import SelectiveAdam
from lsd3d_usd.conditioning.view_sampling import View, sample_views
from lsd3d_usd.ggds.priors.base import Prior
from lsd3d_usd.ggds.settings import GGDSConfig, StrategyConfig
from lsd3d_usd.conditioning.scene import Conditioning
from lsd3d_usd.ggds.run.evaluate import point_triangle_distance
from lsd3d_usd.ggds.run.inputs import GGDSInputs
from lsd3d_usd.ggds.run.optimisation import GGDSRun
from lsd3d_usd.ggds.optim.strategy import MCMCStrategy
from lsd3d_usd.layout.model import LaneCenter, Layout
from lsd3d_usd.semantics import CLASS_COLORS, CLASS_ID
from lsd3d_usd.splats.field import SurfelField
from lsd3d_usd.splats.init import mesh_to_surfels


SKY = torch.tensor([0.5, 0.6, 0.8])


class ClassColourTestPrior(Prior):
    """Test-only prior: the target is the proxy's class colour per pixel, ignoring t."""
    name = "class-colour-test"

    def target(self, x, gbuffer, env, t, n_steps=5, seed=None):
        sem = gbuffer.semantic.clamp(min=0)
        col = torch.from_numpy(CLASS_COLORS)[sem]
        return torch.where((gbuffer.semantic >= 0)[..., None], col, SKY)


def street():
    """A 40 m road strip with a building wall beside it."""
    v, f, ids = [], [], []

    def quad(p0, p1, p2, p3, cls):
        base = len(v)
        v.extend([p0, p1, p2, p3])
        f.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]])
        ids.extend([CLASS_ID[cls]] * 2)

    for x in range(0, 40, 5):  # road in 5 m tiles so faces are not huge
        quad((x, -5, 0), (x + 5, -5, 0), (x + 5, 5, 0), (x, 5, 0), "road")
        quad((x, 5, 0), (x + 5, 5, 0), (x + 5, 5, 8), (x, 5, 8), "building")  # wall facing -y
    return np.array(v, float), np.array(f, np.int64), np.array(ids, np.int32)


def layout():
    return Layout(lanes=[LaneCenter(id="l0", points=[[2, -1.5, 0], [38, -1.5, 0]])])


def new_run(field, proxy, views, prior, cfg, env=None, backdrop=None, **inputs):
    """A GGDSRun over arrays (no scene light: ``backdrop`` as the background)."""
    cond = Conditioning.of_arrays(proxy, env, backdrop=backdrop)
    return GGDSRun(GGDSInputs(field=field, conditioning=cond, views=views, **inputs), prior, cfg)


def make_run(steps=20, seed=0, n=4000, far_extra=0, prior=None, **config):
    V, F, ids = street()
    # Grey start: the run must learn the class colours from the prior.
    field, face = mesh_to_surfels(V, F, ids, count=n, seed=seed, sh_degree=1, color=(0.5, 0.5, 0.5),
                                  return_face_index=True)
    if far_extra:  # surfels 1 km away: never in any view
        far = field.subset(np.arange(far_extra))
        far.positions = far.positions + np.array([1000.0, 1000.0, 0], np.float32)
        field = SurfelField.concat([field, far])
        face = np.concatenate([face, face[:far_extra]])
    views = sample_views(layout(), 6, 64, 48, seed=seed, novel_frac=0.3)
    config.setdefault("strategy", StrategyConfig(relocate_every=10))
    cfg = GGDSConfig(steps=steps, resolution=(64, 48), seed=seed, perceptual=False, **config)
    return new_run(field, (V, F, ids), views, prior or ClassColourTestPrior(), cfg, face_index=face,
                   backdrop=lambda cam: SKY.expand(cam.height, cam.width, 3))


def test_loss_falls_and_stays_finite():
    run = make_run(steps=40)
    for _ in range(40):
        rec = run.step()
        assert np.isfinite(rec["loss"])
    first = np.mean([h["l1"] for h in run.history[:6]])
    last = np.mean([h["l1"] for h in run.history[-6:]])
    assert last < 0.8 * first, (first, last)
    f = run.field()
    assert f.problems() == []


def test_surfels_outside_every_view_are_untouched():
    run = make_run(steps=8, far_extra=200)
    before = {k: v.detach().clone() for k, v in run.params.items()}
    for _ in range(8):
        run.step()
    n = before["means"].shape[0]
    far = slice(n - 200, n)
    for k in P.KEYS:
        assert torch.equal(run.params[k][far], before[k][far]), k
    assert not torch.equal(run.params["sh"][: n - 200], before["sh"][: n - 200])


def test_checkpoint_resume_matches_uninterrupted_run():
    a = make_run(steps=12)
    for _ in range(12):
        a.step()
    b = make_run(steps=12)
    for _ in range(6):
        b.step()
    tensors, meta = b.checkpoint()
    # the checkpoint round-trips through its files: safetensors + JSON, no pickle
    import json
    from safetensors.torch import load, save
    tensors, meta = load(save(tensors)), json.loads(json.dumps(meta))
    c = make_run(steps=12)
    c.restore(tensors, meta)
    for _ in range(6):
        c.step()
    for k in P.KEYS:
        torch.testing.assert_close(c.params[k], a.params[k], rtol=1e-5, atol=1e-6)
    assert [h["view"] for h in c.history] == [h["view"] for h in a.history]


def test_selective_adam_matches_torch_adam_on_full_rows():
    torch.manual_seed(0)
    p = {"w": torch.randn(5, 3, requires_grad=True)}
    q = torch.nn.Parameter(p["w"].detach().clone())
    ours = SelectiveAdam(p, {"w": 0.1})
    ref = torch.optim.Adam([q], lr=0.1, eps=1e-15)
    for _ in range(5):
        g = torch.randn(5, 3)
        p["w"].grad, q.grad = g.clone(), g.clone()
        ours.step(torch.arange(5))
        ref.step()
    torch.testing.assert_close(p["w"].detach(), q.detach())


def test_selective_adam_kernel_matches_torch_reference():
    """The numba pass against the torch gathers and scatters: lr factors per column and per
    channel of the base colour (dark_step_scale), eps per key, rows updated unequally often (per-row bias correction), rows
    never given left alone."""
    torch.manual_seed(3)
    init = {"sh": torch.randn(300, 9, 3), "o": torch.randn(300), "q": torch.randn(300, 4)}
    scales = {"sh": torch.tensor([1.0] + [0.05] * 8)[:, None]}
    runs = []
    for kind in ("step", "step_reference"):
        p = {k: v.clone().requires_grad_(True) for k, v in init.items()}
        opt = SelectiveAdam(p, {"sh": 0.05, "o": 0.1, "q": 0.0}, lr_scales=scales,
                            eps_by_key={"o": 1e-3}, relative={"sh": (0.25, 0.1)})
        gen = torch.Generator().manual_seed(4)
        for _ in range(6):
            for v in p.values():
                v.grad = torch.randn(v.shape, generator=gen) * 1e-3
            getattr(opt, kind)(torch.randperm(250, generator=gen)[:170])
        runs.append((p, opt))
    (a, oa), (b, ob) = runs
    for k in init:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(oa.m[k], ob.m[k], rtol=1e-5, atol=1e-9)
        torch.testing.assert_close(oa.v[k], ob.v[k], rtol=1e-5, atol=1e-12)
        assert torch.equal(a[k][250:], init[k][250:])          # never given: untouched
    assert torch.equal(a["q"], init["q"])                        # lr 0: untouched
    assert not torch.equal(a["sh"], init["sh"]) and torch.equal(oa.t, ob.t)


def test_selective_adam_in_row_blocks_equals_one_block(monkeypatch):
    from lsd3d_usd.ggds.optim import adam
    torch.manual_seed(1)
    init = {"sh": torch.randn(50, 4, 3), "o": torch.randn(50)}
    scales = {"sh": torch.tensor([1.0, 0.5, 0.5, 0.5])[:, None]}
    runs = []
    for block in (1 << 17, 7):
        monkeypatch.setattr(adam, "ROW_BLOCK", block)
        p = {k: v.clone().requires_grad_(True) for k, v in init.items()}
        opt = SelectiveAdam(p, {"sh": 0.05, "o": 0.1}, lr_scales=scales, eps_by_key={"o": 1e-8})
        gen = torch.Generator().manual_seed(2)
        for _ in range(4):
            for v in p.values():
                v.grad = torch.randn(v.shape, generator=gen)
            opt.step_reference(torch.randperm(50, generator=gen)[:37])
        runs.append((p, opt))
    (a, oa), (b, ob) = runs
    for k in init:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
        torch.testing.assert_close(oa.m[k], ob.m[k], rtol=0, atol=0)
    assert torch.equal(oa.t, ob.t)


def test_relocation_moves_dead_surfels_and_conserves_opacity():
    field = SurfelField(np.random.default_rng(0).normal(size=(100, 3)), np.tile([0, 0, 0, 1.0], (100, 1)),
                        np.full((100, 2), 0.1), np.r_[np.full(10, 1e-4), np.full(90, 0.6)],
                        np.zeros((100, 1, 3)))
    params = P.to_params(field)
    opt = SelectiveAdam(params, {k: 0.01 for k in P.KEYS})
    strat = MCMCStrategy(relocate_every=1, noise_scale=0.0, max_relocate_frac=1.0)
    moved = strat.relocate(params, opt)
    assert moved == 10
    dead, src = strat.last_relocation
    op = torch.sigmoid(params["opacities"])
    assert (op[dead] > 0.1).all()
    # Each source and its k copies composite to the source's old opacity: 1-(1-o')^(k+1) = o.
    for s in torch.unique(src):
        k = int((src == s).sum())
        o_new = float(op[s])
        assert abs(1 - (1 - o_new) ** (k + 1) - 0.6) < 1e-4
    np.testing.assert_allclose(params["means"][dead][:, 2].numpy(), params["means"][src][:, 2].numpy(),
                               atol=1e-6)  # offset stays in the tangent (xy) plane


def test_noise_stays_in_tangent_plane():
    n = 50
    field = SurfelField(np.zeros((n, 3)), np.tile([0, 0, 0, 1.0], (n, 1)), np.full((n, 2), 0.2),
                        np.full(n, 1e-4), np.zeros((n, 1, 3)))
    params = P.to_params(field)
    strat = MCMCStrategy(noise_scale=1.0)
    strat.add_noise(params, torch.arange(n), lr_means=1e-3)
    m = params["means"].detach()
    assert m[:, :2].abs().max() > 0.01 and m[:, 2].abs().max() == 0.0


def test_off_surface_metric_and_point_triangle_distance():
    a, b, c = np.array([[0, 0, 0.0]]), np.array([[1, 0, 0.0]]), np.array([[0, 1, 0.0]])
    pts = np.array([[0.2, 0.2, 0.5], [2, 0, 0], [-1, -1, 0], [0.5, 0.5, 0]])
    d = point_triangle_distance(pts, *(np.repeat(x, 4, 0) for x in (a, b, c)))
    np.testing.assert_allclose(d, [0.5, 1.0, np.sqrt(2), 0.0], atol=1e-12)
    run = make_run()
    assert run.off_surface_fraction() == 0.0
    with torch.no_grad():
        run.params["means"][:100, 2] += 1.0  # lift 100 road surfels 1 m
    assert run.off_surface_fraction() >= 100 / run.params["means"].shape[0] * 0.5


def test_views_follow_lanes_and_need_lanes():
    views = sample_views(layout(), 20, 64, 48, seed=3, novel_frac=0.25)
    kinds = [v.kind for v in views]
    assert kinds.count("novel") == 5
    for v in views:
        c = v.camera.center
        assert 2 <= c[0] <= 38
        if v.kind == "lane":
            assert abs(c[1] + 1.5) < 3 and abs(c[2] - 1.6) < 1e-9
    np.testing.assert_allclose(View.from_json(views[0].to_json()).camera.pose, views[0].camera.pose, atol=1e-6)
    from lsd3d_usd.errors import InputError
    with pytest.raises(InputError, match="no drivable lanes"):
        sample_views(Layout(), 3, 64, 48)


def test_stratified_views_leave_no_stretch_of_lane_without_a_view():
    two = Layout(lanes=[LaneCenter(id="a", points=[[0, 0, 0], [300, 0, 0]]),
                        LaneCenter(id="b", points=[[0, 50, 0], [100, 50, 0]])])

    def largest_gap(views):
        x = np.sort([v.camera.center[0] for v in views if v.lane_id == "a"])
        return np.diff(np.r_[0.0, x, 300.0]).max(), len(x)
    for seed in range(5):
        strat = sample_views(two, 40, 32, 24, seed=seed, novel_frac=0.0, stratified=True)
        gap, n_a = largest_gap(strat)
        assert n_a == 30                  # lanes get views in proportion to their length
        assert gap <= 2 * 400 / 40 + 1    # one view in each 10 m of the 400 m of lane
        clipped = sample_views(two, 20, 32, 24, seed=seed, novel_frac=0.25, stratified=True,
                               region=(0, -10, 100, 60), clip=True)
        assert all(-1 <= v.camera.center[0] <= 101 for v in clipped if v.kind == "lane")
        assert [v.kind for v in clipped].count("novel") == 5
    # independent draws leave gaps several times as wide: what the strata are for
    gaps = [largest_gap(sample_views(two, 40, 32, 24, seed=s, novel_frac=0.0))[0] for s in range(5)]
    assert max(gaps) > 25


def test_packed_view_gbuffer_unpacks_to_the_full_gbuffer():
    """GGDS keeps training views packed (depth, face, position, sun) and derives the rest per
    visit: the unpacked G-buffer equals one built straight from the mesh rasteriser."""
    from lsd3d_usd.conditioning.shadow import shadow_map
    from lsd3d_usd.conditioning.gbuffer import view_gbuffer
    from lsd3d_usd.render.camera import Camera, look_at
    from lsd3d_usd.render.gbuffer import render_gbuffer
    V, F, ids = street()
    cam = Camera.from_fov(96, 54, 70, pose=look_at(np.array([3.0, -2.0, 1.6]),
                                                   np.array([30.0, 4.0, 2.0]), (0, 0, 1)))
    shadow = shadow_map(V, F, np.array([0.2, 0.6, 0.5]), resolution=256)  # behind the wall
    gb = view_gbuffer(cam, V, F, ids, shadow)
    ref = render_gbuffer(V, F, cam, ids)
    dirs = np.zeros((cam.height, cam.width, 3))
    for j in range(cam.height):          # plain reference: pinhole ray, rotated, normalised
        for i in range(cam.width):
            d = cam.pose[:3, :3] @ [(i + 0.5 - cam.cx) / cam.fx, (j + 0.5 - cam.cy) / cam.fy, 1.0]
            dirs[j, i] = d / np.linalg.norm(d)
    assert ref.mask.any() and (~ref.mask).any()
    np.testing.assert_array_equal(gb.depth.numpy(), ref.depth)
    np.testing.assert_array_equal(gb.normal.numpy(), ref.normal)
    np.testing.assert_array_equal(gb.semantic.numpy(), ref.semantic)
    # the packing kernel sums the rotated ray in its own order: float32 rounding apart (a
    # ground point's z is 0 there and -2e-16 in numpy's matmul), the same positions
    np.testing.assert_allclose(gb.world_pos.numpy(), np.nan_to_num(ref.position).astype(np.float32),
                               rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(gb.view_dirs.numpy(), dirs, atol=1e-6)
    vis = shadow.visibility(np.where(ref.mask[..., None], ref.position, np.nan))
    np.testing.assert_array_equal(gb.sun_visibility.numpy(), np.where(ref.mask, vis, 1.0))
    assert 0 < gb.sun_visibility[torch.from_numpy(ref.mask)].mean() < 1   # shadow and sun both
    # no shadow map: no sun visibility (all lit), the same positions
    from lsd3d_usd.conditioning.gbuffer import pack_view_gbuffer
    bare = pack_view_gbuffer(cam, V, F, None)
    assert bare.sun is None and torch.equal(bare.world_pos, gb.world_pos)
    # a map of one wall's two faces: the pixels off it are lit, the ones it shades are not,
    # as ShadowMap.visibility says
    used, sub = np.unique(F[6:8], return_inverse=True)
    part = shadow_map(V[used], sub.reshape(-1, 3), np.array([0.2, 0.6, 0.5]), resolution=64)
    uv, _ = part.camera.project(ref.position[ref.mask])
    assert ((uv < 0) | (uv >= 64)).any(axis=1).sum() > 100        # many pixels off the map
    vis = part.visibility(np.where(ref.mask[..., None], ref.position, np.nan))
    assert (vis[ref.mask] == 0).sum() > 100                        # and many it shades
    np.testing.assert_array_equal(pack_view_gbuffer(cam, V, F, part).sun.numpy(),
                                  np.where(ref.mask, vis, 1.0) > 0.5)


def test_training_view_gbuffers_are_keyed_so_the_prior_renders_each_view_once():
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    run = make_run(steps=2)
    prior = ProceduralPrior()
    calls = []
    render = prior.render
    prior.render = lambda gb, env: calls.append(gb.key) or render(gb, env)
    a, b = run.view_data(0).gbuffer, run.view_data(0).gbuffer
    assert a is not b and a.key == b.key and run.view_data(1).gbuffer.key != a.key
    p1, p2 = prior.cached_render(a, run.env), prior.cached_render(b, run.env)
    assert p1 is p2 and calls == [a.key]
    other = make_run(steps=2).view_data(0).gbuffer     # another run's view 0: its own key
    prior.cached_render(other, run.env)
    assert len(calls) == 2


def test_release_views_drops_the_runs_caches_and_only_them():
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    prior = ProceduralPrior()
    run, other = make_run(steps=2, prior=prior), make_run(steps=2, prior=prior)
    for r in (run, other):
        for i in (0, 1):
            prior.cached_render(r.view_data(i).gbuffer, r.env)
    assert len(prior.cached_views()) == 4 and run.views.cached == 2
    before = run.view_data(1).gbuffer
    run.release_views()
    assert not run.views.cached and len(prior.cached_views()) == 2   # the other run's stay
    after = run.view_data(1).gbuffer                                # rebuilt on demand
    assert after.key == before.key and torch.equal(after.depth, before.depth)


def test_view_gbuffer_of_an_empty_proxy_is_all_empty():
    from lsd3d_usd.conditioning.gbuffer import view_gbuffer
    from lsd3d_usd.render.camera import Camera
    gb = view_gbuffer(Camera.from_fov(16, 9, 60), np.zeros((0, 3)), np.zeros((0, 3), np.int64),
                      np.zeros(0, np.int32))
    assert not gb.valid.any() and (gb.semantic == -1).all() and (gb.normal == 0).all()


def test_fit_views_join_the_colour_start_and_leave_nothing_behind():
    """World-space start with training views A and fit-only views B gives the colours of a
    run that trains on A + B (the same least squares); the fit views' targets are not kept."""
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    base = make_run(steps=2)
    views = base.views.views
    a, b = views[:3], views[3:]
    prior = ProceduralPrior()

    def run_with(train, fit):
        r = new_run(base.field(), base.conditioning.proxy, train, prior, base.cfg, fit_views=fit)
        assert r.world_init()
        return r
    split, joint, alone = run_with(a, b), run_with(a + b, []), run_with(a, [])
    np.testing.assert_allclose(split.params["sh"].detach().numpy(), joint.params["sh"].detach().numpy(),
                               rtol=1e-5, atol=1e-6)
    assert not np.allclose(split.params["sh"].detach().numpy(), alone.params["sh"].detach().numpy())
    keys = set(prior.cached_views())
    assert not any(len(k) == 3 and k[1] == "fit" for k in keys)
    assert split.views.cached == len(a)


def test_colour_start_colours_the_unfinished_neighbours_context_and_resumes_with_it():
    """context_start rows (a neighbour's initial surfels) get the colours a run training them
    would start from: the same fit as one run over the region's and those rows (per-surfel
    least squares; the groups' zonal slopes pooled over both); the other context rows keep
    theirs; a checkpoint carries the fitted colours."""
    import dataclasses
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    base = make_run(steps=2)
    full = base.field()
    x = full.positions[:, 0]
    own, ctx = full.subset(np.flatnonzero(x < 20)), full.subset(np.flatnonzero(x >= 20))
    start = ctx.positions[:, 0] >= 30          # an unfinished neighbour's rows
    proxy = base.conditioning.proxy
    prior = ProceduralPrior()
    cfg = dataclasses.replace(base.cfg, world_init_zonal_prior=True)

    def region(cfg=cfg):
        return new_run(own, proxy, base.views.views, prior, cfg, context=ctx, context_start=start)
    fitted = np.flatnonzero((x < 20) | (x >= 30))
    run, joint = region(), new_run(full.subset(fitted), proxy, base.views.views,
                                   prior, cfg)
    assert run.world_init() and joint.world_init()
    np.testing.assert_allclose(run.params["sh"].detach().numpy(),
                               joint.params["sh"].detach().numpy()[x[fitted] < 20], atol=1e-6)
    got = run.context["sh"].float().numpy()
    want = joint.params["sh"].detach().numpy()[x[fitted] >= 30]
    seen = np.any(got[start] != ctx.sh[start].astype(np.float16).astype(np.float32), axis=(1, 2))
    np.testing.assert_allclose(got[start][seen], want[seen],
                               atol=2e-3 + 1e-3 * np.abs(want).max())
    # with per-surfel ridges towards zero, the same as one run over all surfels
    plain_cfg = dataclasses.replace(base.cfg, world_init_zonal_prior=False)
    run = region(plain_cfg)
    joint = new_run(full, proxy, base.views.views, prior, plain_cfg)
    assert run.world_init() and joint.world_init()
    got = run.context["sh"].float().numpy()
    assert np.array_equal(got[~start], ctx.sh[~start].astype(np.float16).astype(np.float32))
    changed = np.any(got[start] != ctx.sh[start].astype(np.float16).astype(np.float32), axis=(1, 2))
    assert changed.mean() > 0.5      # the rows some view sees
    want = joint.params["sh"].detach().numpy()[x >= 20][start][changed]
    np.testing.assert_allclose(got[start][changed], want, atol=2e-3 + 1e-3 * np.abs(want).max())
    # the trainable rows start as they would without the context fit
    plain = new_run(own, proxy, base.views.views, prior, plain_cfg, context=ctx)
    assert plain.world_init()
    assert torch.equal(plain.params["sh"], run.params["sh"])
    assert torch.equal(plain.context["sh"], torch.from_numpy(ctx.sh.astype(np.float16)))
    tensors, meta = run.checkpoint()
    again = region(plain_cfg)
    again.restore(tensors, meta)
    assert torch.equal(again.context["sh"], run.context["sh"])
    with pytest.raises(ValueError, match="context_start"):
        new_run(own, proxy, base.views.views, prior, base.cfg, context=ctx,
                context_start=start[:-1])


def test_context_cull_renders_the_same_image_as_all_context_surfels():
    """render() passes the rasteriser only the context surfels whose bounding sphere reaches
    the view; the image (and the trainable rows' gradients) are those of all of them."""
    from lsd3d_usd.conditioning.visibility import spheres_in_view
    base = make_run(steps=2)
    V, F, ids = street()
    ctx = mesh_to_surfels(V, F, ids, count=6000, seed=3, sh_degree=1, color=(0.3, 0.6, 0.2))
    rng = np.random.default_rng(0)
    ctx.positions = (ctx.positions + rng.uniform(-40, 40, (ctx.n, 3)) * [1, 1, 0.1]
                     ).astype(np.float32)
    ctx.scales = (ctx.scales * rng.uniform(0.5, 30.0, (ctx.n, 1))).astype(np.float32)  # some large
    run = new_run(base.field(), (V, F, ids), base.views.views, ClassColourTestPrior(),
                  base.cfg, context=ctx)
    checked = 0
    for v in base.views.views:
        cam = v.camera
        kept = spheres_in_view(run.context["means"].numpy(), run.context.radii, cam)
        checked += int((~kept).sum() > 0 and kept.sum() > 0)
        got = run.render(cam)
        a = run.state.activated()
        n_own = a["means"].shape[0]
        a = {k: torch.cat([a[k].detach(), run.context[k].to(a[k].dtype)]) for k in a}
        from lsd3d_usd.render.rasterize import rasterize
        from lsd3d_usd.render.raster_types import RasterSettings
        want = rasterize(a["means"], a["quats"], a["scales"], a["opacities"], a["sh"],
                         cam.viewmat, cam.K, cam.width, cam.height,
                         settings=RasterSettings.for_camera(cam))
        torch.testing.assert_close(got.rgb, want.rgb, rtol=0, atol=1e-6)
        torch.testing.assert_close(got.alpha, want.alpha, rtol=0, atol=1e-6)
        # the context's colours are kept in half precision: within a display step of float32
        a["sh"][n_own:] = torch.from_numpy(ctx.sh)
        full = rasterize(a["means"], a["quats"], a["scales"], a["opacities"], a["sh"],
                         cam.viewmat, cam.K, cam.width, cam.height,
                         settings=RasterSettings.for_camera(cam))
        torch.testing.assert_close(got.rgb, full.rgb, rtol=0, atol=1e-3)
        n = run.params["means"].shape[0]
        assert torch.equal(got.visible_index[got.visible_index < n],
                           want.visible_index[want.visible_index < n])
    assert checked >= 3          # views that dropped some context surfels and kept others


def test_checkpoint_tensors_stream_to_a_file_safetensors_reads(tmp_path):
    """safetensors_parts writes the library's format piece by piece: every dtype a checkpoint
    holds, empty and 0-d tensors, read back by safetensors itself bit for bit."""
    from safetensors.torch import load_file, save
    from lsd3d_usd import scene as S
    from lsd3d_usd.ggds.run.store import safetensors_parts
    g = torch.Generator().manual_seed(0)
    tensors = {"params.sh": torch.randn(7, 9, 3, generator=g),
               "adam.t": torch.arange(7, dtype=torch.int64),
               "face_index": torch.arange(5, dtype=torch.int32), "mask": torch.tensor([True, False]),
               "f64": torch.randn(3, dtype=torch.float64, generator=g), "u8": torch.arange(3, dtype=torch.uint8),
               "f16": torch.randn(4, 3, generator=g).half(),
               "empty": torch.zeros(0, 3), "scalar": torch.tensor(2.5),
               "strided": torch.randn(4, 6, generator=g)[:, ::2]}
    path = S.atomic_write_parts(tmp_path / "state.safetensors", safetensors_parts(tensors))
    back = load_file(path)
    assert sorted(back) == sorted(tensors)
    for k, v in tensors.items():
        assert back[k].dtype == v.dtype and back[k].shape == v.shape and torch.equal(back[k], v)
    # the same size as the library's own file (same header fields and padding, same data)
    assert path.stat().st_size == len(save({k: v.contiguous() for k, v in tensors.items()}))


def test_colour_floor_holds_the_updated_rows_base_colour():
    """floor_colour lifts only the given rows' channels below the floor (their other
    coefficients and every other row untouched); all rows without ``rows``; 0 turns it off;
    a step leaves no visible row below it."""
    from lsd3d_usd.shmath import C0
    run = make_run(steps=5)
    st = run.state
    sh = st.params["sh"]
    with torch.no_grad():
        sh[:, 0, :] = -10.0                       # base colour 0.5 - 2.8: clamped black
    before = sh.detach().clone()
    st.floor_colour(torch.arange(0, 100))
    base = 0.5 + C0 * sh.detach()[:, 0, :]
    assert torch.allclose(base[:100], torch.full_like(base[:100], 0.002), atol=1e-6)
    assert torch.equal(sh.detach()[100:], before[100:]) and torch.equal(sh.detach()[:100, 1:],
                                                                        before[:100, 1:])
    st.floor_colour()
    assert (0.5 + C0 * sh.detach()[:, 0, :]).min() >= 0.002 - 1e-6
    off = make_run(steps=5, colour_floor=0.0)
    with torch.no_grad():
        off.state.params["sh"][:, 0, :] = -10.0
    off.state.floor_colour()
    assert (off.state.params["sh"][:, 0, :] == -10.0).all()
    with torch.no_grad():                         # a step: its visible rows end above the floor
        sh[:, 0, :] = -10.0
    rec = run.step()
    assert rec["visible"] > 0
    lifted = (0.5 + C0 * sh.detach()[:, 0, :]).min(1).values >= 0.002 - 1e-6
    assert lifted.sum() >= rec["visible"] and not lifted.all()


def test_stored_configuration_predating_the_dark_colour_options_runs_as_it_did():
    """A run stored before the colour floor and the relative SH steps existed resumes
    without them (recorded 0), not with today's defaults."""
    from lsd3d_usd import configtree as ct
    stored = ct.to_dict(GGDSConfig())
    del stored["colour_floor"], stored["lr"]["sh_relative"]
    old = ct.from_dict(GGDSConfig, stored)
    assert old.colour_floor == 0.0 and old.lr.sh_relative == 0.0
    assert GGDSConfig().colour_floor > 0 and GGDSConfig().lr.sh_relative > 0


def test_colour_start_makes_the_surfels_no_training_view_sees_opaque():
    """Rows only fit views see (or none) start at opacity >= ggds.untrained_opacity; rows a
    training view sees keep theirs for the steps to learn; more training views, fewer such
    rows; 0 turns it off."""
    import dataclasses
    from lsd3d_usd.ggds.priors.procedural import ProceduralPrior
    base = make_run(steps=2)
    views = base.views.views
    a, b = views[:2], views[2:]
    prior = ProceduralPrior()
    init = torch.sigmoid(base.params["opacities"]).detach().clone()

    def raised(train, fit, **cfg):
        r = new_run(base.field(), base.conditioning.proxy, train, prior,
                    dataclasses.replace(base.cfg, **cfg), fit_views=fit)
        assert r.world_init()
        op = torch.sigmoid(r.params["opacities"]).detach()
        up = op > init + 1e-6
        assert torch.equal(op[~up], init[~up])
        assert (op[up] >= 0.99 - 1e-5).all()
        return up
    few, many = raised(a, b), raised(a + b, [])
    assert few.any() and many.sum() < few.sum() and not many[~few].any()
    assert not raised(a, b, untrained_opacity=0.0).any()
