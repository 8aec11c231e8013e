"""Polygon robustness of the proxy builder (issue 17, item 6)."""
import numpy as np
import pytest
import shapely
from shapely.geometry import MultiPolygon, Polygon

from lsd3d_usd.cli import main
from lsd3d_usd.proxy import planar
from lsd3d_usd.proxy.ground import ground_areas, ground_parts
from lsd3d_usd.proxy.mesh import check_part


def _sliver_multipolygon():
    # a valid polygon whose ring spans 1e-13 m: remove_repeated_points collapses it to
    # 2 points and GEOS raises "Invalid number of points in LinearRing found 2"
    return MultiPolygon([Polygon([(0, 0), (10, 0), (10, 10), (0, 10)]),
                         Polygon([(20, 0), (20 + 1e-13, 0), (20, 1e-13)])])


def test_prism_of_a_sliver_ring_is_the_solid_without_it():
    g = _sliver_multipolygon()
    assert g.is_valid
    v, f = planar.prism(g, 0.0, 0.17)
    assert len(f) and planar._closed(f)
    ref_v, ref_f = planar.prism(Polygon([(0, 0), (10, 0), (10, 10), (0, 10)]), 0.0, 0.17)
    assert len(f) == len(ref_f) and np.allclose(np.sort(v, axis=0), np.sort(ref_v, axis=0))


def test_near_vertices_of_different_rings_are_not_sound_and_get_meshed_without_slivers():
    from lsd3d_usd.proxy.mesh import SIDEWALK, MeshPart
    near = Polygon([(1, -2), (0, 0), (0, 5e-5), (0, 1)],
                   [[(3e-9, -3e-9), (5e-5, 0), (0, 5e-5)]])
    far = Polygon([(1, -2), (0, 0), (0, 5e-5), (0, 1)],
                  [[(3e-6, -3e-6), (5e-5, 0), (0, 5e-5)]])
    assert near.is_valid and far.is_valid
    assert not planar._sound(near) and planar._sound(far)
    assert list(planar._sound_all([near, far])) == [False, True]
    v, f = planar.prism(near, 0.0, 0.17)
    assert len(f) and planar._closed(f)
    assert check_part(MeshPart(v, f, SIDEWALK, "ground/sidewalk/t", solid=True)) == []


@pytest.mark.parametrize("geom", [
    _sliver_multipolygon(),
    Polygon([(0, 0), (4, 4), (4, 0), (0, 4)]),                         # bow tie
    Polygon([(0, 0), (5, 0), (5, 0), (5, 5), (5, 5 + 1e-9), (0, 5)]),   # repeated / near points
    Polygon([(0, 0), (10, 0), (10, 10), (0, 10)], [[(2, 2), (2 + 1e-12, 2), (2, 2 + 1e-12)]]),  # sliver hole
    Polygon([(0, 0), (10, 0), (10, 1e-12), (0, 1e-12)]),               # zero-width strip
    Polygon([(0, 0), (10, 0), (5, 0)]),                                # collinear
    # found by the fuzz suite: make_valid pieces that overlap once their rings are cleaned
    Polygon([(1, 2), (1e-13, -1e-13), (3, -2e-13), (3e-13, 1), (3, -4e-13)]),
    # a hole touching the outer ring, its vertex 4e-9 m from the outer ring's corner
    Polygon([(1, -2), (0, 0), (0, 5e-5), (0, 1)], [[(3e-9, -3e-9), (5e-5, 0), (0, 5e-5)]]),
])
def test_clean_area_gives_sound_polygons_that_mesh(geom):
    clean = planar.clean_area(geom)
    assert clean.is_empty or clean.is_valid
    for p in planar.polygons_of(clean):
        assert planar._sound(p)
    assert abs(clean.area - shapely.make_valid(geom).area) < 1e-6
    v, f = planar.prism(geom, 0.0, 1.0)
    assert len(f) == 0 or planar._closed(f)
    xy, tri = planar.triangulate(geom)
    assert len(tri) == 0 or tri.max() < len(xy)


def test_generated_highway_chunk_with_a_sliver_curb_builds(tmp_path, capsys):
    """The issue's reproduction: seed 5, 5000x300 highway; chunk 7,0 held the sliver."""
    L = tmp_path / "L.usda"
    assert main(["layout", "generate", "--seed", "5", "--extent", "5000x300", "--style", "highway",
                 "-o", str(L)]) == 0
    assert main(["proxy", "build", "--layout", str(L), "-o", str(tmp_path / "P.usdc"),
                 "--chunk", "7,0", "--no-windows"]) == 0
    assert "built 1 chunk(s)" in capsys.readouterr().out


XODR = """<?xml version="1.0"?>
<OpenDRIVE><header revMajor="1" revMinor="6" name="narrow"/>
  <road id="1" length="60" junction="-1">
    <planView><geometry s="0" x="0" y="0" hdg="0" length="60"><arc curvature="0.01"/></geometry></planView>
    <lanes>
      <laneSection s="0">
        <left><lane id="1" type="sidewalk"><width sOffset="0" a="2" b="-0.1" c="0" d="0"/></lane></left>
        <center><lane id="0" type="none"/></center>
        <right>
          <lane id="-1" type="driving"><width sOffset="0" a="3.5" b="-0.07" c="0" d="0"/></lane>
          <lane id="-2" type="sidewalk"><width sOffset="0" a="0" b="0" c="0" d="0"/></lane>
          <lane id="-3" type="sidewalk"><width sOffset="0" a="1e-9" b="0" c="0" d="0"/></lane>
        </right>
      </laneSection>
    </lanes>
  </road>
</OpenDRIVE>"""


def test_opendrive_lanes_narrowing_to_zero_width_build(tmp_path):
    """Lanes whose width reaches 0 inside the road give pinched or zero-area polygons."""
    (tmp_path / "n.xodr").write_text(XODR)
    assert main(["layout", "import", str(tmp_path / "n.xodr"), "-o", str(tmp_path / "L.usda")]) == 0
    assert main(["proxy", "build", "--layout", str(tmp_path / "L.usda"), "-o", str(tmp_path / "P.usdc"),
                 "--no-windows"]) == 0


def test_ground_of_degenerate_layout_polygons_is_valid():
    box = (0.0, 0.0, 100.0, 100.0)
    lanes = [(np.array([[10, 50, 0], [10, 50, 0], [90, 50, 0]]), np.array([3.5, 0.0, 3.5]), "driving")]
    sidewalks = [np.array([[0, 0], [1e-12, 0], [0, 1e-12]]),          # sliver
                 np.array([[20, 20], [30, 30], [30, 20], [20, 30]]),   # bow tie
                 np.array([[40, 40], [40, 40], [40, 40]])]             # one point
    areas = ground_areas(box, 12.0, lanes, sidewalks=sidewalks,
                         buildings=[np.array([[60, 60], [70, 60], [70, 60], [60, 60]])])
    for part in ground_parts(areas, "Chunk_0_0"):
        assert check_part(part) == [], part.id
