"""Property-based fuzzing of the readers of untrusted files (issue 17).

Drives the OpenDRIVE importer and the PLY importer through the command line (in process),
the USD layout reader and the polygon/ground builder with generated inputs, and asserts
for every example: either valid output or one error line (InputError), no other
exception, no numpy RuntimeWarning, nothing written on error, and bounded memory
(tracemalloc peak) and work (point counts against lsd3d_usd.limits). Time is bounded by
pytest-timeout (hangs only, never a timing assertion).

The default run is a small derandomised subset; `pytest -m slow tests/test_fuzz_inputs.py`
runs many random examples.
"""
from __future__ import annotations

import contextlib
import io
import math
import os
import tempfile
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from lsd3d_usd import limits  # noqa: E402
from lsd3d_usd.cli import main  # noqa: E402
from lsd3d_usd.errors import InputError  # noqa: E402

FAST = settings(max_examples=30, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck))
FAST_IMPORT = settings(FAST, max_examples=12)      # each example imports and writes a layer
SLOW = settings(max_examples=400, deadline=None, database=None,
                suppress_health_check=list(HealthCheck))
MEMORY_LIMIT = 800 * 2**20      # bytes traced by tracemalloc (numpy arrays included)


@contextlib.contextmanager
def bounded_memory(limit=MEMORY_LIMIT):
    tracemalloc.start()
    try:
        yield
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < limit, f"peak traced memory {peak / 2**20:.0f} MiB"


def run_cli(argv) -> tuple[int, str, str]:
    """main() in process with stdout/stderr captured; numpy RuntimeWarnings are errors."""
    out, err = io.StringIO(), io.StringIO()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def assert_one_line_error(code, err):
    errors = [line for line in err.splitlines() if line.startswith("lsd3d-usd: error: ")]
    assert code == 1 and len(errors) == 1, err
    assert len(errors[0]) < 600, errors[0]            # names the problem, no echoed kilobytes
    assert all(line.startswith("lsd3d-usd: ") for line in err.splitlines() if line.strip()), err


# ------------------------------------------------------------------ OpenDRIVE
# A sound map is generated as a template with named numeric slots filled with sane values;
# 0-3 slots are then replaced by hostile values, and sometimes the bytes are damaged. Both
# the importing and the refusing paths are exercised.
EXTREMES = ["0", "-0", "1e-300", "-1e-9", "99999", "1e5", "1e7", "1e8", "1e12", "1e300",
            "-1e300", "nan", "inf", "-inf", "abc", ""]
LANE_TYPES = ["driving", "driving", "sidewalk", "median", "border", "shoulder", "parking", "bogus"]


def _r(draw, lo, hi):
    return repr(round(draw(st.floats(lo, hi)), 4))


@st.composite
def road_template(draw, rid, slots):
    def slot(value):
        name = f"v{len(slots)}"
        slots[name] = value
        return "{" + name + "}"

    length = round(draw(st.floats(1, 300)), 3)
    kind = draw(st.sampled_from(["line", "arc", "spiral", "poly3", "paramPoly3"]))
    if kind == "line":
        shape = "<line/>"
    elif kind == "arc":
        shape = f'<arc curvature="{slot(_r(draw, -0.05, 0.05))}"/>'
    elif kind == "spiral":
        shape = f'<spiral curvStart="{slot(_r(draw, -0.05, 0.05))}" curvEnd="{slot(_r(draw, -0.05, 0.05))}"/>'
    elif kind == "poly3":
        shape = (f'<poly3 a="0" b="{slot(_r(draw, -0.2, 0.2))}" c="{slot(_r(draw, -0.01, 0.01))}" '
                 f'd="{slot(_r(draw, -1e-4, 1e-4))}"/>')
    else:
        shape = (f'<paramPoly3 aU="0" bU="{slot(repr(length))}" cU="0" dU="0" aV="0" bV="0" '
                 f'cV="{slot(_r(draw, -20, 20))}" dV="{slot(_r(draw, -20, 20))}" '
                 f'pRange="{draw(st.sampled_from(["normalized", "arcLength"]))}"/>')
    geom = (f'<geometry s="{slot("0")}" x="{slot(_r(draw, -200, 200))}" y="{slot(_r(draw, -200, 200))}" '
            f'hdg="{slot(_r(draw, -3.2, 3.2))}" length="{slot(repr(length))}">{shape}</geometry>')

    def lanes(sign, n):
        out = ""
        for k in range(1, n + 1):
            b = draw(st.sampled_from(["0", "0", _r(draw, -0.1, 0.05)]))
            out += (f'<lane id="{sign * k}" type="{draw(st.sampled_from(LANE_TYPES))}">'
                    f'<width sOffset="{slot("0")}" a="{slot(_r(draw, 0, 5))}" b="{slot(b)}" '
                    f'c="{slot("0")}" d="{slot("0")}"/>'
                    + ('<roadMark sOffset="0" type="solid"/>' if draw(st.booleans()) else "")
                    + "</lane>")
        return out

    sections = ""
    starts = ["0"] + ([repr(round(length / 2, 3))] if draw(st.booleans()) else [])
    for s0 in starts:
        sections += (f'<laneSection s="{slot(s0)}"><left>{lanes(1, draw(st.integers(0, 2)))}</left>'
                     f'<center><lane id="0" type="none"/></center>'
                     f'<right>{lanes(-1, draw(st.integers(1, 3)))}</right></laneSection>')
    extra = ""
    if draw(st.booleans()):
        extra += f'<laneOffset s="0" a="{slot(_r(draw, -2, 2))}" b="{slot("0")}" c="0" d="0"/>'
    profiles = ""
    if draw(st.booleans()):
        profiles += (f'<elevationProfile><elevation s="0" a="{slot(_r(draw, -5, 5))}" '
                     f'b="{slot(_r(draw, -0.05, 0.05))}" c="0" d="0"/></elevationProfile>')
    if draw(st.booleans()):
        profiles += (f'<lateralProfile><superelevation s="0" a="{slot(_r(draw, -0.3, 0.3))}" '
                     f'b="{slot("0")}" c="0" d="0"/>'
                     + ('<shape s="0" t="0" a="0" b="0.1" c="0" d="0"/>' if draw(st.booleans()) else "")
                     + "</lateralProfile>")
    link = draw(st.sampled_from(["", '<link><successor elementType="road" elementId="1" '
                                     'contactPoint="start"/></link>']))
    junction = draw(st.sampled_from(["-1", "-1", "5"]))
    return (f'<road id="{rid}" length="{slot(repr(length))}" junction="{junction}">'
            f'{link}<planView>{geom}</planView>{profiles}<lanes>{extra}{sections}</lanes></road>')


@st.composite
def opendrive_bytes(draw):
    slots: dict[str, str] = {}
    ids = draw(st.lists(st.sampled_from(["1", "2", "3", "7"]), min_size=1, max_size=3,
                        unique=draw(st.sampled_from([True, True, True, False]))))
    roads = "".join(draw(road_template(rid, slots)) for rid in ids)
    for name in draw(st.lists(st.sampled_from(sorted(slots)), max_size=3)):
        slots[name] = draw(st.sampled_from(EXTREMES))
    junction = draw(st.sampled_from(["", '<junction id="5"><connection incomingRoad="1" connectingRoad="2" '
                                         'contactPoint="start"><laneLink from="-1" to="1e400"/></connection>'
                                         '</junction>']))
    doc = (f'<?xml version="1.0" encoding="UTF-8"?>\n<OpenDRIVE><header revMajor="1" revMinor="6" '
           f'name="fuzz"/>{roads.format(**slots)}{junction}</OpenDRIVE>').encode()
    mutation = draw(st.sampled_from(["none"] * 8 + ["truncate", "bytes"]))
    if mutation == "truncate":
        doc = doc[:draw(st.integers(0, len(doc)))]
    elif mutation == "bytes":
        at = draw(st.integers(0, len(doc)))
        doc = doc[:at] + draw(st.binary(min_size=1, max_size=8)) + doc[at:]
    return doc


def check_opendrive(doc: bytes):
    from lsd3d_usd.layout.usdio import read_layout

    with tempfile.TemporaryDirectory() as d:
        src, out = Path(d) / "m.xodr", Path(d) / "L.usda"
        src.write_bytes(doc)
        with bounded_memory():
            code, _, err = run_cli(["layout", "import", src, "-o", out])
        if code == 0:
            layout = read_layout(out)                 # our own reader accepts what we wrote
            n_roads = max(1, doc.count(b"<road "))
            points = sum(len(f.coords()) for f in layout.features())
            assert points <= n_roads * limits.ROAD_POINTS.value
        else:
            assert_one_line_error(code, err)
            assert sorted(os.listdir(d)) == ["m.xodr"]   # nothing written


def _xodr(length="100", geom_length=None, shape="<line/>", width="3.5") -> bytes:
    road = (f'<road id="7" length="{length}" junction="-1"><planView><geometry s="0" x="0" y="0" '
            f'hdg="0" length="{geom_length or length}">{shape}</geometry></planView><lanes>'
            '<laneSection s="0"><center><lane id="0" type="none"/></center><right><lane id="-1" '
            f'type="driving"><width sOffset="0" a="{width}" b="0" c="0" d="0"/></lane></right>'
            '</laneSection></lanes></road>')
    return f'<?xml version="1.0"?><OpenDRIVE><header/>{road}</OpenDRIVE>'.encode()


@pytest.mark.timeout(600)
@FAST_IMPORT
@given(opendrive_bytes())
@example(_xodr(length="1e8"))                                       # the 450-byte file
@example(_xodr(length="1e12"))
@example(_xodr(length="50", geom_length="1e9", shape='<poly3 a="0" b="0" c="0" d="0"/>'))
@example(_xodr(width="1e7"))
@example(_xodr().replace(b"</OpenDRIVE>", b"\xff\xfe</OpenDRIVE>"))   # not UTF-8
# a spiral of curvature 1e5: a road area of 111 k points, over the layout reader's own limit
@example(_xodr(length="32.927", shape='<spiral curvStart="99999" curvEnd="-0.0316"/>'))
def test_fuzz_opendrive_import(doc):
    check_opendrive(doc)


@pytest.mark.slow
@pytest.mark.timeout(7200)
@SLOW
@given(opendrive_bytes())
def test_fuzz_opendrive_import_long(doc):
    check_opendrive(doc)


# ------------------------------------------------------------------ USD layout reader
FEATURE_TYPES = ["LaneCenter", "RoadLine", "RoadEdge", "Crosswalk", "Building", "Tree", "StopSign",
                 "ParkingSpot", "Sidewalk", "RoadArea", "VegetationZone", "Hedge", "Bogus"]


_MUTATIONS = ["upAxis", "metersPerUnit", "chunkSize", "extent", "json", "points", "counts",
              "widths", "type", "hint", "far"]


@st.composite
def layout_usda(draw):
    """A sound layout layer with 0-2 hostile mutations (so both the accepting and the
    refusing paths are exercised)."""
    muts = set(draw(st.lists(st.sampled_from(_MUTATIONS), max_size=2)))
    up = draw(st.sampled_from(["X", "x", ""]) if "upAxis" in muts else st.sampled_from([None, "Z", "Y"]))
    mpu = draw(st.sampled_from(["0", "-1", "nan", "inf", "1e-30", "1e30"]) if "metersPerUnit" in muts
               else st.sampled_from([None, "1", "0.01", "1000"]))
    meta = []
    if up is not None:
        meta.append(f'upAxis = "{up}"')
    if mpu is not None:
        meta.append(f"metersPerUnit = {mpu}")
    data = []
    if "chunkSize" in muts:
        data.append("double chunkSize = " + draw(st.sampled_from(["0.01", "0", "-5", "nan", "inf", "1e9"])))
    elif draw(st.booleans()):
        data.append("double chunkSize = " + draw(st.sampled_from(["100", "50", "10", "1000"])))
    x0, y0 = draw(st.floats(-500, 500)), draw(st.floats(-500, 500))
    if "extent" in muts:
        bad = draw(st.sampled_from(["[]", "[0, 0, 1]", f"[{x0!r}, {y0!r}, {x0 - 5!r}, {y0 + 5!r}]",
                                    "[0, 0, nan, 5]", "[0, 0, inf, 5]", "[0, 0, 100000, 100000]",
                                    "[-1e308, 0, 1e308, 1]"]))
        data.append(f"double[] extent = {bad}")
    elif draw(st.booleans()):
        w, h = draw(st.floats(0, 2000)), draw(st.floats(0, 2000))
        data.append(f"double[] extent = [{x0!r}, {y0!r}, {x0 + w!r}, {y0 + h!r}]")
    if "json" in muts:
        data.append(f'string metadataJson = "{draw(st.sampled_from(["[", "not json", "{"]))}"')
    if data:
        meta.append("customLayerData = {\ndictionary lsd3dLayout = {\n" + "\n".join(data) + "\n}\n}")
    prims = []
    sane = st.floats(-300, 300, allow_nan=False, allow_infinity=False)
    n_feats = draw(st.integers(1, 4))
    bad_feat = draw(st.integers(0, n_feats - 1))
    for k in range(n_feats):
        ftype = draw(st.sampled_from(FEATURE_TYPES[:-1]))
        n = draw(st.integers(3 if ftype in ("Crosswalk", "Building", "Sidewalk", "RoadArea",
                                            "VegetationZone") else 2, 6))
        if ftype == "StopSign":
            n = 1
        if ftype == "ParkingSpot":
            n = 4
        coords = [[draw(sane) + x0, draw(sane) + y0, draw(sane) / 100] for _ in range(n)]
        body = []
        if k == bad_feat and "points" in muts:
            coords[0][draw(st.integers(0, 2))] = draw(st.sampled_from([float("nan"), float("inf"), 1e38]))
        if k == bad_feat and "far" in muts:
            coords[-1][0] += draw(st.sampled_from([6e4, 1e7, 1e30]))
        if k == bad_feat and "type" in muts:
            ftype = draw(st.sampled_from(["Bogus", ""]))
        pts = ", ".join(f"({x!r}, {y!r}, {z!r})" for x, y, z in coords)
        body += [f'uniform token lsd3d:featureType = "{ftype}"', f"point3f[] points = [{pts}]"]
        if k == bad_feat and "counts" in muts:
            body.append("int[] curveVertexCounts = [" + ", ".join(
                str(draw(st.integers(-1, 4))) for _ in range(draw(st.integers(1, 3)))) + "]")
        if ftype == "LaneCenter":
            widths = [repr(draw(st.floats(0, 8)))] * (n if draw(st.booleans()) else 1)
            if k == bad_feat and "widths" in muts:
                widths = draw(st.sampled_from([["-1"], ["nan"], ["1"] * (n + 1), ["1e38"]]))
            body.append(f"float[] widths = [{', '.join(widths)}]")
        if k == bad_feat and "hint" in muts:
            body.append(f"uniform double lsd3d:heightHint = {draw(st.sampled_from(['0', '-1', 'nan', '1e300']))}")
        kind = "Points" if ftype in ("Tree", "StopSign") else "BasisCurves"
        prims.append(f'def {kind} "f{k}"\n{{\n' + "\n".join(body) + "\n}")
    return ("#usda 1.0\n(\n" + "\n".join(meta) + "\n)\n"
            'def Xform "World"\n{\ndef Scope "Layout"\n{\n' + "\n".join(prims) + "\n}\n}\n")


def check_layout_usda(text: str):
    from lsd3d_usd.layout.usdio import read_layout

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "L.usda"
        path.write_text(text)
        with bounded_memory(), warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            try:
                layout = read_layout(path)
            except InputError as e:
                assert "\n" not in str(e) and len(str(e)) < 600 + len(str(path))
                return
        (x0, y0), (x1, y1) = layout.area_box()
        assert max(x1 - x0, y1 - y0) <= limits.LAYOUT_EXTENT.value
        (x0, y0), (x1, y1) = layout.bounds()
        assert max(x1 - x0, y1 - y0) <= limits.LAYOUT_EXTENT.value
        assert limits.CHUNK_SIZE_MIN.value <= layout.chunk_size <= limits.CHUNK_SIZE_MAX.value
        ri, rj = layout.chunk_range()        # chunk grid computable, bounded by the limits
        assert len(ri) * len(rj) <= (limits.LAYOUT_EXTENT.value / limits.CHUNK_SIZE_MIN.value + 2) ** 2
        for f in layout.features():
            assert np.isfinite(f.coords()).all()


def _layout(meta: str, points: str = "(0, 0, 0), (10, 0, 0)") -> str:
    return ("#usda 1.0\n(\n" + meta + "\n)\ndef Xform \"World\"\n{\ndef Scope \"Layout\"\n{\n"
            "def BasisCurves \"l\"\n{\nuniform token lsd3d:featureType = \"LaneCenter\"\n"
            f"point3f[] points = [{points}]\n}}\n}}\n}}\n")


_DATA = "customLayerData = {{\ndictionary lsd3dLayout = {{\n{}\n}}\n}}"


@pytest.mark.timeout(600)
@FAST
@given(layout_usda())
@example(_layout("", "(0, 0, 0), (100000, 0, 0)"))                  # 100 km across
@example(_layout(_DATA.format("double chunkSize = 0.01")))
@example(_layout(_DATA.format("double chunkSize = 0")))
@example(_layout(_DATA.format("double chunkSize = nan")))
@example(_layout(_DATA.format("double[] extent = [0, 0, nan, 10]")))
@example(_layout('upAxis = "Y"\nmetersPerUnit = 0.01'))
def test_fuzz_usd_layout_reader(text):
    check_layout_usda(text)


@pytest.mark.slow
@pytest.mark.timeout(7200)
@SLOW
@given(layout_usda())
def test_fuzz_usd_layout_reader_long(text):
    check_layout_usda(text)


# ------------------------------------------------------------------------- PLY
SPLAT_PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
               "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_ply_value = st.one_of(st.floats(-3, 3, allow_nan=False), st.sampled_from(
    [0.0, 1e30, -1e30, 3e38, 1e-45, float("nan"), float("inf"), -float("inf"), 88.0, 1000.0]))


@st.composite
def ply_bytes(draw):
    fmt = draw(st.sampled_from(["binary_little_endian", "binary_big_endian", "ascii", "binary_middle"]))
    props = draw(st.sampled_from([SPLAT_PROPS, SPLAT_PROPS[:12] + SPLAT_PROPS[13:], SPLAT_PROPS[:9],
                                  ["x", "y", "z"], SPLAT_PROPS + ["f_rest_0", "f_rest_1", "f_rest_2"]]))
    types = {p: draw(st.sampled_from(["float", "float", "double", "uchar", "int"])) for p in props}
    n = draw(st.integers(0, 6))
    claim = draw(st.sampled_from([str(n), str(n), "1000000000000", str(10**40), "1e12", "-1", "x" * 5000]))
    lines = ["ply", f"format {fmt} 1.0"]
    if draw(st.booleans()):
        lines.append("element face " + draw(st.sampled_from(["0", "2"])))
        lines.append("property float area")
    lines.append(f"element vertex {claim}")
    lines += [f"property {types[p]} {p}" for p in props]
    junk = draw(st.sampled_from(["", "", "comment hi", "bogus keyword", "property list uchar int vertex_indices",
                                 "x" * 6000, "\xff\xfe"]))
    if junk:
        lines.append(junk)
    if draw(st.booleans()):
        lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("latin-1")
    values = [[draw(_ply_value) for _ in props] for _ in range(n)]
    if fmt == "ascii":
        body = "\n".join(" ".join(repr(v) for v in row) for row in values).encode()
    else:
        endian = ">" if fmt == "binary_big_endian" else "<"
        code = {"float": "f4", "double": "f8", "uchar": "u1", "int": "i4"}
        dt = np.dtype([(p, endian + code[types[p]]) for p in props])
        arr = np.zeros(n, dt)
        with np.errstate(all="ignore"):
            for k, row in enumerate(values):
                for p, v in zip(props, row):
                    arr[p][k] = v if dt[p].kind == "f" else (0 if not math.isfinite(v) else int(np.clip(v, 0, 200)))
        body = arr.tobytes()
    cut = draw(st.sampled_from([None, None, 0, 7]))
    if cut is not None:
        body = body[:cut]
    return header + body


def check_ply(data: bytes):
    from lsd3d_usd.validation import validate

    with tempfile.TemporaryDirectory() as d:
        src, out = Path(d) / "s.ply", Path(d) / "s.usdc"
        src.write_bytes(data)
        with bounded_memory():
            code, _, err = run_cli(["splats", "import-ply", src, "-o", out])
        if code == 0:
            assert [p.line() for p in validate(out) if p.severity == "error"] == []
        else:
            assert_one_line_error(code, err)
            assert sorted(os.listdir(d)) == ["s.ply"]


_PLY_HEAD = b"ply\nformat binary_little_endian 1.0\nelement vertex {}\n" + b"".join(
    b"property float " + p.encode() + b"\n" for p in SPLAT_PROPS) + b"end_header\n"


@pytest.mark.timeout(600)
@FAST
@given(ply_bytes())
@example(_PLY_HEAD.replace(b"{}", b"1000000000000") + bytes(68))
@example(_PLY_HEAD.replace(b"{}", str(10**40).encode()) + bytes(68))
@example(_PLY_HEAD.replace(b"{}", b"1 " + b"9" * 5000))
def test_fuzz_ply_import(data):
    check_ply(data)


@pytest.mark.slow
@pytest.mark.timeout(7200)
@SLOW
@given(ply_bytes())
def test_fuzz_ply_import_long(data):
    check_ply(data)


# -------------------------------------------------------------------- polygons
@st.composite
def messy_polygon(draw):
    """Vertex arrays with repeated points, near-duplicates, spikes, zero width, tiny or
    large scales: what layouts and boolean operations hand the mesh builder."""
    pool = draw(st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=1, max_size=6))
    idx = draw(st.lists(st.integers(0, len(pool) - 1), min_size=3, max_size=12))
    pts = np.array([pool[i] for i in idx], dtype=np.float64)
    jitter = draw(st.sampled_from([0.0, 1e-13, 1e-9, 1e-7, 1e-3]))
    pts = pts + jitter * np.arange(len(pts))[:, None] * np.array([1.0, -1.0])
    scale = draw(st.sampled_from([1.0, 1.0, 1e-6, 1e4]))
    return pts * scale


@st.composite
def ground_case(draw):
    lanes = []
    for _ in range(draw(st.integers(0, 3))):
        pts = draw(messy_polygon())
        w = np.abs(draw(st.lists(st.floats(0, 8), min_size=len(pts), max_size=len(pts))))
        lanes.append((np.column_stack([pts, np.zeros(len(pts))]), np.asarray(w),
                      draw(st.sampled_from(["driving", "sidewalk", "border"]))))
    walks = draw(st.lists(messy_polygon(), max_size=2))
    roads = draw(st.lists(messy_polygon(), max_size=2))
    veg = draw(st.lists(messy_polygon(), max_size=1))
    houses = draw(st.lists(messy_polygon(), max_size=2))
    return lanes, walks, roads, veg, houses


def check_polygons(case):
    from lsd3d_usd.proxy import planar
    from lsd3d_usd.proxy.ground import ground_areas, ground_parts
    from lsd3d_usd.proxy.mesh import check_part

    lanes, walks, roads, veg, houses = case
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for pts in walks + roads + houses:
            clean = planar.area_from_points(pts)
            assert clean.is_empty or clean.is_valid
            assert all(planar._sound(p) for p in planar.polygons_of(clean))
            v, f = planar.prism(clean, 0.0, 1.0)
            assert len(f) == 0 or (planar._closed(f) and f.max() < len(v) and np.isfinite(v).all())
        areas = ground_areas((-20.0, -20.0, 20.0, 20.0), 12.0, lanes, road_areas=roads,
                             sidewalks=walks, vegetation=veg, buildings=houses)
        for part in ground_parts(areas, "Chunk_0_0"):
            assert check_part(part) == [], part.part_id
            assert len(part.faces) < 200_000     # work bounded by the chunk, not the input


@pytest.mark.timeout(600)
@FAST
@given(ground_case())
@example(([], [np.array([[20, 0], [20 + 1e-13, 0], [20, 1e-13]])], [], [], []))   # sliver ring
@example(([], [np.array([[1, 2], [1e-13, -1e-13], [3, -2e-13], [3e-13, 1], [3, -4e-13]])], [], [], []))
# a coordinate of 1e-38 or 1e-20 m: GEOS's mitred buffer raised a divide-by-zero flag (a
# RuntimeWarning)
@example(([], [], [np.array([[0.0, 0.0], [0.0, 1.0], [1.17549435e-38, -1.0], [-1.0, 0.0]])], [], []))
@example(([], [], [np.array([[0.0, 0.0], [0.0, 1.0], [1e-20, -1.0], [-1.0, 0.0]])], [], []))
# a 5e-6 m² sliver at 2.3e5 m: its ring's area cancelled to nothing in raw coordinates
@example(([], [], [], [], [np.array([[-6e4, 0.0], [1e-3, -1e-3], [1.00000002e5, 2.29999998e5],
                                     [1.00000003e5, 2.29999997e5]])]))
# a lane zigzagging over 4e-6 m with one width of 1 m: a valid sliver ribbon whose two
# vertices 1e-21 m apart gave NaN in GEOS's mitred curb buffer (a RuntimeWarning)
@example(([(np.array([[3.999999999999997e-06, 1.0000000000000006e-06, 0.0],
                      [1e-19, -9.999999999999993e-20, 0.0],
                      [3.999999999999997e-06, 1.0000000000000006e-06, 0.0],
                      [3.000000000000002e-19, -3e-19, 0.0],
                      [4.000000000000002e-06, 1e-06, 0.0]]),
            np.array([0.0, 1.0, 0.0, 0.0, 0.0]), "driving")], [], [], [], []))
# a building ring whose vertex lies 4e-9 m inside the sidewalk's corner and touches its
# edge: the sliver between the rings left a 4e-9 m curb wall of no area
@example(([], [np.array([[0.0, 0.0], [1.0, -2.0], [0.0, 1.0]])], [], [],
          [np.array([[3e-9, -3e-9], [5e-5, 0.0], [0.0, 5e-5]])]))
def test_fuzz_polygon_builder(case):
    check_polygons(case)


@pytest.mark.slow
@pytest.mark.timeout(7200)
@SLOW
@given(ground_case())
def test_fuzz_polygon_builder_long(case):
    check_polygons(case)
