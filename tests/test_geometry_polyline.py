"""geometry.polyline against plain float64 loops, one vertex or segment at a time, on random
polylines and the degenerate ones: repeated points, 2-point lines, zero-length segments,
collinear points, closed rings and hairpin turns."""
import math

import numpy as np
import pytest

from lsd3d_usd.geometry import polyline as P

RNG = np.random.default_rng(54)


def _cases():
    walk = np.cumsum(RNG.normal(0, 3, (40, 3)), axis=0)
    square = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 1], [0, 10, 1], [0, 0, 0]], float)
    return {
        "random": walk,
        "random_xy": RNG.uniform(-50, 50, (25, 2)),
        "two_points": np.array([[1.0, 2.0, 0.0], [4.0, -2.0, 1.0]]),
        "repeated": np.repeat(RNG.uniform(-20, 20, (8, 3)), 2, axis=0),
        "zero_segment": np.array([[0, 0, 0], [5, 0, 0], [5, 0, 0], [5, 5, 0]], float),
        "collinear": np.c_[np.linspace(0, 30, 7), np.linspace(0, 15, 7), np.zeros(7)],
        "closed_ring": square,
        "hairpin": np.array([[0, 0, 0], [20, 0, 0], [20.5, 0.5, 0], [0, 1, 0]], float),
        "reversal": np.array([[0, 0, 0], [10, 0, 0], [3, 0, 0]], float),
    }


CASES = _cases()


# ------------------------------------------------------------------ references
def ref_clean(points, tol):
    out = [points[0]]
    for p in points[1:]:
        if math.dist(p, out[-1]) > tol:
            out.append(p)
    return np.array(out)


def ref_point_at(points, s):
    """Walk the segments longer than 1e-9 until s is used up."""
    pts = [p for i, p in enumerate(points) if i == 0 or math.dist(p, points[i - 1]) > 1e-9]
    total = sum(math.dist(a, b) for a, b in zip(pts, pts[1:]))
    s = min(max(s, 0.0), total)
    for a, b in zip(pts, pts[1:]):
        L = math.dist(a, b)
        if s <= L:
            return np.array([x + (y - x) * s / L for x, y in zip(a, b)])
        s -= L
    return np.array(pts[-1], float)


def ref_nearest(points, q):
    best = None
    s0 = 0.0
    for a, b in zip(points[:, :2], points[1:, :2]):
        L = math.dist(a, b)
        dot = (q[0] - a[0]) * (b[0] - a[0]) + (q[1] - a[1]) * (b[1] - a[1])
        t = 0.0 if L == 0 else min(max(dot / L**2, 0), 1)
        c = a + t * (b - a)
        d = math.dist(c, q)
        if best is None or d < best[0] - 1e-12:
            best = (d, s0 + t * L, c)
        s0 += L
    return best


def ref_offset(points, dist, limit=4.0):
    xy = ref_clean(np.asarray(points, float)[:, :2], 1e-6)
    n = len(xy)
    out = []
    for i in range(n):
        normals = []
        for a, b in ((i - 1, i), (i, i + 1)):
            if 0 <= a and b < n:
                dx, dy = xy[b] - xy[a]
                L = math.hypot(dx, dy)
                normals.append(np.array([-dy / L, dx / L]))
        m = sum(normals)
        if np.linalg.norm(m) < 1e-9:            # a reversal: the incoming normal
            m = normals[0]
        m = m / np.linalg.norm(m)
        cos_half = float(np.dot(m, normals[0]))
        out.append(xy[i] + m * dist / min(max(cos_half, 1 / limit), 1.0))
    return np.array(out)


def ref_area(poly):
    return 0.5 * sum(poly[i][0] * poly[(i + 1) % len(poly)][1] - poly[(i + 1) % len(poly)][0] * poly[i][1]
                     for i in range(len(poly)))


def ref_distance(q, line):
    return np.array([ref_nearest(line, p)[0] if len(line) > 1 else math.dist(p[:2], line[0, :2])
                     for p in q])


# ------------------------------------------------------------------ tests
@pytest.mark.parametrize("name", list(CASES))
def test_clean_polyline_and_arc_table(name):
    pts = CASES[name]
    np.testing.assert_array_equal(P.clean_polyline(pts), ref_clean(pts[:, :2], 1e-6))
    kept, cum = P.arc_table(pts)
    np.testing.assert_array_equal(kept, ref_clean(pts, 1e-9))
    ref_cum = np.concatenate([[0.0], np.cumsum([math.dist(a, b) for a, b in zip(kept, kept[1:])])])
    np.testing.assert_allclose(cum, ref_cum, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", list(CASES))
def test_point_at_and_heading_at(name):
    pts = CASES[name]
    total = P.arc_table(pts)[1][-1]
    s = np.concatenate([[-1.0, 0.0, total, total + 1.0], RNG.uniform(0, total, 30)])
    got = P.point_at(pts, s)
    np.testing.assert_allclose(got, [ref_point_at(pts, x) for x in s], rtol=0, atol=1e-9)
    h = P.heading_at(pts, s, half=0.8)
    for x, hx in zip(s, h):
        a, b = ref_point_at(pts, max(x - 0.8, 0.0)), ref_point_at(pts, min(x + 0.8, total))
        ref = math.atan2(b[1] - a[1], b[0] - a[0])
        assert abs(math.remainder(hx - ref, 2 * math.pi)) < 1e-9


def test_point_at_without_length_is_the_point():
    pts = np.array([[3.0, 4.0, 5.0]] * 3)
    np.testing.assert_array_equal(P.point_at(pts, np.array([0.0, 2.0])), pts[:2])


@pytest.mark.parametrize("name", list(CASES))
def test_resample(name):
    pts = CASES[name]
    seg = [math.hypot(*(b[:2] - a[:2])) for a, b in zip(pts, pts[1:])]
    total = sum(seg)
    t = np.linspace(0, 1, 11)
    got = P.resample(pts, t)
    for ti, g in zip(t, got):
        # the first vertex reached at fraction ti by XY length, interpolated in every column
        s, ref = ti * total, pts[-1]
        for k, L in enumerate(seg):
            if s <= L and L > 0:
                ref = pts[k] + (pts[k + 1] - pts[k]) * s / L
                break
            s -= L
        np.testing.assert_allclose(g, ref, rtol=0, atol=1e-9)
    even = P.resample_step(pts, 2.5)
    assert len(even) == max(2, math.ceil(total / 2.5) + 1)
    np.testing.assert_allclose(even[[0, -1]], pts[[0, -1]], rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", list(CASES))
def test_nearest_point_and_distance(name):
    pts = CASES[name]
    lo, hi = pts[:, :2].min(0) - 5, pts[:, :2].max(0) + 5
    qs = np.concatenate([RNG.uniform(lo, hi, (40, 2)), pts[:, :2]])
    for q in qs:
        d, s, c, u = P.nearest_point(pts, q)
        rd, rs, rc = ref_nearest(pts, q)
        assert abs(d - rd) < 1e-9
        np.testing.assert_allclose(c, rc, rtol=0, atol=1e-9)
        if not np.any(np.all(np.abs(pts[:, :2] - c) < 1e-9, axis=1)):  # at a vertex s may jump
            assert abs(s - rs) < 1e-9
        assert abs(np.linalg.norm(u) - 1) < 1e-9 or np.linalg.norm(u) == 0
    np.testing.assert_allclose(P.distance_to_polyline(qs, pts), ref_distance(qs, pts), rtol=0, atol=1e-9)
    np.testing.assert_allclose(P.distance_to_polyline(qs, pts[:1]), ref_distance(qs, pts[:1]),
                               rtol=0, atol=1e-12)


def test_distance_to_segments_fast_path_is_the_brute_one():
    walk = np.cumsum(RNG.normal(0, 1, (1500, 2)), axis=0)
    walk = np.repeat(walk, 2, axis=0)                 # zero-length segments too
    q = walk[::5] + RNG.normal(0, 0.5, (len(walk[::5]), 2))
    a, b = walk[:-1], walk[1:]
    assert len(q) * len(a) > P.BRUTE_PAIRS
    np.testing.assert_allclose(P.distance_to_segments(q, a, b), P.distance_to_segments_brute(q, a, b),
                               rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("dist", [1.75, -3.0, 0.0])
def test_offset_polyline(name, dist):
    got = P.offset_polyline(CASES[name], dist)
    np.testing.assert_allclose(got, ref_offset(CASES[name], dist), rtol=0, atol=1e-9)


def test_offset_of_a_straight_line_is_parallel_and_a_hairpin_mitre_is_limited():
    np.testing.assert_allclose(P.offset_polyline(CASES["collinear"], 2.0)[:, 1] - CASES["collinear"][:, 1],
                               2.0 * 30 / math.hypot(30, 15), rtol=0, atol=1e-12)
    hp = CASES["hairpin"]
    reach = np.linalg.norm(P.offset_polyline(hp, 1.0) - hp[:, :2], axis=1)
    assert reach.max() <= P.MITRE_LIMIT + 1e-12


@pytest.mark.parametrize("name", list(CASES))
def test_rings(name):
    pts = CASES[name]
    assert abs(P.signed_area(pts) - ref_area(pts)) < 1e-9
    ccw = P.orient_ccw(pts)
    assert ref_area(ccw) > 0 or ref_area(pts) == 0
    ring = P.clean_ring(pts)
    # reference: repeats dropped, closing point dropped, None if < 3 points or < 1e-6 m²
    ref = [p for i, p in enumerate(pts) if i == 0 or math.hypot(*(p[:2] - pts[i - 1][:2])) > 1e-9]
    if len(ref) > 3 and math.dist(ref[0][:2], ref[-1][:2]) < 1e-8:
        ref = ref[:-1]
    if len(ref) < 3 or abs(ref_area(ref)) < 1e-6:
        assert ring is None
    else:
        ref = np.array(ref if ref_area(ref) > 0 else ref[::-1])
        np.testing.assert_array_equal(ring, ref)


def test_clean_ring_reorients_a_clockwise_closed_ring():
    cw = CASES["closed_ring"][::-1]
    ring = P.clean_ring(cw)
    assert len(ring) == 4 and P.signed_area(ring) == pytest.approx(100.0)
