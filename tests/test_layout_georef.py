"""geoReference: parsed (pyproj), kept in the layout, written back by `layout export`; two
layouts of one place from two formats land in one frame."""
import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import georef, importers, opendrive_export, usdio
from lsd3d_usd.layout.opendrive import OpenDriveWarning, read_opendrive

_spec = importlib.util.spec_from_file_location("make_real_maps", ROOT / "samples/maps/make_real_maps.py")
maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(maps)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("geo")
    xodr = maps.opendrive_town(d / "town.xodr")
    osm = maps.osm_town_of_opendrive(d / "town.osm")
    return d, read_opendrive(xodr), importers.read_map(osm)[0]


def test_local_tangent_is_lanelet2s_local_cartesian_projection():
    from lanelet2.core import GPSPoint
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector
    lat0, lon0 = 52.52, 13.405
    ref = georef.local_tangent(lat0, lon0)
    proj = LocalCartesianProjector(Origin(lat0, lon0))
    rng = np.random.default_rng(2)
    lat, lon = lat0 + rng.uniform(-0.04, 0.04, 50), lon0 + rng.uniform(-0.06, 0.06, 50)
    ours = ref.from_lonlat(lon, lat)
    theirs = np.array([[q.x, q.y] for q in (proj.forward(GPSPoint(a, o, 0.0)) for a, o in zip(lat, lon))])
    assert np.abs(ours - theirs).max() < 1e-6 and np.abs(theirs).max() > 3000
    lo, la = ref.to_lonlat(ours)
    assert np.abs(lo - lon).max() < 1e-10 and np.abs(la - lat).max() < 1e-10


def test_offset_and_rotation_of_the_header_are_applied():
    ref = georef.GeoReference(maps.TOWN_PROJ, (691500.0, 5334700.0, 0.0, 0.3))
    from pyproj import Transformer
    tr = Transformer.from_crs(maps.TOWN_PROJ, "EPSG:4326", always_xy=True)
    p = np.array([[10.0, -4.0]])
    c, s = np.cos(0.3), np.sin(0.3)
    exp = tr.transform(691500.0 + c * 10 + s * 4, 5334700.0 + s * 10 - c * 4)
    got = ref.to_lonlat(p)
    assert np.allclose([got[0][0], got[1][0]], exp, atol=1e-11)
    assert np.allclose(ref.from_lonlat(*got), p, atol=1e-6)


def test_formats_carry_their_frames(pair):
    _, xo, os_ = pair
    a, b = georef.of_layout(xo), georef.of_layout(os_)
    assert a.proj == maps.TOWN_PROJ and a.offset == maps.TOWN_OFFSET
    assert b.proj.startswith("+proj=ortho") and "osm origin" in b.source


def test_two_formats_of_one_place_land_in_one_frame(pair):
    _, xo, os_ = pair
    ra, rb = georef.of_layout(xo), georef.of_layout(os_)
    off = georef.frame_offset(ra, rb, at=(0.0, 0.0), radius=100.0)
    # the OSM frame's origin is the centre of its bounds, 20 m south of the OpenDRIVE
    # street's frame origin; UTM zone 32 is turned by the meridian convergence here
    assert abs(off.dx) < 0.01 and abs(off.dy + 20.0) < 0.01
    assert abs(off.rotation_deg - 1.9176) < 1e-3 and abs(off.scale - 1.0000506) < 1e-6
    assert off.residual_m < 1e-4
    moved = georef.reproject(os_, ra)
    assert georef.of_layout(moved) == ra
    # each OSM lane lies on an OpenDRIVE lane (same offsets from the same reference line)
    for ln in moved.lanes:
        if ln.is_junction:
            continue
        d = min(np.abs(ln.points[:, 1] - o.points[:, 1].mean()).max() for o in xo.lanes)
        assert d < 0.01, ln.id
    ob = next(b for b in moved.buildings)
    xb = next(b for b in xo.buildings if b.id == "obj_1_b1")
    assert np.hypot(*(ob.footprint[:, :2].mean(0) - xb.footprint[:, :2].mean(0))) < 0.01
    light = moved.traffic_lights[0] if moved.traffic_lights else None
    assert light is not None


def test_export_writes_the_georeference_and_it_reads_back(pair, tmp_path):
    _, xo, os_ = pair
    for layout, name in ((xo, "x"), (os_, "o")):
        out = tmp_path / f"{name}.xodr"
        opendrive_export.write_opendrive(layout, out)
        assert opendrive_export.validate(out) == []
        back = read_opendrive(out)
        ra, rb = georef.of_layout(layout), georef.of_layout(back)
        assert rb.proj == ra.proj and np.allclose(rb.offset, ra.offset)
        p = layout.lanes[0].points[:, :2]
        assert np.abs(np.subtract(ra.to_lonlat(p), rb.to_lonlat(p))).max() < 1e-12


def test_bad_georeference_warns_and_stays_text(tmp_path):
    p = maps.opendrive_town(tmp_path / "t.xodr")
    p.write_text(p.read_text().replace(maps.TOWN_PROJ, "+proj=nonsense +zone=99"))
    with pytest.warns(OpenDriveWarning, match="not a coordinate system pyproj reads"):
        L = read_opendrive(p)
    assert georef.of_layout(L) is None
    assert L.metadata["source"]["geoReference"] == "+proj=nonsense +zone=99"
    with pytest.raises(InputError, match="no geoReference"):
        georef.reproject(L, georef.local_tangent(48.0, 11.0))


def test_cli_import_into_a_frame_and_report_offsets(pair, tmp_path):
    d, xo, _ = pair
    usdio.write_layout(xo, tmp_path / "x.usda")
    run = lambda *a: subprocess.run([sys.executable, "-m", "lsd3d_usd.cli", "layout", *a],  # noqa: E731
                                    capture_output=True, text=True)
    r = run("import", str(d / "town.osm"), "-o", str(tmp_path / "o.usda"))
    assert r.returncode == 0, r.stderr
    r = run("georef", str(tmp_path / "x.usda"), str(tmp_path / "o.usda"), "--json")
    assert r.returncode == 0, r.stderr
    off = json.loads(r.stdout)["offset"]
    assert abs(off["dy"] + 20) < 0.01 and abs(off["rotation_deg"] - 1.9176) < 1e-3
    r = run("import", str(d / "town.osm"), "-o", str(tmp_path / "f.usda"), "--frame", str(tmp_path / "x.usda"))
    assert r.returncode == 0, r.stderr
    r = run("georef", str(tmp_path / "x.usda"), str(tmp_path / "f.usda"), "--json")
    off = json.loads(r.stdout)["offset"]
    assert abs(off["dx"]) < 1e-3 and abs(off["dy"]) < 1e-3 and abs(off["rotation_deg"]) < 1e-6
    r = run("import", str(d / "town.osm"), "-o", str(tmp_path / "g.usda"), "--frame",
            str(ROOT / "samples/layouts/hand_crossing.usda"))
    assert r.returncode != 0 and "no geoReference" in r.stderr
