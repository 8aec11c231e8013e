"""Hostile map, config and file inputs (issue 40, cases 6 and 13-25): one error line
naming what is wrong and where, exit 1, nothing written."""
import os

import numpy as np

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


# ------------------------------------------------------------ 15-18: no tracebacks
DEEP = "a = " + "[" * 2000 + "]" * 2000 + "\n"


def test_deeply_nested_toml(tmp_path, cli_error):
    cfg = tmp_path / "deep.toml"
    cfg.write_text(DEEP)
    cli_error(["generate", "--config", cfg, "-o", tmp_path / "s"], "deep.toml", "nested too deeply")
    spec = tmp_path / "spec.toml"
    spec.write_text('[[scene]]\nname = "a"\n' + DEEP)
    cli_error(["batch", spec, "--dry-run"], "spec.toml", "nested too deeply")
    assert sorted(os.listdir(tmp_path)) == ["deep.toml", "spec.toml"]


def test_generate_below_a_file(tmp_path, cli_error):
    from tests.conftest import LAYOUT
    (tmp_path / "FILE").write_text("x")
    cli_error(["generate", "--layout", LAYOUT, "-o", tmp_path / "FILE" / "x", "--steps", "0"],
              "FILE is a file, not a folder")
    assert os.listdir(tmp_path) == ["FILE"]


def test_os_errors_are_one_line(tmp_path, cli_error, monkeypatch):
    # 16: a folder made immutable mid-run: the OSError of the write is one line naming the file
    import lsd3d_usd.env_commands as envc

    def denied(*a, **k):
        raise PermissionError(13, "Permission denied", str(tmp_path / "ggds" / "loss.png"))
    monkeypatch.setattr(envc, "_env", denied)
    line = cli_error(["env", "-o", tmp_path / "e.exr", "--resolution", "64x32"])
    assert line == f"lsd3d-usd: error: {tmp_path / 'ggds' / 'loss.png'}: Permission denied"


def test_broken_pipe_is_quiet():
    # 17: `lsd3d-usd ... | head -1`: the reader is gone before the command writes
    import subprocess
    import sys
    proc = subprocess.Popen([sys.executable, "-m", "lsd3d_usd", "generate", "--list-options"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141
    assert "Traceback" not in err and "Broken" not in err, err


# ------------------------------------------------------------- 21-23: clear messages
def test_huge_prompt_is_refused_and_unknown_words_are_cut(tmp_path, cli_error, capsys):
    from lsd3d_usd.cli import main
    line = cli_error(["env", "-o", tmp_path / "e.exr", "--resolution", "64x32",
                      "--prompt", "x" * 50_000_000], "prompt length 50000000 characters",
                     "limit of 10000 characters")
    assert len(line) < 300 and os.listdir(tmp_path) == []
    words = " ".join(f"qq{k}" for k in range(1500))
    assert main(["env", "-o", str(tmp_path / "e.exr"), "--resolution", "64x32", "--prompt", words]) == 0
    warn = [ln for ln in capsys.readouterr().err.splitlines() if "not understood" in ln]
    assert len(warn) == 1 and len(warn[0]) < 400 and "(and 1490 more)" in warn[0]


def _splat_ply(tmp_path, field_factory, n=40):
    from lsd3d_usd.splats.ply import splat_vertex_array, write_ply_vertices
    path = tmp_path / "s.ply"
    write_ply_vertices(path, splat_vertex_array(field_factory(n, sh_degree=0, semantic=False)))
    return path


def test_ply_header_over_the_size_limit(tmp_path, field_factory, cli_error):
    path = _splat_ply(tmp_path, field_factory)
    data = path.read_bytes()
    comments = b"".join(b"comment " + b"c" * 90 + b"\n" for _ in range(20_000))   # 1.9 MB
    path.write_bytes(data.replace(b"ply\n", b"ply\n" + comments, 1))
    cli_error(["splats", "import-ply", path, "-o", tmp_path / "o.usdc"], "s.ply",
              "header size", "exceeds the limit of 1048576 bytes")
    assert os.listdir(tmp_path) == ["s.ply"]


def test_ply_binary_header_with_an_ascii_body(tmp_path, field_factory, cli_error):
    import numpy as np
    from lsd3d_usd.plyio import read_ply_vertices
    path = _splat_ply(tmp_path, field_factory)
    data = path.read_bytes()
    head, _ = data.split(b"end_header\n", 1)
    arr = read_ply_vertices(path)
    rows = "\n".join(" ".join(f"{v:.6g}" for v in r) for r in np.array(arr.tolist()))
    path.write_bytes(head + b"end_header\n" + (rows + "\n").encode() * 3)
    cli_error(["splats", "import-ply", path, "-o", tmp_path / "o.usdc"], "s.ply",
              "binary_little_endian", "body is ASCII text")
    assert os.listdir(tmp_path) == ["s.ply"]


# ------------------------------------------------ 24: bad surfels named at render/eval
@pytest.mark.parametrize("attr,value,needle", [
    ("positions", float("nan"), "a non-finite position at particle 14"),
    ("orientations", 0.0, "a zero quaternion at particle 14"),
    ("opacities", 5.0, "an opacity outside [0, 1]"),
])
def test_render_names_the_layer_and_prim_of_bad_surfels(tmp_path, cli_error, attr, value, needle):
    from tests.test_viewer_server import make_scene
    from lsd3d_usd import scene as S
    root = tmp_path / "scene"
    make_scene(root, chunks=((0, 0),), n=40, run=False,
                   cameras={"Top": ((-10, 20, 30), (50, 50, 0))})
    import numpy as np
    from pxr import Usd
    st = Usd.Stage.Open(str(root / "layers" / "surfels.usdc"))   # the writer refuses bad values
    a = st.GetPrimAtPath(S.SURFELS_PATH).GetAttribute(attr)
    arr = np.array(a.Get())
    arr[14] = value
    a.Set(type(a.Get()).FromNumpy(arr))
    st.GetRootLayer().Save()
    before = sorted(os.listdir(root))
    line = cli_error(["render", root, "--camera", "/World/Cameras/Top", "--resolution", "32x24",
                      "-o", tmp_path / "frames"], "surfels.usdc", f"{S.SURFELS_PATH}.{attr}", needle)
    assert len(line) < 400 and not (tmp_path / "frames").exists() and sorted(os.listdir(root)) == before


# ------------------------------------------------------ 8, 9: OSM ways of many nodes
def _random_way(n, seed=1):
    import random
    rnd = random.Random(seed)
    nodes = "".join(f'<node id="{i}" lat="{48.0 + rnd.uniform(0, 700 / 111000)}" '
                    f'lon="{8.4 + rnd.uniform(0, 150 / 74000)}"/>' for i in range(1, n + 1))
    refs = "".join(f'<nd ref="{i}"/>' for i in range(1, n + 1))
    return nodes, f'<way id="1">{refs}<tag k="highway" v="residential"/></way>'


def test_osm_way_over_the_node_limit_is_skipped_by_name(tmp_path, cli_error, capsys):
    from lsd3d_usd.cli import main
    refs = "".join(f'<nd ref="{1 + k % 2}"/>' for k in range(2001))    # alternating refs
    src = tmp_path / "m.osm"
    src.write_text(_osm(_nodes() + f'<way id="9">{refs}<tag k="highway" v="primary"/></way>' + WAY))
    capsys.readouterr()
    assert main(["layout", "import", str(src), "-o", str(tmp_path / "o.usda")]) == 0
    err = capsys.readouterr().err
    assert "way 9: node references of one way 2001 nodes exceeds the limit of 2000 nodes; way skipped" in err
    cli_error(["layout", "import", src, "--strict", "-o", tmp_path / "p.usda"], "way 9", "2000 nodes")
    assert not (tmp_path / "p.usda").exists()


def _spikes_reference(pts, limit_deg):
    """The plain repair: at the first node where the way turns back drop it (or the way's end
    beside it when that shortens the way more), start again."""
    keep = list(range(len(pts)))
    lim = np.cos(np.radians(limit_deg))
    changed = True
    while changed and len(keep) > 2:
        changed = False
        for i in range(1, len(keep) - 1):
            u = pts[keep[i]] - pts[keep[i - 1]]
            v = pts[keep[i + 1]] - pts[keep[i]]
            if np.dot(u, v) / max(np.hypot(*u) * np.hypot(*v), 1e-12) < lim:
                # the node whose removal shortens the way most: the middle one, or an end
                gain = {i: np.hypot(*u) + np.hypot(*v)
                        - np.hypot(*(pts[keep[i + 1]] - pts[keep[i - 1]]))}
                if i - 1 == 0:
                    gain[0] = np.hypot(*u)
                if i + 1 == len(keep) - 1:
                    gain[i + 1] = np.hypot(*v)
                del keep[max(gain, key=lambda k: (gain[k], k == i))]
                changed = True
                break
    return keep


def test_spike_repair_matches_the_plain_reference():
    import warnings
    from lsd3d_usd.layout.importers import ImportOptions
    from lsd3d_usd.layout.osm_features import SPIKE_DEG, sound_highways
    rng = np.random.default_rng(3)
    for n in (3, 10, 60, 300):
        pts = rng.uniform(0, 100, (n, 2))
        xy_of = {k: pts[k] for k in range(n)}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            (_, _, refs), = sound_highways("m.osm", [(1, {}, list(range(n)))], xy_of, ImportOptions())
        assert refs == _spikes_reference(pts, SPIKE_DEG), n


def test_long_way_surface_matches_one_buffer():
    import shapely
    from shapely.geometry import LineString
    from lsd3d_usd.layout.osm_import import _road_strip
    pts = np.random.default_rng(0).uniform(0, 100, (300, 2))
    one = LineString(pts).buffer(3.0, cap_style="flat", join_style="round", quad_segs=4)
    pieces = shapely.union_all(_road_strip(pts, 3.0))
    assert len(_road_strip(pts, 3.0)) > 1
    assert pieces.symmetric_difference(one).area < 1e-5 * one.area


@pytest.mark.slow
def test_random_way_of_2000_nodes_imports(tmp_path):
    from lsd3d_usd.layout.importers import read_map
    nodes, way = _random_way(2000)
    src = tmp_path / "r.osm"
    src.write_text(_osm(nodes + way))
    with pytest.warns(Warning, match="turns back"):
        layout, _ = read_map(src)
    assert layout.lanes


# ------------------------------------------------------- 10: layout point limits
def test_layout_reader_refuses_a_lane_of_too_many_points(tmp_path, cli_error):
    from lsd3d_usd.layout import model as m
    from lsd3d_usd.layout.usdio import write_layout
    n = 100_001
    s = np.linspace(0, 40_000, n)
    lay = m.Layout()
    lay.add(m.LaneCenter("a", points=np.c_[s, np.sin(s / 50), np.zeros(n)], widths=np.full(n, 3.5)))
    write_layout(lay, tmp_path / "L.usdc")
    cli_error(["layout", "export", tmp_path / "L.usdc", "-o", tmp_path / "L.xodr"], "L.usdc",
              ".points", "points of one feature 100001 points exceeds the limit of 100000 points")
    assert not (tmp_path / "L.xodr").exists()


# ------------------------------------------------------- 25: ways with missing nodes
@pytest.mark.parametrize("bbox", [None, "8.3,47.9,8.5,48.1"])
def test_ways_with_missing_nodes_are_named(tmp_path, capsys, bbox):
    from lsd3d_usd.cli import main
    src = tmp_path / "m.osm"
    src.write_text(_osm(_nodes() + WAY + '<way id="8"><nd ref="1"/><nd ref="99"/>'
                        '<tag k="highway" v="residential"/></way>'))
    capsys.readouterr()
    args = ["layout", "import", str(src), "-o", str(tmp_path / "o.usda")] + ([f"--bbox={bbox}"] if bbox else [])
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "way 8" in err and "node 99" in err
