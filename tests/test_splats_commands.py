import numpy as np

import lsd3d_usd  # noqa: F401
from pxr import Gf, Usd, UsdGeom, UsdSemantics

from lsd3d_usd import scene, semantics
from lsd3d_usd.cli import main
from lsd3d_usd.splats.ply import read_ply_vertices
from lsd3d_usd.splats.usdio import read_surfel_file


def _mesh_stage(path):
    """Two labelled quads under /World/Proxy: a road (prim label) and a wall that is
    translated 5 m up and whose second face is relabelled 'building' by a face subset."""
    stage = scene.new_stage()
    road = UsdGeom.Mesh.Define(stage, "/World/Proxy/Road")
    road.GetPointsAttr().Set([(0, 0, 0), (10, 0, 0), (10, 4, 0), (0, 4, 0)])
    road.GetFaceVertexCountsAttr().Set([4])
    road.GetFaceVertexIndicesAttr().Set([0, 1, 2, 3])
    UsdSemantics.LabelsAPI.Apply(road.GetPrim(), "class").CreateLabelsAttr(["road"])
    wall = UsdGeom.Mesh.Define(stage, "/World/Proxy/Wall")
    wall.AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    wall.GetPointsAttr().Set([(0, 0, 0), (2, 0, 0), (2, 0, 2), (0, 0, 2), (4, 0, 0), (4, 0, 2)])
    wall.GetFaceVertexCountsAttr().Set([4, 4])
    wall.GetFaceVertexIndicesAttr().Set([0, 1, 2, 3, 1, 4, 5, 2])
    UsdSemantics.LabelsAPI.Apply(wall.GetPrim(), "class").CreateLabelsAttr(["curb"])
    sub = UsdGeom.Subset.CreateGeomSubset(wall, "facade", UsdGeom.Tokens.face, [1])
    UsdSemantics.LabelsAPI.Apply(sub.GetPrim(), "class").CreateLabelsAttr(["building"])
    scene.save_stage(stage, path)


def test_init_reads_meshes_labels_and_transforms(tmp_path):
    _mesh_stage(tmp_path / "m.usda")
    assert main(["splats", "init", str(tmp_path / "m.usda"), "-o", str(tmp_path / "s.usdc"),
                 "--count", "4800", "--seed", "3"]) == 0
    f = read_surfel_file(str(tmp_path / "s.usdc"))
    assert f.n == 4800
    road = f.semantic_ids == semantics.CLASS_ID["road"]
    curb = f.semantic_ids == semantics.CLASS_ID["curb"]
    bld = f.semantic_ids == semantics.CLASS_ID["building"]
    assert road.sum() + curb.sum() + bld.sum() == f.n
    # areas 40 : 4 : 4 m^2
    assert abs(road.sum() - 4000) <= 1 and abs(curb.sum() - 400) <= 1 and abs(bld.sum() - 400) <= 1
    assert np.all(np.abs(f.positions[road, 2]) < 1e-6)
    assert np.all(f.positions[~road, 2] >= 5 - 1e-5)  # the wall's translate applied
    assert np.all(f.positions[bld, 0] >= 2 - 1e-5)  # subset face is the x in [2, 4] quad
    np.testing.assert_allclose(np.abs(f.normals()[~road, 1]), 1, atol=1e-5)


def test_ply_round_trip_through_commands(tmp_path):
    _mesh_stage(tmp_path / "m.usda")
    main(["splats", "init", str(tmp_path / "m.usda"), "-o", str(tmp_path / "s.usdc"), "--count", "500",
          "--sh-degree", "1"])
    assert main(["splats", "export-ply", str(tmp_path / "s.usdc"), "-o", str(tmp_path / "s.ply")]) == 0
    assert main(["splats", "import-ply", str(tmp_path / "s.ply"), "-o", str(tmp_path / "t.usdc")]) == 0
    a, b = read_surfel_file(str(tmp_path / "s.usdc")), read_surfel_file(str(tmp_path / "t.usdc"))
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.sh, b.sh)
    assert np.array_equal(a.semantic_ids, b.semantic_ids) and a.semantic_classes == b.semantic_classes
    np.testing.assert_allclose(a.scales, b.scales, rtol=1e-6)
    np.testing.assert_allclose(a.opacities, b.opacities, atol=1e-6)
    assert main(["splats", "export-ply", str(tmp_path / "s.usdc"), "-o", str(tmp_path / "g.ply"),
                 "--layout", "3dgs"]) == 0
    assert "scale_2" in read_ply_vertices(tmp_path / "g.ply").dtype.names
    assert main(["splats", "export-3dgs", str(tmp_path / "s.usdc"), "-o", str(tmp_path / "g.usdc")]) == 0
    st = Usd.Stage.Open(str(tmp_path / "g.usdc"))
    assert st.GetPrimAtPath("/World/Surfels").GetTypeName() == "ParticleField3DGaussianSplat"


def test_command_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n")
    assert main(["splats", "import-ply", str(tmp_path / "bad.ply"), "-o", str(tmp_path / "x.usdc")]) == 1
    err = capsys.readouterr().err
    assert "bad.ply" in err and "end_header" in err and "Traceback" not in err
    assert not (tmp_path / "x.usdc").exists()
    stage = scene.new_stage()
    scene.save_stage(stage, tmp_path / "empty.usda")
    assert main(["splats", "init", str(tmp_path / "empty.usda"), "-o", str(tmp_path / "y.usdc")]) == 1
    assert "no Mesh prims" in capsys.readouterr().err
    assert main(["splats", "export-ply", str(tmp_path / "empty.usda"), "-o", str(tmp_path / "y.ply")]) == 1
    assert "no ParticleField" in capsys.readouterr().err
