"""A chunk's proxy work follows what lies near it, not the length of the features through
it: ribbons, dashes and the feature lookup are windowed to the chunk, and the windowed
results equal the whole feature's cut at the chunk."""
import numpy as np
import shapely
from shapely.geometry import box

from lsd3d_usd.layout.generator import generate
from lsd3d_usd.proxy.chunks import FeatureIndex
from lsd3d_usd.proxy.markings import MarkingStyle, road_line_area
from lsd3d_usd.proxy.planar import _quads, _quads_many, dashes, ribbon, ribbons


def _wavy(n=600, length=3000.0):
    x = np.linspace(0.0, length, n)
    return np.column_stack([x, 4.0 * np.sin(x / 37.0), np.zeros(n)])


def test_windowed_ribbon_equals_the_whole_ribbon_inside_the_box():
    pts = _wavy()
    widths = 3.0 + 0.5 * np.cos(pts[:, 0] / 90.0)
    b = (1210.0, -30.0, 1310.0, 30.0)
    whole = shapely.intersection(ribbon(pts, widths / 2), box(*b))
    part = shapely.intersection(ribbon(pts, widths / 2, within=b), box(*b))
    assert whole.area > 100
    assert shapely.symmetric_difference(whole, part).area < 1e-6 * whole.area
    # far from the line: nothing to build
    assert ribbon(pts, 1.5, within=(0, 500, 100, 600)).is_empty


def test_windowed_dashes_are_the_same_dashes_at_the_same_places():
    pts = _wavy()
    b = (1200.0, -20.0, 1300.0, 20.0)
    full = dashes(pts, 3.0, 6.0)
    near = dashes(pts, 3.0, 6.0, within=b)
    keyed = {tuple(np.round(d[0], 9)): d for d in full}
    assert 9 <= len(near) <= 14            # ~100 m / 9 m, not the 333 dashes of the line
    for d in near:
        ref = keyed[tuple(np.round(d[0], 9))]
        np.testing.assert_array_equal(d, ref)
    # every dash of the whole line that meets the box is among them
    meets = [d for d in full if shapely.intersects(shapely.LineString(d), box(*b))]
    assert len(meets) <= len(near)


def test_road_line_paint_near_a_chunk_only():
    pts = _wavy()
    b = (1200.0, -20.0, 1300.0, 20.0)
    st = MarkingStyle()
    for kind, double in (("broken", False), ("broken", True), ("solid", True)):
        whole = shapely.intersection(road_line_area(pts, kind, double, st), box(*b))
        part = road_line_area(pts, kind, double, st, within=b)
        assert part.bounds[0] > b[0] - 10 and part.bounds[2] < b[2] + 10
        cut = shapely.intersection(part, box(*b))
        assert shapely.symmetric_difference(whole, cut).area < 1e-6 * max(whole.area, 1e-9)


def test_vectorised_quads_equal_per_polyline_quads():
    rng = np.random.default_rng(3)
    lines = []
    for _ in range(40):
        p = np.cumsum(rng.normal(size=(int(rng.integers(2, 9)), 2)), axis=0)
        if len(p) > 3:
            p[2] = p[1]                     # a repeated point
        lines.append(p)
    lines.append(np.array([[0.0, 0], [1, 0], [0, 0]]))   # a reversal
    a = _quads_many(lines, 0.3)
    b = np.concatenate([_quads(ln, 0.3) for ln in lines])
    np.testing.assert_allclose(a, b, atol=1e-12)
    assert ribbons(lines, 0.3).area > 0


def test_feature_index_finds_what_features_in_box_finds():
    layout = generate(5, (300.0, 300.0), "urban")
    idx = FeatureIndex(layout)
    for (i, j) in ((0, 0), (1, 2), (2, 1), (5, 5)):
        box_ = ((100.0 * i, 100.0 * j), (100.0 * (i + 1), 100.0 * (j + 1)))
        a = [f.id for f in layout.features_in_box(box_, 12.0).features()]
        b = [f.id for f in idx.near(box_, 12.0).features()]
        assert a == b
