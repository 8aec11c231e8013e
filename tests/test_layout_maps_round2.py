"""Real maps, second round (issue 61): each test builds its own small map and checks the
values its format defines."""
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from lsd3d_usd.layout import opendrive as od

XODR = """<?xml version="1.0" encoding="UTF-8"?>
<OpenDRIVE><header revMajor="1" revMinor="6" name="late"/>
<road id="7" length="400" junction="-1">
 <planView><geometry s="0" x="0" y="0" hdg="0" length="400"><line/></geometry></planView>
 <elevationProfile>{elev}</elevationProfile>
 <lateralProfile>{sup}</lateralProfile>
 <lanes>{offset}
  <laneSection s="0">
   <center><lane id="0" type="none"/></center>
   <right>
    <lane id="-1" type="driving"><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane>
    <lane id="-2" type="driving"><width sOffset="{s2}" a="3.5" b="0.02" c="0" d="0"/></lane>
   </right>
  </laneSection>
 </lanes>
</road></OpenDRIVE>
"""


def write_xodr(tmp_path, s2=180, elev='<elevation s="50" a="10" b="0.1" c="0" d="0"/>',
               sup="", offset=""):
    p = tmp_path / "late.xodr"
    p.write_text(XODR.format(s2=s2, elev=elev, sup=sup, offset=offset))
    return p


def read_warn(p):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        L = od.read_opendrive(p)
    return L, [str(x.message) for x in w]


def at_x(lane, x):
    """Lane centre (y, z) and width at x (a straight road along +x)."""
    P = lane.points
    k = int(np.argmin(np.abs(P[:, 0] - x)))
    assert abs(P[k, 0] - x) < 1e-6
    return P[k, 1], P[k, 2], np.asarray(lane.widths)[k]


def test_opendrive_late_width_and_elevation_hold_first_value(tmp_path):
    L, msgs = read_warn(write_xodr(tmp_path))
    ln = L.lane_by_id("7_0_-2")
    y, z, w = at_x(ln, 0.0)
    # width 3.5 m (the record's a) and z = 10 m (the elevation record's a) at s = 0
    assert w == pytest.approx(3.5, abs=1e-9) and y == pytest.approx(-5.25, abs=1e-9)
    assert z == pytest.approx(10.0, abs=1e-9)
    y, z, w = at_x(ln, 180.0)
    assert w == pytest.approx(3.5, abs=1e-9) and z == pytest.approx(10 + 0.1 * 130, abs=1e-9)
    y, z, w = at_x(ln, 400.0)
    assert w == pytest.approx(3.5 + 0.02 * 220, abs=1e-9)
    late = [m for m in msgs if "held" in m]
    assert len(late) == 1, msgs     # once per road, naming every late record
    assert "road 7" in late[0] and "<width> of lane -2" in late[0] and "sOffset=180" in late[0]
    assert "<elevation> s=50" in late[0]


def test_opendrive_late_offset_and_superelevation_hold(tmp_path):
    p = write_xodr(tmp_path, s2=0, elev="",
                   sup='<superelevation s="100" a="0.05" b="0.001" c="0" d="0"/>',
                   offset='<laneOffset s="20" a="-1" b="0.01" c="0" d="0"/>')
    L, msgs = read_warn(p)
    y, z, w = at_x(L.lane_by_id("7_0_-1"), 0.0)
    roll = 0.05      # held; t is along the rolled surface: -1 - 1.75 from the reference line
    t = -1 - 1.75
    assert y == pytest.approx(t * np.cos(roll), abs=1e-9)
    assert z == pytest.approx(t * np.sin(roll), abs=1e-9)
    late = [m for m in msgs if "held" in m]
    assert len(late) == 1 and "<laneOffset> s=20" in late[0] and "<superelevation> s=100" in late[0]


def test_opendrive_records_from_zero_do_not_warn(tmp_path):
    L, msgs = read_warn(write_xodr(tmp_path, s2=0, elev='<elevation s="0" a="10" b="0" c="0" d="0"/>'))
    assert not [m for m in msgs if "held" in m]
    assert at_x(L.lane_by_id("7_0_-2"), 0.0)[2] == pytest.approx(3.5)


# ------------------------------------------------------------------ Lanelet2

L2_ORIGIN = (49.0, 8.4)


def l2_latlon(x, y, origin=L2_ORIGIN):
    """lat, lon of the point at (x, y) on the ellipsoid's surface, in the ENU frame about
    ``origin`` (lanelet2's own projector, iterated onto height 0)."""
    from lanelet2.core import BasicPoint3d, GPSPoint
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector
    pr = LocalCartesianProjector(Origin(*origin))
    z = 0.0
    for _ in range(3):
        g = pr.reverse(BasicPoint3d(x, y, z))
        z = pr.forward(GPSPoint(g.lat, g.lon, 0.0)).z
    return g.lat, g.lon


def write_l2(tmp_path, xs=(0, 1000, 2000, 3000), ele=0.0, sign=None, name="m.osm"):
    """One straight 3.5 m lanelet along +x; ``sign``: the subtype of a traffic sign rule."""
    nodes, ways, rels = [], [], []
    nid = [0]

    def node(x, y):
        nid[0] += 1
        lat, lon = l2_latlon(x, y)
        nodes.append(f'<node id="{nid[0]}" lat="{lat:.12f}" lon="{lon:.12f}" version="1">'
                     f'<tag k="ele" v="{ele}"/></node>')
        return nid[0]

    def way(wid, refs, **tags):
        nd = "".join(f'<nd ref="{r}"/>' for r in refs)
        tg = "".join(f'<tag k="{k}" v="{v}"/>' for k, v in tags.items())
        ways.append(f'<way id="{wid}" version="1">{nd}{tg}</way>')

    way(1001, [node(x, 1.75) for x in xs], type="line_thin", subtype="solid")
    way(1002, [node(x, -1.75) for x in xs], type="line_thin", subtype="solid")
    reg = ""
    if sign:
        way(1003, [node(40, -3), node(40, -3.5)], type="traffic_sign", subtype=sign)
        rels.append('<relation id="3001" version="1"><member type="way" ref="1003" role="refers"/>'
                    '<tag k="type" v="regulatory_element"/><tag k="subtype" v="traffic_sign"/>'
                    '</relation>')
        reg = '<member type="relation" ref="3001" role="regulatory_element"/>'
    rels.append('<relation id="2001" version="1"><member type="way" ref="1001" role="left"/>'
                f'<member type="way" ref="1002" role="right"/>{reg}<tag k="type" v="lanelet"/>'
                '<tag k="subtype" v="road"/><tag k="location" v="urban"/>'
                '<tag k="one_way" v="yes"/></relation>')
    p = tmp_path / name
    p.write_text('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="test">'
                 + "".join(nodes + ways + rels) + "</osm>\n")
    return p


def read_map(p, **kw):
    from lsd3d_usd.layout import importers
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        L, imp = importers.read_map(p, importers.ImportOptions(**kw))
    return L, imp, [str(x.message) for x in w]


def test_lanelet2_flat_map_stays_flat_3km(tmp_path):
    pytest.importorskip("lanelet2")
    L, imp, _ = read_map(write_l2(tmp_path), origin=L2_ORIGIN)
    assert imp.name == "lanelet2"
    pts = L.lanes[0].points
    # ele is the map's z: no sag by the Earth's curvature (it was 0.70 m at 3 km)
    assert np.abs(pts[:, 2]).max() < 0.01
    assert pts[-1, 0] == pytest.approx(3000, abs=0.005) and pts[-1, 1] == pytest.approx(0, abs=0.005)


def test_lanelet2_ele_is_z_and_the_plan_keeps_its_scale(tmp_path):
    pytest.importorskip("lanelet2")
    L, _, _ = read_map(write_l2(tmp_path, xs=(0, 425, 850), ele=520.0), origin=L2_ORIGIN)
    pts = L.lanes[0].points
    assert np.allclose(pts[:, 2], 520.0, atol=0.01)
    # not shrunk by 520 m / R (7 cm at 850 m)
    assert pts[-1, 0] == pytest.approx(850, abs=0.005)


def test_lanelet2_autoware_stop_sign(tmp_path):
    pytest.importorskip("lanelet2")
    L, _, _ = read_map(write_l2(tmp_path, xs=(0, 100), sign="stop_sign"), origin=L2_ORIGIN)
    assert len(L.stop_signs) == 1 and not L.traffic_signs
    assert L.stop_signs[0].lane_ids == [L.lanes[0].id]
    assert np.allclose(L.stop_signs[0].position[:2], [40, -3], atol=0.005)


# ------------------------------------------------------------------ OpenStreetMap

def write_osm(tmp_path, nodes, ways, name="m.osm", origin=L2_ORIGIN):
    """nodes: [(id, x, y, tags)] in metres about L2_ORIGIN; ways: [(id, [refs], tags)]."""
    def tags(t):
        return "".join(f'<tag k="{k}" v="{v}"/>' for k, v in t.items())
    out = []
    for nid, x, y, t in nodes:
        lat, lon = l2_latlon(x, y, origin)
        out.append(f'<node id="{nid}" version="1" lat="{lat:.10f}" lon="{lon:.10f}">{tags(t)}</node>')
    for wid, refs, t in ways:
        out.append(f'<way id="{wid}" version="1">' + "".join(f'<nd ref="{r}"/>' for r in refs)
                   + tags(t) + "</way>")
    p = tmp_path / name
    p.write_text('<?xml version="1.0"?>\n<osm version="0.6">\n' + "\n".join(out) + "\n</osm>\n")
    return p


def test_osm_first_node_outlier_is_dropped_and_the_road_kept(tmp_path):
    # a 100 m road whose first node lies 1 km past its end
    nodes = [(1, 1100, 0, {})] + [(k + 2, 20 * k, 0, {}) for k in range(6)]
    p = write_osm(tmp_path, nodes, [(7, [n[0] for n in nodes], {"highway": "residential"})])
    L, _, msgs = read_map(p, origin=L2_ORIGIN)
    xs = np.concatenate([ln.points[:, 0] for ln in L.lanes])
    assert xs.min() == pytest.approx(0, abs=0.01) and xs.max() == pytest.approx(100, abs=0.01)
    assert all(ln.length() == pytest.approx(100, abs=0.01) for ln in L.lanes)
    rep = [x for x in msgs if "way 7" in x]
    assert len(rep) == 1 and "dropped node(s) 1 (its first node)" in rep[0], msgs
    assert "at node 2;" in rep[0] and "1200 m -> 100 m" in rep[0]


def test_osm_last_node_outlier_is_dropped(tmp_path):
    nodes = [(k + 1, 20 * k, 0, {}) for k in range(6)] + [(9, -1000, 0, {})]
    p = write_osm(tmp_path, nodes, [(7, [n[0] for n in nodes], {"highway": "residential"})])
    L, _, msgs = read_map(p, origin=L2_ORIGIN)
    assert all(ln.length() == pytest.approx(100, abs=0.01) for ln in L.lanes)
    assert any("dropped node(s) 9 (its last node)" in x for x in msgs), msgs


# ------------------------------------------------------------------ command line

ROAD = [(k + 1, 20 * k - 50, 0, {}) for k in range(6)], [(7, [1, 2, 3, 4, 5, 6], {"highway": "residential"})]


@pytest.mark.parametrize("form", ["space", "equals"])
def test_cli_negative_origin(tmp_path, capsys, form):
    from lsd3d_usd.cli import main
    o = (-23.36, -119.73)
    p = write_osm(tmp_path, *ROAD, origin=o)
    flag = ["--origin", "-23.36,-119.73"] if form == "space" else ["--origin=-23.36,-119.73"]
    assert main(["layout", "import", str(p), *flag, "-o", str(tmp_path / "o.usda")]) == 0
    out = capsys.readouterr().out
    assert "origin lat -23.3600000, lon -119.7300000 (from --origin)" in out


def test_cli_negative_bbox(tmp_path, capsys):
    from lsd3d_usd.cli import main
    from lsd3d_usd.layout import usdio
    p = write_osm(tmp_path, *ROAD, origin=(51.5, 0.0))
    assert main(["layout", "import", str(p), "--bbox", "-0.001,51.499,0.001,51.501",
                 "-o", str(tmp_path / "o.usda")]) == 0
    assert "(the centre of --bbox)" in capsys.readouterr().out
    src = usdio.read_layout(tmp_path / "o.usda").metadata["source"]
    assert src["bbox"] == [-0.001, 51.499, 0.001, 51.501]


def test_cli_negative_value_parses_and_a_missing_value_still_fails():
    from lsd3d_usd.cli import build_parser
    args = build_parser().parse_args(["layout", "import", "m.osm", "--origin", "-1.5,-2",
                                      "-o", "o.usda"])
    from lsd3d_usd import configtree as ct
    assert ct.from_args(args)["origin"] == "-1.5,-2"     # flags of layout.config's tree
    with pytest.raises(SystemExit):
        build_parser().parse_args(["layout", "import", "m.osm", "--origin", "--bbox", "1,2,3,4"])


def test_import_summary_says_where_the_origin_came_from(tmp_path, capsys):
    from lsd3d_usd.cli import main
    p = write_osm(tmp_path, *ROAD)      # no <bounds>
    assert main(["layout", "import", str(p), "-o", str(tmp_path / "o.usda")]) == 0
    out = capsys.readouterr().out
    assert "(the centre of its nodes' extent: the file has no <bounds>; pass --origin" in out


def test_osm_crossing_node_on_a_crossing_way_is_one_crosswalk(tmp_path):
    nodes = [(1, -50, 0, {}), (2, 0, 0, {"highway": "crossing"}), (3, 50, 0, {}),
             (4, 0, -8, {}), (5, 0, 8, {})]
    ways = [(7, [1, 2, 3], {"highway": "residential"}),
            (8, [4, 2, 5], {"highway": "footway", "footway": "crossing"})]
    L, _, _ = read_map(write_osm(tmp_path, nodes, ways), origin=L2_ORIGIN)
    assert [c.id for c in L.crosswalks] == ["crossingway8"]
    # a crossing node alone still gives its crosswalk
    L, _, _ = read_map(write_osm(tmp_path, nodes[:3], ways[:1], name="n.osm"), origin=L2_ORIGIN)
    assert [c.id for c in L.crosswalks] == ["crossing2"]


def lane_z_vs_ele(L, ele_at):
    """Largest |z - ele_at(x)| over the lanes' points (x: the way runs along +x)."""
    return max(float(np.abs(ln.points[:, 2] - ele_at(ln.points[:, 0])).max()) for ln in L.lanes)


def test_osm_ele_climbing_road_gives_rising_lanes(tmp_path):
    # 600 -> 710 m over 300 m; node 3 has no ele (interpolated from its neighbours)
    nodes = [(1, 0, 0, {"ele": "600"}), (2, 100, 0, {"ele": "650"}),
             (3, 150, 0, {"highway": "crossing"}), (4, 300, 0, {"ele": "710 m"})]
    ways = [(7, [1, 2, 3, 4], {"highway": "residential", "sidewalk": "both"})]
    L, _, msgs = read_map(write_osm(tmp_path, nodes, ways), origin=L2_ORIGIN, strict=True)
    assert not [x for x in msgs if "ele" in x], msgs
    known = np.array([0, 100, 300]), np.array([600, 650, 710])
    ele_at = lambda x: np.interp(x, *known)                       # noqa: E731
    assert lane_z_vs_ele(L, ele_at) < 0.01
    zs = np.concatenate([ln.points[:, 2] for ln in L.lanes])
    assert zs.max() - zs.min() == pytest.approx(110, abs=0.01)
    # the road surface, its edges, sidewalks and the crosswalk lie on the same slope
    for f in (*L.road_areas, *L.sidewalks, *L.crosswalks):
        assert np.abs(f.polygon[:, 2] - ele_at(f.polygon[:, 0])).max() < 0.01, f.id
    for f in L.road_edges:
        assert np.abs(f.points[:, 2] - ele_at(f.points[:, 0])).max() < 0.01, f.id
    assert [c.id for c in L.crosswalks] == ["crossing3"]
    assert L.crosswalks[0].polygon[:, 2].mean() == pytest.approx(665, abs=0.01)   # 650 + 50/200 * 60


def test_osm_ele_junction_and_a_way_without_ele(tmp_path):
    # way 8 has no ele at all: it takes the height where it meets way 7; connectors join
    # their lanes' ends without a step
    nodes = [(1, -50, 0, {"ele": "600"}), (2, 0, 0, {}), (3, 50, 0, {"ele": "710"}),
             (4, 0, 60, {}), (5, 500, 500, {"ele": "3"}), (6, 540, 500, {})]
    ways = [(7, [1, 2, 3], {"highway": "residential"}), (8, [2, 4], {"highway": "residential"}),
            (9, [5, 6], {"natural": "tree_row"})]
    L, _, _ = read_map(write_osm(tmp_path, nodes, ways), origin=L2_ORIGIN)
    by_id = {ln.id: ln for ln in L.lanes}
    for ln in L.lanes:
        if ln.road_id == "w8":
            assert np.allclose(ln.points[:, 2], 655.0, atol=0.01)
        for s in ln.successors:
            assert by_id[s].points[0, 2] == pytest.approx(ln.points[-1, 2], abs=1e-6)
    w7 = SimpleNamespace(lanes=[ln for ln in L.lanes if ln.road_id == "w7"])
    assert lane_z_vs_ele(w7, lambda x: np.interp(x, [-50, 50], [600, 710])) < 0.01
    # a tree row stands on its own way (node 6 holds node 5's height)
    rows = [t for t in L.trees if t.id.startswith("treerow9")]
    assert len(rows) == 6 and all(t.position[2] == pytest.approx(3.0) for t in rows)


def test_osm_without_ele_stays_exactly_flat(tmp_path):
    nodes = [(1, -50, 0, {}), (2, 0, 0, {"highway": "crossing"}), (3, 50, 0, {}),
             (4, 0, 60, {}), (10, 20, 20, {}), (11, 40, 20, {}), (12, 40, 40, {}), (13, 20, 40, {})]
    ways = [(7, [1, 2, 3], {"highway": "residential", "sidewalk": "both"}),
            (8, [2, 4], {"highway": "residential"}),
            (9, [10, 11, 12, 13, 10], {"building": "yes"})]
    L, _, msgs = read_map(write_osm(tmp_path, nodes, ways), origin=L2_ORIGIN)
    assert not [x for x in msgs if "ele" in x], msgs
    for f in L.features():
        for a in ("points", "polygon", "footprint", "position", "center"):
            v = getattr(f, a, None)
            if v is not None:
                assert np.all(np.asarray(v)[..., 2] == 0.0), f.id


@pytest.mark.parametrize("bad", ["abc", "NaN", "1e30", "12 ft", "inf"])
def test_osm_malformed_ele_warns_once_and_is_ignored(tmp_path, bad):
    nodes = [(1, -50, 0, {"ele": "600"}), (2, 0, 0, {"ele": bad}), (3, 50, 0, {"ele": "710"})]
    p = write_osm(tmp_path, nodes, [(7, [1, 2, 3], {"highway": "residential"})])
    L, _, msgs = read_map(p, origin=L2_ORIGIN)
    w = [x for x in msgs if "ele" in x]
    assert len(w) == 1 and "node 2: ele" in w[0] and "ignored" in w[0], msgs
    assert lane_z_vs_ele(L, lambda x: np.interp(x, [-50, 50], [600, 710])) < 0.01
    from lsd3d_usd.errors import InputError
    with pytest.raises(InputError, match="node 2: ele"):
        read_map(p, origin=L2_ORIGIN, strict=True)


def test_osm_ele_parse():
    from lsd3d_usd.layout.osm_heights import parse_ele
    assert parse_ele("12") == 12 and parse_ele(" -3.5 ") == -3.5 and parse_ele("12 m") == 12
    assert parse_ele("710m") == 710
    for bad in ("12 ft", "abc", "nan", "NaN", "1e30", "", "12,5", "inf"):
        assert parse_ele(bad) is None, bad

