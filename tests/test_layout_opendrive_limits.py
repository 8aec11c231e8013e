"""OpenDRIVE import under hostile sizes (issue 17, item 5), superelevation (item 10) and the
one-line errors of `layout import`."""
import os
import warnings

import numpy as np
import pytest

from lsd3d_usd import limits
from lsd3d_usd.cli import main
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import opendrive as od

LANES = '<lane id="-1" type="driving"><width sOffset="0" a="{w}" b="0" c="0" d="0"/></lane>'


def road(rid="1", length=100, geometry="<line/>", geom_length=None, width=3.0, extra="",
         lanes_extra="", section_s=0):
    g = length if geom_length is None else geom_length
    return f"""
  <road id="{rid}" length="{length}" junction="-1">
    <planView><geometry s="0" x="0" y="{10 * int(rid) if str(rid).isdigit() else 0}" hdg="0" length="{g}">{geometry}</geometry></planView>
    {extra}
    <lanes>{lanes_extra}
      <laneSection s="{section_s}">
        <center><lane id="0" type="none"/></center>
        <right>{LANES.format(w=width)}</right>
      </laneSection>
    </lanes>
  </road>"""


def xodr(tmp_path, *roads, name="m.xodr"):
    p = tmp_path / name
    p.write_text('<?xml version="1.0"?>\n<OpenDRIVE><header revMajor="1" revMinor="6" name="t"/>'
                 + "".join(roads) + "\n</OpenDRIVE>")
    return p


def read(path, **kw):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        layout = od.read_opendrive(path, **kw)
    return layout, [str(x.message) for x in w]




@pytest.mark.parametrize("bad,match", [
    (road("2", length="1e8"), "length 100000000 m exceeds the limit of 100000 m"),
    (road("2", length="1e12"), "length 1000000000000 m exceeds the limit"),
    (road("2", length=50, geometry='<poly3 a="0" b="0" c="0" d="0"/>', geom_length="1e9"),
     "geometry at s=0.0: length 1000000000 m exceeds the limit"),
    (road("2", width="1e7"), "lane -1: width 10000000 m exceeds the limit of 100 m"),
    (road("2", lanes_extra='<laneOffset s="0" a="5000" b="0" c="0" d="0"/>'),
     "lateral offset of a lane boundary 5000 m exceeds the limit of 1000 m"),
    (road("2", section_s="-1e12"), "laneSection s=-1000000000000.0 lies outside the road"),
])
def test_oversized_road_is_skipped_naming_it(tmp_path, bad, match):
    path = xodr(tmp_path, road("1"), bad)
    layout, msgs = read(path)
    assert [ln.road_id for ln in layout.lanes] == ["1"]
    assert any("road 2" in m and match in m for m in msgs), msgs
    with pytest.raises(InputError, match="road 2"):
        od.read_opendrive(path, strict=True)


def test_tiny_file_with_1e8_road_is_one_line_and_writes_nothing(tmp_path, capsys, cli_error):
    path = xodr(tmp_path, road("7", length="1e8"))
    assert path.stat().st_size < 600
    out = tmp_path / "L.usda"
    line = cli_error(["layout", "import", str(path), "-o", str(out)])
    assert "no road could be imported (all 1 roads were skipped; first road 7: length 100000000 m " \
           "exceeds the limit of 100000 m)" in line
    assert not out.exists() and sorted(os.listdir(tmp_path)) == ["m.xodr"]


def test_strict_flag_refuses_the_first_bad_road(tmp_path, capsys, cli_error):
    path = xodr(tmp_path, road("1"), road("2", width="1e7"))
    line = cli_error(["layout", "import", str(path), "-o", str(tmp_path / "L.usda"),
                                      "--strict"])
    assert "road 2: lane -1: width 10000000 m exceeds the limit of 100 m" in line
    assert main(["layout", "import", str(path), "-o", str(tmp_path / "L.usda")]) == 0


def test_point_budget_bounds_a_curly_road(tmp_path):
    # a 90 km clothoid curling up to a 2 m radius needs millions of points at 0.1 mm
    spiral = road("3", length=90000, geometry='<spiral curvStart="-0.5" curvEnd="0.5"/>')
    layout, msgs = read(xodr(tmp_path, road("1"), spiral), tolerance=1e-4)
    assert [ln.road_id for ln in layout.lanes] == ["1"]
    assert any("road 3" in m and "polyline points" in m and "exceeds the limit of "
               f"{int(limits.ROAD_POINTS.value)}" in m for m in msgs), msgs


def test_road_larger_than_a_layout_is_skipped(tmp_path):
    # a 100 m cubic that swings out by 1300 km
    wild = road("2", length=100, geometry='<paramPoly3 aU="0" bU="100" cU="0" dU="0" aV="0" '
                                          'bV="0" cV="9e6" dV="-9e6" pRange="normalized"/>')
    layout, msgs = read(xodr(tmp_path, road("1"), wild))
    assert [ln.road_id for ln in layout.lanes] == ["1"]
    assert any("road 2: size of the road's geometry" in m and "exceeds the limit of 50000 m" in m
               for m in msgs), msgs


def test_total_road_length_is_bounded(tmp_path):
    roads = [road(str(k), length=99_000) for k in range(1, 103)]
    with pytest.raises(InputError, match="total length of its 102 roads 10098000 m exceeds the limit"):
        od.read_opendrive(xodr(tmp_path, *roads))


def test_far_roads_exceed_the_layout_size(tmp_path):
    far = road("2").replace('x="0"', 'x="80000"')
    with pytest.raises(InputError, match="features span .* more than the limit of 50000 m"):
        od.read_opendrive(xodr(tmp_path, road("1"), far))


def test_non_utf8_bytes_are_one_line(tmp_path, capsys, cli_error):
    p = tmp_path / "bad.xodr"
    p.write_bytes(b'<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header name="\xff\xfe"/>'
                  + road("1").encode() + b"</OpenDRIVE>")
    line = cli_error(["layout", "import", str(p), "-o", str(tmp_path / "L.usda")])
    assert "bad.xodr" in line and "encoding" in line
    assert not (tmp_path / "L.usda").exists()


@pytest.mark.parametrize("target", ["DIR/", "FILE/sub/a.usda", "DIR"])
def test_bad_output_paths_are_one_line_before_reading(tmp_path, capsys, target, cli_error):
    (tmp_path / "DIR").mkdir()
    (tmp_path / "FILE").write_text("x")
    src = xodr(tmp_path, road("1"))
    out = str(tmp_path) + "/" + target
    line = cli_error(["layout", "import", str(src), "-o", out])
    assert ("is a folder" in line) if target.startswith("DIR") else ("is a file, not a folder" in line)
    assert sorted(os.listdir(tmp_path)) == ["DIR", "FILE", "m.xodr"] and os.listdir(tmp_path / "DIR") == []
    line = cli_error(["layout", "generate", "--extent", "100x100", "-o", out])


def test_superelevation_banks_the_cross_section(tmp_path):
    bank = np.deg2rad(60)
    sup = f'<lateralProfile><superelevation s="0" a="{bank}" b="0" c="0" d="0"/></lateralProfile>'
    layout, msgs = read(xodr(tmp_path, road("1", length=50, width=4.0, extra=sup)))
    assert not [m for m in msgs if "superelevation" in m]
    lane = layout.lane_by_id("1_0_-1")
    # lane centre at t = -2 along the banked section: 1 m to the side, 1.73 m down
    np.testing.assert_allclose(lane.points[:, 1], 10 - 2 * np.cos(bank), atol=1e-9)
    np.testing.assert_allclose(lane.points[:, 2], -2 * np.sin(bank), atol=1e-9)
    np.testing.assert_allclose(lane.widths, 4.0)           # width along the surface
    edge = [e for e in layout.road_edges if e.id == "edge_1_0_r"][0]
    np.testing.assert_allclose(edge.points[:, 2], -4 * np.sin(bank), atol=1e-9)


def test_lateral_shape_is_warned_once_per_road(tmp_path):
    shape = ('<lateralProfile><shape s="0" t="0" a="0" b="0.1" c="0" d="0"/>'
             '<shape s="10" t="0" a="0" b="0.1" c="0" d="0"/></lateralProfile>')
    layout, msgs = read(xodr(tmp_path, road("1", extra=shape), road("2", extra=shape)))
    assert len(layout.lanes) == 2
    notes = [m for m in msgs if "<shape> ignored" in m]
    assert len(notes) == 2 and any("road 1" in m for m in notes) and any("road 2" in m for m in notes)


def test_nearly_arc_spiral_is_linear_work(tmp_path):
    # curvature changing by 1e-9 over 20 km: the quadrature fallback; its work must not be
    # samples x length (that was minutes)
    sp = road("1", length=20000, geometry='<spiral curvStart="0.001" curvEnd="0.001000001"/>')
    layout, _ = read(xodr(tmp_path, sp))
    p = layout.lanes[0].points
    r = 1 / 0.001
    # close to a circle of radius ~1 km through the origin (lane centre 1.5 m inside)
    d = np.linalg.norm(p[:, :2] - [0, 10 + r], axis=1)
    assert np.all(np.abs(d - (r + 1.5)) < 0.5)


def test_road_far_from_the_origin_is_skipped(tmp_path):
    # a 100 m road at y = 1e300: small, but float32 points would overflow to inf
    far = road("2").replace('y="20"', 'y="1e300"')
    layout, msgs = read(xodr(tmp_path, road("1"), far))
    assert [ln.road_id for ln in layout.lanes] == ["1"]
    assert any("road 2: a coordinate at 1e+300 m exceeds the limit of 10000000 m" in m for m in msgs), msgs
