"""OpenDRIVE read whole: direct and virtual junctions give the links the file defines (and the
longest route crosses them), objects and signals become layout features and proxy geometry."""
import importlib.util
import warnings

import numpy as np
import pytest

from conftest import ROOT
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import routes as lane_graph
from lsd3d_usd.layout import opendrive as od
from lsd3d_usd.layout import opendrive_export

_spec = importlib.util.spec_from_file_location("make_real_maps", ROOT / "samples/maps/make_real_maps.py")
maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(maps)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("real_xodr")
    return {"direct": maps.opendrive_direct_junction(d / "direct.xodr"),
            "virtual": maps.opendrive_virtual_junction(d / "virtual.xodr"),
            "town": maps.opendrive_town(d / "town.xodr")}


def test_the_test_files_are_valid_opendrive_1_7(files):
    for p in files.values():
        assert opendrive_export.validate(p) == [], p.name


def test_direct_junction_links_incoming_to_linked_roads(files):
    L = od.read_opendrive(files["direct"])
    succ = {ln.id: ln.successors for ln in L.lanes}
    assert succ["1_0_-1"] == ["2_0_-1"]
    assert succ["1_0_-2"] == ["3_0_-1"]          # the exit ramp
    assert succ["2_0_1"] == ["1_0_1"]            # the left lane travels back into road 1
    assert L.lane_by_id("3_0_-1").predecessors == ["1_0_-2"]
    # links join lanes that meet: the successor starts where its predecessor ends
    for a, bs in succ.items():
        for b in bs:
            assert np.hypot(*(L.lane_by_id(a).points[-1, :2] - L.lane_by_id(b).points[0, :2])) < 0.01
    route, length = lane_graph.longest_route(L)
    assert route[0] == "1_0_-1" and route[1] in ("2_0_-1", "3_0_-1")
    assert length > 170


def test_virtual_junction_branches_and_merges_mid_road(files):
    L = od.read_opendrive(files["virtual"])
    # the main road is split at s = 80 and 120 where the junction's roads meet it
    main = [ln for ln in L.lanes if ln.road_id == "1" and ln.id.endswith("_-1")]
    assert [ln.id for ln in main] == ["1_0_-1", "1_1_-1", "1_2_-1"]
    assert np.allclose([ln.length() for ln in main], [80, 40, 80])
    assert set(L.lane_by_id("1_0_-1").successors) == {"1_1_-1", "2_0_-1"}
    assert L.lane_by_id("3_0_-1").successors == ["1_2_-1"]
    assert set(L.lane_by_id("1_2_-1").predecessors) == {"1_1_-1", "3_0_-1"}
    assert L.lane_by_id("2_0_-1").is_junction and L.lane_by_id("2_0_-1").successors == ["4_0_-1"]
    # the left lane of the main road still runs through, against s
    assert L.lane_by_id("1_2_1").successors == ["1_1_1"]
    route, _ = lane_graph.longest_route(L)
    assert route == ["1_0_-1", "2_0_-1", "4_0_-1"]


def test_mid_road_link_off_the_road_warns_and_strict_refuses(tmp_path, files):
    bad = tmp_path / "bad.xodr"
    bad.write_text(files["virtual"].read_text().replace('elementS="80"', 'elementS="900"'))
    with pytest.warns(od.OpenDriveWarning, match=r"road 2: its start links to road 1 at s=900"):
        L = od.read_opendrive(bad)
    assert "2_0_-1" not in L.lane_by_id("1_0_-1").successors
    with pytest.raises(InputError, match="road 2"):
        od.read_opendrive(bad, strict=True)


def test_objects_and_signals_become_features(files):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        L = od.read_opendrive(files["town"])
    c = L.counts()
    assert c["Building"] == 2 and c["Tree"] == 8 and c["Crosswalk"] == 1
    assert c["ParkingSpot"] == 3 and c["Barrier"] == 2 and c["Pole"] == 6
    assert c["TrafficLight"] == 2 and c["StopSign"] == 1 and c["TrafficSign"] == 2
    x0, y0 = maps.TOWN_START
    b1 = next(b for b in L.buildings if b.id == "obj_1_b1")
    assert b1.height_hint == 14 and np.allclose(b1.footprint[:, :2].mean(0), [x0 + 40, y0 + 18])
    trees = sorted(t.position[0] for t in L.trees)
    assert np.allclose(np.diff(trees), 20) and np.allclose([t.position[1] for t in L.trees], y0 + 11)
    rail = next(b for b in L.barriers if b.kind == "guard_rail")
    assert np.isclose(rail.points[0, 0], x0) and np.isclose(rail.points[-1, 0], x0 + 50)
    assert np.allclose(rail.points[:, 1], y0 - 10.5) and rail.height == 0.8
    assert {b.kind for b in L.barriers} == {"guard_rail", "wall"}
    kinds = sorted(p.kind for p in L.poles)
    assert kinds == ["bollard", "pole"] + ["street_lamp"] * 4
    spots = sorted((p.occupied, round(p.length, 2)) for p in L.parking_spots)
    assert spots == [(False, 5.5), (False, 5.5), (True, 4.5)]
    east = next(t for t in L.traffic_lights if t.id == "sig_1_s1")
    # "+" is valid for traffic along s (+x here): it faces -x, controls the validity lanes
    assert np.isclose(abs(east.heading), np.pi) and set(east.lane_ids) == {"1_0_-1", "1_0_-2"}
    assert np.isclose(east.height, 4.2) and np.allclose(east.position[:2], [x0 + 150, y0 - 8])
    west = next(t for t in L.traffic_lights if t.id == "sig_1_s2")
    assert np.isclose(west.heading, 0.0) and set(west.lane_ids) == {"1_0_1", "1_0_2"}
    signs = {t.kind: t for t in L.traffic_signs}
    assert signs["speed_limit"].value == 30 and signs["speed_limit"].code == "DE:274"
    assert signs["yield"].code == "DE:205"
    assert L.stop_signs[0].lane_ids == ["1_0_-1", "1_0_-2"]
    src = L.metadata["source"]
    assert src["signalsComplete"] is True and src["objectsNotRead"] == {"gantry": 1}


def test_bad_object_warns_with_road_and_id(tmp_path, files):
    bad = tmp_path / "bad.xodr"
    bad.write_text(files["town"].read_text().replace('id="p1" type="pole" name="post" s="60"',
                                                     'id="p1" type="pole" name="post" s="600"'))
    with pytest.warns(od.OpenDriveWarning, match=r"road 1: object p1: s=600"):
        L = od.read_opendrive(bad)
    assert len(L.poles) == 5
    with pytest.raises(InputError, match="object p1"):
        od.read_opendrive(bad, strict=True)


def test_map_objects_and_signals_are_proxy_geometry(files):
    from lsd3d_usd.proxy import build_proxy, check_part
    L = od.read_opendrive(files["town"])
    parts = [p for ps in build_proxy(L).values() for p in ps]
    for p in parts:
        check_part(p)
    by_obj = {}
    for p in parts:
        by_obj.setdefault(p.part_id.split("/")[0], set()).add(p.cls)
    assert by_obj["sig_1_s1"] == {"pole", "traffic_light"}
    assert by_obj["sig_1_s5"] == {"pole", "sign"} and by_obj["sig_1_s3"] == {"pole", "sign"}
    assert by_obj["obj_1_b1"] == {"building"} and "vegetation" in by_obj["obj_1_t1_0"]
    assert by_obj["obj_1_g1"] == {"pole"} and by_obj["obj_1_w1"] == {"building"}
    assert by_obj["obj_1_c1"] == {"vehicle"} and "obj_1_ps1" not in by_obj   # an empty bay
    # the map lists its traffic lights: none are derived; lamps near the map's are not doubled
    assert not any(k.startswith("tl_") for k in by_obj)
    lamps = [p.vertices[:, :2].mean(0) for p in parts if p.part_id.endswith("/mast")
             and (p.part_id.startswith("sl_") or p.part_id.startswith("obj_1_l1"))]
    d = np.hypot(*(np.array(lamps)[:, None] - np.array(lamps)[None]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    assert d.min() > 10
