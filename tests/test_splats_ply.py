import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from lsd3d_usd.errors import InputError
from lsd3d_usd.splats.field import SurfelField, quat_to_matrix
from lsd3d_usd.splats.ply import (read_ply, read_ply_vertices, splat_vertex_array, write_gaussian_splat_file,
                                  write_ply, write_ply_vertices)


def _random_splat_ply(path, n=200, n_scales=2, k=4, seed=0):
    """A PLY as 3DGS/2DGS training code writes it (unnormalised quats, logits, logs)."""
    rng = np.random.default_rng(seed)
    props = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(3 * (k - 1))] + ["opacity"]
             + [f"scale_{i}" for i in range(n_scales)] + [f"rot_{i}" for i in range(4)])
    arr = np.zeros(n, dtype=[(p, "<f4") for p in props])
    for p in props:
        arr[p] = rng.normal(size=n)
    arr["nx"] = arr["ny"] = arr["nz"] = 0
    for i in range(n_scales):
        arr[f"scale_{i}"] = rng.uniform(-6, 0, n)
    arr["opacity"] = rng.uniform(-8, 8, n)
    write_ply_vertices(path, arr)
    return arr


def test_2dgs_round_trip(tmp_path):
    src = _random_splat_ply(tmp_path / "a.ply", k=16)
    f = read_ply(tmp_path / "a.ply")
    assert f.n == 200 and f.sh.shape == (200, 16, 3)
    # channel-major f_rest: red's 15 coefficients first
    assert f.sh[3, 1, 0] == src["f_rest_0"][3] and f.sh[3, 1, 1] == src["f_rest_15"][3]
    assert f.sh[3, 15, 2] == src["f_rest_44"][3]
    write_ply(tmp_path / "b.ply", f)
    out = read_ply_vertices(tmp_path / "b.ply")
    assert out.dtype.names == src.dtype.names
    for name in src.dtype.names:
        if name.startswith(("x", "y", "z", "f_", "n")):
            assert np.array_equal(out[name], src[name]), name  # bit-exact
    np.testing.assert_allclose(out["opacity"], src["opacity"], atol=2e-5 * 8)
    for i in range(2):
        np.testing.assert_allclose(out[f"scale_{i}"], src[f"scale_{i}"], atol=1e-6)
    q_src = np.stack([src[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    q_src /= np.linalg.norm(q_src, axis=1, keepdims=True)
    q_out = np.stack([out[f"rot_{i}"] for i in range(4)], 1)
    dots = np.abs(np.einsum("ij,ij->i", q_src, q_out))  # q and -q are the same rotation
    np.testing.assert_allclose(dots, 1.0, atol=1e-6)
    # a second round trip does not drift (float32 logit/sigmoid may wobble by an ulp)
    write_ply(tmp_path / "c.ply", read_ply(tmp_path / "b.ply"))
    again = read_ply_vertices(tmp_path / "c.ply")
    for name in src.dtype.names:
        np.testing.assert_allclose(again[name], out[name], rtol=1e-6, atol=1e-6)


def test_3dgs_flat_gaussian_imports_with_right_normal(tmp_path):
    # A Gaussian flat along world y: scales (x=0.5, y=0.001, z=0.2), rotated 90deg about z,
    # so its thin axis (local y) points along world -x.
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(1, dtype=[(p, "<f4") for p in props])
    arr["scale_0"], arr["scale_1"], arr["scale_2"] = np.log([0.5, 0.001, 0.2])
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    arr["rot_0"], arr["rot_3"] = 2 * c, 2 * s  # wxyz, deliberately unnormalised
    write_ply_vertices(tmp_path / "g.ply", arr)
    f = read_ply(tmp_path / "g.ply")
    R = quat_to_matrix(f.orientations)[0]
    np.testing.assert_allclose(np.abs(R[:, 2]), [1, 0, 0], atol=1e-6)  # normal along ±x
    np.testing.assert_allclose(f.scales[0], [0.5, 0.2], rtol=1e-6)
    np.testing.assert_allclose(np.abs(R[:, 0]), [0, 1, 0], atol=1e-6)  # largest axis: old x -> world y
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert f.sh.shape == (1, 1, 3)


def test_3dgs_export_layout_and_usd_prim(tmp_path):
    rng = np.random.default_rng(1)
    n = 50
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    f = SurfelField(rng.normal(size=(n, 3)), q, rng.uniform(0.01, 1, (n, 2)), rng.uniform(0, 1, n),
                    rng.normal(size=(n, 4, 3)), np.arange(n) % 3, ("road", "curb", "building"))
    arr = splat_vertex_array(f, "3dgs")
    np.testing.assert_allclose(np.exp(arr["scale_2"]), 1e-3 * f.scales.min(1), rtol=1e-5)
    write_ply(tmp_path / "g3.ply", f, layout="3dgs")
    back = read_ply(tmp_path / "g3.ply")
    np.testing.assert_allclose(back.normals() * np.sign(np.sum(back.normals() * f.normals(), 1))[:, None],
                               f.normals(), atol=1e-5)
    np.testing.assert_allclose(np.sort(back.scales, 1), np.sort(f.scales, 1), rtol=1e-5)
    assert np.array_equal(back.semantic_ids, f.semantic_ids)
    assert back.semantic_classes == f.semantic_classes
    # the official 3DGS prim reads back (via the lead's reader) as the same surfels
    from lsd3d_usd.splats.usdio import read_surfel_file
    write_gaussian_splat_file(tmp_path / "g3.usdc", f)
    from pxr import Usd
    st = Usd.Stage.Open(str(tmp_path / "g3.usdc"))
    assert st.GetPrimAtPath("/World/Surfels").GetTypeName() == "ParticleField3DGaussianSplat"
    u = read_surfel_file(str(tmp_path / "g3.usdc"))
    np.testing.assert_allclose(np.abs(np.sum(u.normals() * f.normals(), 1)), 1, atol=1e-5)
    np.testing.assert_allclose(np.sort(u.scales, 1), np.sort(f.scales, 1), rtol=1e-6)
    np.testing.assert_allclose(u.sh, f.sh)


def test_opacity_extremes_stay_finite(tmp_path):
    f = SurfelField(np.zeros((2, 3)), [[0, 0, 0, 1]] * 2, [[1, 1]] * 2, [0.0, 1.0], np.zeros((2, 1, 3)))
    arr = splat_vertex_array(f)
    assert np.all(np.isfinite(arr["opacity"]))
    write_ply(tmp_path / "o.ply", f)
    np.testing.assert_allclose(read_ply(tmp_path / "o.ply").opacities, [0, 1], atol=1e-6)


def test_ascii_and_big_endian_read(tmp_path):
    body = "1 2 3 0.1 0.2 0.3 0 0 0 1 0 0 0\n"
    hdr = ("ply\nformat ascii 1.0\nelement vertex 1\n" + "".join(
        f"property float {p}\n" for p in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                                          "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"])
           + "end_header\n")
    (tmp_path / "a.ply").write_text(hdr + body)
    f = read_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(f.positions, [[1, 2, 3]])
    assert f.opacities[0] == pytest.approx(0.5)
    np.testing.assert_allclose(f.scales, [[1, 1]])
    be = hdr.replace("ascii", "binary_big_endian").encode() + np.array(
        [float(x) for x in body.split()], ">f4").tobytes()
    (tmp_path / "b.ply").write_bytes(be)
    g = read_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(g.positions, f.positions)


@pytest.mark.parametrize("mutate,match", [
    (lambda b: b.replace(b"ply\n", b"plx\n", 1), "magic"),
    (lambda b: b.replace(b"end_header\n", b"end_headr\n"), "keyword|end_header"),
    (lambda b: b.replace(b"binary_little_endian", b"binary_middle_endian"), "format"),
    (lambda b: b[:-7], "truncated"),
    (lambda b: b.replace(b"property float opacity\n", b""), "opacity"),
    (lambda b: b.replace(b"element vertex 10", b"element vertex ten"), "element"),
    (lambda b: b.replace(b"property float scale_1\n", b"property float scale_7\n"), "scale_"),
])
def test_malformed_ply_raises_input_error(tmp_path, mutate, match):
    _random_splat_ply(tmp_path / "ok.ply", n=10, k=1)
    (tmp_path / "bad.ply").write_bytes(mutate((tmp_path / "ok.ply").read_bytes()))
    with pytest.raises(InputError, match=match):
        read_ply(tmp_path / "bad.ply")


def test_missing_file_and_zero_rotation(tmp_path):
    with pytest.raises(InputError, match="cannot open"):
        read_ply(tmp_path / "nope.ply")
    arr = _random_splat_ply(tmp_path / "z.ply", n=5, k=1)
    for i in range(4):
        arr[f"rot_{i}"][2] = 0
    write_ply_vertices(tmp_path / "z.ply", arr)
    with pytest.raises(InputError, match="first vertex 2"):
        read_ply(tmp_path / "z.ply")
