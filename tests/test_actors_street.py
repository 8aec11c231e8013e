"""Pedestrians and cyclists with the IDM traffic (`street.simulate_street`), over many seeds on
the README sample and a generated 400 m layout: boxes never overlap, pedestrians stay on
sidewalks and crosswalks, vehicles stay out of occupied crosswalks, cyclists stay in their
lane, speeds stay in the documented ranges. The runs are computed once per layout (arrays
only, no scenes), with mid-block crossings five times as likely as by default so that they
happen in 5 s runs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Point, Polygon

from lsd3d_usd.actors import assets as A
from lsd3d_usd.actors import people as P
from lsd3d_usd.actors.pedestrians import WalkParams, obb_overlap
from lsd3d_usd.actors.sidewalks import build_walkable
from lsd3d_usd.actors.street import STATES, StreetParams, simulate_street
from lsd3d_usd.layout.routes import LaneGraph
from lsd3d_usd.layout.model import Crosswalk, LaneCenter, Layout

SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "layouts" / "hand_crossing.usda"
SEEDS = range(50)
SECONDS, FPS = 5.0, 5.0
PARAMS = StreetParams(walk=WalkParams(midblock_rate=0.05))
_car, _van = (tuple(A.dimensions_of(A.vehicle_meshes(k))[:2]) for k in ("car", "van"))
VEHICLES = [_car] * 6 + [_van] * 2                  # the procedural car and van
_dims = {k: P.dimensions(k) for k in ("adult", "adult_broad", "child", "cyclist")}
CYCLISTS = [tuple(_dims["cyclist"][:2])] * 4
PEOPLE = ([("adult", *_dims["adult"][:2], False)] * 5 + [("adult_broad", *_dims["adult_broad"][:2], False)] * 3
          + [("child", *_dims["child"][:2], True)] * 4)


def _layouts():
    from lsd3d_usd.layout.generator import generate
    from lsd3d_usd.layout.usdio import read_layout
    return {"sample": read_layout(SAMPLE), "generated400": generate(3, (400.0, 400.0))}


@pytest.fixture(scope="module", params=["sample", "generated400"])
def runs(request):
    L = _layouts()[request.param]
    w, g = build_walkable(L), LaneGraph(L, bike_lanes=True)
    out = [simulate_street(L, VEHICLES, CYCLISTS, PEOPLE, seed=s, seconds=SECONDS, fps=FPS,
                           params=PARAMS, walkable=w, graph=g) for s in SEEDS]
    return L, w, g, out


def _boxes(run):
    tr, pe = run.traffic, run.people
    C = np.concatenate([tr.position[..., :2], pe.position[..., :2]])
    Y = np.concatenate([tr.yaw, pe.yaw])
    H = np.concatenate([np.stack([tr.lengths / 2, tr.widths / 2], 1), pe.dims / 2])
    return C, Y, H


def _poly(c, yaw, h) -> Polygon:
    u = np.array([np.cos(yaw), np.sin(yaw)]) * h[0]
    v = np.array([-np.sin(yaw), np.cos(yaw)]) * h[1]
    return Polygon([c - u - v, c + u - v, c + u + v, c - u + v])


def test_obb_overlap_matches_polygon_reference():
    rng = np.random.default_rng(0)
    n = 4000
    c1, c2 = rng.uniform(-2, 2, (n, 2)), rng.uniform(-2, 2, (n, 2))
    y1, y2 = rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, n)
    h1, h2 = rng.uniform(0.1, 1.5, (n, 2)), rng.uniform(0.1, 1.5, (n, 2))
    got = obb_overlap(c1, y1, h1, c2, y2, h2)
    ref = np.array([_poly(c1[i], y1[i], h1[i]).intersection(_poly(c2[i], y2[i], h2[i])).area > 1e-9
                    for i in range(n)])
    assert got.sum() > n // 10 and (~got).sum() > n // 10
    assert np.array_equal(got, ref)


def test_runs_place_everyone_and_people_do_things(runs):
    L, w, g, out = runs
    assert w.tracks and w.crosswalks
    for r in out:
        assert r.people.n == len(PEOPLE)
        assert int(r.traffic.cyclist.sum()) == len(CYCLISTS)
    states = np.concatenate([r.people.state.ravel() for r in out])
    for s in ("walk", "wait", "cross", "stand"):
        assert (states == STATES.index(s)).any(), s
    # mid-block crossings (polygons after the crosswalks) happen too
    K = len(w.crosswalks)
    assert any(((r.people.crosswalk >= K) & (r.people.state == STATES.index("cross"))).any() for r in out)


def test_no_two_boxes_overlap_at_any_sample(runs):
    _, _, _, out = runs
    worst = []
    for r in out:
        C, Y, H = _boxes(r)
        i, j = np.triu_indices(len(C), 1)
        for k in range(C.shape[1]):
            o = obb_overlap(C[i, k], Y[i, k], H[i], C[j, k], Y[j, k], H[j])
            if o.any():
                worst.append((r.seed, k, int(i[o][0]), int(j[o][0])))
    assert not worst, worst[:5]


def test_pedestrians_stay_on_sidewalks_and_crosswalks(runs):
    """... or on the corridor of their own mid-block crossing."""
    _, w, _, out = runs
    allowed = w.allowed(pad=1e-6)
    shapely.prepare(allowed)
    walk = w.area.buffer(w.curb_width + 0.05)
    cw = shapely.union_all([c.polygon for c in w.crosswalks]).buffer(w.curb_width + 0.05)
    K = len(w.crosswalks)
    for r in out:
        pe = r.people
        P = pe.position[..., :2]
        own = np.zeros(P.shape[:2], bool)       # on the corridor of its own mid-block crossing
        for i, k in zip(*np.nonzero(pe.crosswalk >= K)):
            own[i, k] = r.polygons[pe.crosswalk[i, k]].buffer(1e-6).contains(Point(P[i, k]))
        flat = P.reshape(-1, 2)
        inside = shapely.contains_xy(allowed, flat[:, 0], flat[:, 1]).reshape(own.shape) | own
        assert inside.all(), (r.seed, P[~inside][:3])
        # on the road surface only on a crosswalk (or its own mid-block corridor)
        off_walk = ~shapely.contains_xy(walk, flat[:, 0], flat[:, 1]).reshape(own.shape) & ~own
        assert shapely.contains_xy(cw, P[off_walk][:, 0], P[off_walk][:, 1]).all()


def test_vehicles_stay_out_of_occupied_crosswalks_and_stop_for_them(runs):
    _, w, _, out = runs
    stopped = 0
    for r in out:
        polys = r.polygons           # the crosswalks, then the run's mid-block corridors
        tr = r.traffic
        for c in range(len(polys)):
            for k in np.flatnonzero(r.occupied[c]):
                for i in range(tr.n):
                    box = _poly(tr.position[i, k, :2], tr.yaw[i, k], (tr.lengths[i] / 2, tr.widths[i] / 2))
                    assert not box.intersects(polys[c]), (r.seed, c, k, i)
                    # approaching it on its lane: slowing down (the yielding happens, not
                    # only the absence of conflicts)
                    for cc, s_in, _ in r.crossings[tr.lane[i, k]]:
                        ahead = s_in - tr.s[i, k]
                        if cc == c and 0 < ahead < 30.0 and k + 1 < len(tr.t) and \
                                tr.speed[i, k + 1] < tr.speed[i, k] - 0.05:
                            stopped += 1
    assert stopped > 0


def test_cyclists_stay_within_their_lane(runs):
    L, _, g, out = runs
    for r in out:
        tr = r.traffic
        for i in np.flatnonzero(tr.cyclist):
            for k in range(len(tr.t)):
                lane = g.geoms[tr.lane[i, k]]
                d = LineString(lane.points[:, :2]).distance(Point(tr.position[i, k, :2]))
                assert d + tr.widths[i] / 2 <= lane.width / 2 + 1e-6, (r.seed, i, k, d, lane.id)


def test_speeds_within_documented_ranges(runs):
    _, _, _, out = runs
    p = StreetParams()
    vmax_walk = max(p.walk.speed_adult[1], p.walk.speed_child[1])
    moved = 0.0
    for r in out:
        tr, pe = r.traffic, r.people
        lim = tr.lane_limits[tr.lane]
        assert np.all(tr.speed <= lim + 1e-9) and np.all(tr.speed >= 0)
        cyc = tr.speed[tr.cyclist]
        assert np.all(cyc <= p.cyclist_speed[1] + 1e-9)
        moved = max(moved, float(cyc.max()))
        step = np.linalg.norm(np.diff(pe.position[..., :2], axis=1), axis=2)
        assert np.all(step <= vmax_walk / FPS + 1e-6)
        assert np.all(pe.speed <= vmax_walk + 1e-9)
        stand = pe.state[:, 0] == STATES.index("stand")
        assert np.all(step[stand] == 0)
    assert moved > 2.0


def test_deterministic_per_seed(runs):
    L, w, g, out = runs
    again = simulate_street(L, VEHICLES, CYCLISTS, PEOPLE, seed=out[3].seed, seconds=SECONDS,
                            fps=FPS, params=PARAMS, walkable=w, graph=g)
    assert np.array_equal(again.people.position, out[3].people.position)
    assert np.array_equal(again.traffic.position, out[3].traffic.position)
    assert not np.array_equal(out[4].people.position, out[3].people.position)


# ------------------------------------------------------------------ small cases
def _road_with_crosswalk(length=120.0, cw_x=60.0):
    lane = LaneCenter("a", points=[[0, -1.75, 0], [length, -1.75, 0]], speed_limit_mps=12.0)
    back = LaneCenter("b", points=[[length, 1.75, 0], [0, 1.75, 0]], speed_limit_mps=12.0)
    cw = Crosswalk("cw", polygon=[[cw_x - 1.5, -3.5, 0], [cw_x + 1.5, -3.5, 0],
                                  [cw_x + 1.5, 3.5, 0], [cw_x - 1.5, 3.5, 0]])
    return Layout(lanes=[lane, back], crosswalks=[cw])


def test_vehicle_stops_before_an_occupied_crosswalk_and_goes_after():
    from lsd3d_usd.actors.traffic import Simulation
    L = _road_with_crosswalk()
    w = build_walkable(L)
    assert len(w.crosswalks) == 1
    sim = Simulation(L, 0)
    sim.g.set_crosswalks([w.crosswalks[0].polygon])
    (_, s_in, s_out), = sim.g.crossings[sim.g.index["a"]]
    assert s_in < 58.5 - 1.75 + 0.3 and s_out > 61.5
    car = sim.add_ego(sim.g.route_indices(["a"]), 4.6, s=10.0, v=10.0)
    assert sim.crosswalk_clear(0)          # 45 m away at 10 m/s: it can stop
    sim.occupied = {0}
    for _ in range(200):
        sim.step(0.05)
    assert car.v < 0.05 and car.s + car.length / 2 <= s_in - sim.p.stop_margin + 1e-6
    assert not sim.crosswalk_clear(0) or car.s + car.length / 2 < s_in
    sim.occupied = set()
    for _ in range(200):
        sim.step(0.05)
    assert car.s - car.length / 2 > s_out   # drove on once the crosswalk was free


def test_pedestrian_waits_for_a_vehicle_that_cannot_stop():
    from lsd3d_usd.actors.traffic import Simulation
    L = _road_with_crosswalk()
    sim = Simulation(L, 0)
    w = build_walkable(L)
    sim.g.set_crosswalks([w.crosswalks[0].polygon])
    sim.add_ego(sim.g.route_indices(["a"]), 4.6, s=40.0, v=12.0)   # 15 m before it at 12 m/s
    assert not sim.crosswalk_clear(0)


def test_layout_without_sidewalks_places_no_pedestrians():
    lane = LaneCenter("a", points=[[0, 0, 0], [100, 0, 0]])
    L = Layout(lanes=[lane])
    no_walk = StreetParams()
    from lsd3d_usd.proxy.ground import GroundStyle
    w = build_walkable(L, style=GroundStyle(derive_sidewalks=False))
    assert not w.tracks
    r = simulate_street(L, [], CYCLISTS[:1], PEOPLE[:3], seed=0, seconds=1.0, fps=5.0,
                        params=no_walk, walkable=w)
    assert r.people.n == 0 and r.traffic.n == 1


def test_cyclists_take_bike_lanes_when_the_layout_has_them():
    car = LaneCenter("car", points=[[0, 0, 0], [100, 0, 0]], speed_limit_mps=12.0)
    bike = LaneCenter("bike", points=[[0, -2.5, 0], [100, -2.5, 0]], lane_type="bike",
                      widths=np.full(2, 1.5), speed_limit_mps=6.0)
    L = Layout(lanes=[car, bike])
    r = simulate_street(L, [(4.6, 1.8)] * 2, CYCLISTS[:2], [], seed=1, seconds=2.0, fps=5.0)
    tr = r.traffic
    ids = np.array(tr.lane_ids)
    assert set(ids[tr.lane[tr.cyclist].ravel()]) == {"bike"}
    assert set(ids[tr.lane[~tr.cyclist].ravel()]) == {"car"}
    assert np.allclose(tr.offset[tr.cyclist], 0.0)



def test_a_crossing_reaches_the_other_side():
    from lsd3d_usd.layout.usdio import read_layout
    L = read_layout(SAMPLE)
    r = simulate_street(L, VEHICLES[:4], [], PEOPLE, seed=2, seconds=14.0, fps=5.0)
    st, cw = r.people.state, r.people.crosswalk
    done = np.argwhere((st[:, :-1] == STATES.index("cross")) & (st[:, 1:] == STATES.index("walk")))
    assert len(done)
    i, k = done[0]
    c = r.walkable.crosswalks[int(cw[i, k])]
    start = np.flatnonzero(st[i] == STATES.index("cross"))[0]
    a, b = r.people.position[i, start, :2], r.people.position[i, k + 1, :2]
    axis = (c.b - c.a) / np.linalg.norm(c.b - c.a)
    # it went from one end of the crosswalk to the other, across the road
    assert abs(np.dot(b - a, axis)) > np.linalg.norm(c.b - c.a)


def test_parked_actors_keep_off_crosswalks_and_sidewalks():
    """add_actors parks with the crosswalks as footprints to avoid: no parked box on a
    crosswalk (where pedestrians cross) or on a sidewalk (where they walk)."""
    from lsd3d_usd.actors.placement import crosswalk_footprints, footprint, parked_placements
    from lsd3d_usd.layout.generator import generate
    L = generate(3, (400.0, 400.0))
    dims = {k: tuple(A.dimensions_of(A.vehicle_meshes(k))) for k in A.SPECS}
    cw = crosswalk_footprints(L)
    assert len(cw) == len(L.crosswalks)
    walk = build_walkable(L).area
    places = parked_placements(L, 200, 0, dims, avoid=cw)
    assert len(places) > 20
    for p in places:
        fp = footprint(p.position, p.yaw, dims[p.kind][0], dims[p.kind][1])
        assert not any(fp.intersects(c) for c in cw)
        assert fp.intersection(walk).area < 1e-6


def test_midblock_line_crosses_the_road_away_from_crosswalks():
    from lsd3d_usd.actors.sidewalks import midblock_line
    L = _road_with_crosswalk(length=200.0, cw_x=100.0)
    w = build_walkable(L)
    found = []
    for k, t in enumerate(w.tracks):
        for s in np.linspace(0, t.length, 200, endpoint=False):
            line = midblock_line(w, k, float(s))
            if line is None:
                continue
            p, jt, js, corridor = line
            q = w.tracks[jt].point(js)
            if not 10.0 < p[0] < 190.0:
                continue                 # the band of this layout (no extent) rounds the road ends
            found.append((p, q))
            assert abs(p[0] - q[0]) < 1e-6 and np.sign(p[1]) == -np.sign(q[1])   # straight across
            assert 7.0 < abs(p[1] - q[1]) < 12.0
            assert corridor.distance(w.crosswalks[0].polygon) >= 8.0
    assert len(found) > 20
    xs = np.array([p[0] for p, _ in found])
    assert not np.any(np.abs(xs - 100.0) < 8.0 + 1.5)


def test_rig_ego_stops_for_a_pedestrian_on_a_crosswalk():
    from lsd3d_usd.views.ego import track_from_route
    L = _road_with_crosswalk(length=120.0, cw_x=60.0)
    times = np.arange(0, 12.0, 0.1)
    free = track_from_route(L, ["a"], times)
    on_cw = track_from_route(L, ["a"], times, pedestrians=lambda t: np.array([[60.0, -1.0]]))
    gone = track_from_route(L, ["a"], times, pedestrians=lambda t: np.array([[60.0, -1.0]]) if t < 6.0
                            else np.zeros((0, 2)))
    assert free.positions[-1, 0] > 80.0
    front = on_cw.positions[:, 0] + 4.8 / 2
    assert front.max() < 58.5 - 1.0 + 1e-6 and abs(on_cw.positions[-1, 0] - on_cw.positions[-10, 0]) < 1e-3
    assert gone.positions[-1, 0] > 62.0          # drives on once the pedestrian has gone
