"""The one route API (layout.routes): arc length along a route, projection of a point onto
it and the nearest lane at a point, each against a plain float64 reference; seeded random
routes; routes on degenerate graphs."""
import math

import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from conftest import LAYOUT
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout.routes import LaneGraph, Route, default_route, parse_route, random_routes
from lsd3d_usd.layout.usdio import read_layout


def _lane(lid, pts, **kw):
    return m.LaneCenter(lid, points=np.array(pts, float), **kw)


def _bend():
    """Two lanes: east 30 m, then a 90-degree corner north 20 m (a vertex at the corner)."""
    L = m.Layout()
    L.add(_lane("a", [[0, 0], [10, 0], [30, 0]], successors=["b"]))
    L.add(_lane("b", [[30, 0], [30, 20]], predecessors=["a"]))
    L.add(_lane("back", [[30, 3.5], [0, 3.5]]))                 # the oncoming lane beside a
    return L


def _ref_project(pts, p):
    """Nearest point of a polyline by brute force over fine samples (float64, no shortcuts)."""
    best = (math.inf, 0.0, 0.0)
    cum = 0.0
    for a, b in zip(pts[:-1], pts[1:]):
        seg = math.dist(a, b)
        for k in range(2001):
            f = k / 2000
            q = (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]))
            d = math.dist(q, p)
            if d < best[0]:
                cross = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
                best = (d, cum + f * seg, math.copysign(d, cross))
        cum += seg
    return best


def test_route_arc_length_point_and_heading():
    g = LaneGraph(_bend())
    r = g.route("a,b")
    assert r.ids == ["a", "b"] and r.length == pytest.approx(50.0)
    assert np.allclose(r.point(5.0)[:2], [5.0, 0.0])
    assert np.allclose(r.point(40.0)[:2], [30.0, 10.0])
    assert r.heading(40.0) == pytest.approx(math.pi / 2)
    assert np.allclose(r.point(-3.0)[:2], [0, 0]) and np.allclose(r.point(99.0)[:2], [30, 20])
    pts, cum = r.polyline()
    assert len(pts) == 4 and np.allclose(cum, [0, 10, 30, 50])     # the shared corner once
    assert np.allclose(r.ahead(45.0, 3, 5.0)[:, :2], [[30, 15], [30, 20], [30, 20]])


def test_route_projection_matches_reference():
    r = LaneGraph(_bend()).route(["a", "b"])
    pts = [tuple(p[:2]) for p in r.polyline()[0]]
    rng = np.random.default_rng(0)
    for p in rng.uniform([-5, -10], [40, 25], size=(40, 2)):
        d, off = r.project(p)
        _, d_ref, off_ref = _ref_project(pts, tuple(p))
        assert abs(off) == pytest.approx(abs(off_ref), abs=0.02)
        if abs(off_ref) > 0.05:
            assert math.copysign(1, off) == math.copysign(1, off_ref)
        q = r.point(d)[:2]
        assert math.dist(q, p) == pytest.approx(abs(off_ref), abs=0.02)
    # left of travel is positive; a window keeps the projection near a given distance
    assert r.project([10.0, 2.0]) == pytest.approx((10.0, 2.0))
    assert r.project([28.0, 1.0])[0] == pytest.approx(28.0)
    assert r.project([28.0, 1.0], near=40.0, window=5.0)[0] == pytest.approx(31.0)   # on lane b only


def test_nearest_lane_prefers_the_lane_in_the_direction_of_travel():
    g = LaneGraph(_bend())
    east = g.nearest_lane([10.0, 2.0], heading=0.0)          # nearer to "back" (1.5 m) than "a" (2 m)
    assert g.ids[east.lane] == "a" and east.offset == pytest.approx(2.0)
    assert east.s == pytest.approx(10.0) and abs(east.relative_heading) < 1e-9
    west = g.nearest_lane([10.0, 2.0], heading=math.pi)
    assert g.ids[west.lane] == "back" and west.offset == pytest.approx(1.5)
    anyway = g.nearest_lane([10.0, 2.0])
    assert g.ids[anyway.lane] == "back" and anyway.distance == pytest.approx(1.5)
    wrong = g.nearest_lane([10.0, 0.2], heading=math.pi, lanes=[g.index["a"]])
    assert abs(wrong.relative_heading) == pytest.approx(math.pi)
    assert LaneGraph(m.Layout()).nearest_lane([0, 0]) is None


def test_random_routes_seeded_distinct_and_valid():
    L = read_layout(LAYOUT)
    g = LaneGraph(L)
    a = random_routes(g, 4, 80.0, seed=3)
    assert a == random_routes(L, 4, 80.0, seed=3)             # graph or layout, same draw
    assert len({tuple(r) for r in a}) == 4
    for r in a:
        g.route(r)                                             # each a valid successor path
    with pytest.raises(InputError, match="only .* distinct routes"):
        random_routes(g, 500, 80.0, seed=3)
    with pytest.raises(InputError, match="no drivable lanes"):
        random_routes(m.Layout(), 1, 10.0, seed=0)


def test_default_route_and_parsing():
    L = read_layout(LAYOUT)
    ids, length = default_route(L, seconds=4.0, speed=10.0)
    assert length >= 40.0 and isinstance(LaneGraph(L).route(ids), Route)
    assert default_route(m.Layout(), 4.0) == ([], 0.0)
    assert parse_route(" w_in, j_we ,,e_out") == ["w_in", "j_we", "e_out"]
    with pytest.raises(InputError, match="no lanes given"):
        LaneGraph(L).route("")
    with pytest.raises(InputError, match="does not follow"):
        LaneGraph(L).route("e_out,w_in")
