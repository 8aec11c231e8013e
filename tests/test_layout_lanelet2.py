"""Lanelet2 import: maps built with the lanelet2 API and written with its writer."""
import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import importers
from lsd3d_usd.layout import lanelet2_import as L2

lanelet2 = pytest.importorskip("lanelet2")
ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("make_maps", ROOT / "samples/maps/make_maps.py")
make_maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_maps)
ORIGIN = make_maps.KARLSRUHE


@pytest.fixture(scope="module")
def crossing(tmp_path_factory):
    return make_maps.lanelet2_crossing(tmp_path_factory.mktemp("l2") / "crossing.osm")


def read(path, **kw):
    layout, imp = importers.read_map(path, importers.ImportOptions(**kw))
    assert imp.name == "lanelet2"
    return layout


def test_mapping_of_the_crossing(crossing):
    L = read(crossing, origin=ORIGIN)
    c = L.counts()
    assert c["LaneCenter"] == 8 + 12                 # 4 arms × 2 lanes + 12 junction movements
    assert c["RoadLine"] == 4 and c["RoadEdge"] == 8 and c["Crosswalk"] == 1
    assert c["StopLine"] == 2 and c["StopSign"] == 1 and c["Building"] == 1
    assert c["VegetationZone"] == 1 and c["ParkingSpot"] == 1 and c["RoadArea"] == 20
    L.reindex()
    # the west approach (inbound lane travels +x at y = -1.75 from x = -47 to -7)
    west = next(ln for ln in L.lanes if np.allclose(ln.points[0, :2], [-47, -1.75], atol=1e-6))
    assert np.allclose(west.points[-1, :2], [-7, -1.75], atol=1e-6)
    assert np.allclose(west.widths, 3.5, atol=1e-6) and west.direction == "forward"
    assert west.speed_limit_mps == pytest.approx(50 / 3.6)
    # the routing graph: straight, right and left movements follow the approach
    assert len(west.successors) == 3
    ends = sorted(tuple(np.round(L.lane_by_id(s).points[-1, :2], 3)) for s in west.successors)
    assert ends == [(-1.75, -7.0), (1.75, 7.0), (7.0, -1.75)]
    for s in west.successors:
        nxt = L.lane_by_id(s)
        assert west.id in nxt.predecessors and len(nxt.successors) == 1
    # curbstones turned so that the road lies on their left
    for e in L.road_edges:
        d = e.points[-1, :2] - e.points[0, :2]
        mid = (e.points[0, :2] + e.points[-1, :2]) / 2
        assert d[0] * (-mid[1]) - d[1] * (-mid[0]) > 0     # the centre (0, 0) side is left
    assert {ln.kind for ln in L.road_lines} == {"broken"}
    sign = L.stop_signs[0]
    assert sign.lane_ids and all(x in {ln.id for ln in L.lanes} for x in sign.lane_ids)
    assert L.buildings[0].height_hint == 15.0
    spot = L.parking_spots[0]
    assert spot.length == pytest.approx(20.0, abs=1e-5) and spot.width == pytest.approx(7.0, abs=1e-5)
    assert not spot.occupied
    src = L.metadata["source"]
    assert src["origin"] == list(ORIGIN) and src["originFrom"] == "flag"


def test_default_origin_from_the_file(crossing, tmp_path):
    L = read(crossing)
    assert L.metadata["source"]["originFrom"] == "node extent"
    lat, lon = L.metadata["source"]["origin"]
    assert abs(lat - ORIGIN[0]) < 1e-4 and abs(lon - ORIGIN[1]) < 1e-4
    # a <bounds> element in the header wins
    text = crossing.read_text()
    with_bounds = tmp_path / "b.osm"
    with_bounds.write_text(re.sub(r"(<osm[^>]*>)", r'\1\n  <bounds minlat="49.0" minlon="8.4" maxlat="49.002" maxlon="8.402"/>',
                                  text, count=1))
    L = read(with_bounds)
    assert L.metadata["source"]["originFrom"] == "file bounds"
    assert L.metadata["source"]["origin"] == pytest.approx([49.001, 8.401])


def test_two_way_lanelet_is_direction_both(tmp_path):
    from lanelet2.core import AttributeMap, Lanelet, LaneletMap, LineString3d, Point3d, getId
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    def ls(*pts):
        return LineString3d(getId(), [Point3d(getId(), x, y, 0) for x, y in pts],
                            AttributeMap({"type": "line_thin", "subtype": "solid"}))
    lm = LaneletMap()
    lm.add(Lanelet(getId(), ls((0, 2), (30, 2)), ls((0, -2), (30, -2)),
                   AttributeMap({"type": "lanelet", "subtype": "road", "location": "urban", "one_way": "no"})))
    path = tmp_path / "two.osm"
    lanelet2.io.write(str(path), lm, LocalCartesianProjector(Origin(*ORIGIN)))
    L = read(path, origin=ORIGIN)
    assert [ln.direction for ln in L.lanes] == ["both"]
    assert np.allclose(L.lanes[0].widths, 4.0, atol=1e-6)


def test_broken_references_warn_with_ids(crossing, tmp_path):
    text = crossing.read_text()
    way_id = re.search(r'<way id="(\d+)"', text).group(1)
    broken = tmp_path / "broken.osm"
    broken.write_text(re.sub(rf'<way id="{way_id}".*?</way>', "", text, count=1, flags=re.S))
    with pytest.warns(importers.MapWarning) as rec:
        L = read(broken, origin=ORIGIN)
    msgs = " ".join(str(w.message) for w in rec)
    assert way_id in msgs and "nonexistent member" in msgs
    assert 0 < len(L.lanes) < 20
    with pytest.raises(InputError, match="lanelet2:"):
        read(broken, origin=ORIGIN, strict=True)


def test_no_drivable_lanes_and_not_lanelet2(tmp_path):
    from lanelet2.core import AttributeMap, Lanelet, LaneletMap, LineString3d, Point3d, getId
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector
    lm = LaneletMap()
    mk = lambda y: LineString3d(getId(), [Point3d(getId(), 0, y, 0), Point3d(getId(), 20, y, 0)],
                                AttributeMap({"type": "line_thin", "subtype": "solid"}))
    lm.add(Lanelet(getId(), mk(1), mk(-1), AttributeMap({"type": "lanelet", "subtype": "walkway",
                                                          "location": "urban", "one_way": "no"})))
    path = tmp_path / "walk.osm"
    lanelet2.io.write(str(path), lm, LocalCartesianProjector(Origin(*ORIGIN)))
    with pytest.raises(InputError, match="no drivable lanelet"):
        read(path, origin=ORIGIN)
    plain = tmp_path / "plain.osm"
    plain.write_text('<?xml version="1.0"?><osm version="0.6"><node id="1" lat="1" lon="2"/></osm>')
    assert not L2.sniff(plain, plain.read_bytes())
    with pytest.raises(InputError, match="is not a lanelet2 file"):
        importers.read_map(plain, format="lanelet2")


def test_far_from_origin_and_bad_origin(crossing):
    # the map is at Karlsruhe; an origin ~60 km away warns, ~150 km away is an error, naming ids
    with pytest.warns(importers.MapWarning, match=r"lanelet \d+ lies 5\d\.\d km from the origin"):
        read(crossing, origin=(ORIGIN[0] + 0.5, ORIGIN[1]))
    with pytest.raises(InputError, match=r"lanelet \d+ lies 1\d\d km from the origin"):
        read(crossing, origin=(ORIGIN[0] + 1.5, ORIGIN[1]))
    with pytest.raises(InputError, match="not a latitude"):
        read(crossing, origin=(95.0, 8.0))


def test_size_limit_checked_before_loading(crossing, monkeypatch):
    monkeypatch.setattr(L2, "MAX_FILE_BYTES", 1000)
    with pytest.raises(InputError, match="at most 1000 bytes"):
        L2.read_lanelet2(crossing, importers.ImportOptions(origin=ORIGIN))
