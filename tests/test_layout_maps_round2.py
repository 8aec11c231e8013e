"""Real maps, second round (issue 61): each test builds its own small map and checks the
values its format defines."""
import warnings

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
