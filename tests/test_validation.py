"""`validate`: a good stage passes; each defect is caught on a purpose-built bad stage."""
import json

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, Vt

from lsd3d_usd import scene, validation
from lsd3d_usd.splats import usdio


def _good_stage(field_factory, n=200):
    st = scene.new_stage()
    usdio.write_surfels(st, "/World/Surfels", field_factory(n))
    return st


def _problems(tmp_path, stage, name="s.usda"):
    path = tmp_path / name
    scene.save_stage(stage, path)
    return validation.validate(path)


def _errors(problems):
    return [p for p in problems if p.severity == "error"]


def _one(problems, attribute, check):
    errs = _errors(problems)
    assert [(p.attribute, p.check) for p in errs] == [(attribute, check)], [p.line() for p in errs]
    return errs[0]


def test_good_stage_passes(tmp_path, field_factory):
    assert _errors(_problems(tmp_path, _good_stage(field_factory))) == []


def _set(stage, attr, value):
    stage.GetPrimAtPath("/World/Surfels").GetAttribute(attr).Set(value)


def test_array_length_mismatch(tmp_path, field_factory):
    st = _good_stage(field_factory)
    _set(st, "opacities", Vt.FloatArray([0.5] * 10))
    p = _one(_problems(tmp_path, st), "opacities", "lsd3d:ArrayLength")
    assert "10 values for 200 positions" in p.message


def test_non_finite_positions(tmp_path, field_factory):
    st = _good_stage(field_factory)
    f = field_factory(200)
    pos = f.positions.copy()
    pos[17, 1] = np.nan
    _set(st, "positions", Vt.Vec3fArray.FromNumpy(pos))
    errs = _errors(_problems(tmp_path, st))
    assert any(p.attribute == "positions" and p.check == "lsd3d:Finite" and "first index 17" in p.message
               for p in errs)


def test_opacity_out_of_range(tmp_path, field_factory):
    st = _good_stage(field_factory)
    o = field_factory(200).opacities.copy()
    o[5] = -0.1
    _set(st, "opacities", Vt.FloatArray.FromNumpy(o))
    assert "first index 5" in _one(_problems(tmp_path, st), "opacities", "lsd3d:OpacityRange").message


def test_non_positive_scale(tmp_path, field_factory):
    st = _good_stage(field_factory)
    s = np.zeros((200, 3), np.float32)
    s[:, :2] = 0.1
    s[9, 0] = 0.0
    _set(st, "scales", Vt.Vec3fArray.FromNumpy(s))
    _one(_problems(tmp_path, st), "scales", "lsd3d:ScalePositive")


def test_non_unit_quaternion(tmp_path, field_factory):
    st = _good_stage(field_factory)
    q = field_factory(200).orientations.copy()
    q[3] *= 1.01
    _set(st, "orientations", Vt.QuatfArray.FromNumpy(q))
    _one(_problems(tmp_path, st), "orientations", "lsd3d:UnitQuaternion")


def test_sh_degree_mismatch(tmp_path, field_factory):
    st = _good_stage(field_factory)  # degree 1 → 4 coefficients per particle
    st.GetPrimAtPath("/World/Surfels").GetAttribute("radiance:sphericalHarmonicsDegree").Set(2)
    p = _one(_problems(tmp_path, st), "radiance:sphericalHarmonicsCoefficients", "lsd3d:SHDegree")
    assert "degree 2 needs 9" in p.message


def test_extent_not_covering(tmp_path, field_factory):
    st = _good_stage(field_factory)
    _set(st, "extent", Vt.Vec3fArray([(-1, -1, -1), (1, 1, 1)]))
    _one(_problems(tmp_path, st), "extent", "lsd3d:Extent")


def test_missing_extent(tmp_path, field_factory):
    st = _good_stage(field_factory)
    st.GetPrimAtPath("/World/Surfels").RemoveProperty("extent")
    _one(_problems(tmp_path, st), "extent", "lsd3d:Extent")


def test_semantic_id_out_of_range(tmp_path, field_factory):
    st = _good_stage(field_factory)
    ids = np.zeros(200, np.int32)
    ids[2] = 99
    _set(st, "lsd3d:semanticIds", Vt.IntArray.FromNumpy(ids))
    _one(_problems(tmp_path, st), "lsd3d:semanticIds", "lsd3d:SemanticRange")


def test_unknown_prim_type(tmp_path, field_factory):
    st = _good_stage(field_factory)
    st.DefinePrim("/World/Thing", "NoSuchType")
    p = _one(_problems(tmp_path, st), None, "lsd3d:UnknownPrimType")
    assert p.prim == "/World/Thing"


@pytest.mark.parametrize("what,validator", [
    ("upAxis", "usdGeomValidators:StageMetadataChecker"),
    ("metersPerUnit", "usdGeomValidators:StageMetadataChecker"),
    ("defaultPrim", "usdValidation:StageMetadataChecker"),
])
def test_missing_stage_metadata(tmp_path, field_factory, what, validator):
    st = _good_stage(field_factory)
    layer = st.GetRootLayer()
    {"upAxis": lambda: layer.pseudoRoot.ClearInfo("upAxis"),
     "metersPerUnit": lambda: layer.pseudoRoot.ClearInfo("metersPerUnit"),
     "defaultPrim": layer.ClearDefaultPrim}[what]()
    errs = _errors(_problems(tmp_path, st))
    assert [p.check for p in errs] == [validator], [p.line() for p in errs]
    assert what.lower() in errs[0].message.lower()


def test_unresolvable_texture(tmp_path, field_factory):
    st = _good_stage(field_factory)
    dome = UsdLux.DomeLight.Define(st, "/World/Env")
    dome.CreateTextureFileAttr(Sdf.AssetPath("./textures/missing.exr"))
    errs = _errors(_problems(tmp_path, st))
    assert [(p.prim, p.attribute, p.check) for p in errs] == [
        ("/World/Env", "inputs:texture:file", "lsd3d:AssetPath")], [p.line() for p in errs]


def test_unresolvable_reference_and_payload(tmp_path, field_factory):
    st = _good_stage(field_factory)
    st.DefinePrim("/World/Car").GetReferences().AddReference("./assets/car.usd")
    st.DefinePrim("/World/Chunk").GetPayloads().AddPayload("./chunks/c.usdc")
    msgs = " ".join(p.message for p in _errors(_problems(tmp_path, st)))
    assert "car.usd" in msgs and "c.usdc" in msgs


def test_bulk_data_in_usda(tmp_path, field_factory):
    st = _good_stage(field_factory, n=validation.BULK_TEXT_LIMIT + 1)
    _one(_problems(tmp_path, st, "bulk.usda"), "positions", "lsd3d:BulkDataInUsda")
    assert _errors(_problems(tmp_path, st, "bulk.usdc")) == []


def test_mesh_checks(tmp_path):
    st = scene.new_stage()
    m = UsdGeom.Mesh.Define(st, "/World/M")
    m.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    m.CreateFaceVertexCountsAttr([3])
    m.CreateFaceVertexIndicesAttr([0, 1, 5])
    m.CreateExtentAttr([(0, 0, 0), (1, 1, 0)])
    _one(_problems(tmp_path, st), "faceVertexIndices", "lsd3d:IndexRange")


def test_official_3dgs_file_from_another_tool_validates(tmp_path):
    st = scene.new_stage()
    prim = st.DefinePrim("/World/G", "ParticleField3DGaussianSplat")
    prim.GetAttribute("positions").Set(Vt.Vec3fArray([(0, 0, 0), (1, 0, 0)]))
    prim.GetAttribute("scales").Set(Vt.Vec3fArray([(0.1, 0.2, 0.3)] * 2))
    prim.GetAttribute("opacities").Set(Vt.FloatArray([0.5, 1.0]))
    prim.GetAttribute("orientations").Set(Vt.QuatfArray.FromNumpy(np.array([[0, 0, 0, 1]] * 2, np.float32)))
    prim.GetAttribute("radiance:sphericalHarmonicsDegree").Set(0)
    prim.GetAttribute("radiance:sphericalHarmonicsCoefficients").Set(Vt.Vec3fArray([(0, 0, 0)] * 2))
    prim.GetAttribute("extent").Set(Vt.Vec3fArray([(-0.9, -0.9, -0.9), (1.9, 0.9, 0.9)]))
    assert _errors(_problems(tmp_path, st)) == []
    prim.GetAttribute("scales").Set(Vt.Vec3fArray([(0.1, 0.2, 0.0)] * 2))  # ellipsoid needs z > 0
    _one(_problems(tmp_path, st), "scales", "lsd3d:ScalePositive")


def test_cli_exit_codes_and_json(tmp_path, field_factory, run_cli):
    good, bad = tmp_path / "good.usdc", tmp_path / "bad.usda"
    scene.save_stage(_good_stage(field_factory), good)
    st = _good_stage(field_factory)
    st.DefinePrim("/World/X", "Bogus")
    scene.save_stage(st, bad)
    r = run_cli("validate", good)
    assert r.returncode == 0 and "valid" in r.stdout
    r = run_cli("validate", bad)
    assert r.returncode == 1
    assert "/World/X: unknown prim type 'Bogus'" in r.stdout
    r = run_cli("validate", bad, "--json")
    report = json.loads(r.stdout)
    assert r.returncode == 1 and report["valid"] is False and report["problems"][0]["prim"] == "/World/X"


@pytest.mark.parametrize("counts,kind,basis,wrap,n,message", [
    (None, "linear", None, None, 2, "missing for 2 points"),
    ([2, 2], "linear", None, None, 5, "do not add up to the 5 points"),
    ([2], None, None, None, 2, "type cubic, basis bezier, wrap nonperiodic needs 4 + 3k (type is not authored"),
    ([5], "cubic", "bezier", None, 5, "needs 4 + 3k"),
    ([2], "linear", None, "periodic", 2, "needs at least 3"),
    ([3], "cubic", "bspline", None, 3, "needs at least 4"),
    ([2], "linear", None, None, 2, None),
    ([7, 4], "cubic", "bezier", None, 11, None),
    ([6], "cubic", "bezier", "periodic", 6, None),
    ([2], "cubic", "catmullRom", "pinned", 2, None),
])
def test_basis_curves_checks(tmp_path, counts, kind, basis, wrap, n, message):
    st = scene.new_stage()
    c = UsdGeom.BasisCurves.Define(st, "/World/C")
    c.CreatePointsAttr([(float(i), 0.0, 0.0) for i in range(n)])
    if counts is not None:
        c.CreateCurveVertexCountsAttr(counts)
    for attr, value in (("type", kind), ("basis", basis), ("wrap", wrap)):
        if value is not None:
            c.GetPrim().GetAttribute(attr).Set(value)
    errs = [p for p in _errors(_problems(tmp_path, st)) if p.check == "lsd3d:BasisCurves"]
    if message is None:
        assert errs == []
    else:
        assert len(errs) == 1 and errs[0].attribute == "curveVertexCounts"
        assert message in errs[0].message


def test_sample_layouts_are_valid_basis_curves(tmp_path):
    """Every curve of the sample layouts is one USD tools draw; inspect counts them."""
    from conftest import ROOT
    from lsd3d_usd import inspection
    for f in sorted((ROOT / "samples" / "layouts").glob("*.usda")):
        assert _errors(validation.validate(f)) == [], f
        rows = [r for r in inspection.inspect(f, max_depth=10)["prims"] if r["type"] == "BasisCurves"]
        assert rows and all(r["curves"] >= 1 for r in rows), f
