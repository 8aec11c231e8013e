"""OpenDRIVE import against closed forms, adaptive sampling tolerance, bad input."""
import time
import warnings

import numpy as np
import pytest
from scipy.integrate import quad

from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import opendrive as od

xodr = pytest.importorskip("scenariogeneration").xodr


def write_sg(tmp_path, roads, name="t.xodr"):
    odr = xodr.OpenDrive("test")
    for r in roads:
        odr.add_road(r)
    odr.adjust_roads_and_lanes()
    path = tmp_path / name
    odr.write_xml(str(path))
    return path


def seg_dist(p, a, b):
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
    return np.linalg.norm(p - a - t * ab)


def max_dev(poly, exact_fn, s_dense):
    """Max distance from dense exact points to the polyline (both directions matter: vertices are exact)."""
    pts = exact_fn(s_dense)
    d = []
    for p in pts:
        d.append(min(seg_dist(p, poly[k], poly[k + 1]) for k in range(len(poly) - 1)))
    return max(d)


def lane(layout, road, lane_id, section=0):
    return layout.lane_by_id(f"{road}_{section}_{lane_id}")


def test_straight_500m(tmp_path):
    p = write_sg(tmp_path, [xodr.create_road(xodr.Line(500), 0, left_lanes=1, right_lanes=2,
                                              lane_width=3.5)])
    L = od.read_opendrive(p)
    r1, r2, l1 = lane(L, 0, -1), lane(L, 0, -2), lane(L, 0, 1)
    assert np.allclose(r1.points[[0, -1], :2], [[0, -1.75], [500, -1.75]], atol=1e-9)
    assert np.allclose(r2.points[:, 1], -5.25) and np.allclose(r2.widths, 3.5)
    # left lane travels against s
    assert np.allclose(l1.points[[0, -1], :2], [[500, 1.75], [0, 1.75]], atol=1e-9)
    assert r1.direction == "forward" and r1.lane_type == "driving"
    assert abs(r1.length() - 500) < 1e-9


def test_arc_radius_100_within_2cm(tmp_path):
    p = write_sg(tmp_path, [xodr.create_road(xodr.Arc(0.01, angle=np.pi / 2), 0, left_lanes=1,
                                              right_lanes=1, lane_width=3.0)])
    L = od.read_opendrive(p)
    c = np.array([0.0, 100.0])
    r = lane(L, 0, -1)   # right lane: radius 100 + 1.5
    rad = np.linalg.norm(r.points[:, :2] - c, axis=1)
    assert np.allclose(rad, 101.5, atol=1e-9)
    # chord error of the polyline vs the exact circle
    ang = np.arctan2(r.points[:, 1] - c[1], r.points[:, 0] - c[0])
    dang = np.abs(np.diff(np.unwrap(ang)))
    sagitta = 101.5 * (1 - np.cos(dang / 2))
    assert sagitta.max() <= 0.02 and len(r.points) < 400
    assert np.allclose(r.points[-1, :2], [101.5, 100.0], atol=1e-6)


def test_clothoid_curvature_0_to_001_over_100m(tmp_path):
    p = write_sg(tmp_path, [xodr.create_road(xodr.Spiral(0.0, 0.01, length=100), 0,
                                              left_lanes=1, right_lanes=1, lane_width=3.0)])
    L = od.read_opendrive(p)
    lane_l = lane(L, 0, 1)       # travels against s: its last point is at s = 0
    k = 0.01 / 100

    def exact(s, t=1.5):
        s = np.atleast_1d(s)
        out = []
        for si in s:
            x = quad(lambda u: np.cos(k * u * u / 2), 0, si, epsabs=1e-13)[0]
            y = quad(lambda u: np.sin(k * u * u / 2), 0, si, epsabs=1e-13)[0]
            h = k * si * si / 2
            out.append([x - t * np.sin(h), y + t * np.cos(h)])
        return np.array(out)

    end = exact(100.0)[0]
    assert np.allclose(lane_l.points[0, :2], end, atol=1e-6)
    assert max_dev(lane_l.points[:, :2], exact, np.linspace(0, 100, 301)) <= 0.02


def test_lane_widths_polynomial_and_offset(tmp_path):
    path = tmp_path / "w.xodr"
    path.write_text(XODR_TEMPLATE.format(geometry='<line/>', length=100, extra="""
        <laneOffset s="0" a="0.5" b="0" c="0" d="0"/>""", right="""
        <lane id="-1" type="driving"><width sOffset="0" a="3.0" b="0.01" c="0" d="0"/>
          <roadMark sOffset="0" type="broken" color="white"/></lane>
        <lane id="-2" type="sidewalk"><width sOffset="0" a="2.0" b="0" c="0" d="0"/></lane>"""))
    L = od.read_opendrive(path)
    r = L.lane_by_id("1_0_-1")
    s = r.points[:, 0]
    assert np.allclose(r.widths, 3.0 + 0.01 * s, atol=1e-12)
    assert np.allclose(r.points[:, 1], 0.5 - (3.0 + 0.01 * s) / 2, atol=1e-12)
    assert len(L.sidewalks) == 1 and abs(L.sidewalks[0].area() - 200.0) < 1e-6
    assert any(rl.kind == "broken" for rl in L.road_lines)


def test_param_poly3_normalized_and_arclength(tmp_path):
    """v = 0.02 u^2 written both ways gives the same lane; lane stays 1.5 m off the parabola."""
    lanes = []
    for pr, bu, cv in (("normalized", 50.0, 0.02 * 50.0**2), ("arcLength", 1.0, 0.02)):
        path = tmp_path / f"pp_{pr}.xodr"
        geom = f'<paramPoly3 aU="0" bU="{bu}" cU="0" dU="0" aV="0" bV="0" cV="{cv}" dV="0" pRange="{pr}"/>'
        path.write_text(XODR_TEMPLATE.format(geometry=geom, length=50, extra="", right=RIGHT1))
        lanes.append(od.read_opendrive(path).lane_by_id("1_0_-1").points)
    assert lanes[0].shape == lanes[1].shape and np.allclose(lanes[0], lanes[1], atol=1e-9)
    u = np.linspace(-5, 60, 200001)
    parab = np.stack([u, 0.02 * u**2], axis=1)
    d = np.array([np.min(np.linalg.norm(parab - p[:2], axis=1)) for p in lanes[0]])
    assert np.allclose(d, 1.5, atol=1e-3)
    assert lanes[0][-1, 0] > 45 and lanes[0][-1, 1] < 0.02 * 50**2


def test_elevation_and_junction_links(tmp_path):
    r1 = xodr.create_road(xodr.Line(50), 1, left_lanes=1, right_lanes=1)
    r2 = xodr.create_road(xodr.Line(50), 2, left_lanes=1, right_lanes=1)
    r3 = xodr.create_road(xodr.Line(50), 3, left_lanes=1, right_lanes=1)
    jc = xodr.CommonJunctionCreator(100, "j")
    jc.add_incoming_road_circular_geometry(r1, 20, 0, "successor")
    jc.add_incoming_road_circular_geometry(r2, 20, np.pi / 2, "predecessor")
    jc.add_incoming_road_circular_geometry(r3, 20, np.pi, "predecessor")
    jc.add_connection(1, 2)
    jc.add_connection(1, 3)
    jc.add_connection(2, 3)
    odr = xodr.OpenDrive("j")
    for r in [r1, r2, r3]:
        odr.add_road(r)
    odr.add_junction_creator(jc)
    odr.adjust_roads_and_lanes()
    path = tmp_path / "j.xodr"
    odr.write_xml(str(path))
    L = od.read_opendrive(path)
    conn = [l for l in L.lanes if l.is_junction]
    assert conn and all(l.predecessors and l.successors for l in conn)
    for l in L.lanes:
        for s in l.successors:
            assert np.linalg.norm(L.lane_by_id(s).points[0] - l.points[-1]) < 0.01


def test_elevation_profile(tmp_path):
    path = tmp_path / "e.xodr"
    path.write_text(XODR_TEMPLATE.format(geometry="<line/>", length=100, right=RIGHT1,
                                         extra="").replace(
        "<lanes>", '<elevationProfile><elevation s="0" a="1" b="0.02" c="0" d="0"/></elevationProfile><lanes>'))
    pts = od.read_opendrive(path).lane_by_id("1_0_-1").points
    assert np.allclose(pts[:, 2], 1 + 0.02 * pts[:, 0])


XODR_TEMPLATE = """<?xml version="1.0"?>
<OpenDRIVE><header revMajor="1" revMinor="6" name="t"/>
  <road id="1" length="{length}" junction="-1">
    <planView><geometry s="0" x="0" y="0" hdg="0" length="{length}">{geometry}</geometry></planView>
    <lanes>{extra}
      <laneSection s="0">
        <center><lane id="0" type="none"><roadMark sOffset="0" type="solid solid" color="yellow"/></lane></center>
        <right>{right}</right>
      </laneSection>
    </lanes>
  </road>
</OpenDRIVE>"""
RIGHT1 = '<lane id="-1" type="driving"><width sOffset="0" a="3.0" b="0" c="0" d="0"/></lane>'


def test_bad_input(tmp_path):
    bad = tmp_path / "bad.xodr"
    bad.write_text("<OpenDRIVE><road id='1'")
    with pytest.raises(InputError, match="malformed XML"):
        od.read_opendrive(bad)
    other = tmp_path / "o.xodr"
    other.write_text("<svg/>")
    with pytest.raises(InputError, match="OpenDRIVE"):
        od.read_opendrive(other)
    with pytest.raises(InputError, match="no such file"):
        od.read_opendrive(tmp_path / "missing.xodr")
    # one bad road among good ones: warning naming it, the rest imports
    good = XODR_TEMPLATE.format(geometry="<line/>", length=10, extra="", right=RIGHT1)
    roads = good.split("<road", 1)[1].rsplit("</OpenDRIVE>", 1)[0]
    mixed = good.replace("</OpenDRIVE>", "")
    mixed += "<road" + roads.replace('id="1"', 'id="7"').replace("<line/>", "<clothoid/>")
    mixed += "<road" + roads.replace('id="1"', 'id="8"').replace('length="10">', 'length="-5">')
    mixed += '<road id="9" length="10"><lanes/></road></OpenDRIVE>'
    f = tmp_path / "mixed.xodr"
    f.write_text(mixed)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        L = od.read_opendrive(f)
    msgs = " ".join(str(x.message) for x in w)
    assert "road 7" in msgs and "clothoid" in msgs
    assert "road 8" in msgs and "negative length" in msgs
    assert "road 9" in msgs and "planView" in msgs
    assert [l.road_id for l in L.lanes] == ["1"]
    with pytest.raises(InputError, match="road 7"):
        od.read_opendrive(f, strict=True)


def test_entity_bomb_does_not_hang(tmp_path):
    bomb = '<?xml version="1.0"?>\n<!DOCTYPE lolz [<!ENTITY lol "lol">'
    for k in range(1, 10):
        bomb += f'<!ENTITY lol{k} "{("&lol%s;" % ("" if k == 1 else k - 1)) * 10}">'
    bomb += ']>\n<OpenDRIVE><header name="&lol9;"/></OpenDRIVE>'
    f = tmp_path / "bomb.xodr"
    f.write_text(bomb)
    t = time.perf_counter()
    with pytest.raises(InputError, match="malformed XML|no road"):
        od.read_opendrive(f)
    assert time.perf_counter() - t < 5


def test_an_object_the_layout_reader_would_refuse_is_refused_at_import(tmp_path, cli_error):
    """An outline of 100 500 corners imported, then refused by our own reader (its
    feature_points limit): the import now names the object and writes nothing."""
    ang = np.linspace(0, 2 * np.pi, 100_500, endpoint=False)
    corners = "".join(f'<cornerLocal u="{5 * np.cos(a):.6f}" v="{5 * np.sin(a):.6f}" z="0" '
                      'height="1"/>' for a in ang)
    road = ('<road id="7" length="100" junction="-1"><planView><geometry s="0" x="0" y="0" '
            'hdg="0" length="100"><line/></geometry></planView><lanes><laneSection s="0"><center>'
            '<lane id="0" type="none"/></center><right><lane id="-1" type="driving"><width '
            'sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></right></laneSection></lanes>'
            '<objects><object id="o1" type="building" s="50" t="-20" zOffset="0" hdg="0" '
            f'height="5"><outline>{corners}</outline></object></objects></road>')
    src = tmp_path / "m.xodr"
    src.write_text(f'<?xml version="1.0"?><OpenDRIVE><header/>{road}</OpenDRIVE>')
    cli_error(["layout", "import", src, "-o", tmp_path / "L.usda"], "obj_7_o1", "100500",
              "100000")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.xodr"]
