import numpy as np
import pytest

import lsd3d_usd  # noqa: F401
from lsd3d_usd import semantics
from lsd3d_usd.errors import InputError
from lsd3d_usd.splats.field import SH_C0, quat_to_matrix
from lsd3d_usd.splats.init import face_frames, mesh_to_surfels


def _grid_mesh(n=8, size=10.0, z=0.0):
    """An n x n quad grid in the plane z (2 n^2 triangles, counter-clockwise seen from +z)."""
    xs = np.linspace(0, size, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return V, F


def _box():
    V = np.array([[x, y, z] for x in (0, 2) for y in (0, 3) for z in (0, 1)], float)
    # outward-facing winding
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return V, F


def test_normals_are_face_normals_and_points_lie_on_their_faces():
    V, F = _box()
    field, fidx = mesh_to_surfels(V, F, count=5000, seed=1, return_face_index=True)
    n_ref = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n_ref /= np.linalg.norm(n_ref, axis=1, keepdims=True)
    np.testing.assert_allclose(field.normals(), n_ref[fidx], atol=1e-6)
    # winding is outward for this box: normals point away from the centre
    assert np.all(np.einsum("ij,ij->i", field.normals(), field.positions - [1, 1.5, 0.5]) > 0)
    # each position is inside its triangle (barycentrics in [0,1])
    p0, p1, p2 = V[F[fidx, 0]], V[F[fidx, 1]], V[F[fidx, 2]]
    A = np.stack([p1 - p0, p2 - p0, n_ref[fidx]], axis=2)
    bary = np.linalg.solve(A, (field.positions - p0)[..., None])[..., 0]
    assert np.all(bary[:, :2] >= -1e-6) and np.all(bary[:, :2].sum(1) <= 1 + 1e-6)
    assert np.abs(bary[:, 2]).max() < 1e-6


def test_count_exact_and_area_covered():
    V, F = _box()
    area = face_frames(V, F)[0].sum()
    assert area == pytest.approx(2 * (2 * 3 + 2 * 1 + 3 * 1))
    for count in (1, 7, 12, 999, 20000):
        f = mesh_to_surfels(V, F, count=count, seed=3)
        assert f.n == count
        # Each 1-sigma ellipse has area A/N by construction, so only float32 rounding
        # of the scales separates the sum from the mesh area.
        disk = np.sum(np.pi * f.scales[:, 0].astype(np.float64) * f.scales[:, 1])
        assert disk == pytest.approx(area, rel=1e-5)
        # Per face the covered area is within one surfel's share of the face area.
        _, fidx = mesh_to_surfels(V, F, count=count, seed=3, return_face_index=True)
        per_face = np.bincount(fidx, np.pi * f.scales[:, 0].astype(np.float64) * f.scales[:, 1], 12)
        assert np.all(np.abs(per_face - face_frames(V, F)[0]) <= area / count * (1 + 1e-5))


def test_count_distributed_by_area_and_evenly_inside_faces():
    V, F = _grid_mesh(1, 10.0)  # two big triangles of 50 m^2 each
    V = np.vstack([V, [[20, 0, 0], [21, 0, 0], [20, 1, 0]]])  # plus a 0.5 m^2 triangle
    F = np.vstack([F, [[4, 5, 6]]])
    f, fidx = mesh_to_surfels(V, F, count=2010, seed=0, return_face_index=True)
    counts = np.bincount(fidx, minlength=3)
    expected = 2010 * np.array([50, 50, 0.5]) / 100.5
    assert np.all(np.abs(counts - expected) <= 1)  # systematic sampling: floor or ceil
    # Evenness: in a 10x10 grid of 1 m cells over the square, each cell's count is
    # close to 20 (random uniform sampling would give a spread of ~±4.5 per cell).
    sq = fidx < 2
    H, _, _ = np.histogram2d(f.positions[sq, 0], f.positions[sq, 1], bins=10, range=[[0, 10], [0, 10]])
    assert H.min() >= 14 and H.max() <= 26, H


def test_sliver_faces_get_elongated_surfels_aligned_with_the_face():
    V = np.array([[0, 0, 0], [100, 0, 0], [0, 0.2, 0]], float)
    f = mesh_to_surfels(V, np.array([[0, 1, 2]]), count=10, seed=0)
    R = quat_to_matrix(f.orientations)
    assert np.all(np.abs(R[:, 0, 0]) > 0.999)  # long axis along x
    assert np.all(f.scales[:, 0] > 5 * f.scales[:, 1])
    # a split sliver becomes rounder the more surfels it gets
    f2 = mesh_to_surfels(V, np.array([[0, 1, 2]]), count=2000, seed=0)
    assert f2.scales[0, 0] / f2.scales[0, 1] < f.scales[0, 0] / f.scales[0, 1]


def test_colour_from_semantics_or_monochrome():
    V, F = _box()
    ids = np.arange(12) % 3 - 1  # includes -1 (unlabelled)
    f, fidx = mesh_to_surfels(V, F, ids, count=600, seed=0, return_face_index=True)
    assert np.array_equal(f.semantic_ids, ids[fidx])
    assert f.semantic_classes == semantics.CLASSES
    rgb = 0.5 + SH_C0 * f.sh[:, 0]
    lab = f.semantic_ids >= 0
    np.testing.assert_allclose(rgb[lab], semantics.CLASS_COLORS[f.semantic_ids[lab]], atol=1e-6)
    np.testing.assert_allclose(rgb[~lab], 0.5, atol=1e-6)
    g = mesh_to_surfels(V, F, count=50, color=(0.2, 0.3, 0.4), sh_degree=2)
    assert g.sh.shape == (50, 9, 3) and np.all(g.sh[:, 1:] == 0)
    np.testing.assert_allclose(0.5 + SH_C0 * g.sh[:, 0], np.tile([0.2, 0.3, 0.4], (50, 1)), atol=1e-6)


def test_deterministic_per_seed():
    V, F = _grid_mesh(5)
    a = mesh_to_surfels(V, F, count=777, seed=42)
    b = mesh_to_surfels(V, F, count=777, seed=42)
    c = mesh_to_surfels(V, F, count=777, seed=43)
    for k in ("positions", "orientations", "scales", "sh"):
        assert np.array_equal(getattr(a, k), getattr(b, k))
    assert not np.array_equal(a.positions, c.positions)


def test_degenerate_faces_are_skipped():
    V, F = _grid_mesh(2)
    V = np.vstack([V, [[0, 0, 5], [1, 1, 5], [2, 2, 5]], [[3, 3, 3]]])  # collinear + repeated vertex
    nv = len(V)
    F = np.vstack([F, [[nv - 4, nv - 3, nv - 2], [nv - 1, nv - 1, nv - 1]]])
    f, fidx = mesh_to_surfels(V, F, count=3000, seed=0, return_face_index=True)
    assert not np.isin(fidx, [len(F) - 2, len(F) - 1]).any()
    assert np.all(np.isfinite(f.positions)) and np.all(np.isfinite(f.orientations))
    assert not f.problems()


def test_bad_input():
    V, F = _box()
    with pytest.raises(InputError, match="out of range"):
        mesh_to_surfels(V, F + 100, count=10)
    with pytest.raises(InputError, match="maximum"):
        mesh_to_surfels(V, F, count=5_000_000)
    with pytest.raises(InputError, match="non-zero area"):
        mesh_to_surfels(np.zeros((3, 3)), np.array([[0, 1, 2]]), count=10)
    with pytest.raises(InputError, match="face_semantic_ids"):
        mesh_to_surfels(V, F, np.zeros(3), count=10)


def test_face_weights_shift_density_and_keep_coverage():
    # Two equal unit squares; the second weighted 4x: ~4x the surfels, each 1/4 the area.
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [5, 0, 0], [6, 0, 0], [6, 1, 0], [5, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    f, face = mesh_to_surfels(V, F, count=1000, seed=1, face_weights=[1, 1, 4, 4],
                              return_face_index=True)
    n_heavy = int((face >= 2).sum())
    assert 790 <= n_heavy <= 810
    disk = np.pi * f.scales[:, 0].astype(np.float64) * f.scales[:, 1]
    np.testing.assert_allclose(disk[face < 2].sum(), 1.0, rtol=1e-4)   # each square still tiled
    np.testing.assert_allclose(disk[face >= 2].sum(), 1.0, rtol=1e-4)
    with pytest.raises(Exception, match="face_weights"):
        mesh_to_surfels(V, F, count=10, face_weights=[1, -1, 1, 1])
