"""Chunk-wise GGDS: regions and phases, conditioning on neighbours, resume with finished
chunks untouched, a failing chunk named in one line with the scene left valid."""
import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
from pxr import Sdf

from conftest import ROOT, generate_small
from lsd3d_usd import scene as S
from lsd3d_usd import validation
from lsd3d_usd.errors import InputError
from lsd3d_usd.ggds.settings import RegionConfig
from lsd3d_usd.ggds.regions.inputs import region_context
from lsd3d_usd.ggds.regions.plan import Region, plan_regions

LAYOUT = ROOT / "samples" / "layouts" / "hand_crossing.usda"   # 4 chunks: (-1|0, -1|0)
CHUNKED = {"regions": {"mode": "chunk", "views_per_chunk": 3}, "held_out": 1}
# ... with both border options on (ggds.regions.fit_context, share_views)
BORDERS = {"regions": {**CHUNKED["regions"], "fit_context": True, "share_views": True},
           "held_out": 1}


def gen(out, run=None, **kw):
    """The small scene as chunk regions (CHUNKED), one worker unless asked."""
    return generate_small(out, {"workers": 1, **(run or {})},
                          **{"steps": 3, "seed": 0, "views": 128, "env_resolution": (64, 32),
                             "resolution": (48, 32), "ggds": CHUNKED, **kw})


def test_small_scenes_are_one_region_and_phases_share_no_band():
    keys = [(i, j) for i in range(3) for j in range(3)]
    assert plan_regions(keys[:4], RegionConfig()) == [[Region(tuple(sorted(keys[:4])), "")]]
    dense = {k: {"count": 400_000} for k in keys[:4]}     # small in extent, not in surfels
    assert sum(len(p) for p in plan_regions(dense, RegionConfig())) == 4
    phases = plan_regions(keys, RegionConfig(mode="chunk"))
    assert len(phases) == 4 and sorted(r.keys[0] for ph in phases for r in ph) == sorted(keys)
    for ph in phases:   # no two regions of a phase touch (8-neighbourhood)
        for a in ph:
            for b in ph:
                if a is not b:
                    assert max(abs(a.keys[0][0] - b.keys[0][0]),
                               abs(a.keys[0][1] - b.keys[0][1])) >= 2
    corridor = plan_regions([(i, 0) for i in range(7)], RegionConfig())
    assert len(corridor) == 2 and [len(p) for p in corridor] == [4, 3]
    with pytest.raises(InputError, match="no surfel chunks"):
        plan_regions([], RegionConfig())


@pytest.fixture(scope="module")
def chunked(tmp_path_factory):
    out = tmp_path_factory.mktemp("regions") / "scene"
    summary = gen(out)
    return out, summary


def test_chunk_mode_writes_every_chunk_and_a_valid_scene(chunked):
    out, summary = chunked
    g = summary["ggds"]
    assert g["regions"] == 4 and g["complete"] and g["steps"] == 3
    sc = S.Scene.open(out)
    run = sc.runs()[0]
    assert sorted(p.name for p in (out / "layers" / f"{run.name}_chunks").iterdir()) == \
        ["chunk_0_0.usdc", "chunk_0_m1.usdc", "chunk_m1_0.usdc", "chunk_m1_m1.usdc"]
    layer = Sdf.Layer.FindOrOpen(str(run.path))
    assert len(layer.GetPrimAtPath(S.SURFELS_PATH).nameChildren) == 4
    assert [p.line() for p in validation.validate(out) if p.severity == "error"] == []
    per = json.loads((out / "ggds" / run.name / "summary.json").read_text())["per_region"]
    assert set(per) == {"chunk_0_0", "chunk_0_m1", "chunk_m1_0", "chunk_m1_m1"}
    assert all(r["complete"] and r["stepsDone"] == 3 for r in per.values())
    plan = json.loads((out / "ggds" / run.name / "run.json").read_text())
    assert plan["complete"] and len(plan["phases"]) == 4
    # the border options are off by default
    assert all(r["context_colour_start"] == 0 and r["neighbour_views"] == 0
               for r in per.values())


def test_neighbours_condition_a_region_within_the_band(chunked):
    out, _ = chunked
    sc = S.Scene.open(out)
    region = Region(((0, 0),), "chunk_0_0")
    ctx, initial = region_context(sc, sc.runs()[0].name, region, set(), band_m=20.0,
                                  chunk_size=100.0)
    assert initial.shape == (ctx.n,) and initial.all()
    p = ctx.positions
    tol = 1e-3   # a surfel seeded on a neighbour's edge stays with it (ggds.initial.chunk_owners)
    inside = (p[:, 0] > tol) & (p[:, 0] < 100 - tol) & (p[:, 1] > tol) & (p[:, 1] < 100 - tol)
    assert ctx.n > 0 and not inside.any()
    assert np.all((p[:, 0] >= -20) & (p[:, 1] >= -20) & (p[:, 0] <= 120) & (p[:, 1] <= 120))
    # a finished neighbour conditions with its optimised surfels, not its initial ones
    run = sc.runs()[0].name
    # (optimised surfels may have moved across the band's edge: at most those near it)
    edge = np.minimum.reduce([np.abs(p[:, 0] + 20), np.abs(p[:, 1] + 20), np.abs(p[:, 0] - 120),
                              np.abs(p[:, 1] - 120)]) < 0.05
    done, initial = region_context(sc, run, region, {(-1, 0), (0, -1), (-1, -1)}, 20.0, 100.0)
    assert abs(done.n - ctx.n) <= edge.sum() and not initial.any()
    def rows(f):   # a surfel as its position and colour
        return [tuple(r) for r in np.concatenate([f.positions, f.sh.reshape(f.n, -1)], 1).tolist()]
    initial_rows = set(rows(ctx))
    assert not any(r in initial_rows for r in rows(done))   # the optimised surfels
    # one neighbour finished: only the others' rows are initial, and as they were
    part, initial = region_context(sc, run, region, {(-1, 0)}, 20.0, 100.0)
    assert abs(part.n - ctx.n) <= edge.sum() and 0 < initial.sum() < part.n
    both = rows(part)
    assert all(r in initial_rows for r, i in zip(both, initial) if i)
    assert not any(r in initial_rows for r, i in zip(both, initial) if not i)
    assert region_context(sc, run, region, set(), 0.0, 100.0) is None


def test_interrupted_run_resumes_with_finished_chunks_untouched(tmp_path, monkeypatch):
    from lsd3d_usd.ggds.run import optimisation as R
    out = tmp_path / "scene"
    real = R.GGDSRun.step
    calls = {"n": 0}

    def stop_in_third_region(self):
        calls["n"] += 1
        if calls["n"] == 8:          # regions 1-2 done (3 steps each), region 3 at step 2
            raise KeyboardInterrupt
        return real(self)
    monkeypatch.setattr(R.GGDSRun, "step", stop_in_third_region)
    with pytest.raises(KeyboardInterrupt):   # with the border options: their state resumes
        gen(out, checkpoint_every=1, ggds=BORDERS)
    monkeypatch.setattr(R.GGDSRun, "step", real)
    sc = S.Scene.open(out)
    run = sc.unfinished_runs()[0]
    assert [p.line() for p in validation.validate(out) if p.severity == "error"] == []
    folder = out / "layers" / f"{run}_chunks"
    done = {f.name: f.stat().st_mtime_ns for f in folder.iterdir()}
    assert len(done) == 3            # two finished regions + the interrupted one so far
    progress = {d.name: json.loads((d / "progress.json").read_text())
                for d in (out / "ggds" / run).iterdir() if (d / "progress.json").is_file()}
    finished = [n for n, p in progress.items() if p["complete"]]
    assert len(finished) == 2
    summary = gen(out, run={"resume": True}, ggds=BORDERS)
    assert summary["ggds"]["complete"] and summary["ggds"]["regions"] == 4
    for name in finished:
        f = f"{name}.usdc"
        assert (folder / f).stat().st_mtime_ns == done[f]      # finished chunks untouched
    assert S.Scene.open(out).unfinished_runs() == []
    per = json.loads((out / "ggds" / run / "summary.json").read_text())["per_region"]
    plan = json.loads((out / "ggds" / run / "run.json").read_text())
    # the two regions finished before the interruption still report their task figures
    for name in finished:
        assert per[name]["wall_s"] > 0 and per[name]["views"] > 0 and per[name]["cpu_s"] > 0
    # the third region (interrupted, resumed from its checkpoint) still has an unfinished
    # neighbour, whose band colours the start fitted came back with it; the last region's
    # neighbours had all finished
    third, last = (per[plan["phases"][i][0]] for i in (2, 3))
    assert 0 < third["context_colour_start"] < third["context"]
    assert last["context"] > 0 and last["context_colour_start"] == 0
    # both trained on some of their neighbours' views too (share_views)
    assert third["neighbour_views"] > 0 and last["neighbour_views"] > 0
    from lsd3d_usd.ggds.run.store import run_views
    views = run_views(S.Scene.open(out), run)
    assert len({json.dumps(v, sort_keys=True) for v in views}) == len(views) <= 12


def test_worker_pool_records_each_regions_task(chunked, tmp_path):
    """Regions run in worker processes: each finished region's task record (task.json,
    what a resumed run reports) holds its worker's peak memory, and the run's worker peak is
    the largest of them."""
    src, _ = chunked
    out = tmp_path / "scene"
    shutil.copytree(src, out)
    summary = gen(out, run={"workers": 2})["ggds"]
    assert summary["complete"]
    tasks = {d.name: json.loads((d / "task.json").read_text())
             for d in (out / "ggds" / summary["run"]).iterdir() if (d / "task.json").is_file()}
    assert set(tasks) == {"chunk_0_0", "chunk_0_m1", "chunk_m1_0", "chunk_m1_m1"}
    assert all(t["peak_rss_mb"] > 0 and t["wall_s"] > 0 and t["views"] > 0 for t in tasks.values())
    assert summary["worker_peak_rss_mb"] == max(t["peak_rss_mb"] for t in tasks.values())


def test_failing_chunk_is_named_and_the_scene_stays_valid(chunked, tmp_path):
    src, _ = chunked
    out = tmp_path / "scene"
    shutil.copytree(src, out)
    from lsd3d_usd.splats import chunkio
    bad = chunkio.chunk_folder(out / "layers" / "surfels.usdc") / "chunk_0_0.usdc"
    bad.write_bytes(bad.read_bytes()[:100])
    with pytest.raises(InputError, match=r"GGDS chunk chunk_0_0 failed: .*--resume"):
        gen(out, run={"workers": 2})
    # the corrupt file is reported (validate names it) and nothing else went wrong
    lines = [p.line() for p in validation.validate(out) if p.severity == "error"]
    assert lines and all("chunk_0_0" in ln or "crate file corrupt" in ln for ln in lines)


def test_cameras_layer_holds_every_regions_training_views(chunked):
    """Chunk mode: /World/Cameras/Train are the views sampled for each region, in
    region-name order, each naming its region; what a region trained on (views.json) is,
    in the same order, those of them that see its surfels."""
    from lsd3d_usd.conditioning.view_sampling import View
    from lsd3d_usd.ggds.run.store import run_views
    from lsd3d_usd.render.camera import from_usd
    out, summary = chunked
    sc = S.Scene.open(out)
    trained = [View.from_json(d) for d in run_views(sc, sc.runs()[0].name)]
    assert summary["cameras"]["train"] == 12 and 0 < len(trained) <= 12
    stage = sc.open_stage(load=False)
    regions, poses = [], []
    for k in range(12):
        prim = stage.GetPrimAtPath(f"/World/Cameras/Train/Train_{k:03d}")
        v = trained[0]
        poses.append(from_usd(prim, None, v.camera.width, v.camera.height, conform="stretch").pose)
        regions.append(prim.GetAttribute("lsd3d:camera:region").Get())
    assert regions == sorted(regions) and set(regions) == {"chunk_0_0", "chunk_0_m1", "chunk_m1_0",
                                                          "chunk_m1_m1"}
    k = 0
    for v in trained:      # a subsequence of the authored cameras
        while k < 12 and not np.allclose(poses[k], v.camera.pose, atol=1e-5):
            k += 1
        assert k < 12, "a trained view is not among the scene's Train cameras"
        k += 1


def test_views_seeing_keeps_the_views_a_region_is_in():
    from lsd3d_usd.conditioning.view_sampling import View
    from lsd3d_usd.conditioning.visibility import views_seeing
    from lsd3d_usd.render.camera import Camera, look_at
    pts = np.random.default_rng(0).uniform([0, 0, 0], [10, 10, 2], (50_000, 3))

    def view(eye, target):
        cam = Camera.from_fov(64, 36, 70, pose=look_at(np.array(eye, float),
                                                       np.array(target, float), (0, 0, 1)))
        return View(cam, "lane", "l0", 0.0)
    towards, away = view([-20, 5, 2], [5, 5, 1]), view([-20, 5, 2], [-40, 5, 1])
    beyond = view([30, -30, 2], [60, -60, 1])
    assert views_seeing([towards, away, beyond], pts) == [towards]
    assert views_seeing([towards], np.array([[-20.0, 5.0, 2.0]])) == []   # at the eye: z = 0


def test_fit_views_stand_beyond_the_training_margin_within_the_fit_margin():
    from lsd3d_usd.ggds.settings import GGDSConfig
    from lsd3d_usd.ggds.regions.region_views import region_fit_views
    from lsd3d_usd.layout.usdio import read_layout
    from dataclasses import replace
    layout = read_layout(LAYOUT)
    g = GGDSConfig(resolution=(48, 32), elevated_frac=0.125)     # the counts below
    g = replace(g, world_init_views=0.0, elevated_train=True,    # (fit-only elevated: below)
                regions=replace(g.regions, views_per_chunk=40, fit_view_frac=1.0))
    region = Region(((0, 0),), "chunk_0_0")
    views = region_fit_views(layout, g, 0, region)
    assert 0 < len(views) <= 40
    for v in views:
        x, y = v.camera.center[:2]
        inner = -20 <= x <= 120 and -20 <= y <= 120
        reach = 50 + 8.5     # lane points inside the fit margin; novel views stand up to 8 m off
        assert not inner and -reach <= x <= 100 + reach and -reach <= y <= 100 + reach
    assert [v.camera.center.tolist() for v in region_fit_views(layout, g, 0, region)] == \
        [v.camera.center.tolist() for v in views]                       # deterministic
    whole = Region(((0, 0),), "")          # a whole-scene region: ggds.world_init_views
    assert region_fit_views(layout, g, 0, whole) == []
    half = region_fit_views(layout, replace(g, world_init_views=0.5), 0, whole)
    # 0.5 x 128 views sampled like the training views, and 0.5 x elevated_frac x 128 elevated
    assert [v.kind for v in half] == ["lane"] * 48 + ["novel"] * 16 + ["elevated"] * 8
    off = replace(g, regions=replace(g.regions, fit_margin_m=20.0))
    assert region_fit_views(layout, off, 0, region) == []
    # world_init_views: as many views again sampled like the training views (inside the
    # training margin), ahead of the ones beyond it, which stay as they were
    both = region_fit_views(layout, replace(g, world_init_views=1.0), 0, region)
    elevated = [v for v in both if v.kind == "elevated"]
    assert len(elevated) == 5               # elevated_frac x views_per_chunk, inside the margin
    for v in elevated:      # each looks at a lane point inside the training margin
        c, f = v.camera.center, v.camera.pose[:3, 2]
        x, y = (c + f * (v.camera.center[2] - v.offset_m - c[2]) / f[2])[:2]
        assert -20 - 0.6 <= x <= 120 + 0.6 and -20 - 0.6 <= y <= 120 + 0.6
    # not trained on (the default): the colour start fits to the 5 region_views would train
    # on too, then to the 5 above
    fit_only = region_fit_views(layout, replace(g, world_init_views=1.0, elevated_train=False),
                                0, region)
    assert [v.camera.pose.tolist() for v in fit_only if v.kind == "elevated"][5:] == \
        [v.camera.pose.tolist() for v in elevated]
    assert sum(v.kind == "elevated" for v in fit_only) == 10
    both = [v for v in both if v.kind != "elevated"]
    assert len(both) == 40 + len(views)
    assert [v.camera.center.tolist() for v in both[40:]] == \
        [v.camera.center.tolist() for v in views]
    for v in both[:40]:
        x, y = v.camera.center[:2]
        assert -20 - 8.5 <= x <= 120 + 8.5 and -20 - 8.5 <= y <= 120 + 8.5


def test_a_region_also_trains_on_its_neighbours_views_near_it():
    from lsd3d_usd.ggds.settings import GGDSConfig
    from lsd3d_usd.ggds.regions.region_views import neighbour_views, region_views
    from lsd3d_usd.layout.usdio import read_layout
    from dataclasses import replace
    layout = read_layout(LAYOUT)
    g = GGDSConfig(resolution=(48, 32))
    g = replace(g, regions=replace(g.regions, views_per_chunk=40))
    keys = {(-1, -1), (-1, 0), (0, -1), (0, 0)}
    region = Region(((0, 0),), "chunk_0_0")

    def centres(views):
        return {tuple(np.round(v.camera.center, 9)) for v in views}
    theirs = set()
    for k in keys - {(0, 0)}:
        theirs |= centres(region_views(layout, g, 5, Region((k,), S.chunk_prim_name(*k).lower()))[0])
    got = neighbour_views(layout, g, 5, region, keys)
    assert got and centres(got) <= theirs           # the neighbours' own training views ...
    m = g.regions.view_margin_m                     # ... those standing within the margin
    assert all(-m <= v.camera.center[0] <= 100 + m and -m <= v.camera.center[1] <= 100 + m
               for v in got)
    near = [c for c in theirs if -m <= c[0] <= 100 + m and -m <= c[1] <= 100 + m]
    assert len(got) == len(near) < len(theirs)
    assert not centres(got) & centres(region_views(layout, g, 5, region)[0])
    # a neighbour without surfels has no region and no views
    assert len(neighbour_views(layout, g, 5, region, keys - {(-1, 0)})) < len(got)
    wide = replace(g, regions=replace(g.regions, view_margin_m=60.0))
    assert len(neighbour_views(layout, wide, 5, region, keys)) > len(got)


def test_eval_measures_seams_of_a_chunked_scene(chunked):
    from lsd3d_usd.eval.evaluate import render_view
    from lsd3d_usd.eval.report import _seams_html
    from lsd3d_usd.eval.seams_eval import measure_seams, pooled_psnr, view_errors
    from lsd3d_usd.conditioning.view_sampling import sample_views
    from lsd3d_usd.layout.usdio import read_layout
    from lsd3d_usd.proxy.usdio import proxy_arrays
    from lsd3d_usd.views.stage_data import SceneReader
    out, _ = chunked
    sc = S.Scene.open(out)
    layout = read_layout(sc.layer_path("layout"))
    cams = [v.camera for v in sample_views(layout, 6, 64, 40, seed=5)]
    reader = SceneReader(sc.open_stage(), actors=False)
    frames = [render_view(reader.surfels(), reader.env(), c) for c in cams]
    res, why = measure_seams(sc, sc.runs()[0].name, layout, proxy_arrays(sc.layer_path("proxy")),
                             cams, frames)
    assert why is None
    assert res["pixels"]["border"] > 0 and res["pixels"]["interior"] > 0   # the crossing's borders
    assert res["border_coverage"] > 0.5
    lo, hi = res["psnr_drop_matched_ci95_db"]
    assert lo <= hi and 0 < res["matched_border_frac"] <= 1
    assert "class and distance matched" in _seams_html(SimpleNamespace(seams=res))
    none, why = measure_seams(sc, None, layout, proxy_arrays(sc.layer_path("proxy")), cams, frames)
    assert none is None and "no GGDS run" in why
    # PSNR of given views against the same targets: worse for a frame that is off its target

    def view_psnrs(*a, **kw):
        errs, why = view_errors(*a, **kw)
        return [pooled_psnr([e]) for e in errs], why
    psnrs, why = view_psnrs(sc, sc.runs()[0].name, proxy_arrays(sc.layer_path("proxy")), cams,
                            frames)
    assert why is None and len(psnrs) == len(cams) and all(5 < p < 99 for p in psnrs)
    grey = [dict(fr, rgb=np.full_like(fr["rgb"], 0.5)) for fr in frames]
    worse, _ = view_psnrs(sc, sc.runs()[0].name, proxy_arrays(sc.layer_path("proxy")), cams, grey)
    assert np.mean(worse) < np.mean(psnrs) - 3
    # scored on one region's surface only: nan for views that do not see it
    away, _ = view_psnrs(sc, sc.runs()[0].name, proxy_arrays(sc.layer_path("proxy")), cams,
                         frames, region=(1e5, 1e5, 1e5 + 1, 1e5 + 1))
    assert len(away) == len(cams) and all(np.isnan(away))
    near, _ = view_psnrs(sc, sc.runs()[0].name, proxy_arrays(sc.layer_path("proxy")), cams,
                         frames, region=(-1e4, -1e4, 1e4, 1e4))
    assert all(np.isfinite(near)) and near != psnrs     # the sky is left out


def test_lane_length_inside_a_box():
    from lsd3d_usd.conditioning.view_sampling import lane_length_inside
    from lsd3d_usd.layout.model import LaneCenter, Layout
    layout = Layout(lanes=[LaneCenter(id="l0", points=[[2, -1.5, 0], [38, -1.5, 0]]),
                           LaneCenter(id="l1", points=[[10, -20, 0], [10, 20, 0]])])
    # the lanes views sampled in the box are drawn from: l1 crosses it between two vertices
    # outside, so sample_views(region=box, clip=True) never stands on it
    box = (0, -5, 20, 5)
    assert lane_length_inside(layout, box) == pytest.approx(18, abs=0.6)
    from lsd3d_usd.conditioning.view_sampling import sample_views
    assert {v.lane_id for v in sample_views(layout, 50, 32, 24, seed=1, region=box,
                                            clip=True)} == {"l0"}
    assert lane_length_inside(layout, (100, 100, 200, 200)) == 0.0
    assert lane_length_inside(layout, (-100, -100, 100, 100)) == pytest.approx(36 + 40, abs=1.0)


def test_eval_seams_against_the_same_layout_without_chunk_seams(chunked, tmp_path):
    """eval --seams-reference: the same layout optimised as one region, rendered from the
    evaluated scene's held-out views, gives the part of the seam drop the chunking adds; a
    reference that is the scene itself, chunk-wise, or made with other targets is refused
    before anything is rendered or written."""
    from lsd3d_usd.eval.evaluate import eval_options, evaluate
    out, _ = chunked
    one = tmp_path / "one"
    gen(one, ggds={"regions": {"mode": "scene"}, "views": 6, "held_out": 1})
    before = {f: f.stat().st_mtime_ns for f in one.rglob("*") if f.is_file()}

    def ev(scene, ref, name):
        return evaluate(eval_options(scene=scene, out_dir=tmp_path / name, n_seen=3, n_heldout=4,
                                    per_bin=1, bins=(1.0,), resolution=(64, 40), frames=2,
                                    progress=False, log=lambda *a: None, prior_baseline=False,
                                    seams_reference=ref)).to_json()
    res = ev(out, one, "ev")
    vs = res["seams"]["vs_reference"]
    assert vs["scene"] == str(one) and vs["views"] == 4            # the held-out views only
    assert vs["difference_db"] == pytest.approx(vs["scene_db"] - vs["reference_db"], abs=2e-3)
    lo, hi = vs["ci95_db"]
    assert lo <= vs["difference_db"] <= hi
    assert "adds" in (tmp_path / "ev" / "report.html").read_text()
    # the reference is read, never written
    assert {f: f.stat().st_mtime_ns for f in one.rglob("*") if f.is_file()} == before
    other = tmp_path / "other"                    # another environment: other targets
    gen(other, ggds={"regions": {"mode": "scene"}, "views": 6, "held_out": 1},
        env_resolution=(32, 16))
    for scene, ref, match in ((out, other, "used another env"), (out, out, "scene itself"),
                              (one, out, "chunk regions"), (out, tmp_path / "nope", "nope")):
        with pytest.raises(InputError, match=match):
            ev(scene, ref, "bad")
        assert not (tmp_path / "bad").exists()
