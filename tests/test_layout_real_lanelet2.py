"""Lanelet2 read whole: traffic-light and traffic-sign rules, poles and barriers become layout
features and proxy geometry; degenerate lanelets and stray markings are warned by id and
repaired or skipped by the documented rule (errors with strict)."""
import importlib.util

import numpy as np
import pytest

from conftest import ROOT
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import lanelet2_import as l2
from lsd3d_usd.layout.importers import ImportOptions, MapWarning

_spec = importlib.util.spec_from_file_location("make_real_maps", ROOT / "samples/maps/make_real_maps.py")
maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(maps)
ORIGIN = (49.0069, 8.4037)


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    return maps.lanelet2_real(tmp_path_factory.mktemp("l2") / "street.osm", ORIGIN)


@pytest.fixture(scope="module")
def layout(street):
    with pytest.warns(MapWarning) as rec:
        L = l2.read_lanelet2(street, ImportOptions(origin=ORIGIN))
    return L, [str(w.message) for w in rec]


def test_traffic_light_rule_is_a_light_facing_its_lane(layout):
    L, _ = layout
    (tl,) = L.traffic_lights
    lane = L.lane_by_id(tl.lane_ids[0])
    assert len(tl.lane_ids) == 1 and lane.points[-1, 0] > lane.points[0, 0]   # eastbound
    assert np.isclose(abs(tl.heading), np.pi, atol=1e-6)       # faces the westward view
    assert np.allclose(tl.position[:2], [115, -1.75], atol=0.05)
    assert np.isclose(tl.height, 5.8, atol=0.01)                # head 5 m up + 0.8 m
    assert L.metadata["source"]["signalsComplete"] is True


def test_traffic_signs_keep_kind_code_value_and_lanes(layout):
    L, _ = layout
    signs = {s.kind: s for s in L.traffic_signs}
    assert set(signs) == {"yield", "speed_limit"}
    assert signs["yield"].code == "de205" and signs["speed_limit"].value == 30
    west = L.lane_by_id(signs["yield"].lane_ids[0])
    assert west.points[-1, 0] < west.points[0, 0]
    assert np.isclose(signs["yield"].heading, 0.0, atol=1e-6)   # faces the westbound cars


def test_poles_and_barriers(layout):
    L, _ = layout
    assert sorted(p.kind for p in L.poles) == ["pole", "pole", "street_lamp"]
    assert next(p for p in L.poles if p.kind == "street_lamp").height == 8
    assert {b.kind for b in L.barriers} == {"fence", "guard_rail"}
    # the guard rail is a road edge as well
    assert any(e.id == f"ls{b.id[7:]}" for b in L.barriers if b.kind == "guard_rail"
               for e in L.road_edges)


def test_bad_lanelets_and_markings_are_warned_by_id_and_handled(layout):
    L, msgs = layout
    assert any("lanelet 9001" in m_ and "126 m" in m_ and "repaired" in m_ for m_ in msgs)
    assert any("lanelet 9002" in m_ and "cross" in m_ and "skipped" in m_ for m_ in msgs)
    assert any("line string 9003" in m_ and "lane marking" in m_ for m_ in msgs)
    ids = {f.id for f in L.features()}
    assert "ll9002" not in ids and "area_ll9002" not in ids and "ls9003" not in ids
    # the repaired lanelet: the road stops where its left bound stops (no 100 m spike)
    area = next(a for a in L.road_areas if a.id == "area_ll9001")
    assert area.polygon[:, 0].max() < 174.5 + 1e-6
    lane = L.lane_by_id("ll9001")
    assert 23 < lane.length() < 25 and np.allclose(lane.widths, 3.5, atol=0.05)


def test_strict_makes_bad_geometry_an_error(street):
    with pytest.raises(InputError, match=r"lanelet 900[12]"):
        l2.read_lanelet2(street, ImportOptions(origin=ORIGIN, strict=True))


def test_curved_lanelets_are_not_flagged():
    """Bounds of a tight turn differ by width x turn: not a degenerate lanelet."""
    import lanelet2
    from lanelet2.core import AttributeMap, Lanelet, LineString3d, Point3d, getId
    t = np.linspace(0, np.pi / 2, 12)

    def arc(r):
        return LineString3d(getId(), [Point3d(getId(), r * np.cos(a), r * np.sin(a), 0) for a in t])
    ll = Lanelet(getId(), arc(3.0), arc(6.5), AttributeMap({"type": "lanelet", "subtype": "road"}))
    c, left, right = l2.lanelet_geometry("x", ll, ImportOptions(strict=True))
    assert len(c) >= 2 and len(left) == 12


def test_sample_crossing_imports_without_warnings(tmp_path):
    import warnings
    _s = importlib.util.spec_from_file_location("make_maps", ROOT / "samples/maps/make_maps.py")
    mm = importlib.util.module_from_spec(_s)
    _s.loader.exec_module(mm)
    p = mm.lanelet2_crossing(tmp_path / "c.osm")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        L = l2.read_lanelet2(p, ImportOptions(origin=mm.KARLSRUHE))
    assert len(L.traffic_lights) == 1 and len(L.stop_signs) == 1


def test_lanelet2_signals_are_proxy_geometry(layout):
    from lsd3d_usd.proxy import build_proxy, check_part
    L, _ = layout
    parts = [p for ps in build_proxy(L).values() for p in ps]
    for p in parts:
        check_part(p)
    cls = {}
    for p in parts:
        cls.setdefault(p.part_id.split("/")[0], set()).add(p.cls)
    tl = L.traffic_lights[0]
    assert cls[tl.id] == {"pole", "traffic_light"}
    # the head hangs over the lane; its mast stands at the roadside, an arm between them
    mast = next(p for p in parts if p.part_id == f"{tl.id}/mast")
    assert mast.vertices[:, 1].mean() < -3.5
    assert any(p.part_id == f"{tl.id}/arm" for p in parts)
    assert all(cls[s.id] == {"pole", "sign"} for s in L.traffic_signs)
    assert not any(k.startswith("tl_") for k in cls)      # the map lists its lights
