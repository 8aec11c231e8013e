"""OpenStreetMap import: OSM XML written by the test (and as PBF with osmium)."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import importers
from lsd3d_usd.layout import osm_import as O

osmium = pytest.importorskip("osmium")
ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("make_maps", ROOT / "samples/maps/make_maps.py")
make_maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_maps)
ORIGIN = make_maps.MUNICH


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    return make_maps.osm_town(tmp_path_factory.mktemp("osm") / "town.osm")


def read(path, **kw):
    layout, imp = importers.read_map(path, importers.ImportOptions(**kw))
    assert imp.name == "osm"
    layout.reindex()
    return layout


def lanes_of(L, way):
    return [ln for ln in L.lanes if ln.road_id == f"w{way}"]


def test_mapping_of_the_town(town):
    L = read(town)
    assert L.metadata["source"]["originFrom"] == "file bounds"
    assert L.metadata["source"]["origin"] == pytest.approx(list(ORIGIN), abs=1e-9)
    main = lanes_of(L, 5000)                  # primary, lanes=4, split at two junctions
    assert len(main) == 3 * 4 and {ln.widths[0] for ln in main} == {3.5}
    first = [ln for ln in main if ln.id.startswith("w5000_0_")]
    assert sorted(ln.id[-2:] for ln in first) == ["b0", "b1", "f0", "f1"]
    f0 = next(ln for ln in first if ln.id.endswith("f0"))
    assert np.allclose(f0.points[:, 1], -1.75, atol=0.05)       # right of the centre line
    assert f0.right_neighbors == ["w5000_0_f1"] and f0.speed_limit_mps == pytest.approx(50 / 3.6)
    oneway = lanes_of(L, 5002)                # residential, oneway, lanes=1, width=4
    assert all(ln.id[-2:] == "f0" and ln.widths[0] == 4.0 for ln in oneway)
    assert all(ln.points[0, 1] > ln.points[-1, 1] for ln in oneway)   # drawn north → south
    service = lanes_of(L, 5003)
    assert len(service) == 1 and service[0].direction == "both"
    assert not lanes_of(L, 5004)              # a footway is not a road
    # junctions: connectors join every incoming lane, links meet within 1 cm
    junction = [ln for ln in L.lanes if ln.is_junction]
    assert junction
    for ln in L.lanes:
        for s in ln.successors:
            assert np.abs(L.lane_by_id(s).points[0] - ln.points[-1]).max() < 0.01
            assert ln.id in L.lane_by_id(s).predecessors
    assert all(ln.successors for ln in main if ln.id.startswith("w5000_0_f"))
    # other features
    assert len(L.crosswalks) == 1 and L.crosswalks[0].area() == pytest.approx(3.0 * 14.0, rel=0.01)
    assert len(L.stop_signs) == 1 and L.stop_signs[0].lane_ids
    heights = {b.id: (b.height_hint, b.floors_hint) for b in L.buildings}
    assert heights == {"b5005": (18.0, 0), "b5006": (12.0, 4), "b5007": (12.0, 0)}
    assert len([t for t in L.trees if t.id.startswith("tree1")]) == 6
    assert all(t.height_hint == 11.0 and t.crown_radius_hint == 3.0 for t in L.trees if t.id.startswith("tree1"))
    assert len([t for t in L.trees if t.id.startswith("treerow")]) == 11
    assert [z.kind for z in L.vegetation_zones] == ["park"]
    assert L.sidewalks and L.road_areas and L.road_edges


def test_bbox_cuts_the_area(town):
    lat0, lon0 = make_maps._latlon(ORIGIN, -160.0, -130.0)
    lat1, lon1 = make_maps._latlon(ORIGIN, 0.0, 130.0)      # the west half
    L = read(town, bbox=(lon0, lat0, lon1, lat1))
    assert L.metadata["source"]["originFrom"] == "bbox" and L.extent is not None
    (x0, y0), (x1, y1) = L.extent
    for f in L.features():
        c = f.coords()
        # lanes are cut with their centre line; offsets of a line of latitude (slightly curved in
        # east-north-up) may end a fraction of a millimetre further
        assert c[:, 0].max() <= x1 + 1e-3 and c[:, 0].min() >= x0 - 1e-3, f.id
    assert not lanes_of(L, 5002) and not lanes_of(L, 5003)   # east of the cut
    assert {b.id for b in L.buildings} == {"b5005", "b5007"}


def test_pbf_reads_like_xml(town, tmp_path):
    pbf = tmp_path / "town.osm.pbf"
    with osmium.SimpleWriter(str(pbf)) as w:
        for obj in osmium.FileProcessor(str(town)):
            w.add(obj)
    assert importers.detect(pbf).name == "osm"
    a, b = read(town, origin=ORIGIN), read(pbf, origin=ORIGIN)
    assert a.counts() == b.counts()
    assert max(np.abs(x.points - y.points).max() for x, y in zip(a.lanes, b.lanes)) < 1e-6


def test_limits_checked_while_reading(town, monkeypatch):
    monkeypatch.setattr(O, "MAX_WAYS", 3)
    with pytest.raises(InputError, match="more than 3 ways"):
        read(town)
    monkeypatch.setattr(O, "MAX_NODES", 10)
    lat0, lon0 = make_maps._latlon(ORIGIN, -160.0, -130.0)
    lat1, lon1 = make_maps._latlon(ORIGIN, 160.0, 130.0)
    with pytest.raises(InputError, match="more than 10 nodes in the area"):
        read(town, bbox=(lon0, lat0, lon1, lat1))


def test_bad_input(town, tmp_path):
    text = town.read_text()
    broken = tmp_path / "broken.osm"
    broken.write_text(text.replace('<nd ref="1003"/>', '<nd ref="999999"/>', 1))
    with pytest.warns(importers.MapWarning, match=r"way 5\d+: references node 999999"):
        read(broken)
    with pytest.raises(InputError, match="way 5\\d+: references node 999999"):
        read(broken, strict=True)
    no_roads = tmp_path / "houses.osm"
    no_roads.write_text('<?xml version="1.0"?>\n<osm version="0.6">\n<node id="1" lat="48.1" lon="11.5"/>\n'
                        '<node id="2" lat="48.1" lon="11.5001"/>\n<node id="3" lat="48.1001" lon="11.5001"/>\n'
                        '<way id="9"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="1"/>'
                        '<tag k="building" v="yes"/></way>\n</osm>\n')
    with pytest.raises(InputError, match="no drivable highway"):
        read(no_roads)
    with pytest.raises(InputError, match=r"node \d+ lies 1\d\d km from the origin"):
        read(town, origin=(ORIGIN[0] + 1.0, ORIGIN[1]))
    with pytest.raises(InputError, match="--bbox"):
        read(town, bbox=(11.6, 48.0, 11.5, 48.2))
    not_xml = tmp_path / "x.osm"
    not_xml.write_text("lat,lon\n48.1,11.5\n")
    with pytest.raises(InputError, match="not a map format"):
        importers.read_map(not_xml)
