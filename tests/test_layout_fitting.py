"""Plan-view fitting (lines, arcs, paramPoly3) against a plain float64 reference, and on
degenerate inputs."""
import math

import numpy as np
import pytest

from lsd3d_usd.layout import blocks as B
from lsd3d_usd.layout import fitting as F


def ref_point_segment(p, a, b) -> float:
    """Plain scalar float64 distance of point p to segment ab (the reference)."""
    ax, ay, bx, by = float(a[0]), float(a[1]), float(b[0]), float(b[1])
    dx, dy = bx - ax, by - ay
    L2 = dx * dx + dy * dy
    t = 0.0 if L2 == 0 else max(0.0, min(1.0, ((p[0] - ax) * dx + (p[1] - ay) * dy) / L2))
    return math.hypot(p[0] - ax - t * dx, p[1] - ay - t * dy)


def ref_eval(prim, ds):
    """The primitive at distance ds, written out per OpenDRIVE's definitions (scalar float64)."""
    x, y, h = prim.x, prim.y, prim.hdg
    if prim.kind == "line":
        return x + ds * math.cos(h), y + ds * math.sin(h)
    if prim.kind == "arc":
        k = prim.curvature
        return x + (math.sin(h + k * ds) - math.sin(h)) / k, y - (math.cos(h + k * ds) - math.cos(h)) / k
    aU, bU, cU, dU, aV, bV, cV, dV = prim.coeffs
    p = ds / prim.length
    u = aU + bU * p + cU * p * p + dU * p ** 3
    v = aV + bV * p + cV * p * p + dV * p ** 3
    return x + u * math.cos(h) - v * math.sin(h), y + u * math.sin(h) + v * math.cos(h)


def check_fit(pts, tol=0.02):
    """Fit, then measure with the reference: every vertex within tol/2 of the curve (sampled
    every 2 cm), every curve sample within tol of the polyline, ends exact, spans contiguous."""
    prims, starts = F.fit_polyline(pts, tol)
    assert starts[0] == 0 and starts[-1] == len(pts) - 1 and len(prims) == len(starts) - 1
    for prim, i, j in zip(prims, starts[:-1], starts[1:]):
        span = pts[i:j + 1]
        n = max(50, int(prim.length / 0.02) + 1)
        curve = [ref_eval(prim, prim.length * q / (n - 1)) for q in range(n)]
        assert math.dist(curve[0], span[0][:2]) < 1e-9
        assert math.dist(curve[-1], span[-1][:2]) < 1e-6, (prim.kind, curve[-1], span[-1])
        for c in curve[::max(1, n // 400)]:
            d = min(ref_point_segment(c, span[k], span[k + 1]) for k in range(len(span) - 1))
            assert d <= tol + 1e-9, (prim.kind, d)
        for v in span:
            d = min(ref_point_segment(v, curve[k], curve[k + 1]) for k in range(len(curve) - 1))
            assert d <= tol / 2 + 1e-4, (prim.kind, d)   # + the reference's own 2 cm chords
        # the fast eval agrees with the reference
        ds = np.linspace(0, prim.length, 7)
        assert np.allclose(prim.eval(ds), [ref_eval(prim, d) for d in ds], atol=1e-9)
    return prims


def test_straight_line_is_one_line():
    pts = np.array([[0.0, 0.0], [30.0, 40.0], [60.0, 80.0], [90.0, 120.0]])
    prims = check_fit(pts)
    assert [p.kind for p in prims] == ["line"] and prims[0].length == pytest.approx(150.0)
    assert prims[0].hdg == pytest.approx(math.atan2(4, 3))


@pytest.mark.parametrize("radius,sweep", [(12.0, 4.0), (9.0, -5.5), (1.0, 3.0), (3.0, 6.0),
                                          (500.0, 0.3), (30.0, -0.02)])
def test_sampled_arc_is_one_arc_with_its_radius(radius, sweep):
    pts = B.arc_points(np.array([5.0, -3.0]), radius, 0.7, sweep)   # 1 cm chords, as the generator
    prims = check_fit(pts)
    if len(pts) > 2:
        assert [p.kind for p in prims] == ["arc"]
        assert 1 / prims[0].curvature == pytest.approx(math.copysign(radius, sweep), rel=1e-6)
        assert prims[0].length == pytest.approx(radius * abs(sweep), rel=1e-6)


def test_hermite_connector_is_one_paramPoly3():
    pts = B.hermite(np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([15.0, 12.0]),
                    np.array([0.0, 1.0]))
    prims = check_fit(pts)
    assert [p.kind for p in prims] == ["paramPoly3"]
    _, d_vertex = F.deviation(prims[0], pts)
    assert d_vertex < 1e-3


def test_mixed_line_arc_line():
    line1 = np.stack([np.linspace(-50, 0, 6), np.zeros(6)], axis=1)
    arc = B.arc_points(np.array([0.0, 20.0]), 20.0, -np.pi / 2, np.pi / 2)
    line2 = np.stack([np.full(6, 20.0), np.linspace(20, 70, 6)], axis=1)
    pts = np.concatenate([line1, arc[1:], line2[1:]])
    prims = check_fit(pts)
    kinds = [p.kind for p in prims]
    assert kinds.count("arc") >= 1 and len(prims) <= 4, kinds


def test_wavy_curve_within_tolerance_and_corner_kept():
    x = np.linspace(0, 200, 400)
    pts = np.stack([x, 3 * np.sin(x / 10)], axis=1)
    check_fit(pts)
    corner = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])        # a real 90° corner
    prims = check_fit(corner)
    assert len(prims) == 2 and abs(prims[1].hdg - prims[0].hdg) == pytest.approx(np.pi / 2)


@pytest.mark.parametrize("tol", [0.005, 0.02, 0.1])
def test_random_smooth_polylines(tol):
    rng = np.random.default_rng(4)
    for _ in range(5):
        heading = np.cumsum(rng.normal(0, 0.08, 80))
        pts = np.concatenate([[[0.0, 0.0]], np.cumsum(np.stack([np.cos(heading), np.sin(heading)], 1) * 2.0, 0)])
        check_fit(pts, tol)


def test_degenerate_inputs():
    assert F.fit_polyline(np.array([[1.0, 2.0]])) == ([], [0])           # one point
    p, keep = F.dedupe(np.array([[1.0, 2.0, 0.0], [1.0, 2.0, 5.0], [1.0, 2.0, 0.0]]))
    assert len(p) == 1 and list(keep) == [0]                             # zero length in XY
    with pytest.raises(ValueError, match="zero-length"):
        F.fit_polyline(np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]]))   # not deduplicated
    with pytest.raises(ValueError, match="tolerance"):
        F.fit_polyline(np.array([[0.0, 0.0], [1.0, 0.0]]), 0.0)
    tiny = np.array([[0.0, 0.0], [1e-6, 0.0]])                            # a micrometre
    assert [q.kind for q in F.fit_polyline(tiny)[0]] == ["line"]
    hairpin = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 0.001]])           # folds back on itself
    check_fit(hairpin)
