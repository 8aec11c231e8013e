"""Proxy mesh containers, validity checks, planar helpers and primitives."""
import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Point, Polygon, box

from lsd3d_usd.proxy import planar, shapes
from lsd3d_usd.proxy.mesh import (PROXY_CLASSES, MeshPart, check_part, face_areas_normals,
                                  merge_parts)
from lsd3d_usd.proxy.pointcloud import cluster_vertices


def volume(v, f):
    """Signed volume by the divergence theorem (float64 reference)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_class_names_match_semantics():
    from lsd3d_usd.semantics import CLASSES
    assert set(PROXY_CLASSES) <= set(CLASSES)


def test_prism_with_hole_is_closed_and_has_exact_volume():
    g = box(0, 0, 10, 6).difference(box(2, 2, 4, 4))
    v, f = planar.prism(g, 0.5, 3.5)
    p = MeshPart(v, f, "building", "b", solid=True)
    assert check_part(p) == []
    assert volume(v, f) == pytest.approx(g.area * 3.0, rel=1e-12)


def test_prism_of_empty_or_sliver_area_is_empty():
    v, f = planar.prism(Polygon(), 0, 1)
    assert len(f) == 0
    v, f = planar.prism(LineString([(0, 0), (1, 1)]).buffer(0).union(Polygon()), 0, 1)
    assert len(f) == 0


def test_triangulate_covers_polygon_exactly_and_is_ccw():
    g = Point(0, 0).buffer(5).difference(box(-1, -1, 1, 1))
    xy, f = planar.triangulate(g)
    a = xy[f]
    cross = ((a[:, 1, 0] - a[:, 0, 0]) * (a[:, 2, 1] - a[:, 0, 1])
             - (a[:, 1, 1] - a[:, 0, 1]) * (a[:, 2, 0] - a[:, 0, 0]))
    assert (cross > 0).all()
    assert 0.5 * cross.sum() == pytest.approx(g.area, rel=1e-12)


def test_ribbon_matches_reference_buffer():
    pts = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 15.0]])
    r = planar.ribbon(pts, 1.75)
    ref = LineString(pts).buffer(1.75, cap_style="flat", join_style="mitre")
    assert r.symmetric_difference(ref).area < 1e-9
    # per-vertex widths: a trapezoid
    t = planar.ribbon(np.array([[0.0, 0.0], [10.0, 0.0]]), np.array([1.0, 2.0]))
    assert t.area == pytest.approx(10 * (2 + 4) / 2)


def test_ribbon_degenerate_polyline():
    assert planar.ribbon(np.array([[1.0, 1.0], [1.0, 1.0]]), 1.0).is_empty


def test_dashes_follow_pattern_from_the_first_point():
    d = planar.dashes(np.array([[0.0, 0.0], [30.0, 0.0]]), 3.0, 6.0)
    starts = [s[0, 0] for s in d]
    assert starts == pytest.approx([0, 9, 18, 27])
    assert all(np.linalg.norm(s[-1] - s[0]) == pytest.approx(3.0) for s in d)


def test_check_part_catches_each_defect():
    v, f = shapes.box(2, 2, 0, 1)
    assert check_part(MeshPart(v, f, "vehicle", "ok", solid=True)) == []
    assert "inwards" in check_part(MeshPart(v, f[:, ::-1], "vehicle", "x", solid=True))[0]
    assert "watertight" in check_part(MeshPart(v, f[:-1], "vehicle", "x", solid=True))[0]
    bad = v.copy()
    bad[0, 0] = np.nan
    assert "non-finite" in check_part(MeshPart(bad, f, "vehicle", "x", solid=True))[0]
    deg = np.vstack([f, [[0, 0, 1]]])
    assert any("degenerate" in e for e in check_part(MeshPart(v, deg, "vehicle", "x", solid=True)))
    flat_v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    assert check_part(MeshPart(flat_v, [[0, 1, 2]], "road", "r")) == []
    assert "face down" in check_part(MeshPart(flat_v, [[0, 2, 1]], "road", "r"))[0]
    assert check_part(MeshPart(flat_v, [[0, 2, 1]], "road", "r", faces_up=False)) == []


def test_primitives_are_valid_solids_with_expected_volume():
    for (v, f), vol in [(shapes.box(2, 3, 1, 5), 24.0),
                        (shapes.cylinder(1.0, 0, 2, segments=64), np.pi * 2),
                        (shapes.ellipsoid(1, 1, 1, subdivisions=3), 4 / 3 * np.pi)]:
        assert check_part(MeshPart(v, f, "pole", "p", solid=True)) == []
        assert volume(v, f) == pytest.approx(vol, rel=0.02)
    v, f = shapes.profile_prism(np.array([[0, 0], [4, 0], [4, 1], [0, 1.5]]), 2.0)
    assert check_part(MeshPart(v, f, "vehicle", "v", solid=True)) == []
    assert volume(v, f) == pytest.approx(2.0 * 5.0)


def test_merge_parts_concatenates_per_class_with_part_index():
    a = MeshPart(*shapes.box(1, 1, 0, 1), "vehicle", "a", solid=True)
    b = MeshPart(*shapes.box(1, 1, 2, 3), "vehicle", "b", solid=True)
    c = MeshPart(*shapes.cylinder(0.1, 0, 3), "pole", "c", solid=True)
    m = merge_parts([a, c, b], prefix="Chunk_0_0/")
    assert list(m) == ["vehicle", "pole"]
    veh = m["vehicle"]
    assert veh.part_ids == ("a", "b") and veh.name == "Chunk_0_0/vehicle"
    assert veh.n_faces == a.n_faces + b.n_faces
    np.testing.assert_array_equal(veh.face_part, [0] * a.n_faces + [1] * b.n_faces)
    # faces of part b index b's vertices, shifted
    np.testing.assert_allclose(veh.vertices[veh.faces[veh.face_part == 1]], b.vertices[b.faces])


def test_cluster_vertices_merges_and_drops_collapsed_faces():
    # a fine grid of 2 triangles per cell, clustered 4x coarser
    n = 17
    X, Y = np.meshgrid(np.linspace(0, 1.6, n), np.linspace(0, 1.6, n), indexing="ij")
    v = np.column_stack([X.ravel(), Y.ravel(), np.zeros(n * n)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.vstack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    v2, f2, _ = cluster_vertices(v, f, 0.4)
    assert len(v2) < len(v) / 4 and len(f2) > 0
    area, n2 = face_areas_normals(v2, f2)
    assert (area > 0).all() and (n2[:, 2] > 0).all()
    # opposite faces on the same triple vanish together
    v3 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0], [6, 5, 0], [5, 6, 0]], float)
    f3 = np.array([[0, 1, 2], [0, 2, 1], [3, 4, 5], [4, 5, 3]])
    _, f4, _ = cluster_vertices(v3, f3, 1e-3)
    assert len(f4) == 1
