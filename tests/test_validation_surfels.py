"""validate / inspect on hostile surfel prims (issue 17, item 7) and the .usda bulk rule (item 9)."""
import json

import numpy as np
import pytest
from pxr import Usd, Vt

from lsd3d_usd import inspection, scene, validation
from lsd3d_usd.cli import main
from lsd3d_usd.splats import usdio
from lsd3d_usd.splats.field import SurfelField


def _errors(problems):
    return [p for p in problems if p.severity == "error"]


def _save(tmp_path, stage, name="s.usda", provenance=None):
    path = tmp_path / name
    scene.save_stage(stage, path, provenance)
    return path


def test_positions_missing_but_other_arrays_present(tmp_path, field_factory):
    st = scene.new_stage()
    usdio.write_surfels(st, "/World/Surfels", field_factory(200))
    st.GetPrimAtPath("/World/Surfels").RemoveProperty("positions")
    path = _save(tmp_path, st)
    errs = _errors(validation.validate(path))
    assert [(p.attribute, p.check) for p in errs] == [("positions", "lsd3d:ArrayLength")]
    assert "missing, but orientations has 200 values" in errs[0].message
    # inspect still shows the file and names the defect instead of failing
    info = inspection.inspect(path)
    assert "200 values for 0 positions" in info["surfels"][0]["problem"]


def test_nan_in_a_time_sample(tmp_path, field_factory):
    f = field_factory(50)
    st = scene.new_stage()
    usdio.write_surfels(st, "/World/Surfels", f)
    attr = st.GetPrimAtPath("/World/Surfels").GetAttribute("positions")
    attr.Clear()
    pos = f.positions.copy()
    attr.Set(Vt.Vec3fArray.FromNumpy(pos), Usd.TimeCode(1))
    pos[7, 2] = np.nan
    attr.Set(Vt.Vec3fArray.FromNumpy(pos), Usd.TimeCode(2))
    errs = _errors(validation.validate(_save(tmp_path, st)))
    assert [(p.attribute, p.check) for p in errs] == [("positions", "lsd3d:Finite")], [p.line() for p in errs]
    assert "first index 7" in errs[0].message and "(at time 2)" in errs[0].message


@pytest.mark.parametrize("fmt", ["usda", "usdc"])
def test_zero_particle_prim_is_valid_and_inspectable(tmp_path, fmt, capsys):
    path = tmp_path / f"zero.{fmt}"
    usdio.write_surfel_file(str(path), SurfelField.empty())
    assert _errors(validation.validate(path)) == []
    assert main(["validate", str(path)]) == 0
    assert main(["inspect", str(path)]) == 0
    assert "0 surfels" in capsys.readouterr().out


def test_zero_positions_with_sized_arrays_is_an_error(tmp_path, field_factory):
    st = scene.new_stage()
    usdio.write_surfels(st, "/World/Surfels", field_factory(20))
    st.GetPrimAtPath("/World/Surfels").GetAttribute("positions").Set(Vt.Vec3fArray())
    errs = _errors(validation.validate(_save(tmp_path, st)))
    assert {p.attribute for p in errs} >= {"orientations", "scales", "opacities"}
    assert all(p.check in ("lsd3d:ArrayLength", "lsd3d:SHDegree") for p in errs), [p.line() for p in errs]


def _official_3dgs(stage, extent):
    prim = stage.DefinePrim("/World/G", "ParticleField3DGaussianSplat")
    prim.GetAttribute("positions").Set(Vt.Vec3fArray([(0, 0, 0), (1, 0, 0)]))
    prim.GetAttribute("scales").Set(Vt.Vec3fArray([(0.1, 0.2, 0.3)] * 2))
    prim.GetAttribute("opacities").Set(Vt.FloatArray([0.5, 1.0]))
    prim.GetAttribute("orientations").Set(Vt.QuatfArray.FromNumpy(np.array([[0, 0, 0, 1]] * 2, np.float32)))
    prim.GetAttribute("extent").Set(Vt.Vec3fArray(extent))
    return prim


def test_positions_only_extent_warns_for_other_tools_errors_for_ours(tmp_path):
    positions_only = [(0, 0, 0), (1, 0, 0)]
    st = scene.new_stage()
    _official_3dgs(st, positions_only)
    foreign = validation.validate(_save(tmp_path, st, "foreign.usda"))
    assert _errors(foreign) == []
    warn = [p for p in foreign if p.check == "lsd3d:Extent"]
    assert len(warn) == 1 and warn[0].severity == "warning" and "other converters" in warn[0].message
    ours = validation.validate(_save(tmp_path, st, "ours.usda", scene.provenance("splats.export-3dgs")))
    assert [(p.attribute, p.check) for p in _errors(ours)] == [("extent", "lsd3d:Extent")]


def test_inspect_and_validate_share_the_3dgs_bounds(tmp_path):
    st = scene.new_stage()
    # exact 3-sigma bounds of the two ellipsoids (scales 0.1, 0.2, 0.3): validate accepts them
    # as the extent and inspect reports them (reading the field as surfels drops the x axis)
    exact = [[-0.3, -0.6, -0.9], [1.3, 0.6, 0.9]]
    _official_3dgs(st, exact)
    path = _save(tmp_path, st)
    assert [p for p in validation.validate(path) if p.check == "lsd3d:Extent"] == []
    ext = inspection.inspect(path)["surfels"][0]["extent"]
    np.testing.assert_allclose(ext, exact, atol=1e-6)


def test_kernel_bounds_surflet_ignores_third_axis():
    from lsd3d_usd.splats.field import kernel_bounds
    q = np.array([[0, 0, 0, 1.0]])
    b2 = kernel_bounds(np.zeros((1, 3)), q, np.array([[1.0, 2.0, 5.0]]), surflet=True)
    b3 = kernel_bounds(np.zeros((1, 3)), q, np.array([[1.0, 2.0, 5.0]]), surflet=False)
    np.testing.assert_allclose(b2, [[-3, -6, 0], [3, 6, 0]])
    np.testing.assert_allclose(b3, [[-3, -6, -15], [3, 6, 15]])


def test_kernel_bounds_in_blocks_equal_one_pass(field_factory):
    from lsd3d_usd.splats.field import kernel_bounds
    f = field_factory(1000)
    whole = kernel_bounds(f.positions, f.orientations, f.scales, block=10_000)
    np.testing.assert_array_equal(kernel_bounds(f.positions, f.orientations, f.scales, block=7),
                                  whole)
    rows = f.rows(100, 400)       # views of the field's arrays, not copies
    assert np.shares_memory(rows.sh, f.sh) and rows.n == 300
    np.testing.assert_array_equal(rows.positions, f.subset(np.arange(100, 400)).positions)


def test_export_3dgs_extent_validates(tmp_path, field_factory):
    usdio.write_surfel_file(str(tmp_path / "s.usdc"), field_factory(300))
    assert main(["splats", "export-3dgs", str(tmp_path / "s.usdc"), "-o", str(tmp_path / "g.usdc"),
                 "--thin", "0.5"]) == 0
    assert _errors(validation.validate(tmp_path / "g.usdc")) == []


def test_export_3dgs_to_usda_above_the_bulk_limit_is_refused(tmp_path, field_factory, capsys):
    n = validation.BULK_TEXT_LIMIT + 1
    usdio.write_surfel_file(str(tmp_path / "s.usdc"), field_factory(n, sh_degree=0, semantic=False))
    capsys.readouterr()
    assert main(["splats", "export-3dgs", str(tmp_path / "s.usdc"), "-o", str(tmp_path / "g.usda")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{n} particles exceed the limit of" in err[0] and ".usdc" in err[0]
    assert not (tmp_path / "g.usda").exists()
    # the same count to .usdc validates
    assert main(["splats", "export-3dgs", str(tmp_path / "s.usdc"), "-o", str(tmp_path / "g.usdc")]) == 0
    assert _errors(validation.validate(tmp_path / "g.usdc")) == []
    # and the writers share the rule
    with pytest.raises(Exception, match="exceed the limit"):
        usdio.write_surfel_file(str(tmp_path / "t.usda"), field_factory(n, sh_degree=0, semantic=False))


def test_validate_json_of_zero_particle_prim(tmp_path, run_cli):
    path = tmp_path / "zero.usdc"
    usdio.write_surfel_file(str(path), SurfelField.empty())
    r = run_cli("validate", path, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["valid"] is True and "Traceback" not in r.stderr
