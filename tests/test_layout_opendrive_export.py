"""OpenDRIVE export: XSD validity, the importer's element rules, and the round trip export →
import within 2 cm of the original lane centres (README sample, generated 400 m layout,
imported Lanelet2 map)."""
import importlib.util
import warnings
from pathlib import Path

import numpy as np
import pytest
from lxml import etree

from lsd3d_usd.errors import InputError
from lsd3d_usd.geometry import polyline as P
from lsd3d_usd.layout import generator as G
from lsd3d_usd.layout import importers, opendrive
from lsd3d_usd.layout import model as m
from lsd3d_usd.layout import opendrive_export as X
from lsd3d_usd.layout import usdio

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("make_maps", ROOT / "samples/maps/make_maps.py")
make_maps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_maps)


def polyline_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Max distance of a's vertices to polyline b."""
    return float(P.distance_to_segments(a[:, :2], b[:-1, :2], b[1:, :2]).max())


def check_round_trip(L: m.Layout, path: Path) -> dict:
    """Export, validate, re-import; returns the measured numbers. Imports with half the export
    tolerance so that the importer's sampling and the fit add up to at most 2 cm."""
    rep = X.write_opendrive(L, path, tolerance=0.02)
    assert X.validate(path) == [], "not valid against the ASAM OpenDRIVE 1.7 XSD"
    check_element_rules(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")        # the importer skips nothing
        R = opendrive.read_opendrive(path, tolerance=0.01)
    worst = 0.0
    for ln in L.lanes:
        parts = [R.lane_by_id(f"{r}_0_-1") for r in rep.roads[ln.id]]
        got = np.concatenate([p.points for p in parts])
        want = ln.points if ln.direction != "backward" else ln.points[::-1]
        worst = max(worst, polyline_distance(want, got), polyline_distance(got, want))
        assert np.abs(parts[0].points[0] - want[0]).max() < 1e-6       # ends where it ended
        assert np.abs(parts[-1].points[-1] - want[-1]).max() < 1e-6
        assert np.allclose(np.interp(0.5, [0, 1], parts[0].widths[[0, -1]]),
                           np.interp(0.5, [0, 1], parts[0].widths[[0, -1]]))
        assert abs(parts[0].widths[0] - ln.widths[0 if ln.direction != "backward" else -1]) < 1e-9
        assert all(p.lane_type == ln.lane_type for p in parts)
        # links: the successors of the lane's last road are the first roads of its successors
        want_succ = {f"{rep.roads[s][0]}_0_-1" for s in ln.successors}
        assert set(parts[-1].successors) == want_succ, ln.id
        want_pred = {f"{rep.roads[p][-1]}_0_-1" for p in ln.predecessors}
        assert set(parts[0].predecessors) == want_pred, ln.id
    assert worst <= 0.02, worst
    assert rep.max_curve_deviation <= 0.02 and rep.max_vertex_deviation <= 0.01
    return {"max_error": worst, "report": rep}


def check_element_rules(path: Path) -> None:
    """The rules our importer relies on: unique ids, links to existing roads/junctions with
    contact points, one right lane with width records, junction connections between existing
    roads, connecting roads inside their junction."""
    root = etree.parse(str(path)).getroot()
    roads = {r.get("id"): r for r in root.iter("road")}
    juncs = {j.get("id"): j for j in root.iter("junction")}
    assert len(roads) == len(list(root.iter("road"))) and not set(roads) & set(juncs)
    for rid, r in roads.items():
        total = sum(float(g.get("length")) for g in r.find("planView"))
        assert abs(total - float(r.get("length"))) < 1e-6 and total > 0
        link = r.find("link")
        for el in (link if link is not None else []):
            target = roads if el.get("elementType") == "road" else juncs
            assert el.get("elementId") in target, (rid, el.attrib)
            if el.get("elementType") == "road":
                assert el.get("contactPoint") in ("start", "end")
        lanes = r.find("lanes/laneSection/right")
        assert [ln.get("id") for ln in lanes] == ["-1"] and lanes[0].findall("width")
    for jid, j in juncs.items():
        for c in j.iter("connection"):
            assert c.get("incomingRoad") in roads and c.get("connectingRoad") in roads
            assert c.get("contactPoint") in ("start", "end")
            assert roads[c.get("connectingRoad")].get("junction") == jid


def test_round_trip_readme_sample(tmp_path):
    L = usdio.read_layout(ROOT / "samples/layouts/hand_crossing.usda")
    out = check_round_trip(L, tmp_path / "hand.xodr")
    assert out["max_error"] < 1e-6     # straight lanes: exact lines
    assert out["report"].junctions == 2 and out["report"].geometries == {"line": 16}


def test_round_trip_generated_400m_with_roundabout(tmp_path):
    L = G.generate(42, (400.0, 400.0), "urban")
    assert any("ring" in ln.id for ln in L.lanes)
    out = check_round_trip(L, tmp_path / "gen.xodr")
    rep = out["report"]
    assert set(rep.geometries) == {"line", "arc", "paramPoly3"}
    # ring lanes that are connecting roads at both ends are cut in two roads
    assert any(len(v) == 2 for v in rep.roads.values())
    assert rep.outside_connections == 0


def test_round_trip_imported_lanelet2(tmp_path):
    make_maps.lanelet2_crossing(tmp_path / "ll.osm")
    L, _ = importers.read_map(tmp_path / "ll.osm")
    check_round_trip(L, tmp_path / "ll.xodr")


def test_links_without_a_connecting_road_are_counted(tmp_path):
    """A → {B, C} and D → {B}: B has two predecessors and A two successors, so the link A → B
    has no connecting road of its own."""
    pts = lambda *p: np.array([[x, y, 0.0] for x, y in p])
    L = m.Layout(lanes=[
        m.LaneCenter("A", points=pts((0, 0), (10, 0)), successors=["B", "C"]),
        m.LaneCenter("D", points=pts((10, -10), (10, 0)), successors=["B"]),
        m.LaneCenter("B", points=pts((10, 0), (20, 0)), predecessors=["A", "D"]),
        m.LaneCenter("C", points=pts((10, 0), (10, 10)), predecessors=["A"])])
    root, rep = X.layout_to_opendrive(L)
    assert rep.outside_connections == 1 and rep.junctions == 1
    path = tmp_path / "x.xodr"
    X.write_opendrive(L, path)
    R = opendrive.read_opendrive(path, tolerance=0.01)
    succ = {L.lanes[k].id: set(R.lane_by_id(f"{rep.roads[L.lanes[k].id][-1]}_0_-1").successors)
            for k in range(4)}
    assert succ["A"] == {f"{rep.roads['B'][0]}_0_-1", f"{rep.roads['C'][0]}_0_-1"}
    assert succ["D"] == {f"{rep.roads['B'][0]}_0_-1"}


def test_backward_lanes_elevation_and_varying_width(tmp_path):
    z = np.linspace(0, 3, 9)
    p = np.stack([np.linspace(0, 80, 9), np.zeros(9), z], axis=1)
    L = m.Layout(lanes=[m.LaneCenter("up", points=p, widths=np.linspace(3.0, 4.0, 9)),
                        m.LaneCenter("back", points=p + [0, 5, 0], direction="backward", lane_type="bus")])
    path = tmp_path / "e.xodr"
    rep = X.write_opendrive(L, path)
    R = opendrive.read_opendrive(path, tolerance=0.01)
    up = R.lane_by_id(f"{rep.roads['up'][0]}_0_-1")
    assert np.allclose(np.interp(up.points[:, 0], p[:, 0], z), up.points[:, 2], atol=1e-9)
    assert np.allclose(np.interp(up.points[:, 0], p[:, 0], np.linspace(3, 4, 9)), up.widths, atol=1e-9)
    back = R.lane_by_id(f"{rep.roads['back'][0]}_0_-1")
    assert back.points[0, 0] == pytest.approx(80.0) and back.lane_type == "bus"


def test_zero_length_lane_and_dangling_link_warn_and_empty_layout_fails(tmp_path):
    L = m.Layout(lanes=[m.LaneCenter("dot", points=[[1, 1, 0], [1, 1, 0]]),
                        m.LaneCenter("ok", points=[[0, 0, 0], [5, 0, 0]], successors=["gone"])])
    with pytest.warns(importers.MapWarning) as rec:
        rep = X.write_opendrive(L, tmp_path / "z.xodr")
    msgs = " | ".join(str(w.message) for w in rec)
    assert "lane dot: zero length" in msgs and "lane ok: link to 'gone'" in msgs
    assert rep.skipped == ["dot"] and list(rep.roads) == ["ok"]
    with pytest.raises(InputError, match="no lane"), pytest.warns(importers.MapWarning):
        X.write_opendrive(m.Layout(lanes=[L.lanes[0]]), tmp_path / "n.xodr")
    with pytest.raises(InputError, match="tolerance"):
        X.write_opendrive(L, tmp_path / "t.xodr", tolerance=0)


def test_limits_checked_before_work(monkeypatch, tmp_path):
    monkeypatch.setattr(X, "MAX_LANES", 3)
    with pytest.raises(InputError, match="at most 3"):
        X.layout_to_opendrive(usdio.read_layout(ROOT / "samples/layouts/hand_crossing.usda"))


def test_cli_export_and_validate(run_cli, tmp_path):
    out = tmp_path / "crossing.xodr"
    r = run_cli("layout", "export", ROOT / "samples/layouts/hand_crossing.usda", "-o", out, "--validate")
    assert r.returncode == 0, r.stderr
    assert "valid against the ASAM OpenDRIVE 1.7 XSD" in r.stdout
    # one junction lane is a connecting road at both of its ends: two roads
    assert "14 roads from 13 lanes, 2 junctions" in r.stdout
    r = run_cli("layout", "import", out, "-o", tmp_path / "back.usda")
    assert r.returncode == 0, r.stderr
    assert "14 LaneCenter" in r.stdout


def test_segment_distances_match_the_plain_reference():
    """The KD-tree path of the point-to-polyline distance against trying every pair, on
    curves, noisy polylines, long-and-short segment mixes and degenerate segments."""
    rng = np.random.default_rng(7)
    cases = []
    s = np.linspace(0, 400, 3000)
    cases.append((np.c_[s, 20 * np.sin(s / 40)], rng.uniform([-10, -40], [410, 40], (500, 2))))
    walk = np.cumsum(rng.normal(0, 1, (2000, 2)), axis=0)
    cases.append((walk, walk[::3] + rng.normal(0, 0.5, (667, 2))))
    mixed = np.r_[np.c_[np.linspace(0, 1, 1500), np.zeros(1500)], [[500.0, 0.0], [500.0, 300.0]]]
    cases.append((mixed, rng.uniform([-5, -5], [505, 305], (400, 2))))
    dup = np.repeat(np.c_[np.linspace(0, 50, 800), np.linspace(0, 5, 800) ** 2], 2, axis=0)
    cases.append((dup, rng.uniform([0, 0], [50, 25], (600, 2))))       # zero-length segments
    for pts, q in cases:
        a, b = pts[:-1], pts[1:]
        assert len(q) * len(a) > P.BRUTE_PAIRS                  # the fast path runs
        np.testing.assert_allclose(P.distance_to_segments(q, a, b),
                                   P.distance_to_segments_brute(q, a, b), rtol=0, atol=1e-12)
