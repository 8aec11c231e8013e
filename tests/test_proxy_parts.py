"""Geometry generators: buildings, markings, ground partition, objects."""
import numpy as np
import pytest
import shapely
from shapely.geometry import box

from lsd3d_usd.proxy.buildings import BuildingStyle, building_mesh, choose_roof
from lsd3d_usd.proxy.furniture import stop_sign_parts, street_light_parts, traffic_light_parts
from lsd3d_usd.proxy.ground import ground_areas, ground_parts
from lsd3d_usd.proxy.markings import crosswalk_area, road_line_area, road_line_part
from lsd3d_usd.proxy.mesh import check_part
from lsd3d_usd.proxy.vegetation import hedge_part, tree_parts, zone_shrubs
from lsd3d_usd.proxy.vehicles import vehicle_part

RECT = np.array([[100.0, 200.0], [118.0, 200.0], [118.0, 210.0], [100.0, 210.0]])
ELL = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 10.0], [10.0, 10.0], [10.0, 25.0], [0.0, 25.0]])


def volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


@pytest.mark.parametrize("roof", ["flat", "gable", "hip"])
@pytest.mark.parametrize("fp", [RECT, ELL], ids=["rect", "ell"])
def test_buildings_are_closed_solids_of_the_right_size(roof, fp):
    p = building_mesh("b", fp, 15.0, 5, roof=roof)
    assert check_part(p) == []
    lo, hi = p.bounds()
    np.testing.assert_allclose(lo[:2], fp.min(0), atol=1e-6)
    np.testing.assert_allclose(hi[:2], fp.max(0), atol=1e-6)
    assert lo[2] == pytest.approx(0.0)
    area = shapely.Polygon(fp).area
    plain = building_mesh("b", fp, 15.0, 5, roof=roof, style=BuildingStyle(windows=False))
    # window recesses remove volume and add faces; the plain body holds at least area*height
    assert volume(p.vertices, p.faces) < volume(plain.vertices, plain.faces)
    assert p.n_faces > 10 * plain.n_faces
    assert volume(plain.vertices, plain.faces) >= area * 15.0 - 1e-6
    if fp is ELL or roof == "flat":          # L footprints always get a flat roof + parapet
        assert hi[2] == pytest.approx(15.0 + BuildingStyle().parapet_height)
    else:
        assert hi[2] > 15.5


def test_building_roof_choice_is_stable_and_flat_for_irregular_footprints():
    poly = shapely.Polygon(RECT)
    assert {choose_roof(f"id{k}", poly) for k in range(60)} == {"flat", "gable", "hip"}
    assert choose_roof("x", poly) == choose_roof("x", poly)
    assert {choose_roof(f"id{k}", shapely.Polygon(ELL)) for k in range(20)} == {"flat"}


def test_degenerate_footprint_gives_nothing():
    assert building_mesh("b", np.array([[0, 0], [1, 1], [2, 2]], float), 10.0) is None


def test_objects_are_valid_solids():
    parts = tree_parts("t", (3, 4), 8.0, 2.5) + stop_sign_parts("s", (0, 0), 0.3)
    parts += traffic_light_parts("tl", (5, 5), 1.0) + street_light_parts("sl", (1, 1), 2.0)
    parts += [vehicle_part(f"p{k}", (0, 0), 0.4, L, 2.4) for k, L in enumerate([4.5, 5.5, 9.5, 9.5])]
    parts += [hedge_part("h", np.array([[0, 0], [10, 0], [10, 10]]), 1.2, 0.8, box(-5, -5, 5, 5))]
    for p in parts:
        assert check_part(p) == [], p.part_id
    classes = {p.cls for p in parts}
    assert classes == {"vegetation", "pole", "sign", "traffic_light", "vehicle"}
    # vehicles fit their spots
    for L in (4.5, 5.5, 9.5):
        v = vehicle_part("q", (0, 0), 0.0, L, 2.4)
        ext = np.ptp(v.vertices, axis=0)
        assert max(ext[0], ext[1]) <= L + 1e-9


def test_hedge_is_cut_at_the_clip_box():
    h = hedge_part("h", np.array([[-10.0, 0.0], [10.0, 0.0]]), 1.0, 1.0, box(0, -5, 5, 5))
    lo, hi = h.bounds()
    assert lo[0] == pytest.approx(0.0) and hi[0] == pytest.approx(5.0)


def test_zone_shrubs_belong_to_one_chunk_each():
    zone = box(0, 0, 60, 40)
    a = zone_shrubs("z", zone, "forest", box(0, 0, 30, 100))
    b = zone_shrubs("z", zone, "forest", box(30, 0, 60, 100))
    ids_a, ids_b = {p.part_id for p in a}, {p.part_id for p in b}
    assert ids_a and ids_b and not ids_a & ids_b
    both = zone_shrubs("z", zone, "forest", box(0, 0, 60, 100))
    assert {p.part_id for p in both} == ids_a | ids_b


def test_markings_patterns():
    pts = np.array([[0.0, 0.0], [90.0, 0.0]])
    solid = road_line_area(pts, "solid", False)
    assert solid.area == pytest.approx(90 * 0.15)
    broken = road_line_area(pts, "broken", False)
    assert broken.area == pytest.approx(10 * 3.0 * 0.15)         # dashes at 0, 9, ..., 81
    double = road_line_area(pts, "solid", True)
    assert double.area == pytest.approx(2 * 90 * 0.15) and len(double.geoms) == 2
    cw = crosswalk_area(np.array([[0, 0], [3, 0], [3, 10.5], [0, 10.5]], float))
    assert len(cw.geoms) == 10 and cw.area == pytest.approx(10 * 0.5 * 3)
    part = road_line_part("l", pts, "solid", "yellow", False, box(10, -5, 20, 5), 0.02)
    lo, hi = part.bounds()
    assert (lo[0], hi[0]) == pytest.approx((10.0, 20.0))
    assert lo[2] == pytest.approx(0.03) and part.color[2] < part.color[0]     # yellow paint


def test_ground_partition_is_disjoint_and_covers_the_box():
    lanes = [(np.array([[-30.0, 20.0], [130.0, 25.0]]), np.full(2, 7.0), "driving"),
             (np.array([[60.0, -30.0], [60.0, 130.0]]), np.full(2, 7.0), "driving"),
             (np.array([[0.0, 80.0], [100.0, 80.0]]), np.full(2, 2.0), "sidewalk")]
    areas = ground_areas((0, 0, 100, 100), 12.0, lanes,
                         vegetation=[np.array([[70, 60], [95, 60], [95, 95], [70, 95]], float)],
                         buildings=[np.array([[5, 35], [25, 35], [25, 50], [5, 50]], float)])
    names = list(areas)
    assert all(not areas[n].is_empty for n in names)
    total = sum(a.area for a in areas.values())
    assert total == pytest.approx(10000.0, rel=1e-9)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            assert areas[names[i]].intersection(areas[names[j]]).area < 1e-6
    # 4 curb lines of 100 m, each interrupted where the other road crosses (7 m)
    assert areas["curb"].area == pytest.approx(0.3 * (4 * 100 - 4 * 7), rel=0.01)
    for p in ground_parts(areas, "Chunk_0_0"):
        assert check_part(p) == []
