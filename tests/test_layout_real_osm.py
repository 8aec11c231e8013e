"""OpenStreetMap read whole: clipped to <bounds> by default (--no-clip, --bbox), signals,
signs, lamps, barriers and crossings as layout features and proxy geometry, bad ways
warned by id and handled by the documented rule."""
import importlib.util
import re
import subprocess
import sys

import numpy as np
import pytest
from shapely.geometry import Polygon

from conftest import ROOT
from lsd3d_usd.errors import InputError
from lsd3d_usd.layout import importers
from lsd3d_usd.layout.importers import ImportOptions, MapWarning
from lsd3d_usd.proxy.chunks import ProxyParams

_spec = importlib.util.spec_from_file_location("make_real_maps", ROOT / "samples/maps/make_real_maps.py")
maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(maps)


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    return maps.osm_bounds_city(tmp_path_factory.mktemp("osm") / "city.osm")


def _read(path, **kw):
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MapWarning)     # the bad ways (tested below)
        return importers.read_map(path, ImportOptions(**kw))[0]


@pytest.fixture(scope="module")
def clipped(city):
    return _read(city)


def test_default_clips_to_the_file_bounds(clipped):
    L = clipped
    (x0, y0), (x1, y1) = L.extent
    assert np.allclose([x0, y0, x1, y1], [-100, -100, 100, 100], atol=1.0)
    margin = ProxyParams().margin
    (bx0, by0), (bx1, by1) = L.bounds()
    assert bx0 >= x0 - margin and by0 >= y0 - margin and bx1 <= x1 + margin and by1 <= y1 + margin
    for f in L.features():
        c = f.coords()
        if f.FEATURE_TYPE == "LaneCenter":
            continue   # a lane's centre ends at the box; its width may reach past it
        assert c[:, 0].min() >= x0 - 1e-6 and c[:, 0].max() <= x1 + 1e-6, f.id
        assert c[:, 1].min() >= y0 - 1e-6 and c[:, 1].max() <= y1 + 1e-6, f.id
    # the building across the bounds corner is cut at the box, not kept whole or dropped
    cut = next(b for b in L.buildings if b.id == "b121")
    assert np.isclose(Polygon(cut.footprint[:, :2]).area, (x1 - 80) * (y1 - 80), rtol=0.02)
    # no road edge runs along the cut (no curb across a road that continues)
    for e in L.road_edges:
        p = e.points[:, :2]
        on = [(np.abs(p[k] - v) < 1e-6).all() for k in (slice(None),) for v in ()]
        assert not any(np.allclose(p[:, 0], v) or np.allclose(p[:, 1], v) for v in (x0, x1, y0, y1)
                       if len(p) == 2), e.id
    src = L.metadata["source"]
    assert src["clip"]["from"] == "file bounds" and "bbox" not in src
    assert re.search(r"clipped to the file's <bounds>, 20[01] m x 20[01] m", importers.reach_line(L))


def test_no_clip_keeps_whole_ways_and_bbox_still_cuts(city):
    whole = _read(city, clip=False)
    (x0, _), (x1, _) = whole.bounds()
    assert x1 - x0 > 1300 and whole.extent is None
    assert "not clipped" in importers.reach_line(whole)
    lat0, lon0 = maps._ll(maps.CITY, -50, -50)
    lat1, lon1 = maps._ll(maps.CITY, 50, 50)
    part = _read(city, bbox=(lon0, lat0, lon1, lat1))
    (bx0, by0), (bx1, by1) = part.bounds()
    assert bx0 > -62 and bx1 < 62 and by0 > -62 and by1 < 62
    assert part.metadata["source"]["clip"]["from"] == "bbox"
    touching = _read(city, bbox=(lon0, lat0, lon1, lat1), clip=False)
    assert touching.bounds()[1][0] > 600      # the ways through the area, whole


def test_signals_signs_lamps_barriers_crossings(clipped):
    L = clipped
    lights = {t.id: t for t in L.traffic_lights}
    at_junction = [t for k, t in lights.items() if k.startswith("signals3_")]
    assert len(at_junction) == 4                   # one per road entering the junction
    for t in at_junction:
        lane = L.lane_by_id(t.lane_ids[0])
        end = lane.points[-1, :2]
        assert np.hypot(*end) < 15 and np.hypot(*(t.position[:2] - end)) < 8
        u = lane.points[-1, :2] - lane.points[-2, :2]
        facing = np.array([np.cos(t.heading), np.sin(t.heading)])
        assert np.dot(facing, u) < -0.99 * np.hypot(*u)   # faces the approaching traffic
    (mid,) = [t for k, t in lights.items() if k.startswith("signals5_")]
    assert all(L.lane_by_id(i).points[-1, 0] > L.lane_by_id(i).points[0, 0] for i in mid.lane_ids)
    assert mid.position[1] < 0                      # beside the eastbound lane (right side)
    (yld,) = L.traffic_signs
    assert yld.kind == "yield" and all(L.lane_by_id(i).points[-1, 1] > L.lane_by_id(i).points[0, 1]
                                       for i in yld.lane_ids)     # the northbound approach
    assert sorted(p.kind for p in L.poles) == ["bollard", "street_lamp", "street_lamp"]
    assert sorted(b.kind for b in L.barriers) == ["fence", "guard_rail", "wall"]
    assert next(b for b in L.barriers if b.kind == "wall").height == 2.5
    assert len(L.trees) == 4 and len(L.crosswalks) == 1


def test_bad_ways_are_warned_by_id(city):
    with pytest.warns(MapWarning) as rec:
        importers.read_map(city, ImportOptions())
    msgs = [str(w.message) for w in rec]
    assert any("way 131" in x and "one position" in x for x in msgs)
    assert any("way 130" in x for x in msgs)
    with pytest.raises(InputError, match=r"way 13[01]"):
        importers.read_map(city, ImportOptions(strict=True))


def test_spike_in_a_way_is_repaired(tmp_path):
    o = maps.CITY
    pts = [(0, 0), (50, 0), (80, 0), (60, 0.5), (120, 0)]   # node 4 turns back: a spike
    nodes = "\n".join(f'  <node id="{k + 1}" version="1" lat="{maps._ll(o, x, y)[0]:.9f}" '
                      f'lon="{maps._ll(o, x, y)[1]:.9f}"/>' for k, (x, y) in enumerate(pts))
    refs = "".join(f'<nd ref="{k + 1}"/>' for k in range(len(pts)))
    p = tmp_path / "spike.osm"
    p.write_text(f'<?xml version="1.0"?>\n<osm version="0.6">\n{nodes}\n  <way id="7" version="1">'
                 f'{refs}<tag k="highway" v="residential"/></way>\n</osm>\n')
    with pytest.warns(MapWarning, match=r"way 7: turns back on itself at node 3"):
        L = importers.read_map(p, ImportOptions(origin=o))[0]
    for ln in L.lanes:
        d = np.diff(ln.points[:, :2], axis=0)
        assert (d[:, 0] * np.sign(d[0, 0]) > 0).all()      # runs one way, no fold


def test_osm_signals_are_proxy_geometry(clipped):
    from lsd3d_usd.proxy import build_proxy, check_part
    parts = [p for ps in build_proxy(clipped).values() for p in ps]
    for p in parts:
        check_part(p)
    classes = {}
    for p in parts:
        classes.setdefault(p.part_id.split("/")[0], set()).add(p.cls)
    assert classes["signals3_0"] == {"pole", "traffic_light"}
    assert classes["giveway8_0"] == {"pole", "sign"}
    assert classes["barrier111"] == {"building"} and classes["barrier110"] == {"pole"}
    # OSM does not list its lights completely; none derived next to the mapped ones
    assert not any(k.startswith("tl_") for k in classes)


def test_cli_prints_one_reach_line(city, tmp_path):
    out = subprocess.run([sys.executable, "-m", "lsd3d_usd.cli", "layout", "import", str(city),
                          "-o", str(tmp_path / "c.usda")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    lines = [x for x in out.stdout.splitlines() if x.startswith("layout reaches")]
    assert len(lines) == 1 and "clipped to the file's <bounds>" in lines[0]
    out = subprocess.run([sys.executable, "-m", "lsd3d_usd.cli", "layout", "import", str(city),
                          "-o", str(tmp_path / "w.usda"), "--no-clip"], capture_output=True, text=True)
    assert out.returncode == 0 and "not clipped (--no-clip)" in out.stdout
