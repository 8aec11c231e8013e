"""SurfelField arrays and their USD ParticleField IO."""
import numpy as np
import pytest
from pxr import Sdf, Usd, Vt

import lsd3d_usd
from lsd3d_usd import scene
from lsd3d_usd.errors import InputError
from lsd3d_usd.splats import usdio
from lsd3d_usd.splats.field import (SurfelField, flatten_3d_gaussians, matrix_to_quat,
                                    quat_to_matrix)

FIELDS = ("positions", "orientations", "scales", "opacities", "sh", "semantic_ids")


def test_round_trip_100k_is_bit_exact(tmp_path, field_factory):
    f = field_factory(100_000, sh_degree=3)
    path = tmp_path / "surfels.usdc"
    usdio.write_surfel_file(str(path), f, provenance=scene.provenance("test"))
    g = usdio.read_surfel_file(str(path))
    for name in FIELDS:
        a, b = getattr(f, name), getattr(g, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert a.tobytes() == b.tobytes(), name
    assert g.semantic_classes == f.semantic_classes
    assert g.sh_degree == 3


def test_reads_are_views_not_copies(tmp_path, field_factory):
    path = tmp_path / "s.usdc"
    usdio.write_surfel_file(str(path), field_factory(5000))
    g = usdio.read_surfel_file(str(path))
    # A numpy view over the VtArray buffer: not owning its data, read-only.
    assert not g.positions.flags.owndata and not g.positions.flags.writeable


def test_extent_covers_three_sigma_disk():
    # One disk of scales (2, 1) rotated 90 degrees about z: x half-extent 3, y 6.
    q = np.array([[0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]])
    f = SurfelField([[1, 2, 3]], q, [[2.0, 1.0]], [1.0], np.zeros((1, 1, 3)))
    np.testing.assert_allclose(f.extent(), [[-2, -4, 3], [4, 8, 3]], atol=1e-6)


def test_over_layer_authors_only_named_attributes(field_factory):
    f = field_factory(100)
    base = scene.new_stage()
    usdio.write_surfels(base, "/World/Surfels", f)
    edit = scene.new_stage()
    g = f.subset(slice(None))
    g.opacities = np.clip(f.opacities * 0.5, 0, 1).astype(np.float32)
    usdio.write_surfels(edit, "/World/Surfels", g, over=True, attributes=("opacities",))
    spec = edit.GetRootLayer().GetPrimAtPath("/World/Surfels")
    assert spec.specifier == Sdf.SpecifierOver
    assert set(spec.attributes.keys()) == {"opacities"}
    composed = Usd.Stage.CreateInMemory()
    composed.GetRootLayer().subLayerPaths = [edit.GetRootLayer().identifier, base.GetRootLayer().identifier]
    h = usdio.read_surfels(composed.GetPrimAtPath("/World/Surfels"))
    np.testing.assert_array_equal(h.opacities, g.opacities)
    np.testing.assert_array_equal(h.positions, f.positions)


def test_write_refuses_invalid_field(field_factory):
    f = field_factory(10)
    f.opacities[3] = 1.5
    with pytest.raises(InputError, match="opacities"):
        usdio.write_surfels(scene.new_stage(), "/World/S", f)


def test_read_official_3dgs_flattens_to_surfels():
    stage = scene.new_stage()
    prim = stage.DefinePrim("/World/G", "ParticleField3DGaussianSplat")
    # Ellipsoid with scales (0.5, 0.01, 2): thinnest axis is local y → surfel normal ±y.
    prim.GetAttribute("positions").Set(Vt.Vec3fArray([(0, 0, 0)]))
    prim.GetAttribute("orientations").Set(Vt.QuatfArray.FromNumpy(np.array([[0, 0, 0, 1]], np.float32)))
    prim.GetAttribute("scales").Set(Vt.Vec3fArray([(0.5, 0.01, 2.0)]))
    prim.GetAttribute("opacities").Set(Vt.FloatArray([0.7]))
    f = usdio.read_surfels(prim)
    np.testing.assert_allclose(f.scales, [[2.0, 0.5]], rtol=1e-6)
    np.testing.assert_allclose(np.abs(f.normals()[0]), [0, 1, 0], atol=1e-6)
    assert np.isclose(np.linalg.det(quat_to_matrix(f.orientations)[0]), 1.0)
    # Defaults of the schema: no SH → DC colour 0.5.
    np.testing.assert_allclose(f.colors(), [[0.5, 0.5, 0.5]])


def test_half_precision_attributes_are_read():
    stage = scene.new_stage()
    prim = stage.DefinePrim("/World/S", lsd3d_usd.SURFEL_TYPE)
    prim.GetAttribute("positionsh").Set(Vt.Vec3hArray([(1, 2, 3)]))
    f = usdio.read_surfels(prim)
    assert f.positions.dtype == np.float32
    np.testing.assert_array_equal(f.positions, [[1, 2, 3]])


def test_inconsistent_lengths_raise_naming_attribute():
    stage = scene.new_stage()
    prim = stage.DefinePrim("/World/S", lsd3d_usd.SURFEL_TYPE)
    prim.GetAttribute("positions").Set(Vt.Vec3fArray([(0, 0, 0), (1, 1, 1)]))
    prim.GetAttribute("opacities").Set(Vt.FloatArray([0.5]))
    with pytest.raises(InputError, match=r"/World/S\.opacities: 1 values for 2 positions"):
        usdio.read_surfels(prim)


def test_quaternion_matrix_round_trip_against_reference():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(1000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    m = quat_to_matrix(q)
    # Reference: rotate basis vectors with the quaternion sandwich product in float64.
    def rotate(qv, v):
        x, y, z, w = qv
        u = np.array([x, y, z])
        return v + 2 * np.cross(u, np.cross(u, v) + w * v)
    for i in range(0, 1000, 97):
        for k in range(3):
            np.testing.assert_allclose(m[i][:, k], rotate(q[i], np.eye(3)[k]), atol=1e-12)
    q2 = matrix_to_quat(m)
    np.testing.assert_allclose(np.abs((q2 * q).sum(1)), 1.0, atol=1e-12)


def test_flatten_keeps_right_handed_frames():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    s = rng.uniform(0.01, 1, (500, 3))
    q2, s2 = flatten_3d_gaussians(q, s)
    assert np.all(s2[:, 0] >= s2[:, 1])
    np.testing.assert_allclose(np.linalg.det(quat_to_matrix(q2)), 1.0, atol=1e-6)
    # The surfel normal is the original smallest axis (up to sign).
    rot = quat_to_matrix(q)
    smallest = rot[np.arange(500), :, np.argmin(s, axis=1)]
    np.testing.assert_allclose(np.abs((quat_to_matrix(q2)[..., 2] * smallest).sum(1)), 1, atol=1e-5)


def test_concat_and_problems(field_factory):
    a, b = field_factory(10, sh_degree=0, seed=1), field_factory(5, sh_degree=2, seed=2)
    c = SurfelField.concat([a, b])
    assert c.n == 15 and c.sh_degree == 2
    np.testing.assert_array_equal(c.sh[:10, 1:], 0)
    assert c.problems() == []
    c.orientations[4] *= 2
    c.scales[7, 1] = 0
    probs = " ".join(c.problems())
    assert "orientations" in probs and "first index 4" in probs and "scales" in probs


def test_empty_field_round_trips(tmp_path):
    f = SurfelField.empty(sh_degree=2)
    assert f.n == 0 and f.sh.shape == (0, 9, 3)
    path = tmp_path / "empty.usdc"
    usdio.write_surfel_file(str(path), f)
    assert usdio.read_surfel_file(str(path)).n == 0
    assert SurfelField.concat([f, f]).n == 0
