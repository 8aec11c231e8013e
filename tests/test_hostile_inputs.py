"""Hostile map, config and file inputs (issue 40, cases 6 and 13-25): one error line
naming what is wrong and where, exit 1, nothing written."""
import os

import pytest


def _nodes(lat0=48.0, lon0=8.4, n=5):
    return "".join(f'<node id="{i}" lat="{lat0 + i * 1e-4}" lon="{lon0 + i * 1e-4}"/>'
                   for i in range(1, n + 1))


def _osm(body, decl='<?xml version="1.0"?>'):
    return f'{decl}<osm version="0.6">{body}</osm>'


WAY = '<way id="7"><nd ref="1"/><nd ref="2"/><nd ref="3"/><tag k="highway" v="residential"/></way>'
LANELET = '<relation id="2"><tag k="type" v="lanelet"/></relation>'


@pytest.mark.parametrize("text,needles", [
    # 13: Lanelet2 with a NaN node, truncated, with a DTD
    (_osm('<node id="1" lat="nan" lon="8.4"/>' + LANELET), ("node 1: lat 'nan'",)),
    (_osm('<node id="1" lat="49.0" lon="8.4"/>' + LANELET)[:-len("</osm>")], ("truncated",)),
    (_osm('<node id="1" lat="49.0" lon="8.4"/>' + LANELET,
          '<?xml version="1.0"?><!DOCTYPE osm [<!ENTITY a "b">]>'), ("DOCTYPE", "refused")),
    # 14: OSM highway node NaN / inf / out of range
    (_osm(_nodes() + '<node id="9" lat="NaN" lon="8.4"/>' + WAY.replace('"3"/>', '"9"/>')),
     ("node 9: lat 'NaN'",)),
    (_osm(_nodes() + '<node id="9" lat="48" lon="inf"/>' + WAY.replace('"3"/>', '"9"/>')),
     ("node 9: lon 'inf'",)),
    # 19: DTD in OSM
    (_osm(_nodes() + WAY, '<?xml version="1.0"?>\n<!DOCTYPE osm [\n<!ENTITY x "y">\n]>\n'),
     ("DOCTYPE",)),
])
def test_bad_osm_and_lanelet2_maps(tmp_path, cli_error, text, needles):
    src = tmp_path / "map.osm"
    src.write_text(text)
    cli_error(["layout", "import", src, "-o", tmp_path / "out.usda"], "map.osm", *needles)
    assert sorted(os.listdir(tmp_path)) == ["map.osm"]


def test_opendrive_with_a_dtd(tmp_path, cli_error):
    src = tmp_path / "m.xodr"
    src.write_text('<?xml version="1.0"?><!DOCTYPE OpenDRIVE [<!ENTITY a "b">]>'
                   '<OpenDRIVE><header revMajor="1" revMinor="6"/></OpenDRIVE>')
    cli_error(["layout", "import", src, "-o", tmp_path / "o.usda"], "m.xodr", "DOCTYPE", "refused")
    assert sorted(os.listdir(tmp_path)) == ["m.xodr"]


def test_truncated_and_empty_pbf(tmp_path, cli_error):
    import osmium
    from tests.conftest import ROOT
    pbf = tmp_path / "city.osm.pbf"
    w = osmium.SimpleWriter(str(pbf))
    for o in osmium.FileProcessor(str(ROOT / "samples" / "maps" / "bounds_city.osm")):
        w.add(o)
    w.close()
    data = pbf.read_bytes()
    cut = tmp_path / "cut.osm.pbf"
    cut.write_bytes(data[: len(data) // 2])
    cli_error(["layout", "import", cut, "-o", tmp_path / "o.usda"], "cut.osm.pbf", "truncated")
    empty = tmp_path / "empty.osm.pbf"
    osmium.SimpleWriter(str(empty)).close()
    cli_error(["layout", "import", empty, "-o", tmp_path / "o.usda"], "empty.osm.pbf",
              "empty or truncated")
    assert not (tmp_path / "o.usda").exists()


def test_import_refuses_an_area_beyond_the_layout_limit(tmp_path, cli_error):
    # 6: a small town inside a 1 x 1 degree --bbox: a 111 km layout every reader refuses
    src = tmp_path / "town.osm"
    src.write_text(_osm(_nodes(48.5, 11.5) + WAY))
    cli_error(["layout", "import", src, "--bbox=11,48,12,49", "-o", tmp_path / "o.usda"],
              "town.osm", "extent", "limit of 50000 m")
    assert sorted(os.listdir(tmp_path)) == ["town.osm"]
