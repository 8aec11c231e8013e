"""The proxy's cheap paths give the same output as the plain ones, bit for bit: quads
windowed to a chunk equal the whole polyline's quads near it, the vectorised dashes equal a
per-dash loop, the builder's cached digests and cleaned polygons equal fresh ones, and the
chunk layer authored with Sdf equals the one the UsdGeom / UsdSemantics schema API authors."""
import re

import numpy as np
import pytest
import shapely
from shapely.geometry import MultiPolygon, Polygon, box

import lsd3d_usd  # noqa: F401  (registers the schema before any stage opens)
from pxr import Sdf, Usd, UsdGeom, UsdSemantics, Vt

from lsd3d_usd.layout.generator import generate
from lsd3d_usd.proxy import planar, usdio
from lsd3d_usd.proxy.chunks import ProxyBuilder, build_chunk_parts, chunk_inputs_hash
from lsd3d_usd.proxy.mesh import merge_parts
from lsd3d_usd.scene import chunk_prim_name, provenance, save_layer

BOXES = [(1210.0, -30.0, 1310.0, 30.0), (0.0, -10.0, 40.0, 10.0), (2950.0, -5.0, 3100.0, 5.0),
         (500.0, 3.0, 600.0, 50.0), (100.0, 500.0, 200.0, 600.0)]


def _winding(n=900, seed=0):
    """A long polyline with repeated points, a reversal and loops that leave and re-enter
    the boxes above."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 3000.0, n) + rng.normal(0, 0.2, n)
    y = 40.0 * np.sin(x / 61.0) + rng.normal(0, 0.3, n)
    p = np.column_stack([x, y, np.zeros(n)])
    p[100] = p[99]                                   # repeated
    p[101] = p[99] + [1e-7, 0, 0]                    # within the repeat tolerance
    p[300] = p[298]                                  # a reversal
    return p


def _near(q, b):
    lo, hi = q.min(axis=1), q.max(axis=1)
    return q[(hi[:, 0] >= b[0]) & (lo[:, 0] <= b[2]) & (hi[:, 1] >= b[1]) & (lo[:, 1] <= b[3])]


@pytest.mark.parametrize("seed", [0, 1])
def test_windowed_quads_are_the_whole_polylines_quads_bit_for_bit(seed):
    pts = _winding(seed=seed)
    widths = 1.75 + 0.4 * np.cos(pts[:, 0] / 90.0)
    whole = planar._quads(pts, widths, 0.8 * widths)
    for b in BOXES:
        np.testing.assert_array_equal(planar._quads(pts, widths, 0.8 * widths, within=b),
                                      _near(whole, b))
        many = planar._quads_many([pts, pts[::-1] + 3.0, pts[:5]], 0.075)
        windowed = planar._quads_many(
            [c for c in (planar._near_part(ln, b, planar.MITER_LIMIT * 0.075)
                         for ln in (pts, pts[::-1] + 3.0, pts[:5])) if c is not None], 0.075)
        np.testing.assert_array_equal(_near(windowed, b), _near(many, b))


def test_windowed_ribbons_are_the_whole_ribbons_near_the_box():
    pts = _winding()
    for b in BOXES:
        q = _near(planar._quads_many([pts], 0.075), b)
        ref = planar._union_quads(q)
        got = planar.ribbons([pts], 0.075, within=b)
        assert shapely.equals_exact(got, ref, 0.0)
        np.testing.assert_array_equal(shapely.get_coordinates(got), shapely.get_coordinates(ref))


def _dashes_loop(points, dash, gap, phase=0.0):
    """Plain reference: one dash at a time."""
    xy = planar.clean_polyline(points)
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    out = []
    for a in np.arange(-(phase % (dash + gap)), s[-1], dash + gap):
        a0, a1 = max(a, 0.0), min(a + dash, s[-1])
        if a1 - a0 < 1e-3:
            continue
        i0, i1 = np.searchsorted(s, a0, side="right"), np.searchsorted(s, a1, side="left")
        pa = np.array([np.interp(a0, s, xy[:, 0]), np.interp(a0, s, xy[:, 1])])
        pb = np.array([np.interp(a1, s, xy[:, 0]), np.interp(a1, s, xy[:, 1])])
        out.append(np.vstack([pa, xy[i0:i1], pb]))
    return out


@pytest.mark.parametrize("phase", [0.0, 1.3, 7.9])
def test_vectorised_dashes_equal_a_per_dash_loop(phase):
    pts = _winding()
    got, ref = planar.dashes(pts, 3.0, 6.0, phase), _dashes_loop(pts, 3.0, 6.0, phase)
    assert len(got) == len(ref) > 300
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a, b)


def test_polygons_of_a_multipolygon_keeps_order_and_drops_empty_parts():
    cells = [box(x, 0, x + 1, 1) for x in range(0, 20, 2)]
    mp = MultiPolygon(cells)
    got = planar.polygons_of(mp)
    assert [g.wkb for g in got] == [c.wkb for c in cells]
    gc = shapely.GeometryCollection([mp, Polygon(), cells[0]])
    assert [g.wkb for g in planar.polygons_of(gc)] == [c.wkb for c in cells + [cells[0]]]


def test_clean_area_of_valid_input_is_the_input_polygons():
    """The shortcut for valid (multi)polygons returns what the full check returns: the
    input's own polygons; touching cells (an invalid multipolygon) are still merged."""
    poly = Polygon([(0, 0), (4, 0), (4, 3), (0, 3)], [[(1, 1), (2, 1), (2, 2), (1, 2)]])
    assert planar.clean_area(poly) is poly
    mp = MultiPolygon([box(0, 0, 1, 1), box(3, 0, 4, 1)])
    assert [g.wkb for g in planar.polygons_of(planar.clean_area(mp))] == \
        [g.wkb for g in mp.geoms]
    touching = shapely.GeometryCollection([box(0, 0, 1, 1), box(1, 0, 2, 1)])
    merged = planar.clean_area(touching)
    assert merged.geom_type == "Polygon" and merged.area == pytest.approx(2.0)
    # a repeated vertex is still rebuilt away
    rep = Polygon([(0, 0), (2, 0), (2, 0), (2, 2), (0, 2)])
    assert len(planar.clean_area(rep).exterior.coords) == 5


@pytest.fixture(scope="module")
def city():
    return generate(2, (300.0, 300.0), "urban")


def test_builder_caches_give_the_plain_hash_and_parts(city):
    b = ProxyBuilder(city)
    for key in [(0, 0), (1, 1), (2, 1)]:
        inp = b.inputs(key)
        assert inp.hash == chunk_inputs_hash(inp.layout, inp.fixtures, b.params, key)
        cached, plain = b.build(key, inp), build_chunk_parts(inp, b.params)
        assert [(p.cls, p.part_id) for p in cached] == [(p.cls, p.part_id) for p in plain]
        for p, q in zip(cached, plain):
            np.testing.assert_array_equal(p.vertices, q.vertices)
            np.testing.assert_array_equal(p.faces, q.faces)
    assert usdio.layout_hash(city, b.feature_bytes) == usdio.layout_hash(city)


def _write_with_schema_api(parts, key, path, inputs_hash, params):
    """Plain reference: the chunk layer authored through a stage and the schema API."""
    name = chunk_prim_name(*key)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, f"/{name}")
    stage.SetDefaultPrim(root.GetPrim())
    solid = {}
    for p in parts:
        solid[p.cls] = solid.get(p.cls, True) and p.solid
    merged = merge_parts(parts, prefix=f"{name}/")
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for cls, cm in merged.items():
        mesh = UsdGeom.Mesh.Define(stage, f"/{name}/{cls}")
        pts = np.ascontiguousarray(cm.vertices, dtype=np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(cm.faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(
            np.ascontiguousarray(cm.faces.reshape(-1), dtype=np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDoubleSidedAttr(False)
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(0), pts.max(0)])))
        prim = mesh.GetPrim()
        UsdSemantics.LabelsAPI.Apply(prim, "class").CreateLabelsAttr(Vt.TokenArray([cm.cls]))
        uni = Sdf.VariabilityUniform
        prim.CreateAttribute(usdio.ID_ATTR, Sdf.ValueTypeNames.String, variability=uni).Set(cm.name)
        prim.CreateAttribute(usdio.PART_IDS_ATTR, Sdf.ValueTypeNames.StringArray,
                             variability=uni).Set(Vt.StringArray(list(cm.part_ids)))
        prim.CreateAttribute(usdio.SOLID_ATTR, Sdf.ValueTypeNames.Bool,
                             variability=uni).Set(bool(solid[cls]))
        UsdGeom.PrimvarsAPI(prim).CreatePrimvar(
            usdio.PART_INDEX_PRIMVAR, Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(
            Vt.IntArray.FromNumpy(np.ascontiguousarray(cm.face_part, dtype=np.int32)))
        base = usdio._class_color(cm.cls)
        if any(c is not None for c in cm.part_colors):
            cols = np.array([base if c is None else c for c in cm.part_colors], np.float32)
            mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform).Set(
                Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(cols[cm.face_part])))
        else:
            mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(
                Vt.Vec3fArray.FromNumpy(base[None, :]))
        lo, hi = np.minimum(lo, cm.vertices.min(0)), np.maximum(hi, cm.vertices.max(0))
    UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint([tuple(lo), tuple(hi)])
    prov = provenance("proxy-chunk", params, chunk=[int(key[0]), int(key[1])],
                      inputsHash=inputs_hash,
                      triangles={c: int(cm.n_faces) for c, cm in merged.items()})
    return save_layer(stage.GetRootLayer(), path, prov)


def _text(path):
    txt = Sdf.Layer.OpenAsAnonymous(str(path)).ExportToString()
    return re.sub(r'string created = ".*"', "", txt)


def test_sdf_chunk_layer_equals_the_schema_api_layer(city, tmp_path):
    b = ProxyBuilder(city)
    pdict = b.params.as_dict()
    n_colored = 0
    for key in [(0, 0), (1, 1), (2, 2)]:
        inp = b.inputs(key)
        parts = b.build(key, inp)
        n_colored += sum(p.color is not None for p in parts)
        a = usdio.write_chunk_layer(parts, key, tmp_path / f"a_{key}.usdc", inp.hash, pdict)
        r = _write_with_schema_api(parts, key, tmp_path / f"r_{key}.usdc", inp.hash, pdict)
        assert _text(a) == _text(r)
    assert n_colored > 0            # both display-colour forms compared
