"""Layout model: normalisation, validation, chunk queries, lane graph."""
import numpy as np
import pytest

from lsd3d_usd.layout import model as m


def small_layout():
    L = m.Layout(extent=((0, 0), (200, 100)))
    L.add(m.LaneCenter("a", points=[[10, 50], [90, 50]], successors=["b"]))
    L.add(m.LaneCenter("b", points=[[90, 50], [150, 50]], predecessors=["a"], widths=3.0))
    L.add(m.Building("h", footprint=[[120, 60], [140, 60], [140, 80], [120, 80]]))
    L.add(m.Tree("t", position=[199, 99]))
    L.add(m.ParkingSpot("p", center=[50, 46], heading=np.pi / 2, length=5, width=2))
    return L


def test_points_normalised_to_float64_xyz():
    lane = m.LaneCenter("a", points=[[0, 0], [1, 1]])
    assert lane.points.dtype == np.float64 and lane.points.shape == (2, 3)
    assert np.array_equal(lane.widths, [3.5, 3.5])
    assert m.Tree("t", position=[1, 2]).position.tolist() == [1, 2, 0]


@pytest.mark.parametrize("make, msg", [
    (lambda: m.LaneCenter("x", points=[[0, 0]]), "at least 2"),
    (lambda: m.LaneCenter("x", points=[[0, 0], [1, np.nan]]), "non-finite"),
    (lambda: m.LaneCenter("x", points=[[0, 0], [1, 0]], widths=[1, 2, 3]), "widths"),
    (lambda: m.LaneCenter("x", points=[[0, 0], [1, 0]], direction="up"), "direction"),
    (lambda: m.RoadLine("x", points=[[0, 0], [1, 0]], color="red"), "color"),
    (lambda: m.Building("x", footprint=[[0, 0], [1, 0]]), "at least 3"),
    (lambda: m.Building("x", footprint=[[0, 0], [1, 0], [0, 1]], height_hint=0), "height_hint"),
])
def test_invalid_features_name_themselves(make, msg):
    with pytest.raises(ValueError, match=msg) as e:
        make()
    assert " x " in str(e.value) or "x" in str(e.value).split(":")[0]


def test_bounds_chunks_and_box_query():
    L = small_layout()
    (x0, y0), (x1, y1) = L.bounds()
    assert x0 == 10 - 1.75 and x1 == 199 and y1 == 99
    ri, rj = L.chunk_range()
    assert list(ri) == [0, 1] and list(rj) == [0]
    sub = L.features_in_box(L.chunk_box(1, 0))
    assert {f.id for f in sub.features()} == {"b", "h", "t"}
    # a ends at x = 90, its surface reaches 91.75: inside a 10 m margin, not a 5 m one
    assert "a" in {f.id for f in L.features_in_box(L.chunk_box(1, 0), margin=10).features()}
    assert "a" not in {f.id for f in L.features_in_box(L.chunk_box(1, 0), margin=5).features()}
    sub = L.features_in_box(((0, 0), (48, 44)), margin=1.5)   # spot spans x 49..51, y 43.5..48.5
    assert {f.id for f in sub.features()} == {"p"}


def test_lane_graph_and_parking_polygon():
    L = small_layout()
    assert [l.id for l in L.successors_of("a")] == ["b"]
    assert [l.id for l in L.predecessors_of("b")] == ["a"]
    with pytest.raises(KeyError):
        L.lane_by_id("zz")
    poly = L.parking_spots[0].polygon()
    assert m.polygon_area(poly) == pytest.approx(10.0)
    assert np.allclose(poly[:, :2].min(axis=0), [49, 43.5])


def test_equality_is_exact():
    a, b = small_layout(), small_layout()
    assert a == b
    b.lanes[0].points[0, 0] += 1e-12
    assert a != b
